"""Figures for inspecting a tracking artifact: a landmark contact sheet and head-pose curves."""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: iBUG parts drawn in different colours (BGR)
PART_COLOURS = (
    (range(0, 17), (255, 200, 0)),
    (range(17, 27), (0, 200, 255)),
    (range(27, 36), (0, 255, 0)),
    (range(36, 48), (255, 0, 255)),
    (range(48, 68), (0, 0, 255)),
)


def draw_landmarks(image: np.ndarray, points: np.ndarray, radius: int = 2) -> np.ndarray:
    """A BGR copy of ``image`` with the 68 points drawn, one colour per face part."""
    import cv2

    out = image.copy() if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    for part, colour in PART_COLOURS:
        for i in part:
            x, y = points[i]
            if np.isfinite(x) and np.isfinite(y):
                cv2.circle(out, (int(round(x * 4)), int(round(y * 4))), radius * 4, colour, -1, cv2.LINE_AA, shift=2)
    return out


def face_thumbnail(
    frame: np.ndarray, points: np.ndarray, size: int = 200, margin: float = 0.35, radius: int = 2
) -> np.ndarray:
    """Square close-up of the face (landmark box plus margin) scaled to ``size`` with the points drawn."""
    import cv2

    lo, hi = np.nanmin(points, axis=0), np.nanmax(points, axis=0)
    side = max(hi - lo) * (1 + 2 * margin)
    centre = (lo + hi) / 2
    scale = size / side
    m = np.array([[scale, 0, size / 2 - scale * centre[0]], [0, scale, size / 2 - scale * centre[1]]])
    frame = frame if frame.ndim == 3 else cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
    thumb = cv2.warpAffine(frame, m, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    return draw_landmarks(thumb, points * scale + m[:, 2], radius)


def contact_sheet(
    frames: list[np.ndarray],
    points: list[np.ndarray],
    captions: list[str],
    *,
    columns: int = 7,
    size: int = 200,
    valid: list[bool] | None = None,
    groups: list[int] | None = None,
) -> np.ndarray:
    """Grid of face thumbnails (BGR image); each group (sequence) starts a new row; interpolated frames
    (``valid`` False) get a red caption."""
    import cv2

    groups = [0] * len(frames) if groups is None else list(groups)
    cells: list[tuple[int, int]] = []
    row, col, last = 0, 0, None
    for g in groups:
        if last is not None and (g != last or col == columns):
            row, col = row + 1, 0
        cells.append((row, col))
        col, last = col + 1, g
    if not frames:
        return np.zeros((size, size, 3), np.uint8)
    width = max(c for _, c in cells) + 1
    sheet = np.full(((row + 1) * size, width * size, 3), 32, np.uint8)
    for i, (frame, pts, caption) in enumerate(zip(frames, points, captions)):
        t = face_thumbnail(frame, pts, size)
        ok = valid is None or valid[i]
        cv2.rectangle(t, (0, 0), (size - 1, 18), (0, 0, 0), -1)
        cv2.putText(
            t, caption, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 255) if ok else (0, 0, 255), 1, cv2.LINE_AA
        )
        r, c = cells[i]
        sheet[r * size : (r + 1) * size, c * size : (c + 1) * size] = t
    return sheet


