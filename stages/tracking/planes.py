"""Decoded video frames, converted to BGR only where the tracker looks: the face region the landmark model sees and
the face crop, instead of the whole frame.

FFmpeg's conversion of planar 4:2:0 Y'CbCr (limited or full range; what nearly every video decodes to) to BGR is
pixel-local: a pixel's BGR value depends only on its own luma sample and the chroma samples of its block. So
converting a frame that holds only a rectangle of the planes (its origin on the chroma grid and on the 32-pixel
grid of FFmpeg's vector code) gives exactly the pixels the whole-frame conversion gives in that rectangle (tested
bit for bit). The tracker asks for the bounding box of what a warp will sample, plus a margin, converts it into a
frame-sized canvas at its place (one canvas per stream, reused) and warps the canvas with the warp's own map: the
model's input patch and the face crops are the same bytes as when every whole frame was converted, at a fraction
of the conversion and with no whole-frame array allocated per frame.

A region is kept on the frame once converted (grown by ``REGION_MARGIN`` so the crop, which covers about the same
face region as the model's patch, usually reuses it). Frames in other pixel formats, or of odd width or height
(which FFmpeg converts another way), are converted whole, once.
"""

from __future__ import annotations

import numpy as np

#: pixel formats converted region by region (checked bit for bit against whole frames): name -> chroma
#: subsampling (x, y). Others (4:2:2, 4:4:4, packed, ...) are converted whole: FFmpeg's generic path for them
#: does not give a region the bytes it gives the whole frame.
PLANAR = {"yuv420p": (2, 2), "yuvj420p": (2, 2)}
#: a converted region is this much larger than asked for (fraction of its size, on each side)
REGION_MARGIN = 0.15
#: region origins and sizes are multiples of this many pixels (columns line up with the whole frame's vector
#: blocks; scratch frames and converters are reused frame after frame)
REGION_ALIGN = 32
#: pixels a bilinear warp may read beyond the preimage of its output
SAMPLE_MARGIN = 2


def preimage_box(affine: np.ndarray, size: int, width: int, height: int) -> tuple[int, int, int, int]:
    """[x0, x1) x [y0, y1): the frame pixels a warp by ``affine`` (frame -> patch) to a ``size`` square reads,
    clipped to the frame."""
    m = np.vstack([np.asarray(affine, dtype=np.float64), [0.0, 0.0, 1.0]])
    inv = np.linalg.inv(m)[:2]
    corners = np.array([[0, 0, 1], [size, 0, 1], [0, size, 1], [size, size, 1]], dtype=np.float64) @ inv.T
    lo = np.floor(corners.min(axis=0)) - SAMPLE_MARGIN
    hi = np.ceil(corners.max(axis=0)) + SAMPLE_MARGIN
    x0, y0 = int(max(lo[0], 0)), int(max(lo[1], 0))
    x1, y1 = int(min(hi[0], width)), int(min(hi[1], height))
    return x0, max(x1, x0 + 1), y0, max(y1, y0 + 1)


