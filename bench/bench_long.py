"""Long takes end to end (issue 14): the default pipeline with its test take replaced by 2 s, 1 min and 10 min takes.

    python bench/bench_long.py [--lengths 2s,1min,10min] [-j 2] [--out bench/out/long] [--until STAGE] [--per-stage]

The takes are built at run time from the embedded CREMA-D sad clip (480x360, 29.97 fps), repeated back to back
with its own sound cut to the picture, and encoded as H.264 + AAC MP4 under ``--out`` (nothing large is committed;
a take already built is reused). For each length a pipeline file is generated next to them: ``pipeline.yaml``
with ``track_test`` reading the long take, no ``publish:``, and a store of its own under ``--out``: a fresh copy
of a warm-up store that a first, untimed run of the default take filled with the training branch (track_train,
aam, bilinear, character, headdb, ...), so every timed run computes exactly the stages that depend on the test
take, whatever earlier runs left behind.

Each timed run is ``python -m msflow.cli run <generated pipeline> -j N`` in a subprocess (``--until track_test``:
tracking alone, no warm-up). Printed per length, the issue's table: the wall (and CPU) seconds of the tracking
(track_test), edit and export stages from the run record, the whole run's wall time and CPU time (user + sys of
msflow and all its workers), the peak resident memory of the run (the sum over msflow and its worker processes,
sampled every 0.1 s with psutil), the load average; then the 10 min / 1 min ratios against the goals (linear:
10x +- 15%; peak RSS <= 1.5 GB), and, per run, the peak RSS of the process that ran each stage while it ran (the
run record's ``worker`` names its pid: since -j N runs stages in the run's own process first, docs/framework.md
"Where -j N runs a stage", that is usually msflow's own process, whose RSS holds the run's planning and what its
earlier stages left to the allocator, so the rise over the RSS at the stage's start is printed beside it).
``--per-stage``: each test-dependent stage alone in its own ``msflow run`` (wall, CPU, peak RSS per stage).
Wall-clock figures depend on the machine's load (printed); CPU seconds and memory much less.
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
#: table column -> stage
TRACKED_STAGES = {"track": "track_test", "edit": "edit", "export": "export"}
#: the stages that depend on the test take, in an order that runs each after its inputs (--per-stage)
TEST_STAGES = (
    "track_test",
    "pitch_test",
    "edit",
    "keyshapes",
    "blend",
    "trellis",
    "motion_blend",
    "export",
)


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


def fresh_store(out: Path, name: str, warm: bool) -> Path:
    """An empty store for one timed run, or a copy of the warm-up store (training branch already computed), so
    every stage that depends on the test take runs, whatever earlier runs left behind."""
    import shutil

    store = out / f"store-{name}"
    shutil.rmtree(store, ignore_errors=True)
    if warm:
        shutil.copytree(out / "store-warm", store)
    return store


def pipeline_for(take: Path, out: Path, name: str, store: Path) -> Path:
    """pipeline.yaml with the test take replaced, the given store, absolute data paths, nothing published."""
    import yaml

    spec = yaml.safe_load((ROOT / "pipeline.yaml").read_text())
    spec["vars"]["clips"] = str(ROOT / "data" / "crema-d")
    spec["store"] = str(store)
    spec["stages"]["track_test"]["inputs"]["videos"] = {"sad": {"path": str(take), "speaker": "1001"}}
    for stage in spec["stages"].values():
        for key, ref in list(stage.get("inputs", {}).items()):
            if isinstance(ref, dict) and set(ref) == {"path"} and not Path(ref["path"]).is_absolute():
                stage["inputs"][key] = {"path": str(ROOT / ref["path"])}
    spec.pop("publish", None)
    path = out / f"pipeline_{name}.yaml"
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return path


def process_rss(proc) -> dict[int, int]:
    """Resident bytes of a process and each of its descendants, by pid."""
    import psutil

    try:
        procs = [proc] + proc.children(recursive=True)
    except psutil.NoSuchProcess:
        return {}
    out = {}
    for p in procs:
        try:
            out[p.pid] = p.memory_info().rss
        except psutil.NoSuchProcess:
            pass
    return out


def read_lines(stream, lines: list) -> None:
    """Collect (time, line) from the run's progress output (one line per stage state change)."""
    for line in stream:
        lines.append((time.perf_counter(), line))


