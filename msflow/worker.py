"""Execute one stage: the unit of work every executor runs (in-process, a process pool, a Dask worker).

A job and its outcome are JSON strings, so nothing but JSON crosses process or machine boundaries. The worker
takes the key's lock, re-checks the store (a concurrent run may have produced the artifact meanwhile; or the runner
left the check to it, ``Job.checked``), runs the stage, validates its result, and publishes the artifact
atomically before releasing the lock.
"""

from __future__ import annotations

import contextlib
import os
import time
import traceback
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

from msflow.jobs import Job, JobInput, Outcome, StageStatus
from msflow.shipping import worker_name

if TYPE_CHECKING:
    from msflow.stage import Result, Stage
    from msflow.stores.base import ArtifactWriter, Store

BLAS_VARS = (
    "OPENBLAS_NUM_THREADS",
    "OMP_NUM_THREADS",
    "MKL_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "NUMEXPR_NUM_THREADS",
)


def pin_blas_threads() -> None:
    """One BLAS thread per worker process: parallelism comes from running stages side by side."""
    for var in BLAS_VARS:
        os.environ.setdefault(var, "1")


_CONTROLLER: Any = None

NANNY_MALLOC_TRIM = "65536"  #: the MALLOC_TRIM_THRESHOLD_ a Dask nanny sets for its workers (msflow.dask_setup)
MMAP_THRESHOLD = 32 << 20  # glibc's largest adaptive mmap threshold on 64-bit (DEFAULT_MMAP_THRESHOLD_MAX)
TRIM_THRESHOLD = 2 * MMAP_THRESHOLD  # what the adaptive rule sets beside it
_TUNED = False


def tune_malloc() -> bool:
    """Undo the nanny's malloc-trim default in this process (glibc only, once); True when it did."""
    import sys

    global _TUNED
    if _TUNED or os.environ.get("MALLOC_TRIM_THRESHOLD_") != NANNY_MALLOC_TRIM or not sys.platform.startswith("linux"):
        return False
    _TUNED = True
    import ctypes

    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:  # not glibc (musl): the variable means nothing there
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3  # <malloc.h>
    return bool(libc.mallopt(m_mmap_threshold, MMAP_THRESHOLD)) and bool(libc.mallopt(m_trim_threshold, TRIM_THRESHOLD))


def single_threaded_blas() -> contextlib.AbstractContextManager[object]:
    """Limit already-loaded BLAS/OpenMP pools to one thread (env vars only reach libraries loaded later)."""
    global _CONTROLLER
    from threadpoolctl import ThreadpoolController

    if _CONTROLLER is None:  # scanning the loaded libraries costs milliseconds: once per process
        _CONTROLLER = ThreadpoolController()
    limited: contextlib.AbstractContextManager[object] = _CONTROLLER.limit(limits=1)
    return limited


def run_job(job_json: str) -> str:
    """Run one job (``Job`` as JSON) and return its ``Outcome`` as JSON. Never raises."""
    from msflow.errors import CorruptArtifact, StageFailed, UserError

    tune_malloc()  # a Dask nanny's malloc-trim default slows numpy-heavy stages 2x
    job = Job.from_json(job_json)
    started = time.perf_counter()
    try:
        outcome = run_locked(job)
    except CorruptArtifact as exc:  # an input failed its integrity check: the runner repairs and retries
        corrupt = {"key": exc.key or "", "problem": exc.problem}
        outcome = Outcome(StageStatus.FAILED, error=str(exc), corrupt=corrupt)
    except UserError as exc:
        exc.located(stage=job.stage)
        outcome = Outcome(StageStatus.FAILED, user_error=exc.to_json(), error=str(exc))
    except StageFailed as exc:  # the stage's own error and traceback (none for a result that breaks its schema)
        outcome = Outcome.crashed(exc.message, exc.traceback or None)
    except Exception as exc:
        outcome = Outcome.crashed(f"{type(exc).__name__}: {exc}", traceback.format_exc())
    outcome.seconds = time.perf_counter() - started
    outcome.pid = os.getpid()
    outcome.worker = worker_name()
    return outcome.to_json()


