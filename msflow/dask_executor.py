"""Dask executor: stage executions as Dask tasks on a LocalCluster or an existing cluster.

Tasks carry JSON jobs and return JSON outcomes (a manifest of content hashes); arrays go worker -> store, never
through the scheduler. Each worker runs one task at a time with BLAS pinned to one thread. A worker that dies
mid-stage leaves at most an unpublished temporary directory, and Dask reschedules the task on another worker
(``distributed.scheduler.allowed-failures`` times); the per-key store lock keeps reruns exactly-once.
"""

from __future__ import annotations

import uuid
from concurrent.futures import Future
from typing import Any

from msflow.errors import UserError
from msflow.worker import BLAS_VARS


class DaskExecutor:
    name = "dask"

    def __init__(self, jobs: int = 1, scheduler: str | None = None, timeout: float = 10.0):
        try:
            from distributed import Client, LocalCluster
        except ImportError:
            raise UserError(
                "the Dask executor needs dask.distributed: pip install 'msflow[dask]'", field="--executor"
            ) from None
        self.cluster = None
        if scheduler:
            try:
                self.client = Client(scheduler, timeout=timeout, set_as_default=False)
            except (OSError, TimeoutError) as exc:
                raise UserError(
                    f"cannot reach the Dask scheduler at {scheduler} within {timeout:g}s "
                    f"({type(exc).__name__}); is it running and is the address right?",
                    field="--scheduler",
                ) from None
        else:
            import dask

            env = {var: "1" for var in BLAS_VARS}
            # the statistical profiler samples every worker's stack every 10 ms; msflow never reads it
            with dask.config.set({"distributed.worker.profile.enabled": False}):
                self.cluster = LocalCluster(
                    n_workers=jobs,
                    threads_per_worker=1,
                    processes=True,
                    dashboard_address=None,
                    env=env,
                    silence_logs=40,
                )
            self.client = Client(self.cluster, set_as_default=False)

    def submit(self, job_json: str) -> Future[str]:
        from msflow.jobs import Job
        from msflow.worker import run_job

        job = Job.from_json(job_json)
        key = f"msflow-{job.stage}-{job.key[:12]}-{uuid.uuid4().hex[:6]}"
        task = self.client.submit(run_job, job_json, key=key, pure=False)
        future: Future[str] = Future()

        def transfer(done: Any) -> None:
            try:
                future.set_result(done.result())
            except Exception as exc:
                future.set_exception(exc)

        task.add_done_callback(transfer)
        return future

    def shutdown(self) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()
