"""Face crops: each frame warped by a similarity transform to a square, eyes level at a fixed distance.

The transform maps the midpoints of the two eyes' corners (iBUG 36/39 and 42/45; corners move less than lids
during blinks) to fixed positions in a ``crop_size`` square: level, ``eye_distance`` x crop_size apart, at height
``eye_height`` x crop_size. Downstream texture models (the paper's AAM appearance, Sec. 3.1) sample these
crops with ``crop_landmarks`` and never reread the video.
"""

from __future__ import annotations

import numpy as np

from stages.tracking.landmarks68 import LEFT_EYE, RIGHT_EYE


def eye_centres(landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 2) centres of the subject's right and left eye: midpoint of each eye's two corners."""
    lm = np.asarray(landmarks, dtype=np.float64)
    right = (lm[..., RIGHT_EYE[0], :] + lm[..., RIGHT_EYE[3], :]) / 2
    left = (lm[..., LEFT_EYE[0], :] + lm[..., LEFT_EYE[3], :]) / 2
    return right, left


def similarity_transforms(
    landmarks: np.ndarray, crop_size: int = 128, eye_distance: float = 0.30, eye_height: float = 0.33
) -> np.ndarray:
    """(frames, 2, 3) similarity transforms mapping image pixels to crop pixels (vectorised over frames).

    The subject's right eye (image left) lands at ((1 - eye_distance) / 2, eye_height) x crop_size and the left
    eye at ((1 + eye_distance) / 2, eye_height) x crop_size.
    """
    right, left = eye_centres(landmarks)
    d = left - right
    dist = np.linalg.norm(d, axis=-1)
    scale = eye_distance * crop_size / np.maximum(dist, 1e-9)
    cos, sin = d[..., 0] / np.maximum(dist, 1e-9), d[..., 1] / np.maximum(dist, 1e-9)
    # rotate by -angle and scale: [[c, s], [-s, c]] * scale
    a = np.stack([np.stack([cos, sin], -1), np.stack([-sin, cos], -1)], -2) * scale[..., None, None]
    mid = (right + left) / 2
    target = np.array([crop_size / 2.0, eye_height * crop_size])
    offset = target - np.einsum("...ij,...j->...i", a, mid)
    return np.concatenate([a, offset[..., None]], axis=-1)


def similarity_transform(
    landmarks: np.ndarray, crop_size: int = 128, eye_distance: float = 0.30, eye_height: float = 0.33
) -> np.ndarray:
    """One frame's (2, 3) transform; the same numbers as ``similarity_transforms`` with scalar arithmetic
    (the per-frame path while a video streams, where numpy's per-call overhead dominates)."""
    lm = landmarks
    rx = (lm[RIGHT_EYE[0], 0] + lm[RIGHT_EYE[3], 0]) / 2
    ry = (lm[RIGHT_EYE[0], 1] + lm[RIGHT_EYE[3], 1]) / 2
    lx = (lm[LEFT_EYE[0], 0] + lm[LEFT_EYE[3], 0]) / 2
    ly = (lm[LEFT_EYE[0], 1] + lm[LEFT_EYE[3], 1]) / 2
    dx, dy = float(lx - rx), float(ly - ry)
    dist = max((dx * dx + dy * dy) ** 0.5, 1e-9)
    scale = eye_distance * crop_size / dist
    c, s = dx / dist * scale, dy / dist * scale
    mx, my = float(rx + lx) / 2, float(ry + ly) / 2
    return np.array([[c, s, crop_size / 2.0 - (c * mx + s * my)], [-s, c, eye_height * crop_size - (-s * mx + c * my)]])


def apply_transforms(points: np.ndarray, transforms: np.ndarray) -> np.ndarray:
    """(frames, n, 2) points mapped by per-frame (frames, 2, 3) affine transforms."""
    return np.einsum("fij,fnj->fni", transforms[..., :2], points) + transforms[:, None, :, 2]


def warp_crop(gray: np.ndarray, transform: np.ndarray, crop_size: int) -> np.ndarray:
    """One grayscale crop (crop_size, crop_size) uint8; outside the frame repeats the border."""
    import cv2

    return cv2.warpAffine(
        gray, transform, (crop_size, crop_size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )


def to_gray(frame: np.ndarray) -> np.ndarray:
    import cv2

    return frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
