"""Export: what an animator opens. The retargeted morph weights (paper Eq 9), the synthesised head motion (Sec 5)
and the gaze on the character, as

- a GLB (glTF 2.0, valid for the Khronos glTF Validator: no errors, no warnings): the character skinned to a
  ``Root`` joint, a ``Head`` joint at the head pivot carrying the head rotation and translation, and an eye joint
  per eyeball carrying the gaze when the character has eyes (stages.export.rig); the morph-weight animation on the
  mesh. Every vertex but the eyeballs' follows the head with weight 1;
- a Live Link Face CSV (stages.formats.live_link): the 52 ARKit blendshapes from the character's morphs through the
  public ARKit mapping, head and eye angles (radians by default), exact timecodes;
- a BVH of the head joint, given head motion (stages.formats.bvh), in centimetres and degrees;
- a preview MP4 (stages.export.preview): the character rendered with the take's audio.

Every file is sampled at the output frame rate ``fps`` (default: the blend's); see stages.export.timeline for how
the streams are aligned and resampled. docs/formats.md states every convention and unit.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from msflow import Input, Output, Result, Stage, UserError
from stages.export.timeline import (
    align_head_motion,
    clock_frames,
    clock_positions,
    frame_clock,
    level_head,
    nominal_rate,
    sample_linear,
    sample_rotations,
    select_take,
    take_clock,
    translation_scale,
)
from stages.formats.live_link import ARKIT_NAMES, UNTRACKED_COLUMNS, ArkitMapping, arkit_mapping, check_aliases
from stages.geometry.held_gaps import ease_into_found_face, found_again_spans
from stages.geometry.rotations import quat_continuous, quat_normalize, quat_to_euler, quat_to_rotvec

#: preview levels: "full" renders every triangle at params.video_size; "low" renders half the pixels of each side
PREVIEW_LEVELS = ("low", "full")


@dataclass
class Performance:
    """The take as exported: every stream on the output timeline (``frames`` at ``fps``)."""

    label: str | None
    fps: float
    weights: np.ndarray  # (frames, targets) in the character's target order, in [0, 1]
    rotation: np.ndarray | None = None  # (frames, 4) head rotation (w, x, y, z)
    translation: np.ndarray | None = None  # (frames, 3) head translation, metres, as exported
    gaze: np.ndarray | None = None  # (frames, 2, 2) degrees, [left, right][yaw, pitch up]
    meta: dict = field(default_factory=dict)
    metrics: dict = field(default_factory=dict)

    @property
    def frames(self) -> int:
        return len(self.weights)

    @property
    def times(self) -> np.ndarray:
        return np.arange(self.frames) / self.fps


# ------------------------------------------------------------------------------------------------ validate


def character_targets(character) -> tuple[list[str], np.ndarray]:
    """The character's morph names and (targets, V, 3) deltas, checked against each other."""
    names = list(character.meta.get("target_names") or [])
    deltas = np.asarray(character["deltas"], dtype=np.float32)
    if len(names) != len(deltas):
        raise UserError(
            f"character meta lists {len(names)} target names for {len(deltas)} morph targets",
            field="inputs.character",
        )
    return names, deltas


def blend_take(blend, sequence: str | None) -> tuple[np.ndarray, np.ndarray | None, str | None, float]:
    """The chosen take's rows of the blend: weights (frames, M), gaze (frames, 2, 2) or None, label, fps."""
    fps = blend.meta.get("fps")
    if not fps or fps <= 0:
        raise UserError("the blend has no meta fps", field="inputs.blend")
    (weights, gaze), label = select_take(blend, ("weights", "gaze"), sequence, None, "the blend")
    weights = np.asarray(weights, dtype=np.float64)
    names = list(blend.meta.get("target_names") or [])
    if weights.ndim != 2 or weights.shape[1] != len(names):
        raise UserError(
            f"blend weights {weights.shape} do not match its {len(names)} target names", field="inputs.blend"
        )
    if len(weights) == 0:
        raise UserError("the blend has no frames", field="inputs.blend")
    if gaze is not None and np.shape(gaze) != (len(weights), 2, 2):
        raise UserError(f"blend gaze {np.shape(gaze)}, expected ({len(weights)}, 2, 2)", field="inputs.blend")
    return weights, gaze, label, float(fps)


