"""The export's timeline: which take, which rows, and every stream sampled at the output frames.

Streams are on one clock: row i of the blend weights (and gaze) is at i / fps seconds; the head motion's row j at
j / head_fps; the take's audio starts ``audio_offset`` seconds after the first video frame. The output has
``frames_out = round(frames * out_fps / fps)`` frames at ``out_fps`` (default: the blend's rate), so it lasts as
long as the input; a stream is sampled at t_k = k / out_fps: linear interpolation between its two neighbouring
rows (slerp for rotations), the last row held past its end.

A head motion at another frame rate than the blend is an error unless ``resample_head`` is set; a head motion
shorter or longer than the face animation by at most ``max_length_mismatch`` seconds is held at its last frame or
cut, more is an error.

A tracked head's rotation is the camera's view of it: a phone held below the face reads as a head turned up for the
whole take. ``level_head`` takes the take's mean orientation out (the character then faces the viewer on average).
"""

from __future__ import annotations

import numpy as np

from msflow import UserError
from stages.geometry.rotations import (
    quat_conjugate,
    quat_continuous,
    quat_mean,
    quat_multiply,
    quat_normalize,
    quat_slerp,
)

UNITS_TO_METRES = {"m": 1.0, "metre": 1.0, "meter": 1.0, "metres": 1.0, "meters": 1.0, "cm": 0.01, "mm": 0.001}


def output_frames(frames: int, fps: float, out_fps: float) -> int:
    """Frames at ``out_fps`` covering the duration of ``frames`` at ``fps`` (at least one)."""
    return max(1, int(round(frames * out_fps / fps)))


def sample_positions(frames_out: int, out_fps: float, source_fps: float, source_frames: int) -> np.ndarray:
    """Fractional source row of each output frame k (time k / out_fps), clamped to the source's rows."""
    position = np.arange(frames_out) * (source_fps / out_fps)
    return np.clip(position, 0, source_frames - 1)


#: a take whose frame times stray from a constant rate's by more than this fraction of a frame has a variable
#: frame rate (a phone drops frames in dim light); a container's millisecond timestamps stray by 0.015 at 30 fps
VFR_TOLERANCE = 0.25


def frame_clock(times: np.ndarray | None, fps: float, field: str | None = None) -> np.ndarray | None:
    """A take's frame times (seconds from its first frame) when they are not a constant rate's, else None (rows
    are then at i / fps, as ``sample_positions`` has them). UserError naming ``field`` (the input the times came
    from) when they do not increase (``check_clock``)."""
    if times is None or len(times) < 2:
        return None
    clock = np.asarray(times, np.float64) - float(times[0])
    if np.abs(clock - np.arange(len(clock)) / fps).max() <= VFR_TOLERANCE / fps:
        return None
    check_clock(clock, field)
    return clock


#: frame rates a variable-frame-rate take's typical frame interval is snapped to (within 0.5%)
STANDARD_RATES = (23.976, 24.0, 25.0, 29.97, 30.0, 48.0, 50.0, 59.94, 60.0)


def check_clock(clock: np.ndarray | None, field: str | None) -> None:
    """Refuse frame times that do not increase from frame to frame: they give no rate to export at and no order
    to sample the rows by (a video re-encoded without timestamps, tracked before such files were re-timed)."""
    if clock is not None and not bool(np.all(np.diff(clock) > 0)):
        repeated = int(np.count_nonzero(np.diff(clock) <= 0))
        raise UserError(
            f"the take's frame times do not increase ({repeated} of {len(clock)} frames at or before the previous "
            f"frame's time; the video's timestamps are unusable): track the take again, which times such frames "
            f"by the video's frame rate",
            field=field,
        )


