"""The tracking stages (paper Fig. 1 "tracking", Sec. 3.1): FaceMesh, OpticalFlow and TrackFile, one output
schema (TRACKING_OUTPUTS), swappable with ``uses:``."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from msflow import Input, Result, Stage, UserError
from stages.data import DATA
from stages.tracking.assemble import CropCollector, SequenceTrack, TrackingParams, assemble, resolve_face3d
from stages.tracking.crops import to_gray
from stages.tracking.figures import FIGURES
from stages.tracking.gaps import fill_face_gaps, interpolate_gaps
from stages.tracking.landmarks68 import mesh_to_ibug68
from stages.tracking.schema import TRACKING_OUTPUTS
from stages.tracking.takes import AudioSource, audio_sources, labels_fields, preflight_audio
from stages.tracking.video import iter_frames, probe_video

MODELS = DATA / "models" / "mediapipe-face"
DETECTOR_MODEL = MODELS / "face_detection_short_range.tflite"
LANDMARK_MODEL = MODELS / "face_landmark.tflite"

VIDEOS_DOC = "labelled videos (label -> file); any container/codec FFmpeg reads"
FACE3D_DOC = "optional 3D face for head pose: a JSON file with 'neutral' (68, 3) like data/face3d"
MODELS_DOC = "optional MediaPipe models: labels 'detector' and 'landmarks' (.tflite); default data/models"
AUDIO_DOC = (
    "optional separate audio files (WAV, FLAC, MP3, ...) matched to the takes by label; params.audio_offset "
    "places each take's first frame in its file"
)

# default data files the stages read when no input overrides them: hashed into the cache key
DEFAULT_FACE3D_FILE = DATA / "face3d" / "ict_landmarks68.json"
MESH_RESOURCES = {"detector": DETECTOR_MODEL, "landmarks": LANDMARK_MODEL, "face3d": DEFAULT_FACE3D_FILE}


def model_paths(models: dict | None) -> tuple[Path, Path]:
    models = dict(models or {})
    unknown = set(models) - {"detector", "landmarks"}
    if unknown:
        raise UserError(
            f"unknown model labels {sorted(unknown)}; use 'detector' and 'landmarks'", field="inputs.models"
        )
    return Path(models.get("detector", DETECTOR_MODEL)), Path(models.get("landmarks", LANDMARK_MODEL))


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
    output_mesh: bool = Field(True, description="include the 468-point mesh output")


def new_tracker(params, models: dict | None):
    from stages.tracking.facemesh import FaceMeshTracker

    detector, landmarks = model_paths(models)
    return FaceMeshTracker(
        detector,
        landmarks,
        min_detection_score=params.min_detection_score,
        min_presence=params.min_presence,
        redetect_every=getattr(params, "redetect_every", 0),
    )


def track_facemesh_video(
    tracker, label: str, path: Path, params: FaceMeshParams, audio: AudioSource | None = None
) -> SequenceTrack:
    """Face mesh over one video, crops made while it streams; gaps filled (or refused) afterwards."""
    field = f"inputs.videos.{label}"
    info = probe_video(path, field=field)
    tracker.reset()
    collector = CropCollector(params, params.max_gap_frames)
    times, meshes, scores, found = [], [], [], []
    for t, frame in iter_frames(path, field=field):
        points, score = tracker.step(frame)
        collector.add(to_gray(frame), None if points is None else mesh_to_ibug68(points[:, :2]))
        times.append(t)
        meshes.append(np.full((468, 3), np.nan) if points is None else points)
        scores.append(score)
        found.append(points is not None)
    times_arr, valid = np.array(times), np.array(found, dtype=bool)
    mesh = fill_face_gaps(np.array(meshes), valid, params.max_gap_frames, times_arr, file=str(path), field=field)
    landmarks = mesh_to_ibug68(mesh[:, :, :2])
    crops, transforms = collector.finish(landmarks)
    return SequenceTrack(
        label,
        path.name,
        landmarks,
        valid,
        np.array(scores),
        times_arr,
        info.fps,
        (info.width, info.height),
        field,
        mesh=mesh if params.output_mesh else None,
        crops=crops,
        crop_transforms=transforms,
        video=path,
        audio_source=audio,
        meta={"detector_runs": tracker.detections},
    )


class FaceMesh(Stage):
    """Face tracking with MediaPipe's BlazeFace detector and 468-point face mesh (OpenCV DNN), 68 iBUG points
    through a fixed mapping, head pose, face crops and audio per labelled video."""

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
        tracker = new_tracker(params, inputs.get("models"))
        sequences = [
            track_facemesh_video(tracker, label, Path(path), params, audio[label]) for label, path in videos.items()
        ]
        fields = labels_fields(videos, inputs.get("audio"))
        return assemble(sequences, params, face3d, face3d_name, "FaceMesh", fields=fields)


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


def track_flow_video(
    label: str,
    path: Path,
    params: OpticalFlowParams,
    init: tuple[int, np.ndarray] | None,
    tracker_factory,
    model,
    audio: AudioSource | None = None,
) -> SequenceTrack:
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
    mesh_tracker = None
    times, shapes, conf, valid, fb_errors = [], [], [], [], []
    started = False
    for i, (t, frame) in enumerate(iter_frames(path, field=field)):
        gray = to_gray(frame)
        points, ok, c = None, False, 0.0
        if not started:
            if init is None:
                mesh_tracker = mesh_tracker or tracker_factory()
                mesh, score = mesh_tracker.step(frame)
                if mesh is not None:
                    points, c = mesh_to_ibug68(mesh[:, :2]), score
            elif i == init[0]:
                points, c = init[1], 1.0
            if points is not None:
                flow.start(gray, points)
                started, ok = True, True
        else:
            points, good, fb = flow.step(gray)
            ok = not flow.is_lost(good)
            c = float(good.mean())
            fb_errors.append(float(np.median(fb)))
        collector.add(gray, points if ok else None)
        times.append(t)
        shapes.append(points if points is not None else np.full((68, 2), np.nan))
        conf.append(c)
        valid.append(ok)
    if init is not None and not started:
        raise UserError(
            f"the init shape is for frame {init[0]} but the video has only {len(times)} frames",
            file=str(path),
            field=f"inputs.init.{label}",
        )
    times_arr, valid_arr = np.array(times), np.array(valid, dtype=bool)
    landmarks = fill_face_gaps(
        np.array(shapes), valid_arr, params.max_gap_frames, times_arr, file=str(path), field=field
    )
    crops, transforms = collector.finish(landmarks)
    return SequenceTrack(
        label,
        path.name,
        landmarks,
        valid_arr,
        np.array(conf),
        times_arr,
        info.fps,
        (info.width, info.height),
        field,
        crops=crops,
        crop_transforms=transforms,
        video=path,
        audio_source=audio,
        meta={
            "init": "file" if init is not None else "facemesh",
            "fb_error_px": float(np.mean(fb_errors)) if fb_errors else 0.0,
        },
    )


class OpticalFlow(Stage):
    """Pyramidal Lucas-Kanade tracking of the 68 points from an initial shape (an init file, or FaceMesh on the
    first frame with a face), forward-backward checked and constrained by a point distribution model."""

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
        return assemble(sequences, params, face3d, face3d_name, "OpticalFlow", extra_meta=extra, fields=fields)


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
    frame_size: tuple[int, int] | None = Field(
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
        from stages.tracking.pose import openface_pose_to_gltf
        from stages.tracking.trackfile import read_track

        tracks = _require_files(inputs["tracks"], "tracks")
        videos = dict(inputs.get("videos") or {})
        if videos and set(videos) != set(tracks):
            raise UserError(
                f"video labels {sorted(videos)} do not match track labels {sorted(tracks)}", field="inputs.videos"
            )
        audio = audio_sources(
            {label: videos.get(label) for label in tracks}, inputs.get("audio"), params, "inputs.tracks"
        )
        face3d, face3d_name = resolve_face3d(inputs.get("face3d"))
        sequences = []
        for label, path in tracks.items():
            path = Path(path)
            field = f"inputs.tracks.{label}"
            track = read_track(path, params.format, frame_base=params.frame_base, face_id=params.face_id, field=field)
            if params.min_confidence > 0:
                track.valid &= track.confidence >= params.min_confidence
            video = Path(videos[label]) if label in videos else None
            crops = transforms = None
            if video is not None:
                vfield = f"inputs.videos.{label}"
                info = probe_video(video, field=vfield)
                row_of = {int(f): r for r, f in enumerate(track.frame) if track.valid[r]}
                collector = CropCollector(params, params.max_gap_frames)
                times = []
                for i, (t, frame) in enumerate(iter_frames(video, field=vfield)):
                    collector.add(to_gray(frame), track.landmarks[row_of[i]] if i in row_of else None)
                    times.append(t)
                n = len(times)
                times_arr, fps, size = np.array(times), info.fps, (info.width, info.height)
            else:
                n = int(track.frame.max()) + 1
                times_arr, fps = track_times(track, n, params, path, field)
                size = track.frame_size or params.frame_size
                if size is None:
                    raise UserError(
                        "frame size unknown (needed for head pose): give the video or "
                        "params.frame_size [width, height]",
                        file=str(path),
                        field=field,
                    )
            landmarks, valid, conf = dense_track(track, n, label, path)
            landmarks = fill_face_gaps(landmarks, valid, params.max_gap_frames, times_arr, file=str(path), field=field)
            if video is not None:
                crops, transforms = collector.finish(landmarks)
            rotation = translation = None
            if params.pose_source == "file":
                if track.openface_pose is None:
                    raise UserError(
                        "pose_source 'file' needs OpenFace pose columns pose_Tx..pose_Rz", file=str(path), field=field
                    )
                q, t = openface_pose_to_gltf(track.openface_pose[:, 3:], track.openface_pose[:, :3])
                dense_q, dense_t = np.zeros((n, 4)), np.zeros((n, 3))
                dense_q[track.frame], dense_t[track.frame] = q, t
                rotation = interpolate_gaps(dense_q, valid)
                rotation /= np.linalg.norm(rotation, axis=1, keepdims=True)
                translation = interpolate_gaps(dense_t, valid)
            sequences.append(
                SequenceTrack(
                    label,
                    path.name,
                    landmarks,
                    valid,
                    conf,
                    times_arr,
                    fps,
                    (int(size[0]), int(size[1])),
                    field,
                    crops=crops,
                    crop_transforms=transforms,
                    video=video,
                    audio_source=audio[label],
                    rotation=rotation,
                    translation=translation,
                    meta={"track_format": track.format},
                )
            )
        fields = labels_fields(tracks, videos, inputs.get("audio"))
        return assemble(sequences, params, face3d, face3d_name, "TrackFile", fields=fields)


__all__ = ["FaceMesh", "OpticalFlow", "TrackFile"]
