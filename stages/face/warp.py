"""Piecewise-affine warping between landmark shapes (the shape-free texture of paper Sec 3.1, Eq 2).

Forward: every face image is warped onto one reference shape (the AAM mean shape drawn in a small texture image).
The reference is triangulated once (Delaunay), and for every texture pixel inside the face hull the containing
triangle and its barycentric coordinates are precomputed. The source position of all pixels for many frames is
then each pixel's three barycentric weights applied to its triangle's vertices in the source shape, and each frame
is resampled by one ``cv2.remap``.

Inverse: a texture in the reference frame is drawn back onto an arbitrary (e.g. edited) shape. The target
triangles change every frame, so their pixel coverage is rasterised per frame (``cv2.fillConvexPoly``, cheap)
and each covered pixel is mapped into the texture through its triangle's affine map.

Pixel convention: integer coordinates are pixel centres (OpenCV's ``remap`` convention); x right, y down.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: sub-pixel bits used when rasterising triangles (cv2 ``shift``)
_RASTER_SHIFT = 4


def delaunay_triangles(points: np.ndarray) -> np.ndarray:
    """Delaunay triangulation (T, 3) int32 of 2-D points, triangles oriented consistently (positive area)."""
    from scipy.spatial import Delaunay

    tri = Delaunay(np.asarray(points, dtype=np.float64)).simplices.astype(np.int32)
    return orient_triangles(points, tri)


def orient_triangles(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Reorder vertices so every triangle has positive signed area in ``points`` (x right, y down)."""
    p = np.asarray(points, dtype=np.float64)[np.asarray(triangles)]
    area = triangle_signed_areas(p)
    out = np.array(triangles, dtype=np.int32, copy=True)
    flip = area < 0
    out[flip, 1], out[flip, 2] = triangles[flip, 2], triangles[flip, 1]
    return out


def triangle_signed_areas(corners: np.ndarray) -> np.ndarray:
    """Signed areas of triangles given as corner coordinates (..., 3, 2)."""
    a, b, c = corners[..., 0, :], corners[..., 1, :], corners[..., 2, :]
    return 0.5 * ((b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0]))


