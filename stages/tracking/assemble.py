"""What every tracking implementation shares once it has 68 points per frame: gap filling, head pose, face
crops, audio, and the concatenated TRACKING_OUTPUTS result with its metadata and quality metrics."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, field_validator

from msflow import Result, UserError
from msflow.stage import Params
from stages.geometry.rotations import quat_conjugate, quat_multiply, quat_to_euler, quat_to_rotvec
from stages.tracking.crops import apply_transforms, similarity_transform, similarity_transforms
from stages.tracking.face3d import DEFAULT_FACE3D, Face3D, load_face3d
from stages.tracking.landmarks68 import NOSE_BRIDGE_TOP
from stages.tracking.pose import camera_matrix, solve_head_pose
from stages.tracking.takes import AudioSource, TakeAudio, load_take_audio

NonNegativeSeconds = Annotated[float, Field(ge=0, allow_inf_nan=False)]


class TrackingParams(Params):
    """Parameters every tracking implementation shares."""

    max_gap_frames: int = Field(
        15,
        ge=0,
        description="longest run of frames without a face that is interpolated; longer runs are held (see long_gaps)",
    )
    long_gaps: Literal["hold", "error"] = Field(
        "hold",
        description="a run of frames without a face longer than max_gap_frames: 'hold' keeps the last tracked "
        "face (landmarks, pose, crop) through it, marked valid = False and listed in meta['gaps'] with a warning; "
        "'error' fails naming the frames",
    )
    focal_length: float | Literal["estimated"] | None = Field(
        "estimated",
        description="camera focal length in pixels for head pose; 'estimated': the one that leaves the FaceMesh's "
        "rigid points most rigid over the take's first FOCAL_FRAMES frames (shapes3d.estimate_focal: cropped "
        "talking heads are filmed with far longer lenses than the frame width, and a wrong focal length reads "
        "about 0.8 of a head turn; trackers and track files without a mesh get the frame width); None: the frame "
        "width (about 53 degrees horizontal field of view)",
    )
    pose_landmarks: Literal["eyes_nose", "rigid", "all"] = Field(
        "eyes_nose",
        description="landmarks solvePnP fits: 'eyes_nose' = the eye corners and the nose's nine points "
        "(landmarks68.RIGID; mouth and brows excluded so expressions do not tilt the head), 'rigid' = the ICT "
        "FaceKit rigid subset (the same eye corners, the nose bridge and wings, and the jaw line's two ends: the "
        "tracker's jaw ends slide along the jaw as the head nods, and held fixed they read about 0.6 of a nod on "
        "a head turned by known angles, docs/tracking.md), 'all' = the 68 points",
    )

    @field_validator("focal_length", mode="before")
    @classmethod
    def _focal_length(cls, value):
        """One message naming every choice, rather than one per member of the union."""
        if value is None or value == "estimated":
            return value
        try:
            number = float(value)
        except (TypeError, ValueError):
            number = float("nan")
        if not 0 < number < float("inf"):
            raise ValueError("give a focal length in pixels (> 0), 'estimated' or null")
        return number

    crop_size: int = Field(128, ge=16, le=1024, description="side of the square grayscale face crops (pixels)")
    crop_eye_distance: float = Field(
        0.30, gt=0.05, lt=0.9, description="distance between the eye centres in the crop, as a fraction of crop_size"
    )
    crop_eye_height: float = Field(
        0.33, gt=0.0, lt=1.0, description="height of the eye line in the crop, as a fraction of crop_size from the top"
    )
    audio: Literal["required", "optional", "none"] = Field(
        "required",
        description="each video's audio track: 'required' fails on a video without one, "
        "'optional' goes without, 'none' skips audio",
    )
    audio_rate: int = Field(16000, ge=4000, le=192000, description="audio sample rate of the 'audio' output (Hz)")
    audio_offset: NonNegativeSeconds | dict[str, NonNegativeSeconds] = Field(
        0.0,
        description="where each take's video starts in its separate audio file (inputs.audio), in seconds from "
        "the file's first sample: one number for every take or {label: seconds}",
    )
    audio_tolerance: NonNegativeSeconds = Field(
        0.25, description="seconds the audio may end before the video does; more is an error naming the file"
    )


@dataclass
class SequenceTrack:
    """One labelled sequence after tracking and gap filling."""

    label: str
    source: str
    landmarks: np.ndarray  # (n, 68, 2) float64, gaps filled
    valid: np.ndarray  # (n,) bool: a face was found (False = interpolated)
    confidence: np.ndarray  # (n,)
    time: np.ndarray  # (n,) seconds since the first frame
    fps: float
    frame_size: tuple[int, int]
    field: str
    mesh: np.ndarray | None = None  # (n, 468, 3)
    crops: np.ndarray | None = None  # (n, c, c) uint8
    crop_transforms: np.ndarray | None = None
    video: Path | None = None  # the tracked video, when there is one
    audio_source: AudioSource | None = None  # where the take's audio comes from (stages.tracking.takes)
    rotation: np.ndarray | None = None  # pose from the track file, when used
    translation: np.ndarray | None = None
    gaps: list = field(default_factory=list)  # long gaps held: [start, stop) frame ranges
    meta: dict = field(default_factory=dict)


class CropCollector:
    """Face crops made while the video streams past: a frame with landmarks is cropped at once; a frame without
    waits (kept in memory) until the gap is filled. Runs longer than ``max_pending`` are not kept: a long gap
    holds the crop of the frame it holds."""

    def __init__(self, params: TrackingParams, max_pending: int):
        self.size = params.crop_size
        self.eye_distance = params.crop_eye_distance
        self.eye_height = params.crop_eye_height
        self.max_pending = max_pending
        self.crops: list[np.ndarray | None] = []
        self.transforms: list[np.ndarray | None] = []
        self.pending: dict[int, np.ndarray] = {}
        self.run = 0

    def transform(self, landmarks: np.ndarray) -> np.ndarray:
        return similarity_transform(landmarks, self.size, self.eye_distance, self.eye_height)

    def add(self, image, landmarks: np.ndarray | None) -> None:
        """Next frame (``planes.FramePlanes``, or anything with ``warp_gray``) and its landmarks (None: no face)."""
        if landmarks is not None:
            m = self.transform(landmarks)
            self.crops.append(image.warp_gray(m, self.size))
            self.transforms.append(m)
            self.run = 0
            return
        self.crops.append(None)
        self.transforms.append(None)
        self.run += 1
        if self.run <= self.max_pending:
            from stages.tracking.stream import luma_copy

            self.pending[len(self.crops) - 1] = luma_copy(image)

    def finish(self, landmarks: np.ndarray, sources: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(crops (n, c, c) uint8, transforms (n, 2, 3)) once every frame has (filled) landmarks. A frame of a
        long gap (no picture kept) copies the crop of the frame it holds (``sources``, from gaps.gap_plan)."""
        if len(landmarks) != len(self.crops):
            raise ValueError(f"{len(landmarks)} landmark frames for {len(self.crops)} video frames")
        for i, crop in enumerate(self.crops):
            if crop is None and i in self.pending:
                m = self.transform(landmarks[i])
                self.crops[i] = self.pending.pop(i).warp_gray(m, self.size)
                self.transforms[i] = m
        for i, crop in enumerate(self.crops):
            if crop is None:
                self.crops[i], self.transforms[i] = self.crops[sources[i]], self.transforms[sources[i]]
        n = len(self.crops)
        return (
            np.array(self.crops, dtype=np.uint8).reshape(n, self.size, self.size),
            np.array(self.transforms, dtype=np.float64).reshape(n, 2, 3),
        )