def code_root(job: Job) -> str:
    """Where the job's stage modules import from: the project folder, or for a shipped job (``job.code``) the
    code tree rebuilt in this worker's cache after checking that its environment matches the key's."""
    from msflow.plan import ensure_importable

    if job.code is None:
        ensure_importable(job.project_root)
        return job.project_root
    from msflow.shipping import check_environment, check_store, shipped_code

    check_store(job)
    check_environment(job)
    return str(shipped_code(job))


def run_locked(job: Job) -> Outcome:
    """Under the key's lock: reuse an artifact a concurrent run published meanwhile, or compute and publish."""
    from msflow.stores import open_store

    root = code_root(job)
    store = open_store(job.store, job.store_options)
    waited: list[object] = []  # another run held the key's lock: what is found then is that run's work

    def on_wait(holder: dict[str, Any]) -> None:
        waited.append(holder)
        report_waiting(job.stage, holder)

    with (
        store.lock(job.key, on_wait=on_wait),
        store.writer(job.key) as writer,  # before the re-check: a remote writer journals its folder meanwhile
    ):
        if store.has(job.key) and not job.force:
            concurrent = job.checked or bool(waited)  # unchecked (Job.checked) and no wait: a plain cache hit
            return Outcome(StageStatus.CACHED, manifest=store.manifest(job.key), concurrent=concurrent)
        return execute(job, store, writer, root)


def settle() -> None:
    """Let this process's store work that outlives its jobs land: the lease releases in flight
    (msflow.stores.remote.settle_releases). Executors call it when a run ends, in every process that ran jobs."""
    import sys

    remote = sys.modules.get("msflow.stores.remote")
    if remote is not None:
        remote.settle_releases()


def report_waiting(stage: str, holder: dict[str, Any]) -> None:
    """Tell the user why a stage seems stuck: another run (named by the lock) is computing the same key."""
    import sys

    from msflow.stores.base import describe_holder

    who = describe_holder(holder) if holder else "another process"
    print(
        f"msflow: stage '{stage}' is being computed by another run ({who}); waiting for it", file=sys.stderr, flush=True
    )


def report_waiting_for_part(stage: str, label: str, holder: dict[str, Any]) -> None:
    """Tell the user why a stage seems stuck on one of its parts (msflow.parts): another run is computing it."""
    report_waiting(f"{stage}' part '{label}", holder)


@dataclass
class Computed:
    """A stage's validated result: outputs (numpy arrays or finished sinks), strict-JSON meta and metrics,
    warnings (as messages), the seconds ``run`` took, and every warning ``run`` raised (``caught``, with its
    category, for callers that re-emit them)."""

    arrays: dict[str, Any]
    meta: dict[str, Any]
    metrics: dict[str, float]
    warnings: list[str]
    seconds: float
    caught: list[Any] = field(default_factory=list)


def compute(
    cls: type[Stage],
    name: str,
    params: Any,
    inputs: dict[str, Any],
    *,
    jobs: int = 1,
    chunk_target: Any = None,
    parts: Any = None,
    pin_blas: bool = True,
) -> Computed:
    """Run a stage and validate what it returns: the one execution path of the runner's workers and of
    ``msflow.testing.run_stage``. Exceptions of ``run`` propagate unchanged; an invalid result raises
    ``TypeError``/``ValueError`` naming the stage and output. ``pin_blas``: one BLAS thread during ``run`` (the
    runner's workers run stages side by side); ``run_stage`` leaves the caller's BLAS threading alone."""
    from msflow.errors import InvalidResult
    from msflow.sinks import nonfinite_warnings
    from msflow.stage import to_strict_json, validate_result

    stage = cls(name, jobs=jobs, chunk_target=chunk_target, parts=parts)
    started = time.perf_counter()
    with (
        single_threaded_blas() if pin_blas else contextlib.nullcontext(),
        warnings.catch_warnings(record=True) as caught,
    ):
        warnings.simplefilter("always", UserWarning)  # the stage's own warnings, each time
        result = stage.run(params, inputs)
    seconds = time.perf_counter() - started
    try:
        arrays = validate_result(name, cls, result)
        meta = to_strict_json(result.meta, f"stage '{name}' meta")
        metrics = to_strict_json(result.metrics, f"stage '{name}' metrics")
        stage_warnings = collect_warnings(result, caught)
    except (TypeError, ValueError) as exc:
        raise InvalidResult(str(exc)) from None
    bad = [k for k, v in metrics.items() if not isinstance(v, (int, float)) or isinstance(v, bool)]
    if bad:
        raise InvalidResult(f"stage '{name}': metrics must be scalar numbers; not: {bad}")
    stage_warnings += nonfinite_warnings(arrays)  # usable, most likely wrong: said, never a failure
    return Computed(arrays, meta, metrics, stage_warnings, seconds, list(caught))


