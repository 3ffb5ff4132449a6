"""Dask executor: stage executions as Dask tasks on a LocalCluster or on an existing cluster (``--scheduler``).

Tasks carry JSON jobs and return JSON outcomes (a manifest of content hashes); arrays go worker -> store, never
through the scheduler. Each worker runs one task at a time with BLAS pinned to one thread.

On an existing cluster the workers need only the store and a Python environment: jobs are *shipped*
(``msflow.shipping``): the stages' code and the data files reach the workers as content-addressed blobs in the
store, and a worker whose environment differs from the key's refuses the job. A LocalCluster shares this
machine's disk, so its jobs read the project folder directly (``MSFLOW_DASK_SHIP=1`` ships them anyway, to try a
project's shipping locally).

A worker that dies mid-stage leaves at most an unpublished temporary folder, and Dask reschedules the task on
another worker (``distributed.scheduler.allowed-failures`` times); the per-key store lock keeps reruns
exactly-once. The executor follows the scheduler's ``remove-worker`` events, so each stage's outcome says how many
attempts it took and which workers were lost, and the progress display shows a retry when it starts.

Workers are started without the nanny's ``MALLOC_TRIM_THRESHOLD_`` default: that variable switches off glibc's
adaptive mmap threshold, so every large numpy temporary is mapped and unmapped again (page faults on every use)
and numpy-heavy stages took 1.4-1.7x the CPU (bench/bench_dask.py). The LocalCluster is configured so; external
workers get the same with ``--preload-nanny msflow.dask_setup`` (README, "Run on a cluster").
"""

from __future__ import annotations

import os
import shutil
import socket
import tempfile
import threading
import time
import uuid
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

from msflow.errors import UserError
from msflow.worker import BLAS_VARS

DEFAULT_PORT = 8786
#: Dask settings for msflow's workers: no malloc-trim override (see the module docstring), no statistical
#: profiler (it samples every worker's stack every 10 ms; msflow never reads it), and the per-process system
#: monitor (psutil, every 0.5 s, for the dashboard's graphs) and event-loop tick (20 ms, for "event loop blocked"
#: warnings) slowed: an idle 2-worker LocalCluster took 0.069 of a core, 0.025 with these (bench/bench_dask.py)
WORKER_CONFIG: dict[str, Any] = {
    "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
    "distributed.worker.profile.enabled": False,
    "distributed.admin.system-monitor.interval": "5s",
    "distributed.admin.tick.interval": "200ms",
}


@dataclass(frozen=True)
class SchedulerAddress:
    """A checked scheduler address: what the user wrote, and the scheme, host and port Dask will use."""

    given: str
    scheme: str
    host: str
    port: int

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{self.scheme}://{host}:{self.port}"


def parse_scheduler_address(given: str) -> SchedulerAddress:
    """Check ``--scheduler`` before anything runs: ``[tcp|tls|ws|wss]://host[:port]`` (port 8786 by default)."""
    text = given.strip()
    scheme, sep, location = text.partition("://")
    if not sep:
        scheme, location = "tcp", text

    def bad(cause: str) -> UserError:
        return UserError(f"invalid Dask scheduler address '{given}': {cause}", field="--scheduler")

    if scheme not in ("tcp", "tls", "ws", "wss"):
        hint = " (http:// is the dashboard's address)" if scheme in ("http", "https") else ""
        raise bad(f"unknown scheme '{scheme}://'{hint}; write tcp://HOST:{DEFAULT_PORT}")
    location = location.rstrip("/")
    if not location or "/" in location:
        raise bad(f"expected {scheme}://HOST:PORT")
    if location.startswith("["):  # [ipv6]:port
        host, _, rest = location[1:].partition("]")
        port_text = rest[1:] if rest.startswith(":") else ("" if not rest else None)
    else:
        host, _, port_text = location.rpartition(":") if ":" in location else (location, "", "")
    if port_text is None or not host:
        raise bad(f"expected {scheme}://HOST:PORT")
    if not port_text:
        return SchedulerAddress(given, scheme, host, DEFAULT_PORT)
    if not port_text.isdigit():
        raise bad(f"the port '{port_text}' is not a number")
    port = int(port_text)
    if not 0 < port < 65536:
        raise bad(f"the port {port} is out of range (1-65535)")
    return SchedulerAddress(given, scheme, host, port)


def probe(address: SchedulerAddress, timeout: float) -> None:
    """Open (and close) a TCP connection to the scheduler's port: names the cause when nothing is there."""
    try:
        with socket.create_connection((address.host, address.port), timeout=timeout):
            pass
    except ConnectionRefusedError:
        cause = "connection refused (is the scheduler running, and is this its port?)"
    except socket.gaierror as exc:
        cause = f"unknown host '{address.host}' ({exc.strerror})"
    except TimeoutError:
        cause = f"no answer within {timeout:g}s (a firewall, or a wrong host?)"
    except OSError as exc:
        cause = (exc.strerror or str(exc)).lower()
    else:
        return
    raise UserError(f"cannot reach the Dask scheduler at {address.given}: {cause}", field="--scheduler")