def resolve_face3d(files: dict | None) -> tuple[Face3D, str]:
    """The 3D face for pose: the optional ``face3d`` input (one JSON file) or the project's ICT landmarks."""
    if files:
        if len(files) != 1:
            raise UserError(f"give one 3D face file, got {len(files)}", field="inputs.face3d")
        label, path = next(iter(files.items()))
        return load_face3d(path, field=f"inputs.face3d.{label}"), Path(path).name
    return load_face3d(DEFAULT_FACE3D), DEFAULT_FACE3D.name


def assumed_focal(params: TrackingParams) -> float | None:
    """The focal length the pose starts from: the one given, or None (the frame width) when it is estimated
    from the take (``focal_length: estimated``, ``stream.BlockWriter``) or not given."""
    return None if params.focal_length == "estimated" else params.focal_length


def pose_point_indices(params: TrackingParams, face3d: Face3D) -> np.ndarray | None:
    """The landmarks the head pose is fitted to (``pose_landmarks``); None: all 68."""
    from stages.tracking.landmarks68 import RIGID

    if params.pose_landmarks == "eyes_nose":
        return np.asarray(RIGID, dtype=np.int64)
    if params.pose_landmarks == "all" or not face3d.rigid:
        return None
    return np.asarray(face3d.rigid, dtype=np.int64)


