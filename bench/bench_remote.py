"""Remote store figures (issue 7) against a moto S3 server on 127.0.0.1, with a local store for reference.

    python bench/bench_remote.py [--repeats 7] [--latency-ms 20] [--parts noop,overhead,chain,default]

1. No-op rerun of the 10-stage numeric pipeline (bench_core.ten_stage_pipeline): wall clock and CPU (user+sys
   of the ``msflow run`` child process), best of N; and the S3 requests it makes, by operation.
2. Per-stage overhead: 40 tiny Source stages run from an empty store in one process (wall per stage, which is
   almost all store work: lease, has, upload, commit, release), and the requests per executed stage.
3. A chain of 40 stages, each reading the previous one's output, in one process, from an empty store: wall and
   requests per stage as they are against moto, and with ``--latency-ms`` (default 20) added to every request,
   which stands in for a real S3's round trip: what a stage costs there is mostly its serial round trips.
4. ``--parts default``: the default pipeline from an empty store, in one process: its requests by operation and
   kind of object, and its wall time against moto and with ``--latency-ms`` added, with small artifacts packed
   into one object (the default) and without (``MSFLOW_STORE_PACK_MB=0``: each array's zarr.json beside its
   chunks).

moto answers on the loopback in about a millisecond; on real S3 each request costs ~10-30 ms, so the request
counts are what carries over: multiply them by the round trip of your endpoint.
"""

from __future__ import annotations

import argparse
import collections
import json
import logging
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

from bench_core import NUMPROJECT, ten_stage_pipeline  # noqa: E402


def start_moto():
    import boto3
    from moto.server import ThreadedMotoServer

    logging.getLogger("werkzeug").setLevel(logging.ERROR)
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    endpoint = f"http://{host}:{port}"
    boto3.client(
        "s3", endpoint_url=endpoint, aws_access_key_id="bench", aws_secret_access_key="bench", region_name="us-east-1"
    ).create_bucket(Bucket="bench")
    return server, {"endpoint_url": endpoint, "key": "bench", "secret": "bench"}


def use_store(pipeline_file: Path, url: str, options: dict) -> None:
    text = pipeline_file.read_text()
    header = f"store: {url}\nstore_options: {json.dumps(options)}\n"
    pipeline_file.write_text(text.replace("version: 1\n", "version: 1\n" + header, 1))


