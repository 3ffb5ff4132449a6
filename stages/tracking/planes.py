"""Decoded video frames kept as their Y'CbCr planes: the tracker takes only the small patches it needs (the face
region for the landmark model, the face crop) from them, instead of converting every whole frame to BGR.

A frame is warped plane by plane: ``cv2.warpAffine`` of the luma plane with the patch's affine map, and of each
chroma plane with the same map composed with the chroma subsampling (a chroma sample (i, j) of a 4:2:0 plane sits
at luma position (2j + 0.5, 2i + 0.5) in pixel-centre coordinates, the centred siting swscale's own 4:2:0 -> RGB
converters assume), then the patch alone is converted to RGB:

    R = s (Y - y0) + r_v (V - 128)
    G = s (Y - y0) - g_u (U - 128) - g_v (V - 128)
    B = s (Y - y0) + b_u (U - 128)

with the BT.601 or BT.709 coefficients (Rec. ITU-R BT.601-7 Table 3, BT.709-6 Item 3.2) scaled for limited range
(``s`` = 255/219, y0 = 16, chroma scaled by 255/224) or full range (``s`` = 1, y0 = 0); an untagged frame is BT.601,
as swscale assumes. Grayscale face crops are the luma patch mapped to full range (s (Y - y0)): the gray value
OpenCV computes from RGB (0.299 R + 0.587 G + 0.114 B) is exactly that luma, up to rounding and RGB clipping.

Any other pixel format is converted once per frame to 4:4:4 planes (``yuv444p``) by swscale.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: (K_R, K_B) luma weights per colour matrix
MATRICES = {"bt601": (0.299, 0.114), "bt709": (0.2126, 0.0722)}
#: FFmpeg AVColorSpace values meaning BT.709 (1) and the 601 family (5 BT470BG, 6 SMPTE170M); others use BT.601
BT709_SPACES = {1}
#: pixel formats used as they come: name -> (chroma subsampling x, y, full range)
PLANAR = {
    "yuv420p": (2, 2, False),
    "yuvj420p": (2, 2, True),
    "yuv422p": (2, 1, False),
    "yuvj422p": (2, 1, True),
    "yuv444p": (1, 1, False),
    "yuvj444p": (1, 1, True),
}


def yuv_to_rgb_matrix(matrix: str = "bt601", full_range: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(3x3 M, offsets o) with RGB (0..255) = M @ ([Y, U, V] - o)."""
    kr, kb = MATRICES[matrix]
    kg = 1.0 - kr - kb
    y_scale, c_scale, y0 = (1.0, 1.0, 0.0) if full_range else (255.0 / 219.0, 255.0 / 224.0, 16.0)
    rv = 2.0 * (1.0 - kr) * c_scale
    bu = 2.0 * (1.0 - kb) * c_scale
    gu = bu * kb / kg
    gv = rv * kr / kg
    m = np.array([[y_scale, 0.0, rv], [y_scale, -gu, -gv], [y_scale, bu, 0.0]])
    return m, np.array([y0, 128.0, 128.0])


def luma_to_gray_table(full_range: bool) -> np.ndarray:
    """uint8 lookup table mapping luma codes to full-range gray."""
    codes = np.arange(256, dtype=np.float64)
    gray = codes if full_range else (codes - 16.0) * 255.0 / 219.0
    return np.clip(np.rint(gray), 0, 255).astype(np.uint8)


GRAY_TABLES = {False: luma_to_gray_table(False), True: luma_to_gray_table(True)}


def chroma_affine(affine: np.ndarray, sx: int, sy: int) -> np.ndarray:
    """The map from chroma-plane pixels to patch pixels, given ``affine`` from luma-plane pixels to patch pixels.

    ``cv2.warpAffine`` takes the map from source to destination: luma (x, y) -> patch. A chroma sample at (cx, cy)
    sits at luma ((cx + 0.5) sx - 0.5, (cy + 0.5) sy - 0.5), so chroma -> patch is ``affine`` applied after that.
    """
    a = np.asarray(affine, dtype=np.float64)
    to_luma = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])
    return (np.vstack([a, [0.0, 0.0, 1.0]]) @ to_luma)[:2]


