"""Eyes from the Face Landmarker v2's 478 points: eyelid aperture (blinks) and gaze angles, vectorised over frames.

Conventions (contract 3 of the team brief, the ARKit convention): eye index 0 is the performer's **left** eye
(ARKit ``_L``; mesh corners 263 outer / 362 inner, iris points 473-477, on the image's right for a frontal face),
index 1 the performer's right eye (corners 33 / 133, iris 468-472).

Aperture (the eye aspect ratio of Soukupova & Cech, "Real-Time Eye Blink Detection using Facial Landmarks",
CVWW 2016, with three lid pairs): the mean distance between the upper and lower lid at three points along the
eye, in the image, over the corner-to-corner distance in 3D mesh coordinates (x, y image pixels, z depth in
pixels), so that turning the head does not foreshorten the width. (The lid gap is taken in the image: the model's
depth of a closed lid's upper and lower points differs by a pixel or two, which would keep a closed eye at 0.11
instead of 0.08.) About 0.25-0.35 open, below 0.1 closed.

Gaze: the eyeball's rotation relative to the head, [yaw, pitch] in degrees; yaw > 0 turns towards the
performer's left, pitch > 0 up. In each eye's frame, built from the mesh so it turns with the head,

    x = unit vector from the eye's corner on the performer's right side to the one on the left side,
    y = the head's up direction (forehead 10 minus chin 152) made orthogonal to x,

the iris centre's offset from the midpoint of the corners, in eye widths w, is (e_x, e_y). The iris centre sits
on a sphere of radius R w about the eyeball's centre of rotation; the eye turning by yaw (about the head's up
axis) then pitch (about the turned horizontal axis) moves it by R (sin(yaw) cos(pitch), sin(pitch)) from where
it sits looking straight ahead, (rest_x, rest_y). So

    pitch = asin((e_y - rest_y) / R),   yaw = asin((e_x - rest_x) / (R cos(pitch))),

with R = ``EYEBALL_RADIUS`` (the iris centre turns about 12 mm from the centre of rotation and the eye's corners
lie about 30 mm apart; equivalently R is about one visible iris diameter, 11.7 mm). Looking straight ahead the
iris centre is not midway between the corners: it sits towards the outer corner (the inner corner reaches further
in) and above the corners' line. ``REST_OFFSET`` = (temporal, up) in eye widths, measured as the median over
frontal talking-head footage where speakers look at the camera (docs/tracking.md); the temporal direction is +x
for the left eye and -x for the right.
"""

from __future__ import annotations

import numpy as np

#: eye index -> (outer corner, inner corner, corner on the performer's right, corner on the performer's left)
EYE_CORNERS = {0: (263, 362, 362, 263), 1: (33, 133, 33, 133)}
#: eye index -> upper/lower lid vertex pairs at three points from the outer to the inner corner
LID_PAIRS = {
    0: ((387, 373), (386, 374), (385, 380)),
    1: ((160, 144), (159, 145), (158, 153)),
}
#: eye index -> the iris centre's point index in the 478-point output (rim points follow it)
IRIS_CENTRE = {0: 473, 1: 468}
FOREHEAD, CHIN = 10, 152
#: iris-centre sphere radius over the eye's corner-to-corner width
EYEBALL_RADIUS = 0.40
#: where the iris centre sits in the eye looking straight ahead: (towards the outer corner, up), in eye widths,
#: per eye pass (each model places the lid corners a little differently; bench/bench_tracking.py section 4)
REST_OFFSETS = {"landmarker_v2": (0.05, 0.075), "iris": (0.04, 0.083)}
REST_OFFSET = REST_OFFSETS["landmarker_v2"]
#: eye index -> sign of the temporal direction along the eye frame's x axis (towards the performer's left)
TEMPORAL_SIGN = {0: 1.0, 1: -1.0}


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def eye_aperture(points: np.ndarray) -> np.ndarray:
    """(frames, 2) float32 eyelid gap (image) over eye width (3D) from (frames, >= 468, 3) mesh points; [:, 0] is
    the performer's left eye."""
    p = np.asarray(points, dtype=np.float64)
    out = np.empty(p.shape[:-2] + (2,), dtype=np.float64)
    for eye in (0, 1):
        outer, inner = EYE_CORNERS[eye][:2]
        width = np.linalg.norm(p[..., outer, :] - p[..., inner, :], axis=-1)
        gaps = [np.linalg.norm(p[..., up, :2] - p[..., low, :2], axis=-1) for up, low in LID_PAIRS[eye]]
        out[..., eye] = np.mean(gaps, axis=0) / np.maximum(width, 1e-9)
    return out.astype(np.float32)


