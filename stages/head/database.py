"""The head-motion database (paper Sec. 5, Fig. 5): pairs of speech audio and head motion, at one motion rate.

Three ingest stages share one output schema (``HEADDB_OUTPUTS``), so ``uses:`` swaps them:
- ``TrackedHeadDb``: video-derived head pose and demuxed audio from a tracking artifact;
- ``BvhHeadDb``: one named joint of BVH files (any channel order, ``Frame Time``) with audio files;
- ``CsvHeadDb``: ``time, rx, ry, rz, tx, ty, tz`` CSV files (degrees or radians, declared) with audio files.

The artifact follows the tracking artifact's audio conventions (``audio``, ``audio_bounds``, meta ``labels``,
``audio_rate``, ``audio_offset``, ``fps``), so the ``pitch`` stage reads a database and a test take through one
code path; pitch is a separate stage so that retuning it never re-ingests motion. Mirrored copies (the paper's
"mirror imaging the head motion") are extra sequences that share their original's audio range.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field

from msflow import Input, Output, Result, Stage, UserError
from stages.geometry.rotations import (
    euler_order_to_quat,
    mirror_quat,
    quat_conjugate,
    quat_continuous,
    quat_mean,
    quat_multiply,
    quat_normalize,
    quat_resample,
    quat_to_euler,
    quat_to_matrix,
)

HEADDB_OUTPUTS = {
    "rotation": Output.array(
        "f",
        shape=("frames", 4),
        dtype="float64",
        doc="unit quaternions (stages.geometry.rotations), relative to each sequence's mean pose "
        "when meta center is true",
    ),
    "translation": Output.array("f", shape=("frames", 3), dtype="float64", doc="glTF axes, meta translation_units"),
    "angles": Output.array("f", shape=("frames", 3), dtype="float64", doc="yaw, pitch, roll in radians"),
    "time": Output.array("f", shape=("frames",), dtype="float64", doc="seconds since the sequence's first frame"),
    "sequence": Output.array("i", shape=("frames",), dtype="int32", doc="index into meta labels"),
    "audio": Output.array("f", shape=("samples",), dtype="float32", doc="mono audio, meta audio_rate Hz"),
    "audio_bounds": Output.array(
        "i",
        shape=("sequences", 2),
        dtype="int64",
        doc="per sequence [start, stop) into audio; a mirrored copy shares its original's",
    ),
}


@dataclass
class Recording:
    """One take as ingested, before resampling: motion on its own clock, audio placed on that clock."""

    label: str
    source: str
    time: np.ndarray  # (n,) seconds, increasing; the first frame is the sequence's time 0
    rotation: np.ndarray  # (n, 4)
    translation: np.ndarray  # (n, 3)
    samples: np.ndarray  # (m,) float32 audio
    audio_rate: int
    audio_offset: float  # time of the first audio sample relative to the first motion frame
    field: str
    speaker: str | None = None  # the take's speaker label (field "speaker"), None when unlabelled


def check_motion_finite(rec: Recording) -> None:
    bad = ~(np.isfinite(rec.rotation).all(axis=1) & np.isfinite(rec.translation).all(axis=1))
    if bad.any():
        first = int(np.argmax(bad))
        raise UserError(
            f"NaN or Inf in the head motion of '{rec.label}' ({int(bad.sum())} frames, first at "
            f"{rec.time[first] - rec.time[0]:.3f} s, frame {first})",
            file=rec.source,
            field=rec.field,
        )
    if len(rec.time) < 2 or not np.all(np.diff(rec.time) > 0):
        raise UserError(
            f"motion of '{rec.label}' needs at least two frames with increasing times", file=rec.source, field=rec.field
        )


def check_lengths(rec: Recording, max_mismatch: float) -> None:
    """Audio and motion must cover about the same span (a wrong pairing of files shows up here)."""
    frame = float(np.median(np.diff(rec.time)))
    motion_length = rec.time[-1] - rec.time[0] + frame
    audio_length = len(rec.samples) / rec.audio_rate
    if abs(audio_length - motion_length) > max_mismatch:
        raise UserError(
            f"audio of '{rec.label}' lasts {audio_length:.3f} s but its motion {motion_length:.3f} s "
            f"(more than max_length_mismatch {max_mismatch} s apart: wrong pairing?)",
            file=rec.source,
            field=rec.field,
        )


def resample_motion(
    time: np.ndarray, rotation: np.ndarray, translation: np.ndarray, fps: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Slerp rotations and interpolate translations onto k / fps, k = 0 .. the last frame's time, give or take a
    tenth of a frame: container timestamps are rounded (to milliseconds in FLV), and the same rate must keep every
    frame."""
    t = time - time[0]
    n = int(np.floor(t[-1] * fps + 0.1)) + 1
    grid = np.arange(n) / fps
    rot = quat_resample(t, rotation, grid)
    trans = np.stack([np.interp(grid, t, translation[:, k]) for k in range(3)], axis=1)
    return grid, rot, trans


