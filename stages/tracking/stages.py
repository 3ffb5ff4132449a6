"""The tracking stages (paper Fig. 1 "tracking", Sec. 3.1): FaceMesh, OpticalFlow and TrackFile, one output
schema (TRACKING_OUTPUTS), swappable with ``uses:``."""

from __future__ import annotations

from contextlib import contextmanager
from functools import lru_cache, partial
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, PositiveInt, field_validator

from msflow import Input, Result, Stage, UserError
from stages.data import DATA
from stages.tracking.assemble import (
    CropCollector,
    FrameOutputs,
    SequenceTrack,
    TakeTrack,
    TrackingParams,
    assemble,
    assumed_focal,
    pose_point_indices,
    resolve_face3d,
    write_sequence,
)
from stages.tracking.eyes import REST_OFFSETS
from stages.tracking.figures import FIGURES
from stages.tracking.gaps import apply_plan, fill_gaps, gap_plan
from stages.tracking.landmarks68 import mesh_to_ibug68
from stages.tracking.parts import TAKE_READS, take_from_part, take_part
from stages.tracking.schema import TRACKING_OUTPUTS
from stages.tracking.takes import AudioSource, audio_sources, labels_fields, preflight_audio
from stages.tracking.video import VideoInfo, iter_planes, probe_video

MODELS = DATA / "models" / "mediapipe-face"
DETECTOR_MODEL = MODELS / "face_detection_short_range.tflite"
LANDMARK_MODEL = MODELS / "face_landmark.tflite"
LANDMARKER_V2_MODEL = MODELS / "face_landmarks_detector.tflite"
IRIS_MODEL = MODELS / "iris_landmark.tflite"
#: the eye pass ``eyes: true`` means
DEFAULT_EYES = "landmarker_v2"

VIDEOS_DOC = "labelled videos (label -> file); any container/codec FFmpeg reads"
FACE3D_DOC = "optional 3D face for head pose: a JSON file with 'neutral' (68, 3) like data/face3d"
MODELS_DOC = "optional MediaPipe models: labels 'detector', 'landmarks' and 'eyes' (.tflite); default data/models"
AUDIO_DOC = (
    "optional separate audio files (WAV, FLAC, MP3, ...) matched to the takes by label; params.audio_offset "
    "places each take's first frame in its file"
)

# default data files the stages read when no input overrides them: hashed into the cache key
DEFAULT_FACE3D_FILE = DATA / "face3d" / "ict_landmarks68.json"
MESH_RESOURCES = {
    "detector": DETECTOR_MODEL,
    "landmarks": LANDMARK_MODEL,
    "landmarks_v2": LANDMARKER_V2_MODEL,
    "iris": IRIS_MODEL,
    "face3d": DEFAULT_FACE3D_FILE,
}


def model_paths(
    models: dict | None, model: str = "face_mesh_v1", eyes: str | bool = DEFAULT_EYES
) -> tuple[Path, Path, Path]:
    """(detector, landmark model, eye model) files: the ``models`` input's, or the project's for ``model`` and
    the ``eyes`` pass."""
    models = dict(models or {})
    unknown = set(models) - {"detector", "landmarks", "eyes"}
    if unknown:
        raise UserError(
            f"unknown model labels {sorted(unknown)}; use 'detector', 'landmarks' and 'eyes'", field="inputs.models"
        )
    default = LANDMARKER_V2_MODEL if model == "face_landmarker_v2" else LANDMARK_MODEL
    return (
        Path(models.get("detector", DETECTOR_MODEL)),
        Path(models.get("landmarks", default)),
        Path(models.get("eyes", IRIS_MODEL if eyes == "iris" else LANDMARKER_V2_MODEL)),
    )


def _require_files(files: dict | None, name: str) -> dict:
    if not files:
        raise UserError(f"no files given for '{name}'", field=f"inputs.{name}")
    return files


def video_durations(videos: dict) -> dict[str, float]:
    """Declared duration of each labelled video (0.0 when the container does not say)."""
    return {label: probe_video(path, field=f"inputs.videos.{label}").duration for label, path in videos.items()}


