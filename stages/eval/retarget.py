"""Retargeting evaluation: does the character's animation do what the performer's face did?

The character's 68 landmark vertices, deformed by the animation's morph weights, are placed in the tracked head
pose and projected into the video (the pose is the one tracking solved for its 3D face model, so the character is
first aligned to that model by a 3D similarity on the rigid landmarks), then compared with the tracked landmarks:

- **landmark error** per region (mouth, eyes, brows, jaw), RMS / inter-ocular distance (IOD), in the face's own
  axes (eye line horizontal). ``*_error_iod`` is the absolute error, which includes the fixed difference between
  the performer's face and the character's; ``*_neutral_error_iod`` (rest aligned) removes each take's error of
  the character's *neutral* face at the performer's closed-mouth rest frames, leaving everything the animation
  does; ``*_motion_error_iod`` removes each take's mean error per landmark instead. The same number for the
  animation shifted by half a take (``*_shifted``) says how far a wrong animation scores: the metric's calibration
  on the same data. ``*_face_posed_error_iod`` (with a FaceMesh) is the absolute error with the character posed on
  the performer's own tracked 3D face instead of with the generic model's head pose (``pose_on_tracked_face``).
- **lip closures**: runs of >= ``closure_frames`` frames where the performer's inner-lip gap is below
  ``closure_gap`` IOD; a closure is reproduced when the character's mean gap over those frames is at most
  ``closure_ratio`` times the performer's.
- **blinks**: dips of the eye aperture (lid gap / eye width, both eyes averaged) below ``blink_ratio`` times the
  take's open aperture (90th percentile) inside a narrowing below ``blink_narrow_ratio`` that lasts at most
  ``blink_max_seconds`` (longer is a squint); performer (tracking ``eye_aperture`` when present, else the
  landmarks) against the character (its projected landmark vertices). Recall and false blinks with a tolerance
  of ``blink_tolerance`` frames.
- **audio**: Pearson correlation of the mouth opening with the audio's RMS envelope, for the character, the
  performer (the reference) and the character shifted by half a take (no timing: the chance level).
- **jaw vs funnel**: at the performer's widest-jaw frames (top ``widest_fraction`` of each take by the chin's drop
  in the head's frame, or with ``widest_by: image`` by the chin-to-nose-bridge distance in the image), jawOpen
  minus mouthFunnel, and how often jawOpen is the larger.
- **pressed lips apart**: how often a lip press (mouthPress) is on while the performer's lips are apart
  (``press_apart_fraction``: an ARKit rig shows pressed lips over an open mouth).
- **columns that follow the movement**: per take and column whose movement the performer made, the correlation of
  the column's weight with its probe over the frames (``meta["takes"][...]["following"]``, with the weight rolled
  by half the take as chance), pooled as ``following_r_median`` and the share below 0.3 (``following_weak``). The
  probes are not specific to one morph (below), so a low r flags a column to look at, not a proven fault.
- **dead ARKit columns**: columns (the export's mapping, ``stages.formats.live_link``) that never exceed
  ``dead_level`` in a take, sorted by whether the performer made that movement there (the movement probes of
  ``stages.retarget.movements`` on the tracked FaceMesh; eyes from ``eye_aperture`` and ``gaze``). A column dead
  where moved is *made* when the character's face makes the movement all the same, through other morphs: its
  landmark vertices under the animation, aligned and read by the performer's own probes
  (``columns.character_movements``; ``dead_arkit_moved_missing`` counts the others, the movements the animation
  lacks; the reading per column in ``meta["takes"][...]["character_movements"]``).
- **false movements**: the converse, the (take, column) pairs whose movement the character's face makes (read the
  same way) where the performer's probe did not move: ``false_movements`` (count), ``false_movement_rate`` (their
  share of the pairs the performer did not move), and its chance level ``false_movement_rate_shuffled`` (the
  character's movements of each take against the performer's of every other take). Per take in
  ``columns["made_not_moved"]``.
- **keyshape residual**: the decomposition residual (Eq 8) of the keyshapes artifact, when given.

Pooled over the takes as stage metrics, per take in ``meta["takes"]``.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from msflow import Input, Output, Result, Stage, UserError
from stages.eval.columns import (
    character_movements,
    column_following,
    dead_where_moved,
    false_movements,
    movement_gains,
    outside_blinks,
    performer_frame,
    pooled_dead,
    pooled_false_movements,
    pooled_following,
    pooled_gains,
    take_movements,
)
from stages.eval.events import (
    blink_events,
    blink_frame_limits,
    closure_agreement,
    event_agreement,
    eye_aperture,
    lip_gap,
    pearson,
)
from stages.retarget.face_measures import inter_ocular_distance
from stages.retarget.regions import EVAL_REGIONS, RIGID, find_morph, find_side_morph
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
    from stages.retarget.morph_fit import fit_similarity

    rigid = list(RIGID)
    return fit_similarity(np.asarray(character_points)[rigid], np.asarray(model_points)[rigid])


def pose_on_tracked_face(points: np.ndarray, mesh_points: np.ndarray) -> np.ndarray:
    """The character's landmark vertices (frames, 68, 3, head axes) posed on the performer's own tracked 3D face:
    image pixels (frames, 68, 2). Per frame, the 3D similarity (Umeyama) of the rigid points onto the tracked iBUG
    points (FaceMesh image x, y and relative depth z, ``mesh_points`` (frames, 68, 3)), read in x, y. Unlike the
    tracked head pose (the pose of a generic face model fitted to the 2D landmarks), it does not depend on how the
    performer's proportions differ from that model's. FaceMesh is taken as it comes, a scaled orthographic view:
    taking a pinhole perspective out of it first (``shapes3d.undo_perspective``) made the error larger on every
    clip but one, the more so the shorter the focal length assumed (docs/retarget.md)."""
    from stages.retarget.shapes3d import MESH_TO_HEAD_AXES, similarity_align

    return similarity_align(np.asarray(points, np.float64) * MESH_TO_HEAD_AXES, mesh_points)[..., :2]


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


# ------------------------------------------------------------------------------------------------ audio, jaw


def audio_envelope(
    samples: np.ndarray, rate: float, offset: float, fps: float, frames: int, times: np.ndarray | None = None
) -> np.ndarray:
    """RMS of the audio in a window of one frame centred on each video frame (``offset``: seconds of the first
    sample relative to the first frame), the frames at ``times`` (seconds, the take's tracked frame times: a
    variable-frame-rate video's frames are not at i / fps) or at i / ``fps``."""
    samples = np.asarray(samples, np.float64)
    at = np.arange(frames) / fps if times is None else np.asarray(times, np.float64) - float(times[0])
    centre = (at - offset) * rate
    half = 0.5 * rate / fps
    lo = np.clip(np.round(centre - half).astype(np.int64), 0, len(samples))
    hi = np.clip(np.round(centre + half).astype(np.int64), 0, len(samples))
    power = np.r_[0.0, np.cumsum(samples**2)]
    count = np.maximum(hi - lo, 1)
    return np.sqrt((power[hi] - power[lo]) / count)


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

    in_process = True

    class Params(Stage.Params):
        #: a lip closure: inner-lip gap below this (IOD) ...
        closure_gap: float = Field(0.03, gt=0)
        #: ... for at least this many frames
        closure_frames: int = Field(2, ge=1)
        #: a closure is reproduced when the character's gap is at most this times the performer's
        closure_ratio: float = Field(1.2, gt=0)
        #: a blink: a dip of the eye aperture below this fraction of the take's open aperture (90th percentile) ...
        blink_ratio: float = Field(0.5, gt=0, lt=1)
        #: ... inside a narrowing below this fraction, no longer than blink_max_seconds (a longer one is a squint).
        #: 0.5 / 0.65 / 0.5 s find the 33 blinks marked by hand on the CREMA-D and talking-head clips (Face
        #: Landmarker v2 apertures), one event each and no false one (``python bench/eval_retarget.py --blinks``)
        blink_narrow_ratio: float = Field(0.65, gt=0, lt=1)
        #: frames of slack when matching blinks
        blink_tolerance: int = Field(1, ge=0)
        #: a narrowing longer than this (seconds) is a squint or closed eyes, not a blink
        blink_max_seconds: float = Field(0.5, gt=0)
        #: the performer's widest-jaw frames: this top fraction of each take ...
        widest_fraction: float = Field(0.1, gt=0, le=1)
        #: ... by the chin's drop in the head's frame (the JawOpen probe; the image's measure for a take without a
        #: FaceMesh) or in the image (chin to nose bridge over the eye distance, which a nod or a turn changes too)
        widest_by: Literal["head_frame", "image"] = "head_frame"
        #: lips apart: the performer's inner-lip gap above this (IOD) ...
        apart_gap: float = Field(0.1, gt=0)
        #: ... where a lip press (mouthPress*) above this is pressing lips that do not touch (``press_apart_fraction``)
        press_level: float = Field(0.2, gt=0, le=1)
        #: an ARKit column or morph is dead when its weight never exceeds this ...
        dead_level: float = Field(0.02, ge=0)
        #: ... and the performer made its movement when its probe (stages.retarget.movements) held above this
        #: (IOD) for moved_frames frames in a row, and above 4x its own frame-to-frame jitter
        moved_level: float = Field(0.02, gt=0)
        #: the same for a blink (the eye's closure, 0 open .. 1 shut) ...
        moved_closure: float = Field(0.5, gt=0, lt=1)
        #: ... and for gaze (degrees from the take's median direction)
        moved_degrees: float = Field(8.0, gt=0)
        moved_frames: int = Field(3, ge=1)
        #: the probes read the FaceMesh with a pinhole's perspective taken out, with the focal length that leaves
        #: each take's rigid points most rigid over the whole take (``estimated``, shapes3d.estimate_focal) or
        #: tracking's (``tracked``: its estimate from the take's first frames, or what it was given)
        probe_focal: Literal["estimated", "tracked"] = "estimated"
        #: the performer's rest for the probes and the rest-aligned errors: the closed-mouth frames' mean, the brows
        #: there too (``closed_mouth``) or at their median over the take (``median``); set it as the capture
        #: keyshapes' ``brow_rest`` (stages.retarget.face_measures.rest_pose)
        brow_rest: Literal["closed_mouth", "median"] = "closed_mouth"

        @model_validator(mode="after")
        def _narrowing_above_dip(self):
            if self.blink_narrow_ratio <= self.blink_ratio:
                raise ValueError(
                    f"blink_narrow_ratio ({self.blink_narrow_ratio}) must be above blink_ratio ({self.blink_ratio})"
                )
            return self

    inputs = {
        "tracks": Input.artifact(
            "landmarks",
            "rotation",
            "translation",
            "sequence",
            doc="tracking of the performance the blend animates (its FaceMesh, eye_aperture and gaze when present)",
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
            "mesh": tracks.lazy("mesh") if "mesh" in tracks else None,
            "audio": _take_audio(tracks, sequence),
            "fps": [float(f) for f in (meta.get("fps") or [30.0])],
            "time": np.asarray(tracks["time"], np.float64) if "time" in tracks else None,
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
            sequence = data["sequence"]
            if residual.shape[-1] == len(sequence):  # the decomposition of these very frames: per take too
                for take, label in zip(np.unique(sequence), results["meta"]["takes"]):
                    rows = residual[..., sequence == take]
                    results["meta"]["takes"][label]["metrics"]["keyshape_residual_rms_iod"] = float(
                        np.sqrt(np.mean(rows**2))
                    )
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
        start, stop = (int(v) for v in bounds[i]) if i < len(bounds) else (0, 0)
        # a take tracked without sound (audio: optional) has empty bounds: no envelope, rather than one of zeros
        if stop <= start or not per_take("audio_rate", i, None):
            out.append(None)
            continue
        out.append(
            (audio[start:stop], float(per_take("audio_rate", i, 0)), float(per_take("audio_offset", i, 0.0) or 0.0))
        )
    return out


def evaluate(params, **data) -> dict:
    """All the metrics from validated inputs (see the module docstring): pooled over the takes in ``metrics``,
    per take in ``meta["takes"]``."""
    sequence, weights, names = data["sequence"], data["weights"], data["names"]
    frames = posed_frames(data, params.brow_rest)
    context = event_context(params, data, frames)
    from stages.formats.live_link import ARKIT_NAMES, UNTRACKED_COLUMNS, arkit_weights

    arkit, _ = arkit_weights(weights, names, data["deltas"])
    columns = [c for c in ARKIT_NAMES if c not in UNTRACKED_COLUMNS]
    arkit = arkit[:, [ARKIT_NAMES.index(c) for c in columns]]
    takes, labels = {}, data["labels"]
    # the character's lids close as far as the eye aperture says, FaceMesh's lids less: gains outside blinks
    still_lids = outside_blinks(context["performer_blinks"] + context["character_blinks"], len(sequence))
    for take in np.unique(sequence):
        rows = sequence == take
        performer = performer_frame(data, rows, params)
        gaps = (context["performer_gap"][rows], context["character_gap"][rows])
        movements, probes = take_movements(data, rows, gaps[0], performer, params)
        widest_by = params.widest_by if performer is not None else "image"  # the head frame needs the FaceMesh
        if widest_by == "head_frame":
            use_jaw_opening(context, rows, probes["JawOpen"], sequence, params.widest_fraction)
        made, character_probes = None, {}
        if performer is not None:
            made, character_probes = character_movements(data, weights[rows], performer, gaps, params)
        dead = dead_where_moved(arkit, columns, movements, rows, params.dead_level, made)
        dead["made"] = sorted(c for c, m in (made or {}).items() if m["moved"])
        dead["made_not_moved"] = false_movements(movements, made)
        focal = None if performer is None else performer.focal
        label = labels[take] if take < len(labels) else f"take{take}"
        takes[label] = {
            "metrics": summary(params, data, frames, context, rows),
            "columns": dead,
            "movements": {c: [round(v["peak"], 4), round(v["level"], 4)] for c, v in movements.items()},
            "character_movements": {c: [round(m["peak"], 4), round(m["level"], 4)] for c, m in (made or {}).items()},
            "following": column_following(arkit[rows], columns, probes, movements),
            "movement_gains": movement_gains(probes, character_probes, movements, still_lids[rows]),
            "probe_focal_length": None if focal is None or not np.isfinite(focal) else round(focal, 1),
            "widest_by": widest_by,
        }
    metrics = summary(params, data, frames, context, np.ones(len(sequence), bool))
    metrics.update(pooled_dead(takes, arkit, columns, params.dead_level))
    metrics.update(pooled_false_movements(takes))
    metrics.update(pooled_following(takes))
    metrics.update(pooled_gains(takes))
    peak = weights.max(axis=0, initial=0.0)
    dead_morphs = [n for n, p in zip(names, peak) if p < params.dead_level]
    metrics["dead_morphs"] = float(len(dead_morphs))
    predicted = frames["predicted"]
    metrics["pose_rms_px"] = float(
        np.sqrt(np.mean((predicted[:, list(RIGID)] - data["landmarks"][:, list(RIGID)]) ** 2) * 2)
    )
    return pack_evaluation(metrics, takes, context, frames, dead_morphs, data)


def posed_frames(data, brow_rest: str = "closed_mouth") -> dict[str, np.ndarray]:
    """The character's landmark vertices posed with the tracked head and projected: the animation
    (``predicted``), the same rolled by half of each take (``shifted``) and the neutral face (``neutral``); with
    their error vectors against the tracked landmarks (``face_frame_errors``): ``absolute``, ``neutral_aligned``
    (less each take's error of the neutral face at the performer's rest: the fixed difference of two faces at
    rest, the brows' as ``brow_rest`` says: ``face_measures.rest_pose``), ``motion`` (less each take's mean error) and ``motion_shifted``."""
    from stages.retarget.face_measures import level, rest_frames, rest_pose

    sequence, tracked, weights = data["sequence"], data["landmarks"], data["weights"]
    neutral_points = character_landmarks(data["neutral"], data["deltas"], data["landmark_ids"], weights[:1] * 0)[0]
    to_model = align_to_model(neutral_points, data["model"])

    def project(w):
        points = to_model.apply(character_landmarks(data["neutral"], data["deltas"], data["landmark_ids"], w))
        return pose_and_project(points, data["rotation"], data["translation"], data["camera"])

    out = {"predicted": project(weights), "shifted": project(shift_within_takes(weights, sequence))}
    out["neutral"] = project(np.zeros_like(weights))
    out["absolute"] = face_frame_errors(out["predicted"], tracked)
    at_rest = face_frame_errors(out["neutral"], tracked)
    out["neutral_aligned"] = out["absolute"].copy()
    for take in np.unique(sequence):
        rows = np.flatnonzero(sequence == take)
        rest = rest_frames(level(tracked[rows]))
        out["neutral_aligned"][rows] -= rest_pose(at_rest[rows], rest, brow_rest)
    out["motion"] = remove_take_offsets(out["absolute"], sequence)
    out["motion_shifted"] = remove_take_offsets(face_frame_errors(out["shifted"], tracked), sequence)
    out["scale"] = np.array(to_model.scale)
    if data.get("mesh") is not None:
        points = character_landmarks(data["neutral"], data["deltas"], data["landmark_ids"], weights)
        out["face_posed"] = face_frame_errors(face_posed_projection(points, data), tracked)
    return out


def face_posed_projection(points: np.ndarray, data) -> np.ndarray:
    """``pose_on_tracked_face`` take by take (each take's FaceMesh read as one slice of the stored mesh)."""
    from stages.tracking.landmarks68 import mesh_to_ibug68

    out = np.empty(points.shape[:2] + (2,))
    for take in np.unique(data["sequence"]):
        rows = np.flatnonzero(data["sequence"] == take)
        mesh_points = mesh_to_ibug68(data["mesh"][rows[0] : rows[-1] + 1])
        out[rows] = pose_on_tracked_face(points[rows], mesh_points)
    return out


def event_context(params, data, frames) -> dict:
    """What the event metrics compare: lip gaps, eye apertures and their events (closures, blinks), the widest-jaw
    frames and the audio envelope, each for the whole sequence (events never cross a take boundary)."""
    sequence, tracked = data["sequence"], data["landmarks"]
    performer_gap, character_gap = lip_gap(tracked), lip_gap(frames["predicted"])
    closures = closure_agreement(
        performer_gap, character_gap, sequence, gap=params.closure_gap, frames=params.closure_frames,
        ratio=params.closure_ratio,
    )  # fmt: skip
    performer_aperture = data["aperture"] if data["aperture"] is not None else eye_aperture(tracked)
    character_aperture = eye_aperture(frames["predicted"])
    longest = blink_frame_limits(data["fps"], sequence, params.blink_max_seconds)
    ratios = (params.blink_ratio, params.blink_narrow_ratio)
    out = {
        "performer_gap": performer_gap,
        "character_gap": character_gap,
        "closures": closures,
        "performer_aperture": performer_aperture,
        "character_aperture": character_aperture,
        "performer_blinks": blink_events(performer_aperture, sequence, *ratios, longest),
        "character_blinks": blink_events(character_aperture, sequence, *ratios, longest),
        "jaw_opening": jaw_drop(tracked),  # the head frame's chin drop replaces it take by take (evaluate)
        "widest": widest_frames(jaw_drop(tracked), sequence, params.widest_fraction),
        "envelope": None,
        "envelope_r": {},
    }
    if data["audio"] is not None and any(a is not None for a in data["audio"]):
        out["envelope"], out["envelope_r"] = envelope_correlations(
            data, performer_gap, character_gap, lip_gap(frames["shifted"])
        )
    return out


def summary(params, data, frames, context, rows: np.ndarray) -> dict[str, float]:
    """The metrics over the frames ``rows`` (a take, or all of them)."""
    metrics: dict[str, float] = {}
    for region, points in EVAL_REGIONS.items():
        for name, key in (
            ("error_iod", "absolute"), ("neutral_error_iod", "neutral_aligned"), ("motion_error_iod", "motion"),
            ("motion_error_iod_shifted", "motion_shifted"),
        ):  # fmt: skip
            metrics[f"{region}_{name}"] = float(np.sqrt(np.mean(region_rms(frames[key][rows], points) ** 2)))
        if "face_posed" in frames:
            error = region_rms(frames["face_posed"][rows], points)
            metrics[f"{region}_face_posed_error_iod"] = float(np.sqrt(np.mean(error**2)))
    closures = [c for c in context["closures"] if rows[c["start"]]]
    metrics["closures"] = float(len(closures))
    metrics["closures_reproduced"] = float(sum(c["reproduced"] for c in closures))
    metrics["closure_gap_ratio_max"] = float(
        max((c["character_gap"] / c["performer_gap"] for c in closures), default=0.0)
    )
    blinks = event_agreement(
        [e for e in context["performer_blinks"] if rows[e[0]]],
        [e for e in context["character_blinks"] if rows[e[0]]],
        params.blink_tolerance,
    )
    metrics.update(
        blinks=float(blinks["reference"]), blinks_found=float(blinks["found"]), false_blinks=float(blinks["false"]),
        blink_recall=float(blinks["recall"]), false_blink_rate=float(blinks["false_rate"]),
    )  # fmt: skip
    metrics.update(jaw_metrics(data["weights"], data["names"], context["widest"][rows[context["widest"]]]))
    apart = np.flatnonzero(rows & (context["performer_gap"] > params.apart_gap))
    metrics.update(press_metrics(data["weights"], data["names"], apart, params.press_level))
    metrics.update(take_envelope(context, data["sequence"], rows))
    return metrics


def use_jaw_opening(context: dict, rows: np.ndarray, opening: np.ndarray, sequence: np.ndarray, fraction: float):
    """The take ``rows``' widest-jaw frames from ``opening`` (its frames' chin drop in the head frame) instead of
    the image's chin-to-nose-bridge distance over the eye distance, which the head's pose changes too: a turn of
    30 degrees narrows the eyes' distance by 13%, more than an open vowel's chin drop (5-11% at the widest frames
    of the CREMA-D and talking-head takes)."""
    context["jaw_opening"][rows] = opening
    context["widest"] = widest_frames(context["jaw_opening"], sequence, fraction)


def jaw_metrics(weights: np.ndarray, names: list[str], widest: np.ndarray) -> dict[str, float]:
    """jawOpen against mouthFunnel at the performer's widest-jaw frames (none when the character lacks them)."""
    jaw, funnel = find_morph(names, "jawOpen"), find_morph(names, "mouthFunnel")
    if jaw is None or funnel is None or not len(widest):
        return {}
    diff = weights[widest, jaw] - weights[widest, funnel]
    return {
        "jaw_minus_funnel": float(diff.mean()),
        "jaw_over_funnel_fraction": float((diff > 0).mean()),
        "jaw_open_at_widest": float(weights[widest, jaw].mean()),
    }


def press_metrics(weights: np.ndarray, names: list[str], apart: np.ndarray, level: float) -> dict[str, float]:
    """How often a lip press (mouthPress*, either side, above ``level``) presses lips that are apart: at the
    frames ``apart`` where the performer's lips are apart (none when the character has no press or the lips never
    part)."""
    press = [m for m in (find_side_morph(names, "mouthPress", side) for side in ("L", "R")) if m is not None]
    if not press or not len(apart):
        return {}
    return {"press_apart_fraction": float((weights[np.ix_(apart, press)].max(axis=1) > level).mean())}


def take_envelope(context, sequence: np.ndarray, rows: np.ndarray) -> dict[str, float]:
    """The envelope correlations of the takes among ``rows`` (their mean)."""
    takes = set(np.unique(sequence[rows]).tolist())
    out = {}
    for key, per_take in context["envelope_r"].items():
        values = [r for take, r in per_take.items() if take in takes]
        if values:
            out[key] = float(np.mean(values))
    return out


def pack_evaluation(metrics, takes, context, frames, dead_morphs, data) -> dict:
    """The evaluation's metrics, meta and arrays."""
    from stages.formats.live_link import ARKIT_NAMES

    columns: dict[str, dict[str, list[str]]] = {}
    for label, take in takes.items():
        for key, names in take["columns"].items():
            for name in names if key != "measured" else ():
                columns.setdefault(name, {}).setdefault(key, []).append(label)
    for label, take in takes.items():
        for key in ("dead_moved", "dead_not_moved", "dead_unmeasured"):
            take["metrics"][key.replace("dead_", "dead_arkit_")] = float(len(take["columns"][key]))
        missing = len(take["columns"]["dead_moved"]) - len(take["columns"]["dead_moved_made"])
        take["metrics"]["dead_arkit_moved_missing"] = float(missing)
        take["metrics"].update(pooled_false_movements({label: take}))
    blinks = event_agreement(context["performer_blinks"], context["character_blinks"], 0)
    meta = {
        "regions": list(EVAL_REGIONS),
        "labels": data["labels"],
        "takes": takes,
        "arkit_columns": {c: columns[c] for c in ARKIT_NAMES if c in columns},
        "dead_arkit_columns": sorted({c for t in takes.values() for c in t["columns"]["dead_moved"]}),
        "closures": context["closures"],
        "blinks": {"performer": context["performer_blinks"], "character": context["character_blinks"], **blinks},
        "blink_source": "tracking eye_aperture" if data["aperture"] is not None else "landmarks",
        "movement_source": "FaceMesh (3D)" if data.get("mesh") is not None else "2D landmarks",
        "widest_jaw_frames": context["widest"].tolist(),
        "dead_morphs": dead_morphs,
        "similarity_to_pose_model": {"scale": float(frames["scale"])},
    }
    region_error = np.stack([region_rms(frames["motion"], EVAL_REGIONS[r]) for r in EVAL_REGIONS], axis=1)
    arrays = {
        "landmarks": frames["predicted"],
        "region_error": region_error,
        "lip_gap": np.stack([context["performer_gap"], context["character_gap"]], axis=1),
        "eye_aperture": np.stack(
            [context["performer_aperture"].mean(axis=1), context["character_aperture"].mean(axis=1)], axis=1
        ),
    }
    if context["envelope"] is not None:
        arrays["envelope"] = context["envelope"]
    return {"metrics": metrics, "meta": meta, "arrays": arrays, "warnings": evaluation_warnings(data)}


def evaluation_warnings(data) -> list[str]:
    """What the evaluation could not measure, and why."""
    warnings = []
    if data.get("mesh") is None:
        warnings.append(
            "the tracking has no FaceMesh: whether the performer moved the face (dead ARKit columns) is measured for "
            "the eyes only (2D landmarks read a turn of the head as a sideways jaw or a frown), and the widest-jaw "
            "frames by the image (a turn of the head lengthens the chin's distance to the nose bridge too)"
        )
    if find_morph(data["names"], "jawOpen") is None or find_morph(data["names"], "mouthFunnel") is None:
        warnings.append("the character has no jawOpen/mouthFunnel morphs: jaw vs funnel not measured")
    audio = data["audio"] or [None] * len(data["labels"])
    silent = [label for label, take_audio in zip(data["labels"], audio) if take_audio is None]
    if silent:
        named = ", ".join(silent[:5]) + (f" and {len(silent) - 5} more takes" if len(silent) > 5 else "")
        warnings.append(f"no audio in {named}: the mouth's correlation with the sound is not measured there")
    return warnings


def envelope_correlations(data, performer_gap, character_gap, shifted_gap) -> tuple[np.ndarray, dict]:
    """Audio envelope per frame (a variable-frame-rate take's frames at their own times) and, per take, its
    correlation with each mouth opening."""
    from stages.export.timeline import frame_clock

    sequence = data["sequence"]
    envelope = np.zeros(len(sequence))
    r: dict[str, dict[int, float]] = {"envelope_r_character": {}, "envelope_r_performer": {}, "envelope_r_shifted": {}}
    for take in np.unique(sequence):
        audio = data["audio"][take] if take < len(data["audio"]) else None
        if audio is None:
            continue
        rows = np.flatnonzero(sequence == take)
        fps = data["fps"][take] if take < len(data["fps"]) else data["fps"][0]
        clock = None if data.get("time") is None else frame_clock(data["time"][rows], fps)  # None: a constant rate
        envelope[rows] = audio_envelope(audio[0], audio[1], audio[2], fps, len(rows), clock)
        for key, gap in (("character", character_gap), ("performer", performer_gap), ("shifted", shifted_gap)):
            r[f"envelope_r_{key}"][int(take)] = pearson(gap[rows], envelope[rows])
    return envelope, r
