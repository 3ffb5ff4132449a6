"""Capture on worse footage than the clips: each clip made dim and noisy, compressed hard, and shrunk, then captured
like the original (``eval/retarget.yaml``'s capture branch) and compared with the original's capture.

    python bench/bench_degraded.py ../shared/data/talking-heads/{hdtf_aoc,retalking_3,vlog_31}.mp4

Conditions (each copy keeps every frame of the clip, so frames compare one to one; copies are silent, as the capture
reads only the face):

- ``dim``: a room lit a third as brightly, with sensor noise (pixel values x 0.35, Gaussian noise of 8 levels);
- ``compressed``: H.264 at CRF 40, what a messaging app leaves of a clip;
- ``small``, ``tiny``: a quarter, an eighth of the width and height (the talking heads' eye distance of 150-190
  pixels becomes 40-47, 19-23: a wide shot).

Per condition, pooled over the clips (frames weigh alike):

- **landmarks**: distance of the tracked 68 landmarks from the original's tracking, per frame, mean over the points /
  the original's eye distance (IOD): the median frame and the 95th percentile; the mouth's points alone;
- **head**: per frame, the angle between the copy's tracked head rotation and the original's, less the take's mean
  difference (the export writes the head relative to its mean orientation), degrees;
- **blinks** against the blinks marked by hand (``bench_tracking.HAND_BLINKS``) where the clip has them;
- **animation**: per morph that moves in the original's animation (weight spread above 0.05), the correlation of its
  weight with the original's over the frames; the median over (clip, morph) pairs, and jawOpen's;
- **lip closures** (the inner lips under 0.03 IOD for 2 frames or more) in the condition's tracking against the
  original's: the original's found again, and others;
- the evaluation's own figures on the condition's own tracking: mouth error rest aligned, lip closures reproduced,
  jaw > funnel (``docs/retarget.md``, Evaluation).

The copies land in ``out/bench_degraded/<condition>/``; their tracking is cached in the project's store like any run.
"""

from __future__ import annotations

import os
import shutil
import sys
from fractions import Fraction
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
PIPELINE = ROOT / "eval" / "retarget.yaml"
OUT = ROOT / "out" / "bench_degraded"
CONDITIONS = ("original", "dim", "compressed", "small", "tiny")
SHRINK = {"small": 4, "tiny": 8}  # the copy's width and height: 1/4, 1/8
MOVING_SPREAD = 0.05  # a morph whose weight spreads less than this in the original is not compared


