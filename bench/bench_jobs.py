"""Cold runs with -j 1 and -j 2 side by side: does a second core help, and what does it cost?

    python bench/bench_jobs.py [--rounds 3] [--jobs 1,2] [--code DIR ...] [--cpus N] [--] [PIPELINE [-S ...]]
    python bench/bench_jobs.py -- pipelines/capture.yaml -S vars.take=/path/to/clip.mp4

Each variant (a code tree given by ``--code``, default this checkout, times a ``-j`` value) runs
``python -m msflow.cli run PIPELINE -j N -q ...`` in its own copy of the project (msflow/, stages/, data/ and the
pipeline files, copied once under ``--work``), whose store and ``out/`` are deleted before every run: nothing is
reused, as on a first run. The copies keep their bytecode caches, as users have them (one untimed run per copy
writes them; PYTHONDONTWRITEBYTECODE is unset for the runs). Variants alternate within each round, so a change of
the machine's load reaches them alike. Printed per run: wall seconds, CPU seconds (user + system of msflow and every
process it started, waited for), how many processes ran stages (the run record's ``worker`` fields) and the load
average; then per variant the median and range over the rounds. ``--code`` several times compares code trees
(e.g. a checkout of the commit before a change): ``--code /tmp/before --code .``. ``--cpus 1`` runs msflow on the
first CPU only (Linux affinity), as on a machine whose other cores are busy: what -j 2 costs when it cannot gain.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
COPIED = ("msflow", "stages", "data", "pipelines", "eval", "pipeline.yaml", "pyproject.toml")


def copy_project(code: Path, dest: Path) -> Path:
    """A copy of the code tree ``code`` (its msflow and stages) with the project's data and pipeline files."""
    if dest.exists():
        return dest
    dest.mkdir(parents=True)
    for name in COPIED:
        src = code / name if (code / name).exists() else ROOT / name
        if src.is_dir():
            shutil.copytree(src, dest / name, ignore=shutil.ignore_patterns("__pycache__", "*.lock", ".local_*"))
        else:
            shutil.copy2(src, dest / name)
    return dest


def cold_run(project: Path, args: list[str], jobs: int, cpus: int | None = None) -> dict:
    """One run from an empty store: wall and CPU seconds, the processes that ran stages."""
    for folder in (".msflow", "out"):
        shutil.rmtree(project / folder, ignore_errors=True)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env["PYTHONPATH"] = str(project)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    load = os.getloadavg()[0]
    started = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "msflow.cli", "run", *args, "-j", str(jobs), "-q"],
        cwd=project,
        env=env,
        capture_output=True,
        text=True,
        preexec_fn=(lambda: os.sched_setaffinity(0, range(cpus))) if cpus else None,
    )
    wall = time.perf_counter() - started
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"run failed in {project}:\n{proc.stderr[-3000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"wall": wall, "cpu": cpu, "load": load, "processes": len(stage_processes(project))}


def stage_processes(project: Path) -> set[str]:
    """The processes that ran the stages of the last run (its record's ``worker`` fields)."""
    records = sorted((project / ".msflow" / "runs").glob("*.json"))
    stages = json.loads(records[-1].read_text())["stages"]
    return {s["worker"] for s in stages.values() if s.get("worker")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--jobs", default="1,2", help="-j values, comma-separated")
    parser.add_argument("--code", action="append", type=Path, help="code tree(s) to compare (default: this one)")
    parser.add_argument("--cpus", type=int, help="run msflow on this many CPUs only (the first ones)")
    parser.add_argument("--work", type=Path, default=Path("/tmp/msflow-bench-jobs"), help="where the copies go")
    parser.add_argument("pipeline", nargs=argparse.REMAINDER, help="pipeline file and -S overrides")
    options = parser.parse_args()
    args = [a for a in options.pipeline if a != "--"] or ["pipeline.yaml"]
    codes = [c.resolve() for c in options.code or [ROOT]]
    jobs = [int(j) for j in options.jobs.split(",")]
    projects = {code: copy_project(code, options.work / f"code{i}") for i, code in enumerate(codes)}
    for project in projects.values():
        cold_run(project, args, 1)  # writes the copy's bytecode caches; not timed
    variants = [(code, j) for code in codes for j in jobs]
    results: dict[tuple[Path, int], list[dict]] = {v: [] for v in variants}
    cpus = options.cpus or os.cpu_count()
    print(f"cold runs of {' '.join(args)}, {options.rounds} rounds, on {cpus} of {os.cpu_count()} CPUs")
    for round_ in range(options.rounds):
        for code, j in variants if round_ % 2 == 0 else variants[::-1]:
            run = cold_run(projects[code], args, j, options.cpus)
            results[(code, j)].append(run)
            print(
                f"  round {round_ + 1} {code.name or code} -j {j}: {run['wall']:.2f} s wall, {run['cpu']:.2f} s CPU, "
                f"{run['processes']} process(es) ran stages, load {run['load']:.1f}",
                flush=True,
            )
    print("\nvariant: wall median (range), CPU median (range)")
    for (code, j), runs in results.items():
        wall = [r["wall"] for r in runs]
        cpu = [r["cpu"] for r in runs]
        print(
            f"  {code} -j {j}: {statistics.median(wall):.2f} s ({min(wall):.2f}-{max(wall):.2f}), "
            f"CPU {statistics.median(cpu):.2f} s ({min(cpu):.2f}-{max(cpu):.2f})"
        )


if __name__ == "__main__":
    main()
