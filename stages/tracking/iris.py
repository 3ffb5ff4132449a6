"""Eyes from MediaPipe's iris landmark model: a 64x64 crop per eye instead of a second full-face pass.

``iris_landmark.tflite`` (MediaPipe Iris; Ablavatski et al., "Real-time Pupil Tracking from Monocular Video for
Digital Puppetry", CVPR workshops 2020) sees one eye at a time, in a crop built as MediaPipe's
iris_landmark_landmarks_to_roi graph builds it from the face mesh:

- the eye's two corners (mesh 33 -> 133 for the performer's right eye, 362 -> 263 for the left, both running
  from the image's left to its right on a frontal face) give the centre (their midpoint) and the rotation (the
  line between them made level);
- the square side is ``EYE_ROI_SCALE`` = 2.3 times the corner distance (MediaPipe: 2.3 x the longer side of the
  corners' bounding box, the same for a level eye; the distance does not shrink when the head rolls);
- the model was trained on one eye only, the one outlined by 33/133: the other eye's crop is mirrored
  left-right, so its outer corner also lands on the crop's left. Here the mirror is part of the crop's affine map
  (the crop's x axis points the other way), so points map back through the same map with no flip of their own.

Input: RGB scaled to 0..1 (MediaPipe's converter with ``zero_center: false``). Outputs, in crop pixels:
``output_eyes_contours_and_brows`` (71 x (x, y, z)) and ``output_iris`` (5 x (x, y, z): centre, then 4 rim
points). The first 16 contour points are the eyelids, which MediaPipe writes over mesh vertices when it refines
the mesh (``CONTOUR_TO_MESH``: 9 lower-lid points from the outer to the inner corner, corners included, then 7
upper-lid points); the rest (halos, brow) are not used here.

The eye pass returns the 478-point layout of Face Landmarker v2 (the mesh with its lids replaced by the iris
model's, then the 10 iris points, 468-472 the eye outlined by 33/133), so ``eyes.eye_aperture`` and
``eyes.gaze_angles`` measure both passes the same way. As in MediaPipe's refinement, the lids keep the mesh's
depth and each iris gets the mean depth of its eye's 16 lid points.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

IRIS_INPUT = 64
EYE_ROI_SCALE = 2.3
OUTPUTS = ("output_eyes_contours_and_brows", "output_iris")
CONTOUR_POINTS, IRIS_POINTS = 71, 5
#: iris pass eye order: 0 = the performer's left eye (mirrored crop), 1 = the right eye (as the model expects);
#: each eye's box runs from its corner on the image's left to the one on its right
EYE_BOUNDARY = ((362, 263), (33, 133))
MIRRORED = (True, False)
#: per eye: mesh vertex of each of the first 16 contour points (lower lid outer -> inner corner, upper lid)
CONTOUR_TO_MESH = (
    (263, 249, 390, 373, 374, 380, 381, 382, 362, 466, 388, 387, 386, 385, 384, 398),
    (33, 7, 163, 144, 145, 153, 154, 155, 133, 246, 161, 160, 159, 158, 157, 173),
)
#: per eye: where its 5 iris points start in the 478-point layout
IRIS_START = (473, 468)
#: iris points of a mirrored crop in Face Landmarker v2's order: the rim points on the crop's right and left
#: (1 and 3) trade places, so that each index means the same side of the iris in the image for both eyes
MIRRORED_IRIS_ORDER = (0, 3, 2, 1, 4)


def eye_crop_maps(points: np.ndarray, scale: float = EYE_ROI_SCALE, size: int = IRIS_INPUT) -> np.ndarray:
    """(..., 2, 2, 3) affine maps crop pixels -> image pixels of both eyes' crops (eye 0 the performer's left,
    mirrored) from (..., >= 468, 2+) mesh points (module docstring)."""
    p = np.asarray(points, dtype=np.float64)[..., :2]
    maps = np.empty(p.shape[:-2] + (2, 2, 3))
    for eye, (start, end) in enumerate(EYE_BOUNDARY):
        a, b = p[..., start, :], p[..., end, :]
        side = scale * np.linalg.norm(b - a, axis=-1, keepdims=True)
        along = (b - a) / np.maximum(np.linalg.norm(b - a, axis=-1, keepdims=True), 1e-12)
        across = np.stack([-along[..., 1], along[..., 0]], axis=-1)  # along turned 90 degrees (image y down)
        u = along * side / size * (-1.0 if MIRRORED[eye] else 1.0)
        v = across * side / size
        origin = (a + b) / 2 - (u + v) * size / 2
        maps[..., eye, :, :] = np.stack([u, v, origin], axis=-1)
    return maps


def crop_to_image(local: np.ndarray, maps: np.ndarray) -> np.ndarray:
    """(..., points, 3) crop-pixel points (x, y, depth) through (..., 2, 3) maps to image pixels; depth is scaled
    like a length (by the map's scale)."""
    local = np.asarray(local, dtype=np.float64)
    out = np.empty_like(local)
    out[..., :2] = local[..., :2] @ np.swapaxes(maps[..., :2], -1, -2) + maps[..., None, :, 2]
    scale = np.sqrt(np.abs(np.linalg.det(maps[..., :2])))
    out[..., 2] = local[..., 2] * scale[..., None]
    return out


def refined_points(mesh: np.ndarray, contours: np.ndarray, irises: np.ndarray) -> np.ndarray:
    """(..., 478, 3) Face Landmarker v2 layout from (..., >= 468, 3) mesh points and both eyes' model outputs in
    image pixels, (..., 2, 71, 3) contours and (..., 2, 5, 3) irises (eye order of ``EYE_BOUNDARY``)."""
    mesh = np.asarray(mesh, dtype=np.float64)
    out = np.empty(mesh.shape[:-2] + (478, 3))
    out[..., :468, :] = mesh[..., :468, :]
    for eye, vertices in enumerate(CONTOUR_TO_MESH):
        idx = list(vertices)
        out[..., idx, :2] = contours[..., eye, : len(idx), :2]  # lids: the iris model's x, y; the mesh's depth
        iris = slice(IRIS_START[eye], IRIS_START[eye] + IRIS_POINTS)
        order = list(MIRRORED_IRIS_ORDER if MIRRORED[eye] else range(IRIS_POINTS))
        out[..., iris, :2] = irises[..., eye, order, :2]
        out[..., iris, 2] = mesh[..., idx, 2].mean(axis=-1)[..., None]
    return out


def image_to_crop(maps: np.ndarray) -> np.ndarray:
    """The warp (image pixel -> crop pixel index, for ``cv2.warpAffine``) sampling the crops of (..., 2, 3) maps.

    The model's points are continuous crop coordinates (pixel i spans [i, i + 1), as MediaPipe normalises them by
    the crop's side), so crop pixel i is sampled at map(i + 0.5): the inverse map minus half a pixel. Without it a
    crop would sit half a pixel off its map, in opposite directions for the mirrored and the plain eye."""
    a = np.linalg.inv(maps[..., :2])
    return np.concatenate([a, -(a @ maps[..., 2:]) - 0.5], axis=-1)


class IrisEyeModel:
    """The iris landmark model through OpenCV's DNN module: both eyes of a frame in one batch of two."""

    points = 478

    def __init__(self, model_path: str | Path):
        from stages.tracking.tflite import TfliteNet

        self.net = TfliteNet(model_path, OUTPUTS)

    def eye_patches(self, frame, maps: np.ndarray) -> np.ndarray:
        """(2, 3, 64, 64) float32 blob of both eyes' crops, RGB in 0..1."""
        import cv2

        patches = [frame.warp_bgr(m, IRIS_INPUT) for m in image_to_crop(maps)]
        return cv2.dnn.blobFromImages(patches, 1 / 255.0, swapRB=True)

    def infer(self, frame, mesh_points: np.ndarray) -> np.ndarray:
        """(478, 3) refined points (``refined_points``) of one frame (anything with ``warp_bgr``) from its
        (>= 468, 3) mesh points."""
        maps = eye_crop_maps(mesh_points)
        contours, irises = self.net.forward(self.eye_patches(frame, maps))
        contours = crop_to_image(np.asarray(contours, np.float64).reshape(2, CONTOUR_POINTS, 3), maps)
        irises = crop_to_image(np.asarray(irises, np.float64).reshape(2, IRIS_POINTS, 3), maps)
        return refined_points(mesh_points, contours, irises)
