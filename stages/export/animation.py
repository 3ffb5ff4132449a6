"""Export: what an animator opens. The retargeted morph weights (paper Eq 9) and the synthesised head motion
(Sec 5) on the character, as

- a GLB (glTF 2.0): the character with a morph-weight animation and, given head motion, rotation and translation
  on its ``Head`` node (valid for the Khronos glTF Validator: no errors, no warnings);
- a Live Link Face CSV: ``Timecode, BlendShapeCount``, the 52 ARKit blendshapes in PascalCase, then head and eye
  angles (61 values per row), as the Live Link Face app records them;
- a preview MP4: the character rendered (stages.geometry.render) at the pipeline fps with the take's audio muxed in;
- a BVH of the head joint, given head motion (stages.formats.bvh).

Streams are on one timeline: frame i of the blend weights is at i / fps seconds, the take's audio is placed by its
``audio_offset`` (start of the audio relative to the first video frame). A head motion at another frame rate is an
error unless ``resample_head`` is set (then it is resampled: slerp for rotation, linear for translation); a head
motion shorter or longer than the face animation by at most ``max_length_mismatch`` seconds is held at its last
frame or cut, more is an error.
"""

from __future__ import annotations

import io
from fractions import Fraction

import numpy as np
from pydantic import field_validator

from msflow import Input, Output, Result, Stage, UserError
from stages.formats.live_link import ARKIT_NAMES, UNTRACKED_COLUMNS, arkit_mapping, check_aliases, live_link_csv
from stages.geometry.rotations import quat_continuous, quat_normalize, quat_slerp, quat_to_euler

UNITS_TO_METRES = {"m": 1.0, "metre": 1.0, "meter": 1.0, "metres": 1.0, "meters": 1.0, "cm": 0.01, "mm": 0.001}


# ------------------------------------------------------------------------------------------------ timelines


def resample_head_motion(
    rotation: np.ndarray, translation: np.ndarray, source_fps: float, target_fps: float, frames: int
) -> tuple[np.ndarray, np.ndarray]:
    """Head motion sampled at ``frames`` instants i / target_fps: slerp between the neighbouring source frames
    for rotation, linear for translation; past the last source frame the last pose holds."""
    rotation = quat_continuous(quat_normalize(rotation))
    position = np.arange(frames) * (source_fps / target_fps)
    position = np.clip(position, 0, len(rotation) - 1)
    lo = np.floor(position).astype(np.int64)
    hi = np.minimum(lo + 1, len(rotation) - 1)
    frac = position - lo
    rot = quat_slerp(rotation[lo], rotation[hi], frac)
    trans = translation[lo] * (1 - frac)[:, None] + translation[hi] * frac[:, None]
    return rot, trans


