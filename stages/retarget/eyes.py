"""Eyes (issue 13.3, retarget side): blinks from the performer's eyelid aperture, gaze into eyeLook morphs.

Blinks are too brief for keyshapes (PCA extremes of a take rarely land on one), so the blend drives the blink morphs
from tracking directly:

- the performer's closure c(t) = clip(1 - a(t) / a_open, 0, 1) per eye, a(t) the aperture (lid gap / eye width:
  tracking ``eye_aperture``, or the same ratio from the 68 landmarks) and a_open its 90th percentile over the take;
- the character's eye is to be open by the same fraction of its neutral opening, 1 - c(t), all its morphs
  together: the expression's squint, a lowered brow and the blink. With its other morphs applied the eye is open
  R(t) = A_others(t) / A(0) (landmark vertices, front view); the blink morph supplies the rest of the closure,
  1 - A(w) / A(0) = max(0, R(t) - (1 - c(t))), A(w) its own aperture under blink weight w (sampled on [0, 1],
  made monotone and inverted by interpolation). The blink morph follows the aperture alone, replacing what the
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


def closure(aperture: np.ndarray, sequence: np.ndarray, open_quantile: float = 0.9) -> np.ndarray:
    """c(t) per eye (frames, 2): how far each eye is from its open aperture in its take, 0 open .. 1 shut."""
    aperture = np.asarray(aperture, np.float64)
    out = np.zeros_like(aperture)
    for take in np.unique(sequence):
        rows = sequence == take
        opened = np.quantile(aperture[rows], open_quantile, axis=0)
        out[rows] = np.clip(1.0 - aperture[rows] / np.maximum(opened, 1e-9), 0.0, 1.0)
    return out


def blink_curve(
    rest_landmarks: np.ndarray, blink_deltas: np.ndarray, samples: int = 21
) -> tuple[np.ndarray, np.ndarray]:
    """The character's aperture of one eye against its blink weight: weights (samples,), apertures relative to
    the open eye (samples,), made monotone so it can be inverted. ``blink_deltas`` (68, 3) at the landmarks."""
    w = np.linspace(0.0, 1.0, samples)
    shapes = np.asarray(rest_landmarks, np.float64)[None] + w[:, None, None] * np.asarray(blink_deltas)[None]
    aperture = eye_aperture_2d(shapes)
    side = int(np.argmax(np.abs(aperture[-1] - aperture[0])))  # the eye this morph closes
    relative = aperture[:, side] / max(aperture[0, side], 1e-12)
    return w, np.minimum.accumulate(relative)


def blink_weights(closure_of_eye: np.ndarray, curve: tuple[np.ndarray, np.ndarray], others=None) -> np.ndarray:
    """Blink weight w with 1 - A(w)/A(0) = max(0, R - (1 - c)): the closure the other morphs leave to the blink;
    ``others`` R, the eye's relative opening with the other morphs applied (1 when None)."""
    w, relative = curve
    closure_of_eye = np.asarray(closure_of_eye, np.float64)
    others = np.ones_like(closure_of_eye) if others is None else np.asarray(others, np.float64)
    needed = np.maximum(others - (1.0 - closure_of_eye), 0.0)
    # np.interp needs increasing x: the relative aperture falls with the weight
    return np.interp(-(1.0 - needed), -relative, w)


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