def child_run(cmd: list[str], cwd: Path) -> tuple[float, float]:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    subprocess.run(cmd, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
    wall = time.perf_counter() - started
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime


class RequestCounter:
    """Counts S3 requests made in this process (by API operation); ``latency`` seconds are added to each."""

    def __init__(self, latency: float = 0.0):
        import asyncio

        from msflow.stores.objects import S3Objects

        self.counts: collections.Counter = collections.Counter()
        self.objects: collections.Counter = collections.Counter()  # (operation, kind of object)
        self._cls = S3Objects
        self._original = S3Objects._call
        counts, objects = self.counts, self.objects
        original = self._original

        async def counted(self_, method, **kwargs):
            counts[method] += 1
            path = self_._rel(kwargs.get("Key") or kwargs.get("Prefix") or "")
            objects[(method, object_kind(path, listing=method.startswith("list")))] += 1
            if latency:
                await asyncio.sleep(latency)
            return await original(self_, method, **kwargs)

        S3Objects._call = counted

    def take(self) -> dict:
        out = dict(self.counts)
        self.counts.clear()
        self.objects.clear()
        return out

    def close(self) -> None:
        self._cls._call = self._original


def object_kind(rel: str, listing: bool = False) -> str:
    """What a store path is: the top folder of the layout (artifacts, commits, locks, pending, blobs, runs), an
    artifact's object split into zarr.json (group and array metadata) and chunks (a listing: its top folder)."""
    top = rel.split("/", 1)[0]
    if top == "artifacts" and not listing:
        return "artifacts: zarr.json" if rel.endswith("zarr.json") else "artifacts: chunks"
    return top or "(store root)"


def bench_default(tmp: Path, options: dict, latency_ms: float) -> dict:
    """The default pipeline from an empty S3 store, in one process: its requests by operation and kind of object,
    and its wall time against moto and with ``latency_ms`` added to every request (a distant S3), with small
    artifacts packed into one object (msflow.stores.packs) and without (``MSFLOW_STORE_PACK_MB=0``)."""
    from bench_dask import copy_repo

    import msflow

    out: dict = {}
    for packs in ("8", "0"):
        os.environ["MSFLOW_STORE_PACK_MB"] = packs
        for latency in (0.0, latency_ms / 1000):
            label = f"packs {'on' if packs != '0' else 'off'}, {latency * 1000:g} ms added per request"
            project = copy_repo(tmp / f"default-{packs}-{latency}")
            use_store(project / "pipeline.yaml", f"s3://bench/default-{packs}-{latency}", options)
            counter = RequestCounter(latency)
            try:
                started = time.perf_counter()
                result = msflow.run(project / "pipeline.yaml")
                wall = time.perf_counter() - started
                by_object = {f"{op} {kind}": n for (op, kind), n in counter.objects.most_common()}
                total = sum(counter.take().values())
            finally:
                counter.close()
            out[label] = {"stages": len(result.record["stages"]), "wall_s": round(wall, 2), "requests": total}
            if not latency:
                out[label]["by_object"] = by_object
    os.environ.pop("MSFLOW_STORE_PACK_MB")
    return out


def bench_noop(tmp: Path, options: dict, repeats: int) -> dict:
    import msflow

    cli = [sys.executable, "-m", "msflow.cli", "run", "ten.yaml", "-q"]
    out = {}
    for label, url in (("local", None), ("s3", "s3://bench/noop")):
        proj = tmp / f"noop-{label}"
        ten_stage_pipeline(proj)
        if url:
            use_store(proj / "ten.yaml", url, options)
        first_wall, _ = child_run(cli, proj)
        runs = [child_run(cli, proj) for _ in range(repeats)]
        out[label] = {
            "first_run_wall_s": round(first_wall, 3),
            "noop_wall_s": round(min(w for w, _ in runs), 3),
            "noop_cpu_s": round(min(c for _, c in runs), 3),
        }
        if url:
            counter = RequestCounter()
            try:
                msflow.run(proj / "ten.yaml")
                out[label]["noop_requests"] = counter.take()
            finally:
                counter.close()
    baseline = min(child_run([sys.executable, "-c", "import s3fs, botocore.session"], tmp)[1] for _ in range(3))
    out["cpu_to_import_s3fs_s"] = round(baseline, 3)
    return out


def bench_stage_overhead(tmp: Path, options: dict, stages: int = 40) -> dict:
    import msflow

    out = {}
    for label, url in (("local", None), ("s3", "s3://bench/overhead")):
        proj = tmp / f"overhead-{label}"
        shutil.copytree(NUMPROJECT, proj, ignore=shutil.ignore_patterns(".msflow", "*.lock", "__pycache__"))
        body = "".join(
            f"  s{i}:\n    uses: numstages.basic:Source\n    params: {{n: {i + 3}}}\n" for i in range(stages)
        )
        (proj / "many.yaml").write_text("version: 1\nstages:\n" + body)
        if url:
            use_store(proj / "many.yaml", url + "-warm", options)
        msflow.run(proj / "many.yaml", overrides=["s0.n=2"])  # warm imports, store connection, memo
        if url:  # measure against an empty prefix
            (proj / "many.yaml").write_text((proj / "many.yaml").read_text().replace(url + "-warm", url))
        else:
            shutil.rmtree(proj / ".msflow" / "artifacts")
        counter = RequestCounter() if url else None
        try:
            started = time.perf_counter()
            result = msflow.run(proj / "many.yaml")
            wall = time.perf_counter() - started
            requests = counter.take() if counter else None
        finally:
            if counter:
                counter.close()
        out[label] = {
            "stages": stages,
            "executed": len(result.executed),
            "wall_s": round(wall, 3),
            "per_stage_ms": round(1000 * wall / stages, 1),
        }
        if requests is not None:
            out[label]["requests_per_stage"] = {k: round(v / stages, 2) for k, v in sorted(requests.items())}
    return out


def bench_chain(tmp: Path, options: dict, latency_ms: float, stages: int = 40, repeats: int = 3) -> dict:
    from bench_dask import chain_pipeline

    import msflow

    out = {}
    for label, latency in (("moto", 0.0), (f"moto + {latency_ms:g} ms per request", latency_ms / 1000)):
        walls, requests = [], {}
        for repeat in range(repeats + 1):  # the first warms imports and the store connection
            pipeline = chain_pipeline(tmp / f"chain-{latency}-{repeat}", stages if repeat else 3)
            use_store(pipeline, f"s3://bench/chain-{latency}-{repeat}", options)
            counter = RequestCounter(latency)
            try:
                started = time.perf_counter()
                msflow.run(pipeline)
                wall = time.perf_counter() - started
                requests = counter.take()
            finally:
                counter.close()
            if repeat:
                walls.append(1000 * wall / stages)
        out[label] = {
            "per_stage_ms": round(sorted(walls)[len(walls) // 2], 1),
            "all": [round(w, 1) for w in walls],
            "requests_per_stage": round(sum(requests.values()) / stages, 2),
        }
    return out


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--latency-ms", type=float, default=20.0)
    parser.add_argument("--parts", default="noop,overhead,chain,default")
    args = parser.parse_args()
    parts = args.parts.split(",")
    os.environ.setdefault("AWS_EC2_METADATA_DISABLED", "true")
    server, options = start_moto()
    try:
        with tempfile.TemporaryDirectory() as tmp:
            tmp = Path(tmp)
            if "noop" in parts:
                print("no-op rerun, 10 stages:", json.dumps(bench_noop(tmp, options, args.repeats), indent=1))
            if "overhead" in parts:
                print("per-stage overhead:", json.dumps(bench_stage_overhead(tmp, options), indent=1))
            if "chain" in parts:
                chain = bench_chain(tmp, options, args.latency_ms)
                print("chain of 40 stages, in process:", json.dumps(chain, indent=1))
            if "default" in parts:
                default = bench_default(tmp, options, args.latency_ms)
                print("default pipeline, in process:", json.dumps(default, indent=1))
    finally:
        server.stop()


if __name__ == "__main__":
    main()
