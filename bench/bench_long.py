"""Long takes end to end: the default pipeline with its test take replaced by 2 s, 1 min and 10 min takes.

    python bench/bench_long.py [--lengths 2s,1min,10min] [-j 2] [--out bench/out/long]

The takes are built at run time from the embedded CREMA-D sad clip (480x360, 29.97 fps), repeated back to back
with its own sound cut to the picture, and encoded as H.264 + AAC MP4 under ``--out`` (nothing large is committed;
a take already built is reused). For each length a pipeline file is generated next to them: ``pipeline.yaml``
with ``track_test`` reading the long take, its own store under ``--out``, no ``publish:``. A first, untimed run
of the default take fills that store with the training branch (track_train, aam, bilinear, character, headdb,
...), so every timed run computes exactly the stages that depend on the test take.

Each timed run is ``python -m msflow.cli run <generated pipeline> -j N`` in a subprocess; printed per length:
the wall seconds of the tracking (track_test), edit and export stages from the run record, the whole run's wall
time and CPU time (user + sys of msflow and all its workers), and the peak resident memory of the run: the sum
over msflow and its worker processes, sampled every 0.1 s with psutil.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from fractions import Fraction
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SOURCE = ROOT / "data" / "crema-d" / "1001_DFA_SAD_XX.flv"
LENGTHS = {"2s": 1, "1min": 30, "10min": 300}  # repetitions of the 2.0 s clip


def build_take(path: Path, repeat: int) -> Path:
    """The sad clip ``repeat`` times over: H.264 (CRF 18) and AAC, 29.97 fps, sound cut to each repetition."""
    import av
    import numpy as np

    from stages.formats.audio import decode_audio
    from stages.tracking.video import probe_video, read_frames

    if path.exists():
        return path
    info = probe_video(SOURCE)
    _, frames = read_frames(SOURCE)
    rate = 44100
    audio = decode_audio(SOURCE, rate)
    start = int(round(-audio.offset_to_video * rate))  # the audio sample at the first frame
    length = int(round(len(frames) / info.fps * rate))
    clip_audio = np.zeros(length, np.float32)
    piece = audio.samples[start : start + length]
    clip_audio[: len(piece)] = piece
    tmp = path.with_suffix(".tmp.mp4")
    with av.open(str(tmp), "w") as out:
        video = out.add_stream("libx264", rate=Fraction(30000, 1001))
        video.width, video.height, video.pix_fmt = info.width, info.height, "yuv420p"
        video.options = {"preset": "veryfast", "crf": "18"}
        sound = out.add_stream("aac", rate=rate)
        sound.layout = "mono"
        for _ in range(repeat):
            for frame in frames:
                for packet in video.encode(av.VideoFrame.from_ndarray(frame, format="bgr24")):
                    out.mux(packet)
        for packet in video.encode():
            out.mux(packet)
        whole = np.tile(clip_audio, repeat)
        for k in range(0, len(whole), 1024):
            chunk = av.AudioFrame.from_ndarray(whole[None, k : k + 1024], format="flt", layout="mono")
            chunk.sample_rate, chunk.pts = rate, k
            for packet in sound.encode(chunk):
                out.mux(packet)
        for packet in sound.encode():
            out.mux(packet)
    tmp.replace(path)
    return path


def pipeline_for(take: Path, out: Path, name: str) -> Path:
    """pipeline.yaml with the test take replaced, its own store, absolute data paths, nothing published."""
    import yaml

    spec = yaml.safe_load((ROOT / "pipeline.yaml").read_text())
    spec["vars"]["clips"] = str(ROOT / "data" / "crema-d")
    spec["store"] = str(out / "store")
    spec["stages"]["track_test"]["inputs"]["videos"] = {"sad": str(take)}
    for stage in spec["stages"].values():
        for key, ref in list(stage.get("inputs", {}).items()):
            if isinstance(ref, dict) and set(ref) == {"path"} and not Path(ref["path"]).is_absolute():
                stage["inputs"][key] = {"path": str(ROOT / ref["path"])}
    spec.pop("publish", None)
    path = out / f"pipeline_{name}.yaml"
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return path


def tree_rss(proc) -> int:
    """Resident bytes of a process and all its descendants."""
    import psutil

    total = 0
    try:
        procs = [proc] + proc.children(recursive=True)
    except psutil.NoSuchProcess:
        return 0
    for p in procs:
        try:
            total += p.memory_info().rss
        except psutil.NoSuchProcess:
            pass
    return total


def timed_run(pipeline: Path, jobs: int) -> dict:
    """Run the pipeline in a subprocess: wall and CPU seconds (with workers), peak tree RSS, the run record."""
    import psutil

    env = dict(os.environ, PYTHONPATH=str(ROOT))
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-m", "msflow.cli", "run", str(pipeline), "-j", str(jobs)],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    watched, peak = psutil.Process(proc.pid), 0
    while proc.poll() is None:
        peak = max(peak, tree_rss(watched))
        time.sleep(0.1)
    wall = time.perf_counter() - started
    output = proc.stdout.read()
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"run of {pipeline} failed ({proc.returncode}):\n{output}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"wall": wall, "cpu": cpu, "peak_rss": peak, "record": latest_record(pipeline), "output": output}


def latest_record(pipeline: Path) -> dict:
    import yaml

    store = Path(yaml.safe_load(pipeline.read_text())["store"])
    records = sorted((store / "runs").glob("*.json"), key=lambda p: p.stat().st_mtime)
    return json.loads(records[-1].read_text())


def stage_seconds(record: dict, *names: str) -> float:
    return sum(record["stages"][n]["seconds"] for n in names if record["stages"][n]["state"] == "ran")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lengths", default="2s,1min", help="comma list of " + ", ".join(LENGTHS))
    ap.add_argument("-j", "--jobs", type=int, default=2)
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "out" / "long")
    args = ap.parse_args()
    args.out = args.out.resolve()
    (args.out / "takes").mkdir(parents=True, exist_ok=True)
    warm = pipeline_for(SOURCE, args.out, "warmup")
    print(f"warm-up run (training branch into {args.out / 'store'}) ...", flush=True)
    timed_run(warm, args.jobs)
    rows = []
    for name in args.lengths.split(","):
        take = build_take(args.out / "takes" / f"sad_{name}.mp4", LENGTHS[name])
        run = timed_run(pipeline_for(take, args.out, name), args.jobs)
        record = run["record"]
        frames = LENGTHS[name] * 60
        rows.append(
            (
                name,
                frames,
                stage_seconds(record, "track_test"),
                stage_seconds(record, "edit"),
                stage_seconds(record, "export"),
                run["wall"],
                run["cpu"],
                run["peak_rss"] / 1e9,
            )
        )
        print(f"{name}: {run['wall']:.1f} s wall, ran {record['counts']['ran']} stages", flush=True)
    print(f"\n-j {args.jobs}, {os.cpu_count()} CPUs; stage times are wall seconds from the run record")
    print("| take | frames | tracking | edit | export | whole run, wall | whole run, CPU | peak RSS |")
    print("|---|---|---|---|---|---|---|---|")
    for name, frames, track, edit, export, wall, cpu, rss in rows:
        print(
            f"| {name} | {frames} | {track:.1f} s | {edit:.1f} s | {export:.1f} s | {wall:.1f} s | {cpu:.1f} s "
            f"| {rss:.2f} GB |"
        )


if __name__ == "__main__":
    main()