def character_weights(blend_weights: np.ndarray, blend_names: list[str], character_names: list[str]) -> np.ndarray:
    """Blend weights re-ordered to the character's targets; targets the blend does not drive stay 0."""
    unknown = [n for n in blend_names if n not in character_names]
    if unknown:
        raise UserError(
            f"the blend drives morph targets the character does not have: {unknown[:10]}", field="inputs.blend"
        )
    out = np.zeros((blend_weights.shape[0], len(character_names)))
    out[:, [character_names.index(n) for n in blend_names]] = blend_weights
    return out


def ease_held_head(head, label, rotation: np.ndarray, translation: np.ndarray, fps: float, params):
    """The take's head eased from the pose the tracker held through each long gap into the one it found after it
    (``stages.geometry.held_gaps``; the head input's meta gaps, a tracking artifact's); and how many gaps."""
    labels, gaps = list(head.meta.get("labels") or []), head.meta.get("gaps")
    if not gaps or label not in labels:
        return rotation, translation, 0
    one_take = np.zeros(len(rotation), np.int64)
    spans = found_again_spans(one_take, [gaps[labels.index(label)]], [float(fps)], params.held_gap_ease)
    return ease_into_found_face(rotation, spans, rotations=True), ease_into_found_face(translation, spans), len(spans)


def head_motion(head, params, label: str | None, frames: int, fps: float, out_fps: float, frames_out: int):
    """Head rotation and translation (metres, as exported) on the output timeline (``frames_out`` at ``out_fps``),
    and what was done. A tracked head of a variable-frame-rate take is sampled by its frame times."""
    head_fps = head.meta.get("fps")
    (rotation, translation, times), head_label = select_take(
        head, ("rotation", "translation", "time"), params.sequence, label, "the head motion"
    )
    if isinstance(head_fps, (list, tuple)) and head_fps:  # a tracking artifact as the head motion: one rate per take
        labels = list(head.meta.get("labels") or [])
        head_fps = head_fps[labels.index(head_label)] if head_label in labels else head_fps[0]
    if not isinstance(head_fps, (int, float)) or head_fps <= 0:  # its rows' times and lengths divide by it
        raise UserError(f"the head motion has no usable meta fps (got {head_fps!r})", field="inputs.head")
    rotation, translation = np.asarray(rotation, np.float64), np.asarray(translation, np.float64)
    rotation, translation, eased = ease_held_head(head, head_label, rotation, translation, head_fps, params)
    clock = frame_clock(times, float(head_fps), "inputs.head")  # a tracked head's frame times
    if clock is None:
        rotation, translation, info = align_head_motion(
            rotation,
            translation,
            float(head_fps),
            fps,
            frames,
            resample=params.resample_head,
            max_mismatch=params.max_length_mismatch,
            out_fps=out_fps,
            frames_out=frames_out,
        )
    else:  # the tracked head of a variable-frame-rate take: each output frame at its time
        position = clock_positions(clock, len(rotation), float(head_fps), frames_out, out_fps)
        rotation, translation = sample_rotations(rotation, position), sample_linear(translation, position)
        info = {"head_fps": float(head_fps), "head_frames": len(clock), "held_frames": 0, "frame_times": True}
    info["take"], info["held_gaps_eased"] = head_label, eased
    scale = None
    if params.head_translation != "none":
        scale, info["translation_units"] = translation_scale(head.meta, params.translation_scale)
    if scale is None:
        translation = np.zeros_like(translation)
    else:
        translation = translation * scale
        if params.head_translation == "relative":
            translation = translation - translation.mean(axis=0)
    info["translation_exported"] = scale is not None
    if params.head_rotation == "relative":
        rotation, mean = level_head(rotation)
        info["orientation_taken_out_deg"] = dict(
            zip(("yaw", "pitch", "roll"), np.degrees(quat_to_euler(mean)).round(3).tolist())
        )
        info["levelled_deg"] = float(np.degrees(np.linalg.norm(quat_to_rotvec(mean))))
    return quat_continuous(quat_normalize(rotation)), translation, info