def png_bytes(image: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise ValueError("PNG encoding failed")
    return buf.tobytes()


def _video_paths(inputs: dict | None) -> dict:
    videos = (inputs or {}).get("videos") or {}
    return {str(k): Path(v) for k, v in videos.items()}


def contact_sheet_png(
    view, inputs: dict | None = None, *, every: int = 10, columns: int = 7, size: int = 200, most: int = 28
) -> bytes:
    """PNG contact sheet of a tracking artifact: every ``every``-th frame of each sequence (fewer on long takes:
    at most ``most`` per sequence, evenly spaced) with its 68 points, drawn on the video frame when the video is
    among ``inputs['videos']``, else on the stored face crop."""
    from stages.tracking.video import iter_frames

    labels = list(view.meta.get("labels", []))
    landmarks, sequence, valid = view["landmarks"], view["sequence"], view["valid"]
    videos = _video_paths(inputs)
    frames, points, captions, flags, groups = [], [], [], [], []
    for s, label in enumerate(labels):
        rows = np.flatnonzero(sequence == s)
        wanted = set(range(0, len(rows), max(every, -(-len(rows) // most))))
        if label in videos and videos[label].is_file():
            for i, (_, frame) in enumerate(iter_frames(videos[label])):
                if i in wanted:
                    frames.append(frame)
                    points.append(landmarks[rows[i]])
                    captions.append(f"{label} #{i}")
                    flags.append(bool(valid[rows[i]]))
                    groups.append(s)
        elif "crops" in view and view["crops"].size:
            crops, crop_points = view["crops"], view["crop_landmarks"]
            for i in sorted(wanted):
                frames.append(crops[rows[i]])
                points.append(crop_points[rows[i]])
                captions.append(f"{label} #{i}")
                flags.append(bool(valid[rows[i]]))
                groups.append(s)
    return png_bytes(contact_sheet(frames, points, captions, columns=columns, size=size, valid=flags, groups=groups))


def head_pose_figure(view, inputs: dict | None = None):
    """Yaw, pitch and roll (degrees) over time, one line per sequence."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from stages.geometry.rotations import quat_to_euler

    euler = np.degrees(quat_to_euler(view["rotation"]))
    time, sequence = view["time"], view["sequence"]
    fig, axes = plt.subplots(3, 1, figsize=(8, 6), sharex=True)
    for s, label in enumerate(view.meta.get("labels", [])):
        rows = sequence == s
        for ax, k in zip(axes, range(3)):
            ax.plot(time[rows], euler[rows, k], label=label)
    for ax, name in zip(axes, ("yaw", "pitch", "roll")):
        ax.set_ylabel(f"{name} (deg)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, ncol=4)
    axes[-1].set_xlabel("time (s)")
    fig.suptitle("Head pose (solvePnP against the ICT FaceKit landmarks)")
    fig.tight_layout()
    return fig


def confidence_figure(view, inputs: dict | None = None):
    """Tracking confidence per frame and the nose-bridge step between consecutive frames."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    time, sequence = view["time"], view["sequence"]
    nose = view["landmarks"][:, 27]
    fig, axes = plt.subplots(2, 1, figsize=(8, 4.5), sharex=True)
    for s, label in enumerate(view.meta.get("labels", [])):
        rows = np.flatnonzero(sequence == s)
        axes[0].plot(time[rows], view["confidence"][rows], label=label)
        step = np.linalg.norm(np.diff(nose[rows], axis=0), axis=1)
        axes[1].plot(time[rows][1:], step, label=label)
    axes[0].set_ylabel("confidence")
    axes[1].set_ylabel("nose-bridge step (px)")
    axes[1].set_xlabel("time (s)")
    axes[0].legend(fontsize=8, ncol=4)
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def eyes_figure(view, inputs: dict | None = None):
    """Eyelid aperture (blinks found shaded) and gaze yaw/pitch of each eye over time, one panel column per
    sequence (Face Landmarker v2 artifacts; a note otherwise)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from stages.tracking.eyes import detect_blinks

    labels = list(view.meta.get("labels", []))
    if "eye_aperture" not in view:
        fig, ax = plt.subplots(figsize=(6, 1.2))
        ax.axis("off")
        ax.text(0.5, 0.5, "no eye outputs: the landmark model was face_mesh_v1", ha="center", va="center")
        return fig
    time, sequence = view["time"], view["sequence"]
    aperture, gaze, valid = view["eye_aperture"], view["gaze"], view["valid"]
    fig, axes = plt.subplots(3, max(len(labels), 1), figsize=(4 * max(len(labels), 1), 6), sharey="row", squeeze=False)
    for s, label in enumerate(labels):
        rows = np.flatnonzero(sequence == s)
        t = time[rows]
        ax = axes[0, s]
        for eye, name in ((0, "left"), (1, "right")):
            ax.plot(t, aperture[rows, eye], label=name)
            axes[1, s].plot(t, gaze[rows, eye, 0], label=name)
            axes[2, s].plot(t, gaze[rows, eye, 1], label=name)
        for a, b in detect_blinks(aperture[rows], valid[rows]):
            ax.axvspan(t[a], t[b - 1], color="0.85")
        ax.set_title(label, fontsize=9)
    axes[0, 0].set_ylabel("eye aperture")
    axes[1, 0].set_ylabel("gaze yaw (deg)")
    axes[2, 0].set_ylabel("gaze pitch (deg)")
    axes[0, 0].legend(fontsize=8)
    for ax in axes.ravel():
        ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    fig.suptitle("Eyes (blinks found shaded; yaw > 0 towards the performer's left, pitch > 0 up)")
    fig.tight_layout()
    return fig


FIGURES = {
    "contact_sheet": contact_sheet_png,
    "head_pose": head_pose_figure,
    "confidence": confidence_figure,
    "eyes": eyes_figure,
}
