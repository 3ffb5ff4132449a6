"""Retargeting evaluation: does the character's animation do what the performer's face did?

The character's 68 landmark vertices, deformed by the animation's morph weights, are placed in the tracked head
pose and projected into the video (the pose is the one tracking solved for its 3D face model, so the character is
first aligned to that model by a 3D similarity on the rigid landmarks), then compared with the tracked landmarks:

- **landmark error** per region (mouth, eyes, brows, jaw), RMS / inter-ocular distance (IOD), in the face's own
  axes (eye line horizontal). ``*_error_iod`` is the absolute error, which includes the fixed difference between
  the performer's face and the character's; ``*_motion_error_iod`` removes each take's mean offset per landmark
  (identity), leaving what the retarget got wrong over time. The same number for the animation shifted by half a
  take (``*_shifted``) says how far a wrong animation scores: the metric's calibration on the same data.
- **lip closures**: runs of >= ``closure_frames`` frames where the performer's inner-lip gap is below
  ``closure_gap`` IOD; a closure is reproduced when the character's mean gap over those frames is at most
  ``closure_ratio`` times the performer's.
- **blinks**: frames where the eye aperture (lid gap / eye width, both eyes averaged) falls below ``blink_ratio``
  times the take's open aperture (90th percentile) inside a narrowing (below halfway to open) that lasts at most
  ``blink_max_seconds`` (longer is a squint); performer (tracking ``eye_aperture`` when present, else the landmarks) against
  the character (its projected landmark vertices). Recall and false blinks with a tolerance of ``blink_tolerance``
  frames.
- **audio**: Pearson correlation of the mouth opening with the audio's RMS envelope, for the character, the
  performer (the reference) and the character shifted by half a take (no timing: the chance level).
- **jaw vs funnel**: at the performer's widest-jaw frames (chin-to-nose-bridge distance, top ``widest_fraction``
  of each take), jawOpen minus mouthFunnel, and how often jawOpen is the larger.
- **dead channels**: ARKit columns (the export's mapping, ``stages.formats.live_link``) and character morphs that
  never exceed ``dead_level`` although their region moved (RMS landmark motion above ``moved_level`` IOD; eyes:
  aperture std; gaze needs tracking ``gaze``; the tongue is never tracked).
- **keyshape residual**: the decomposition residual (Eq 8) of the keyshapes artifact, when given.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from msflow import Input, Output, Result, Stage, UserError
from stages.retarget.keyshapes import inter_ocular_distance
from stages.retarget.regions import (
    CHIN,
    EVAL_REGIONS,
    RIGID,
    find_morph,
    morph_region,
)
from stages.tracking.face3d import DEFAULT_FACE3D

# ------------------------------------------------------------------------------------------------ geometry


def character_landmarks(neutral: np.ndarray, deltas: np.ndarray, landmark_ids: np.ndarray, weights: np.ndarray):
    """The character's landmark vertices under morph weights: (frames, 68, 3) = neutral + sum_m w_m delta_m."""
    ids = np.asarray(landmark_ids, dtype=np.int64)
    base = np.asarray(neutral, np.float64)[ids]
    local = np.asarray(deltas, np.float64)[:, ids]  # (M, 68, 3)
    return base[None] + np.einsum("fm,mpc->fpc", np.asarray(weights, np.float64), local)


def quat_matrices(q: np.ndarray) -> np.ndarray:
    from stages.geometry.rotations import quat_to_matrix

    return quat_to_matrix(np.asarray(q, np.float64))


