"""Executors run jobs (JSON strings, see msflow.worker) and hand back futures of JSON outcomes.

``inline`` runs in the calling process (``-j 1``); ``local`` is a process pool (``-j N``) whose workers pin BLAS to
one thread; ``dask`` lives in msflow.dask_executor. All produce the same artifacts and keys.

``submit`` takes an optional ``on_retry(lost_worker, attempt)``: executors that retry a job after losing its
worker (Dask) call it when the new attempt starts, from their own thread.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, Protocol

OnRetry = Callable[[str, int], None]


class Executor(Protocol):
    """Runs jobs (``msflow.jobs.Job`` as JSON) and hands back futures of JSON outcomes (``Outcome``)."""

    @property
    def name(self) -> str: ...

    def submit(self, job_json: str, on_retry: OnRetry | None = None) -> Future[str]: ...

    def shutdown(self, *, abort: bool = False) -> None:
        """Release the workers once their jobs are done; ``abort`` (the run was interrupted): stop the jobs
        running now instead of waiting for them (a job killed mid-write leaves only a temporary folder)."""


class InlineExecutor:
    name = "inline"

    def submit(self, job_json: str, on_retry: OnRetry | None = None) -> Future[str]:
        from msflow.worker import run_job

        future: Future[str] = Future()
        future.set_result(run_job(job_json))
        return future

    def shutdown(self, *, abort: bool = False) -> None:
        from msflow.worker import settle

        settle()


class ProcessExecutor:
    """A pool of ``jobs`` worker processes, spawned: no inherited threads or locks, and the environment of the
    run (a fork server would freeze the environment of its first use)."""

    name = "local"

    def __init__(self, jobs: int):
        import multiprocessing
        import os
        from concurrent.futures import ProcessPoolExecutor

        from msflow.processes import quiet_resource_tracker
        from msflow.worker import pin_blas_threads

        pin_blas_threads()  # inherited by the workers, so set before any of them imports numpy
        quiet_resource_tracker()  # before the first spawn, which would start it with its warnings
        self.pool = ProcessPoolExecutor(
            max_workers=jobs,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=start_worker,
            initargs=(os.getpid(),),
        )

    def submit(self, job_json: str, on_retry: OnRetry | None = None) -> Future[str]:
        from msflow.worker import run_job

        return self.pool.submit(run_job, job_json)

    def shutdown(self, *, abort: bool = False) -> None:
        if not abort:
            self.pool.shutdown(wait=True, cancel_futures=True)
            return
        # the pool's own shutdown waits for the jobs running (a stage of minutes; and Ctrl-C does not reach the
        # workers, which lead their own groups): stop its workers with what their stages started (a render pool,
        # FFmpeg), which a worker killed alone left running; _processes is private, but the pool has no public way
        from msflow.processes import stop_groups

        workers = list(getattr(self.pool, "_processes", {}).values())
        self.pool.shutdown(wait=False, cancel_futures=True)
        stop_groups(workers)


def start_worker(run_pid: int) -> None:
    """Initialise a ``ProcessExecutor`` worker: one BLAS thread; the leader of its own process group, which the
    processes its stages start join, so that stopping the run stops them too (``msflow.processes``); gone, with
    that group, if the run's process (``run_pid``) dies without stopping it (SIGKILL)."""
    from msflow.processes import exit_with_parent, lead_own_group
    from msflow.worker import pin_blas_threads

    pin_blas_threads()
    lead_own_group()
    exit_with_parent(run_pid)


class LazyExecutor:
    """Starts the real executor on the first job: a run whose stages are all cached starts no process pool and
    no Dask cluster. ``on_start`` runs once, just before (e.g. clearing leftovers of killed runs)."""

    def __init__(self, factory: Callable[[], Executor], on_start: Callable[[], object] | None = None):
        self._factory = factory
        self._on_start = on_start
        self._executor: Executor | None = None

    @property
    def name(self) -> str:
        return self._executor.name if self._executor is not None else "none"

    def submit(self, job_json: str, on_retry: OnRetry | None = None) -> Future[str]:
        if self._executor is None:
            if self._on_start is not None:
                self._on_start()
            self._executor = self._factory()
        return self._executor.submit(job_json, on_retry)

    def shutdown(self, *, abort: bool = False) -> None:
        if self._executor is not None:
            self._executor.shutdown(abort=abort)


def make_executor(
    kind: str = "local",
    jobs: int = 1,
    scheduler: str | None = None,
    timeout: float = 10.0,
    on_start: Callable[[], object] | None = None,
    code_trees: Callable[[str], Any] | None = None,
) -> LazyExecutor:
    """Validate the executor options now; start the executor when the first job arrives. ``code_trees`` maps a
    project root to its ``msflow.shipping.CodeTree``, for executors that ship code to their workers."""
    from msflow.errors import UserError

    if jobs < 1:
        raise UserError(f"-j must be at least 1, got {jobs}", field="-j")
    if timeout <= 0:
        raise UserError(f"--connect-timeout must be positive, got {timeout:g}", field="--connect-timeout")
    if kind == "dask" or scheduler is not None:
        if scheduler is not None:  # an empty one too (an unset variable): an error, not a silent local run
            from msflow.dask_executor import parse_scheduler_address

            parse_scheduler_address(scheduler)  # a malformed address fails now, before any stage runs

        def factory() -> Executor:
            from msflow.dask_executor import DaskExecutor
            from msflow.shipping import Shipper

            shipper = Shipper(code_trees) if code_trees is not None else None
            return DaskExecutor(jobs=jobs, scheduler=scheduler, timeout=timeout, shipper=shipper)
    elif kind in ("local", "inline"):

        def factory() -> Executor:
            return InlineExecutor() if jobs == 1 or kind == "inline" else ProcessExecutor(jobs)
    else:
        raise UserError(f"unknown executor '{kind}'; choose local or dask", field="--executor")
    return LazyExecutor(factory, on_start)