def barycentric(points: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (P, 3) of points (P, 2) in their triangles, corners (P, 3, 2)."""
    a = corners[:, 0]
    m = np.stack([corners[:, 1] - a, corners[:, 2] - a], axis=-1)  # (P, 2, 2), columns b-a, c-a
    det = m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] * m[:, 1, 0]
    det = np.where(np.abs(det) < 1e-12, np.inf, det)  # degenerate triangle: weight everything on corner a
    d = points - a
    l1 = (m[:, 1, 1] * d[:, 0] - m[:, 0, 1] * d[:, 1]) / det
    l2 = (-m[:, 1, 0] * d[:, 0] + m[:, 0, 0] * d[:, 1]) / det
    return np.stack([1.0 - l1 - l2, l1, l2], axis=-1)


def rasterise_triangles(
    points: np.ndarray, triangles: np.ndarray, size: tuple[int, int], min_area: float = 1e-3
) -> np.ndarray:
    """Triangle index map (h, w) int32 of a triangulated shape, -1 outside; later triangles win overlaps.

    Triangles of (near) zero area are skipped: they cover no pixels and their affine map is singular.
    """
    w, h = size
    index_map = np.full((h, w), -1, dtype=np.int32)
    corners = np.asarray(points, dtype=np.float64)[triangles]
    areas = np.abs(triangle_signed_areas(corners))
    fixed = np.round(corners * (1 << _RASTER_SHIFT)).astype(np.int32)
    import cv2

    for t in np.flatnonzero(areas >= min_area):
        cv2.fillConvexPoly(index_map, fixed[t], int(t), lineType=cv2.LINE_8, shift=_RASTER_SHIFT)
    return index_map


@dataclass(frozen=True)
class PixelTriangles:
    """Pixels of an image covered by a triangulated shape: where they are and how they weigh the shape's points.

    Each covered pixel has its triangle's three vertex indices and its barycentric coordinates there, so the
    same weights applied to another shape with the same triangulation give the pixel's corresponding position:
    the piecewise-affine correspondence. As a sparse (P, n_points) matrix (``weights``), positions for many shapes
    at once are one matrix product (``PiecewiseAffineWarp.source_positions``).
    """

    size: tuple[int, int]  # (w, h) of the image
    n_points: int
    pixel_index: np.ndarray  # (P,) flat indices (row-major) of covered pixels
    triangle: np.ndarray  # (P,) triangle of each covered pixel
    vertices: np.ndarray  # (P, 3) point indices of that triangle
    bary: np.ndarray  # (P, 3) barycentric coordinates

    @property
    def mask(self) -> np.ndarray:
        w, h = self.size
        m = np.zeros(h * w, dtype=bool)
        m[self.pixel_index] = True
        return m.reshape(h, w)

    def weights(self):
        """(P, n_points) CSR matrix (scipy.sparse), three barycentric weights per row."""
        from scipy.sparse import csr_matrix

        p = len(self.pixel_index)
        return csr_matrix(
            (self.bary.reshape(-1), self.vertices.reshape(-1), np.arange(0, 3 * p + 1, 3)), (p, self.n_points)
        )

    def positions(self, shape: np.ndarray) -> np.ndarray:
        """(P, 2) positions of the covered pixels in another shape (n_points, 2) with the same triangulation."""
        return np.einsum("pk,pkd->pd", self.bary, np.asarray(shape, dtype=np.float64)[self.vertices])

    @classmethod
    def from_index_map(cls, points: np.ndarray, triangles: np.ndarray, index_map: np.ndarray) -> PixelTriangles:
        h, w = index_map.shape
        flat = index_map.reshape(-1)
        pixel_index = np.flatnonzero(flat >= 0)
        tri = flat[pixel_index]
        xy = np.stack([pixel_index % w, pixel_index // w], axis=-1).astype(np.float64)
        vertices = np.asarray(triangles)[tri]
        bary = barycentric(xy, np.asarray(points, dtype=np.float64)[vertices])
        return cls((w, h), len(points), pixel_index, tri.astype(np.int32), vertices, bary)


def pixels_of_reference(points: np.ndarray, triangles: np.ndarray, size: tuple[int, int]) -> PixelTriangles:
    """Exact pixel coverage of a reference shape: a pixel centre belongs to the first triangle containing it
    (barycentric coordinates >= -1e-9; triangles with |2 x area| <= 1e-12 contain nothing).

    Drawn by the project's one rasteriser (stages.geometry.render.rasterize) in float64, pixel centres at
    integer coordinates, each triangle at a constant depth that decreases with its index so the first wins.
    """
    from stages.geometry.render import rasterize

    w, h = size
    pts = np.asarray(points, dtype=np.float64)
    tri = np.asarray(triangles)
    corners = pts[tri]  # (T, 3, 2)
    usable = np.flatnonzero(np.abs(2.0 * triangle_signed_areas(corners)) > 1e-12)
    flat = corners[usable].reshape(-1, 2)  # unshared corners: each triangle gets its own depth
    depth = -np.repeat(usable, 3).astype(np.float64)
    local, _ = rasterize(
        flat, depth, np.arange(len(flat)).reshape(-1, 3), (w, h), cull=False, eps=1e-9, centre=0.0, dtype=np.float64
    )
    index_map = np.where(local >= 0, usable[np.maximum(local, 0)], -1).astype(np.int32)
    return PixelTriangles.from_index_map(pts, triangles, index_map)


class PiecewiseAffineWarp:
    """Warp images from their own landmark shapes onto one fixed reference shape (the AAM texture frame).

    Built once per reference; ``warp(images, shapes)`` returns (frames, P) samples at the reference's covered
    pixels (``pixels.pixel_index``), ``to_image`` scatters such samples back into (h, w) images.
    """

    def __init__(self, reference: np.ndarray, triangles: np.ndarray, size: tuple[int, int]):
        self.reference = np.asarray(reference, dtype=np.float64)
        self.triangles = np.asarray(triangles, dtype=np.int32)
        self.size = (int(size[0]), int(size[1]))
        self.pixels = pixels_of_reference(self.reference, self.triangles, self.size)
        self._weights = self.pixels.weights()
        self._nearest_inside = nearest_inside_index(self.pixels.mask)

    @property
    def n_pixels(self) -> int:
        return len(self.pixels.pixel_index)

    def source_positions(self, shapes: np.ndarray) -> np.ndarray:
        """(frames, P, 2) float32 position in each source image of every covered reference pixel.

        A sparse product (three barycentric weights per pixel) in float64, rounded once to float32: each position is
        its three terms summed in a fixed order, so a frame's positions do not depend on the frames batched with
        it. (A dense float32 matrix product over the batch did: BLAS blocks the sum differently for other batch
        sizes on some CPUs, ``cv2.remap`` quantises positions to 1/32 pixel, so a one-ulp difference could change a
        grey level, and a take's textures depended on the takes processed beside it.)
        """
        shapes = np.asarray(shapes, dtype=np.float64)
        n, k, _ = shapes.shape
        flat = shapes.transpose(1, 0, 2).reshape(k, n * 2)  # (points, frames*2)
        pos = self._weights @ flat  # (P, frames*2)
        return pos.reshape(-1, n, 2).transpose(1, 0, 2).astype(np.float32)

    def warp(self, images: np.ndarray, shapes: np.ndarray, chunk: int = 256) -> np.ndarray:
        """Sample every image (frames, H, W) at its shape's correspondence of the reference pixels.

        Returns (frames, P) float32 grey levels; source positions outside an image replicate its border.
        """
        import cv2

        images = np.asarray(images)
        shapes = np.asarray(shapes)
        n = len(images)
        w, h = self.size
        out = np.empty((n, self.n_pixels), dtype=np.float32)
        map_x = np.full(h * w, -1.0, dtype=np.float32)
        map_y = np.full(h * w, -1.0, dtype=np.float32)
        idx = self.pixels.pixel_index
        for start in range(0, n, chunk):
            pos = self.source_positions(shapes[start : start + chunk])
            for i in range(len(pos)):
                map_x[idx] = pos[i, :, 0]
                map_y[idx] = pos[i, :, 1]
                warped = cv2.remap(
                    images[start + i],
                    map_x.reshape(h, w),
                    map_y.reshape(h, w),
                    interpolation=cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE,
                )
                out[start + i] = warped.reshape(-1)[idx]
        return out

    def to_image(self, samples: np.ndarray, fill: float = 0.0) -> np.ndarray:
        """Scatter (..., P) samples into (..., h, w) images of the reference frame; ``fill`` outside the hull."""
        samples = np.asarray(samples)
        w, h = self.size
        lead = samples.shape[:-1]
        out = np.full(lead + (h * w,), fill, dtype=samples.dtype if samples.dtype.kind == "f" else np.float32)
        out[..., self.pixels.pixel_index] = samples
        return out.reshape(lead + (h, w))

    def draw_on_shape(
        self, texture_image: np.ndarray, shape: np.ndarray, size: tuple[int, int]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Inverse warp: draw a reference-frame texture image onto ``shape`` in an image of ``size`` (w, h).

        Returns (image float32 (h, w), mask bool (h, w) of the pixels drawn). Folded target triangles are
        allowed (the later triangle wins); degenerate ones draw nothing.
        """
        import cv2

        w, h = int(size[0]), int(size[1])
        shape = np.asarray(shape, dtype=np.float64)
        index_map = rasterise_triangles(shape, self.triangles, (w, h))
        target = PixelTriangles.from_index_map(shape, self.triangles, index_map)
        pos = target.positions(self.reference)  # (P, 2) positions in the texture image
        map_x = np.full(h * w, -1.0, dtype=np.float32)
        map_y = np.full(h * w, -1.0, dtype=np.float32)
        map_x[target.pixel_index] = pos[:, 0]
        map_y[target.pixel_index] = pos[:, 1]
        image = cv2.remap(
            np.asarray(texture_image, dtype=np.float32),
            map_x.reshape(h, w),
            map_y.reshape(h, w),
            interpolation=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
        return image, target.mask

    def fill_outside(self, images: np.ndarray) -> np.ndarray:
        """Texture images (..., h, w) with every pixel outside the hull set to its nearest inside pixel, so
        bilinear sampling at the hull edge does not blend in the background."""
        h, w = self.size[1], self.size[0]
        flat = np.asarray(images).reshape(images.shape[:-2] + (h * w,))
        return flat[..., self._nearest_inside].reshape(images.shape)


def nearest_inside_index(mask: np.ndarray) -> np.ndarray:
    """(h*w,) flat index of the nearest pixel inside ``mask`` for every pixel (itself when inside)."""
    from scipy.ndimage import distance_transform_edt

    h, w = mask.shape
    if mask.all() or not mask.any():
        return np.arange(h * w)
    _, (iy, ix) = distance_transform_edt(~mask, return_indices=True)
    return (iy * w + ix).reshape(-1)