def pose_and_project(points: np.ndarray, rotation: np.ndarray, translation: np.ndarray, camera: np.ndarray):
    """Image pixels (frames, P, 2) of head-frame points (frames, P, 3) under per-frame poses (glTF camera axes:
    x right, y up, z towards the viewer; rotation unit quaternions (w, x, y, z)) through pinhole ``camera`` (3, 3),
    or one camera per frame (frames, 3, 3)."""
    cam = np.einsum("fij,fpj->fpi", quat_matrices(rotation), points) + np.asarray(translation, np.float64)[:, None]
    depth = -cam[..., 2]  # OpenCV looks along +z, glTF's camera along -z
    k = np.broadcast_to(np.asarray(camera, np.float64), (len(cam), 3, 3))
    u = k[:, 0, 0, None] * cam[..., 0] / depth + k[:, 0, 2, None]
    v = -k[:, 1, 1, None] * cam[..., 1] / depth + k[:, 1, 2, None]
    return np.stack([u, v], axis=-1)


def align_to_model(character_points: np.ndarray, model_points: np.ndarray):
    """The 3D similarity that carries the character's neutral landmarks onto the pose model's (rigid points)."""
    from stages.retarget.keymorphs import fit_similarity

    rigid = list(RIGID)
    return fit_similarity(np.asarray(character_points)[rigid], np.asarray(model_points)[rigid])


def face_frame_errors(predicted: np.ndarray, tracked: np.ndarray) -> np.ndarray:
    """Error vectors (frames, 68, 2) of predicted vs tracked image landmarks, rotated so the tracked eye line is
    horizontal and divided by the tracked inter-ocular distance."""
    tracked = np.asarray(tracked, np.float64)
    eye = tracked[:, 45] - tracked[:, 36]
    iod = np.linalg.norm(eye, axis=1)
    c, s = eye[:, 0] / iod, eye[:, 1] / iod
    d = np.asarray(predicted, np.float64) - tracked
    rotated = np.stack(
        [c[:, None] * d[..., 0] + s[:, None] * d[..., 1], -s[:, None] * d[..., 0] + c[:, None] * d[..., 1]], -1
    )
    return rotated / iod[:, None, None]


def remove_take_offsets(errors: np.ndarray, sequence: np.ndarray) -> np.ndarray:
    """Errors less each take's mean error per landmark: the fixed part (the faces' different proportions)."""
    out = np.array(errors, np.float64)
    for take in np.unique(sequence):
        rows = sequence == take
        out[rows] -= out[rows].mean(axis=0)
    return out


def region_rms(errors: np.ndarray, points: tuple[int, ...]) -> np.ndarray:
    """Per-frame RMS length of the error vectors of one region's landmarks."""
    return np.sqrt((np.asarray(errors)[:, list(points)] ** 2).sum(-1).mean(-1))


