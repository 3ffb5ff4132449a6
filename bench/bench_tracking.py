"""Tracking speed and quality on the six CREMA-D clips (plain script; figures for the issue report).

    OPENBLAS_NUM_THREADS=1 python bench/bench_tracking.py [--out DIR] [--repeat N]

Speed is per core (cv2.setNumThreads(1)): FaceMesh tracking alone (decode + detector/mesh per frame), the whole
FaceMesh stage (plus crops, head pose, audio), OpticalFlow and TrackFile. Quality: frames with a face, nose-bridge
steps between consecutive frames, OpticalFlow's distance to FaceMesh's 68 points per clip (normalised by the
outer-eye-corner distance), head-pose ranges and steps. With --out, writes the contact sheet and pose plot.
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
from stages.geometry.rotations import quat_to_euler  # noqa: E402
from stages.tracking import FaceMesh, OpticalFlow, TrackFile  # noqa: E402
from stages.tracking.assemble import inter_ocular  # noqa: E402
from stages.tracking.facemesh import FaceMeshTracker  # noqa: E402
from stages.tracking.stages import DETECTOR_MODEL, LANDMARK_MODEL  # noqa: E402
from stages.tracking.trackfile import write_openface_csv  # noqa: E402
from stages.tracking.video import iter_frames  # noqa: E402

EMOTIONS = ("NEU", "HAP", "ANG", "SAD", "DIS", "FEA")
VIDEOS = {e: ROOT / "data" / "crema-d" / f"1001_DFA_{e}_XX.flv" for e in EMOTIONS}


def best_of(repeat: int, fn):
    times, result = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t)
    return min(times), result


def tracking_only() -> int:
    tracker = FaceMeshTracker(DETECTOR_MODEL, LANDMARK_MODEL)
    frames = 0
    for path in VIDEOS.values():
        tracker.reset()
        for _, frame in iter_frames(path):
            tracker.step(frame)
            frames += 1
    return frames


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    videos = {k: str(v) for k, v in VIDEOS.items()}

    tracking_only()  # warm-up: model loading, imports
    t_track, frames = best_of(args.repeat, tracking_only)
    t_stage, fm = best_of(args.repeat, lambda: run_stage(FaceMesh, {}, {"videos": videos}))
    t_flow, flow = best_of(args.repeat, lambda: run_stage(OpticalFlow, {}, {"videos": videos}))
    print(f"frames: {frames} in {len(videos)} clips")
    print(f"FaceMesh tracking only (decode + detector/mesh): {frames / t_track:7.1f} frames/s per core")
    print(
        f"FaceMesh stage (+ crops, pose, audio):            {frames / t_stage:7.1f} frames/s per core "
        f"(crops+pose+audio add {100 * (t_stage / t_track - 1):.1f}%)"
    )
    print(f"OpticalFlow stage (FaceMesh start, LK + shape model): {frames / t_flow:7.1f} frames/s per core")

    lm, seq, valid = fm.arrays["landmarks"], fm.arrays["sequence"], fm.arrays["valid"]
    print(
        f"\nFaceMesh: frames with a face {int(valid.sum())}/{len(valid)}; "
        f"detector runs per clip {fm.meta['detector_runs']}"
    )
    euler = np.degrees(quat_to_euler(fm.arrays["rotation"]))
    print(
        "clip  IOD px  nose step px (mean/p95)  nose jitter px  |yaw|max |pitch|max |roll|max  max pose step deg"
        "  flow/FaceMesh mean (max) IOD"
    )
    for s, label in enumerate(fm.meta["labels"]):
        rows = seq == s
        st = fm.meta["sequence_stats"][label]
        steps = np.linalg.norm(np.diff(lm[rows, 27], axis=0), axis=1)
        iod = inter_ocular(lm[rows])
        dist = np.linalg.norm(flow.arrays["landmarks"][rows] - lm[rows], axis=2).mean(axis=1) / iod
        e = np.abs(euler[rows])
        print(
            f"{label:4s} {iod.mean():7.1f}  {steps.mean():8.2f} / {np.percentile(steps, 95):5.2f}"
            f"      {st['nose_jitter_px']:8.2f}       {e[:, 0].max():6.1f}   {e[:, 1].max():6.1f}   "
            f"{e[:, 2].max():6.1f}      {st['max_pose_step_deg']:6.2f}           "
            f"{100 * dist.mean():5.2f}% ({100 * dist.max():5.2f}%)"
        )

    # head pose: the default rigid landmark subset against all 68 points
    from stages.tracking.assemble import rotation_steps_deg
    from stages.tracking.face3d import load_face3d
    from stages.tracking.pose import camera_matrix, solve_head_pose

    face3d = load_face3d()
    cam = camera_matrix(480, 360)
    for name, points in (("rigid (default)", np.array(face3d.rigid)), ("all 68", None)):
        worst = []
        for s in range(len(fm.meta["labels"])):
            q, _, rms = solve_head_pose(lm[seq == s].astype(np.float64), face3d.neutral, cam, points)
            e = np.degrees(quat_to_euler(q))
            worst.append((np.abs(e[:, 0]).max(), np.abs(e[:, 1]).max(), rotation_steps_deg(q).max(), rms.mean()))
        w = np.array(worst)
        print(
            f"pose landmarks {name:16s}: max |yaw| {w[:, 0].max():4.1f} deg, max |pitch| {w[:, 1].max():4.1f} deg,"
            f" max step {w[:, 2].max():4.2f} deg/frame, mean reprojection RMS {w[:, 3].mean():4.2f} px"
        )

    # TrackFile round trip of a synthetic OpenFace CSV with success = 0 rows
    import tempfile

    rows = seq == 0
    truth = lm[rows].astype(np.float64)
    success = np.ones(len(truth), dtype=bool)
    success[[3, 4, 5, 20]] = False
    with tempfile.TemporaryDirectory() as tmp:
        csv = Path(tmp) / "neutral.csv"
        csv.write_text(write_openface_csv(truth, time=fm.arrays["time"][rows], success=success))
        t_file, tf = best_of(
            args.repeat,
            lambda: run_stage(TrackFile, {}, {"tracks": {"NEU": str(csv)}, "videos": {"NEU": videos["NEU"]}}),
        )
    err = np.abs(tf.arrays["landmarks"] - truth)
    print(
        f"\nTrackFile OpenFace round trip: max error on success rows {err[success].max():.2e} px; "
        f"{int((~tf.arrays['valid']).sum())} success=0 rows flagged and interpolated "
        f"(max {err[~success].max():.2f} px from FaceMesh); {len(truth) / t_file:.0f} frames/s with crops+audio"
    )

    if args.out:
        from stages.tracking.figures import contact_sheet_png, head_pose_figure

        args.out.mkdir(parents=True, exist_ok=True)
        view = fm.view()
        (args.out / "tracking_contact_sheet.png").write_bytes(contact_sheet_png(view, {"videos": videos}))
        head_pose_figure(view).savefig(args.out / "tracking_head_pose.png", dpi=100)
        (args.out / "tracking_flow_contact_sheet.png").write_bytes(contact_sheet_png(flow.view(), {"videos": videos}))
        print(f"figures written to {args.out}")


if __name__ == "__main__":
    main()