class FaceMeshParams(TrackingParams):
    min_detection_score: float = Field(0.5, gt=0, lt=1, description="BlazeFace score needed to accept a face")
    min_presence: float = Field(
        0.5,
        gt=0,
        lt=1,
        description="face-mesh presence score below which the tracked face counts as lost and the detector runs again",
    )
    redetect_every: int = Field(
        0, ge=0, description="also re-run the detector every this many frames (0: only when the face is lost)"
    )
    face: Literal["most_certain", "largest", "leftmost", "rightmost"] = Field(
        "most_certain",
        description="the face to track when the first frame with a face shows several (two people in the shot): "
        "the detector's most certain, the largest, or the one furthest left or right in the picture; after that "
        "the tracker follows that face, also when it is lost and found again",
    )
    output_mesh: bool = Field(True, description="include the 468-point mesh output")
    model: Literal["face_mesh_v1", "face_landmarker_v2"] = Field(
        "face_mesh_v1",
        description="landmark model for the mesh and the 68 points: MediaPipe's 468-point face mesh, or Face "
        "Landmarker v2 (478 points: the mesh plus the irises; 2.2x slower per frame)",
    )
    eyes: Literal["iris", "landmarker_v2", False] = Field(
        DEFAULT_EYES,
        description="eye outputs (eye_aperture, gaze, iris) and the model making them: 'landmarker_v2' (Face "
        "Landmarker v2, whose eyelids follow blinks: the landmark model's own points when it is v2, else a second "
        "pass on the same face region), 'iris' (MediaPipe's iris model on a 64 px crop around each eye), false "
        f"(none); true means '{DEFAULT_EYES}'",
    )

    @field_validator("eyes", mode="before")
    @classmethod
    def true_means_the_default_eye_pass(cls, value):
        return DEFAULT_EYES if value is True else value


def new_tracker(params, models: dict | None):
    from stages.tracking.facemesh import FaceMeshTracker

    model = getattr(params, "model", "face_mesh_v1")
    eye_pass = getattr(params, "eyes", False)
    detector, landmarks, eyes = model_paths(models, model, eye_pass)
    second_pass = eye_pass == "iris" or (eye_pass == "landmarker_v2" and model != "face_landmarker_v2")
    return FaceMeshTracker(
        detector,
        landmarks,
        min_detection_score=params.min_detection_score,
        min_presence=params.min_presence,
        redetect_every=getattr(params, "redetect_every", 0),
        model=model,
        eye_model_path=eyes if second_pass else None,
        eye_pass=eye_pass or DEFAULT_EYES,
        first_face=getattr(params, "face", "most_certain"),
    )


def stage_jobs(stage: Stage) -> int:
    """The run's worker count (``-j``) as the stage sees it."""
    return max(1, int(stage.jobs))


@contextmanager
def cv_threads(n: int):
    """OpenCV's thread count set to ``n`` for the duration (its DNN layers and warps split work across threads
    with the same results)."""
    import cv2

    before = cv2.getNumThreads()
    cv2.setNumThreads(n)
    try:
        yield
    finally:
        cv2.setNumThreads(before)


def track_facemesh_take(
    tracker, label: str, path: Path, params: FaceMeshParams, face3d, outputs: FrameOutputs, audio, jobs: int = 1
) -> TakeTrack:
    """One take streamed through the landmark model into ``outputs`` (stages/tracking/stream.py)."""
    from stages.tracking.pose import PoseSolver, camera_matrix
    from stages.tracking.stream import FOCAL_FRAMES, BlockWriter, CropSettings, check_gaps, stream_take
    from stages.tracking.video import iter_planes

    field = f"inputs.videos.{label}"
    info = probe_video(path, field=field)
    tracker.reset()
    crop = CropSettings(params.crop_size, params.crop_eye_distance, params.crop_eye_height)
    camera = camera_matrix(info.width, info.height, assumed_focal(params))
    solver = PoseSolver(face3d.neutral, camera, pose_point_indices(params, face3d))
    eyes = tracker.eye_offset if params.eyes else None
    rest = REST_OFFSETS.get(params.eyes)
    focal_frames = FOCAL_FRAMES if params.focal_length == "estimated" else 0
    writer = BlockWriter(
        tracker.points, crop, solver, outputs.append, params.output_mesh, eyes, eye_rest=rest, focal_frames=focal_frames
    )
    frames = iter_planes(path, field=field, threads=jobs)
    stream_take(frames, tracker, writer, crop, params.max_gap_frames, path, field)
    s = writer.finish()
    gaps = check_gaps(s, params.max_gap_frames, params.long_gaps, path, field)
    size, focal = (info.width, info.height), float(solver.camera[0, 0])
    meta = {"detector_runs": tracker.detections}
    return TakeTrack(
        label, path.name, field, info.fps, size, focal, s.time, s.valid, s.landmarks, s.rotation, s.pose_rms, audio,
        gaps, meta,
    )  # fmt: skip


