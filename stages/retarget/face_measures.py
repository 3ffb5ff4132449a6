"""Measures on iBUG-68 landmark shapes that keyshapes, keymorphs, the lip seal and the evaluation share: the
inter-ocular distance (outer eye corners, iBUG 36 and 45, the 300-W convention), the mouth opening and the
vertical inner-lip gap, the levelled eye line, and the performer's rest pose (the closed-mouth frames).
"""

from __future__ import annotations

import numpy as np

from stages.retarget.regions import BROWS

#: iBUG-68 polylines (point ranges; closed ones repeat their first point) for drawing shapes
IBUG68_CONTOURS: tuple[tuple[int, ...], ...] = (
    tuple(range(0, 17)),
    tuple(range(17, 22)),
    tuple(range(22, 27)),
    tuple(range(27, 31)),
    tuple(range(31, 36)),
    tuple(range(36, 42)) + (36,),
    tuple(range(42, 48)) + (42,),
    tuple(range(48, 60)) + (48,),
    tuple(range(60, 68)) + (60,),
)
OUTER_EYE_CORNERS = (36, 45)
INNER_LIP_PAIRS = ((61, 67), (62, 66), (63, 65))


def inter_ocular_distance(shapes: np.ndarray) -> np.ndarray:
    """Distance between the outer eye corners (iBUG 36, 45) of each (..., 68, 2) shape."""
    shapes = np.asarray(shapes, np.float64)
    return np.linalg.norm(shapes[..., OUTER_EYE_CORNERS[1], :] - shapes[..., OUTER_EYE_CORNERS[0], :], axis=-1)


def mouth_opening(shapes: np.ndarray) -> np.ndarray:
    """Mean gap between the inner lips (iBUG 61-67, 62-66, 63-65) of each (..., 68, 2) shape."""
    shapes = np.asarray(shapes, np.float64)
    upper = shapes[..., [a for a, _ in INNER_LIP_PAIRS], :]
    lower = shapes[..., [b for _, b in INNER_LIP_PAIRS], :]
    return np.linalg.norm(lower - upper, axis=-1).mean(axis=-1)


def mean_squared_landmark_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Mean over landmarks of the squared point distance between shapes a (..., 68, 2) and b (..., 68, 2)."""
    return ((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2).sum(axis=-1).mean(axis=-1)


def relative_rms_error(shapes: np.ndarray, reference: np.ndarray, scale: float) -> np.ndarray:
    """RMS over landmarks of the point error between two (..., 68, 2) shape sets, divided by ``scale``."""
    return np.sqrt(mean_squared_landmark_distance(shapes, reference)) / scale


def rest_frames(shapes: np.ndarray, quantile: float = 0.1) -> np.ndarray:
    """Indices of a closed-mouth rest pose: the frames whose inner-lip gap is in the lowest ``quantile``.

    The plain mean of a talking face has its mouth half open; retargeting measures deformations from a rest
    pose that matches a character's closed-mouth neutral.
    """
    gap = mouth_opening(shapes)
    count = max(1, int(np.ceil(quantile * len(gap))))
    return np.sort(np.argsort(gap, kind="stable")[:count])


def rest_shape(shapes: np.ndarray, quantile: float = 0.1) -> np.ndarray:
    """The mean shape of ``rest_frames``."""
    shapes = np.asarray(shapes, np.float64)
    return shapes[rest_frames(shapes, quantile)].mean(axis=0)


def rest_pose(
    shapes: np.ndarray, rest: np.ndarray, brow_rest: str = "closed_mouth", typical: np.ndarray | None = None
) -> np.ndarray:
    """The rest pose deformations are measured from: the mean of the closed-mouth ``rest`` frames
    (``rest_frames``) of shapes (frames, n >= 68, d); with ``brow_rest="median"`` the brows (iBUG 17-26) at their
    per-coordinate median over the ``typical`` frames instead (all frames when None).

    Closed-mouth frames are a tenth of the take, picked by the mouth alone: in 7 of 11 talking-head clips the
    brows sat higher in those frames than their median over the clip (by up to 0.011 IOD, a third of a unit of
    ICT's browDown), and a character whose brows rest there frowns through the take. The median is where the
    brows spend most of their time, which is their rest only when the take does not hold an expression
    (docs/retarget.md, "The rest pose")."""
    shapes = np.asarray(shapes, np.float64)
    out = shapes[np.asarray(rest)].mean(axis=0)
    if brow_rest == "median":
        pool = shapes if typical is None else shapes[np.asarray(typical)]
        out[list(BROWS)] = np.nanmedian(pool[:, list(BROWS)], axis=0)
    return out


def level(shapes: np.ndarray) -> np.ndarray:
    """Image landmarks (..., 68, 2) turned about their eye line's midpoint so the eye line is horizontal."""
    shapes = np.asarray(shapes, np.float64)
    eye = shapes[..., 45, :] - shapes[..., 36, :]
    angle = np.arctan2(eye[..., 1], eye[..., 0])[..., None]
    c, s = np.cos(-angle), np.sin(-angle)
    d = shapes - 0.5 * (shapes[..., 45:46, :] + shapes[..., 36:37, :])
    return np.stack([c * d[..., 0] - s * d[..., 1], s * d[..., 0] + c * d[..., 1]], axis=-1)


def lip_gap_iod(shapes: np.ndarray) -> np.ndarray:
    """Vertical inner-lip gap / inter-ocular distance of (..., 68, 2) shapes in image convention (y down), the
    eye line about level: mean over the pairs 61-67, 62-66, 63-65 of lower y minus upper y (negative when the lips
    press into each other). Vertical, because the lip seal's model of the character's gap is (stages.retarget.lips):
    at a closure the inner-lip points are a millimetre apart sideways and in depth, which a distance would count."""
    shapes = np.asarray(shapes, np.float64)
    upper = shapes[..., [a for a, _ in INNER_LIP_PAIRS], 1]
    lower = shapes[..., [b for _, b in INNER_LIP_PAIRS], 1]
    return (lower - upper).mean(axis=-1) / inter_ocular_distance(shapes)