def rotation_steps_deg(q: np.ndarray) -> np.ndarray:
    """Angle (degrees) between consecutive rotations."""
    if len(q) < 2:
        return np.zeros(0)
    rel = quat_multiply(quat_conjugate(q[:-1]), q[1:])
    return np.degrees(np.linalg.norm(quat_to_rotvec(rel), axis=-1))


def inter_ocular(landmarks: np.ndarray) -> np.ndarray:
    """Outer-eye-corner distance (iBUG 36-45) per frame: the 300-W normalisation."""
    return np.linalg.norm(landmarks[..., 36, :] - landmarks[..., 45, :], axis=-1)


def sequence_stats(seq: TakeTrack) -> dict:
    nose = seq.landmarks[:, NOSE_BRIDGE_TOP]
    both = seq.valid[1:] & seq.valid[:-1]
    steps = np.linalg.norm(np.diff(nose, axis=0), axis=1)[both]
    second = np.linalg.norm(nose[2:] - 2 * nose[1:-1] + nose[:-2], axis=1) / 2
    second = second[seq.valid[2:] & seq.valid[1:-1] & seq.valid[:-2]]
    iod = float(np.mean(inter_ocular(seq.landmarks)))
    rotation, rms = seq.rotation, seq.pose_rms
    euler = np.degrees(quat_to_euler(rotation))
    pose_steps = rotation_steps_deg(rotation)
    return {
        "frames": int(len(seq.valid)),
        "valid_frames": int(seq.valid.sum()),
        "interpolated_frames": int((~seq.valid).sum()),
        "inter_ocular_px": iod,
        "nose_step_px": float(steps.mean()) if steps.size else 0.0,
        "nose_jitter_px": float(second.mean()) if second.size else 0.0,
        "max_abs_yaw_deg": float(np.abs(euler[:, 0]).max()),
        "max_abs_pitch_deg": float(np.abs(euler[:, 1]).max()),
        "max_abs_roll_deg": float(np.abs(euler[:, 2]).max()),
        "max_pose_step_deg": float(pose_steps.max()) if pose_steps.size else 0.0,
        "pose_rms_px": float(rms.mean()),
    }


