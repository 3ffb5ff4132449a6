"""Tracking speed and quality: FaceMesh with either landmark model, on CREMA-D and on talking-head footage.

    python bench/bench_tracking.py [--talking-heads DIR] [--out DIR] [--fresh] [--sections 1 2 3 4] [--crema-only]

DIR defaults to ../shared/data/talking-heads beside the project, or ../../shared/... from a worktree (skipped
when absent). Printed:

1. speed per core (one OpenCV thread, one decoder thread; CPU seconds, so other load matters little) of the whole
   FaceMesh stage (decode, landmarks, crops, head pose, eyes, audio) in each configuration (``CONFIGS``: the
   default, face_mesh_v1 landmarks with eyes from a Face Landmarker v2 pass; v2 alone; v1 alone) on CREMA-D;
2. 1080p and 720p speed with 2 workers (``jobs`` = 2: decoder threads and OpenCV threads): a 1920x1080 clip made
   by upscaling 20 s of ``address_us.mp4`` with PyAV (written under --out), and ``address_us.mp4`` itself;
3. landmark agreement, per clip: the streaming pipeline (Y'CbCr planes) against the previous one (whole frames
   converted to BGR by FFmpeg) with the same model (face_mesh_v1), and Face Landmarker v2 against face_mesh_v1;
   nose-bridge jitter (mean second difference) of both models;
4. eyes: blinks found by ``eyes.detect_blinks`` on each configuration's eye aperture (face_mesh_v1 alone: its
   own lids, measured the same way) against blinks marked by hand, frame by frame, on contact sheets of the eye
   region (``HAND_BLINKS``), with the open and closed aperture levels; for each eye pass (``EYE_PASSES``: Face
   Landmarker v2, the iris model) the rest position of the iris in the eye (median over every clip's open-eye
   frames; ``eyes.REST_OFFSETS``); the iris pass's gaze against the v2 pass's; the CPU per frame of each pass
   alone. ``--sections 4`` runs only this section.

Tracks are cached per clip and model under --out/tracks/<hash of stages/tracking> (``--fresh`` recomputes them),
so a change to the tracker never compares stale tracks. ``--crema-only``: sections 3 and 4 on the CREMA-D clips
alone (section 2 still needs the talking heads).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from msflow.testing import run_stage  # noqa: E402
from stages.tracking import FaceMesh  # noqa: E402
from stages.tracking.assemble import inter_ocular  # noqa: E402
from stages.tracking.eyes import REST_OFFSETS, angles_to_offsets, detect_blinks, eye_aperture  # noqa: E402
from stages.tracking.facemesh import eye_pass_points  # noqa: E402
from stages.tracking.planes import BgrImage  # noqa: E402

CREMA = sorted((ROOT / "data" / "crema-d").glob("*.flv"))
#: FaceMesh configurations compared: the default (face_mesh_v1 landmarks, eyes from a Face Landmarker v2 pass on
#: the same face region), Face Landmarker v2 as the landmark model, face_mesh_v1 alone
CONFIGS = {
    "default": {},
    "eyes_landmarker_v2": {"eyes": "landmarker_v2"},
    "eyes_iris": {"eyes": "iris"},
    "face_landmarker_v2": {"model": "face_landmarker_v2"},
    "face_mesh_v1": {"eyes": False},
}
#: the eye passes compared in section 4 (face_mesh_v1 landmarks plus a second model for the eyes)
EYE_PASSES = {"eyes_landmarker_v2": "landmarker_v2", "eyes_iris": "iris"}
#: blinks marked by hand on eye-region contact sheets: clip -> (frames looked at, or None for all;
#: [first, last] closed-or-closing frames, inclusive)
HAND_BLINKS = {
    "1001_DFA_ANG_XX": (None, []),
    "1001_DFA_DIS_XX": (None, []),
    "1001_DFA_FEA_XX": (None, [(0, 4)]),
    "1001_DFA_HAP_XX": (None, [(5, 8)]),
    "1001_DFA_NEU_XX": (None, [(7, 10)]),
    "1001_DFA_SAD_XX": (None, [(6, 8)]),
    "hdtf_aoc": (
        None,
        [(9, 12), (25, 27), (33, 37), (56, 59), (80, 82), (96, 98), (110, 112), (129, 131), (150, 152), (177, 179)],
    ),
    "retalking_3": (None, [(11, 14), (27, 29), (35, 37), (57, 61), (81, 84), (98, 100), (112, 113)]),
    "vlog_31": (
        200,
        [
            (23, 27),
            (37, 39),
            (44, 46),
            (50, 52),
            (62, 63),
            (69, 71),
            (99, 102),
            (112, 115),
            (120, 124),
            (143, 146),
            (159, 161),
            (193, 196),
        ],
    ),  # fmt: skip
}


def tracker_code_hash() -> str:
    """Hash of the tracking code (stages/tracking/*.py): the key of the track cache."""
    import hashlib

    digest = hashlib.sha256()
    for path in sorted((ROOT / "stages" / "tracking").glob("*.py")):
        digest.update(path.name.encode() + path.read_bytes())
    return digest.hexdigest()[:12]


def track(clip: Path, config: str, cache: Path, fresh: bool) -> dict:
    """FaceMesh arrays of one clip with one of CONFIGS (cached), with the CPU seconds it took."""
    path = cache / f"{clip.stem}.{config}.npz"
    if path.exists() and not fresh:
        return dict(np.load(path))
    started = time.process_time()
    out = run_stage(FaceMesh, {**CONFIGS[config], "audio": "none"}, {"videos": {clip.stem: clip}})
    keep = ("mesh", "landmarks", "valid", "time", "iris", "eye_aperture", "gaze")
    arrays = {k: np.asarray(out.arrays[k]) for k in keep if k in out.arrays}
    arrays["cpu"] = np.array(time.process_time() - started)
    np.savez(path, **arrays)
    return arrays


def previous_pipeline_landmarks(clip: Path) -> np.ndarray:
    """face_mesh_v1 landmarks as the tracker made them before streaming: whole frames converted to BGR."""
    from stages.tracking.facemesh import FaceMeshTracker
    from stages.tracking.landmarks68 import mesh_to_ibug68
    from stages.tracking.stages import DETECTOR_MODEL, LANDMARK_MODEL
    from stages.tracking.video import iter_frames

    tracker = FaceMeshTracker(DETECTOR_MODEL, LANDMARK_MODEL)
    out = []
    for _, frame in iter_frames(clip):
        points, _ = tracker.step(frame)
        out.append(np.full((68, 2), np.nan) if points is None else mesh_to_ibug68(points[:, :2]))
    return np.array(out)


def rms(a: np.ndarray, b: np.ndarray) -> float:
    d = np.linalg.norm(a - b, axis=-1)
    return float(np.sqrt(np.nanmean(d**2)))


def jitter(landmarks: np.ndarray) -> float:
    nose = landmarks[:, 27]
    return float(np.mean(np.linalg.norm(nose[2:] - 2 * nose[1:-1] + nose[:-2], axis=1) / 2))


def speed_per_core(out: Path) -> None:
    print("1. FaceMesh stage on the six CREMA-D clips, one core (CPU time):")
    videos = {c.stem: c for c in CREMA}
    for config, params in CONFIGS.items():
        run_stage(FaceMesh, params, {"videos": {"w": CREMA[0]}})  # warm-up: imports, model load
        started = time.process_time()
        result = run_stage(FaceMesh, params, {"videos": videos})
        cpu = time.process_time() - started
        n = len(result.arrays["valid"])
        print(f"   {config:20s} {n / cpu:6.1f} frames/s per core ({1000 * cpu / n:.1f} ms CPU per frame)")


def upscaled_1080p(source: Path, path: Path, seconds: float = 20.0) -> Path:
    """``seconds`` of ``source`` scaled to 1920x1080 (bicubic) and encoded with libx264 (CRF 18)."""
    import av

    if path.exists():
        return path
    with av.open(str(source)) as inp, av.open(str(path), "w") as dst:
        stream = inp.streams.video[0]
        enc = dst.add_stream("libx264", rate=stream.average_rate)
        enc.width, enc.height, enc.pix_fmt = 1920, 1080, "yuv420p"
        enc.options = {"preset": "veryfast", "crf": "18"}
        for frame in inp.decode(stream):
            if frame.time > seconds:
                break
            for packet in enc.encode(frame.reformat(1920, 1080, "yuv420p", interpolation="BICUBIC")):
                dst.mux(packet)
        for packet in enc.encode():
            dst.mux(packet)
    return path


def speed_high_resolution(heads: Path | None, out: Path) -> None:
    if heads is None:
        return
    source = heads / "address_us.mp4"
    clips = {"1080p (address_us upscaled)": upscaled_1080p(source, out / "address_us_1080p.mp4"), "720p": source}
    print("2. FaceMesh stage, 2 workers and 1 worker: frames/s wall (CPU per frame, load average)")
    runs = [("default", 2), ("default", 1), ("eyes_iris", 1), ("face_mesh_v1", 2)]
    best: dict[str, float] = {}
    for name, clip in clips.items():
        for config, jobs in runs:
            started, cpu0 = time.perf_counter(), time.process_time()
            params = {**CONFIGS[config], "audio": "none"}
            result = run_stage(FaceMesh, params, {"videos": {"c": clip}}, jobs=jobs)
            wall, cpu = time.perf_counter() - started, time.process_time() - cpu0
            n = len(result.arrays["valid"])
            load = os.getloadavg()[0]
            best[f"{name}, {config}"] = max(best.get(f"{name}, {config}", 0.0), n / wall)
            print(
                f"   {name:28s} {config:13s} jobs {jobs}: {n / wall:6.1f} frames/s ({1000 * cpu / n:.1f} ms CPU per frame, "
                f"load {load:.1f})"
            )
    for what, rate in best.items():
        if what.startswith("1080p"):
            print(f"   {what}: best {rate:.1f} frames/s wall (goal >= 60 on 2 cores; wall depends on the load)")


def agreement(clips: list[Path], cache: Path, fresh: bool) -> None:
    print("3. landmarks (68 points), RMS px and % of the outer-eye-corner distance (IOD):")
    print("   clip                 IOD px | streaming vs previous (v1) | v2 vs v1        | jitter v2 / v1 px")
    worst = 0.0
    for clip in clips:
        v2, v1 = track(clip, "face_landmarker_v2", cache, fresh), track(clip, "face_mesh_v1", cache, fresh)
        before = previous_pipeline_landmarks(clip)
        iod = float(np.mean(inter_ocular(v1["landmarks"])))
        same, models = rms(v1["landmarks"], before), rms(v2["landmarks"], v1["landmarks"])
        worst = max(worst, same)
        print(
            f"   {clip.stem:20s} {iod:6.1f} | {same:5.2f} px ({100 * same / iod:4.2f}%)       "
            f"| {models:4.2f} px ({100 * models / iod:4.2f}%) | {jitter(v2['landmarks']):.2f} / "
            f"{jitter(v1['landmarks']):.2f}"
        )
    print(f"   largest RMS, streaming vs previous pipeline: {worst:.2f} px (goal <= 0.5 px)")


def closed_levels(aperture: np.ndarray, hand: list[tuple[int, int]]) -> list[float]:
    """Each hand-marked blink's most closed aperture (mean of both eyes)."""
    a = aperture.mean(axis=1)
    return [float(a[first : last + 1].min()) for first, last in hand]


def blink_recall(clips: list[Path], cache: Path, fresh: bool) -> None:
    """Blinks found against the hand-marked ones, with each configuration's open and closed aperture levels."""
    by_stem = {c.stem: c for c in clips}
    print("   configuration        recall          false blinks    aperture open (median) / closed (median of blinks)")
    for config in CONFIGS:
        if config == "default":
            continue
        marked = found = detected = false = 0
        opened, closed = [], []
        for stem, (limit, hand) in HAND_BLINKS.items():
            if stem not in by_stem:
                continue
            arrays = track(by_stem[stem], config, cache, fresh)
            n = limit or len(arrays["valid"])
            # face_mesh_v1 alone has no eye outputs: its own lids, measured the same way
            aperture = arrays["eye_aperture"][:n] if "eye_aperture" in arrays else eye_aperture(arrays["mesh"][:n])
            blinks = [(a, b - 1) for a, b in detect_blinks(aperture, arrays["valid"][:n])]

            def overlaps(x, y):
                return x[0] <= y[1] and y[0] <= x[1]

            marked += len(hand)
            found += sum(any(overlaps(h, b) for b in blinks) for h in hand)
            detected += len(blinks)
            false += sum(not any(overlaps(b, h) for h in hand) for b in blinks)
            opened.append(float(np.median(aperture[arrays["valid"][:n]].mean(axis=1))))
            closed += closed_levels(aperture, hand)
        print(
            f"   {config:20s} {found:2d}/{marked} = {found / max(marked, 1):4.0%}   {false:2d}/{detected:2d} = "
            f"{false / max(detected, 1):4.0%}      {np.median(opened):.3f} / {np.median(closed):.3f}"
        )


def open_eyes(arrays: dict) -> np.ndarray:
    """Tracked frames whose eyes are open (aperture above 0.6 x the take's median): gaze means something there."""
    aperture = arrays["eye_aperture"].mean(axis=1)
    return arrays["valid"] & (aperture > 0.6 * np.median(aperture))


def rest_positions(clips: list[Path], cache: Path, fresh: bool) -> None:
    """Each eye pass's iris rest position: the median over clips of each clip's median offset (open eyes)."""
    for config, kind in EYE_PASSES.items():
        medians = []
        for clip in clips:
            arrays = track(clip, config, cache, fresh)
            e = np.median(angles_to_offsets(arrays["gaze"], rest=REST_OFFSETS[kind])[open_eyes(arrays)], axis=0)
            medians.append([e[0, 0], -e[1, 0], e[0, 1], e[1, 1]])  # temporal L, R; up L, R
        m = np.array(medians)
        print(
            f"   {config:20s} iris rest position over {len(clips)} clips (median of per-clip medians, eye widths): "
            f"towards the outer corner {np.median(m[:, :2]):.3f}, up {np.median(m[:, 2:]):.3f} "
            f"(eyes.REST_OFFSETS['{kind}'] = {REST_OFFSETS[kind]})"
        )


def gaze_agreement(clips: list[Path], cache: Path, fresh: bool, shift: int = 25) -> None:
    """Gaze of the iris pass against the v2 pass (deg RMS over open-eye frames, both eyes, yaw and pitch); the
    same with each clip's median difference taken off (what differs beyond a constant offset); against the v2
    pass shifted by ``shift`` frames (how far apart two unrelated gazes of the clip are); the v2 pass's own
    spread (RMS about its median)."""
    print(
        f"   gaze, iris pass vs v2 pass, deg RMS yaw, pitch | clip offsets removed | v2 shifted {shift} frames | "
        "v2 spread:"
    )
    for name, group in (
        ("CREMA-D", [c for c in clips if c in CREMA]),
        ("talking heads", [c for c in clips if c not in CREMA]),
    ):
        same, moving, shifted, spread = [], [], [], []
        for clip in group:
            iris, v2 = track(clip, "eyes_iris", cache, fresh), track(clip, "eyes_landmarker_v2", cache, fresh)
            ok = open_eyes(iris) & open_eyes(v2)
            a, b = iris["gaze"].astype(np.float64), v2["gaze"].astype(np.float64)
            same.append((a - b)[ok])
            moving.append((a - b)[ok] - np.median((a - b)[ok], axis=0))
            spread.append((b - np.median(b[ok], axis=0))[ok])
            k = min(shift, len(a) // 2)
            both = ok[k:] & ok[:-k]
            shifted.append((a[k:] - b[:-k])[both])
        if not group:
            continue

        def rms(parts):
            d = np.concatenate(parts)
            return np.sqrt(np.mean(d**2, axis=(0, 1)))

        cells = " | ".join(f"{r[0]:4.1f}, {r[1]:4.1f}" for r in map(rms, (same, moving, shifted, spread)))
        print(f"   {name:14s} ({len(group):2d} clips): {cells}")


def eye_pass_cpu(clips: list[Path]) -> None:
    """CPU per frame of each eye pass alone (one thread), on the face_mesh_v1 tracks of the clips' frames."""
    from stages.tracking.facemesh import FaceMeshTracker, new_eye_pass
    from stages.tracking.stages import DETECTOR_MODEL, IRIS_MODEL, LANDMARK_MODEL, LANDMARKER_V2_MODEL
    from stages.tracking.video import read_frames

    tracker = FaceMeshTracker(DETECTOR_MODEL, LANDMARK_MODEL)
    work = []
    for clip in clips:
        tracker.reset()
        for frame in read_frames(clip)[1]:
            roi = tracker.roi
            points, _ = tracker.step(frame)
            if roi is not None and points is not None:
                work.append((BgrImage(frame), roi, points))
    passes = {"landmarker_v2": LANDMARKER_V2_MODEL, "iris": IRIS_MODEL}
    for kind, path in passes.items():
        model = new_eye_pass(kind, path)
        eye_pass_points(model, *work[0])  # warm-up
        started = time.process_time()
        for item in work:
            eye_pass_points(model, *item)
        cpu = time.process_time() - started
        print(f"   eye pass {kind:14s} {1000 * cpu / len(work):5.2f} ms CPU per frame ({len(work)} CREMA-D frames)")


def eyes(clips: list[Path], cache: Path, fresh: bool) -> None:
    print("4. eyes: blinks against the hand-marked ones (a hand blink is found when a detected one overlaps it):")
    blink_recall(clips, cache, fresh)
    rest_positions(clips, cache, fresh)
    gaze_agreement(clips, cache, fresh)
    eye_pass_cpu(CREMA)


def default_talking_heads() -> Path:
    """../shared/data/talking-heads beside the project (a checkout), or two levels up (a worktree under wt/)."""
    near = ROOT.parent / "shared" / "data" / "talking-heads"
    far = ROOT.parent.parent / "shared" / "data" / "talking-heads"
    return near if near.is_dir() or not far.is_dir() else far


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--talking-heads", type=Path, default=default_talking_heads())
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "out" / "tracking")
    ap.add_argument("--fresh", action="store_true", help="recompute cached tracks")
    ap.add_argument("--sections", type=int, nargs="+", default=[1, 2, 3, 4], help="sections to run (default all)")
    ap.add_argument("--crema-only", action="store_true", help="sections 3 and 4 on the CREMA-D clips only")
    args = ap.parse_args()
    cache = args.out / "tracks" / tracker_code_hash()
    cache.mkdir(parents=True, exist_ok=True)
    heads = args.talking_heads if args.talking_heads.is_dir() else None
    clips = CREMA + (sorted(heads.glob("*.mp4")) if heads and not args.crema_only else [])
    sections = set(args.sections)
    print(f"{os.cpu_count()} CPUs, load average {'/'.join(f'{x:.1f}' for x in os.getloadavg())} at the start")
    cv2.setNumThreads(1)
    if 1 in sections:
        speed_per_core(args.out)
    if 2 in sections:
        speed_high_resolution(heads, args.out)
    cv2.setNumThreads(1)
    if 3 in sections:
        agreement(clips, cache, args.fresh)
    if 4 in sections:
        eyes(clips, cache, args.fresh)


if __name__ == "__main__":
    main()
