"""msflow core performance figures (issues 2 and 15).

    python bench/bench_core.py            # all msflow figures
    python bench/bench_core.py --quick    # skip the 1 GB hashing figure
    python bench/bench_core.py --quick --compare /tmp/benchenv/bin --sizes 10,500,1000 --rounds 3
                                          # + DVC and Snakemake side by side (issue 15)

1. CPU (user+sys) of a no-op ``msflow run`` and of ``msflow status`` on a 10-stage pipeline (best of N runs,
   measured through getrusage of the child process), fast path and full path.
2. Hashing a 1 GB data file from the page cache (GB/s; goal >= 3) and a rerun with the file unchanged (no reread).
3. Store overhead per executed stage for small outputs (open, write, publish, record; goal <= 20 ms).
4. A 2 GB data file: a second process (``msflow status``, full path) does not reread it (CPU and page faults,
   against the same process without the memo).
5. Corruption probes (flipped byte, deleted chunk, truncated manifest, emptied folder) x (run, show, export): caught,
   repaired by run, no traceback.
6. Checksum cost: crc32c time as a share of writing and of reading a 100 MB artifact.
7. --compare BIN: no-op and status CPU of msflow, DVC and Snakemake on the same DAGs (10 and 1000 stages), in
   interleaved rounds (median); BIN holds the dvc and snakemake executables (a separate venv: nothing of theirs
   is a dependency of msflow).
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


def child_cpu(cmd: list[str], cwd: Path, repeats: int, env: dict | None = None) -> float:
    """Best CPU time (user + sys) of ``repeats`` runs of ``cmd`` (the machine is shared: best is least disturbed)."""
    return min(child_usage(cmd, cwd, env)[0] for _ in range(repeats))


def child_usage(cmd: list[str], cwd: Path, env: dict | None = None, check: bool = True) -> tuple[float, float, int]:
    """(CPU seconds, wall seconds, minor + major page faults) of one run of ``cmd``."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    subprocess.run(
        cmd,
        cwd=cwd,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        check=check,
        env={**os.environ, **(env or {})},
    )
    wall = time.perf_counter() - started
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime
    faults = after.ru_minflt - before.ru_minflt + after.ru_majflt - before.ru_majflt
    return cpu, wall, faults


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
    full = {"MSFLOW_FASTPATH": "0"}
    noop_full = child_cpu(msflow + ["run", "ten.yaml", "-q"], proj, repeats, env=full)
    status_full = child_cpu(msflow + ["status", "ten.yaml"], proj, repeats, env=full)
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
        "noop_run_full_path_cpu_s": noop_full,
        "status_full_path_cpu_s": status_full,
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
    started, cpu = time.perf_counter(), time.process_time()
    result = msflow.run(proj / "many.yaml")
    wall, cpu = time.perf_counter() - started, time.process_time() - cpu
    return {
        "stages": stages,
        "wall_s": wall,
        "per_stage_ms": 1000 * wall / stages,
        "per_stage_cpu_ms": 1000 * cpu / stages,  # the figure to trust on a loaded machine
        "executed": len(result.executed),
    }


