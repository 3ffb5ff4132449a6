"""Sweep and executor figures (issue 7).

    python bench/bench_sweep.py                 # all figures
    python bench/bench_sweep.py --skip-default  # only the numeric figures

1. An 8-variant sweep of the default pipeline over keyshapes.k from an empty store: executed stage count against
   the number of distinct keys, and wall time against running the 8 variants one after another, each from an
   empty store (no sharing).
2. Speed-up of -j 2 (local worker processes: the burn stage says neither ``in_process`` nor ``cheap``, so msflow's
   own process runs none of it) and Dask with 2 workers over -j 1 on a sweep of independent CPU-bound variants
   (goal >= 1.7x on 2 cores).
3. Overhead per stage through Dask (trivial stages) against in-process execution.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NUMPROJECT = ROOT / "tests" / "numproject"


def copy_repo(dest: Path) -> Path:
    dest.mkdir(parents=True)
    for name in ("pipeline.yaml", "data", "stages", "pyproject.toml"):
        src = ROOT / name
        (shutil.copytree if src.is_dir() else shutil.copy2)(
            src, dest / name, **({"ignore": shutil.ignore_patterns("__pycache__")} if src.is_dir() else {})
        )
    return dest / "pipeline.yaml"


def default_sweep(tmp: Path, jobs: int) -> dict:
    import msflow
    from msflow.sweep import expand_variants, run_sweep

    values = "keyshapes.k=6,8,10,12,14,16,18,20"
    variants = expand_variants([values], None)
    pipeline = copy_repo(tmp / "sweep")
    started = time.perf_counter()
    result = run_sweep(pipeline, variants, jobs=jobs)
    sweep_wall = time.perf_counter() - started
    sequential = 0.0
    for i, variant in enumerate(variants):
        alone = copy_repo(tmp / f"alone{i}")
        started = time.perf_counter()
        msflow.run(alone, overrides=[f"keyshapes.k={variant['keyshapes.k']}"])
        sequential += time.perf_counter() - started
    return {
        "variants": len(variants),
        "executed": result.executed,
        "distinct_keys": result.unique_keys,
        "sweep_wall_s": round(sweep_wall, 2),
        "sequential_empty_store_wall_s": round(sequential, 2),
        "jobs": jobs,
        "failed": sum(not v.ok for v in result.variants),
    }


def numeric_project(tmp: Path, name: str) -> Path:
    dest = tmp / name
    shutil.copytree(NUMPROJECT, dest, ignore=shutil.ignore_patterns(".msflow", "*.lock", "__pycache__"))
    (dest / "burn.yaml").write_text(
        "version: 1\nstages:\n  burn:\n    uses: numstages.basic:Burn\n    params: {rounds: 400000}\n"
    )
    return dest / "burn.yaml"


def speedup(tmp: Path) -> dict:
    from msflow.sweep import expand_variants, run_sweep

    variants = expand_variants(["burn.seed=1,2,3,4,5,6,7,8"], None)
    times = {}
    for label, options in {"j1": {"jobs": 1}, "j2": {"jobs": 2}, "dask2": {"jobs": 2, "executor": "dask"}}.items():
        pipeline = numeric_project(tmp, label)
        started = time.perf_counter()
        result = run_sweep(pipeline, variants, **options)
        times[label] = time.perf_counter() - started
        assert result.executed == 8, result.executed
    from msflow.dask_executor import DaskExecutor

    started = time.perf_counter()
    DaskExecutor(jobs=2).shutdown()
    cluster = time.perf_counter() - started
    return {
        "j1_s": round(times["j1"], 2),
        "j2_s": round(times["j2"], 2),
        "dask2_s": round(times["dask2"], 2),
        "speedup_j2": round(times["j1"] / times["j2"], 2),
        "speedup_dask2": round(times["j1"] / times["dask2"], 2),
        "dask2_cluster_start_s": round(cluster, 2),
        "speedup_dask2_excluding_cluster_start": round(times["j1"] / (times["dask2"] - cluster), 2),
    }


def dask_overhead(tmp: Path, stages: int = 40) -> dict:
    import msflow

    dest = tmp / "overhead"
    shutil.copytree(NUMPROJECT, dest, ignore=shutil.ignore_patterns(".msflow", "*.lock", "__pycache__"))
    body = "".join(f"  s{i}:\n    uses: numstages.basic:Source\n    params: {{n: {i + 3}}}\n" for i in range(stages))
    (dest / "many.yaml").write_text("version: 1\nstages:\n" + body)
    results = {}
    for label, options in {"inline": {}, "dask1": {"executor": "dask", "jobs": 1}}.items():
        shutil.rmtree(dest / ".msflow", ignore_errors=True)
        msflow.run(dest / "many.yaml", overrides=["s0.n=2"], **options)  # warm up (cluster start excluded below)
        shutil.rmtree(dest / ".msflow", ignore_errors=True)
        started = time.perf_counter()
        msflow.run(dest / "many.yaml", **options)
        results[label] = time.perf_counter() - started
    from msflow.dask_executor import DaskExecutor

    started = time.perf_counter()
    DaskExecutor(jobs=1).shutdown()
    startup = time.perf_counter() - started
    return {
        "inline_per_stage_ms": round(1000 * results["inline"] / stages, 1),
        "dask_per_stage_ms_incl_cluster_start": round(1000 * results["dask1"] / stages, 1),
        "dask_cluster_start_s": round(startup, 2),
        "dask_per_stage_ms": round(1000 * (results["dask1"] - startup) / stages, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--skip-default", action="store_true")
    parser.add_argument("-j", type=int, default=2)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if not args.skip_default:
            print("8-variant sweep of the default pipeline:", default_sweep(tmp, args.j), flush=True)
        print("speed-up on 8 independent CPU-bound variants:", speedup(tmp), flush=True)
        print("Dask overhead:", dask_overhead(tmp), flush=True)


if __name__ == "__main__":
    main()
