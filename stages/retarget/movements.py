"""Did the performer make the movement an ARKit column stands for? Movement probes on the tracked face.

A morph channel that never moves is only a fault where the performer made that movement. Each ARKit column gets a
*probe*: a per-frame measure, on the performer's tracked face in the head's frame (3D FaceMesh shapes, pose
removed, inter-ocular distance (IOD) units; x towards the performer's left, y up, z towards the viewer), of the
movement the column names, positive in its direction:

- landmark probes are displacements in IOD from the take's rest: the mean of its closed-mouth frames, the rest
  the capture keyshapes measure their deformations from, so what the probe calls a movement is what the
  retarget sees as one (lip press: from the lips' usual height when closed). Speech is dominated by the jaw:
  opening it also lowers the lip corners, pulls the chin back and narrows the mouth. A probe marked ``jaw-free``
  is the part of its measure that the jaw opening does not explain: its least-squares regression on the chin drop
  over the take is taken out, so a dropped jaw is not read as a frown or a pucker;
- eyelids (blink): the eye's closure from the tracking's ``eye_aperture`` (1 - aperture / open aperture); gaze
  (eyeLook*): the eye's turn from the take's median direction, degrees (the tracking's ``gaze``).

A probe *moved* in a take when it stays above its level for ``frames`` frames in a row (default 3, 0.1 s: one
noisy frame is no movement) and that level is at least ``noise`` times its own frame-to-frame jitter (a robust
standard deviation of its first differences). Levels: ``landmark_level`` IOD (default 0.02: 2% of the eye
distance, about 1.3 mm on an adult face; half that for the eyelids and the skin below them, ``FINE_MOVEMENTS``),
``closure_level`` of the eye's opening, ``gaze_level`` degrees.
``column_probes`` lists the columns; ``MOVEMENT_TABLE`` says how each is measured (docs/retarget.md).
A column without a probe (the tongue: no tracker here sees it) is *not measurable* and reported as such.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import numpy as np

#: ARKit column -> how the probe measures it (documentation; the code is ``landmark_probes``)
MOVEMENT_TABLE: dict[str, str] = {
    "EyeBlink": "eye closure 1 - aperture / open aperture (tracking eye_aperture), per eye",
    "EyeLookUp": "gaze pitch up from the take's median, degrees",
    "EyeLookDown": "gaze pitch down from the take's median, degrees",
    "EyeLookIn": "gaze yaw towards the nose from the take's median, degrees",
    "EyeLookOut": "gaze yaw away from the nose from the take's median, degrees",
    "EyeSquint": "lower lid (iBUG 46-47 / 40-41) up, relative to the eye corners",
    "EyeWide": "upper lid (iBUG 43-44 / 37-38) up, relative to the eye corners",
    "JawOpen": "chin (iBUG 8) down",
    "JawForward": "chin forward, jaw-free (the chin moves back as the jaw opens)",
    "JawLeft": "chin sideways towards the performer's left",
    "JawRight": "chin sideways towards the performer's right",
    "MouthClose": "chin down beyond the lips' own gap while they are closed (gap < closure gap)",
    "MouthFunnel": "lip centre (iBUG 50-52, 56-58) forward while the lips are apart, jaw-free",
    "MouthPucker": "mouth width (iBUG 48-54) narrower, jaw-free",
    "MouthLeft": "lips sideways towards the performer's left, beyond the chin's own sideways shift",
    "MouthRight": "lips sideways towards the performer's right, beyond the chin's",
    "MouthSmile": "lip corner (iBUG 54 / 48) up, jaw-free",
    "MouthFrown": "lip corner down, jaw-free",
    "MouthDimple": "lip corner back (depth) beyond what its rise explains, jaw-free",
    "MouthStretch": "lip corner outwards beyond what its rise explains, jaw-free",
    "MouthRollLower": "lower red lip thinner (iBUG 57 to 66)",
    "MouthRollUpper": "upper red lip thinner (iBUG 51 to 62)",
    "MouthShrugLower": "chin up above its closed-mouth rest (chin raiser)",
    "MouthShrugUpper": "upper lip centre (iBUG 51) up, jaw-free",
    "MouthPress": "lips closed and the lip height at that side (iBUG 52-56 / 50-58) below its usual closed height",
    "MouthLowerDown": "lower lip at that side (iBUG 56 / 58) down, jaw-free",
    "MouthUpperUp": "upper lip at that side (iBUG 52 / 50) up, jaw-free",
    "BrowDown": "brow (iBUG 22-26 / 17-21) down and towards the nose (a frown draws the brows together)",
    "BrowInnerUp": "inner brow ends (iBUG 21, 22) up",
    "BrowOuterUp": "outer brow end (iBUG 26 / 17) up",
    "CheekPuff": "both mid-cheeks (FaceMesh 411, 425, 376 / 187, 205, 147) outwards and forward beyond what the "
    "corner's rise explains (a smile bulges them too), jaw-free",
    "CheekSquint": "the skin below the lower lid (FaceMesh 346, 347, 330 / 117, 118, 101) up beyond what the lip "
    "corner's rise lifts it (SMILE_CHEEK_LIFT), jaw-free",
    "NoseSneer": "nostril wing (iBUG 35 / 31) up, jaw-free",
}

#: per side: mouth corner, upper-lip side, lower-lip side, eye corners, upper lid, lower lid, brow, outer brow,
#: nostril wing (iBUG); sign of "outwards" along x. Left = the performer's left (+x, ARKit "Left").
SIDE_POINTS = {
    "Left": {
        "corner": 54,
        "upper": 52,
        "lower": 56,
        "eye": (42, 45),
        "lid_up": (43, 44),
        "lid_low": (46, 47),
        "brow": (22, 23, 24, 25, 26),
        "outer_brow": 26,
        "nostril": 35,
        "out": 1.0,
    },
    "Right": {
        "corner": 48,
        "upper": 50,
        "lower": 58,
        "eye": (36, 39),
        "lid_up": (37, 38),
        "lid_low": (40, 41),
        "brow": (17, 18, 19, 20, 21),
        "outer_brow": 17,
        "nostril": 31,
        "out": -1.0,
    },
}
#: FaceMesh vertices of each cheek (they are no iBUG point): mid-cheek, where a puff bulges, and below the lower
#: lid, where a cheek raise lifts the skin. ``landmark_probes`` finds them after the 68 points, in this order
CHEEK_VERTICES = {
    "Left": {"puff": (411, 425, 376), "raise": (346, 347, 330)},
    "Right": {"puff": (187, 205, 147), "raise": (117, 118, 101)},
}
EXTRA_VERTICES = tuple(v for side in CHEEK_VERTICES.values() for group in side.values() for v in group)
#: How far a smile lifts the skin below the lower lid per unit of the lip corner's rise. A lip-corner puller
#: (FACS AU12) raises the cheek too; a cheek raise (AU6, ARKit's cheekSquint) is the lift beyond that. ICT
#: FaceKit's mouthSmile, built on FACS, lifts those FaceMesh points 0.035-0.040 IOD while it raises its corner
#: 0.118 IOD (``python bench/eval_retarget.py --probes`` measures it on the character). The performers' cheek lift
#: follows their corner rise at r 0.45-0.95 (median 0.8) over the 17 takes of docs/retarget.md
SMILE_CHEEK_LIFT = 0.32
#: movements of the eyelids and the skin below them: a tenth of an open eye's height, half the landmark level
FINE_MOVEMENTS = ("EyeSquint", "EyeWide", "CheekSquint")
CHIN = 8
LIPS = tuple(range(48, 68))
INNER_GAP = ((61, 67), (62, 66), (63, 65))


def jaw_free(values: np.ndarray, chin_down: np.ndarray, rounds: int = 8, fit: np.ndarray | None = None) -> np.ndarray:
    """``values`` (frames,) less their regression on the chin drop over the frames given: the part of a measure
    the jaw opening does not explain (at the rest, where the chin is up, the measure is kept). The slope is a
    robust one (Huber's, by iteratively reweighted least squares, scale from the residuals' MAD): a smile held
    while talking must not teach the regression that the jaw lifts the corners, or every later open vowel would
    read as a frown. ``fit`` (frames,) bool: learn the slope on those frames only and take it out of all of them
    (``probes_read_on``: another face read with the performer's regressions)."""
    x, y = np.asarray(chin_down, np.float64), np.asarray(values, np.float64)
    learn = np.ones(len(x), bool) if fit is None else np.asarray(fit, bool)
    xs, ys = x[learn], y[learn]
    weights = np.ones_like(xs)
    slope = 0.0
    for _ in range(rounds):
        mx, my = (weights @ xs) / weights.sum(), (weights @ ys) / weights.sum()
        slope = float((weights * (xs - mx)) @ (ys - my) / max(float((weights * (xs - mx)) @ (xs - mx)), 1e-12))
        residual = ys - my - slope * (xs - mx)
        scale = 1.4826 * np.median(np.abs(residual - np.median(residual))) + 1e-12
        weights = np.minimum(1.0, 1.345 * scale / np.maximum(np.abs(residual), 1e-300))
    return y - slope * x


def landmark_probes(
    shapes: np.ndarray, rest: np.ndarray, lip_gap: np.ndarray, closure_gap: float, fit: np.ndarray | None = None
) -> dict:
    """Column -> per-frame movement (frames,) in IOD from one take's head-frame shapes (frames, 68, 3) and its
    rest (68, 3); ``lip_gap`` (frames,) the inner-lip gap / IOD (``MOVEMENT_TABLE`` says what each one is). With
    the ``EXTRA_VERTICES`` after the 68 points (frames, 68 + 12, 3), the cheeks too."""
    d = np.asarray(shapes, np.float64) - np.asarray(rest, np.float64)
    chin_down = -d[:, CHIN, 1]
    lip_gap = np.asarray(lip_gap, np.float64)
    closed = lip_gap < closure_gap
    lips_sideways = d[:, list(LIPS), 0].mean(axis=1)
    sideways = lips_sideways - d[:, CHIN, 0]
    free = partial(jaw_free, chin_down=chin_down, fit=fit)
    out = {
        "JawOpen": chin_down,
        "JawForward": free(d[:, CHIN, 2]),
        "JawLeft": d[:, CHIN, 0],
        "JawRight": -d[:, CHIN, 0],
        "MouthClose": np.where(closed, chin_down - lip_gap, 0.0),
        "MouthLeft": sideways,
        "MouthRight": -sideways,
        "MouthShrugLower": -chin_down,
        "MouthShrugUpper": free(d[:, 51, 1]),
        "MouthRollUpper": -(d[:, 51, 1] - d[:, 62, 1]),
        "MouthRollLower": -(d[:, 66, 1] - d[:, 57, 1]),
        "BrowInnerUp": d[:, [21, 22], 1].mean(axis=1),
    }
    width = np.linalg.norm(shapes[:, 54] - shapes[:, 48], axis=-1) - np.linalg.norm(rest[54] - rest[48])
    out["MouthPucker"] = free(-width)
    forward = d[:, [50, 51, 52, 56, 57, 58], 2].mean(axis=1)
    out["MouthFunnel"] = np.where(closed, 0.0, free(forward))
    for side, p in SIDE_POINTS.items():
        out.update({f"{name}{side}": value for name, value in side_probes(d, shapes, rest, p, free, closed, fit)})
    if d.shape[1] >= 68 + len(EXTRA_VERTICES):
        out.update(cheek_probes(d, chin_down, fit=fit))
    return out


def probes_read_on(
    shapes: np.ndarray, rest: np.ndarray, lip_gap: np.ndarray, closure_gap: float, motion: np.ndarray, gap: np.ndarray
) -> dict:
    """The landmark probes of another face's ``motion`` (frames, 68 [+ 12], 3: its deformation from its own rest,
    in the performer's head frame and IOD units; e.g. the character's animation) as the performer's probes read
    it: on the performer's rest, with each jaw-free probe's slope learned on the performer's ``shapes`` and
    ``rest`` (``landmark_probes``) and the lips' closed height the performer's. A face whose jaw lowers the lip
    corners less than the performer's jaw does reads, by its own regression, as making no smile where the
    performer's probe reads one, though both corners sit at the same place; read this way it makes the same
    movement. ``gap`` (frames,) is that face's inner-lip gap / IOD."""
    points = np.shape(motion)[1]  # without the cheek points the other face is read on the 68
    rest = np.asarray(rest, np.float64)[:points]
    stacked = np.concatenate([np.asarray(shapes, np.float64)[:, :points], rest + np.asarray(motion, np.float64)])
    fit = np.arange(len(stacked)) < len(shapes)
    gaps = np.concatenate([np.asarray(lip_gap, np.float64), np.asarray(gap, np.float64)])
    return {c: v[len(shapes) :] for c, v in landmark_probes(stacked, rest, gaps, closure_gap, fit=fit).items()}


def cheek_probes(d: np.ndarray, chin_down: np.ndarray, fit: np.ndarray | None = None) -> dict:
    """CheekPuff (both mid-cheeks outwards and forward beyond what a smile's corner rise explains, one column)
    and CheekSquint per side (the skin below the lower lid up), jaw-free, from the ``EXTRA_VERTICES`` of
    deformations ``d`` (frames, 68 + 12, 3)."""
    free = partial(jaw_free, chin_down=chin_down, fit=fit)

    def points(side, group):
        return [68 + EXTRA_VERTICES.index(v) for v in CHEEK_VERTICES[side][group]]

    out, puff = {}, []
    for side, p in SIDE_POINTS.items():
        bulge = (p["out"] * d[:, points(side, "puff"), 0] + d[:, points(side, "puff"), 2]).mean(axis=1)
        smile = free(d[:, p["corner"], 1])  # a smile bulges the cheeks too, lifting the corners
        puff.append(free(bulge) - np.maximum(smile, 0.0))
        lift = free(d[:, points(side, "raise"), 1].mean(axis=1))
        out[f"CheekSquint{side}"] = lift - SMILE_CHEEK_LIFT * np.maximum(smile, 0.0)
    out["CheekPuff"] = 0.5 * (puff[0] + puff[1])
    return out


def side_probes(d, shapes, rest, p, free, closed, fit=None):
    """(name, movement) of one side's probes (``landmark_probes``; ``free``: ``jaw_free`` of the take)."""
    corner = p["corner"]
    rise = free(d[:, corner, 1])
    outwards = free(p["out"] * (d[:, corner, 0] - d[:, list(LIPS), 0].mean(axis=1)))
    back = free(-d[:, corner, 2])
    eye_line = d[:, list(p["eye"]), 1].mean(axis=1)
    height = shapes[:, p["upper"], 1] - shapes[:, p["lower"], 1]
    learned = closed if fit is None else closed & fit
    closed_height = np.median(height[learned]) if learned.any() else 0.0  # the lips' usual height when closed
    brow = d[:, list(p["brow"])]
    return [
        ("MouthSmile", rise),
        ("MouthFrown", -rise),
        ("MouthStretch", outwards - np.maximum(rise, 0.0)),
        ("MouthDimple", back - np.maximum(rise, 0.0)),
        ("MouthPress", np.where(closed, closed_height - height, 0.0)),
        ("MouthLowerDown", free(-d[:, p["lower"], 1])),
        ("MouthUpperUp", free(d[:, p["upper"], 1])),
        ("EyeSquint", d[:, list(p["lid_low"]), 1].mean(axis=1) - eye_line),
        ("EyeWide", d[:, list(p["lid_up"]), 1].mean(axis=1) - eye_line),
        ("BrowDown", (-brow[..., 1] - p["out"] * brow[..., 0]).mean(axis=1)),
        ("BrowOuterUp", d[:, p["outer_brow"], 1]),
        ("NoseSneer", free(d[:, p["nostril"], 1])),
    ]


def eye_probes(aperture: np.ndarray | None, gaze: np.ndarray | None, open_quantile: float = 0.9) -> dict:
    """Column -> per-frame movement from one take's eye outputs: closure (0 open .. 1 shut) for the blinks,
    degrees from the take's median direction for eyeLook*. Empty where tracking has no such output."""
    out = {}
    if aperture is not None:
        aperture = np.asarray(aperture, np.float64)
        opened = np.quantile(aperture, open_quantile, axis=0)
        closure = 1.0 - aperture / np.maximum(opened, 1e-9)
        out["EyeBlinkLeft"], out["EyeBlinkRight"] = closure[:, 0], closure[:, 1]
    if gaze is not None:
        turn = np.asarray(gaze, np.float64) - np.median(gaze, axis=0)
        for eye, side in enumerate(("Left", "Right")):
            yaw, pitch = turn[:, eye, 0], turn[:, eye, 1]
            towards_left = yaw if side == "Left" else -yaw  # yaw > 0: towards the performer's left
            out[f"EyeLookOut{side}"], out[f"EyeLookIn{side}"] = towards_left, -towards_left
            out[f"EyeLookUp{side}"], out[f"EyeLookDown{side}"] = pitch, -pitch
    return out


def jitter(values: np.ndarray) -> float:
    """Robust standard deviation of frame-to-frame noise: 1.4826 MAD of the first differences / sqrt(2)."""
    step = np.diff(np.asarray(values, np.float64))
    if step.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(step - np.median(step))) / np.sqrt(2.0))