#: inputs whose tracking may carry the take's frame times (``timeline.take_clock``), in this order
CLOCKS = ("audio", "performer", "head")


def read_performance(params, inputs, names: list[str]) -> Performance:
    """Validate the blend and head inputs and put every stream on the output timeline."""
    blend_weights, gaze, label, fps = blend_take(inputs["blend"], params.sequence)
    weights = character_weights(blend_weights, list(inputs["blend"].meta.get("target_names")), names)
    clipped = float(np.mean((blend_weights < -1e-6) | (blend_weights > 1 + 1e-6)))  # of the blend's entries
    # a variable-frame-rate take (its tracking's frame times) is put on the output timeline by those times, at
    # the rate it was shot at unless params.fps says otherwise (its average rate is no camera's)
    clocks = ((n, take_clock(inputs[n], label, len(weights), fps, f"inputs.{n}")) for n in CLOCKS)
    source, clock = next(((n, c) for n, c in clocks if c is not None), ("", None))
    out_fps = float(params.fps or (fps if clock is None else nominal_rate(clock, f"inputs.{source}")))
    frames_out = clock_frames(clock, len(weights), fps, out_fps)
    position = clock_positions(clock, len(weights), fps, frames_out, out_fps)
    perf = Performance(
        label,
        out_fps,
        np.clip(sample_linear(weights, position), 0.0, 1.0),
        gaze=None if gaze is None else sample_linear(gaze, position),
        meta={
            "fps": out_fps,
            "source_fps": fps,
            "target_names": names,
            "take": label,
            "variable_frame_rate": clock is not None,
        },
        metrics={"frames": frames_out, "duration_s": frames_out / out_fps, "clipped_fraction": clipped},
    )
    if inputs["head"] is not None:
        perf.rotation, perf.translation, info = head_motion(
            inputs["head"], params, label, len(weights), fps, out_fps, frames_out
        )
        perf.meta["head"] = info
        perf.metrics["head_held_frames"] = info["held_frames"]
        perf.metrics["head_translation_exported"] = int(info.pop("translation_exported"))
        if "levelled_deg" in info:  # the mean orientation taken out (head_rotation: relative)
            perf.metrics["head_levelled_deg"] = info["levelled_deg"]
    return perf


# ------------------------------------------------------------------------------------------------ pack


def character_mesh(character, names: list[str], deltas: np.ndarray):
    """The character as a stages.formats.gltf MorphMesh (materials, landmark ids and pivot in its extras)."""
    from stages.formats.gltf import MaterialGroup, MorphMesh

    groups = [
        MaterialGroup(g.get("name", f"group{i}"), tuple(g.get("color", (0.8, 0.8, 0.8, 1.0))))
        for i, g in enumerate(character.meta.get("groups") or [])
    ]
    return MorphMesh(
        positions=np.asarray(character["neutral"], np.float32),
        triangles=np.asarray(character["triangles"], np.int32),
        target_names=names,
        deltas=deltas,
        triangle_groups=character["triangle_groups"] if "triangle_groups" in character else None,
        groups=groups,
        extras={
            "landmarkVertexIds": [int(i) for i in character["landmark_ids"]],
            "headPivot": list(pivot_of(character)),
        },
        name="Character",
    )