class FaceMesh(Stage):
    """Face tracking with MediaPipe's BlazeFace detector and 468-point face mesh (OpenCV DNN), 68 iBUG points
    through a fixed mapping, head pose, face crops and audio per labelled video."""

    in_process = True

    Params = FaceMeshParams
    inputs = {
        "videos": Input.files(doc=VIDEOS_DOC),
        "audio": Input.files(optional=True, doc=AUDIO_DOC),
        "face3d": Input.files(optional=True, doc=FACE3D_DOC),
        "models": Input.files(optional=True, doc=MODELS_DOC),
    }
    outputs = TRACKING_OUTPUTS
    resources = MESH_RESOURCES
    figures = FIGURES

    def run(self, params: FaceMeshParams, inputs: dict) -> Result:
        videos = _require_files(inputs["videos"], "videos")
        audio = audio_sources(videos, inputs.get("audio"), params)
        preflight_audio(audio, video_durations(videos), params)
        face3d, face3d_name = resolve_face3d(inputs.get("face3d"))
        outputs, jobs = FrameOutputs(self.sink, TRACKING_OUTPUTS), stage_jobs(self)
        trackers: list = []  # the models load once, and only when some take is not stored yet

        def track(label: str, path: Path, sink) -> Result:
            if not trackers:
                trackers.append(new_tracker(params, inputs.get("models")))
            part_outputs = FrameOutputs(sink, TRACKING_OUTPUTS)
            take = track_facemesh_take(trackers[0], label, path, params, face3d, part_outputs, None, jobs)
            return take_part(take, part_outputs)

        takes = []
        with cv_threads(jobs):
            for label, path in videos.items():
                make = partial(track, label, Path(path))
                part = self.part(label, make, **TAKE_READS)
                takes.append(take_from_part(part, outputs, label, Path(path), f"inputs.videos.{label}", audio[label]))
        fields = labels_fields(videos, inputs.get("audio"))
        extra = {"landmark_model": params.model, "eye_model": params.eyes}
        return assemble(takes, outputs, params, face3d_name, "FaceMesh", extra_meta=extra, fields=fields)


# ---------------------------------------------------------------------------------------------- OpticalFlow


class OpticalFlowParams(TrackingParams):
    window: int = Field(21, ge=5, le=101, description="Lucas-Kanade window side (pixels)")
    pyramid_levels: int = Field(3, ge=0, le=6, description="pyramid levels above the full-resolution image")
    fb_threshold: float = Field(
        1.0, gt=0, description="forward-backward error (pixels) above which a point counts as lost in that frame"
    )
    shape_model: bool = Field(True, description="project every tracked shape onto the point distribution model")
    shape_variance: float = Field(0.995, gt=0.5, lt=1.0, description="fraction of the model's shape variance kept")
    shape_noise: float = Field(
        0.02,
        gt=0,
        description="point noise of the shape fit, in units of the shape's "
        "RMS radius (smaller follows the tracked points more closely)",
    )
    min_good_fraction: float = Field(
        0.5,
        gt=0,
        le=1,
        description="frames where fewer points pass the "
        "forward-backward check are flagged as not tracked (valid = False)",
    )
    min_detection_score: float = Field(0.5, gt=0, lt=1, description="BlazeFace score for the FaceMesh start")
    model: Literal["face_mesh_v1", "face_landmarker_v2"] = Field(
        "face_mesh_v1", description="landmark model of the FaceMesh start (see FaceMesh)"
    )
    min_presence: float = Field(0.5, gt=0, lt=1, description="face-mesh presence score for the FaceMesh start")
    init_frame_base: int | None = Field(
        None, description="first frame number in the init files (default: 1 for OpenFace CSV, 0 otherwise)"
    )