def sustained_peak(values: np.ndarray, frames: int) -> float:
    """The largest value the probe holds for ``frames`` frames in a row (the max of its running minimum)."""
    values = np.asarray(values, np.float64)
    if len(values) < frames:  # a take shorter than that: what it holds throughout
        return float(values.min(initial=0.0))
    from numpy.lib.stride_tricks import sliding_window_view

    return float(sliding_window_view(values, frames).min(axis=1).max())


@dataclass(frozen=True)
class MovedLevels:
    """When a probe counts as moved (module docstring)."""

    landmark_level: float = 0.02
    closure_level: float = 0.5
    gaze_level: float = 8.0
    frames: int = 3
    noise: float = 4.0

    def level(self, column: str) -> float:
        if column.startswith("EyeBlink"):
            return self.closure_level
        if column.startswith("EyeLook"):
            return self.gaze_level
        if column.startswith(FINE_MOVEMENTS):
            return 0.5 * self.landmark_level
        return self.landmark_level


def moved(probes: dict[str, np.ndarray], levels: MovedLevels) -> dict[str, dict]:
    """Per probe: its sustained peak, jitter, the level used and whether it moved (module docstring)."""
    out = {}
    for column, values in probes.items():
        peak, noise = sustained_peak(values, levels.frames), jitter(values)
        level = max(levels.level(column), levels.noise * noise)
        out[column] = {"peak": peak, "jitter": noise, "level": level, "moved": bool(peak > level)}
    return out