def pivot_of(character) -> tuple[float, float, float]:
    return tuple(float(v) for v in character.meta.get("pivot", (0.0, 0.0, 0.0)))


def character_eyes(character):
    """The character's eyeballs (stages.export.rig.find_eyes), [] without eye material groups."""
    from stages.export.rig import find_eyes

    groups = [g.get("name", "") for g in character.meta.get("groups") or []]
    triangle_groups = character["triangle_groups"] if "triangle_groups" in character else None
    return find_eyes(character["neutral"], character["triangles"], triangle_groups, groups)


def pack_glb(mesh, perf: Performance, eyes, skin: bool, pivot) -> bytes:
    """The GLB: the skinned character (root, head and eye joints) or the plain node layout, with the animation."""
    from stages.export.rig import EYE_JOINTS, character_skeleton, gaze_rotations
    from stages.formats.gltf import Animation, write_morph_glb

    joint_rotations = {}
    if skin and eyes and perf.gaze is not None:
        rotations = gaze_rotations(perf.gaze)
        joint_rotations = {EYE_JOINTS[eye.side]: rotations[:, eye.side] for eye in eyes}
    animation = Animation(
        times=perf.times,
        weights=perf.weights,
        rotation=perf.rotation,
        translation=perf.translation,
        pivot=pivot,
        joint_rotations=joint_rotations,
    )
    return write_morph_glb(
        mesh,
        animation=animation,
        skeleton=character_skeleton(len(mesh.positions), pivot, eyes) if skin else None,
        generator="msflow stages.export.animation",
        scene_extras={"fps": perf.fps, "take": perf.label},
    )


def angles_in(radians: np.ndarray | None, units: str) -> np.ndarray | None:
    return None if radians is None else np.degrees(radians) if units == "degrees" else radians


def pack_live_link(perf: Performance, mapping: ArkitMapping, angle_units: str) -> tuple[bytes, np.ndarray]:
    """The Live Link Face CSV and its (frames, 52) ARKit weights."""
    from stages.export.rig import gaze_euler
    from stages.formats.live_link import live_link_csv

    arkit = mapping.weights(perf.weights)
    head = angles_in(quat_to_euler(perf.rotation) if perf.rotation is not None else None, angle_units)
    eyes = angles_in(gaze_euler(perf.gaze).reshape(perf.frames, 6) if perf.gaze is not None else None, angle_units)
    return live_link_csv(arkit, perf.fps, head, eyes), arkit


def live_link_report(mapping: ArkitMapping, weights: np.ndarray, angle_units: str) -> tuple[dict, list[str]]:
    """meta["live_link"] and the warnings about missing ARKit columns and dropped morphs."""
    missing = [c for c in mapping.missing_columns if c not in UNTRACKED_COLUMNS]
    dropped = mapping.dropped(weights)
    meta = {
        "destinations": {n: d for n, d in mapping.destinations.items() if d},
        "rules": mapping.rule,
        "fitted_explained": mapping.explained,
        "columns_from": mapping.sources,
        "empty_columns": mapping.missing_columns,
        "dropped_morphs": dropped,
        "angle_units": angle_units,
    }
    warnings = []
    if missing:
        warnings.append(
            f"Live Link CSV: the character has no morph for the ARKit columns {first_few(missing, 'empty_columns')}"
            f" (written as 0); name its equivalents in params.arkit_aliases"
        )
    if dropped:
        warnings.append(
            f"Live Link CSV: the morphs {first_few(dropped, 'dropped_morphs')} move but have no ARKit column: "
            f"dropped from the CSV (kept in the GLB); give them one in params.arkit_aliases"
        )
    return meta, warnings


#: names a warning lists before pointing at the meta entry that holds them all (a character without ARKit morphs
#: misses 51 columns: one line of them is unreadable)
WARNED_NAMES = 8


