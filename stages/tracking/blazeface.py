"""BlazeFace short-range face detector: SSD anchors, box decoding and weighted non-maximum suppression.

The model (``face_detection_short_range.tflite``) maps a 128x128 RGB image in [-1, 1] to 896 anchor-relative
boxes (``regressors``: centre offset, size, 6 keypoints) and 896 logits (``classificators``). The anchor layout
and decoding follow MediaPipe's face_detection_short_range graph (SsdAnchorsCalculator with 4 layers, strides
8, 16, 16, 16, fixed anchor size; TensorsToDetectionsCalculator with scale 128; weighted NMS at IoU 0.3).
Bazarevsky et al., "BlazeFace: Sub-millisecond Neural Face Detection on Mobile GPUs", 2019.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

INPUT_SIZE = 128
STRIDES = (8, 16, 16, 16)
#: keypoint order of the model's 6 keypoints (subject's right/left, as MediaPipe names them)
KEYPOINTS = ("right_eye", "left_eye", "nose_tip", "mouth_centre", "right_ear_tragion", "left_ear_tragion")


def ssd_anchor_centres(input_size: int = INPUT_SIZE, strides=STRIDES, anchor_offset: float = 0.5) -> np.ndarray:
    """(896, 2) anchor centres in [0, 1] image coordinates, in the order the model emits them.

    MediaPipe's SsdAnchorsCalculator groups consecutive layers with equal stride into one feature map; each map
    cell gets 2 anchors per layer in the group (aspect ratio 1 plus the interpolated-scale anchor). With
    ``fixed_anchor_size`` every anchor is 1 x 1, so only centres matter: 16x16x2 + 8x8x6 = 896.
    """
    centres = []
    layer = 0
    while layer < len(strides):
        stride = strides[layer]
        same = 0
        while layer < len(strides) and strides[layer] == stride:
            same += 1
            layer += 1
        cells = int(np.ceil(input_size / stride))
        ys, xs = np.meshgrid(
            (np.arange(cells) + anchor_offset) / cells, (np.arange(cells) + anchor_offset) / cells, indexing="ij"
        )
        grid = np.stack([xs.ravel(), ys.ravel()], axis=-1)
        centres.append(np.repeat(grid, 2 * same, axis=0))
    return np.concatenate(centres).astype(np.float64)


ANCHORS = ssd_anchor_centres()


@dataclass
class Detections:
    """Faces found in one image, best first. Coordinates in the pixels of the image given to ``detect``."""

    FIELDS = ("scores", "boxes", "keypoints")

    scores: np.ndarray  # (k,)
    boxes: np.ndarray  # (k, 4) x_min, y_min, x_max, y_max
    keypoints: np.ndarray  # (k, 6, 2) see KEYPOINTS

    def __len__(self) -> int:
        return len(self.scores)


def decode_boxes(
    regressors: np.ndarray, anchors: np.ndarray = ANCHORS, scale: float = INPUT_SIZE
) -> tuple[np.ndarray, np.ndarray]:
    """Anchor-relative regressors (n, 16) to boxes (n, 4: x_min, y_min, x_max, y_max) and keypoints (n, 6, 2),
    all in [0, 1] coordinates of the model input (MediaPipe's decoding with unit anchor size)."""
    reg = np.asarray(regressors, dtype=np.float64).reshape(len(anchors), -1)
    centre = reg[:, 0:2] / scale + anchors
    half = reg[:, 2:4] / scale / 2
    boxes = np.concatenate([centre - half, centre + half], axis=1)
    keypoints = reg[:, 4:16].reshape(-1, 6, 2) / scale + anchors[:, None, :]
    return boxes, keypoints


def box_iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Intersection over union of one box (4,) with many (n, 4), corner format."""
    lo = np.maximum(box[:2], boxes[:, :2])
    hi = np.minimum(box[2:], boxes[:, 2:])
    inter = np.prod(np.clip(hi - lo, 0, None), axis=1)
    area = np.prod(box[2:] - box[:2])
    areas = np.prod(boxes[:, 2:] - boxes[:, :2], axis=1)
    return inter / np.maximum(area + areas - inter, 1e-12)


def weighted_nms(
    scores: np.ndarray,
    boxes: np.ndarray,
    keypoints: np.ndarray,
    iou_threshold: float = 0.3,
    max_faces: int | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted non-maximum suppression (MediaPipe's WEIGHTED algorithm, BlazeFace paper Sec. 2.3).

    Candidates are taken best first; every remaining candidate overlapping the best one by more than
    ``iou_threshold`` joins its cluster and is removed. The cluster's box and keypoints are the score-weighted
    mean of its members, its score the best member's: averaging the overlapping anchors' predictions makes the
    box steadier from frame to frame than keeping the single best anchor.
    """
    order = np.argsort(-scores, kind="stable")
    scores, boxes, keypoints = scores[order], boxes[order], keypoints[order]
    out_scores, out_boxes, out_keypoints = [], [], []
    remaining = np.arange(len(scores))
    while remaining.size and (max_faces is None or len(out_scores) < max_faces):
        best = remaining[0]
        overlap = box_iou(boxes[best], boxes[remaining]) > iou_threshold
        cluster = remaining[overlap]
        weights = scores[cluster] / scores[cluster].sum()
        out_scores.append(scores[best])
        out_boxes.append(weights @ boxes[cluster])
        out_keypoints.append(np.tensordot(weights, keypoints[cluster], axes=1))
        remaining = remaining[~overlap]
    if not out_scores:
        return np.zeros(0), np.zeros((0, 4)), np.zeros((0, 6, 2))
    return np.array(out_scores), np.array(out_boxes), np.array(out_keypoints)


def letterbox_transform(width: int, height: int, size: int = INPUT_SIZE) -> np.ndarray:
    """2x3 affine mapping image pixels into a ``size`` square, aspect kept, padded evenly (MediaPipe's
    ``keep_aspect_ratio`` letterbox)."""
    scale = size / max(width, height)
    return np.array([[scale, 0.0, (size - width * scale) / 2], [0.0, scale, (size - height * scale) / 2]])


#: tile sides of the search for small faces (``BlazeFaceDetector.detect``), as fractions of the frame's shorter
#: side: with the model finding faces down to about a fifth of its input, they find faces down to about a tenth
#: and a twentieth of the frame's height
TILE_FRACTIONS = (0.5, 0.25)
#: no tile smaller than this (pixels): a face a fifth of it is too small for the landmark model to be of use
MIN_TILE = 64


def tile_transforms(width: int, height: int, fractions=TILE_FRACTIONS, overlap: float = 0.5) -> list[np.ndarray]:
    """2x3 affines mapping image pixels into the model's input square for overlapping square tiles covering the
    frame: each side of ``fractions`` x the shorter side (at least ``MIN_TILE``), consecutive tiles overlapping by
    ``overlap`` of a side, the last flush with the frame's edge."""
    out = []
    for fraction in fractions:
        side = fraction * min(width, height)
        if side < MIN_TILE:
            continue
        scale = INPUT_SIZE / side
        for y0 in tile_starts(height, side, overlap):
            for x0 in tile_starts(width, side, overlap):
                out.append(np.array([[scale, 0.0, -x0 * scale], [0.0, scale, -y0 * scale]]))
    return out


def tile_starts(length: int, side: float, overlap: float) -> np.ndarray:
    """Start positions (pixels) of tiles of ``side`` along ``length``, evenly spread, overlapping by at least
    ``overlap`` of a side."""
    count = int(np.ceil(max(length - side, 0.0) / (side * (1.0 - overlap)))) + 1
    return np.linspace(0.0, max(length - side, 0.0), count)


def sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x))