@lru_cache(maxsize=4)
def cached_shape_model(face3d_key: str, variance: float):
    from stages.tracking.face3d import DEFAULT_FACE3D, load_face3d
    from stages.tracking.shape_model import build_shape_model

    path = Path(face3d_key.rsplit("|", 2)[0]) if face3d_key else DEFAULT_FACE3D
    return build_shape_model(load_face3d(path), variance=variance, expressions_per_sample=8)


def initial_shape(init_path: Path, label: str, params: OpticalFlowParams) -> tuple[int, np.ndarray]:
    """(frame index, (68, 2) points) of the first valid shape in an init file (.pts, CSV, .npz)."""
    from stages.tracking.trackfile import read_track

    track = read_track(init_path, frame_base=params.init_frame_base, field=f"inputs.init.{label}")
    rows = np.flatnonzero(track.valid)
    if not rows.size:
        raise UserError(
            "init file has no valid shape (every row failed)", file=str(init_path), field=f"inputs.init.{label}"
        )
    return int(track.frame[rows[0]]), track.landmarks[rows[0]]


class FlowStart:
    """Where optical flow starts: the init file's shape at its frame, else FaceMesh's first face."""

    def __init__(self, init: tuple[int, np.ndarray] | None, tracker_factory):
        self.init, self.factory, self.mesh_tracker = init, tracker_factory, None

    def shape(self, index: int, frame) -> tuple[np.ndarray | None, float]:
        """(68 points, confidence) to start from at this frame, or (None, 0.0)."""
        if self.init is not None:
            return (self.init[1], 1.0) if index == self.init[0] else (None, 0.0)
        self.mesh_tracker = self.mesh_tracker or self.factory()
        mesh, score = self.mesh_tracker.step(frame)
        return (None, 0.0) if mesh is None else (mesh_to_ibug68(mesh[:468, :2]), score)


def flow_frames(path: Path, field: str, flow, start: FlowStart, collector: CropCollector):
    """Per frame (time, 68 points or None, tracked, confidence, median forward-backward error or None)."""
    started = False
    for i, (t, frame) in enumerate(iter_planes(path, field=field)):
        gray = frame.gray()
        if not started:
            points, c = start.shape(i, frame)
            started = ok = points is not None
            if started:
                flow.start(gray, points)
            fb = None
        else:
            points, good, errors = flow.step(gray)
            ok, c, fb = not flow.is_lost(good), float(good.mean()), float(np.median(errors))
        collector.add(frame, points if ok else None)
        yield t, points, ok, c, fb