def smooth_motion(rotation: np.ndarray, translation: np.ndarray, sd_frames: float) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian smoothing over ``sd_frames`` frames: quaternion components on one hemisphere (valid for the small
    steps between frames), renormalised; translations alike. Removes tracking jitter, keeps head motion."""
    from scipy.ndimage import gaussian_filter1d

    q = gaussian_filter1d(quat_continuous(rotation), sd_frames, axis=0, mode="nearest")
    return quat_normalize(q), gaussian_filter1d(translation, sd_frames, axis=0, mode="nearest")


def lowpass_motion(
    rotation: np.ndarray, translation: np.ndarray, fps: float, cutoff: float, order: int = 4
) -> tuple[np.ndarray, np.ndarray]:
    """Zero-phase Butterworth low-pass (``order``, applied forwards and backwards: no delay, gain 1/2 at
    ``cutoff`` Hz and falling as (f / cutoff)^(2 order) above it) of the quaternion components (on one hemisphere,
    renormalised) and translations.

    Tracked head pose carries frame-to-frame jitter whose acceleration swamps that of the head's own motion
    (acceleration weighs a frequency f by f^4 in power), while head strokes -- nods and turns -- live below about 3 Hz.
    A cutoff above that band removes the jitter and leaves the strokes' timing and size alone, unlike a Gaussian
    smoothing strong enough to remove the same jitter. A cutoff at or above the Nyquist rate leaves the motion as
    it is."""
    from scipy.signal import butter, sosfiltfilt

    if cutoff >= 0.5 * fps or len(rotation) < 3:
        return rotation, translation
    sos = butter(order, cutoff / (0.5 * fps), output="sos")
    pad = min(3 * (2 * len(sos) + 1), len(rotation) - 1)
    q = sosfiltfilt(sos, quat_continuous(rotation), axis=0, padlen=pad)
    return quat_normalize(q), sosfiltfilt(sos, translation, axis=0, padlen=pad)


def center_motion(rotation: np.ndarray, translation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Motion relative to the sequence's mean pose, in the mean head's frame: q' = q_mean^* q,
    t' = R_mean^T (t - mean t). Takes with different resting poses can then be stitched."""
    q_mean = quat_mean(rotation)
    rel = quat_continuous(quat_multiply(quat_conjugate(q_mean), rotation))
    rel = np.where(rel[:1, :1] < 0, -rel, rel)
    r_mean = quat_to_matrix(q_mean)
    return rel, (translation - translation.mean(axis=0)) @ r_mean