def dim(frame: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A third of the light and the sensor noise that comes with it."""
    noisy = frame.astype(np.float32) * 0.35 + rng.normal(0.0, 8.0, frame.shape)
    return np.clip(np.round(noisy), 0, 255).astype(np.uint8)


def shrink(frame: np.ndarray, factor: int) -> np.ndarray:
    """1/``factor`` of the width and height (even sides, as H.264 wants)."""
    import cv2

    height, width = frame.shape[:2]
    size = (max(2, width // (2 * factor) * 2), max(2, height // (2 * factor) * 2))
    return cv2.resize(frame, size, interpolation=cv2.INTER_AREA)


def degrade(frame: np.ndarray, condition: str, rng: np.random.Generator) -> np.ndarray:
    """One frame as ``condition`` leaves it (compression happens in the encoder)."""
    if condition == "dim":
        return dim(frame, rng)
    return shrink(frame, SHRINK[condition]) if condition in SHRINK else frame


def write_copy(source: Path, target: Path, condition: str) -> None:
    """Every frame of ``source``, degraded as ``condition`` says, encoded with H.264 at the source's frame rate."""
    import av

    from stages.tracking.video import iter_frames, probe_video

    rng = np.random.default_rng(0)
    fps = probe_video(source).fps
    crf = "40" if condition == "compressed" else "16"
    with av.open(str(target), "w") as out:
        stream = None
        for _, frame in iter_frames(source):
            frame = degrade(frame, condition, rng)
            if stream is None:
                stream = out.add_stream(
                    "libx264", rate=Fraction(fps).limit_denominator(1001), options={"crf": crf, "preset": "veryfast"}
                )
                stream.height, stream.width = frame.shape[:2]
                stream.pix_fmt = "yuv420p"
            out.mux(stream.encode(av.VideoFrame.from_ndarray(frame, format="bgr24")))
        out.mux(stream.encode())


def make_copies(clips: list[Path]) -> dict[str, Path]:
    """The folder of each condition, with every clip in it (the original as it is) and nothing else: copies of
    clips not asked for this time are removed, copies already made are kept."""
    folders = {}
    for condition in CONDITIONS:
        folder = OUT / condition
        folder.mkdir(parents=True, exist_ok=True)
        for stale in set(folder.glob("*.mp4")) - {folder / (clip.stem + ".mp4") for clip in clips}:
            stale.unlink()
        for clip in clips:
            target = folder / (clip.stem + ".mp4")
            if condition == "original" and not target.exists():
                shutil.copy2(clip, target)
            elif not target.exists():
                partial = target.with_suffix(".partial.mp4")
                write_copy(clip, partial, condition)
                partial.replace(target)
        folders[condition] = folder
    return folders


def capture(folder: Path):
    """The capture branch of the evaluation on one folder: (tracks, blend, evaluation) artifacts."""
    import msflow

    relative = os.path.relpath(folder, PIPELINE.parent)
    result = msflow.run(PIPELINE, [f"vars.takes={relative}", "vars.videos=*.mp4"], until="capture_eval")
    return tuple(result.artifact(stage) for stage in ("capture_track", "capture_blend", "capture_eval"))


def takes_by_stem(tracks) -> dict[str, np.ndarray]:
    """Each take's frame rows, by its file's stem."""
    sequence = np.asarray(tracks["sequence"])
    return {Path(label).stem: np.flatnonzero(sequence == i) for i, label in enumerate(tracks.meta["labels"])}


def landmark_distances(original, degraded, rows_o, rows_d, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Per frame, the mean distance of all 68 landmarks and of the mouth's 20 from the original's, in its IOD."""
    from stages.retarget.face_measures import inter_ocular_distance

    reference = np.asarray(original["landmarks"], np.float64)[rows_o]
    moved = np.asarray(degraded["landmarks"], np.float64)[rows_d] * scale
    distance = np.linalg.norm(moved - reference, axis=-1) / inter_ocular_distance(reference)[:, None]
    return distance.mean(axis=1), distance[:, 48:].mean(axis=1)


def head_angles(original, degraded, rows_o, rows_d) -> np.ndarray:
    """Per frame, the angle (degrees) by which the copy's tracked head rotation differs from the original's, less
    the take's mean difference: the head motion the export writes (relative to its mean orientation) as the copy
    gives it, against the original's."""
    from stages.geometry.rotations import quat_conjugate, quat_continuous, quat_multiply, quat_normalize

    a = quat_normalize(np.asarray(original["rotation"], np.float64)[rows_o])
    b = quat_normalize(np.asarray(degraded["rotation"], np.float64)[rows_d])
    difference = quat_continuous(quat_multiply(quat_conjugate(a), b))
    mean = quat_normalize(difference.mean(axis=0))
    dot = np.abs(np.sum(difference * mean, axis=1))
    return np.degrees(2.0 * np.arccos(np.clip(dot, 0.0, 1.0)))


def weight_correlations(original, degraded, rows_o, rows_d) -> dict[str, float]:
    """Per morph moving in the original's animation, the correlation of the degraded capture's weight with it."""
    names = original.meta["target_names"]
    reference = np.asarray(original["weights"], np.float64)[rows_o]
    other = np.asarray(degraded["weights"], np.float64)[rows_d]
    out = {}
    for m, name in enumerate(names):
        if np.ptp(reference[:, m]) > MOVING_SPREAD and np.ptp(other[:, m]) > 0:
            out[name] = float(np.corrcoef(reference[:, m], other[:, m])[0, 1])
    return out


def closures_against_original(reference, runs) -> dict[str, int]:
    """The performer's lip closures in the condition's tracking against those in the original's (the frames line up:
    the same clips in the same order, every frame kept): original closures found again, and closures the original
    does not have."""
    from stages.eval.events import event_agreement

    events = [[(c["start"], c["stop"]) for c in view.meta["closures"]] for view in (reference[2], runs[2])]
    return event_agreement(events[0], events[1], 0)


def compare(reference, runs) -> dict:
    """One condition's capture against the original's, pooled over the clips."""
    tracks_o, blend_o, _ = reference
    tracks_d, blend_d, evaluation = runs
    rows_o, rows_d = takes_by_stem(tracks_o), takes_by_stem(tracks_d)
    whole, mouth, head, correlations, jaw = [], [], [], [], []
    for stem, ro in rows_o.items():
        rd = rows_d[stem]
        if len(rd) != len(ro):
            raise SystemExit(f"{stem}: {len(rd)} frames in the copy, {len(ro)} in the original")
        take_o, take_d = list(rows_o).index(stem), list(rows_d).index(stem)
        scale = tracks_o.meta["frame_size"][take_o][0] / tracks_d.meta["frame_size"][take_d][0]
        distances = landmark_distances(tracks_o, tracks_d, ro, rd, scale)
        whole.append(distances[0])
        mouth.append(distances[1])
        head.append(head_angles(tracks_o, tracks_d, ro, rd))
        r = weight_correlations(blend_o, blend_d, ro, rd)
        correlations += list(r.values())
        jaw.append(r.get("jawOpen", np.nan))
    whole, mouth, head = np.concatenate(whole), np.concatenate(mouth), np.concatenate(head)
    return {
        "landmarks": (np.median(whole), np.percentile(whole, 95)),
        "mouth": (np.median(mouth), np.percentile(mouth, 95)),
        "head": (np.median(head), np.percentile(head, 95)),
        "r": (float(np.median(correlations)), float(np.nanmedian(jaw))),
        "metrics": evaluation.metrics,
        "closures": closures_against_original(reference, runs),
    }


def main(clips: list[str]) -> None:
    from eval_retarget import hand_blink_agreement

    from stages.eval.retarget import RetargetEval

    clips = [Path(c).resolve() for c in clips]
    os.chdir(ROOT)
    folders = make_copies(clips)
    runs = {condition: capture(folder) for condition, folder in folders.items()}
    params = RetargetEval.Params()
    print(f"{len(clips)} clips: {', '.join(c.stem for c in clips)}\n")
    print(
        "| condition | landmarks from the original's, median; p95 (IOD) | mouth, median; p95 | head motion from "
        "the original's, median; p95 (degrees) | blinks found / marked, "
        "false | animation r with the original's: median morph; jawOpen | lip closures: the original's found, "
        "others | mouth err, rest aligned | closures reproduced | jaw > funnel |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for condition, result in runs.items():
        c = compare(runs["original"], result)
        blinks = hand_blink_agreement(result[0], params)
        m = c["metrics"]
        print(
            f"| {condition} | {c['landmarks'][0]:.3f}; {c['landmarks'][1]:.3f} | {c['mouth'][0]:.3f}; "
            f"{c['mouth'][1]:.3f} | {c['head'][0]:.2f}; {c['head'][1]:.2f} | {blinks['found']}/{blinks['reference']}, {blinks['false']} | {c['r'][0]:.2f}; "
            f"{c['r'][1]:.2f} | {c['closures']['found']}/{c['closures']['reference']}, {c['closures']['false']} | "
            f"{m['mouth_neutral_error_iod']:.1%} | {m['closures_reproduced']:.0f}/"
            f"{m['closures']:.0f} | {m['jaw_over_funnel_fraction']:.0%} |"
        )


if __name__ == "__main__":
    if len(sys.argv) < 2:
        raise SystemExit(__doc__)
    main(sys.argv[1:])