def align_head_motion(
    rotation: np.ndarray,
    translation: np.ndarray,
    head_fps: float,
    fps: float,
    frames: int,
    *,
    resample: bool,
    max_mismatch: float,
    fps_tolerance: float = 1e-3,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """The head motion on the face animation's timeline (``frames`` at ``fps``): see the module docstring."""
    info: dict = {"head_fps": float(head_fps), "head_frames": int(len(rotation))}
    if abs(head_fps - fps) > fps_tolerance * fps:
        if not resample:
            raise UserError(
                f"frame-rate mismatch: head motion at {head_fps:g} fps, blend weights at {fps:g} fps; "
                f"resample the head motion (params.resample_head: true) or make the streams agree",
                field="inputs.head",
            )
        info["resampled"] = True
    head_duration = len(rotation) / head_fps
    duration = frames / fps
    shortfall = duration - head_duration
    if shortfall > max_mismatch or -shortfall > max_mismatch:
        raise UserError(
            f"head motion lasts {head_duration:.3f} s but the face animation {duration:.3f} s "
            f"(difference above params.max_length_mismatch = {max_mismatch:g} s)",
            field="inputs.head",
        )
    rot, trans = resample_head_motion(rotation, translation, head_fps, fps, frames)
    info["held_frames"] = int(max(0, frames - int(np.floor(head_duration * fps + 1e-9))))
    return rot, trans, info


def choose_take(labels: list[str], explicit: str | None, preferred: str | None, field: str) -> int:
    """Index of the take to use among ``labels``: the one named by params.sequence (must exist), else the one the
    blend's take is called (when present), else the only one; several takes and no way to choose is an error."""
    if explicit is not None:
        if labels and explicit not in labels:
            raise UserError(f"no take labelled '{explicit}' in {field}; labels: {labels}", field="params.sequence")
        return labels.index(explicit) if labels else 0
    if preferred is not None and preferred in labels:
        return labels.index(preferred)
    if len(labels) > 1:
        raise UserError(
            f"{field} holds several takes {labels}; choose one with params.sequence", field="params.sequence"
        )
    return 0


def take_audio(
    audio_view, explicit: str | None, preferred: str | None, fps: float, frames: int
) -> tuple[np.ndarray, int, dict]:
    """The chosen take's audio on the animation timeline: shifted by its audio_offset (leading silence or
    dropped samples) and cut or padded to ``frames / fps`` seconds."""
    meta = audio_view.meta
    if "audio" not in audio_view or "audio_bounds" not in audio_view:
        raise UserError("the audio input has no audio (its tracking ran without audio)", field="inputs.audio")
    labels = list(meta.get("labels") or [])
    index = choose_take(labels, explicit, preferred, "the audio input")

    def per_take(key, default=None):
        value = meta.get(key, default)
        return value[index] if isinstance(value, (list, tuple)) else value

    rate = per_take("audio_rate")
    if not rate:
        raise UserError("the audio input has no meta audio_rate", field="inputs.audio")
    rate = int(rate)
    take_fps = per_take("fps")
    if take_fps and abs(float(take_fps) - fps) > 1e-3 * fps:
        raise UserError(
            f"frame-rate mismatch: the take '{labels[index] if labels else index}' was tracked at "
            f"{float(take_fps):g} fps but the blend weights are at {fps:g} fps",
            field="inputs.audio",
        )
    bounds = np.asarray(audio_view["audio_bounds"])
    start, stop = (int(v) for v in bounds[index])
    samples = np.asarray(audio_view["audio"][start:stop], dtype=np.float32)
    offset = float(per_take("audio_offset", 0.0) or 0.0)
    shift = int(round(offset * rate))
    if shift > 0:
        samples = np.concatenate([np.zeros(shift, np.float32), samples])
    elif shift < 0:
        samples = samples[-shift:]
    length = int(round(frames / fps * rate))
    info = {
        "audio_label": labels[index] if labels else None,
        "audio_rate": rate,
        "audio_offset": offset,
        "audio_seconds_source": float((stop - start) / rate),
    }
    if len(samples) < length:
        samples = np.concatenate([samples, np.zeros(length - len(samples), np.float32)])
    return samples[:length], rate, info


# ------------------------------------------------------------------------------------------------ video


def video_codec_name(requested: str = "auto") -> str:
    """libx264 when PyAV's FFmpeg has it, else the built-in MPEG-4 Part 2 encoder."""
    import av

    available = av.codecs_available
    if requested != "auto":
        if requested not in available:
            raise UserError(f"video codec '{requested}' is not available in PyAV's FFmpeg", field="params.video_codec")
        return requested
    return "libx264" if "libx264" in available else "mpeg4"


def encode_mp4(
    frames,
    fps: float,
    size: tuple[int, int],
    *,
    audio: np.ndarray | None = None,
    audio_rate: int | None = None,
    codec: str = "auto",
    crf: int = 20,
) -> tuple[bytes, str]:
    """Encode RGB uint8 frames (an iterable of (H, W, 3)) and optional mono float audio into MP4 bytes."""
    import av

    codec = video_codec_name(codec)
    buffer = io.BytesIO()
    rate = Fraction(fps).limit_denominator(1001)
    with av.open(buffer, mode="w", format="mp4") as container:
        video = container.add_stream(codec, rate=rate)
        video.width, video.height = size
        video.pix_fmt = "yuv420p"
        video.codec_context.thread_count = 1  # one core, and byte-identical output from run to run
        if codec == "libx264":
            video.options = {"crf": str(crf), "preset": "medium"}
        else:
            video.codec_context.bit_rate = 2_000_000
        astream = None
        if audio is not None and len(audio):
            astream = container.add_stream("aac", rate=int(audio_rate))
            astream.layout = "mono"
        for index, rgb in enumerate(frames):
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
            # explicit timestamps: without them x264's rate control sees undefined frame times and the output
            # varies from run to run
            frame.pts = index
            frame.time_base = 1 / rate
            for packet in video.encode(frame):
                container.mux(packet)
        for packet in video.encode(None):
            container.mux(packet)
        if astream is not None:
            # explicit timestamps let the encoder mark its priming samples, which the MP4 edit list then skips:
            # the first audio sample plays with the first video frame
            if not astream.codec_context.is_open:
                astream.codec_context.open()
            step = astream.codec_context.frame_size or 1024
            samples = np.asarray(audio, np.float32).reshape(1, -1)
            for start in range(0, samples.shape[1], step):
                chunk = av.AudioFrame.from_ndarray(
                    np.ascontiguousarray(samples[:, start : start + step]), format="flt", layout="mono"
                )
                chunk.sample_rate = int(audio_rate)
                chunk.pts = start
                chunk.time_base = Fraction(1, int(audio_rate))
                for packet in astream.encode(chunk):
                    container.mux(packet)
            for packet in astream.encode(None):
                container.mux(packet)
    return buffer.getvalue(), codec


# ------------------------------------------------------------------------------------------------ the stage


def _select_frames(blend, explicit: str | None) -> tuple[np.ndarray, str | None]:
    """Rows of the blend weights for one take when the blend holds several (``sequence`` + meta labels), and
    the take's label (None when the blend does not name it)."""
    weights = np.asarray(blend["weights"], dtype=np.float64)
    labels = list(blend.meta.get("labels") or [])
    if "sequence" in blend and labels:
        sequence = np.asarray(blend["sequence"])
        present = [labels[i] for i in np.unique(sequence)]
        if len(present) > 1:
            index = choose_take(labels, explicit, None, "the blend")
            return weights[sequence == index], labels[index]
        return weights, present[0] if present else None
    return weights, (labels[0] if len(labels) == 1 else None)


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


def translation_scale(meta: dict, override: float | None) -> tuple[float | None, str]:
    """Metres per unit of the head translation: the param, else from meta translation_units. Undeclared units
    ("unknown", e.g. a BVH database without a stated unit) give None: the translation is left out, rotation
    stays. Declared units that are not lengths (pixels) are the user's to convert."""
    if override is not None:
        return float(override), "params.translation_scale"
    units = meta.get("translation_units", meta.get("units"))
    if units is None or str(units).lower() in ("", "unknown"):
        return None, "unknown: head translation left out (set params.translation_scale, metres per unit)"
    if str(units).lower() not in UNITS_TO_METRES:
        raise UserError(
            f"head translation is in '{units}', which has no known size in metres; set "
            f"params.translation_scale (metres per unit) or params.head_translation: none",
            field="params.translation_scale",
        )
    return UNITS_TO_METRES[str(units).lower()], str(units)


def select_take(
    view, names: tuple[str, ...], explicit: str | None, preferred: str | None, field: str
) -> tuple[list[np.ndarray], str | None]:
    """Rows of ``names`` for one take of an artifact holding several back to back (``sequence`` output + meta
    labels, e.g. motion_blend over several test utterances); an artifact with one take is used whole."""
    arrays = [np.asarray(view[n]) for n in names]
    labels = list(view.meta.get("labels") or [])
    if "sequence" not in view or len(labels) <= 1:
        return arrays, (labels[0] if labels else None)
    index = choose_take(labels, explicit, preferred, field)
    rows = np.asarray(view["sequence"]) == index
    return [a[rows] for a in arrays], labels[index]


class Export(Stage):
    """GLB with morph-weight (and head) animation, Live Link Face CSV, preview MP4 with audio, head BVH."""

    class Params(Stage.Params):
        #: take label: picks the take in a multi-take blend, head motion and audio input (their meta labels);
        #: default: the blend's take, or the only take
        sequence: str | None = None
        #: head motion at another frame rate than the blend: False = error, True = resample onto the blend's frames
        resample_head: bool = False
        #: longest tolerated difference in duration between head motion and face animation, seconds
        max_length_mismatch: float = 0.25
        #: "relative": head position minus its mean; "absolute": as given; "none": rotation only (also what
        #: happens when the head's translation_units are unknown and translation_scale is not set)
        head_translation: str = "relative"
        #: metres per unit of the head translation (default: from the head meta translation_units)
        translation_scale: float | None = None
        #: Live Link Face angle columns in "radians" or "degrees"
        angle_units: str = "radians"
        #: extra ARKit destinations for the character's morphs, {morph: {ARKit column: factor}}, taking
        #: precedence over the built-in rules (stages.formats.live_link); e.g. {smile_left: {MouthSmileLeft: 1}}
        arkit_aliases: dict[str, dict[str, float]] = {}

        @field_validator("arkit_aliases")
        @classmethod
        def _known_columns(cls, value):
            return check_aliases(value)

        preview: bool = True
        video_size: int = 384
        video_codec: str = "auto"
        #: "face" frames the landmarks, "head" the whole mesh
        framing: str = "face"
        view_yaw: float = 0.0
        supersample: int = 1

    inputs = {
        "character": Input.artifact("neutral", "triangles", "deltas", "landmark_ids", doc="stages.retarget.character"),
        "blend": Input.artifact("weights", doc="morph weights (frames, M) in [0, 1], meta target_names, fps"),
        "head": Input.artifact("rotation", "translation", optional=True, doc="head motion, meta fps"),
        "audio": Input.artifact(optional=True, doc="a tracking artifact with the take's audio"),
    }
    outputs = {
        "animation": Output.file(".glb", doc="the character with morph-weight and head animation"),
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
    }

    def run(self, params, inputs):
        from stages.formats.gltf import Animation, MaterialGroup, MorphMesh, write_morph_glb

        if params.head_translation not in ("relative", "absolute", "none"):
            raise UserError(
                "head_translation must be 'relative', 'absolute' or 'none'", field="params.head_translation"
            )
        if params.angle_units not in ("radians", "degrees"):
            raise UserError("angle_units must be 'radians' or 'degrees'", field="params.angle_units")
        if params.video_size < 16:
            raise UserError("video_size must be at least 16 pixels", field="params.video_size")
        character, blend, head, audio = inputs["character"], inputs["blend"], inputs["head"], inputs["audio"]
        char_names = list(character.meta.get("target_names") or [])
        deltas = np.asarray(character["deltas"], dtype=np.float32)
        if len(char_names) != len(deltas):
            raise UserError(
                f"character meta lists {len(char_names)} target names for {len(deltas)} morph targets",
                field="inputs.character",
            )
        fps = blend.meta.get("fps")
        if not fps or fps <= 0:
            raise UserError("the blend has no meta fps", field="inputs.blend")
        fps = float(fps)
        blend_weights, label = _select_frames(blend, params.sequence)
        blend_names = list(blend.meta.get("target_names") or [])
        if blend_weights.ndim != 2 or blend_weights.shape[1] != len(blend_names):
            raise UserError(
                f"blend weights {blend_weights.shape} do not match its {len(blend_names)} target names",
                field="inputs.blend",
            )
        frames = blend_weights.shape[0]
        if frames == 0:
            raise UserError("the blend has no frames", field="inputs.blend")
        weights = np.clip(character_weights(blend_weights, blend_names, char_names), 0.0, 1.0)
        clipped = float(np.mean((blend_weights < -1e-6) | (blend_weights > 1 + 1e-6)))  # of the blend's entries
        times = np.arange(frames) / fps
        meta: dict = {"fps": fps, "target_names": char_names, "take": label}
        warnings: list[str] = []
        metrics: dict = {"frames": frames, "duration_s": frames / fps, "clipped_fraction": clipped}

        rotation = translation = None
        if head is not None:
            head_fps = head.meta.get("fps")
            if not head_fps:
                raise UserError("the head motion has no meta fps", field="inputs.head")
            (head_rot, head_trans), head_label = select_take(
                head, ("rotation", "translation"), params.sequence, label, "the head motion"
            )
            rotation, translation, info = align_head_motion(
                head_rot.astype(np.float64),
                head_trans.astype(np.float64),
                float(head_fps),
                fps,
                frames,
                resample=params.resample_head,
                max_mismatch=params.max_length_mismatch,
            )
            rotation = quat_continuous(quat_normalize(rotation))
            info["take"] = head_label
            scale = None
            if params.head_translation != "none":
                scale, info["translation_units"] = translation_scale(head.meta, params.translation_scale)
            if scale is None:
                translation = np.zeros_like(translation)
            else:
                translation = translation * scale
                if params.head_translation == "relative":
                    translation = translation - translation.mean(axis=0)
            meta["head"] = info
            metrics["head_held_frames"] = info["held_frames"]
            metrics["head_translation_exported"] = int(scale is not None)

        groups_meta = character.meta.get("groups") or []
        groups = [
            MaterialGroup(g.get("name", f"group{i}"), tuple(g.get("color", (0.8, 0.8, 0.8, 1.0))))
            for i, g in enumerate(groups_meta)
        ]
        tri_groups = character["triangle_groups"] if "triangle_groups" in character else None
        pivot = tuple(float(v) for v in character.meta.get("pivot", (0.0, 0.0, 0.0)))
        mesh = MorphMesh(
            positions=np.asarray(character["neutral"], np.float32),
            triangles=np.asarray(character["triangles"], np.int32),
            target_names=char_names,
            deltas=deltas,
            triangle_groups=tri_groups,
            groups=groups,
            extras={"landmarkVertexIds": [int(i) for i in character["landmark_ids"]], "headPivot": list(pivot)},
            name="Character",
        )
        animation = Animation(times=times, weights=weights, rotation=rotation, translation=translation, pivot=pivot)
        glb = write_morph_glb(
            mesh,
            animation=animation,
            generator="msflow stages.export.animation",
            scene_extras={"fps": fps, "take": label},
        )

        mapping = arkit_mapping(char_names, deltas, params.arkit_aliases)
        arkit = mapping.weights(weights)
        head_angles = quat_to_euler(rotation) if rotation is not None else None
        if head_angles is not None and params.angle_units == "degrees":
            head_angles = np.degrees(head_angles)
        csv = live_link_csv(arkit, fps, head_angles)
        missing = [c for c in mapping.missing_columns if c not in UNTRACKED_COLUMNS]
        dropped = mapping.dropped(weights)
        meta["live_link"] = {
            "destinations": {n: d for n, d in mapping.destinations.items() if d},
            "rules": mapping.rule,
            "fitted_explained": mapping.explained,
            "columns_from": mapping.sources,
            "empty_columns": mapping.missing_columns,
            "dropped_morphs": dropped,
            "angle_units": params.angle_units,
        }
        metrics["live_link_columns_filled"] = len(mapping.sources)
        if missing:
            warnings.append(
                f"Live Link CSV: the character has no morph for the ARKit columns {missing} (written as 0); "
                f"name its equivalents in params.arkit_aliases"
            )
        if dropped:
            warnings.append(
                f"Live Link CSV: the morphs {dropped} move but have no ARKit column: dropped from the CSV "
                f"(kept in the GLB); give them one in params.arkit_aliases"
            )

        arrays = {
            "animation": glb,
            "live_link": csv,
            "weights": weights.astype(np.float32),
            "arkit": arkit.astype(np.float32),
            "time": times,
        }
        if rotation is not None:
            from stages.formats.bvh import head_bvh

            arrays["head_rotation"] = rotation
            arrays["head_translation"] = translation
            # BVH convention: centimetres
            arrays["head_bvh"] = head_bvh(rotation, translation * 100.0, fps).encode("utf-8")

        if params.preview:
            samples = rate = None
            if audio is not None:
                samples, rate, audio_info = take_audio(audio, params.sequence, label, fps, frames)
                meta["audio"] = audio_info
            video, codec = render_preview(character, weights, rotation, translation, fps, params, samples, rate)
            arrays["preview"] = video
            meta["video"] = {
                "codec": codec,
                "size": params.video_size // 2 * 2,
                "framing": params.framing,
                "audio": samples is not None,
            }
        metrics["glb_bytes"] = len(glb)
        return Result(arrays, meta=meta, metrics=metrics, warnings=warnings)


def render_preview(
    character, weights: np.ndarray, rotation, translation, fps: float, params, audio=None, audio_rate=None
) -> tuple[bytes, str]:
    """Render every frame (stages.geometry.render) and encode the MP4 (frames stream into the encoder one by one)."""
    from stages.geometry.render import CharacterRenderer

    size = int(params.video_size) // 2 * 2  # yuv420p needs even sides
    renderer = CharacterRenderer.from_artifact(
        character, size=size, framing=params.framing, yaw=params.view_yaw, supersample=params.supersample
    )
    frames = (
        renderer(weights[i], None if rotation is None else rotation[i], None if translation is None else translation[i])
        for i in range(len(weights))
    )
    return encode_mp4(frames, fps, (size, size), audio=audio, audio_rate=audio_rate, codec=params.video_codec)


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
