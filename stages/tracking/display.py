"""Video frames as a player shows them: the container's display matrix applied.

Phones store a portrait video as landscape frames with a display matrix that tells players to turn them (a front
camera's may mirror them too); FFmpeg's command-line tool applies it, PyAV does not. Tracking a stored frame would
read the performer lying on their side: a head rolled 90°, a frame size with width and height swapped, crops on
their side. So tracking works in display coordinates: a stored pixel (x, y) is shown at L (x, y) + t, where L is
the matrix's 2 x 2 part (a quarter turn, a mirror, or both) and t brings the picture back to the origin.

The convention (FFmpeg's ``AV_FRAME_DATA_DISPLAYMATRIX``, nine 32-bit integers, the 2 x 2 part in 16.16 fixed
point: x' = a x + c y, y' = b x + d y for a, b, c, d = m[0], m[1], m[3], m[4]) was checked against ``ffmpeg``'s own
auto-rotation on all eight turns and mirrors (tests/test_tracking_display.py builds videos the same way).
"""

from __future__ import annotations

import struct

import numpy as np

from msflow import UserError

IDENTITY = np.eye(2, dtype=np.int64)


def display_matrix(angle: float, hflip: bool = False, vflip: bool = False) -> list[int]:
    """The nine integers of a display matrix that turns a picture by ``angle`` degrees and mirrors it: FFmpeg's
    ``av_display_rotation_set`` then ``av_display_matrix_flip``, written out (for writing videos that carry one)."""
    r = -np.radians(angle)
    m = [int(v * 65536) for v in (np.cos(r), -np.sin(r), 0.0, np.sin(r), np.cos(r), 0.0, 0.0, 0.0, 0.0)]
    m[8] = 1 << 30
    flip = (1 - 2 * int(hflip), 1 - 2 * int(vflip), 1)
    return [m[i] * flip[i % 3] for i in range(9)]


def matrix_linear(matrix) -> np.ndarray:
    """The (2, 2) part of a display matrix (nine integers), in pixels: x' = a x + c y, y' = b x + d y."""
    return np.array([[matrix[0], matrix[3]], [matrix[1], matrix[4]]], dtype=np.float64) / 65536.0


def stored_picture(image: np.ndarray, matrix) -> np.ndarray:
    """The picture to store so that a player applying ``matrix`` (a quarter turn or mirror) shows ``image``."""
    return show_upright(image, np.rint(np.linalg.inv(np.rint(matrix_linear(matrix)))).astype(np.int64))


def display_linear(frame, *, file: str | None = None, field: str | None = None) -> np.ndarray:
    """The (2, 2) integer matrix L that shows a decoded PyAV frame upright (identity without a display matrix).

    Raises UserError for a matrix that is no quarter turn or mirror (an arbitrary angle or a scaling): tracking
    would need to resample the picture, which no camera asks for."""
    for data in _side_data(frame):
        if "DISPLAYMATRIX" not in str(data.type):
            continue
        linear = matrix_linear(struct.unpack("<9i", bytes(data)[:36]))
        rounded = np.rint(linear)
        if np.abs(linear - rounded).max() > 1e-3 or abs(abs(np.linalg.det(rounded)) - 1.0) > 1e-9:
            angle = np.degrees(np.arctan2(linear[1, 0], linear[0, 0]))
            raise UserError(
                f"the video's display matrix turns its picture by {angle:.0f} degrees (or scales it): only quarter "
                "turns and mirrors are supported; turn the video upright first (ffmpeg -i in.mp4 out.mp4 applies it)",
                file=file,
                field=field,
            )
        return rounded.astype(np.int64)
    return IDENTITY


def _side_data(frame):
    """A frame's side-data entries: PyAV up to 18.0 iterates them, 18.1 made the container a mapping whose
    iteration gives their types (each entry is then looked up by its type)."""
    container = frame.side_data
    for item in container:
        yield item if hasattr(item, "type") else container[item]


def display_affine(linear: np.ndarray, width: int, height: int) -> np.ndarray:
    """(2, 3) affine from stored pixel coordinates (pixel centres at integers) to displayed ones: ``linear``, then
    the shift that puts the displayed picture's corner at the origin."""
    corners = np.array([[0, width - 1, 0, width - 1], [0, 0, height - 1, height - 1]], dtype=np.float64)
    shift = -(np.asarray(linear, np.float64) @ corners).min(axis=1)
    return np.hstack([np.asarray(linear, np.float64), shift[:, None]])


def displayed_size(linear: np.ndarray, width: int, height: int) -> tuple[int, int]:
    """(width, height) of the displayed picture."""
    return (height, width) if np.asarray(linear)[0, 0] == 0 else (width, height)


def show_upright(image: np.ndarray, linear: np.ndarray) -> np.ndarray:
    """A stored image (h, w[, c]) as displayed: its pixels moved by ``display_affine`` (a permutation)."""
    if np.array_equal(linear, IDENTITY):
        return image
    import cv2

    height, width = image.shape[:2]
    size = displayed_size(linear, width, height)
    return cv2.warpAffine(image, display_affine(linear, width, height), size, flags=cv2.INTER_NEAREST)


def then(affine: np.ndarray, display: np.ndarray) -> np.ndarray:
    """(2, 3) affine ``affine`` (displayed -> patch) after ``display`` (stored -> displayed): stored -> patch."""
    a = np.vstack([np.asarray(affine, np.float64), [0.0, 0.0, 1.0]])
    d = np.vstack([np.asarray(display, np.float64), [0.0, 0.0, 1.0]])
    return (a @ d)[:2]


class UprightPlanes:
    """A ``planes.FramePlanes`` (or ``BgrImage``) seen in display coordinates: its warps compose the display
    affine with theirs, so the lazy region conversion of the stored frame stays as it is."""

    def __init__(self, stored, linear: np.ndarray):
        self.stored, self.linear = stored, np.asarray(linear)
        height, width = stored.shape
        self.affine = display_affine(self.linear, width, height)
        self._shape = displayed_size(self.linear, width, height)[::-1]

    @property
    def shape(self) -> tuple[int, int]:
        return self._shape

    def warp_bgr(self, affine: np.ndarray, size: int) -> np.ndarray:
        return self.stored.warp_bgr(then(affine, self.affine), size)

    def warp_gray(self, affine: np.ndarray, size: int) -> np.ndarray:
        return self.stored.warp_gray(then(affine, self.affine), size)

    def gray_image(self):
        from stages.tracking.planes import BgrImage

        return BgrImage(show_upright(self.stored.gray(), self.linear))

    def gray(self) -> np.ndarray:
        return self.gray_image().bgr