def identify(address: SchedulerAddress, timeout: float, deadline: float | None = None) -> str:
    """Ask the server at ``address`` what it is (Dask's ``identity`` call), all within ``timeout``: a port that
    accepts connections but never answers would otherwise hang the Client forever. ``deadline``: seconds left of
    ``timeout`` (the one messages name)."""
    import asyncio

    from distributed.comm.core import connect as open_comm

    async def ask() -> Any:
        comm = await open_comm(address.url, timeout=timeout)
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            comm.abort()

    try:
        reply = asyncio.run(asyncio.wait_for(ask(), timeout if deadline is None else deadline))
    except Exception as exc:  # whatever a foreign server's bytes make Dask's parser raise
        if isinstance(exc, TimeoutError):
            cause = f"no Dask handshake within {timeout:g}s"
        elif isinstance(exc, OSError):
            cause = str(exc) or type(exc).__name__
        else:  # e.g. an HTTP server: its reply read as Dask frame lengths (a MemoryError of exabytes)
            cause = "what it says is not Dask's protocol"
        raise UserError(
            f"cannot reach the Dask scheduler at {address.given}: the port answers, but {cause}; is this the "
            f"scheduler's port ({DEFAULT_PORT} by default; 8787 is the dashboard)?",
            field="--scheduler",
        ) from None
    kind = reply.get("type") if isinstance(reply, dict) else None
    if kind != "Scheduler":
        raise UserError(
            f"{address.given} is a Dask {kind or 'server'}, not the scheduler: give the scheduler's address",
            field="--scheduler",
        )
    return str(reply.get("id", ""))