def track_flow_video(
    label: str,
    path: Path,
    params: OpticalFlowParams,
    init: tuple[int, np.ndarray] | None,
    tracker_factory,
    model,
    audio: AudioSource | None = None,
) -> SequenceTrack:
    """Lucas-Kanade tracking of one video from its start shape; gaps filled (or held) afterwards."""
    from stages.tracking.opticalflow import LucasKanadeTracker

    field = f"inputs.videos.{label}"
    info = probe_video(path, field=field)
    flow = LucasKanadeTracker(
        window=params.window,
        levels=params.pyramid_levels,
        fb_threshold=params.fb_threshold,
        model=model,
        model_noise=params.shape_noise,
        min_good_fraction=params.min_good_fraction,
    )
    collector = CropCollector(params, params.max_gap_frames)
    rows = list(flow_frames(path, field, flow, FlowStart(init, tracker_factory), collector))
    times = np.array([r[0] for r in rows])
    valid = np.array([r[2] for r in rows], dtype=bool)
    if init is not None and init[0] >= len(rows):
        raise UserError(
            f"the init shape is for frame {init[0]} but the video has only {len(rows)} frames",
            file=str(path),
            field=f"inputs.init.{label}",
        )
    shapes = np.array([np.full((68, 2), np.nan) if r[1] is None else r[1] for r in rows])
    landmarks, sources, gaps = fill_gaps(
        shapes, valid, params.max_gap_frames, params.long_gaps, times, file=str(path), field=field
    )
    crops, transforms = collector.finish(landmarks, sources)
    fb_errors = [r[4] for r in rows if r[4] is not None]
    meta = {
        "init": "file" if init is not None else "facemesh",
        "fb_error_px": float(np.mean(fb_errors)) if fb_errors else 0.0,
    }
    size = (info.width, info.height)
    conf = np.array([r[3] for r in rows])
    return SequenceTrack(
        label, path.name, landmarks, valid, conf, times, info.fps, size, field, crops=crops,
        crop_transforms=transforms, video=path, audio_source=audio, gaps=gaps, meta=meta,
    )  # fmt: skip


class OpticalFlow(Stage):
    """Pyramidal Lucas-Kanade tracking of the 68 points from an initial shape (an init file, or FaceMesh on the
    first frame with a face), forward-backward checked and constrained by a point distribution model."""

    in_process = True

    Params = OpticalFlowParams
    inputs = {
        "videos": Input.files(doc=VIDEOS_DOC),
        "init": Input.files(
            optional=True,
            doc="initial shapes per label (.pts, OpenFace or plain CSV, "
            ".npz): the first valid row starts the tracker at its frame",
        ),
        "audio": Input.files(optional=True, doc=AUDIO_DOC),
        "face3d": Input.files(optional=True, doc=FACE3D_DOC),
        "models": Input.files(optional=True, doc=MODELS_DOC),
    }
    outputs = TRACKING_OUTPUTS
    resources = MESH_RESOURCES
    figures = FIGURES

    def run(self, params: OpticalFlowParams, inputs: dict) -> Result:
        videos = _require_files(inputs["videos"], "videos")
        inits = dict(inputs.get("init") or {})
        unknown = set(inits) - set(videos)
        if unknown:
            raise UserError(
                f"init files for labels with no video: {sorted(unknown)} (videos: {sorted(videos)})",
                field="inputs.init",
            )
        if inits and set(inits) != set(videos):
            raise UserError(
                f"no init file for {sorted(set(videos) - set(inits))}: give one per video label, or "
                "none to start from FaceMesh",
                field="inputs.init",
            )
        audio = audio_sources(videos, inputs.get("audio"), params)
        preflight_audio(audio, video_durations(videos), params)
        face3d_files = inputs.get("face3d")
        face3d, face3d_name = resolve_face3d(face3d_files)
        model = None
        if params.shape_model:
            key = ""
            if face3d_files:  # the path plus its size and mtime: an edited file rebuilds the model
                path = Path(next(iter(face3d_files.values())))
                stat = path.stat()
                key = f"{path}|{stat.st_size}|{stat.st_mtime_ns}"
            model = cached_shape_model(key, params.shape_variance)
        shared_tracker = []

        def factory():
            if not shared_tracker:
                shared_tracker.append(new_tracker(params, inputs.get("models")))
            shared_tracker[0].reset()
            return shared_tracker[0]

        sequences = []
        for label, path in videos.items():
            init = initial_shape(Path(inits[label]), label, params) if label in inits else None
            sequences.append(track_flow_video(label, Path(path), params, init, factory, model, audio[label]))
        extra = {"shape_modes": int(model.basis.shape[1]) if model is not None else 0}
        fields = labels_fields(videos, inputs.get("init"), inputs.get("audio"))
        outputs = FrameOutputs(self.sink, TRACKING_OUTPUTS)
        takes = [write_sequence(seq, params, face3d, outputs) for seq in sequences]
        return assemble(takes, outputs, params, face3d_name, "OpticalFlow", extra_meta=extra, fields=fields)


# ---------------------------------------------------------------------------------------------- TrackFile