class BlazeFaceDetector:
    """Runs the short-range BlazeFace model through OpenCV's DNN module on BGR frames."""

    def __init__(self, model_path: str | Path, *, min_score: float = 0.5, iou_threshold: float = 0.3):
        from stages.tracking.tflite import TfliteNet

        self.net = TfliteNet(model_path, ("classificators", "regressors"))
        self.min_score = min_score
        self.iou_threshold = iou_threshold

    def detect(self, frame, max_faces: int | None = None, tiles: bool = False, every_scale: bool = False) -> Detections:
        """Faces in a frame: a BGR array, or anything with ``shape`` and ``warp_bgr`` (``planes.FramePlanes``).

        The whole frame is searched at once (letterboxed to the model's input). With ``tiles``, when that finds
        nothing, overlapping square tiles are searched too (``tile_transforms``): the short-range model sees a face
        filling at least about a fifth of its input, and a medium or wide shot's face is a tenth of the frame or
        less. Only faces whole within a tile count (every face smaller than half a tile lies whole in one).
        ``every_scale``: search the tiles even when the whole frame shows a face (every face in the shot, small
        ones beside a large one)."""
        from stages.tracking.planes import as_image

        frame = as_image(frame)
        height, width = frame.shape[:2]
        found = self._detect_in(frame, letterbox_transform(width, height), None if every_scale else max_faces)
        if (len(found) and not every_scale) or not tiles:
            return found
        parts = [self._detect_in(frame, to_input, None, whole=True) for to_input in tile_transforms(width, height)]
        parts.append(found)
        if not any(len(part) for part in parts):
            return found
        scores, boxes, keypoints = (np.concatenate([getattr(p, name) for p in parts]) for name in Detections.FIELDS)
        return Detections(*weighted_nms(scores, boxes, keypoints, self.iou_threshold, max_faces))

    def detect_near(self, frame, cx: float, cy: float, side: float) -> Detections:
        """Faces whole within the square of ``side`` pixels centred on (``cx``, ``cy``) (padded black beyond the
        frame): where a face lost a moment ago most likely still is, found in one inference however small."""
        from stages.tracking.planes import as_image

        frame = as_image(frame)
        scale = INPUT_SIZE / side
        to_input = np.array([[scale, 0.0, -(cx - side / 2) * scale], [0.0, scale, -(cy - side / 2) * scale]])
        return self._detect_in(frame, to_input, None, whole=True)

    def _detect_in(self, frame, to_input: np.ndarray, max_faces: int | None, whole: bool = False) -> Detections:
        """Faces in the square the affine ``to_input`` (image pixels -> the model's input) cuts out of ``frame``, in
        image pixels; ``whole``: only boxes inside that square (a face cut by a tile's edge is left to the tile
        that holds it whole)."""
        import cv2

        square = frame.warp_bgr(to_input, INPUT_SIZE)  # black padding
        # the detector was trained on RGB in [-1, 1]
        blob = cv2.dnn.blobFromImage(square, 1 / 127.5, mean=(127.5, 127.5, 127.5), swapRB=True)
        logits, regressors = self.net.forward(blob)
        # MediaPipe clips logits to +-100 before the sigmoid
        scores = sigmoid(np.clip(logits.reshape(-1).astype(np.float64), -100, 100))
        keep = scores >= self.min_score
        if not keep.any():
            return Detections(np.zeros(0), np.zeros((0, 4)), np.zeros((0, 6, 2)))
        boxes, keypoints = decode_boxes(regressors.reshape(-1, 16))
        scores, boxes, keypoints = weighted_nms(
            scores[keep], boxes[keep], keypoints[keep], self.iou_threshold, max_faces
        )
        if whole:
            inside = ((boxes >= -0.02) & (boxes <= 1.02)).all(axis=1)
            scores, boxes, keypoints = scores[inside], boxes[inside], keypoints[inside]
        # [0, 1] model coordinates -> image pixels (undo the letterbox)
        scale, ox, oy = to_input[0, 0], to_input[0, 2], to_input[1, 2]
        offset = np.array([ox, oy])
        boxes = (boxes.reshape(-1, 2, 2) * INPUT_SIZE - offset) / scale
        keypoints = (keypoints * INPUT_SIZE - offset) / scale
        return Detections(scores, boxes.reshape(-1, 4), keypoints)