def first_few(names: list[str], meta_entry: str) -> str:
    """``names`` for a warning: all of them when few, else the first WARNED_NAMES and where the rest are."""
    if len(names) <= WARNED_NAMES:
        return str(names)
    more = len(names) - WARNED_NAMES
    return f"{names[:WARNED_NAMES]} and {more} more (msflow show STAGE: meta live_link.{meta_entry} lists them all)"


def posed_face(character, perf: Performance) -> np.ndarray:
    """The character's landmark vertices in every output frame, posed (``render.posed_points``): what the "face"
    framing must hold, so a nod or a lean does not take the face out of the picture."""
    from stages.geometry.render import posed_points

    return posed_points(
        character["neutral"],
        character["deltas"],
        character["landmark_ids"],
        perf.weights,
        perf.rotation,
        perf.translation,
        np.asarray(pivot_of(character)),
    )


def pack_preview(
    character, perf: Performance, eyes, params, audio_view, jobs: int, performer_view=None
) -> tuple[bytes, dict, list[str]]:
    """The preview MP4 with the take's audio (and the performer's face crops beside the character, given their
    tracking), its meta and warnings (a silent take)."""
    from stages.export.preview import Poses, beside_performer, encode_mp4, rendered_frames
    from stages.export.rig import gaze_rotations
    from stages.export.timeline import performer_rows, take_audio
    from stages.geometry.render import CharacterRenderer

    samples = rate = None
    meta: dict = {}
    warnings = []
    if audio_view is not None:
        seconds = perf.frames / perf.fps
        samples, rate, meta["audio"] = take_audio(
            audio_view, params.sequence, perf.label, perf.meta["source_fps"], seconds
        )
        if samples is None:
            warnings.append(f"the take '{meta['audio']['audio_label']}' has no audio: the preview is silent")
    size = int(params.video_size) // (2 if params.preview == "low" else 1) // 2 * 2  # yuv420p needs even sides
    renderer = CharacterRenderer.from_artifact(
        character,
        size=size,
        framing=params.framing,
        face_points=posed_face(character, perf) if params.framing == "face" else None,
        yaw=params.view_yaw,
        supersample=params.supersample,
        eyes=[(eye.vertices, eye.center) for eye in eyes],
    )
    eye_rotations = gaze_rotations(perf.gaze) if eyes and perf.gaze is not None else None
    poses = Poses(perf.weights, perf.rotation, perf.translation, eye_rotations)
    frames = rendered_frames(renderer, poses, jobs=jobs)
    width, performer = size, None
    if performer_view is not None:
        rows, performer = performer_rows(
            performer_view, params.sequence, perf.label, perf.meta["source_fps"], perf.frames, perf.fps
        )
        frames, width = beside_performer(frames, performer_view.lazy("crops"), rows, size), 2 * size
    video, codec = encode_mp4(frames, perf.fps, (width, size), audio=samples, audio_rate=rate, codec=params.video_codec)
    meta["video"] = {"codec": codec, "size": size, "framing": params.framing, "level": params.preview}
    meta["video"]["performer"] = performer
    meta["video"]["audio"] = samples is not None
    return video, meta, warnings


# ------------------------------------------------------------------------------------------------ the stage


