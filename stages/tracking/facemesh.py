"""MediaPipe face landmarks on a rotated square region of interest, with tracking and re-detection.

Two landmark models, one interface (``LANDMARK_MODELS``):

- ``face_mesh_v1`` (``face_landmark.tflite``): the 468-point face mesh, 192x192 input (Kartynnik et al.,
  "Real-time Facial Surface Geometry from Monocular Video on Mobile GPUs", 2019);
- ``face_landmarker_v2`` (``face_landmarks_detector.tflite``): MediaPipe Face Landmarker v2, 256x256 input, the same
  468 mesh points plus 10 iris points (468-472: centre then rim of the eye with corners 33/133, the subject's
  right; 473-477 the same for the eye with corners 263/362, the subject's left); its eyelids close on blinks.

Per frame: the model input is the frame warped from a square ROI that is rotated so the eyes lie level; the model
returns the points (x, y in input pixels, z relative depth in the same units) and a face-presence logit. In
tracking mode the next frame's ROI comes from the current points (their bounding box, scaled 1.5x, squared,
rotated by the eye line: MediaPipe's face_landmark_landmarks_to_roi); BlazeFace runs only on the first frame and
whenever the presence score falls below the threshold: around where the face was last seen, then on the whole
frame and, while that finds no face, now and then on tiles of it (a face too small for the whole-frame pass: a
medium or wide shot); of several faces it follows the one nearest where the performer's was.

Frames are anything with ``warp_bgr(affine, size)`` (``stages.tracking.planes``: a decoded frame converted only
where the patch reads it, or a BGR image).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from stages.tracking.blazeface import BlazeFaceDetector, Detections, sigmoid
from stages.tracking.planes import as_image

#: while no face is found, the detector's tile search for small faces (``BlazeFaceDetector.detect``) runs on the
#: first such frame and every this many after (a frame's search costs about 0.3 s on a 720p frame; a face
#: appearing in a wide shot is found within a third of a second at 30 fps)
TILE_SEARCH_EVERY = 10
#: a face lost a moment ago is looked for first in a square this many times its last ROI (which is 1.5 times the
#: face's box), centred where it was: the face fills a third of it, as the detector likes
NEAR_SEARCH = 2.0
MESH_INPUT = 192
ROI_SCALE = 1.5
MESH_POINTS = 468
#: mesh vertices used for the ROI's rotation: outer corners of the subject's right and left eye
RIGHT_EYE_OUTER, LEFT_EYE_OUTER = 33, 263


@dataclass(frozen=True)
class Roi:
    """A square region in image pixels: centre, side length, rotation (radians, image axes, y down)."""

    cx: float
    cy: float
    size: float
    angle: float

    def input_to_image(self, input_size: int = MESH_INPUT) -> np.ndarray:
        """2x3 affine mapping model-input pixels to image pixels."""
        c, s = np.cos(self.angle), np.sin(self.angle)
        k = self.size / input_size
        u, v = np.array([c, s]) * k, np.array([-s, c]) * k
        origin = np.array([self.cx, self.cy]) - (u + v) * input_size / 2
        return np.column_stack([u, v, origin])

    def image_to_input(self, input_size: int = MESH_INPUT) -> np.ndarray:
        return invert_affine(self.input_to_image(input_size))


def invert_affine(m: np.ndarray) -> np.ndarray:
    """Inverse of 2x3 affine transforms (..., 2, 3)."""
    m = np.asarray(m, dtype=np.float64)
    a = m[..., :2]
    inv = np.linalg.inv(a)
    return np.concatenate([inv, -(inv @ m[..., 2:])], axis=-1)


def roll_angle(start: np.ndarray, end: np.ndarray) -> float:
    """Angle of the line start -> end in image axes (y down); 0 when level."""
    d = np.asarray(end, dtype=np.float64) - np.asarray(start, dtype=np.float64)
    return float(np.arctan2(d[1], d[0]))


def square_roi(x_min: float, y_min: float, x_max: float, y_max: float, angle: float, scale: float = ROI_SCALE) -> Roi:
    """MediaPipe's RectTransformation with square_long: centre of the box, side = scale x the longer edge."""
    side = scale * max(x_max - x_min, y_max - y_min)
    return Roi((x_min + x_max) / 2, (y_min + y_max) / 2, side, angle)


def roi_from_detection(detections: Detections, index: int = 0) -> Roi:
    """The landmark model's ROI from a BlazeFace detection (box, rotated by the eye keypoints)."""
    box = detections.boxes[index]
    right_eye, left_eye = detections.keypoints[index, 0], detections.keypoints[index, 1]
    return square_roi(*box, roll_angle(right_eye, left_eye))


