"""Execute one stage: the unit of work every executor runs (in-process, a process pool, a Dask worker).

A job and its outcome are JSON strings, so nothing but JSON crosses process or machine boundaries. The worker
takes the key's lock, re-checks the store (a concurrent run may have produced the artifact meanwhile), runs the
stage, validates its result, and publishes the artifact atomically before releasing the lock.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
import traceback
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

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


_CONTROLLER = None


def single_threaded_blas():
    """Limit already-loaded BLAS/OpenMP pools to one thread (env vars only reach libraries loaded later)."""
    global _CONTROLLER
    from threadpoolctl import ThreadpoolController

    if _CONTROLLER is None:  # scanning the loaded libraries costs milliseconds: once per process
        _CONTROLLER = ThreadpoolController()
    return _CONTROLLER.limit(limits=1)


def run_job(job_json: str) -> str:
    """Run one job (JSON) and return its outcome (JSON). Never raises."""
    job = json.loads(job_json)
    started = time.perf_counter()
    try:
        outcome = _run(job)
    except Exception as exc:
        from msflow.errors import UserError

        if isinstance(exc, UserError):
            exc.located(stage=job["stage"])
            outcome = {"state": "failed", "user_error": exc.to_json(), "error": str(exc)}
        else:
            outcome = {"state": "failed", "error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}
    outcome["seconds"] = time.perf_counter() - started
    outcome["pid"] = os.getpid()
    return json.dumps(outcome, allow_nan=False)


def _run(job: dict) -> dict:
    from msflow.plan import ensure_importable
    from msflow.store import open_store

    ensure_importable(job["project_root"])
    store = open_store(job["store"], job.get("store_options"))
    key = job["key"]
    with store.lock(key):
        if store.has(key) and not job.get("force"):
            return {"state": "cached", "manifest": store.manifest(key), "concurrent": True}
        with store.writer(key) as writer:
            return _execute(job, store, writer)


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
    cls,
    name: str,
    params: Any,
    inputs: dict[str, Any],
    *,
    jobs: int = 1,
    chunk_target: Any = None,
    pin_blas: bool = True,
) -> Computed:
    """Run a stage and validate what it returns: the one execution path of the runner's workers and of
    ``msflow.testing.run_stage``. Exceptions of ``run`` propagate unchanged; an invalid result raises
    ``TypeError``/``ValueError`` naming the stage and output. ``pin_blas``: one BLAS thread during ``run`` (the
    runner's workers run stages side by side); ``run_stage`` leaves the caller's BLAS threading alone."""
    from msflow.errors import InvalidResult
    from msflow.stage import to_strict_json, validate_result

    stage = cls(name, jobs=jobs, chunk_target=chunk_target)
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
    return Computed(arrays, meta, metrics, stage_warnings, seconds, list(caught))


def _execute(job: dict, store, writer) -> dict:
    from msflow.errors import InvalidResult, StageFailed, UserError
    from msflow.plan import import_stage_class

    name = job["stage"]
    cls = import_stage_class(job["uses"], stage=name, root=job["project_root"])
    params = cls.Params(**job["params"])
    inputs = open_inputs(job["inputs"], store)
    try:
        done = compute(cls, name, params, inputs, jobs=int(job.get("jobs", 1)), chunk_target=writer)
    except UserError:
        raise
    except InvalidResult as exc:
        raise StageFailed(name, str(exc)) from exc
    except Exception as exc:
        raise StageFailed(name, f"{type(exc).__name__}: {exc}", traceback.format_exc()) from exc
    suffixes = {k: spec.file_suffix for k, spec in cls.outputs.items() if spec.file_suffix}
    extra = {
        "meta": done.meta,
        "metrics": done.metrics,
        "key": job["key"],
        "stage": name,
        "uses": job["uses"],
        "key_parts": job.get("key_parts"),
        "created": time.time(),
    }
    if done.warnings:
        extra["warnings"] = done.warnings
    manifest = writer.commit(done.arrays, extra, suffixes, replace=bool(job.get("force")))
    return {"state": "ran", "manifest": manifest, "compute_seconds": done.seconds}


def collect_warnings(result, caught: list) -> list[str]:
    """The stage's warnings: ``Result.warnings`` then ``UserWarning``s raised in ``run``, in order, each once."""
    messages = list(getattr(result, "warnings", None) or [])
    messages += [str(w.message) for w in caught if issubclass(w.category, UserWarning)]
    if not all(isinstance(m, str) for m in messages):
        raise TypeError("Result.warnings must be a list of strings")
    return list(dict.fromkeys(messages))


def open_inputs(spec: dict, store) -> dict:
    """Materialise a job's inputs: artifacts as views, single outputs as numpy (or lazy), files as Paths."""
    from msflow.stage import Files

    inputs: dict = {}
    for name, entry in spec.items():
        if entry is None:
            inputs[name] = None
        elif entry["kind"] == "files":
            inputs[name] = Files({label: Path(path) for label, path in entry["files"]}, entry.get("fields"))
        elif entry["kind"] == "artifact":
            inputs[name] = store.open(entry["key"])
        else:
            view = store.open(entry["key"])
            inputs[name] = view.lazy(entry["output"]) if entry.get("lazy") else view[entry["output"]]
    return inputs