class Export(Stage):
    """GLB with morph-weight, head and eye animation, Live Link Face CSV, preview MP4 with audio, head BVH."""

    in_process = True  # its preview's render processes (long takes) watch the process that started them

    class Params(Stage.Params):
        #: take label: picks the take in a multi-take blend, head motion and audio input (their meta labels);
        #: default: the blend's take, or the only take
        sequence: str | None = None
        #: output frame rate of every file (e.g. 24, 25, 30, 60); default: the blend's
        fps: float | None = Field(None, gt=0, le=240)
        #: head motion at another frame rate than the blend: False = error, True = resample onto the blend's frames
        resample_head: bool = False
        #: longest tolerated difference in duration between head motion and face animation, seconds
        max_length_mismatch: float = Field(0.25, ge=0)
        #: where the tracker held the head through a long gap (the head input's meta gaps) and found it again, the
        #: last this many seconds of the gap turn from the held pose into the found one instead of jumping; 0: jump
        held_gap_ease: float = Field(0.25, ge=0, le=10)
        #: "relative": head position minus its mean; "absolute": as given; "none": rotation only (also what
        #: happens when the head's translation_units are unknown and translation_scale is not set)
        head_translation: Literal["relative", "absolute", "none"] = "relative"
        #: "relative": the head's rotation relative to its mean orientation over the take (a camera below or above
        #: the face, which makes a tracked head look up or down throughout, taken out: the character faces the
        #: viewer on average; positions stay in the camera's axes); "absolute": as given (a tracked head: as the
        #: camera saw it)
        head_rotation: Literal["relative", "absolute"] = "relative"
        #: metres per unit of the head translation (default: from the head meta translation_units)
        translation_scale: float | None = Field(None, gt=0)
        #: Live Link Face angle columns (head and eyes) in "radians" or "degrees"
        angle_units: Literal["radians", "degrees"] = "radians"
        #: extra ARKit destinations for the character's morphs, {morph: {ARKit column: factor}}, taking
        #: precedence over the built-in rules (stages.formats.live_link); e.g. {smile_left: {MouthSmileLeft: 1}}
        arkit_aliases: dict[str, dict[str, float]] = {}
        #: GLB layout: True = skinned to Root/Head/eye joints (Unreal keeps morph targets on skinned meshes only);
        #: False = a Head node over the mesh node
        skin: bool = True
        #: preview video: False (none), "low" (half the size) or "full"
        preview: Literal[False, "low", "full"] = "full"
        video_size: int = Field(384, ge=16, le=4096)
        video_codec: Literal["auto", "libx264", "mpeg4"] = "auto"
        #: "face" frames the landmarks, "head" the whole mesh
        framing: Literal["face", "head"] = "face"
        #: camera yaw about the character, radians
        view_yaw: float = Field(0.0, ge=-np.pi, le=np.pi)
        #: render k times larger and average k x k blocks (anti-aliasing at k^2 the cost)
        supersample: int = Field(1, ge=1, le=4)

        @field_validator("arkit_aliases")
        @classmethod
        def _known_columns(cls, value):
            return check_aliases(value)

        @field_validator("preview", mode="before")
        @classmethod
        def _preview_true_is_full(cls, value):
            return "full" if value is True else value

    inputs = {
        "character": Input.artifact("neutral", "triangles", "deltas", "landmark_ids", doc="stages.retarget.character"),
        "blend": Input.artifact(
            "weights", doc="morph weights (frames, M) in [0, 1], meta target_names, fps; optional gaze (frames, 2, 2)"
        ),
        "head": Input.artifact("rotation", "translation", optional=True, doc="head motion, meta fps"),
        "audio": Input.artifact(optional=True, doc="a tracking artifact with the take's audio"),
        "performer": Input.artifact(
            "crops",
            optional=True,
            doc="a tracking artifact: the take's face crops go beside the character in the preview (twice as wide)",
        ),
    }
    outputs = {
        "animation": Output.file(".glb", doc="the skinned character with morph-weight, head and eye animation"),
        "live_link": Output.file(".csv", doc="Live Link Face CSV, 61 values per frame"),
        "preview": Output.file(".mp4", optional=True, doc="rendered preview with the take's audio"),
        "head_bvh": Output.file(".bvh", optional=True, doc="the head joint's motion"),
        "weights": Output.array(
            "f",
            shape=("frames", "targets"),
            dtype="float32",
            doc="morph weights in the character's target order, as exported",
        ),
        "arkit": Output.array(
            "f", shape=("frames", len(ARKIT_NAMES)), dtype="float32", doc="the 52 Live Link Face blendshape columns"
        ),
        "time": Output.array("f", shape=("frames",), dtype="float64", doc="seconds"),
        "head_rotation": Output.array(
            "f",
            shape=("frames", 4),
            dtype="float64",
            optional=True,
            doc="head rotation on the animation timeline (w, x, y, z)",
        ),
        "head_translation": Output.array(
            "f", shape=("frames", 3), dtype="float64", optional=True, doc="head translation as exported, metres"
        ),
        "gaze": Output.array(
            "f", shape=("frames", 2, 2), dtype="float32", optional=True, doc="gaze as exported, degrees"
        ),
    }

    def run(self, params, inputs):
        character = inputs["character"]
        names, deltas = character_targets(character)
        perf = read_performance(params, inputs, names)
        eyes = character_eyes(character)
        meta, metrics, warnings = perf.meta, perf.metrics, []
        meta["eyes"] = [{"side": e.side, "center": e.center.tolist(), "radius": e.radius} for e in eyes]
        if perf.gaze is not None and not (eyes and params.skin):
            warnings.append(
                "the character has no eye joints (no eye material groups, or params.skin false): "
                "gaze goes to the Live Link CSV only"
            )
        mapping = arkit_mapping(names, deltas, params.arkit_aliases)
        csv, arkit = pack_live_link(perf, mapping, params.angle_units)
        meta["live_link"], mapping_warnings = live_link_report(mapping, perf.weights, params.angle_units)
        warnings += mapping_warnings
        metrics["live_link_columns_filled"] = len(mapping.sources)
        glb = pack_glb(character_mesh(character, names, deltas), perf, eyes, params.skin, pivot_of(character))
        metrics["glb_bytes"] = len(glb)
        arrays = {
            "animation": glb,
            "live_link": csv,
            "weights": perf.weights.astype(np.float32),
            "arkit": arkit.astype(np.float32),
            "time": perf.times,
        }
        if perf.gaze is not None:
            arrays["gaze"] = perf.gaze.astype(np.float32)
        if perf.rotation is not None:
            from stages.formats.bvh import head_bvh

            arrays["head_rotation"] = perf.rotation
            arrays["head_translation"] = perf.translation
            arrays["head_bvh"] = head_bvh(perf.rotation, perf.translation * 100.0, perf.fps).encode("utf-8")
        if params.preview:
            arrays["preview"], video_meta, video_warnings = pack_preview(
                character, perf, eyes, params, inputs["audio"], self.jobs, inputs["performer"]
            )
            meta.update(video_meta)
            warnings += video_warnings
        return Result(arrays, meta=meta, metrics=metrics, warnings=warnings)