def execute(job: Job, store: Store, writer: ArtifactWriter, root: str) -> Outcome:
    """Import the stage class (from ``root``), open its inputs, compute, and commit the artifact through
    ``writer``."""
    from msflow.errors import CorruptArtifact, InvalidResult, StageFailed, UserError
    from msflow.parts import StoreParts
    from msflow.plan import import_stage_class

    cls = import_stage_class(job.uses, stage=job.stage, root=root)
    params = cls.Params(**job.params)
    inputs = open_inputs(job.inputs, store, job)
    parts = None
    if job.key_parts is not None:
        waiting = partial(report_waiting_for_part, job.stage)
        parts = StoreParts(store, job.key_parts, job.stage, job.force, on_wait=waiting)
    cpu = cpu_time()
    try:
        done = compute(cls, job.stage, params, inputs, jobs=job.jobs, chunk_target=writer, parts=parts)
    except (UserError, CorruptArtifact):
        raise
    except InvalidResult as exc:
        raise StageFailed(job.stage, str(exc)) from exc
    except Exception as exc:
        raise StageFailed(job.stage, f"{type(exc).__name__}: {exc}", traceback.format_exc()) from exc
    suffixes = {k: spec.file_suffix for k, spec in cls.outputs.items() if spec.file_suffix}
    extra: dict[str, Any] = {
        "meta": done.meta,
        "metrics": done.metrics,
        "key": job.key,
        "stage": job.stage,
        "uses": job.uses,
        "key_parts": job.key_parts,
        "created": time.time(),
    }
    if done.warnings:
        extra["warnings"] = done.warnings
    if parts is not None and parts.used:  # the parts it was built from: gc keeps them with it
        extra["parts"] = {"keys": parts.used, "reused": parts.reused}
    cpu = cpu_time() - cpu
    # how long it took is kept beside the content (msflow show), outside every hash and key
    extra.update(compute_seconds=round(done.seconds, 6), cpu_seconds=round(cpu, 6))
    manifest = writer.commit(done.arrays, extra, suffixes, replace=job.force)
    return Outcome(StageStatus.RAN, manifest=manifest, compute_seconds=done.seconds, cpu_seconds=cpu)


def cpu_time() -> float:
    """CPU seconds (user + system) of this process and of the child processes it has waited for (an FFmpeg a stage
    ran): differences of it measure a stage's execution in the process that ran it."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def collect_warnings(result: Result, caught: list[Any]) -> list[str]:
    """The stage's warnings: ``Result.warnings`` then ``UserWarning``s raised in ``run``, in order, each once."""
    messages = list(getattr(result, "warnings", None) or [])
    messages += [str(w.message) for w in caught if issubclass(w.category, UserWarning)]
    if not all(isinstance(m, str) for m in messages):
        raise TypeError("Result.warnings must be a list of strings")
    return list(dict.fromkeys(messages))


def open_inputs(spec: Mapping[str, JobInput | None], store: Store, job: Job | None = None) -> dict[str, Any]:
    """Materialise a job's inputs: artifacts as views, single outputs as numpy (or lazy), files as ``Files``
    (shipped files, ``entry.blobs``, fetched from the store into this worker's cache)."""
    from msflow.stage import Files

    inputs: dict[str, Any] = {}
    for name, entry in spec.items():
        if entry is None:
            inputs[name] = None
        elif entry.kind == "files" and entry.blobs is not None and job is not None:
            from msflow.shipping import shipped_files

            inputs[name] = shipped_files(entry, job)
        elif entry.kind == "files":
            inputs[name] = Files({label: Path(path) for label, path in entry.files}, entry.fields)
        else:
            assert entry.key is not None
            view = store.open(entry.key)
            if entry.kind == "artifact":
                inputs[name] = view
            else:
                assert entry.output is not None
                inputs[name] = view.lazy(entry.output) if entry.lazy else view[entry.output]
    return inputs