def stage_peaks(record: dict, lines: list, samples: list, run_pid: int) -> dict[str, dict]:
    """Peak RSS of the process that ran each stage while it ran: the pid in the stage's run record (``worker``:
    ``<host> pid <pid>``), sampled between its "running" and "done" progress lines. That process is msflow's own
    (``run_pid``) for a stage that ran there (``Stage.in_process`` under -j N, every stage under -j 1), else a
    worker. A process keeps memory its earlier stages freed to the allocator, and msflow's own holds the run's
    planning too, so a peak is an upper bound of what the stage itself needed; ``rise`` (the peak less the RSS
    sampled when the stage started) is closer to it. Per stage: ``{"where", "peak", "start", "rise"}``."""
    import re

    bounds: dict[str, list[float]] = {}
    for t, line in lines:
        m = re.match(r"^\S+\s+(\S+)\s+(running|done)\b", line)
        if m:
            bounds.setdefault(m.group(1), [t, t])[0 if m.group(2) == "running" else 1] = t
    peaks = {}
    for name, stage in record.get("stages", {}).items():
        worker = re.search(r"pid (\d+)", stage.get("worker") or "")
        if stage["state"] != "ran" or not worker or name not in bounds:
            continue
        pid, (start, stop) = int(worker.group(1)), bounds[name]
        inside = [rss[pid] for t, rss in samples if start - 0.1 <= t <= stop + 0.1 and pid in rss]
        if not inside:
            continue
        where = "msflow's process" if pid == run_pid else f"worker {pid}"
        peaks[name] = {"where": where, "peak": max(inside), "start": inside[0], "rise": max(inside) - inside[0]}
    return peaks


def format_peaks(peaks: dict[str, dict]) -> str:
    return ", ".join(
        f"{stage} {p['peak'] / 1e9:.2f} GB (+{p['rise'] / 1e9:.2f}; {p['where']})" for stage, p in peaks.items()
    )