def eye_offsets(points: np.ndarray) -> np.ndarray:
    """(frames, 2, 2) iris-centre offsets (e_x, e_y) from the corners' midpoint, in eye widths, in each eye's
    frame (x towards the performer's left, y up), from (frames, 478, 3) points."""
    p = np.asarray(points, dtype=np.float64)
    up = p[..., FOREHEAD, :] - p[..., CHIN, :]
    up = up * np.array([1.0, -1.0, -1.0])  # image y and the model's z point down and away: make y up
    out = np.empty(p.shape[:-2] + (2, 2), dtype=np.float64)
    for eye in (0, 1):
        outer, inner, right_side, left_side = EYE_CORNERS[eye]
        flip = np.array([1.0, -1.0, -1.0])
        a, b = p[..., right_side, :] * flip, p[..., left_side, :] * flip
        width = np.linalg.norm(b - a, axis=-1)
        x = _unit(b - a)
        y = _unit(up - np.sum(up * x, axis=-1, keepdims=True) * x)
        d = p[..., IRIS_CENTRE[eye], :] * flip - (a + b) / 2
        out[..., eye, 0] = np.sum(d * x, axis=-1) / np.maximum(width, 1e-9)
        out[..., eye, 1] = np.sum(d * y, axis=-1) / np.maximum(width, 1e-9)
    return out


def rest_offsets(rest: tuple[float, float] = REST_OFFSET) -> np.ndarray:
    """(2, 2) rest position (e_x, e_y) of each eye's iris centre from the (temporal, up) offset."""
    return np.array([[TEMPORAL_SIGN[eye] * rest[0], rest[1]] for eye in (0, 1)])


def offsets_to_angles(e: np.ndarray, radius: float = EYEBALL_RADIUS, rest=REST_OFFSET) -> np.ndarray:
    """(..., 2, 2) iris offsets (e_x, e_y) to [yaw, pitch] degrees (module docstring)."""
    d = (np.asarray(e, dtype=np.float64) - rest_offsets(rest)) / radius
    pitch = np.arcsin(np.clip(d[..., 1], -1.0, 1.0))
    yaw = np.arcsin(np.clip(d[..., 0] / np.maximum(np.cos(pitch), 1e-6), -1.0, 1.0))
    return np.degrees(np.stack([yaw, pitch], axis=-1))


def angles_to_offsets(angles: np.ndarray, radius: float = EYEBALL_RADIUS, rest=REST_OFFSET) -> np.ndarray:
    """(..., 2, 2) iris offsets (e_x, e_y) from [yaw, pitch] degrees: the inverse of ``offsets_to_angles`` (for
    offsets within the sphere), e = rest + R (sin(yaw) cos(pitch), sin(pitch))."""
    yaw, pitch = np.radians(np.asarray(angles, dtype=np.float64)).swapaxes(0, -1)
    moved = np.stack([np.sin(yaw) * np.cos(pitch), np.sin(pitch)]).swapaxes(0, -1)
    return rest_offsets(rest) + radius * moved


def gaze_angles(points: np.ndarray, radius: float = EYEBALL_RADIUS, rest=REST_OFFSET) -> np.ndarray:
    """(frames, 2, 2) float32 degrees: [eye (0 left, 1 right)][yaw, pitch] of each eyeball relative to the head
    from (frames, 478, 3) points (yaw > 0 towards the performer's left, pitch > 0 up)."""
    return offsets_to_angles(eye_offsets(points), radius, rest).astype(np.float32)


def detect_blinks(
    aperture: np.ndarray, valid: np.ndarray | None = None, closed_fraction: float = 0.5, bridge: int = 1
) -> list[tuple[int, int]]:
    """Blinks as [start, stop) frame ranges: runs of frames where both eyes' mean aperture is below
    ``closed_fraction`` x its median over the valid frames (the open level), runs ``bridge`` frames apart or
    less joined. Frames not ``valid`` never start a blink."""
    a = np.asarray(aperture, dtype=np.float64)
    a = a.mean(axis=-1) if a.ndim == 2 else a
    ok = np.ones(len(a), dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    if not ok.any():
        return []
    closed = (a < closed_fraction * np.median(a[ok])) & ok
    edges = np.diff(np.concatenate([[0], closed.astype(np.int8), [0]]))
    runs = list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)))
    merged: list[tuple[int, int]] = []
    for start, stop in runs:
        if merged and start - merged[-1][1] <= bridge:
            merged[-1] = (merged[-1][0], int(stop))
        else:
            merged.append((int(start), int(stop)))
    return merged
