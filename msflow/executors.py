"""Executors run jobs (JSON strings, see msflow.worker) and hand back futures of JSON outcomes.

``inline`` runs in the calling process (``-j 1``); ``local`` (``-j N``) runs N stages at a time, one of them in the
run's own process when its stage allows it (``Stage.in_process``) and the others in worker processes started only
when needed, whose BLAS is pinned to one thread; ``dask`` lives in msflow.dask_executor. All produce the same
artifacts and keys.

``submit`` takes an optional ``on_retry(lost_worker, attempt)``: executors that retry a job after losing its
worker (Dask) call it when the new attempt starts, from their own thread.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
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


#: where ``LocalExecutor`` may run a job: a worker (the default), the run's own process first and else a worker
#: (``Stage.in_process``), only the run's own process (``Stage.cheap``, but in a sweep)
WORKER, ANY, CHEAP = "worker", "any", "cheap"


@dataclass
class _Waiting:
    job_json: str
    placement: str
    future: Future[str]


class LocalExecutor:
    """``-j N`` on this machine: at most N stages at a time, one of them in the run's own process.

    The run's own process comes first: a stage that allows it (``Stage.in_process``) runs there, in a thread,
    whenever it has no stage, and finds the libraries the run has imported already. Another stage goes to a
    worker process only while the run's process is on a stage that is not cheap (``Stage.cheap``: it will soon be
    free), or when it may not run there; a cheap stage never does, but in a sweep (``batch``), whose variants of
    it share a worker's imports. A worker (a ``ProcessExecutor`` of one) is spawned when none is idle, and kept for
    the rest of the run. So a chain of stages starts no worker and imports each library once, and two long stages
    ready at once still run side by side.

    Why: a spawned worker imports what its stages need again (numpy, scipy, OpenCV, PyAV: a cheap stage's 0.02 s
    cost 0.5 s of imports in a worker of the default pipeline), which a short pipeline's parallel part does not
    repay on a busy machine; and a pool of N spawned another worker whenever a job came in the instant between a
    worker's result and its being counted idle again, so this executor counts its workers itself."""

    name = "local"

    def __init__(self, jobs: int, batch: bool = False):
        import threading
        from collections import deque

        self.jobs = jobs
        self.batch = batch
        self._lock = threading.RLock()  # a worker's result may come back (and dispatch) inside _dispatch
        self._waiting: deque[_Waiting] = deque()
        self._running = 0
        self._here: threading.Thread | None = None  # the thread running a stage in this process ...
        self._here_cheap = False  # ... and whether that stage is cheap (it will soon be done)
        self._idle: list[ProcessExecutor] = []
        self._workers: list[ProcessExecutor] = []
        self._stopping = False

    def submit(self, job_json: str, on_retry: OnRetry | None = None) -> Future[str]:
        import json

        job = json.loads(job_json)
        placement = CHEAP if job.get("cheap") and not self.batch else ANY if job.get("in_process") else WORKER
        waiting = _Waiting(job_json, placement, Future())
        with self._lock:
            self._waiting.append(waiting)
            self._dispatch()
        return waiting.future

    def _dispatch(self) -> None:
        """Start waiting jobs, each the first come among those a free place may take, while fewer than ``jobs``
        run (under the lock). While this process is on a cheap stage, a worker takes only what may not wait for
        it."""
        while self._running < self.jobs and not self._stopping:
            if self._here is None and (job := self._take({ANY, CHEAP})) is not None:
                start = self._start_here
            elif (job := self._take({WORKER} if self._here_cheap else {WORKER, ANY})) is not None:
                start = self._start_in_worker
            else:
                return
            try:
                start(job)
            except Exception as exc:  # no thread or process to be had (a process limit, no memory): the job fails
                job.future.set_exception(exc)  # (the runner: "worker lost"), not the thread that was handing it on
                continue
            self._running += 1

    def _take(self, placements: set[str]) -> _Waiting | None:
        for index, waiting in enumerate(self._waiting):
            if waiting.placement in placements:
                del self._waiting[index]
                return waiting
        return None

    def _start_here(self, job: _Waiting) -> None:
        import threading

        thread = threading.Thread(target=self._run_here, args=(job,), name="msflow-stage", daemon=True)
        thread.start()  # it frees the place under the lock held here: it cannot do so before it is taken
        self._here, self._here_cheap = thread, job.placement == CHEAP

    def _run_here(self, job: _Waiting) -> None:
        from msflow.worker import run_job

        result: str | BaseException
        try:
            result = run_job(job.job_json)
        except BaseException as exc:  # KeyboardInterrupt raised into this thread by shutdown(abort=True)
            result = exc
        with self._lock:  # free before telling: the runner's next job may then come here, not to a new worker
            self._here, self._here_cheap = None, False
            self._running -= 1
            self._dispatch()
        _resolve(job.future, result)

    def _start_in_worker(self, job: _Waiting) -> None:
        worker = self._idle.pop() if self._idle else self._new_worker()
        try:
            inner = worker.submit(job.job_json)
        except Exception:  # it died while idle (the OOM killer), or could not be started: a new one takes the job
            self._workers.remove(worker)
            worker = self._new_worker()
            try:
                inner = worker.submit(job.job_json)
            except Exception:  # none can be started: the job fails (_dispatch)
                self._workers.remove(worker)
                raise
        inner.add_done_callback(lambda done: self._worker_done(worker, done, job.future))

    def _new_worker(self) -> ProcessExecutor:
        worker = ProcessExecutor(1)
        self._workers.append(worker)
        return worker

    def _worker_done(self, worker: ProcessExecutor, done: Future[str], future: Future[str]) -> None:
        result: str | BaseException
        if done.cancelled():
            result = KeyboardInterrupt()
        else:
            error = done.exception()
            result = done.result() if error is None else error
        with self._lock:  # free before telling, as in _run_here
            self._running -= 1
            if isinstance(result, str):
                self._idle.append(worker)
            elif worker in self._workers:  # broken (it died mid-stage; its pool has cleared up): no more jobs
                self._workers.remove(worker)
            self._dispatch()
        _resolve(future, result)

    def shutdown(self, *, abort: bool = False) -> None:
        from msflow.processes import STOP_GRACE_SECONDS, interrupt_thread
        from msflow.worker import settle

        with self._lock:
            self._stopping = True
            waiting, here, workers = list(self._waiting), self._here, list(self._workers)
            self._waiting.clear()
        for job in waiting:
            job.future.cancel()
        if abort and here is not None:
            interrupt_thread(here)  # as Ctrl-C does to a stage of -j 1: it unwinds, its writer clears its folder
        for worker in workers:
            worker.shutdown(abort=abort)
        if here is not None:
            here.join(STOP_GRACE_SECONDS if abort else None)
        settle()  # this process ran jobs too


def _resolve(future: Future[str], result: str | BaseException) -> None:
    if isinstance(result, BaseException):
        future.set_exception(result)
    else:
        future.set_result(result)


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
    batch: bool = False,
) -> LazyExecutor:
    """Validate the executor options now; start the executor when the first job arrives. ``code_trees`` maps a
    project root to its ``msflow.shipping.CodeTree``, for executors that ship code to their workers; ``batch``:
    the jobs are several variants' (a sweep: ``LocalExecutor``)."""
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
            return InlineExecutor() if jobs == 1 or kind == "inline" else LocalExecutor(jobs, batch)
    else:
        raise UserError(f"unknown executor '{kind}'; choose local or dask", field="--executor")
    return LazyExecutor(factory, on_start)
