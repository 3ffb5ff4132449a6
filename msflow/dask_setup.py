"""Dask worker set-up for msflow: ``dask worker SCHEDULER --preload-nanny msflow.dask_setup``.

The nanny spawns each worker process with ``MALLOC_TRIM_THRESHOLD_=65536``
(``distributed.nanny.pre-spawn-environ``). Setting that variable switches off glibc's adaptive mmap threshold:
every numpy temporary above 128 KiB is then mapped and unmapped again, and its pages faulted in on every use.
msflow's numpy-heavy stages took 1.4-1.7x the CPU on such workers (bench/bench_dask.py). As a nanny preload this
module removes the variable before the nanny spawns (and respawns) its worker, so workers run with glibc's defaults,
as local runs do.

``msflow.worker.tune_malloc`` is the safety net for workers started without the preload: run once per worker
process before its first job, it restores large mmap and trim thresholds (the values glibc's adaptive rule reaches
for large arrays) when the variable holds the nanny's default.
"""

from __future__ import annotations

import os
from typing import Any


def dask_setup(nanny: Any) -> None:
    """Nanny preload: spawn workers without the malloc-trim override (and with one BLAS thread each)."""
    for env in (getattr(nanny, "pre_spawn_env", None), getattr(nanny, "env", None)):
        if isinstance(env, dict):
            env.pop("MALLOC_TRIM_THRESHOLD_", None)
    os.environ.pop("MALLOC_TRIM_THRESHOLD_", None)  # the nanny's own, inherited by respawned workers
    from msflow.worker import BLAS_VARS

    if isinstance(getattr(nanny, "env", None), dict):
        for var in BLAS_VARS:
            nanny.env.setdefault(var, "1")