def roi_from_mesh(points: np.ndarray) -> Roi:
    """The next frame's ROI from this frame's points (tracking mode): the bounding box of the 468 mesh points
    (the iris points of v2 lie inside it)."""
    xy = points[:MESH_POINTS, :2]
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    return square_roi(lo[0], lo[1], hi[0], hi[1], roll_angle(xy[RIGHT_EYE_OUTER], xy[LEFT_EYE_OUTER]))


@dataclass(frozen=True)
class LandmarkModelSpec:
    """A face landmark model: its file, input side, output names (points, presence logit) and point count."""

    file: str
    input_size: int
    outputs: tuple[str, str]
    points: int


LANDMARK_MODELS = {
    "face_mesh_v1": LandmarkModelSpec("face_landmark.tflite", 192, ("conv2d_21", "conv2d_31"), 468),
    "face_landmarker_v2": LandmarkModelSpec("face_landmarks_detector.tflite", 256, ("Identity", "Identity_1"), 478),
}


class FaceMeshModel:
    """A face landmark model (``LANDMARK_MODELS``) through OpenCV's DNN module."""

    def __init__(self, model_path: str | Path, spec: LandmarkModelSpec = LANDMARK_MODELS["face_mesh_v1"]):
        from stages.tracking.tflite import TfliteNet

        self.spec = spec
        self.net = TfliteNet(model_path, spec.outputs)

    def infer(self, frame, roi: Roi) -> tuple[np.ndarray, float]:
        """(points, 3) landmarks (x, y image pixels; z depth in pixels, same scale as x) and the presence score."""
        import cv2

        size = self.spec.input_size
        patch = as_image(frame).warp_bgr(roi.image_to_input(size), size)
        blob = cv2.dnn.blobFromImage(patch, 1 / 255.0, swapRB=True)  # RGB in 0..1
        raw, presence = self.net.forward(blob)
        local = raw.reshape(self.spec.points, 3).astype(np.float64)
        to_image = roi.input_to_image(size)
        points = np.empty_like(local)
        points[:, :2] = local[:, :2] @ to_image[:, :2].T + to_image[:, 2]
        points[:, 2] = local[:, 2] * roi.size / size
        return points, float(sigmoid(float(np.clip(presence.reshape(-1)[0], -100, 100))))


#: points of an eye pass (the Face Landmarker v2 layout, whichever model made it)
EYE_PASS_POINTS = 478


def new_eye_pass(kind: str, path: str | Path):
    """The eye pass model: 'landmarker_v2' (Face Landmarker v2 on the face ROI) or 'iris' (the iris model)."""
    if kind == "iris":
        from stages.tracking.iris import IrisEyeModel

        return IrisEyeModel(path)
    return FaceMeshModel(path, LANDMARK_MODELS["face_landmarker_v2"])


def eye_pass_points(model, frame, roi: Roi, points: np.ndarray) -> np.ndarray:
    """(478, 3) eye-pass points of one frame: v2 sees the same ROI as the landmark model; the iris model crops
    each eye around this frame's mesh corners."""
    if isinstance(model, FaceMeshModel):
        return model.infer(frame, roi)[0]
    return model.infer(frame, points)