def _timed(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


# ---------------------------------------------------------------------------------------------------------- issue 15
def bench_big_input(tmp: Path, gigabytes: int = 2) -> dict:
    """A second process must not reread an unchanged large input: its CPU and page faults with the memo saved by
    the first process, against the same command after the memo is deleted (which rehashes the file)."""
    proj = tmp / "bigin"
    shutil.copytree(NUMPROJECT, proj, ignore=shutil.ignore_patterns(".msflow", "*.lock", "__pycache__"))
    big = proj / "data" / "big.bin"
    block = os.urandom(1 << 24)
    with open(big, "wb") as fh:
        for _ in range(gigabytes * 64):
            fh.write(block)
    (proj / "big.yaml").write_text(
        "version: 1\nstages:\n  takes:\n    uses: numstages.basic:Takes\n    inputs: {takes: {path: data/big.bin}}\n"
    )
    msflow = [sys.executable, "-m", "msflow.cli"]
    full = {"MSFLOW_FASTPATH": "0"}
    first = child_usage(msflow + ["run", "big.yaml", "-q"], proj, full)
    second = child_usage(msflow + ["status", "big.yaml"], proj, full)
    second_read = bytes_hashed_by(["status", "big.yaml"], proj, full)
    (proj / ".msflow" / "cache" / "memo.json").unlink()
    without_memo = child_usage(msflow + ["status", "big.yaml"], proj, full)
    (proj / ".msflow" / "cache" / "memo.json").unlink()
    without_memo_read = bytes_hashed_by(["status", "big.yaml"], proj, full)
    big.unlink()
    return {
        "input_GB": gigabytes,
        "first_run": {"cpu_s": first[0], "faults": first[2]},
        "second_process_status": {"cpu_s": second[0], "faults": second[2], "MB_hashed": second_read / 1e6},
        "same_without_memo": {
            "cpu_s": without_memo[0],
            "faults": without_memo[2],
            "MB_hashed": without_memo_read / 1e6,
        },
    }


def bytes_hashed_by(args: list[str], cwd: Path, env: dict) -> int:
    """Bytes of data files the msflow command hashed (it hashes through mmap, so read() counters miss them)."""
    code = (
        "import os, sys; import msflow.hashing as h; real = h.file_hash; n = [0]\n"
        "def counted(path):\n    n[0] += os.path.getsize(path)\n    return real(path)\n"
        "h.file_hash = counted\nfrom msflow.cli import main\nmain(sys.argv[1:])\nprint(n[0], file=sys.stderr)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code, *args], cwd=cwd, env={**os.environ, **env}, capture_output=True, text=True
    )
    return int(out.stderr.strip().splitlines()[-1])


def bench_corruption(tmp: Path) -> dict:
    """Each probe x (run, show, export) in separate processes: caught (exit 1 naming the artifact for show and
    export; repaired with a warning by run), tracebacks counted."""
    import yaml

    msflow = [sys.executable, "-m", "msflow.cli"]
    caught, total, tracebacks, repaired = 0, 0, 0, 0
    for probe in ("flip_byte", "delete_chunk", "truncate_manifest", "empty_folder"):
        proj = tmp / f"probe-{probe}"
        shutil.copytree(NUMPROJECT, proj, ignore=shutil.ignore_patterns(".msflow", "*.lock", "__pycache__"))
        subprocess.run(msflow + ["run", "-q"], cwd=proj, check=True)
        key = yaml.safe_load((proj / "pipeline.lock").read_text())["stages"]["src"]["key"]
        folder = proj / ".msflow" / "artifacts" / key[:2] / key
        damage(folder, probe)
        for args, ok_code in ((["show", "src.x"], 1), (["export", "src.x", str(tmp / "x.npy")], 1)):
            out = subprocess.run(msflow + args, cwd=proj, capture_output=True, text=True)
            total += 1
            caught += out.returncode == ok_code and key in out.stderr
            tracebacks += "Traceback" in out.stderr
        out = subprocess.run(msflow + ["run", "-q", "-S", "scaled.factor=5"], cwd=proj, capture_output=True, text=True)
        total += 1
        caught += out.returncode == 0 and "was corrupt" in out.stderr
        tracebacks += "Traceback" in out.stderr
        verify = subprocess.run(msflow + ["verify"], cwd=proj, capture_output=True, text=True)
        repaired += verify.returncode == 0
    return {"caught": f"{caught}/{total}", "repaired_by_run": f"{repaired}/4", "tracebacks": tracebacks}


def damage(folder: Path, probe: str) -> None:
    chunk = folder / "x" / "c" / "0"
    if probe == "flip_byte":
        data = bytearray(chunk.read_bytes())
        data[len(data) // 2] ^= 0x40
        chunk.write_bytes(bytes(data))
    elif probe == "delete_chunk":
        chunk.unlink()
    elif probe == "truncate_manifest":
        (folder / "zarr.json").write_bytes((folder / "zarr.json").read_bytes()[:40])
    else:
        for entry in folder.iterdir():
            shutil.rmtree(entry) if entry.is_dir() else entry.unlink()


def bench_checksum(tmp: Path, megabytes: int = 100, repeats: int = 3) -> dict:
    """crc32c's share of writing and of reading a 100 MB artifact (float32 frames of smooth, compressible data)."""
    import google_crc32c
    import numpy as np

    from msflow.artifact import read_artifact, write_artifact

    frames = megabytes * (1 << 20) // (468 * 3 * 4)
    t = np.linspace(0, 60, frames, dtype=np.float32)[:, None, None]
    data = (np.sin(t + np.arange(468 * 3, dtype=np.float32).reshape(1, 468, 3)) * 100).astype(np.float32)
    write_s, read_s = [], []
    for i in range(repeats):
        started = time.perf_counter()
        write_artifact(tmp / f"ck{i}", {"mesh": data}, {})
        write_s.append(time.perf_counter() - started)
        started = time.perf_counter()
        read_artifact(tmp / f"ck{i}")["mesh"]
        read_s.append(time.perf_counter() - started)
    chunks = [p.read_bytes() for p in sorted((tmp / "ck0" / "mesh" / "c").rglob("*")) if p.is_file()]
    crc_s = min(_timed(lambda: [google_crc32c.value(c[:-4]) for c in chunks]) for _ in range(repeats))
    for i in range(repeats):
        shutil.rmtree(tmp / f"ck{i}")
    return {
        "MB": megabytes,
        "write_s": min(write_s),
        "read_s": min(read_s),
        "crc_s": crc_s,
        "crc_share_of_write": crc_s / min(write_s),
        "crc_share_of_read": crc_s / min(read_s),
    }


# ---------------------------------------------------------------------------------------------------------- vs DVC, Snakemake
def dag_projects(tmp: Path, stages: int) -> dict[str, Path]:
    """The same DAG for the three tools: chains of 10 stages, each stage copying its predecessor's output."""
    chains = stages // 10
    ms = tmp / f"msflow-{stages}"
    shutil.copytree(NUMPROJECT, ms, ignore=shutil.ignore_patterns(".msflow", "*.lock", "__pycache__"))
    body = []
    for c in range(chains):
        body.append(f"  c{c}s0:\n    uses: numstages.basic:Source\n    params: {{n: {c % 7 + 3}}}\n")
        for k in range(1, 10):
            src = f"c{c}s{k - 1}.x" if k == 1 else f"c{c}s{k - 1}.y"
            body.append(f"  c{c}s{k}:\n    uses: numstages.scaling:Scale\n    inputs: {{x: {src}}}\n")
    (ms / "dag.yaml").write_text("version: 1\nstages:\n" + "".join(body))
    dvc = tmp / f"dvc-{stages}"
    dvc.mkdir()
    (dvc / "src.txt").write_text("1\n")
    lines = ["stages:"]
    for c in range(chains):
        for k in range(10):
            dep = "src.txt" if k == 0 else f"c{c}s{k - 1}.txt"
            lines += [
                f"  c{c}s{k}:",
                f"    cmd: cp {dep} c{c}s{k}.txt",
                f"    deps: [{dep}]",
                f"    outs: [c{c}s{k}.txt]",
            ]
    (dvc / "dvc.yaml").write_text("\n".join(lines) + "\n")
    smk = tmp / f"snakemake-{stages}"
    smk.mkdir()
    (smk / "src.txt").write_text("1\n")
    targets = ", ".join(f'"c{c}s9.txt"' for c in range(chains))
    (smk / "Snakefile").write_text(
        f"rule all:\n    input: [{targets}]\n\n"
        'rule first:\n    input: "src.txt"\n    output: "c{c}s0.txt"\n    shell: "cp {input} {output}"\n\n'
        'def previous(w):\n    return f"c{w.c}s{int(w.k) - 1}.txt"\n\n'
        'rule step:\n    input: previous\n    output: "c{c}s{k,[1-9]}.txt"\n    shell: "cp {input} {output}"\n'
    )
    return {"msflow": ms, "dvc": dvc, "snakemake": smk}


def bench_compare(tmp: Path, bin_dir: Path, sizes: tuple[int, ...], rounds: int, dvc_max: int) -> dict:
    """No-op and status of the three tools on the same DAGs; DVC only up to ``dvc_max`` stages (its no-op takes
    minutes beyond: issue 15 measured 65 s at 500)."""
    import statistics

    dvc, smk = str(bin_dir / "dvc"), str(bin_dir / "snakemake")
    msflow = [sys.executable, "-m", "msflow.cli"]
    results: dict = {}
    for stages in sizes:
        projects = dag_projects(tmp, stages)
        with_dvc = stages <= dvc_max
        setup = [(msflow + ["run", "dag.yaml", "-q"], projects["msflow"]), ([smk, "-c1", "-q"], projects["snakemake"])]
        if with_dvc:
            subprocess.run([dvc, "init", "--no-scm", "-q"], cwd=projects["dvc"], check=True)
            setup.append(([dvc, "repro", "-q"], projects["dvc"]))
        for cmd, cwd in setup:
            subprocess.run(cmd, cwd=cwd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        commands = {
            "msflow run (no-op)": (msflow + ["run", "dag.yaml", "-q"], projects["msflow"], None),
            "msflow status": (msflow + ["status", "dag.yaml"], projects["msflow"], None),
            "msflow run, full path": (msflow + ["run", "dag.yaml", "-q"], projects["msflow"], {"MSFLOW_FASTPATH": "0"}),
            "msflow status, full path": (msflow + ["status", "dag.yaml"], projects["msflow"], {"MSFLOW_FASTPATH": "0"}),
            "dvc repro (no-op)": ([dvc, "repro", "-q"], projects["dvc"], None),
            "dvc status": ([dvc, "status", "-q"], projects["dvc"], None),
            "snakemake (no-op)": ([smk, "-c1", "-q"], projects["snakemake"], None),
            "snakemake -n": ([smk, "-c1", "-n", "-q"], projects["snakemake"], None),
        }
        if not with_dvc:
            commands = {k: v for k, v in commands.items() if not k.startswith("dvc")}
        samples: dict[str, list] = {name: [] for name in commands}
        for _ in range(rounds):  # interleaved: every tool sees the same machine load
            for name, (cmd, cwd, env) in commands.items():
                samples[name].append(child_usage(cmd, cwd, env, check=False)[:2])
        results[stages] = {
            name: {"cpu_s": statistics.median(c for c, _ in s), "wall_s": statistics.median(w for _, w in s)}
            for name, s in samples.items()
        }
    return results


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true", help="skip the 1 GB hashing and 2 GB input figures")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--compare", type=Path, help="folder with dvc and snakemake executables")
    parser.add_argument("--sizes", default="10,1000", help="DAG sizes for --compare")
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds for --compare")
    parser.add_argument("--dvc-max", type=int, default=500, help="largest DAG DVC runs on in --compare")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        print("no-op run / status (10 stages):", bench_noop(tmp, args.repeats))
        print("store overhead:", bench_store_overhead(tmp))
        print("corruption probes:", bench_corruption(tmp))
        print("checksum cost:", bench_checksum(tmp))
        if not args.quick:
            print("hashing:", bench_hashing(tmp))
            print("unchanged 2 GB input, second process:", bench_big_input(tmp))
        if args.compare:
            sizes = tuple(int(n) for n in args.sizes.split(","))
            for stages, rows in bench_compare(tmp, args.compare, sizes, args.rounds, args.dvc_max).items():
                print(f"\n{stages} stages (median of {args.rounds} interleaved rounds):")
                for name, figures in rows.items():
                    print(f"  {name:<26} CPU {figures['cpu_s']:7.3f} s   wall {figures['wall_s']:7.3f} s")


if __name__ == "__main__":
    main()
