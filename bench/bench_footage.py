"""Tracking on footage that is not a studio close-up, made from an embedded CREMA-D take with known answers:
a phone's portrait video (stored turned, with a display matrix; and turned and mirrored), medium and wide shots
(the take pasted small into a 1280 x 720 frame), two performers with a blank moment, and a variable frame rate
(frames dropped, timestamps kept). Each is tracked with FaceMesh and compared with the take's own close-up.

    python bench/bench_footage.py            # from the project root; about a minute

Prints one row per variant: frames with a face, the landmarks' median distance from the close-up's (mapped back
into the close-up's pixels, in inter-ocular distances; not for the two performers, where the tracker starts with
whichever it is most certain of and must keep it), the mean head roll, and what else the variant checks.
"""

from __future__ import annotations

import sys
import tempfile
from fractions import Fraction
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's msflow and stages, whichever one pip installed
TAKE = ROOT / "data" / "crema-d" / "1001_DFA_HAP_XX.flv"
OTHER = ROOT / "data" / "crema-d" / "1001_DFA_ANG_XX.flv"
WIDE = (720, 1280)
AT = (700, 400)  # where a small take is pasted (x, y)
DROPPED = (10, 11, 12, 25, 26, 40)


def frames_of(path: Path) -> tuple[list[np.ndarray], np.ndarray]:
    """BGR frames and their times (seconds from the first)."""
    from stages.tracking.video import iter_frames

    times, frames = zip(*iter_frames(path))
    return list(frames), np.array(times)


def write(path: Path, frames, times=None, display=None) -> Path:
    """H.264 (lossless-ish, crf 10) MP4 of BGR frames, at 30 fps or at ``times``, with an optional display matrix."""
    import av

    with av.open(str(path), "w") as out:
        stream = out.add_stream("libx264", rate=30)
        stream.height, stream.width = frames[0].shape[:2]
        stream.pix_fmt = "yuv420p"
        stream.options = {"crf": "10"}
        stream.codec_context.time_base = Fraction(1, 1000)
        if display is not None:
            stream.set_display_matrix(list(display))
        for i, frame in enumerate(frames):
            picture = av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="bgr24")
            picture.pts = int(round((times[i] if times is not None else i / 30.0) * 1000))
            picture.time_base = Fraction(1, 1000)
            for packet in stream.encode(picture):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    return path


def pasted(frames, scale: float, others=None, blank=()) -> list[np.ndarray]:
    """The frames at ``scale`` in a 1280 x 720 grey picture (and ``others`` beside them), ``blank`` frames empty."""
    import cv2

    out = []
    for i, frame in enumerate(frames):
        canvas = np.full((*WIDE, 3), 90, np.uint8)
        if i not in blank:
            small = cv2.resize(frame, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
            canvas[AT[1] : AT[1] + small.shape[0], AT[0] - 600 * (others is not None) :][:, : small.shape[1]] = small
            if others is not None:
                other = cv2.resize(others[i], None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
                canvas[AT[1] : AT[1] + other.shape[0], AT[0] : AT[0] + other.shape[1]] = other
        out.append(canvas)
    return out


def variants(work: Path) -> dict[str, tuple[Path, object]]:
    """label -> (video, how its landmarks map back to the close-up's pixels)."""
    from stages.tracking.display import display_matrix, stored_picture

    frames, times = frames_of(TAKE)
    n = len(frames)
    out = {"close-up": (write(work / "close.mp4", frames), lambda p: p)}
    for label, matrix in {
        "portrait (display 90)": display_matrix(90),
        "portrait, mirrored (270)": display_matrix(270, hflip=True),
    }.items():
        stored = [stored_picture(f, matrix) for f in frames]  # what the matrix shows upright
        out[label] = (write(work / f"{len(out)}.mp4", stored, display=matrix), lambda p: p)
    for scale in (0.5, 0.3, 0.2):
        path = write(work / f"wide{scale}.mp4", pasted(frames, scale))
        out[f"wide shot, {scale:g} size"] = (path, lambda p, s=scale: (p - AT) / s)
    others, _ = frames_of(OTHER)
    two = pasted(frames[:n], 0.5, others[:n], blank=range(20, 25))
    out["two performers, 5 blank frames"] = (write(work / "two.mp4", two), lambda p: p)
    kept = [i for i in range(n) if i not in DROPPED]
    vfr = write(work / "vfr.mp4", [frames[i] for i in kept], times=times[kept])
    out["variable frame rate (6 dropped)"] = (vfr, kept)
    return out


def main() -> None:
    from msflow.testing import run_stage
    from stages.export.timeline import frame_clock, nominal_rate
    from stages.geometry.rotations import quat_to_euler
    from stages.tracking import FaceMesh

    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        cases = variants(work)
        videos = {label: path for label, (path, _) in cases.items()}
        run = run_stage(FaceMesh, {"audio": "none"}, {"videos": videos}, store=work / "store")
    labels, sequence = run.meta["labels"], run.arrays["sequence"]
    rows = {label: np.flatnonzero(sequence == labels.index(label)) for label in cases}
    landmarks, valid = run.arrays["landmarks"], run.arrays["valid"]
    close = landmarks[rows["close-up"]]
    iod = float(np.linalg.norm(close[:, 45] - close[:, 36], axis=-1).mean())
    roll = np.degrees(quat_to_euler(run.arrays["rotation"]))[:, 2]
    print("| footage | frames with a face | landmarks from the close-up's (median, IOD) | head roll ° | also |")
    print("|---|---|---|---|---|")
    for label, (_, back) in cases.items():
        r = rows[label]
        also = ""
        if isinstance(back, list):  # the variable frame rate: its frames are the close-up's kept ones
            error = np.linalg.norm(landmarks[r] - close[back], axis=-1)
            fps = run.meta["fps"][labels.index(label)]
            clock = frame_clock(run.arrays["time"][r], fps)
            off = np.abs(run.arrays["time"][r] - run.arrays["time"][r][0] - np.arange(len(r)) / fps).max() * 1000
            rate = "-" if clock is None else f"{nominal_rate(clock, label):g}"
            also = f"average {fps:.2f} fps, rows up to {off:.0f} ms off their times; exported at {rate} fps by time"
        else:
            shown = valid[r]
            error = np.linalg.norm(back(landmarks[r][shown]) - close[shown], axis=-1)
            if label.startswith("two"):  # whichever performer it starts with (the most certain), it must keep
                error = np.full(1, np.nan)
                nose = landmarks[r][:, 30, 0]
                side = "the same performer" if abs(nose[25:].mean() - nose[:20].mean()) < 100 else "ANOTHER performer"
                also = f"after the gap: {side}, found on frame {np.flatnonzero(valid[r][20:])[0] + 20}"
        distance = "-" if np.isnan(error).all() else f"{np.median(error) / iod:.3f}"
        print(f"| {label} | {int(valid[r].sum())} / {len(r)} | {distance} | {roll[r][valid[r]].mean():+.1f} | {also} |")


if __name__ == "__main__":
    main()