def shift_within_takes(values: np.ndarray, sequence: np.ndarray) -> np.ndarray:
    """Each take's rows rolled by half its length: the same animation, out of time with the performer."""
    out = np.array(values)
    for take in np.unique(sequence):
        rows = np.flatnonzero(sequence == take)
        out[rows] = np.roll(values[rows], len(rows) // 2, axis=0)
    return out


# ------------------------------------------------------------------------------------------------ events


def runs(mask: np.ndarray, sequence: np.ndarray, min_length: int = 1) -> list[tuple[int, int]]:
    """[start, stop) of the runs of True at least ``min_length`` frames long, never across a take boundary."""
    mask = np.asarray(mask, bool)
    sequence = np.asarray(sequence)
    edges = np.diff(np.r_[0, mask.astype(np.int8), 0])
    cut = np.r_[False, sequence[1:] != sequence[:-1]]
    out = []
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    for a, b in zip(starts, stops):
        breaks = np.flatnonzero(cut[a + 1 : b]) + a + 1
        for lo, hi in zip(np.r_[a, breaks], np.r_[breaks, b]):
            if hi - lo >= min_length:
                out.append((int(lo), int(hi)))
    return out


def lip_gap(shapes: np.ndarray) -> np.ndarray:
    """Vertical inner-lip gap per frame (iBUG 61-67, 62-66, 63-65 mean, across the eye line) / inter-ocular
    distance: the same measure the lip seal works with (``stages.retarget.keyshapes.lip_gap_iod``)."""
    from stages.retarget.keyshapes import level, lip_gap_iod

    return lip_gap_iod(level(shapes))


def eye_aperture(shapes: np.ndarray) -> np.ndarray:
    """(frames, 2) lid gap / eye-corner distance from iBUG landmarks; index 0 = the performer's left eye
    (iBUG 42-47, ARKit ``_L``), 1 = right (36-41), as tracking's ``eye_aperture``."""
    from stages.retarget.eyes import eye_aperture_2d

    return eye_aperture_2d(shapes)


def blink_frames(aperture: np.ndarray, sequence: np.ndarray, ratio: float, open_quantile: float = 0.9) -> np.ndarray:
    """Frames whose aperture (mean of both eyes) is below ``ratio`` x the take's open aperture (its 90th
    percentile: the eyes' usual opening, whatever the expression narrows them to for a while)."""
    mean = np.asarray(aperture, np.float64).reshape(len(sequence), -1).mean(axis=1)
    closed = np.zeros(len(mean), dtype=bool)
    for take in np.unique(sequence):
        rows = sequence == take
        closed[rows] = mean[rows] < ratio * np.quantile(mean[rows], open_quantile)
    return closed


def blink_frame_limits(fps: list[float], sequence: np.ndarray, seconds: float) -> np.ndarray:
    """Per take, the most frames a blink may last."""
    takes = int(np.max(sequence, initial=0)) + 1
    return np.array([max(1, int(round(seconds * (fps[i] if i < len(fps) else fps[-1])))) for i in range(takes)])


def blink_events(aperture, sequence, ratio: float, longest: np.ndarray) -> list[tuple[int, int]]:
    """Blinks: quick dips. A run of frames narrowed below halfway between ``ratio`` and open, no longer than its
    take's ``longest``, that reaches below ``ratio`` x open somewhere (a longer narrowing is a squint or closed
    eyes, and a squint hovering about the threshold is not a string of blinks)."""
    closed = blink_frames(aperture, sequence, ratio)
    narrowed = blink_frames(aperture, sequence, 0.5 * (1.0 + ratio))
    return [(a, b) for a, b in runs(narrowed, sequence) if b - a <= longest[sequence[a]] and closed[a:b].any()]


def event_agreement(reference: list[tuple[int, int]], predicted: list[tuple[int, int]], tolerance: int) -> dict:
    """Recall (reference events overlapped by a predicted one, within ``tolerance`` frames) and the false rate
    (predicted events that overlap no reference event)."""

    def overlaps(a, b):
        return a[0] - tolerance < b[1] and b[0] - tolerance < a[1]

    found = sum(any(overlaps(r, p) for p in predicted) for r in reference)
    false = sum(not any(overlaps(p, r) for r in reference) for p in predicted)
    return {
        "reference": len(reference),
        "predicted": len(predicted),
        "found": int(found),
        "false": int(false),
        "recall": found / len(reference) if reference else 1.0,
        "false_rate": false / len(predicted) if predicted else 0.0,
    }


def closure_agreement(
    performer_gap: np.ndarray, character_gap: np.ndarray, sequence: np.ndarray, *, gap: float, frames: int, ratio: float
) -> list[dict]:
    """Each performer lip closure (gap < ``gap`` for >= ``frames`` frames) with the mean gaps of performer and
    character over it, and whether the character's is at most ``ratio`` times the performer's."""
    out = []
    for a, b in runs(performer_gap < gap, sequence, frames):
        p, c = float(performer_gap[a:b].mean()), float(character_gap[a:b].mean())
        out.append({"start": a, "stop": b, "performer_gap": p, "character_gap": c, "reproduced": c <= ratio * p})
    return out


# ------------------------------------------------------------------------------------------------ audio, jaw


def audio_envelope(samples: np.ndarray, rate: float, offset: float, fps: float, frames: int) -> np.ndarray:
    """RMS of the audio in a window of one frame centred on each video frame (``offset``: seconds of the first
    sample relative to the first frame)."""
    samples = np.asarray(samples, np.float64)
    centre = (np.arange(frames) / fps - offset) * rate
    half = 0.5 * rate / fps
    lo = np.clip(np.round(centre - half).astype(np.int64), 0, len(samples))
    hi = np.clip(np.round(centre + half).astype(np.int64), 0, len(samples))
    power = np.r_[0.0, np.cumsum(samples**2)]
    count = np.maximum(hi - lo, 1)
    return np.sqrt((power[hi] - power[lo]) / count)


def pearson(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation; 0 when either series is constant."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    a, b = a - a.mean(), b - b.mean()
    denominator = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / denominator) if denominator > 0 else 0.0


def jaw_drop(shapes: np.ndarray) -> np.ndarray:
    """Chin (iBUG 8) to nose bridge (27) distance / inter-ocular distance."""
    shapes = np.asarray(shapes, np.float64)
    return np.linalg.norm(shapes[:, 8] - shapes[:, 27], axis=-1) / inter_ocular_distance(shapes)


def widest_frames(values: np.ndarray, sequence: np.ndarray, fraction: float) -> np.ndarray:
    """Per take, the frames in the top ``fraction`` of ``values`` (at least one)."""
    chosen = []
    for take in np.unique(sequence):
        rows = np.flatnonzero(sequence == take)
        count = max(1, int(np.ceil(fraction * len(rows))))
        chosen.append(rows[np.argsort(-values[rows], kind="stable")[:count]])
    return np.sort(np.concatenate(chosen)) if chosen else np.zeros(0, np.int64)


# ------------------------------------------------------------------------------------------------ motion, dead


def aligned_shapes(shapes: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Each frame's landmarks similarity-aligned (rigid points) onto ``reference``: pose taken out in 2D."""
    from stages.retarget.keymorphs import fit_similarity

    out = np.empty_like(np.asarray(shapes, np.float64))
    for f, shape in enumerate(np.asarray(shapes, np.float64)):
        out[f] = fit_similarity(shape[list(RIGID)], reference[list(RIGID)]).apply(shape)
    return out


def region_motion(shapes: np.ndarray, sequence: np.ndarray) -> dict[str, float]:
    """How much each region moved: RMS landmark deviation from each take's mean shape, after 2D alignment, / IOD.
    ``eyes`` is measured on the lid gaps alone (eye corners are alignment points)."""
    shapes = np.asarray(shapes, np.float64)
    out: dict[str, list[float]] = {}
    for take in np.unique(sequence):
        rows = shapes[sequence == take]
        reference = rows.mean(axis=0)
        aligned = aligned_shapes(rows, reference)
        deviation = (aligned - aligned.mean(axis=0)) / inter_ocular_distance(reference)
        for region, points in {"mouth": EVAL_REGIONS["mouth"], "jaw": CHIN, "brows": EVAL_REGIONS["brows"]}.items():
            out.setdefault(region, []).append(float(np.sqrt((deviation[:, list(points)] ** 2).sum(-1).mean())))
        out.setdefault("eyes", []).append(float(eye_aperture(rows).std(axis=0).mean()))
        out.setdefault("cheeks", []).append(
            float(np.sqrt((deviation[:, [1, 2, 3, 13, 14, 15, 31, 35]] ** 2).sum(-1).mean()))
        )
    return {region: max(values) for region, values in out.items()}


def dead_channels(weights: np.ndarray, names: list[str], moved: dict[str, bool], level: float) -> list[str]:
    """Morphs whose weight never exceeds ``level`` although their region moved."""
    peak = np.asarray(weights).max(axis=0, initial=0.0)
    return [n for n, p in zip(names, peak) if moved.get(morph_region(n) or "", False) and p < level]


# ------------------------------------------------------------------------------------------------ figures


def figure_timeline(view, inputs=None):
    """Per-frame mouth/eyes/brows error, lip gaps with the performer's closures, eye apertures with blinks."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(8, 6.5), sharex=True)
    error = view["region_error"]
    for r, region in enumerate(view.meta["regions"]):
        axes[0].plot(100 * error[:, r], label=region, lw=1)
    axes[0].axhline(3.0, color="r", ls="--", lw=0.7)
    axes[0].set_ylabel("error, % IOD")
    axes[0].set_title("Landmark error of the character (take offsets removed)")
    axes[0].legend(fontsize=7, ncol=4)
    gap = view["lip_gap"]
    axes[1].plot(100 * gap[:, 0], "k", lw=1, label="performer")
    axes[1].plot(100 * gap[:, 1], "C3", lw=1, label="character")
    for c in view.meta["closures"]:
        axes[1].axvspan(c["start"] - 0.5, c["stop"] - 0.5, color="g" if c["reproduced"] else "r", alpha=0.2)
    axes[1].set_ylabel("inner-lip gap, % IOD")
    axes[1].set_title("Lip closures (green: reproduced, red: not)")
    axes[1].legend(fontsize=7)
    aperture = view["eye_aperture"]
    axes[2].plot(aperture[:, 0], "k", lw=1, label="performer")
    axes[2].plot(aperture[:, 1], "C3", lw=1, label="character")
    for a, b in view.meta["blinks"]["performer"]:
        axes[2].axvspan(a - 0.5, b - 0.5, color="k", alpha=0.15)
    axes[2].set_ylabel("eye aperture")
    axes[2].set_xlabel("frame")
    axes[2].set_title(f"Blinks (grey: performer's; source: {view.meta['blink_source']})")
    axes[2].legend(fontsize=7)
    fig.tight_layout()
    return fig


# ------------------------------------------------------------------------------------------------ stage

EVAL_OUTPUTS = {
    "landmarks": Output.array(
        "f", shape=("frames", 68, 2), dtype="float32", doc="the character's landmark vertices posed and projected (px)"
    ),
    "region_error": Output.array(
        "f",
        shape=("frames", "regions"),
        dtype="float32",
        doc="per-frame RMS landmark error / IOD, take offsets removed, per meta['regions']",
    ),
    "lip_gap": Output.array("f", shape=("frames", 2), dtype="float32", doc="inner-lip gap / IOD: performer, character"),
    "eye_aperture": Output.array(
        "f", shape=("frames", 2), dtype="float32", doc="eye aperture (both eyes' mean): performer, character"
    ),
    "envelope": Output.array("f", shape=("frames",), dtype="float32", optional=True, doc="audio RMS per frame"),
}


class RetargetEval(Stage):
    """Metrics of a retargeted animation (blend weights on a character) against the tracked performer."""

    class Params(Stage.Params):
        #: a lip closure: inner-lip gap below this (IOD) ...
        closure_gap: float = Field(0.03, gt=0)
        #: ... for at least this many frames
        closure_frames: int = Field(2, ge=1)
        #: a closure is reproduced when the character's gap is at most this times the performer's
        closure_ratio: float = Field(1.2, gt=0)
        #: a blink: aperture below this fraction of the take's open aperture (FaceMesh's 468-point lids close
        #: to about 2/3 in a blink, Face Landmarker v2's to about 1/3)
        blink_ratio: float = Field(0.7, gt=0, lt=1)
        #: frames of slack when matching blinks
        blink_tolerance: int = Field(1, ge=0)
        #: a narrowing longer than this (seconds) is a squint or closed eyes, not a blink
        blink_max_seconds: float = Field(0.5, gt=0)
        #: the performer's widest-jaw frames: this top fraction of each take
        widest_fraction: float = Field(0.1, gt=0, le=1)
        #: a morph is dead when its weight never exceeds this ...
        dead_level: float = Field(0.02, ge=0)
        #: ... while its region moved more than this (RMS landmark motion / IOD; eyes: aperture std)
        moved_level: float = Field(0.01, ge=0)

    inputs = {
        "tracks": Input.artifact(
            "landmarks", "rotation", "translation", "sequence", doc="tracking of the performance the blend animates"
        ),
        "blend": Input.artifact("weights", doc="blend artifact: morph weights per frame, meta target_names"),
        "character": Input.artifact("neutral", "deltas", "landmark_ids", doc="the character artifact"),
        "keyshapes": Input.artifact("residual", optional=True, doc="keyshapes artifact: decomposition residual"),
    }
    outputs = EVAL_OUTPUTS
    resources = {"face3d": DEFAULT_FACE3D}
    figures = {"timeline": figure_timeline}

    def run(self, params, inputs):
        data = self._validate(inputs)
        results = evaluate(params, **data)
        return self._pack(results, data, inputs.get("keyshapes"))

    # ---------------------------------------------------------------------------------------------- validate
    @staticmethod
    def _validate(inputs) -> dict:
        from stages.tracking.face3d import load_face3d

        tracks, blend, character = inputs["tracks"], inputs["blend"], inputs["character"]
        landmarks = np.asarray(tracks["landmarks"], np.float64)
        weights = np.asarray(blend["weights"], np.float64)
        names = list(blend.meta.get("target_names", character.meta.get("target_names", [])))
        deltas = np.asarray(character["deltas"], np.float64)
        if len(weights) != len(landmarks):
            raise UserError(
                f"the blend has {len(weights)} frames but the tracking {len(landmarks)}: wire the tracking of the "
                "take the blend animates",
                field="inputs.tracks",
            )
        if weights.shape[1] != len(deltas) or len(names) != len(deltas):
            raise UserError(
                f"the blend drives {weights.shape[1]} morphs, the character has {len(deltas)}",
                field="inputs.character",
            )
        meta = tracks.meta
        sequence = np.asarray(tracks["sequence"]).astype(np.int64)
        data = {
            "landmarks": landmarks,
            "rotation": np.asarray(tracks["rotation"], np.float64),
            "translation": np.asarray(tracks["translation"], np.float64),
            "sequence": sequence,
            "labels": list(meta.get("labels") or [f"take{i}" for i in range(int(sequence.max(initial=0)) + 1)]),
            "camera": take_cameras(meta, sequence)[sequence],
            "weights": weights,
            "names": names,
            "neutral": np.asarray(character["neutral"], np.float64),
            "deltas": deltas,
            "landmark_ids": np.asarray(character["landmark_ids"]),
            "model": load_face3d(DEFAULT_FACE3D, field="resources.face3d").neutral,
            "aperture": np.asarray(tracks["eye_aperture"], np.float64) if "eye_aperture" in tracks else None,
            "gaze": np.asarray(tracks["gaze"], np.float64) if "gaze" in tracks else None,
            "audio": _take_audio(tracks, sequence),
            "fps": [float(f) for f in (meta.get("fps") or [30.0])],
        }
        return data

    # ---------------------------------------------------------------------------------------------- pack
    @staticmethod
    def _pack(results: dict, data: dict, keyshapes) -> Result:
        metrics = dict(results["metrics"])
        if keyshapes is not None:
            residual = np.asarray(keyshapes["residual"], np.float64)
            metrics["keyshape_residual_rms_iod"] = float(np.sqrt(np.mean(residual**2))) if residual.size else 0.0
            metrics["keyshape_residual_max_iod"] = float(residual.max(initial=0.0))
        arrays = {k: v.astype(np.float32) for k, v in results["arrays"].items()}
        return Result(arrays, meta=results["meta"], metrics=metrics, warnings=results["warnings"])


def take_cameras(meta: dict, sequence: np.ndarray) -> np.ndarray:
    """The pinhole camera tracking solved each take's pose with (its frame size and focal length): (takes, 3, 3)."""
    from stages.tracking.pose import camera_matrix

    sizes = meta.get("frame_size") or [[640, 480]]
    focals = meta.get("focal_length") or [None]
    takes = int(np.max(sequence, initial=0)) + 1

    def pick(values, i):
        return values[i] if i < len(values) else values[-1]

    return np.stack([camera_matrix(*pick(sizes, i), pick(focals, i)) for i in range(takes)])


def _take_audio(tracks, sequence) -> list | None:
    """Per take (samples, rate, offset), or None without audio."""
    if "audio" not in tracks or "audio_bounds" not in tracks:
        return None
    meta = tracks.meta
    audio, bounds = np.asarray(tracks["audio"]), np.asarray(tracks["audio_bounds"])
    takes = int(sequence.max(initial=0)) + 1

    def per_take(key, i, default):
        value = meta.get(key, default)
        return value[i] if isinstance(value, (list, tuple)) else value

    out = []
    for i in range(takes):
        if i >= len(bounds) or not per_take("audio_rate", i, None):
            out.append(None)
            continue
        start, stop = (int(v) for v in bounds[i])
        out.append(
            (audio[start:stop], float(per_take("audio_rate", i, 0)), float(per_take("audio_offset", i, 0.0) or 0.0))
        )
    return out


def evaluate(params, **data) -> dict:
    """All the metrics from validated inputs (see the module docstring)."""
    sequence, tracked, weights, names = data["sequence"], data["landmarks"], data["weights"], data["names"]
    warnings = []
    # the character in the pose model's frame, posed and projected like the tracked face
    neutral_points = character_landmarks(data["neutral"], data["deltas"], data["landmark_ids"], weights[:1] * 0)[0]
    to_model = align_to_model(neutral_points, data["model"])

    def project(w):
        points = to_model.apply(character_landmarks(data["neutral"], data["deltas"], data["landmark_ids"], w))
        return pose_and_project(points, data["rotation"], data["translation"], data["camera"])

    predicted = project(weights)
    shifted = project(shift_within_takes(weights, sequence))
    regions = list(EVAL_REGIONS)
    absolute = face_frame_errors(predicted, tracked)
    motion = remove_take_offsets(absolute, sequence)
    motion_shifted = remove_take_offsets(face_frame_errors(shifted, tracked), sequence)
    metrics: dict[str, float] = {}
    region_error = np.zeros((len(tracked), len(regions)))
    for r, region in enumerate(regions):
        points = EVAL_REGIONS[region]
        region_error[:, r] = region_rms(motion, points)
        metrics[f"{region}_error_iod"] = float(np.sqrt(np.mean(region_rms(absolute, points) ** 2)))
        metrics[f"{region}_motion_error_iod"] = float(np.sqrt(np.mean(region_error[:, r] ** 2)))
        metrics[f"{region}_motion_error_iod_shifted"] = float(np.sqrt(np.mean(region_rms(motion_shifted, points) ** 2)))

    # lips
    performer_gap, character_gap = lip_gap(tracked), lip_gap(predicted)
    closures = closure_agreement(
        performer_gap,
        character_gap,
        sequence,
        gap=params.closure_gap,
        frames=params.closure_frames,
        ratio=params.closure_ratio,
    )
    metrics["closures"] = float(len(closures))
    metrics["closures_reproduced"] = float(sum(c["reproduced"] for c in closures))
    metrics["closure_gap_ratio_max"] = float(
        max((c["character_gap"] / c["performer_gap"] for c in closures), default=0.0)
    )

    # eyes
    performer_aperture = data["aperture"] if data["aperture"] is not None else eye_aperture(tracked)
    character_aperture = eye_aperture(predicted)
    longest = blink_frame_limits(data["fps"], sequence, params.blink_max_seconds)
    performer_blinks = blink_events(performer_aperture, sequence, params.blink_ratio, longest)
    character_blinks = blink_events(character_aperture, sequence, params.blink_ratio, longest)
    blinks = event_agreement(performer_blinks, character_blinks, params.blink_tolerance)
    metrics["blinks"] = float(blinks["reference"])
    metrics["blink_recall"] = float(blinks["recall"])
    metrics["false_blink_rate"] = float(blinks["false_rate"])

    # audio
    envelope = None
    if data["audio"] is not None and any(a is not None for a in data["audio"]):
        envelope, r = envelope_correlations(data, performer_gap, character_gap, lip_gap(shifted))
        metrics.update(r)

    # jaw vs funnel
    widest = widest_frames(jaw_drop(tracked), sequence, params.widest_fraction)
    jaw, funnel = find_morph(names, "jawOpen"), find_morph(names, "mouthFunnel")
    if jaw is not None and funnel is not None:
        diff = weights[widest, jaw] - weights[widest, funnel]
        metrics["jaw_minus_funnel"] = float(diff.mean())
        metrics["jaw_over_funnel_fraction"] = float((diff > 0).mean())
    else:
        warnings.append("the character has no jawOpen/mouthFunnel morphs: jaw vs funnel not measured")

    # dead channels
    moved_amount = region_motion(tracked, sequence)
    moved = {region: amount > params.moved_level for region, amount in moved_amount.items()}
    if data["gaze"] is not None:
        moved["gaze"] = bool(np.asarray(data["gaze"]).std(axis=0).max() > 2.0)
    from stages.formats.live_link import ARKIT_NAMES, UNTRACKED_COLUMNS, arkit_weights

    arkit, _ = arkit_weights(weights, names, data["deltas"])
    dead_columns = [
        c for c in dead_channels(arkit, ARKIT_NAMES, moved, params.dead_level) if c not in UNTRACKED_COLUMNS
    ]
    dead = dead_channels(weights, names, moved, params.dead_level)
    metrics["dead_arkit_columns"] = float(len(dead_columns))
    metrics["dead_morphs"] = float(len(dead))

    metrics["pose_rms_px"] = float(np.sqrt(np.mean((predicted[:, list(RIGID)] - tracked[:, list(RIGID)]) ** 2) * 2))
    meta = {
        "regions": regions,
        "labels": data["labels"],
        "closures": closures,
        "blinks": {"performer": performer_blinks, "character": character_blinks, **blinks},
        "blink_source": "tracking eye_aperture" if data["aperture"] is not None else "landmarks",
        "widest_jaw_frames": widest.tolist(),
        "region_motion": moved_amount,
        "dead_arkit_columns": dead_columns,
        "dead_morphs": dead,
        "similarity_to_pose_model": {"scale": float(to_model.scale)},
    }
    arrays = {
        "landmarks": predicted,
        "region_error": region_error,
        "lip_gap": np.stack([performer_gap, character_gap], axis=1),
        "eye_aperture": np.stack([performer_aperture.mean(axis=1), character_aperture.mean(axis=1)], axis=1),
    }
    if envelope is not None:
        arrays["envelope"] = envelope
    return {"metrics": metrics, "meta": meta, "arrays": arrays, "warnings": warnings}


def envelope_correlations(data, performer_gap, character_gap, shifted_gap) -> tuple[np.ndarray, dict]:
    """Audio envelope per frame and the mean over takes of its correlation with each mouth opening."""
    sequence = data["sequence"]
    envelope = np.zeros(len(sequence))
    r = {"envelope_r_character": [], "envelope_r_performer": [], "envelope_r_shifted": []}
    for take in np.unique(sequence):
        audio = data["audio"][take] if take < len(data["audio"]) else None
        if audio is None:
            continue
        rows = np.flatnonzero(sequence == take)
        fps = data["fps"][take] if take < len(data["fps"]) else data["fps"][0]
        envelope[rows] = audio_envelope(audio[0], audio[1], audio[2], fps, len(rows))
        r["envelope_r_character"].append(pearson(character_gap[rows], envelope[rows]))
        r["envelope_r_performer"].append(pearson(performer_gap[rows], envelope[rows]))
        r["envelope_r_shifted"].append(pearson(shifted_gap[rows], envelope[rows]))
    return envelope, {k: float(np.mean(v)) for k, v in r.items() if v}
