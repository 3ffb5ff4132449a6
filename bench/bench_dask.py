"""Dask cluster figures (issue 17): the default pipeline on two workers that cannot read the project folder.

    python bench/bench_dask.py [--repeats 3] [--parts default,cli,overhead,floor,malloc,idle] [--s3-server moto]

The cluster is the stand-in of tests/test_dask.py: a ``dask scheduler`` and two ``dask worker`` processes (one
thread each, ``--preload-nanny msflow.dask_setup``) started in their own folder, in a mount namespace that hides
the project copies and this checkout, as ``nobody`` when run as root. Two stores the workers can reach:

- ``s3``: moto's S3 on loopback, in its own process (its CPU is counted apart: a real S3 costs no local CPU), served
  alone (bench/moto_s3.py; ``--s3-server moto``: ``python -m moto.server``, whose dispatcher for all of AWS costs
  about 1.4 ms of CPU more per request on the same 2 cores);
- ``folder``: a store folder outside the project (what a shared file system gives a real cluster).

1. The default pipeline from an empty store, interleaved ``--repeats`` times: local ``-j 2`` (``LocalExecutor``: the
   stages in the run's own process, here this script's, but the second tracking stage, in one worker process; store
   in the project), cluster with the S3 store, cluster with the folder store. Wall time; CPU (user+sys) of the
   client, the workers, the scheduler, the moto server; the stages' own CPU (sum of ``cpu_seconds``); and whether
   every output hash equals the local run's (the edit's preview MP4 differs between two local runs too: x264
   threads without frame timestamps, stages/face/edit.py).
   ``cli``: the same three as a user runs them, ``msflow run`` in a fresh process each time (what every run pays
   to start: interpreter, imports, the store client, the Dask connection, a local worker process).
2. Per-stage overhead: chains of 40 and 80 trivial stages (each reads the previous one's array) from an empty
   store, so every stage waits for the one before. What one more stage costs, (wall(80) - wall(40)) / 40, is the
   full round trip of one stage (client scheduling, shipping, scheduler, worker, store, outcome) besides the stage
   itself (~0.1 ms of numpy), without the run's fixed costs (planning, the first request to a store, connecting
   to the cluster); also the end-to-end wall per stage and the worker-side part
   (``seconds - compute_seconds`` in the run record). ``local -j 1, S3`` runs the chain in this
   process against the same S3 server: the store's own share of the cluster's S3 figure. ``local -j 2`` twice: the
   chain's stages as they are (they say neither ``in_process`` nor ``cheap``: one worker process runs them) and
   subclassed with ``in_process = True`` (msflow's own process runs them in a thread, as it runs the default
   pipeline's). ``floor``: Dask's own
   round trip on the same cluster, a chain of tasks that do nothing.

3. The nanny's ``MALLOC_TRIM_THRESHOLD_``: the default pipeline on a 2-worker LocalCluster with the variable set
   and nothing undoing it, with Dask's default undone in each worker by ``msflow.worker.tune_malloc``, and unset
   (msflow's LocalCluster and ``--preload-nanny msflow.dask_setup``), interleaved: the stages' CPU seconds. (Part 1
   gives the cluster's side: its stages' CPU against a local run's.)
4. An idle 2-worker LocalCluster's CPU with Dask's system-monitor and tick intervals and with msflow's.

The machine's load (1-minute load average, before and after each measurement) is printed with the figures: on a
shared machine only the ratios measured side by side and the CPU times mean much.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

UNSTABLE = {("edit", "video")}


def cpu_of(pids: list[int]) -> float:
    """User+system CPU seconds of these processes and all their descendants (alive now)."""
    import psutil

    total = 0.0
    for pid in pids:
        try:
            proc = psutil.Process(pid)
            for p in [proc, *proc.children(recursive=True)]:
                times = p.cpu_times()
                total += times.user + times.system
        except psutil.NoSuchProcess:
            continue
    return total


def self_cpu() -> float:
    times = os.times()
    return times.user + times.system + times.children_user + times.children_system


def start_moto(server: str = "s3-only") -> tuple[subprocess.Popen, dict]:
    """moto on a free loopback port: its S3 application alone (``s3-only``, bench/moto_s3.py) or ``python -m
    moto.server`` (``moto``: every AWS service behind moto's dispatcher, which costs CPU per request)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    command = {
        "s3-only": [str(HERE / "moto_s3.py"), str(port)],
        "moto": ["-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
    }[server]
    proc = subprocess.Popen(
        [sys.executable, *command],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    endpoint = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            break
        except OSError:
            time.sleep(0.05)
    return proc, {"endpoint_url": endpoint, "key": "bench", "secret": "bench"}


def new_bucket(options: dict) -> str:
    import uuid

    import boto3

    name = f"bench-{uuid.uuid4().hex[:10]}"
    boto3.client(
        "s3",
        endpoint_url=options["endpoint_url"],
        aws_access_key_id="bench",
        aws_secret_access_key="bench",
        region_name="us-east-1",
    ).create_bucket(Bucket=name)
    return name


def use_store(pipeline_file: Path, url: str, options: dict | None = None) -> None:
    header = f"store: {url}\n" + (f"store_options: {json.dumps(options)}\n" if options else "")
    text = pipeline_file.read_text()
    pipeline_file.write_text(text.replace("version: 1\n", "version: 1\n" + header, 1))


def copy_repo(dest: Path) -> Path:
    from conftest import copy_project

    return copy_project(dest)


def measure(label: str, run, cluster, moto) -> dict:
    """Run ``run()`` (returns a RunResult) and collect wall, CPU per party and load."""
    load = os.getloadavg()[0]
    pids = [p.pid for p in cluster.procs]
    before = (self_cpu(), cpu_of(pids), cpu_of([moto.pid]))
    started = time.perf_counter()
    result = run()
    wall = time.perf_counter() - started
    after = (self_cpu(), cpu_of(pids), cpu_of([moto.pid]))
    stages = result.record["stages"]
    return {
        "label": label,
        "wall_s": round(wall, 2),
        "cpu_client_s": round(after[0] - before[0], 2),
        "cpu_cluster_s": round(after[1] - before[1], 2),
        "cpu_moto_s": round(after[2] - before[2], 2),
        "stage_cpu_s": round(sum(s["cpu_seconds"] for s in stages.values()), 2),
        "load_before_after": [round(load, 1), round(os.getloadavg()[0], 1)],
        "record": result.record,
    }


def same_outputs(record: dict, reference: dict) -> bool:
    for name, stage in reference["stages"].items():
        ours = record["stages"][name]["outputs"]
        if {k: v for k, v in ours.items() if (name, k) not in UNSTABLE} != {
            k: v for k, v in stage["outputs"].items() if (name, k) not in UNSTABLE
        }:
            return False
    return True


def local_run(project: Path, cluster):
    import msflow

    return lambda: msflow.run(project / "pipeline.yaml", jobs=2)


def s3_run(project: Path, cluster):
    import msflow

    return lambda: msflow.run(project / "pipeline.yaml", scheduler=cluster.address, jobs=2)


folder_run = s3_run  # the store is in the pipeline file


def default_pipeline(tmp: Path, cluster, moto, options: dict, repeats: int) -> None:
    store_folder = cluster.env_dir / "store"
    rows = []
    runs = {"local -j 2": local_run, "cluster, S3": s3_run, "cluster, folder": folder_run}
    order = list(runs)
    for i in range(repeats):
        # rotate which configuration goes first: the first cluster run is the fresh cluster's first
        for label in order[i % 3 :] + order[: i % 3]:
            project = copy_repo(tmp / f"{label.replace(', ', '-').replace(' ', '')}{i}")
            if label == "cluster, S3":
                use_store(project / "pipeline.yaml", f"s3://{new_bucket(options)}/p", options)
            elif label == "cluster, folder":
                shutil.rmtree(store_folder, ignore_errors=True)
                use_store(project / "pipeline.yaml", str(store_folder))
            rows.append(measure(label, runs[label](project, cluster), cluster, moto))
            rows[-1]["repeat"] = i
        mine = rows[-3:]
        reference = next(r for r in mine if r["label"] == "local -j 2")["record"]
        for row in mine:
            if row["label"] != "local -j 2":
                row["identical_outputs"] = same_outputs(row["record"], reference)
            print(json.dumps({k: v for k, v in row.items() if k != "record"}), flush=True)
    print("\ndefault pipeline, medians over", repeats, "interleaved repeats:")
    for label in ("local -j 2", "cluster, S3", "cluster, folder"):
        mine = [r for r in rows if r["label"] == label]
        med = {k: statistics.median(r[k] for r in mine) for k in ("wall_s", "cpu_client_s", "cpu_cluster_s")}
        stage_cpu = statistics.median(r["stage_cpu_s"] for r in mine)
        print(
            f"  {label:16s} wall {med['wall_s']:6.1f} s (all: {[r['wall_s'] for r in mine]}), "
            f"stage CPU {stage_cpu:5.1f} s, CPU client {med['cpu_client_s']:5.1f} s + cluster "
            f"{med['cpu_cluster_s']:5.1f} s, identical outputs {[r.get('identical_outputs', True) for r in mine]}"
        )
    for label in ("cluster, S3", "cluster, folder"):
        ratios = []
        for i in range(repeats):
            wall = {r["label"]: r["wall_s"] for r in rows if r["repeat"] == i}
            ratios.append(round(wall[label] / wall["local -j 2"], 2))
        print(f"  wall {label} / local -j 2, per repeat (repeat 0: the fresh cluster's first run): {ratios}")
    print_stage_table(rows)


def cli_runs(tmp: Path, cluster, options: dict, repeats: int) -> None:
    """The default pipeline as a user runs it: ``msflow run`` in a fresh process each time (interpreter, imports,
    the store client and the Dask connection paid by every run; bytecode caches allowed, as users have them),
    local ``-j 2`` vs ``--scheduler`` with the S3 and the folder store, interleaved, the order rotated."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    labels = ["local -j 2", "cluster, S3", "cluster, folder"]
    walls: dict[str, list[float]] = {label: [] for label in labels}
    for i in range(repeats):
        for label in labels[i % 3 :] + labels[: i % 3]:
            project = copy_repo(tmp / f"cli-{label.replace(', ', '-').replace(' ', '')}{i}")
            command = [sys.executable, "-m", "msflow.cli", "run", "pipeline.yaml", "-q"]
            if label == "cluster, S3":
                use_store(project / "pipeline.yaml", f"s3://{new_bucket(options)}/p", options)
            elif label == "cluster, folder":
                shutil.rmtree(cluster.env_dir / "store", ignore_errors=True)
                use_store(project / "pipeline.yaml", str(cluster.env_dir / "store"))
            command += ["-j", "2"] if label == "local -j 2" else ["--scheduler", cluster.address]
            started = time.perf_counter()
            subprocess.run(command, cwd=project, env=env, check=True, capture_output=True)
            walls[label].append(round(time.perf_counter() - started, 2))
        ratios = {label: round(walls[label][-1] / walls["local -j 2"][-1], 2) for label in labels[1:]}
        print(json.dumps({"repeat": i, "wall_s": {k: v[-1] for k, v in walls.items()}, "ratio": ratios}), flush=True)
    print(f"\ndefault pipeline through the CLI, {repeats} interleaved repeats (load {os.getloadavg()[0]:.1f}):")
    for label in labels[1:]:
        ratios = [round(c / local, 2) for c, local in zip(walls[label], walls["local -j 2"])]
        print(f"  {label} / local -j 2: {ratios} (median {statistics.median(ratios)})")


def print_stage_table(rows: list[dict]) -> None:
    """Per stage: CPU seconds in the stage's run, local vs on the workers (medians)."""
    names = list(rows[0]["record"]["stages"])
    print("\n  stage CPU seconds (median): local -j 2 | cluster S3 | cluster folder")
    for name in names:
        cells = []
        for label in ("local -j 2", "cluster, S3", "cluster, folder"):
            values = [r["record"]["stages"][name]["cpu_seconds"] for r in rows if r["label"] == label]
            cells.append(f"{statistics.median(values):6.2f}")
        print(f"  {name:14s} " + " | ".join(cells))


#: the chain's stages marked to run in msflow's own process under -j N (docs/framework.md, "Where -j N runs a stage")
MARKED_STAGES = """from numstages.basic import Source as _Source
from numstages.scaling import Scale as _Scale


class Source(_Source):
    in_process = True


class Scale(_Scale):
    in_process = True
"""


def chain_pipeline(folder: Path, n: int, marked: bool = False) -> Path:
    """``s0`` (a Source) then ``s1 .. s{n-1}``, each scaling the previous output (distinct factors: distinct keys);
    ``marked``: the same stages with ``in_process = True``."""
    shutil.copytree(ROOT / "tests" / "numproject", folder, ignore=shutil.ignore_patterns(".msflow", "*.lock"))
    source_uses, scale_uses = "numstages.basic:Source", "numstages.scaling:Scale"
    if marked:
        (folder / "numstages" / "marked.py").write_text(MARKED_STAGES)
        source_uses, scale_uses = "numstages.marked:Source", "numstages.marked:Scale"
    body = f"  s0:\n    uses: {source_uses}\n    params: {{n: 1000}}\n"
    for i in range(1, n):
        source = "s0.x" if i == 1 else f"s{i - 1}.y"
        body += f"  s{i}:\n    uses: {scale_uses}\n    inputs: {{x: {source}}}\n"
        body += f"    params: {{factor: {1 + i / 1000}}}\n"
    (folder / "chain.yaml").write_text("version: 1\nstages:\n" + body)
    return folder / "chain.yaml"


def overhead(tmp: Path, cluster, moto, options: dict, n: int = 40) -> None:
    """Per-stage overhead as the marginal cost of a stage: chains of ``n`` and ``2 n`` trivial stages, run in
    turn; (wall(2n) - wall(n)) / n is what one more stage costs, without the run's fixed costs (planning, the
    first request to a store, connecting), which the intercept shows."""
    import msflow

    print(f"\nper-stage overhead: chains of {n} and {2 * n} trivial stages (each waits for the previous one):")
    configs = {
        "local -j 1 (in process)": ({}, None),
        "local -j 1, S3": ({}, "s3"),  # the store's own part of the cluster's S3 figure
        "local -j 2 (a worker)": ({"jobs": 2}, None),  # the chain's stages say neither in_process nor cheap
        "local -j 2 (msflow's process)": ({"jobs": 2}, "marked"),  # the same marked in_process
        "cluster, S3": ({"scheduler": cluster.address}, "s3"),
        "cluster, folder": ({"scheduler": cluster.address}, "folder"),
    }
    for index, (label, (kwargs, store)) in enumerate(configs.items()):
        walls: dict[int, list[float]] = {n: [], 2 * n: []}
        worker_side, cpus = [], []
        for attempt in range(5):
            for length in (n, 2 * n):
                pipeline = chain_pipeline(tmp / f"chain-{index}-{attempt}-{length}", length, store == "marked")
                if store == "s3":
                    use_store(pipeline, f"s3://{new_bucket(options)}/c", options)
                elif store == "folder":
                    shutil.rmtree(cluster.env_dir / "chainstore", ignore_errors=True)
                    use_store(pipeline, str(cluster.env_dir / "chainstore"))
                pids = [p.pid for p in cluster.procs]
                cpu = (self_cpu(), cpu_of(pids), cpu_of([moto.pid]))
                started = time.perf_counter()
                result = msflow.run(pipeline, **kwargs)
                walls[length].append(time.perf_counter() - started)
                after = (self_cpu(), cpu_of(pids), cpu_of([moto.pid]))
                cpus.append((length, tuple(b - a for a, b in zip(cpu, after))))
                stages = [s for s in result.record["stages"].values() if s["state"] == "ran"]
                assert len(stages) == length, "every stage of the chain must run"
                worker_side.append(statistics.median((s["seconds"] - s["compute_seconds"]) * 1000 for s in stages))
        slopes = [(b - a) / n * 1000 for a, b in zip(walls[n], walls[2 * n])]
        short = [c for length, c in cpus if length == n]
        long = [c for length, c in cpus if length == 2 * n]
        cpu_slope = [
            (statistics.median(x[k] for x in long) - statistics.median(x[k] for x in short)) / n * 1000
            for k in range(3)
        ]
        intercept = statistics.median(walls[n]) - statistics.median(slopes) * n / 1000
        print(
            f"  {label:26s} {statistics.median(slopes):6.1f} ms per added stage (median of 5; all "
            f"{[round(w, 1) for w in slopes]}), fixed {intercept:5.2f} s per run; end to end "
            f"{min(walls[n]) / n * 1000:.1f} ms per stage for {n}, {min(walls[2 * n]) / (2 * n) * 1000:.1f} for "
            f"{2 * n} (best of 5); worker side {min(worker_side):5.1f} ms; CPU per added stage: "
            f"{' + '.join(f'{v:.1f}' for v in cpu_slope)} ms (client + cluster + moto); load {os.getloadavg()[0]:.1f}",
            flush=True,
        )


def dask_round_trip(cluster, tasks: int = 200) -> None:
    """Dask's own floor: a task that does nothing (its argument as big as a shipped job, ~800 bytes), submitted
    when the one before has come back, as msflow submits a chain's stages; per task: wall and the CPU of this
    process (the client) and of the cluster's processes. Twice: with Dask's client as it comes (its messages
    batched 10 ms apart) and as msflow's executor sets it up (each sent as made: ``send_without_delay``)."""
    from msflow.dask_executor import send_without_delay

    def noop(job: str) -> str:
        return job

    pids = [p.pid for p in cluster.procs]
    stream = cluster.client.scheduler_comm
    for label, at_once in (("as it comes", False), ("as msflow sets it up", True)):
        batching = stream.interval
        if at_once:
            send_without_delay(cluster.client)
        for _ in range(20):  # warm: the function's pickle reaches every worker
            cluster.client.submit(noop, "x", pure=False).result()
        cpu = (self_cpu(), cpu_of(pids))
        started = time.perf_counter()
        for _ in range(tasks):
            cluster.client.submit(noop, "x" * 800, pure=False).result()
        wall = (time.perf_counter() - started) / tasks * 1000
        client, workers = ((b - a) / tasks * 1000 for a, b in zip(cpu, (self_cpu(), cpu_of(pids))))
        stream.interval = batching
        print(
            f"  Dask alone, a task that does nothing, client {label}: {wall:.1f} ms per task ({tasks} in a row), "
            f"CPU {client:.1f} (client) + {workers:.1f} (cluster) ms; load {os.getloadavg()[0]:.1f}",
            flush=True,
        )


def malloc_trim(tmp: Path, repeats: int) -> None:
    """Stage CPU on LocalCluster workers spawned with and without the nanny's malloc-trim default."""
    import msflow
    import msflow.dask_executor as dask_executor

    ours = dict(dask_executor.WORKER_CONFIG)
    key = "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_"
    variants = {
        # 65537: the nanny's setting in effect, but not the value msflow.worker.tune_malloc undoes
        "set, no safety net": {**ours, key: 65537},
        "nanny default + tune_malloc": {k: v for k, v in ours.items() if k != key},
        "msflow (unset)": ours,
    }
    cpu: dict[str, list[dict]] = {label: [] for label in variants}
    for i in range(repeats):
        for v, (label, config) in enumerate(variants.items()):
            # a LocalCluster's nannies live in this process and write their pre-spawn variables into its
            # environment (distributed.nanny), where every later nanny picks them up: start each variant clean
            os.environ.pop("MALLOC_TRIM_THRESHOLD_", None)
            dask_executor.WORKER_CONFIG = config
            project = copy_repo(tmp / f"malloc-{i}-{v}")
            result = msflow.run(project / "pipeline.yaml", executor="dask", jobs=2)
            cpu[label].append({n: s["cpu_seconds"] for n, s in result.record["stages"].items()})
    dask_executor.WORKER_CONFIG = ours
    print(f"\nstage CPU seconds on a 2-worker LocalCluster (median of {repeats}), load {os.getloadavg()[0]:.1f}:")
    for label, runs in cpu.items():
        total = statistics.median(sum(r.values()) for r in runs)
        top = {n: round(statistics.median(r[n] for r in runs), 2) for n in ("track_train", "keymorphs", "export")}
        print(f"  {label:24s} all stages {total:5.2f} s; {top}")


def idle_cpu(others: list[int], seconds: float = 10.0, repeats: int = 2) -> None:
    """CPU of an idle 2-worker LocalCluster (this process and its children but ``others``, the stand-in cluster
    and moto, and theirs): Dask's monitors at their defaults and as msflow sets them
    (``msflow.dask_executor.WORKER_CONFIG``)."""
    import psutil

    import msflow.dask_executor as dask_executor

    def cpu() -> float:
        me = psutil.Process()
        skip = set(others)
        for pid in others:
            skip |= {c.pid for c in psutil.Process(pid).children(recursive=True)}
        procs = [me, *(c for c in me.children(recursive=True) if c.pid not in skip)]
        return sum(t.user + t.system for t in (p.cpu_times() for p in procs))

    ours = dict(dask_executor.WORKER_CONFIG)
    monitors = ("distributed.admin.system-monitor.interval", "distributed.admin.tick.interval")
    variants = {"Dask's monitor intervals": {k: v for k, v in ours.items() if k not in monitors}, "msflow's": ours}
    found: dict[str, list[float]] = {label: [] for label in variants}
    for _ in range(repeats):
        for label, config in variants.items():
            dask_executor.WORKER_CONFIG = config
            executor = dask_executor.DaskExecutor(jobs=2)
            executor.client.run(lambda: None)
            time.sleep(2)  # start-up done
            before = cpu()
            time.sleep(seconds)
            found[label].append((cpu() - before) / seconds)
            executor.shutdown()
    dask_executor.WORKER_CONFIG = ours
    print(f"\nidle 2-worker LocalCluster, cores busy (median of {repeats}), load {os.getloadavg()[0]:.1f}:")
    for label, values in found.items():
        print(f"  {label:26s} {statistics.median(values):.3f}")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--parts", default="default,cli,overhead,floor,malloc,idle")
    parser.add_argument("--s3-server", choices=["s3-only", "moto"], default="s3-only")
    args = parser.parse_args()
    import logging

    logging.getLogger("distributed").setLevel(logging.ERROR)
    from test_dask import IsolatedCluster

    os.umask(0)  # the folder stores are shared with the workers' user (nobody)
    moto, options = start_moto(args.s3_server)
    os.environ["AWS_EC2_METADATA_DISABLED"] = "true"
    with tempfile.TemporaryDirectory(prefix="msflow-bench-dask-") as tmp_name:
        tmp = Path(tmp_name)
        tmp.chmod(0o700)
        cluster = IsolatedCluster(hidden=[tmp], extra_env={})
        try:
            print(f"cluster {cluster.address}: 2 workers as uid {set(cluster.client.run(os.getuid).values())}")
            print(f"load average (1, 5, 15 min): {os.getloadavg()}, {os.cpu_count()} CPUs", flush=True)
            parts = args.parts.split(",")
            if "default" in parts:
                default_pipeline(tmp, cluster, moto, options, args.repeats)
            if "cli" in parts:
                cli_runs(tmp, cluster, options, args.repeats)
            if "overhead" in parts:
                overhead(tmp, cluster, moto, options)
            if "floor" in parts:
                dask_round_trip(cluster)
            if "malloc" in parts:
                malloc_trim(tmp, args.repeats)
            if "idle" in parts:
                idle_cpu([p.pid for p in cluster.procs] + [moto.pid])
        finally:
            cluster.close()
            moto.terminate()
            moto.wait()


if __name__ == "__main__":
    main()