def plot_curves(view, inputs=None):
    """Morph weights over time (the ten most active targets) and the head angles."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    weights = view["weights"]
    time = view["time"]
    names = view.meta["target_names"]
    top = np.argsort(-weights.mean(axis=0))[:10]
    has_head = "head_rotation" in view
    fig, axes = plt.subplots(2 if has_head else 1, 1, figsize=(9, 5 if has_head else 3), sharex=True, squeeze=False)
    for i in top:
        axes[0, 0].plot(time, weights[:, i], label=names[i], lw=1)
    axes[0, 0].set_ylabel("morph weight")
    axes[0, 0].set_ylim(0, 1)
    axes[0, 0].legend(fontsize=7, ncol=2, loc="upper right")
    if has_head:
        angles = np.degrees(quat_to_euler(view["head_rotation"]))
        for k, name in enumerate(("yaw", "pitch", "roll")):
            axes[1, 0].plot(time, angles[:, k], label=name, lw=1)
        axes[1, 0].set_ylabel("head angle (deg)")
        axes[1, 0].legend(fontsize=7)
    axes[-1, 0].set_xlabel("time (s)")
    fig.tight_layout()
    return fig


def preview_video(view, inputs=None):
    return view.bytes("preview") if "preview" in view else None


Export.figures = {"curves": plot_curves, "preview": preview_video}