def mirror_motion(rotation: np.ndarray, translation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mirror image about the face's mid-plane: negate yaw, roll and the sideways (x) translation."""
    return mirror_quat(rotation), translation * np.array([-1.0, 1.0, 1.0])


def cut_recording(rec: Recording, piece: float) -> list[Recording]:
    """``rec`` cut into nearly equal pieces of about ``piece`` seconds (one when shorter), each a take of its own:
    label and source ``name#k`` (k from 1), the same speaker. The audio is cut at each piece's first frame (the first
    piece keeps any audio before the take's first frame, the last any after its end), so the pieces' audio laid end
    to end is the take's."""
    rel = rec.time - rec.time[0]
    frame = float(np.median(np.diff(rel)))
    count = max(1, int(round((rel[-1] + frame) / piece)))
    if count == 1:
        return [rec]
    edges = np.linspace(0.0, rel[-1] + frame, count + 1)
    rows = [np.flatnonzero((rel >= edges[k] - 1e-9) & (rel < edges[k + 1] - 1e-9)) for k in range(count)]
    starts = [float(rel[r[0]]) for r in rows]
    cuts = [int(np.clip(np.ceil((t - rec.audio_offset) * rec.audio_rate - 1e-6), 0, len(rec.samples))) for t in starts]
    cuts = [0, *cuts[1:], len(rec.samples)]
    return [
        Recording(
            f"{rec.label}#{k + 1}",
            f"{rec.source}#{k + 1}",
            rec.time[rows[k]],
            rec.rotation[rows[k]],
            rec.translation[rows[k]],
            rec.samples[cuts[k] : cuts[k + 1]],
            rec.audio_rate,
            rec.audio_offset + cuts[k] / rec.audio_rate - starts[k],
            rec.field,
            rec.speaker,
        )
        for k in range(count)
    ]


def build_database(
    recordings: list[Recording],
    *,
    fps: float,
    mirror: bool,
    center: bool,
    max_length_mismatch: float,
    smoothing: float = 0.0,
    jitter_cutoff: float | None = None,
    piece: float | None = None,
    translation_units: str,
) -> Result:
    """Resample every recording to ``fps`` (after cutting it into pieces of about ``piece`` seconds), optionally
    low-pass and centre it and add its mirror image; one artifact."""
    audio_rate = _check_recordings(recordings, max_length_mismatch)
    if piece:
        recordings = [part for rec in recordings for part in cut_recording(rec, piece)]
    sequences = []
    audio_chunks, audio_cursor = [], 0
    for rec in recordings:
        grid, rot, trans = _prepared_motion(rec, fps, jitter_cutoff, smoothing, center)
        bounds = (audio_cursor, audio_cursor + len(rec.samples))
        audio_chunks.append(np.asarray(rec.samples, dtype=np.float32))
        audio_cursor = bounds[1]
        sequences.append((rec.label, rec, grid, rot, trans, bounds, False))
        if mirror:
            mrot, mtrans = mirror_motion(rot, trans)
            sequences.append((f"{rec.label}~mirror", rec, grid, mrot, mtrans, bounds, True))
    frames = [len(s[2]) for s in sequences]
    meta = {
        "labels": [s[0] for s in sequences],
        "sources": [s[1].source for s in sequences],
        "recordings": [s[1].label for s in sequences],
        "mirrored": [s[6] for s in sequences],
        "fps": float(fps),
        "frames": frames,
        "audio_rate": audio_rate,
        "audio_offset": [float(s[1].audio_offset) for s in sequences],
        "speakers": [s[1].speaker for s in sequences],
        "center": center,
        "translation_units": translation_units,
    }
    metrics = {
        "recordings": len(recordings),
        "speakers": len({r.speaker for r in recordings}),
        "sequences": len(sequences),
        "motion_seconds": float(sum(frames) / fps),
        "audio_seconds": float(audio_cursor / meta["audio_rate"]),
    }
    return Result(_database_arrays(sequences, audio_chunks), meta, metrics)


def _check_recordings(recordings: list[Recording], max_length_mismatch: float) -> int:
    """The recordings' one audio rate, after checking that there are some, that they share it, and that each one's
    motion is finite and about as long as its audio."""
    if not recordings:
        raise UserError("the database has no recordings", field="inputs")
    rates = {r.audio_rate for r in recordings}
    if len(rates) != 1:
        raise UserError(f"audio rates differ between recordings: {sorted(rates)}", field="inputs")
    for rec in recordings:
        check_motion_finite(rec)
        check_lengths(rec, max_length_mismatch)
    return int(rates.pop())


def _prepared_motion(
    rec: Recording, fps: float, jitter_cutoff: float | None, smoothing: float, center: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One recording's motion as the database holds it: resampled to ``fps``, then optionally low-passed,
    smoothed and centred on its mean pose; returns the time grid, rotations and translations."""
    grid, rot, trans = resample_motion(rec.time, quat_normalize(rec.rotation), rec.translation, fps)
    if jitter_cutoff:
        rot, trans = lowpass_motion(rot, trans, fps, jitter_cutoff)
    if smoothing > 0:
        rot, trans = smooth_motion(rot, trans, smoothing * fps)
    if center:
        rot, trans = center_motion(rot, trans)
    return grid, rot, trans


def _database_arrays(sequences: list[tuple], audio_chunks: list[np.ndarray]) -> dict[str, np.ndarray]:
    """The artifact's arrays: the sequences' motion laid end to end, and the audio with each sequence's range."""
    rotation = np.concatenate([s[3] for s in sequences])
    return {
        "rotation": rotation,
        "translation": np.concatenate([s[4] for s in sequences]),
        "angles": quat_to_euler(rotation),
        "time": np.concatenate([s[2] for s in sequences]),
        "sequence": np.concatenate([np.full(len(s[2]), k, np.int32) for k, s in enumerate(sequences)]),
        "audio": np.concatenate(audio_chunks),
        "audio_bounds": np.array([s[5] for s in sequences], dtype=np.int64).reshape(-1, 2),
    }


class HeadDbParams(Stage.Params):
    fps: float | None = Field(None, gt=0, description="motion rate of the database; None: the first take's own rate")
    mirror: bool = Field(True, description="add each take's mirror image (paper Sec. 6)")
    center: bool = Field(True, description="motion relative to each take's mean pose")
    max_length_mismatch: float = Field(
        0.5, ge=0, description="seconds allowed between the audio and motion lengths of a take"
    )
    smoothing: float = Field(
        0.0, ge=0, description="Gaussian smoothing (s, sd) of the motion against tracking jitter (0: none)"
    )
    jitter_cutoff: float | None = Field(
        5.0,
        gt=0,
        description="zero-phase low-pass (Hz) of the motion against tracking jitter, above the head-stroke band "
        "(None: as recorded, the paper)",
    )
    piece: float | None = Field(
        None,
        gt=0,
        description="cut every take into pieces of about this many seconds, each a take of its own (label#k), "
        "e.g. to leave one piece out with the speaker's other pieces in the database (None: whole takes)",
    )
    speaker: str | None = Field(
        None,
        min_length=1,
        description="speaker of the takes that carry no 'speaker' field (pitch is normalised per speaker); "
        "None: takes without the field stay unlabelled",
    )


def label_speakers(recordings: list[Recording], fields: dict, default: str | None) -> list[Recording]:
    """Each recording's speaker: its label's ``speaker`` field (contract: labelled files), else ``default``."""
    for rec in recordings:
        rec.speaker = (fields.get(rec.label) or {}).get("speaker") or default
    return recordings


TRACKS_DOC = "tracking artifact (stages/tracking/schema.py) with audio"


class TrackedHeadDb(Stage):
    """Database from tracking outputs: video head pose (rotation, translation) and each video's audio; the takes
    of ``tracks`` and, optionally, of a second tracking artifact ``more_tracks`` (say, another corpus)."""

    cheap = True

    class Params(HeadDbParams):
        labels: list[str] | None = Field(None, description="use only these sequences of the tracking artifacts")

    inputs = {
        "tracks": Input.artifact("rotation", "translation", "time", "sequence", doc=TRACKS_DOC),
        "more_tracks": Input.artifact("rotation", "translation", "time", "sequence", optional=True, doc=TRACKS_DOC),
    }
    outputs = HEADDB_OUTPUTS

    def run(self, params, inputs):
        views = [(name, inputs[name]) for name in ("tracks", "more_tracks") if inputs.get(name) is not None]
        recordings = []
        for name, view in views:
            wanted = (
                None if params.labels is None else [x for x in params.labels if x in (view.meta.get("labels") or [])]
            )
            found = recordings_from_tracking(view, wanted, field=f"inputs.{name}")
            recordings += label_speakers(found, view.meta.get("fields") or {}, params.speaker)
        check_labels(recordings, params.labels)
        fps = params.fps or _first(views[0][1].meta.get("fps"))
        if not fps:
            fps = 1.0 / float(np.median(np.diff(recordings[0].time)))
        return build_database(
            recordings,
            fps=float(fps),
            mirror=params.mirror,
            center=params.center,
            max_length_mismatch=params.max_length_mismatch,
            smoothing=params.smoothing,
            jitter_cutoff=params.jitter_cutoff,
            piece=params.piece,
            translation_units=str(views[0][1].meta.get("translation_units", "unknown")),
        )


def check_labels(recordings: list[Recording], wanted: list[str] | None) -> None:
    """Every take label once across the tracking artifacts, and every wanted label found."""
    labels = [r.label for r in recordings]
    twice = sorted({x for x in labels if labels.count(x) > 1})
    if twice:
        raise UserError(f"takes {twice} appear in both tracking artifacts; labels must be unique", field="inputs")
    missing = [x for x in (wanted or []) if x not in labels]
    if missing:
        raise UserError(f"labels {missing} are not in the tracking artifacts ({labels})", field="params.labels")


def _first(value):
    if isinstance(value, (list, tuple)):
        return value[0] if value else None
    return value


def recordings_from_tracking(view, labels: list[str] | None, field: str = "inputs.tracks") -> list[Recording]:
    """The takes ``labels`` (None: all) of a tracking artifact, each sequence's motion with its range of the audio;
    sequences without a label are named ``sequence<k>``."""
    meta = view.meta
    if "audio" not in view or "audio_bounds" not in view:
        raise UserError(
            "the tracking artifact has no audio; the head-motion database pairs motion with speech "
            "(track the videos with audio)",
            field=field,
        )
    sequence = np.asarray(view["sequence"])
    all_labels = _sequence_labels(meta, sequence)
    n = len(all_labels)
    wanted = list(labels) if labels is not None else all_labels
    unknown = [w for w in wanted if w not in all_labels]
    if unknown:
        raise UserError(f"labels {unknown} are not in the tracking artifact ({all_labels})", field="params.labels")
    sources = _per_sequence(meta, "sources", None, n)
    offsets = _per_sequence(meta, "audio_offset", 0.0, n)
    has_audio = _per_sequence(meta, "has_audio", True, n)
    rate = int(meta.get("audio_rate") or 16000)
    audio, bounds = view["audio"], np.asarray(view["audio_bounds"]).reshape(-1, 2)
    rotation, translation, time = view["rotation"], view["translation"], view["time"]
    out = []
    for label in wanted:
        k = all_labels.index(label)
        mask = sequence == k
        if not mask.any():
            raise UserError(f"sequence '{label}' has no frames", field=field)
        a, b = bounds[k]
        _check_take_audio(label, has_audio[k], a, b, sources[k], field)
        out.append(
            Recording(
                label,
                str(sources[k] or label),
                np.asarray(time[mask], dtype=np.float64),
                rotation[mask],
                translation[mask],
                np.asarray(audio[a:b], dtype=np.float32),
                rate,
                float(offsets[k] or 0.0),
                f"{field}[{label}]",
            )
        )
    return out


def _sequence_labels(meta: dict, sequence: np.ndarray) -> list[str]:
    """The labels of every sequence of a tracking artifact: meta ``labels``, ``sequence<k>`` for those beyond."""
    all_labels = list(meta.get("labels") or [])
    n = max(len(all_labels), int(sequence.max()) + 1 if len(sequence) else 0)
    return all_labels + [f"sequence{k}" for k in range(len(all_labels), n)]


def _per_sequence(meta: dict, key: str, default, n: int) -> list:
    """Meta ``key`` as one value per sequence: a list as is, a single value (or ``default``) repeated."""
    value = meta.get(key)
    if isinstance(value, (list, tuple)):
        return list(value)
    return [default if value is None else value] * n


def _check_take_audio(label: str, has_audio: bool, a: int, b: int, source, field: str) -> None:
    """A take of the database needs audio: the tracking saw some, and its range [a, b) is not empty."""
    if not has_audio or b <= a:
        raise UserError(
            f"take '{label}' has no audio (a silent video); the head-motion database pairs motion with speech",
            file=str(source or label),
            field=f"{field}[{label}]",
        )


def _paired(motion: dict, audio: dict, kind: str) -> list[tuple[str, object, object]]:
    if set(motion) != set(audio):
        raise UserError(
            f"{kind} and audio files must have the same labels; {kind} only: "
            f"{sorted(set(motion) - set(audio))}, audio only: {sorted(set(audio) - set(motion))}",
            field="inputs",
        )
    return [(label, motion[label], audio[label]) for label in motion]


def _decode(path, rate: int, label: str):
    from stages.formats.audio import decode_audio

    return decode_audio(path, rate, field=f"inputs.audio.{label}").samples


class FileHeadDbParams(HeadDbParams):
    audio_rate: int = Field(16000, ge=4000, le=192000, description="decoding rate of the audio files (Hz)")
    translation_scale: float = Field(1.0, gt=0, description="multiplies positions (e.g. 10 for cm -> mm)")
    translation_units: str = "unknown"
    audio_offset: dict[str, float] = {}  # per label: start of the audio relative to the first motion frame


class BvhHeadDb(Stage):
    """Database from BVH files (one named joint's local rotation and position) paired with audio files."""

    cheap = True

    class Params(FileHeadDbParams):
        joint: str = "Head"

    inputs = {
        "motion": Input.files(doc="labelled BVH files"),
        "audio": Input.files(doc="audio per label (WAV, FLAC, MP3 or any container PyAV decodes)"),
    }
    outputs = HEADDB_OUTPUTS

    def run(self, params, inputs):
        from stages.formats.bvh import joint_rotation, joint_translation, read_bvh

        recordings, rates = [], []
        for label, motion_path, audio_path in _paired(inputs["motion"], inputs["audio"], "motion"):
            field = f"inputs.motion.{label}"
            bvh = read_bvh(motion_path, field=field)
            rotation = joint_rotation(bvh, params.joint, field="params.joint")
            translation = joint_translation(bvh, params.joint, field="params.joint") * params.translation_scale
            rates.append(bvh.fps)
            recordings.append(
                Recording(
                    label,
                    motion_path.name,
                    np.arange(bvh.frames) * bvh.frame_time,
                    rotation,
                    translation,
                    _decode(audio_path, params.audio_rate, label),
                    params.audio_rate,
                    params.audio_offset.get(label, 0.0),
                    field,
                )
            )
        label_speakers(recordings, {**inputs["audio"].fields, **inputs["motion"].fields}, params.speaker)
        return build_database(
            recordings,
            fps=params.fps or rates[0],
            mirror=params.mirror,
            center=params.center,
            max_length_mismatch=params.max_length_mismatch,
            smoothing=params.smoothing,
            jitter_cutoff=params.jitter_cutoff,
            piece=params.piece,
            translation_units=params.translation_units,
        )


CSV_COLUMNS = ("time", "rx", "ry", "rz", "tx", "ty", "tz")


def read_motion_csv(path, *, angle_unit: str, rotation_order: str, field: str):
    """``time, rx, ry, rz, tx, ty, tz`` (header required, any column order, extra columns ignored).

    rx, ry, rz are angles about x, y, z composed as ``rotation_order`` lists them (default "YXZ": R = R_Y(ry)
    R_X(rx) R_Z(rz), the project's yaw-pitch-roll convention). Returns time, quaternions, translations.
    """
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
    except OSError as exc:
        raise UserError(f"cannot read CSV ({exc})", file=str(path), field=field) from None
    if not rows:
        raise UserError("empty CSV file", file=str(path), field=field)
    header = [h.strip().lower() for h in rows[0]]
    missing = [c for c in CSV_COLUMNS if c not in header]
    if missing:
        raise UserError(
            f"CSV lacks columns {missing}; needs {', '.join(CSV_COLUMNS)} (header row first)",
            file=str(path),
            field=field,
        )
    columns = [header.index(c) for c in CSV_COLUMNS]
    try:
        data = np.array(
            [[float(row[c]) for c in columns] for row in rows[1:] if any(x.strip() for x in row)], dtype=np.float64
        ).reshape(-1, len(CSV_COLUMNS))
    except (ValueError, IndexError) as exc:
        raise UserError(f"non-numeric or missing value in CSV ({exc})", file=str(path), field=field) from None
    angles = {"x": data[:, 1], "y": data[:, 2], "z": data[:, 3]}
    ordered = np.stack([angles[a] for a in rotation_order.lower()], axis=1)
    if angle_unit == "degrees":
        ordered = np.radians(ordered)
    return data[:, 0], euler_order_to_quat(ordered, rotation_order), data[:, 4:7]


class CsvHeadDb(Stage):
    """Database from CSV head motion (time on the audio's clock, angles, positions) paired with audio files."""

    cheap = True

    class Params(FileHeadDbParams):
        angle_unit: Literal["degrees", "radians"]
        rotation_order: Literal["XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"] = "YXZ"

    inputs = {
        "motion": Input.files(doc="labelled CSV files"),
        "audio": Input.files(doc="audio per label (WAV, FLAC, MP3 or any container PyAV decodes)"),
    }
    outputs = HEADDB_OUTPUTS

    def run(self, params, inputs):
        recordings, rates = [], []
        for label, motion_path, audio_path in _paired(inputs["motion"], inputs["audio"], "motion"):
            field = f"inputs.motion.{label}"
            time, rotation, translation = read_motion_csv(
                motion_path, angle_unit=params.angle_unit, rotation_order=params.rotation_order, field=field
            )
            if len(time) >= 2:
                rates.append(1.0 / float(np.median(np.diff(time))))
            # CSV times are on the audio's clock unless an offset is given: audio starts time[0] before frame 0
            offset = params.audio_offset.get(label, -float(time[0]) if len(time) else 0.0)
            recordings.append(
                Recording(
                    label,
                    motion_path.name,
                    time,
                    rotation,
                    translation * params.translation_scale,
                    _decode(audio_path, params.audio_rate, label),
                    params.audio_rate,
                    offset,
                    field,
                )
            )
        label_speakers(recordings, {**inputs["audio"].fields, **inputs["motion"].fields}, params.speaker)
        fps = params.fps or (rates[0] if rates else None)
        if not fps:
            raise UserError("cannot tell the motion rate (CSV with fewer than two rows); set fps", field="params.fps")
        return build_database(
            recordings,
            fps=fps,
            mirror=params.mirror,
            center=params.center,
            max_length_mismatch=params.max_length_mismatch,
            smoothing=params.smoothing,
            jitter_cutoff=params.jitter_cutoff,
            piece=params.piece,
            translation_units=params.translation_units,
        )