def nominal_rate(clock: np.ndarray, field: str) -> float:
    """The frame rate a variable-frame-rate take was shot at: the mean of its frame intervals up to 1.5 times the
    median (a dropped frame's longer interval left out; millisecond timestamps alternate 33 and 34 ms at 30 fps),
    snapped to a standard rate within 0.5%. UserError naming ``field`` (the input the clock came from) when the
    times do not increase (``check_clock``)."""
    check_clock(clock, field)
    steps = np.diff(clock)
    rate = 1.0 / float(steps[steps <= 1.5 * np.median(steps)].mean())
    nearest = min(STANDARD_RATES, key=lambda r: abs(r - rate))
    return nearest if abs(nearest - rate) <= 0.005 * nearest else rate


def clock_frames(clock: np.ndarray | None, rows: int, fps: float, out_fps: float) -> int:
    """Output frames covering a take of ``rows`` rows: ``output_frames``, or with a clock its span plus a frame."""
    if clock is None:
        return output_frames(rows, fps, out_fps)
    return max(1, int(round((clock[-1] + 1.0 / fps) * out_fps)))


def clock_positions(clock: np.ndarray | None, rows: int, fps: float, frames_out: int, out_fps: float) -> np.ndarray:
    """Fractional row of each output frame k (time k / out_fps): ``sample_positions``, or with a clock the row
    whose frame time it is (linear between the frames around it, the ends held)."""
    if clock is None:
        return sample_positions(frames_out, out_fps, fps, rows)
    return np.interp(np.arange(frames_out) / out_fps, clock, np.arange(rows, dtype=np.float64))


def take_clock(view, label: str | None, rows: int, fps: float, field: str | None = None) -> np.ndarray | None:
    """The ``frame_clock`` of take ``label`` of a tracking artifact (its ``time`` output, the input ``field``),
    when it has that take with ``rows`` frames; None otherwise (no clock: rows at a constant rate)."""
    if view is None or "time" not in view:
        return None
    labels = list(view.meta.get("labels") or [])
    if "sequence" in view and labels:
        label = labels[0] if label is None and len(labels) == 1 else label
        if label not in labels:
            return None
        times = np.asarray(view["time"])[np.asarray(view["sequence"]) == labels.index(label)]
    else:
        times = np.asarray(view["time"])
    return frame_clock(times, fps, field) if len(times) == rows else None


def sample_linear(values: np.ndarray, position: np.ndarray) -> np.ndarray:
    """Rows of ``values`` (frames, ...) at fractional rows ``position``: linear between neighbours.

    Integer positions return the rows exactly (no interpolation rounding).
    """
    values = np.asarray(values, dtype=np.float64)
    lo = np.floor(position).astype(np.int64)
    hi = np.minimum(lo + 1, len(values) - 1)
    frac = (position - lo).reshape((-1,) + (1,) * (values.ndim - 1))
    return np.where(frac == 0, values[lo], values[lo] * (1 - frac) + values[hi] * frac)