def timed_run(pipeline: Path, jobs: int, until: str | None = None) -> dict:
    """Run the pipeline in a subprocess: wall and CPU seconds (with workers), peak tree RSS (msflow and its
    workers together, sampled every 0.1 s), peak RSS per stage (``stage_peaks``), the run record."""
    import threading

    import psutil

    env = dict(os.environ, PYTHONPATH=str(ROOT))
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    extra = ["--until", until] if until else []
    proc = subprocess.Popen(
        [sys.executable, "-m", "msflow.cli", "run", str(pipeline), "-j", str(jobs), *extra],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    lines: list = []
    reader = threading.Thread(target=read_lines, args=(proc.stdout, lines), daemon=True)
    reader.start()
    watched, samples = psutil.Process(proc.pid), []
    while proc.poll() is None:
        samples.append((time.perf_counter(), process_rss(watched)))
        time.sleep(0.1)
    wall = time.perf_counter() - started
    reader.join()
    output = "".join(line for _, line in lines)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"run of {pipeline} failed ({proc.returncode}):\n{output}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    record = latest_record(pipeline)
    peak = max((sum(rss.values()) for _, rss in samples), default=0)
    return {
        "wall": wall,
        "cpu": cpu,
        "peak_rss": peak,
        "stage_rss": stage_peaks(record, lines, samples, proc.pid),
        "record": record,
        "output": output,
    }


def latest_record(pipeline: Path) -> dict:
    import yaml

    store = Path(yaml.safe_load(pipeline.read_text())["store"])
    records = sorted((store / "runs").glob("*.json"), key=lambda p: p.stat().st_mtime)
    return json.loads(records[-1].read_text())


def stage_times(record: dict, name: str) -> str:
    """ "wall s (CPU s)" of a stage from the run record, "-" when it did not run."""
    stage = record.get("stages", {}).get(name)
    if not stage or stage["state"] != "ran":
        return "-"
    return f"{stage['seconds']:.1f} s ({stage.get('cpu_seconds', 0.0):.1f} s CPU)"


def per_stage(pipeline: Path, jobs: int) -> list[tuple[str, float, float, float]]:
    """Each test-dependent stage alone (``--until`` it, its inputs already stored), in its own ``msflow run``
    process: (stage, wall s, CPU s, peak RSS bytes of the run's process tree)."""
    rows = []
    for stage in TEST_STAGES:
        run = timed_run(pipeline, jobs, stage)
        rows.append((stage, run["wall"], run["cpu"], run["peak_rss"]))
        print(
            f"   {stage}: {run['wall']:.1f} s wall, {run['cpu']:.1f} s CPU, {run['peak_rss'] / 1e9:.2f} GB", flush=True
        )
    return rows


def print_per_stage(tables: dict[str, list]) -> None:
    names = list(tables)
    print("| stage | " + " | ".join(f"{n}: wall, CPU, peak RSS" for n in names) + " |")
    print("|---|" + "---|" * len(names))
    for i, stage in enumerate(TEST_STAGES):
        cells = [f"{t[i][1]:.1f} s, {t[i][2]:.1f} s, {t[i][3] / 1e9:.2f} GB" for t in tables.values()]
        print(f"| {stage} | " + " | ".join(cells) + " |")


def print_table(rows: list[dict], jobs: int, until: str | None) -> None:
    print(
        f"\n-j {jobs}, {os.cpu_count()} CPUs; stage times: wall (CPU of the stage's run) from the run record; whole "
        f"run CPU = user + sys of msflow and its workers; peak RSS = msflow and its workers together"
        f"{f'; run --until {until}' if until else ''}"
    )
    print("| take | frames | tracking | edit | export | whole run, wall | whole run, CPU | peak RSS | load average |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['name']} | {r['frames']} | {r['track']} | {r['edit']} | {r['export']} | {r['wall']:.1f} s "
            f"| {r['cpu']:.1f} s | {r['rss'] / 1e9:.2f} GB | {r['load']} |"
        )
    by_name = {r["name"]: r for r in rows}
    if "1min" in by_name and "10min" in by_name:
        a, b = by_name["1min"], by_name["10min"]
        print(
            f"10 min / 1 min: CPU {b['cpu'] / a['cpu']:.2f}x, wall {b['wall'] / a['wall']:.2f}x "
            f"(linear: 10x +- 15%); peak RSS {b['rss'] / 1e9:.2f} GB (goal <= 1.5 GB)"
        )


def loads() -> str:
    return "/".join(f"{x:.1f}" for x in os.getloadavg())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lengths", default="2s,1min", help="comma list of " + ", ".join(LENGTHS))
    ap.add_argument("-j", "--jobs", type=int, default=2)
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "out" / "long")
    ap.add_argument("--until", default=None, help="run only up to this stage (e.g. track_test: tracking alone)")
    ap.add_argument(
        "--per-stage",
        action="store_true",
        help="run each test-dependent stage alone in its own process: wall, CPU and peak RSS per stage",
    )
    args = ap.parse_args()
    args.out = args.out.resolve()
    (args.out / "takes").mkdir(parents=True, exist_ok=True)
    if not args.until:
        warm = pipeline_for(SOURCE, args.out, "warmup", args.out / "store-warm")
        print(f"warm-up run (training branch into {args.out / 'store-warm'}) ...", flush=True)
        timed_run(warm, args.jobs)
    rows, tables = [], {}
    for name in args.lengths.split(","):
        take = build_take(args.out / "takes" / f"sad_{name}.mp4", LENGTHS[name])
        store = fresh_store(args.out, name, warm=not args.until)
        pipeline = pipeline_for(take, args.out, name, store)
        if args.per_stage:
            print(f"{name}, stage by stage (load average {loads()}):", flush=True)
            tables[name] = per_stage(pipeline, args.jobs)
            continue
        run = timed_run(pipeline, args.jobs, args.until)
        record = run["record"]
        row = {"name": name, "frames": LENGTHS[name] * 60, "wall": run["wall"], "cpu": run["cpu"]}
        row.update(rss=run["peak_rss"], load=loads())
        row.update({key: stage_times(record, stage) for key, stage in TRACKED_STAGES.items()})
        rows.append(row)
        print(
            f"{name}: {run['wall']:.1f} s wall, ran {record['counts'].get('ran', 0)} stages, load {row['load']}",
            flush=True,
        )
        print(
            "   peak RSS of the process that ran each stage, while it ran (+ its rise over the stage's start; where): "
            + format_peaks(run["stage_rss"]),
            flush=True,
        )
    if tables:
        print(f"\n-j {args.jobs}, {os.cpu_count()} CPUs; each stage alone in its own msflow run process")
        print_per_stage(tables)
    else:
        print_table(rows, args.jobs, args.until)


if __name__ == "__main__":
    main()
