"""msflow core performance figures (issue 2).

    python bench/bench_core.py            # all figures
    python bench/bench_core.py --quick    # skip the 1 GB hashing figure

1. CPU (user+sys) of a no-op ``msflow run`` and of ``msflow status`` on a 10-stage pipeline (best of N runs,
   measured through getrusage of the child process). Goal: <= 0.3 s and <= 0.25 s.
2. Hashing a 1 GB data file from the page cache (GB/s; goal >= 3) and a rerun with the file unchanged (no reread).
3. Store overhead per executed stage for small outputs (open, write, publish, record; goal <= 20 ms).
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
NUMPROJECT = HERE.parent / "tests" / "numproject"


def child_cpu(cmd: list[str], cwd: Path, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        subprocess.run(cmd, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        best = min(best, after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
    return best


def ten_stage_pipeline(dest: Path) -> Path:
    shutil.copytree(NUMPROJECT, dest, ignore=shutil.ignore_patterns(".msflow", "*.lock", "__pycache__"))
    stages = ["  s0:\n    uses: numstages.basic:Source\n    params: {n: 50}\n"]
    for i in range(1, 8):
        stages.append(
            f"  s{i}:\n    uses: numstages.scaling:Scale\n    inputs: {{x: s{i - 1}.x}}\n"
            if i == 1
            else f"  s{i}:\n    uses: numstages.scaling:Scale\n    inputs: {{x: s{i - 1}.y}}\n"
        )
    stages.append("  csv:\n    uses: numstages.basic:LoadCsv\n    inputs: {table: {path: data/table.csv}}\n")
    stages.append("  total:\n    uses: numstages.basic:Sum\n    inputs: {a: s7, b: csv.x}\n")
    (dest / "ten.yaml").write_text("version: 1\nstages:\n" + "".join(stages))
    return dest / "ten.yaml"


def bench_noop(tmp: Path, repeats: int) -> dict:
    proj = tmp / "noop"
    ten_stage_pipeline(proj)
    msflow = [sys.executable, "-m", "msflow.cli"]
    subprocess.run(msflow + ["run", "ten.yaml", "-q"], cwd=proj, check=True)
    noop = child_cpu(msflow + ["run", "ten.yaml", "-q"], proj, repeats)
    status = child_cpu(msflow + ["status", "ten.yaml"], proj, repeats)
    baseline = child_cpu([sys.executable, "-c", "pass"], proj, repeats)
    # the no-op path must not import zarr, numpy or stage modules
    probe = subprocess.run(
        [
            sys.executable,
            "-c",
            (
                "import sys; from msflow.cli import main; main(['run', 'ten.yaml', '-q']); "
                "print(sorted(m for m in ('zarr', 'numpy', 'numstages', 'stages') if m in sys.modules))"
            ),
        ],
        cwd=proj,
        capture_output=True,
        text=True,
        check=True,
    )
    return {
        "noop_run_cpu_s": noop,
        "status_cpu_s": status,
        "python_startup_cpu_s": baseline,
        "noop_imports_heavy": probe.stdout.strip(),
    }


def bench_hashing(tmp: Path) -> dict:
    from msflow.hashing import FileHashMemo, file_hash

    big = tmp / "big.bin"
    chunk = os.urandom(1 << 20)
    with open(big, "wb") as fh:
        for _ in range(1024):
            fh.write(chunk)
    file_hash(big)  # warm the page cache
    best = min(_timed(lambda: file_hash(big)) for _ in range(3))
    memo = FileHashMemo()
    memo.hash(big)
    rerun = min(_timed(lambda: memo.hash(big)) for _ in range(5))
    return {"hash_1GB_GBps": 1.0737 / best, "memo_rehash_s": rerun}


def bench_store_overhead(tmp: Path, stages: int = 40) -> dict:
    import msflow

    proj = tmp / "overhead"
    shutil.copytree(NUMPROJECT, proj, ignore=shutil.ignore_patterns(".msflow", "*.lock", "__pycache__"))
    body = "".join(f"  s{i}:\n    uses: numstages.basic:Source\n    params: {{n: {i + 3}}}\n" for i in range(stages))
    (proj / "many.yaml").write_text("version: 1\nstages:\n" + body)
    msflow.run(proj / "many.yaml", overrides=["s0.n=2"])  # warm imports (numpy, zarr, stage module)
    shutil.rmtree(proj / ".msflow")
    started = time.perf_counter()
    result = msflow.run(proj / "many.yaml")
    wall = time.perf_counter() - started
    return {"stages": stages, "wall_s": wall, "per_stage_ms": 1000 * wall / stages, "executed": len(result.executed)}


def _timed(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        print("no-op run / status (10 stages):", bench_noop(tmp, args.repeats))
        print("store overhead:", bench_store_overhead(tmp))
        if not args.quick:
            print("hashing:", bench_hashing(tmp))


if __name__ == "__main__":
    main()
