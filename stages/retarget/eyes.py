"""Eyes (issue 13.3, retarget side): blinks from the performer's eyelid aperture, gaze into eyeLook morphs.

Blinks are too brief for keyshapes (PCA extremes of a take rarely land on one), so the blend drives the blink morphs
from tracking directly:

- the performer's closure c(t) = clip(1 - a(t) / a_open, 0, 1) per eye, a(t) the aperture (lid gap / eye width:
  tracking ``eye_aperture``, or the same ratio from the 68 landmarks) and a_open its 90th percentile over the take;
- the character's eye is to be open by the same fraction of its neutral opening A(0), 1 - c(t), all its morphs
  together: the expression's squint, a lowered or raised brow, the gaze (ICT's eyeLook morphs move the lids with
  the eyes, so the gaze morphs are set first) and the blink. The blink weight w solves
  A(u_others + w e_blink) = A(0) (1 - c(t)) per frame and eye (A: the eye's aperture on the landmark vertices,
  front view; bisection on [0, 1], the aperture falling as w grows); 0 where the other morphs already close the
  eye that far. The blink morph follows the aperture alone, replacing what the
  keymorphs gave it: the keyshape decomposition of the eye region already follows the lids part of the way, so
  adding the two would close the character's eyes twice for every dip of the performer's.

Gaze (tracking ``gaze``, degrees, [eye][yaw, pitch]; yaw > 0 towards the performer's left, pitch > 0 up) goes into
the ARKit-style eyeLook morphs: for the left eye, yaw > 0 looks out (away from the nose), for the right eye in;
weight = angle / ``full_degrees`` (the gaze angle that ARKit's weight 1 stands for; a character's eyeLook morphs
often move only the lids and skin, its eyeballs turning by joints: the blend's ``gaze`` output), clipped to 1.
"""

from __future__ import annotations

import numpy as np

from stages.retarget.regions import LEFT_EYE, RIGHT_EYE, find_side_morph

#: ARKit side suffixes: index 0 = the performer's left eye
SIDES = ("L", "R")


def eye_aperture_2d(shapes: np.ndarray) -> np.ndarray:
    """(frames, 2) lid gap / eye-corner distance of iBUG shapes (..., 68, >= 2), x and y only; 0 = left eye."""
    shapes = np.asarray(shapes, np.float64)[..., :2]

    def one(eye):
        c0, u1, u2, c1, l2, l1 = eye
        gap = np.linalg.norm(shapes[..., u1, :] - shapes[..., l1, :], axis=-1)
        gap = gap + np.linalg.norm(shapes[..., u2, :] - shapes[..., l2, :], axis=-1)
        return 0.5 * gap / np.linalg.norm(shapes[..., c1, :] - shapes[..., c0, :], axis=-1)

    return np.stack([one(LEFT_EYE), one(RIGHT_EYE)], axis=-1)


def open_level(aperture: np.ndarray, sequence: np.ndarray, open_quantile: float = 0.9) -> np.ndarray:
    """Each frame's open aperture (frames, 2): its take's 90th percentile, per eye."""
    aperture = np.asarray(aperture, np.float64)
    out = np.zeros_like(aperture)
    for take in np.unique(sequence):
        rows = sequence == take
        out[rows] = np.quantile(aperture[rows], open_quantile, axis=0)
    return out


def closure(aperture: np.ndarray, sequence: np.ndarray, open_quantile: float = 0.9) -> np.ndarray:
    """c(t) per eye (frames, 2): how far each eye is from its open aperture in its take, 0 open .. 1 shut."""
    aperture = np.asarray(aperture, np.float64)
    opened = open_level(aperture, sequence, open_quantile)
    return np.clip(1.0 - aperture / np.maximum(opened, 1e-9), 0.0, 1.0)


def blink_for_aperture(
    rest: np.ndarray, others: np.ndarray, blink: np.ndarray, eye: int, target: np.ndarray, iterations: int = 30
) -> np.ndarray:
    """Blink weights w (frames,) with the eye's aperture of rest + others + w blink equal to ``target`` (frames,)
    (bisection on [0, 1]): ``rest`` (68, 3) landmark vertices, ``others`` (frames, 68, 3) the other morphs' motion,
    ``blink`` (68, 3) the blink morph's, ``eye`` 0 = left."""
    base = np.asarray(rest, np.float64)[None] + np.asarray(others, np.float64)
    blink = np.asarray(blink, np.float64)
    target = np.asarray(target, np.float64)

    def aperture(w):
        return eye_aperture_2d(base + w[:, None, None] * blink[None])[:, eye]

    lo, hi = np.zeros(len(base)), np.ones(len(base))
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        too_open = aperture(mid) > target
        lo, hi = np.where(too_open, mid, lo), np.where(too_open, hi, mid)
    return np.where(aperture(np.zeros(len(base))) <= target, 0.0, hi)


def gaze_morphs(names: list[str]) -> dict[tuple[int, str], int]:
    """(eye, direction) -> morph index for the eyeLook{In,Out,Up,Down}_{L,R} morphs the character has."""
    out = {}
    for eye, side in enumerate(SIDES):
        for direction in ("In", "Out", "Up", "Down"):
            index = find_side_morph(names, f"eyeLook{direction}", side)
            if index is not None:
                out[(eye, direction)] = index
    return out


def gaze_weights(gaze: np.ndarray, morphs: dict[tuple[int, str], int], full_degrees: float, count: int):
    """Morph weights (frames, count) from gaze (frames, 2, 2) degrees; weight 1 at ``full_degrees``."""
    gaze = np.asarray(gaze, np.float64)
    out = np.zeros((len(gaze), count))
    for (eye, direction), m in morphs.items():
        yaw, pitch = gaze[:, eye, 0], gaze[:, eye, 1]
        # yaw > 0 turns both eyes towards the performer's left: out for the left eye, in for the right
        toward = {"Out": yaw if eye == 0 else -yaw, "In": -yaw if eye == 0 else yaw, "Up": pitch, "Down": -pitch}
        out[:, m] = np.clip(toward[direction] / full_degrees, 0.0, 1.0)
    return out