def connect(address: SchedulerAddress, timeout: float) -> Any:
    """A Client of the scheduler at ``address``; a UserError naming address and cause within ``timeout``."""
    from distributed import Client

    started = time.monotonic()
    probe(address, timeout)
    if address.scheme == "tcp":  # tls needs the cluster's security settings: left to the Client
        identify(address, timeout, max(0.5, timeout - (time.monotonic() - started)))
    left = max(0.5, timeout - (time.monotonic() - started))
    try:
        return Client(address.url, timeout=left, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        cause = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise UserError(
            f"cannot connect to the Dask scheduler at {address.given}: {cause}", field="--scheduler"
        ) from None


@dataclass
class Tracked:
    """A submitted task: attempts started so far, the workers lost while running it, who to tell of a retry."""

    attempts: int = 1
    lost: list[str] = field(default_factory=list)
    on_retry: Callable[[str, int], None] | None = None


class DaskExecutor:
    name = "dask"

    def __init__(
        self,
        jobs: int = 1,
        scheduler: str | None = None,
        timeout: float = 10.0,
        shipper: Any = None,
    ):
        try:
            import dask
            from distributed import Client, LocalCluster
        except ImportError:
            raise UserError(
                "the Dask executor needs dask.distributed: pip install 'msflow[dask]'", field="--executor"
            ) from None
        self.cluster = None
        self.scratch: str | None = None
        if scheduler is not None:
            self.client = connect(parse_scheduler_address(scheduler), timeout)
            warn_if_no_workers(self.client, scheduler)
        else:
            env = {var: "1" for var in BLAS_VARS}
            # the workers' scratch space in a folder of its own, deleted at shutdown: Dask's default,
            # $TMPDIR/dask-scratch-space, keeps two lock files there after every run
            self.scratch = tempfile.mkdtemp(prefix="msflow-dask-")
            with dask.config.set({**WORKER_CONFIG, "temporary-directory": self.scratch}):
                self.cluster = LocalCluster(
                    n_workers=jobs,
                    threads_per_worker=1,
                    processes=True,
                    dashboard_address=None,
                    # no dashboard; its HTTP server on a free port of loopback (not 8787, maybe taken)
                    scheduler_kwargs={"dashboard": False, "dashboard_address": "127.0.0.1:0"},
                    env=env,
                    silence_logs=40,
                )
            self.client = Client(self.cluster, set_as_default=False)
        send_without_delay(self.client)
        ship = scheduler is not None or os.environ.get("MSFLOW_DASK_SHIP", "") not in ("", "0")
        self.shipper = shipper if ship else None
        self.tracked: dict[str, Tracked] = {}
        # Dask futures whose results were taken, released at the next submission (if their worker dies before
        # that, Dask reruns them: the stage is then a cache hit under its lock, and nobody waits for it)
        self.finished: list[Any] = []
        self.lock = threading.Lock()
        self.client.subscribe_topic("all", self.on_event)

    def on_event(self, event: Any) -> None:
        """A worker left while running some of our tasks: the scheduler reruns them elsewhere (a new attempt)."""
        _, message = event
        if not isinstance(message, dict) or message.get("action") != "remove-worker":
            return
        lost = str(message.get("worker", "?"))
        for key in message.get("processing-tasks", ()):
            with self.lock:
                tracked = self.tracked.get(str(key))
                if tracked is None:
                    continue
                tracked.attempts += 1
                tracked.lost.append(lost)
            if tracked.on_retry is not None:
                tracked.on_retry(lost, tracked.attempts)

    def submit(self, job_json: str, on_retry: Callable[[str, int], None] | None = None) -> Future[str]:
        from msflow.jobs import Job
        from msflow.worker import run_job

        job = Job.from_json(job_json)
        if self.shipper is not None:
            job = self.shipper.ship(job)
            job_json = job.to_json()
        key = f"msflow-{job.stage}-{job.key[:12]}-{uuid.uuid4().hex[:6]}"
        tracked = Tracked(on_retry=on_retry)
        with self.lock:
            self.tracked[key] = tracked
        task = self.client.submit(run_job, job_json, key=key, pure=False)
        with self.lock:  # after the submission: the releases it would otherwise wait behind (Dask batches them)
            taken, self.finished = self.finished, []
        del taken
        future: Future[str] = Future()

        def transfer(done: Any) -> None:
            with self.lock:
                self.tracked.pop(key, None)
                self.finished.append(done)
            try:
                result = done.result()
            except (KeyboardInterrupt, SystemExit):
                raise
            except BaseException as exc:  # asyncio's CancelledError too: the task is lost
                future.set_result(lost_outcome(exc, tracked))
            else:
                future.set_result(with_attempts(result, tracked))

        task.add_done_callback(transfer)
        return future

    def shutdown(self, *, abort: bool = False) -> None:
        """Closing a LocalCluster stops its workers, running stages or not; a cluster's own workers finish the
        stage they run (Dask cannot stop a task), and its artifact is kept for the next run."""
        import contextlib

        from msflow.worker import settle

        with contextlib.suppress(Exception):  # the scheduler may be gone already
            self.client.unsubscribe_topic("all")
        with contextlib.suppress(Exception):  # the workers' lease releases in flight land before the run ends
            self.client.run(settle)
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()
        if self.scratch is not None:
            shutil.rmtree(self.scratch, ignore_errors=True)


def send_without_delay(client: Any) -> None:
    """Make the client send each message to the scheduler as it is made. Dask's client batches them 10 ms apart
    (a ``BatchedSend`` interval, not configurable): in a chain, the next stage's submission follows the release of
    the previous stage's result by under a millisecond, so it waited ~9 ms for the batch, the largest part of a
    stage's overhead on a cluster (bench/bench_dask.py). msflow's messages are few and small; batching buys nothing.
    A private attribute: a Dask without it keeps its batching, which costs only time."""
    stream = getattr(client, "scheduler_comm", None)
    if stream is not None and isinstance(getattr(stream, "interval", None), float):
        stream.interval = 0.0


def with_attempts(outcome_json: str, tracked: Tracked) -> str:
    """The worker's outcome with what only the client knows: attempts and the workers lost on the way."""
    if tracked.attempts == 1:
        return outcome_json
    from msflow.jobs import Outcome

    outcome = Outcome.from_json(outcome_json)
    outcome.attempts = tracked.attempts
    return outcome.to_json()


def lost_outcome(exc: BaseException, tracked: Tracked) -> str:
    """The outcome of a task that ended without one: Dask gave up after ``allowed-failures`` lost workers, or the
    cluster went away."""
    from msflow.jobs import Outcome

    if type(exc).__name__ == "KilledWorker":
        last = tracked.lost[-1] if tracked.lost else "?"
        message = (
            f"worker lost: {len(tracked.lost) or 'several'} workers died running this stage (the last: {last}); "
            "Dask gave up (distributed.scheduler.allowed-failures); see the workers' logs"
        )
    else:
        message = f"worker lost: {type(exc).__name__}: {exc}"
    outcome = Outcome.crashed(message)
    outcome.attempts = tracked.attempts
    return outcome.to_json()


def warn_if_no_workers(client: Any, scheduler: str) -> None:
    """Stages would wait silently for a worker: say so."""
    import sys

    try:
        workers = client.scheduler_info().get("workers", {})
    except Exception:
        return
    if not workers:
        print(
            f"msflow: the Dask scheduler at {scheduler} has no workers yet; stages wait until one connects",
            file=sys.stderr,
            flush=True,
        )