class FaceMeshTracker:
    """Detector + landmark model with MediaPipe's tracking logic for one face, one frame at a time."""

    def __init__(
        self,
        detector_path: str | Path,
        landmark_path: str | Path,
        *,
        min_detection_score: float = 0.5,
        min_presence: float = 0.5,
        redetect_every: int = 0,
        model: str = "face_mesh_v1",
        eye_model_path: str | Path | None = None,
        eye_pass: str = "landmarker_v2",
        first_face: str = "most_certain",
    ):
        self.detector = BlazeFaceDetector(detector_path, min_score=min_detection_score)
        self.mesh = FaceMeshModel(landmark_path, LANDMARK_MODELS[model])
        #: a second model for the eyes, giving the 478-point layout: Face Landmarker v2 on the same ROI
        #: (``eye_pass`` 'landmarker_v2') or the iris model on a crop around each eye ('iris', stages/tracking/iris.py)
        self.eyes = new_eye_pass(eye_pass, eye_model_path) if eye_model_path else None
        self.min_presence = min_presence
        self.redetect_every = redetect_every
        #: which of several faces a take starts with: "most_certain" (the detector's), "largest", "leftmost" or
        #: "rightmost" (in the picture); after that the tracker follows it (``follow``)
        self.first_face = first_face
        self.reset()

    def reset(self) -> None:
        """Forget the face (the next frame starts with detection)."""
        self.roi: Roi | None = None
        self.faceless = 0  # frames in a row without a face
        self.last_seen: Roi | None = None  # the ROI of the last frame with a face
        self.since_detection = 0
        self.detections = 0
        self.detector_scores: list[float] = []

    @property
    def points(self) -> int:
        """Points per frame ``step`` returns: the landmark model's, then the eye model's when there is one."""
        return self.mesh.spec.points + (EYE_PASS_POINTS if self.eyes is not None else 0)

    @property
    def eye_offset(self) -> int | None:
        """Where a 478-point (Face Landmarker v2) layout starts in ``step``'s points; None: no eyes."""
        if self.eyes is not None:
            return self.mesh.spec.points
        return 0 if self.mesh.spec.points >= 478 else None

    def step(self, frame) -> tuple[np.ndarray | None, float]:
        """(``points``, 3) landmarks and presence score for the next frame (BGR array or ``planes.FramePlanes``);
        (None, 0.0) when no face is found. With an eye model its 478 points follow the landmark model's.

        The ROI comes from the previous frame's points; the detector runs when there is none, when the presence
        score drops below ``min_presence`` (the tracked face was lost) or every ``redetect_every`` frames.
        """
        frame = as_image(frame)
        if self.redetect_every and self.since_detection >= self.redetect_every:
            self.roi = None
        roi, points, score = self.roi, None, 0.0
        if roi is not None:
            points, score = self.mesh.infer(frame, roi)
        if roi is None or score < self.min_presence:
            found = self.find_face(frame)
            self.detections += 1
            self.since_detection = 0
            roi, points, score = None, None, 0.0
            if len(found):
                index = self.follow(found)
                self.detector_scores.append(float(found.scores[index]))
                roi = roi_from_detection(found, index)
                points, score = self.mesh.infer(frame, roi)
        self.since_detection += 1
        if points is None or score < self.min_presence:
            self.roi, self.faceless = None, self.faceless + 1
            return None, 0.0
        self.roi, self.faceless = roi_from_mesh(points), 0
        self.last_seen = self.roi
        if self.eyes is not None:
            points = np.concatenate([points, eye_pass_points(self.eyes, frame, roi, points)])
        return points, score

    def find_face(self, frame) -> Detections:
        """Faces in a frame without a tracked one: first around where the face was last seen (a square
        ``NEAR_SEARCH`` times its ROI: it is most likely still there, and found in one inference however small),
        then in the whole frame, and on the first frame without a face and every ``TILE_SEARCH_EVERY``-th after,
        in the frame's tiles (a face too small for the whole-frame pass)."""
        if self.last_seen is not None:
            seen = self.last_seen
            near = self.detector.detect_near(frame, seen.cx, seen.cy, NEAR_SEARCH * seen.size)
            if len(near):
                return near
        choose = self.last_seen is None and self.first_face != "most_certain"  # every face, at every scale
        return self.detector.detect(frame, tiles=choose or self.faceless % TILE_SEARCH_EVERY == 0, every_scale=choose)

    def follow(self, found: Detections) -> int:
        """Which detection is the performer: the one nearest where the face was last seen (another face in the
        shot is someone else), or on a take's first detection the one ``first_face`` names."""
        centres = found.boxes.reshape(-1, 2, 2).mean(axis=1)
        if self.last_seen is not None:
            return int(np.argmin(np.linalg.norm(centres - [self.last_seen.cx, self.last_seen.cy], axis=1)))
        if self.first_face == "largest":
            return int(np.argmax(np.prod(found.boxes[:, 2:] - found.boxes[:, :2], axis=1)))
        if self.first_face in ("leftmost", "rightmost"):
            return int(np.argmin(centres[:, 0]) if self.first_face == "leftmost" else np.argmax(centres[:, 0]))
        return 0

    def track(self, frames: Iterable) -> tuple[np.ndarray, np.ndarray]:
        """All frames at once: (points (n, points, 3) with NaN where no face, presence scores (n,))."""
        self.reset()
        n_points = self.points
        points, scores = [], []
        for frame in frames:
            p, s = self.step(frame)
            points.append(np.full((n_points, 3), np.nan) if p is None else p)
            scores.append(s)
        return np.array(points).reshape(-1, n_points, 3), np.array(scores)
