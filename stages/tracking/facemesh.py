"""MediaPipe face mesh (468 points) on a rotated square region of interest, with tracking and re-detection.

Per frame: the 192x192 model input is the frame warped from a square ROI that is rotated so the eyes lie level;
the model returns 468 points (x, y in input pixels, z relative depth) and a face-presence logit. In tracking
mode the next frame's ROI comes from the current points (their bounding box, scaled 1.5x, squared, rotated by
the eye line: MediaPipe's face_landmark_landmarks_to_roi); BlazeFace runs only on the first frame and whenever
the presence score falls below the threshold. Kartynnik et al., "Real-time Facial Surface Geometry from
Monocular Video on Mobile GPUs", 2019.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from stages.tracking.blazeface import BlazeFaceDetector, Detections, sigmoid

MESH_INPUT = 192
ROI_SCALE = 1.5
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
    """The next frame's ROI from this frame's 468 points (tracking mode)."""
    xy = points[:, :2]
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    return square_roi(lo[0], lo[1], hi[0], hi[1], roll_angle(xy[RIGHT_EYE_OUTER], xy[LEFT_EYE_OUTER]))


class FaceMeshModel:
    """The 468-point landmark model (``face_landmark.tflite``) through OpenCV's DNN module."""

    def __init__(self, model_path: str | Path):
        from stages.tracking.tflite import TfliteNet

        self.net = TfliteNet(model_path, ("conv2d_21", "conv2d_31"))

    def infer(self, bgr: np.ndarray, roi: Roi) -> tuple[np.ndarray, float]:
        """(468, 3) points (x, y image pixels; z depth in pixels, same scale as x) and the presence score."""
        import cv2

        to_input = roi.image_to_input()
        patch = cv2.warpAffine(
            bgr,
            to_input,
            (MESH_INPUT, MESH_INPUT),
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=(0, 0, 0),
        )
        blob = cv2.dnn.blobFromImage(patch, 1 / 255.0, swapRB=True)
        raw, presence = self.net.forward(blob)
        local = raw.reshape(468, 3).astype(np.float64)
        to_image = roi.input_to_image()
        points = np.empty_like(local)
        points[:, :2] = local[:, :2] @ to_image[:, :2].T + to_image[:, 2]
        points[:, 2] = local[:, 2] * roi.size / MESH_INPUT
        return points, float(sigmoid(float(np.clip(presence.reshape(-1)[0], -100, 100))))


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
    ):
        self.detector = BlazeFaceDetector(detector_path, min_score=min_detection_score)
        self.mesh = FaceMeshModel(landmark_path)
        self.min_presence = min_presence
        self.redetect_every = redetect_every
        self.reset()

    def reset(self) -> None:
        """Forget the face (the next frame starts with detection)."""
        self.roi: Roi | None = None
        self.since_detection = 0
        self.detections = 0
        self.detector_scores: list[float] = []

    def step(self, frame: np.ndarray) -> tuple[np.ndarray | None, float]:
        """(468, 3) points and presence score for the next BGR frame; (None, 0.0) when no face is found.

        The ROI comes from the previous frame's points; the detector runs when there is none, when the presence
        score drops below ``min_presence`` (the tracked face was lost) or every ``redetect_every`` frames.
        """
        if self.redetect_every and self.since_detection >= self.redetect_every:
            self.roi = None
        points, score = None, 0.0
        if self.roi is not None:
            points, score = self.mesh.infer(frame, self.roi)
        if self.roi is None or score < self.min_presence:
            found = self.detector.detect(frame, max_faces=1)
            self.detections += 1
            self.since_detection = 0
            points, score = None, 0.0
            if len(found):
                self.detector_scores.append(float(found.scores[0]))
                points, score = self.mesh.infer(frame, roi_from_detection(found))
        self.since_detection += 1
        if points is None or score < self.min_presence:
            self.roi = None
            return None, 0.0
        self.roi = roi_from_mesh(points)
        return points, score

    def track(self, frames: Iterable[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """All frames at once: (points (n, 468, 3) with NaN where no face, presence scores (n,))."""
        self.reset()
        points, scores = [], []
        for frame in frames:
            p, s = self.step(frame)
            points.append(np.full((468, 3), np.nan) if p is None else p)
            scores.append(s)
        return np.array(points).reshape(-1, 468, 3), np.array(scores)