class RegionConverter:
    """BGR of rectangles of decoded frames through FFmpeg's converter (module docstring), written into a frame-sized
    canvas at their place, so warps read them with their own maps (bit for bit what they read from a whole
    converted frame). One per stream: the canvas and the scratch frames are reused from frame to frame."""

    def __init__(self):
        from av.video.reformatter import VideoReformatter

        self.reformatter = VideoReformatter()
        self.scratch: dict[tuple, object] = {}
        self.canvas: np.ndarray | None = None
        self.gray_canvas: np.ndarray | None = None

    def canvases(self, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
        if self.canvas is None or self.canvas.shape[:2] != (height, width):
            self.canvas = np.zeros((height, width, 3), np.uint8)
            self.gray_canvas = np.zeros((height, width), np.uint8)
        return self.canvas, self.gray_canvas

    def convert(self, frame, x0: int, x1: int, y0: int, y1: int) -> tuple[int, int, int, int]:
        """Convert a region covering [x0, x1) x [y0, y1) of a planar frame into the canvas; returns the region."""
        import av

        sx, sy = PLANAR[frame.format.name]
        # columns on the same 32-pixel grid as the whole frame's: FFmpeg's vector code converts blocks of pixels
        # from the start of each row, so blocks must line up
        x0, y0 = x0 - x0 % REGION_ALIGN, y0 - y0 % sy
        w = min(frame.width - x0, -(-(x1 - x0) // REGION_ALIGN) * REGION_ALIGN)
        h = min(frame.height - y0, -(-(y1 - y0) // REGION_ALIGN) * REGION_ALIGN)
        key = (frame.format.name, w, h)
        if key not in self.scratch:
            self.scratch[key] = av.VideoFrame(w, h, frame.format.name)
        sub = self.scratch[key]
        sub.colorspace, sub.color_range = frame.colorspace, frame.color_range
        for i, (dx, dy) in enumerate(((1, 1), (sx, sy), (sx, sy))):
            src, dst = frame.planes[i], sub.planes[i]
            rows, cols = -(-h // dy), -(-w // dx)
            view = np.frombuffer(src, np.uint8).reshape(-1, src.line_size)
            out = np.frombuffer(dst, np.uint8).reshape(-1, dst.line_size)
            out[:rows, :cols] = view[y0 // dy : y0 // dy + rows, x0 // dx : x0 // dx + cols]
        canvas, _ = self.canvases(frame.height, frame.width)
        canvas[y0 : y0 + h, x0 : x0 + w] = self.reformatter.reformat(sub, format="bgr24").to_ndarray()
        return x0, x0 + w, y0, y0 + h


class FramePlanes:
    """One decoded frame; BGR made on demand for the regions warps read (exactly FFmpeg's whole-frame BGR there).
    Valid while it is the stream's current frame (the converter's canvas is shared)."""

    def __init__(self, frame, converter: RegionConverter):
        self.frame, self.converter = frame, converter
        # odd frame sizes take another of FFmpeg's code paths, whose output depends on more than a pixel's block
        self.planar = frame.format.name in PLANAR and frame.width % 2 == 0 and frame.height % 2 == 0
        self.region: tuple[int, int, int, int] | None = None  # converted [x0, x1) x [y0, y1) in the canvas
        self.gray_region: tuple[int, int, int, int] | None = None
        if not self.planar:  # other layouts and odd sizes: one whole-frame conversion
            canvas, _ = converter.canvases(frame.height, frame.width)
            canvas[:] = frame.to_ndarray(format="bgr24")
            self.region = (0, frame.width, 0, frame.height)

    @property
    def shape(self) -> tuple[int, int]:
        return self.frame.height, self.frame.width

    def _ensure(self, box: tuple[int, int, int, int]) -> None:
        """Make the canvas hold this frame's BGR over ``box`` = (x0, x1, y0, y1)."""
        if self.region is not None and inside(box, self.region):
            return
        x0, x1, y0, y1 = box
        grow_x, grow_y = int((x1 - x0) * REGION_MARGIN), int((y1 - y0) * REGION_MARGIN)
        h, w = self.shape
        grown = (max(x0 - grow_x, 0), min(x1 + grow_x, w), max(y0 - grow_y, 0), min(y1 + grow_y, h))
        self.region, self.gray_region = self.converter.convert(self.frame, *grown), None

    def _ensure_gray(self, box: tuple[int, int, int, int]) -> np.ndarray:
        import cv2

        self._ensure(box)
        canvas, gray = self.converter.canvases(*self.shape)
        if self.gray_region != self.region:
            x0, x1, y0, y1 = self.region
            gray[y0:y1, x0:x1] = cv2.cvtColor(canvas[y0:y1, x0:x1], cv2.COLOR_BGR2GRAY)
            self.gray_region = self.region
        return gray

    def warp_bgr(self, affine: np.ndarray, size: int) -> np.ndarray:
        """(size, size, 3) uint8 BGR: the frame warped by ``affine`` (frame -> patch pixels), black outside it."""
        import cv2

        h, w = self.shape
        self._ensure(preimage_box(affine, size, w, h))
        canvas, _ = self.converter.canvases(h, w)
        return cv2.warpAffine(canvas, affine, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)

    def warp_gray(self, affine: np.ndarray, size: int) -> np.ndarray:
        """(size, size) uint8 gray (OpenCV's BGR to gray), border pixels repeated outside the frame."""
        import cv2

        h, w = self.shape
        gray = self._ensure_gray(preimage_box(affine, size, w, h))
        return cv2.warpAffine(gray, affine, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def gray_image(self):
        """The whole frame as a gray ``BgrImage`` (a copy: what a frame waiting in a gap keeps for its crop)."""
        h, w = self.shape
        return BgrImage(self._ensure_gray((0, w, 0, h)).copy())

    def gray(self) -> np.ndarray:
        """The whole frame, gray (a copy)."""
        return self.gray_image().bgr


def inside(box: tuple[int, int, int, int], region: tuple[int, int, int, int]) -> bool:
    return region[0] <= box[0] and box[1] <= region[1] and region[2] <= box[2] and box[3] <= region[3]


class BgrImage:
    """A BGR (or gray) uint8 image with the FramePlanes interface."""

    def __init__(self, bgr: np.ndarray):
        self.bgr = bgr

    @property
    def shape(self) -> tuple[int, int]:
        return self.bgr.shape[:2]

    def warp_bgr(self, affine: np.ndarray, size: int) -> np.ndarray:
        import cv2

        return cv2.warpAffine(
            self.bgr, affine, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
        )

    def warp_gray(self, affine: np.ndarray, size: int) -> np.ndarray:
        import cv2

        return cv2.warpAffine(
            self.gray(), affine, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )

    def gray_image(self) -> BgrImage:
        return BgrImage(self.gray())

    def gray(self) -> np.ndarray:
        import cv2

        return cv2.cvtColor(self.bgr, cv2.COLOR_BGR2GRAY) if self.bgr.ndim == 3 else self.bgr


def as_image(frame):
    """Frames given as BGR arrays get the planes' interface (``BgrImage``); anything with ``warp_bgr`` passes
    through."""
    return frame if hasattr(frame, "warp_bgr") else BgrImage(np.asarray(frame))


def frame_planes(frame, converter: RegionConverter | None = None) -> FramePlanes:
    """A decoded PyAV VideoFrame as a ``FramePlanes`` (``converter``: one per stream, reused frame to frame)."""
    return FramePlanes(frame, converter or RegionConverter())