@dataclass
class FramePlanes:
    """One frame as Y'CbCr planes (views into the decoder's buffers while the frame object lives)."""

    y: np.ndarray
    u: np.ndarray
    v: np.ndarray
    sx: int
    sy: int
    full_range: bool
    matrix: str
    frame: object = None  # keeps the decoder's buffers alive

    @property
    def shape(self) -> tuple[int, int]:
        return self.y.shape

    def warp_rgb(self, affine: np.ndarray, size: int) -> np.ndarray:
        """(size, size, 3) float32 RGB in 0..1: the frame warped by ``affine`` (image -> patch pixels), black
        outside the frame."""
        import cv2

        black_y = 0.0 if self.full_range else 16.0
        flags, border = cv2.INTER_LINEAR, cv2.BORDER_CONSTANT
        y = cv2.warpAffine(self.y, affine, (size, size), flags=flags, borderMode=border, borderValue=black_y)
        c = chroma_affine(affine, self.sx, self.sy)
        u = cv2.warpAffine(self.u, c, (size, size), flags=flags, borderMode=border, borderValue=128)
        v = cv2.warpAffine(self.v, c, (size, size), flags=flags, borderMode=border, borderValue=128)
        m, offset = yuv_to_rgb_matrix(self.matrix, self.full_range)
        yuv = np.stack([y, u, v], axis=-1).astype(np.float32) - offset.astype(np.float32)
        rgb = yuv @ (m.T / 255.0).astype(np.float32)
        return np.clip(rgb, 0.0, 1.0, out=rgb)

    def warp_gray(self, affine: np.ndarray, size: int) -> np.ndarray:
        """(size, size) uint8 full-range gray: the luma plane warped by ``affine``, border pixels repeated."""
        import cv2

        y = cv2.warpAffine(self.y, affine, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return GRAY_TABLES[self.full_range][y]

    def gray(self) -> np.ndarray:
        """The whole frame as full-range gray (a copy)."""
        return GRAY_TABLES[self.full_range][self.y]


@dataclass
class BgrImage:
    """A BGR uint8 image with the FramePlanes interface (for frames that are already images)."""

    bgr: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.bgr.shape[:2]

    def warp_rgb(self, affine: np.ndarray, size: int) -> np.ndarray:
        import cv2

        patch = cv2.warpAffine(
            self.bgr, affine, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
        )
        return patch[..., ::-1].astype(np.float32) / 255.0

    def warp_gray(self, affine: np.ndarray, size: int) -> np.ndarray:
        import cv2

        gray = cv2.cvtColor(self.bgr, cv2.COLOR_BGR2GRAY) if self.bgr.ndim == 3 else self.bgr
        return cv2.warpAffine(gray, affine, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def gray(self) -> np.ndarray:
        import cv2

        return cv2.cvtColor(self.bgr, cv2.COLOR_BGR2GRAY) if self.bgr.ndim == 3 else self.bgr.copy()


def plane_view(plane, height: int, width: int) -> np.ndarray:
    """A (height, width) uint8 view of one PyAV plane (rows padded to its line size)."""
    return np.frombuffer(plane, np.uint8).reshape(-1, plane.line_size)[:height, :width]


def frame_planes(frame) -> FramePlanes:
    """The planes of a decoded PyAV VideoFrame (converted to yuv444p when its format is not planar Y'CbCr)."""
    name = frame.format.name
    if name not in PLANAR:
        frame = frame.reformat(format="yuv444p")
        name = "yuv444p"
    sx, sy, full = PLANAR[name]
    full = full or getattr(frame, "color_range", 0) == 2  # AVCOL_RANGE_JPEG
    matrix = "bt709" if getattr(frame, "colorspace", 2) in BT709_SPACES else "bt601"
    h, w = frame.height, frame.width
    ch, cw = -(-h // sy), -(-w // sx)
    p = frame.planes
    return FramePlanes(
        plane_view(p[0], h, w), plane_view(p[1], ch, cw), plane_view(p[2], ch, cw), sx, sy, full, matrix, frame
    )
