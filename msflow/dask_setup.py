"""Dask worker set-up for msflow:
``dask worker SCHEDULER --preload-nanny msflow.dask_setup --preload msflow.dask_setup``.

As a **nanny** preload: the nanny spawns each worker process with ``MALLOC_TRIM_THRESHOLD_=65536``
(``distributed.nanny.pre-spawn-environ``). Setting that variable switches off glibc's adaptive mmap threshold:
every numpy temporary above 128 KiB is then mapped and unmapped again, and its pages faulted in on every use.
msflow's numpy-heavy stages took 1.4-1.7x the CPU on such workers (bench/bench_dask.py). This module removes the
variable before the nanny spawns (and respawns) its worker, so workers run with glibc's defaults, as local runs do.
``msflow.worker.tune_malloc`` is the safety net for workers started without the preload: run once per worker
process before its first job, it restores large mmap and trim thresholds (the values glibc's adaptive rule reaches
for large arrays) when the variable holds the nanny's default.

As a **worker** preload: the worker imports, before it joins the scheduler, what every msflow job needs (msflow's
worker path, numpy, zarr, the store backends that are installed) and the modules named in ``MSFLOW_WORKER_IMPORTS``
(comma-separated, e.g. ``scipy.signal,cv2,av``: the stages' heavy libraries). Otherwise each worker process pays
those imports and the scan of installed distributions (1-2 s of CPU each) inside the first run's first stages, which on a fresh cluster made the first run
markedly slower than the next (bench/bench_dask.py). A module that fails to import is reported in the worker's log
and left to the job that needs it, which then fails with the real error.
"""

from __future__ import annotations

import importlib
import logging
import os
from typing import Any

#: imported by every worker at start-up: the modules each msflow job imports before its stage's own
WORKER_MODULES = (
    "msflow.worker",
    "msflow.shipping",
    "msflow.plan",  # shipped code is made importable through it (and it brings pydantic: ~0.12 s)
    "msflow.stage",  # results are validated through it
    "msflow.stores",
    "msflow.stores.local",
    "numpy",
    "zarr",
    "threadpoolctl",  # BLAS pools limited around every stage
)
#: imported when installed: the object-store backends of remote stores
OPTIONAL_MODULES = ("msflow.stores.remote", "s3fs")
IMPORTS_VAR = "MSFLOW_WORKER_IMPORTS"


def dask_setup(server: Any) -> None:
    """Dask preload hook: a nanny gets the spawn environment fixed, a worker its imports warmed."""
    from distributed import Nanny

    if isinstance(server, Nanny):
        setup_nanny(server)
    else:
        warm_imports(extra_modules(os.environ.get(IMPORTS_VAR, "")))


def setup_nanny(nanny: Any) -> None:
    """Spawn workers without the malloc-trim override (and with one BLAS thread each)."""
    for env in (getattr(nanny, "pre_spawn_env", None), getattr(nanny, "env", None)):
        if isinstance(env, dict):
            env.pop("MALLOC_TRIM_THRESHOLD_", None)
    os.environ.pop("MALLOC_TRIM_THRESHOLD_", None)  # the nanny's own, inherited by respawned workers
    from msflow.worker import BLAS_VARS

    if isinstance(getattr(nanny, "env", None), dict):
        for var in BLAS_VARS:
            nanny.env.setdefault(var, "1")


def extra_modules(value: str) -> list[str]:
    """The module names of ``MSFLOW_WORKER_IMPORTS`` (commas or spaces between them)."""
    return [name for name in value.replace(",", " ").split() if name]


def warm_imports(extra: list[str]) -> dict[str, str]:
    """Import msflow's worker path, the installed store backends and ``extra``; returns the failures (module ->
    error), each also logged, so a mistyped name never stops the worker."""
    from msflow.worker import pin_blas_threads, tune_malloc

    pin_blas_threads()
    tune_malloc()
    failed: dict[str, str] = {}
    for name in (*WORKER_MODULES, *OPTIONAL_MODULES, *extra):
        try:
            importlib.import_module(name)
        except ImportError as exc:
            if name not in OPTIONAL_MODULES:
                failed[name] = f"{type(exc).__name__}: {exc}"
        except Exception as exc:  # a module that raises on import: its stage will report it
            failed[name] = f"{type(exc).__name__}: {exc}"
    from msflow.fingerprint import warm_distribution_index

    warm_distribution_index()  # every job's environment check maps its imports to distributions
    for name, error in failed.items():
        logging.getLogger("msflow.dask_setup").warning("msflow: could not pre-import %s (%s)", name, error)
    return failed