def pose_of(
    seq: SequenceTrack, params: TrackingParams, face3d: Face3D
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """(rotation, translation, reprojection RMS, focal length) of one sequence: solvePnP of its landmarks, or
    the pose its track file carried (the RMS still measures how well the 3D face fits the landmarks)."""
    w, h = seq.frame_size
    camera = camera_matrix(w, h, assumed_focal(params))
    rot, trans, rms = solve_head_pose(seq.landmarks, face3d.neutral, camera, pose_point_indices(params, face3d))
    if seq.rotation is not None:
        rot, trans = seq.rotation, seq.translation
    return rot, trans, rms, float(camera[0, 0])


def video_end(seq: TakeTrack) -> float:
    """End of the sequence's last frame, seconds from its first (the last frame lasts one frame period)."""
    n = len(seq.time)
    if n == 0:
        return 0.0
    period = 1.0 / seq.fps if seq.fps else float(np.median(np.diff(seq.time))) if n > 1 else 0.0
    return float(seq.time[-1] + period)


class FrameOutputs:
    """The stage's per-frame outputs, appended take by take in blocks of frames.

    With ``sink`` (the stage's ``Stage.sink``) every output is an output sink: in a store run its chunks are
    written as blocks come, so no whole-take array is held; without it, blocks are concatenated at the end.
    """

    def __init__(self, sink=None, schema: dict | None = None):
        self.sink, self.schema = sink, schema or {}
        self.outputs: dict = {}

    def append(self, arrays: dict) -> None:
        for name, block in arrays.items():
            if name not in self.outputs:
                spec = self.schema.get(name)
                dtype = spec.dtype if spec is not None and spec.dtype else block.dtype
                self.outputs[name] = self._open(name, dtype, block.shape[1:])
            self.outputs[name].append(block)

    def _open(self, name: str, dtype, row_shape: tuple):
        if self.sink is not None:
            return self.sink(name, dtype=dtype, row_shape=row_shape)
        return _Blocks(dtype)

    def arrays(self) -> dict:
        """Output name -> sink (or array, when there is no sink)."""
        return {name: out if self.sink is not None else out.array() for name, out in self.outputs.items()}


class _Blocks:
    def __init__(self, dtype):
        self.dtype, self.blocks = np.dtype(dtype), []

    def append(self, block: np.ndarray) -> None:
        self.blocks.append(np.asarray(block, dtype=self.dtype))

    def array(self) -> np.ndarray:
        return np.concatenate(self.blocks)


@dataclass
class TakeTrack:
    """One take once its frames went to the outputs: what the metadata, metrics and audio need."""

    label: str
    source: str
    field: str
    fps: float
    frame_size: tuple[int, int]
    focal_length: float
    time: np.ndarray
    valid: np.ndarray
    landmarks: np.ndarray
    rotation: np.ndarray
    pose_rms: np.ndarray
    audio_source: AudioSource | None = None
    gaps: list = field(default_factory=list)  # long gaps held: [start, stop) frame ranges
    meta: dict = field(default_factory=dict)


def write_sequence(seq: SequenceTrack, params: TrackingParams, face3d: Face3D, outputs: FrameOutputs) -> TakeTrack:
    """Head pose and crop landmarks of a whole-sequence track; its per-frame arrays appended to ``outputs``."""
    rot, trans, rms, focal = pose_of(seq, params, face3d)
    n = len(seq.valid)
    transforms = seq.crop_transforms
    if transforms is None:
        transforms = similarity_transforms(
            seq.landmarks, params.crop_size, params.crop_eye_distance, params.crop_eye_height
        )
    arrays = {
        "landmarks": seq.landmarks.astype(np.float32),
        "confidence": np.asarray(seq.confidence, dtype=np.float32),
        "valid": np.asarray(seq.valid, dtype=bool),
        "time": np.asarray(seq.time, dtype=np.float64),
        "rotation": rot.astype(np.float64),
        "translation": trans.astype(np.float64),
        "pose_rms": rms.astype(np.float32),
        "crop_transforms": transforms.astype(np.float64),
        "crop_landmarks": apply_transforms(seq.landmarks.astype(np.float64), transforms).astype(np.float32),
        "crops": seq.crops if seq.crops is not None else np.zeros((n, 0, 0), dtype=np.uint8),
    }
    if seq.mesh is not None:
        arrays["mesh"] = seq.mesh.astype(np.float32)
    outputs.append(arrays)
    return TakeTrack(
        seq.label, seq.source, seq.field, seq.fps, seq.frame_size, focal, seq.time, seq.valid, seq.landmarks, rot, rms,
        seq.audio_source, seq.gaps, seq.meta,
    )  # fmt: skip


def audio_arrays(audios: list[TakeAudio | None]) -> dict:
    """``audio`` (all takes' samples end to end) and ``audio_bounds`` ([start, stop) per take; empty for a
    silent take); nothing when no take has audio."""
    if all(a is None for a in audios):
        return {}
    lengths = np.array([0 if a is None else len(a.samples) for a in audios], dtype=np.int64)
    stops = np.cumsum(lengths)
    samples = [a.samples for a in audios if a is not None]
    return {
        "audio": np.concatenate(samples).astype(np.float32),
        "audio_bounds": np.stack([stops - lengths, stops], axis=1),
    }


def tracking_meta(
    sequences: list[TakeTrack],
    audios: list[TakeAudio | None],
    params: TrackingParams,
    face3d_name: str,
    implementation: str,
    fields: dict,
) -> dict:
    """Strict-JSON metadata: per-sequence lists in sequence order, then the settings that shaped the outputs."""
    has_audio = [a is not None for a in audios]
    per_sequence_extra = sorted({k for s in sequences for k in s.meta})
    return {
        "implementation": implementation,
        "labels": [s.label for s in sequences],
        "fields": {s.label: dict(fields.get(s.label, {})) for s in sequences},
        "sources": [s.source for s in sequences],
        "frames": [int(len(s.valid)) for s in sequences],
        "fps": [float(s.fps) for s in sequences],
        "frame_size": [[int(s.frame_size[0]), int(s.frame_size[1])] for s in sequences],
        "audio_rate": int(params.audio_rate) if any(has_audio) else None,
        "audio_offset": [None if a is None else a.offset_to_video for a in audios],
        "audio_sources": [None if a is None else a.source for a in audios],
        "has_audio": has_audio,
        "landmark_scheme": "ibug68",
        "focal_length": [s.focal_length for s in sequences],
        "pose_landmarks": params.pose_landmarks,
        "pose_model": face3d_name,
        "translation_units": "cm",
        "crop_eye_distance": params.crop_eye_distance,
        "crop_eye_height": params.crop_eye_height,
        "max_gap_frames": params.max_gap_frames,
        "long_gaps": params.long_gaps,
        "gaps": [[[int(a), int(b)] for a, b in s.gaps] for s in sequences],
        **{k: [s.meta.get(k) for s in sequences] for k in per_sequence_extra},
    }


def tracking_metrics(stats: dict, valid: np.ndarray) -> dict:
    """Scalar quality metrics over all sequences (frame-weighted means, worst cases)."""
    all_stats = list(stats.values())
    frames = np.array([st["frames"] for st in all_stats], dtype=np.float64)

    def mean(key: str) -> float:
        return float(np.average([st[key] for st in all_stats], weights=frames))

    return {
        "frames": float(len(valid)),
        "valid_fraction": float(valid.mean()) if len(valid) else 0.0,
        "interpolated_frames": float(sum(st["interpolated_frames"] for st in all_stats)),
        "nose_step_px": mean("nose_step_px"),
        "nose_jitter_px": mean("nose_jitter_px"),
        "max_abs_yaw_deg": max(st["max_abs_yaw_deg"] for st in all_stats),
        "max_abs_pitch_deg": max(st["max_abs_pitch_deg"] for st in all_stats),
        "max_pose_step_deg": max(st["max_pose_step_deg"] for st in all_stats),
        "pose_rms_px": mean("pose_rms_px"),
    }


def gap_warnings(takes: list[TakeTrack], max_gap: int) -> list[str]:
    """One warning per take with long gaps held (``long_gaps: hold``)."""
    out = []
    for take in takes:
        if take.gaps:
            spans = ", ".join(
                f"frames {a}-{b - 1} ({take.time[a]:.2f}-{take.time[b - 1]:.2f} s)" for a, b in take.gaps[:5]
            )
            more = f" and {len(take.gaps) - 5} more" if len(take.gaps) > 5 else ""
            out.append(
                f"take '{take.label}': no face in {spans}{more}, longer than max_gap_frames = {max_gap}: the last "
                "tracked face is held there (valid = False; meta gaps)"
            )
    return out


def assemble(
    takes: list[TakeTrack],
    outputs: FrameOutputs,
    params: TrackingParams,
    face3d_name: str,
    implementation: str,
    extra_meta: dict | None = None,
    extra_metrics: dict | None = None,
    fields: dict | None = None,
) -> Result:
    """Audio of every take, then the TRACKING_OUTPUTS result: ``outputs`` (every take's frames, in order) plus
    ``sequence``, the audio, metadata and metrics.

    ``fields`` is each label's fields (speaker, expression, ...) from the labelled inputs: ``meta["fields"]``.
    """
    audios = [load_take_audio(take.audio_source, video_end(take), params, take.field) for take in takes]
    arrays = outputs.arrays()
    arrays["sequence"] = np.concatenate([np.full(len(t.valid), i, dtype=np.int32) for i, t in enumerate(takes)])
    arrays.update(audio_arrays(audios))
    meta = tracking_meta(takes, audios, params, face3d_name, implementation, fields or {})
    meta["has_crops"] = arrays["crops"].shape[1] > 0
    meta["crop_size"] = params.crop_size if meta["has_crops"] else 0
    stats = {take.label: sequence_stats(take) for take in takes}
    meta["sequence_stats"] = stats
    meta.update(extra_meta or {})
    valid = np.concatenate([t.valid for t in takes])
    metrics = {**tracking_metrics(stats, valid), **(extra_metrics or {})}
    return Result(arrays, meta=meta, metrics=metrics, warnings=gap_warnings(takes, params.max_gap_frames))