def sample_rotations(rotation: np.ndarray, position: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) at fractional rows ``position``: slerp between neighbours."""
    rotation = quat_continuous(quat_normalize(rotation))
    lo = np.floor(position).astype(np.int64)
    hi = np.minimum(lo + 1, len(rotation) - 1)
    return quat_slerp(rotation[lo], rotation[hi], position - lo)


def resample_head_motion(
    rotation: np.ndarray, translation: np.ndarray, source_fps: float, target_fps: float, frames: int
) -> tuple[np.ndarray, np.ndarray]:
    """Head motion sampled at ``frames`` instants i / target_fps: slerp between the neighbouring source frames
    for rotation, linear for translation; past the last source frame the last pose holds."""
    position = sample_positions(frames, target_fps, source_fps, len(rotation))
    return sample_rotations(rotation, position), sample_linear(translation, position)


def check_head_timing(
    head_frames: int, head_fps: float, frames: int, fps: float, *, resample: bool, max_mismatch: float
) -> dict:
    """Refuse a head motion whose rate or length does not fit the face animation (module docstring)."""
    info: dict = {"head_fps": float(head_fps), "head_frames": int(head_frames)}
    if abs(head_fps - fps) > 1e-3 * fps:
        if not resample:
            raise UserError(
                f"frame-rate mismatch: head motion at {head_fps:g} fps, blend weights at {fps:g} fps; "
                f"resample the head motion (params.resample_head: true) or make the streams agree",
                field="inputs.head",
            )
        info["resampled"] = True
    head_duration, duration = head_frames / head_fps, frames / fps
    if abs(duration - head_duration) > max_mismatch:
        raise UserError(
            f"head motion lasts {head_duration:.3f} s but the face animation {duration:.3f} s "
            f"(difference above params.max_length_mismatch = {max_mismatch:g} s)",
            field="inputs.head",
        )
    info["held_frames"] = int(max(0, frames - int(np.floor(head_duration * fps + 1e-9))))
    return info


def align_head_motion(
    rotation: np.ndarray,
    translation: np.ndarray,
    head_fps: float,
    fps: float,
    frames: int,
    *,
    resample: bool,
    max_mismatch: float,
    out_fps: float | None = None,
    frames_out: int | None = None,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """The head motion checked against the face animation (``frames`` at ``fps``) and sampled at the output
    frames (``frames_out`` at ``out_fps``, default the animation's span at ``fps``): see the module docstring."""
    info = check_head_timing(len(rotation), head_fps, frames, fps, resample=resample, max_mismatch=max_mismatch)
    out_fps = out_fps or fps
    frames_out = frames_out or output_frames(frames, fps, out_fps)
    rot, trans = resample_head_motion(rotation, translation, head_fps, out_fps, frames_out)
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


def select_take(
    view, names: tuple[str, ...], explicit: str | None, preferred: str | None, field: str
) -> tuple[list[np.ndarray | None], str | None]:
    """Rows of ``names`` for one take of an artifact holding several back to back (``sequence`` output + meta
    labels, e.g. a blend or motion_blend over several test utterances); an artifact with one take is used whole.
    A name the artifact does not have gives None."""
    arrays = [np.asarray(view[n]) if n in view else None for n in names]
    labels = list(view.meta.get("labels") or [])
    if "sequence" not in view or not labels:
        return arrays, (labels[0] if len(labels) == 1 else None)
    sequence = np.asarray(view["sequence"])
    present = [labels[i] for i in np.unique(sequence)]
    if len(present) <= 1:
        return arrays, (present[0] if present else None)
    index = choose_take(labels, explicit, preferred, field)
    rows = sequence == index
    return [None if a is None else a[rows] for a in arrays], labels[index]


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


def take_audio(
    audio_view, explicit: str | None, preferred: str | None, fps: float, seconds: float
) -> tuple[np.ndarray | None, int | None, dict]:
    """The chosen take's audio on the animation timeline: shifted by its audio_offset (leading silence or
    dropped samples) and cut or padded to ``seconds``. A silent take (no audio output, or meta has_audio false
    for it) gives (None, None, info with ``silent``)."""
    meta = audio_view.meta
    labels = list(meta.get("labels") or [])
    index = choose_take(labels, explicit, preferred, "the audio input")
    label = labels[index] if labels else None
    check_take_fps(meta, index, label, fps)
    if "audio" not in audio_view or "audio_bounds" not in audio_view or not take_has_audio(meta, index, label):
        return None, None, {"audio_label": label, "silent": True}

    def per_take(key, default=None):
        value = meta.get(key, default)
        return value[index] if isinstance(value, (list, tuple)) else value

    rate = per_take("audio_rate")
    if not rate:
        raise UserError("the audio input has no meta audio_rate", field="inputs.audio")
    rate = int(rate)
    start, stop = (int(v) for v in np.asarray(audio_view["audio_bounds"])[index])
    offset = float(per_take("audio_offset", 0.0) or 0.0)
    # only this take's samples are read (the artifact may hold many takes back to back)
    samples = np.asarray(audio_view.lazy("audio")[start:stop], dtype=np.float32)
    samples = place_audio(samples, rate, offset, seconds)
    info = {
        "audio_label": label,
        "audio_rate": rate,
        "audio_offset": offset,
        "audio_seconds_source": float((stop - start) / rate),
    }
    return samples, rate, info


def take_has_audio(meta: dict, index: int, label: str | None) -> bool:
    """meta has_audio of a take: {label: bool} (tracking contract), a per-take list, or one bool; absent: True."""
    has_audio = meta.get("has_audio", True)
    if isinstance(has_audio, dict):
        return bool(has_audio.get(label, True))
    if isinstance(has_audio, (list, tuple)):
        return bool(has_audio[index]) if index < len(has_audio) else True
    return bool(has_audio)


def check_take_fps(meta: dict, index: int, label: str | None, fps: float, field: str = "inputs.audio") -> None:
    """The take must have been tracked at the blend's frame rate (its frames are the blend's rows)."""
    take_fps = meta.get("fps")
    take_fps = take_fps[index] if isinstance(take_fps, (list, tuple)) else take_fps
    if take_fps and abs(float(take_fps) - fps) > 1e-3 * fps:
        raise UserError(
            f"frame-rate mismatch: the take '{label if label is not None else index}' was tracked at "
            f"{float(take_fps):g} fps but the blend weights are at {fps:g} fps",
            field=field,
        )


def place_audio(samples: np.ndarray, rate: int, offset: float, seconds: float) -> np.ndarray:
    """Audio whose first sample is ``offset`` seconds after the first video frame, on the video's clock from 0 to
    ``seconds``: leading silence (offset > 0) or dropped samples (offset < 0), then cut or padded with zeros."""
    shift = int(round(offset * rate))
    if shift > 0:
        samples = np.concatenate([np.zeros(shift, np.float32), samples])
    elif shift < 0:
        samples = samples[-shift:]
    length = int(round(seconds * rate))
    if len(samples) < length:
        samples = np.concatenate([samples, np.zeros(length - len(samples), np.float32)])
    return samples[:length]


def level_head(rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The head motion relative to its mean orientation: the camera's tilt taken out.

    A tracked rotation R(t) maps the head's axes to the camera's: R(t) = C H(t), with C the camera's tilt from
    level and H(t) the head's own orientation. Taking C as the mean orientation M (``quat_mean``: the head faces
    the camera on average), H(t) = M^-1 R(t). Positions stay in the camera's axes: a tracked head's image
    position is measured, its distance only estimated from its size (the lens's focal length, and the face's size
    changes as it nods), and turning them with M^-1 would carry that depth's error into the height.

    Parameters
    ----------
    rotation : ndarray (frames, 4)
        Unit quaternions (w, x, y, z), head to camera.

    Returns
    -------
    rotation : ndarray (frames, 4)
        The levelled rotation.
    mean : ndarray (4,)
        The orientation taken out (M).
    """
    mean = quat_mean(rotation)
    levelled = quat_multiply(quat_conjugate(mean), rotation)  # broadcast over the frames
    return quat_normalize(levelled), mean


def performer_rows(
    view, explicit: str | None, preferred: str | None, fps: float, frames_out: int, out_fps: float
) -> tuple[np.ndarray, str | None]:
    """Per output frame, the row of a tracking artifact (``view``) holding the chosen take's frame on screen at that
    time, the last one that started at or before it (the take tracked at ``fps``, the blend's source rate; output
    frames at ``out_fps``), and the take's label."""
    labels = list(view.meta.get("labels") or [])
    index = choose_take(labels, explicit, preferred, "the performer input")
    label = labels[index] if labels else None
    check_take_fps(view.meta, index, label, fps, field="inputs.performer")
    if "sequence" in view:
        rows = np.flatnonzero(np.asarray(view["sequence"]) == index)
    else:
        rows = np.arange(len(view.lazy("crops")))
    clock = frame_clock(np.asarray(view["time"])[rows], fps, "inputs.performer") if "time" in view else None
    position = clock_positions(clock, len(rows), fps, frames_out, out_fps)
    return rows[np.floor(position + 1e-9).astype(int)], label