class TrackFileParams(TrackingParams):
    format: Literal["auto", "openface", "csv", "npz", "pts"] = Field(
        "auto", description="track file format; 'auto' goes by suffix and CSV header"
    )
    frame_base: int | None = Field(
        None,
        description="number of the first video frame in the file's frame "
        "column (default: 1 for OpenFace CSV, 0 for plain CSV and .npz)",
    )
    face_id: int = Field(0, ge=0, description="which face of a multi-face OpenFace CSV")
    min_confidence: float = Field(0.0, ge=0, le=1, description="rows below this confidence count as no face")
    fps: float | None = Field(
        None, gt=0, description="frame rate when there is no video and the file has no timestamps"
    )
    frame_size: tuple[PositiveInt, PositiveInt] | None = Field(
        None, description="[width, height] of the tracked video when no video is given (needed for head pose)"
    )
    pose_source: Literal["landmarks", "file"] = Field(
        "landmarks",
        description="'landmarks': solvePnP like the other implementations; 'file': the OpenFace "
        "CSV's pose_T/pose_R columns converted to the stages.geometry.rotations convention",
    )
    audio: Literal["required", "optional", "none"] = Field("optional", description="audio from the videos, when given")


def dense_track(track, n_frames: int, label: str, path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows placed on the frame axis 0..n_frames-1: (landmarks with NaN where absent, valid, confidence)."""
    if track.frame.max() >= n_frames:
        raise UserError(
            f"track has frame {int(track.frame.max())} (0-based) but the video has {n_frames} frames "
            "(check params.frame_base)",
            file=str(path),
            field=f"inputs.tracks.{label}",
        )
    landmarks = np.full((n_frames, 68, 2), np.nan)
    valid = np.zeros(n_frames, dtype=bool)
    conf = np.zeros(n_frames)
    landmarks[track.frame] = track.landmarks
    valid[track.frame] = track.valid
    conf[track.frame] = track.confidence
    return landmarks, valid, conf


def track_times(track, n_frames: int, params: TrackFileParams, path: Path, field: str) -> tuple[np.ndarray, float]:
    fps = params.fps or track.fps
    if fps is None and track.time is not None and len(track.frame) > 1:
        span = float(track.time[-1] - track.time[0])  # over the whole file: timestamps are often rounded to ms
        fps = float(track.frame[-1] - track.frame[0]) / span if span > 0 else None
    if not fps:
        raise UserError(
            "frame rate unknown: give the video, or params.fps (the file has no timestamps)",
            file=str(path),
            field=field,
        )
    return np.arange(n_frames) / fps, float(fps)


class TrackFile(Stage):
    """Existing landmark tracks (OpenFace 2.0 CSV, plain CSV, .npz, iBUG .pts sequences) in the tracking schema;
    no video analysis. Videos, when given (same labels), supply crops, timing and audio."""

    in_process = True

    Params = TrackFileParams
    inputs = {
        "tracks": Input.files(doc="labelled track files (label -> file, or a directory of .pts files)"),
        "videos": Input.files(optional=True, doc="the tracked videos, same labels: crops, timing, audio"),
        "audio": Input.files(optional=True, doc=AUDIO_DOC),
        "face3d": Input.files(optional=True, doc=FACE3D_DOC),
    }
    outputs = TRACKING_OUTPUTS
    resources = {"face3d": DEFAULT_FACE3D_FILE}
    figures = FIGURES

    def run(self, params: TrackFileParams, inputs: dict) -> Result:
        tracks = _require_files(inputs["tracks"], "tracks")
        videos = dict(inputs.get("videos") or {})
        if videos and set(videos) != set(tracks):
            raise UserError(
                f"video labels {sorted(videos)} do not match track labels {sorted(tracks)}", field="inputs.videos"
            )
        takes = {label: videos.get(label) for label in tracks}
        audio = audio_sources(takes, inputs.get("audio"), params, "inputs.tracks")
        preflight_audio(audio, video_durations(videos), params)
        face3d, face3d_name = resolve_face3d(inputs.get("face3d"))
        sequences = [
            trackfile_sequence(label, Path(path), params, takes[label], audio[label]) for label, path in tracks.items()
        ]
        fields = labels_fields(tracks, videos, inputs.get("audio"))
        outputs = FrameOutputs(self.sink, TRACKING_OUTPUTS)
        takes_out = [write_sequence(seq, params, face3d, outputs) for seq in sequences]
        return assemble(takes_out, outputs, params, face3d_name, "TrackFile", fields=fields)


def video_crops(video: Path, track, params: TrackFileParams, label: str) -> tuple[CropCollector, np.ndarray, VideoInfo]:
    """Crops (collected while the video streams) at the file's valid rows, the video's frame times and info."""
    field = f"inputs.videos.{label}"
    info = probe_video(video, field=field)
    row_of = {int(f): r for r, f in enumerate(track.frame) if track.valid[r]}
    collector = CropCollector(params, params.max_gap_frames)
    times = []
    for i, (t, frame) in enumerate(iter_planes(video, field=field)):
        collector.add(frame, track.landmarks[row_of[i]] if i in row_of else None)
        times.append(t)
    return collector, np.array(times), info


def file_frame_size(track, params: TrackFileParams, path: Path, field: str) -> tuple[int, int]:
    size = track.frame_size or params.frame_size
    if size is None:
        raise UserError(
            "frame size unknown (needed for head pose): give the video or params.frame_size [width, height]",
            file=str(path),
            field=field,
        )
    return int(size[0]), int(size[1])


def file_pose(track, valid: np.ndarray, n: int, params: TrackFileParams, path: Path, field: str):
    """(rotation, translation) from the OpenFace pose columns, filled like the landmarks; (None, None) unless
    params.pose_source is 'file'."""
    from stages.tracking.pose import openface_pose_to_gltf

    if params.pose_source != "file":
        return None, None
    if track.openface_pose is None:
        raise UserError("pose_source 'file' needs OpenFace pose columns pose_Tx..pose_Rz", file=str(path), field=field)
    q, t = openface_pose_to_gltf(track.openface_pose[:, 3:], track.openface_pose[:, :3])
    dense_q, dense_t = np.zeros((n, 4)), np.zeros((n, 3))
    dense_q[track.frame], dense_t[track.frame] = q, t
    plan = gap_plan(valid, params.max_gap_frames)[:3]
    rotation = apply_plan(dense_q, *plan)
    rotation /= np.linalg.norm(rotation, axis=1, keepdims=True)
    return rotation, apply_plan(dense_t, *plan)


def trackfile_sequence(
    label: str, path: Path, params: TrackFileParams, video: Path | None, audio: AudioSource | None
) -> SequenceTrack:
    """One track file on the frame axis (of its video, when given), gaps filled (or held), crops, pose."""
    from stages.tracking.trackfile import read_track

    field = f"inputs.tracks.{label}"
    track = read_track(path, params.format, frame_base=params.frame_base, face_id=params.face_id, field=field)
    if params.min_confidence > 0:
        track.valid &= track.confidence >= params.min_confidence
    collector = None
    if video is not None:
        collector, times, info = video_crops(Path(video), track, params, label)
        n, fps, size = len(times), info.fps, (info.width, info.height)
    else:
        n = int(track.frame.max()) + 1
        (times, fps), size = track_times(track, n, params, path, field), file_frame_size(track, params, path, field)
    landmarks, valid, conf = dense_track(track, n, label, path)
    landmarks, sources, gaps = fill_gaps(
        landmarks, valid, params.max_gap_frames, params.long_gaps, times, file=str(path), field=field
    )
    crops, transforms = collector.finish(landmarks, sources) if collector is not None else (None, None)
    rotation, translation = file_pose(track, valid, n, params, path, field)
    return SequenceTrack(
        label, path.name, landmarks, valid, conf, times, fps, size, field, crops=crops, crop_transforms=transforms,
        video=video, audio_source=audio, rotation=rotation, translation=translation, gaps=gaps,
        meta={"track_format": track.format},
    )  # fmt: skip


__all__ = ["FaceMesh", "OpticalFlow", "TrackFile"]
