"""A small software rasteriser for previews: shaded triangle meshes to uint8 RGB images, numpy only.

Method (measured in bench/bench_render.py against OpenCV ``fillConvexPoly`` per triangle in depth order): a
vectorised z-buffer. Triangles are culled (back faces, off-screen, no pixel centre covered), bucketed by the
power-of-two size of their pixel bounding box, and every bucket is rasterised in one batch: each triangle's
candidate pixels are generated at once, barycentric coordinates from the edge functions decide coverage and
depth, and ``np.maximum.at`` keeps the nearest fragment per pixel. Shading is Gouraud (per-vertex Lambert plus a
Blinn-Phong highlight, interpolated with the barycentrics) times a per-triangle albedo.

Camera convention (glTF): the view looks along -z at ``View.center``; image x is camera +x, image y is camera -y.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class View:
    """Where the camera looks from and how the scene is lit.

    ``rotation`` (3x3) turns world coordinates into camera coordinates about ``center``; ``extent`` is the world
    size shown by the image height; ``perspective`` is the camera distance in units of ``extent`` (None:
    orthographic); ``light`` points towards the light, in camera coordinates.
    """

    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    extent: float = 1.0
    rotation: tuple[tuple[float, ...], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    perspective: float | None = 4.0
    light: tuple[float, float, float] = (0.35, 0.45, 1.0)
    ambient: float = 0.28
    diffuse: float = 0.72
    specular: float = 0.12
    shininess: float = 24.0
    background: tuple[float, float, float] = (0.12, 0.13, 0.15)

    @classmethod
    def fit(cls, points: np.ndarray, *, yaw: float = 0.0, pitch: float = 0.0, margin: float = 1.1, **kwargs) -> View:
        """Frame ``points`` (e.g. the neutral mesh, or its face landmarks) seen from ``yaw``/``pitch`` radians
        (stages.geometry.rotations convention: yaw about +y, pitch about +x)."""
        from stages.geometry.rotations import euler_to_quat, quat_to_matrix

        rot = quat_to_matrix(euler_to_quat(-yaw, -pitch, 0.0))  # turn the world the other way to move the eye
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        lo, hi = p.min(axis=0), p.max(axis=0)
        center = 0.5 * (lo + hi)
        q = (p - center) @ rot.T
        extent = float(max(2 * np.abs(q[:, :2]).max(), 1e-9))
        perspective = kwargs.get("perspective", cls.perspective)
        for _ in range(3 if perspective is not None else 0):  # nearer points project larger: grow to fit them
            distance = perspective * extent
            factor = distance / np.maximum(distance - q[:, 2], 1e-9 * distance)
            extent = float(max(2 * np.abs(q[:, :2] * factor[:, None]).max(), 1e-9))
        return cls(
            center=tuple(float(v) for v in center),
            extent=extent * margin,
            rotation=tuple(tuple(float(v) for v in row) for row in rot),
            **kwargs,
        )

    def with_(self, **changes) -> View:
        from dataclasses import replace

        return replace(self, **changes)


#: named camera positions for ``render(..., view="front")``: yaw of the eye about +y, radians
NAMED_VIEWS = {"front": 0.0, "three-quarter": 0.6, "left": np.pi / 2, "right": -np.pi / 2}


def resolve_view(view, vertices: np.ndarray) -> View:
    """A View, a name from NAMED_VIEWS (framing ``vertices``), or None (front)."""
    if view is None:
        return View.fit(vertices)
    if isinstance(view, str):
        key = view.lower().replace("_", "-")
        if key not in NAMED_VIEWS:
            raise ValueError(f"unknown view {view!r}; named views: {sorted(NAMED_VIEWS)}")
        return View.fit(vertices, yaw=NAMED_VIEWS[key])
    return view


def _size(size) -> tuple[int, int]:
    if np.isscalar(size):
        return int(size), int(size)
    w, h = size
    return int(w), int(h)


def project(vertices: np.ndarray, view: View, size) -> tuple[np.ndarray, np.ndarray]:
    """Camera-space (V, 3) points and their pixel coordinates (V, 2) (x right, y down, pixel centres at +0.5)."""
    width, height = _size(size)
    rot = np.asarray(view.rotation, dtype=np.float32)
    cam = (np.asarray(vertices, dtype=np.float32) - np.asarray(view.center, dtype=np.float32)) @ rot.T
    scale = height / view.extent
    if view.perspective is not None:
        distance = view.perspective * view.extent
        factor = distance / np.maximum(distance - cam[:, 2], 1e-6 * view.extent)
    else:
        factor = np.ones(len(cam), dtype=np.float32)
    xy = np.empty((len(cam), 2), dtype=np.float32)
    xy[:, 0] = 0.5 * width + cam[:, 0] * factor * scale
    xy[:, 1] = 0.5 * height - cam[:, 1] * factor * scale
    return cam, xy


#: candidate grid sides: a triangle's pixel bounding box side is padded to the next of these, or beyond the
#: last to the next power of two, and triangles with the same padded box are tested together (few batches,
#: little padding where most triangles are)
GRID_SIDES = np.array([1, 2, 3, 4, 6, 8])
#: side in pixels of the depth tiles of the occlusion test
TILE = 8


def grid_side(n: np.ndarray) -> np.ndarray:
    """Candidate grid side for bounding-box sides ``n``: the next of GRID_SIDES, else the next power of two."""
    pow2 = (1 << np.ceil(np.log2(np.maximum(n, 1))).astype(np.int64)).astype(np.int64)
    small = GRID_SIDES[np.minimum(np.searchsorted(GRID_SIDES, n), len(GRID_SIDES) - 1)]
    return np.where(n <= GRID_SIDES[-1], small, pow2)


@dataclass
class TriangleSetup:
    """Per-triangle constants of the rasteriser for the triangles that can cover a pixel centre.

    Barycentrics are affine in the pixel position: at pixel (xmin + ox, ymin + oy) the weight of corner 0 is
    ``b0 = base0 + a0 * ox + c0 * oy``, of corner 1 ``b1 = base1 + a1 * ox + c1 * oy``, of corner 2 1 - b0 - b1,
    and the depth is ``z2 + b0 * zd0 + b1 * zd1``. ``coef`` rows hold base0, a0, c0, base1, a1, c1, z2, zd0, zd1.
    """

    ids: np.ndarray  # (n,) triangle indices
    box: np.ndarray  # (4, n) int64 xmin, ymin, xmax, ymax: the pixels whose centres the box holds
    coef: np.ndarray  # (9, n)

    def take(self, rows) -> TriangleSetup:
        return TriangleSetup(self.ids[rows], self.box[:, rows], self.coef[:, rows])

    @property
    def nearest(self) -> np.ndarray:
        """Largest depth of each triangle (its corner nearest the viewer)."""
        return self.coef[6] + np.maximum(np.maximum(self.coef[7], self.coef[8]), 0)


def triangle_setup(xy, depth, triangles, size, *, cull: bool, centre: float, dtype) -> TriangleSetup:
    """Edge-function coefficients of the front-facing (``cull``) triangles whose box holds a pixel centre.

    Pixel (i, j) has its centre at (i + centre, j + centre). Screen y points down, so a counter-clockwise mesh's
    front faces have negative signed area.
    """
    width, height = _size(size)
    p = np.asarray(xy, dtype=dtype)
    px, py = np.ascontiguousarray(p[:, 0]), np.ascontiguousarray(p[:, 1])
    tri = np.asarray(triangles)
    corner = [np.ascontiguousarray(tri[:, k]) for k in range(3)]
    x0, x1, x2 = (px[k] for k in corner)
    y0, y1, y2 = (py[k] for k in corner)
    area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
    keep = area < 0 if cull else area != 0
    xmin = np.maximum(np.ceil(np.minimum(np.minimum(x0, x1), x2) - centre), 0).astype(np.int64)
    xmax = np.minimum(np.floor(np.maximum(np.maximum(x0, x1), x2) - centre), width - 1).astype(np.int64)
    ymin = np.maximum(np.ceil(np.minimum(np.minimum(y0, y1), y2) - centre), 0).astype(np.int64)
    ymax = np.minimum(np.floor(np.maximum(np.maximum(y0, y1), y2) - centre), height - 1).astype(np.int64)
    keep &= (xmax >= xmin) & (ymax >= ymin)
    ids = np.flatnonzero(keep)
    x0, x1, x2, y0, y1, y2 = (v[ids] for v in (x0, x1, x2, y0, y1, y2))
    inv = (1.0 / area[ids]).astype(dtype)
    cx, cy = xmin[ids].astype(dtype) + centre, ymin[ids].astype(dtype) + centre
    z = np.asarray(depth, dtype=dtype)
    z0, z1, z2 = (z[k[ids]] for k in corner)
    coef = np.stack(
        [
            ((x1 - cx) * (y2 - cy) - (x2 - cx) * (y1 - cy)) * inv,
            (y1 - y2) * inv,
            (x2 - x1) * inv,
            ((x2 - cx) * (y0 - cy) - (x0 - cx) * (y2 - cy)) * inv,
            (y2 - y0) * inv,
            (x0 - x2) * inv,
            z2,
            z0 - z2,
            z1 - z2,
        ]
    )
    return TriangleSetup(ids, np.stack([xmin[ids], ymin[ids], xmax[ids], ymax[ids]]), coef)


def batch_fragments(
    setup: TriangleSetup, grid_w: int, grid_h: int, eps: float, width: int, height: int, overflow: bool = True
):
    """Fragments of triangles sharing a candidate grid: (flat pixel, depth, row of ``setup``, b0, b1) where
    the pixel centre is inside (barycentrics >= -eps) and on the image (``overflow``: the grid of some triangle
    reaches past the image, so the fragments are checked)."""
    cells = grid_w * grid_h
    oy, ox = np.divmod(np.arange(cells, dtype=np.int64), grid_w)
    c = setup.coef
    oxf, oyf = ox.astype(c.dtype), oy.astype(c.dtype)
    b0 = c[0][:, None] + c[1][:, None] * oxf + c[2][:, None] * oyf
    b1 = c[3][:, None] + c[4][:, None] * oxf + c[5][:, None] * oyf
    hit = np.flatnonzero((b0 >= -eps) & (b1 >= -eps) & (b0 + b1 <= 1 + eps))
    row, cell = np.divmod(hit, cells)
    b0, b1 = b0.reshape(-1)[hit], b1.reshape(-1)[hit]
    depth = c[6][row] + b0 * c[7][row] + b1 * c[8][row]
    px, py = setup.box[0][row] + ox[cell], setup.box[1][row] + oy[cell]
    if overflow:
        on = (px < width) & (py < height)
        px, py, depth, row, b0, b1 = px[on], py[on], depth[on], row[on], b0[on], b1[on]
    return py * width + px, depth, row, b0, b1


def setup_fragments(setup: TriangleSetup, eps: float, width: int, height: int) -> list[tuple]:
    """Fragments of every triangle of ``setup`` (rows numbered as in ``setup``), batched by padded box size."""
    grid_w = grid_side(setup.box[2] - setup.box[0] + 1)
    grid_h = grid_side(setup.box[3] - setup.box[1] + 1)
    batch = grid_w * 65536 + grid_h
    order = np.argsort(batch, kind="stable")
    batch = batch[order]
    starts = np.flatnonzero(np.r_[True, batch[1:] != batch[:-1]]) if len(batch) else np.zeros(0, np.int64)
    ends = np.r_[starts[1:], len(batch)].astype(np.int64)
    ordered = setup.take(order)  # batches are then contiguous slices (views)
    # padded grids may reach past the image: only batches holding such a triangle check their fragments
    overflow = ((setup.box[0] + grid_w > width) | (setup.box[1] + grid_h > height))[order]
    out = []
    for s, e in zip(starts, ends):
        pix, depth, row, b0, b1 = batch_fragments(
            ordered.take(slice(s, e)),
            int(batch[s] // 65536),
            int(batch[s] % 65536),
            eps,
            width,
            height,
            bool(overflow[s:e].any()),
        )
        out.append((pix, depth, order[s + row], b0, b1))
    return out


@dataclass
class Fragments:
    """The rasterised image, compactly: the covered pixels (flat indices), the triangle seen at each and its
    barycentric weights of corners 0 and 1 (corner 2 has 1 - b0 - b1)."""

    size: tuple[int, int]
    pixels: np.ndarray
    triangle: np.ndarray
    b0: np.ndarray
    b1: np.ndarray

    def maps(self) -> tuple[np.ndarray, np.ndarray]:
        """(H, W) triangle ids (-1: background) and (H, W, 3) barycentrics."""
        width, height = self.size
        tri_map = np.full(width * height, -1, dtype=np.int32)
        bary = np.zeros((width * height, 3), dtype=np.float32)
        tri_map[self.pixels] = self.triangle
        bary[self.pixels, 0], bary[self.pixels, 1] = self.b0, self.b1
        bary[self.pixels, 2] = 1.0 - self.b0 - self.b1
        return tri_map.reshape(height, width), bary.reshape(height, width, 3)


def rasterize_fragments(
    xy: np.ndarray,
    depth: np.ndarray,
    triangles: np.ndarray,
    size,
    *,
    cull: bool = True,
    eps: float = 1e-5,
    centre: float = 0.5,
    dtype=np.float32,
) -> Fragments:
    """The visible triangle and barycentrics at every covered pixel, compactly (see ``rasterize``)."""
    width, height = _size(size)
    setup = triangle_setup(xy, depth, triangles, size, cull=cull, centre=centre, dtype=dtype)
    frags = setup_fragments(setup, eps, width, height)
    if not frags:
        empty = np.zeros(0, np.int64)
        return Fragments((width, height), empty, empty.astype(np.int32), empty.astype(dtype), empty.astype(dtype))
    pix, z, rows, b0, b1 = (np.concatenate(parts) for parts in zip(*frags))
    zbuf = np.full(width * height, -np.inf, dtype=z.dtype)
    np.maximum.at(zbuf, pix, z)
    win = np.flatnonzero(z >= zbuf[pix])
    # of fragments tied at a pixel's depth keep the last one
    owner = np.full(width * height, -1, dtype=np.int64)
    owner[pix[win]] = win
    win = owner[owner >= 0]
    return Fragments((width, height), pix[win], setup.ids[rows[win]].astype(np.int32), b0[win], b1[win])


def rasterize(
    xy: np.ndarray,
    depth: np.ndarray,
    triangles: np.ndarray,
    size,
    *,
    cull: bool = True,
    eps: float = 1e-5,
    centre: float = 0.5,
    dtype=np.float32,
):
    """Visible triangle per pixel: (H, W) int32 triangle ids (-1: background) and (H, W, 3) barycentrics.

    ``depth`` grows towards the viewer; the nearest fragment wins a pixel (of equal depths, one of them). With
    ``cull``, triangles whose screen winding is clockwise (back faces of a counter-clockwise mesh) are skipped.
    A pixel centre (i + centre, j + centre) belongs to a triangle when its barycentrics are all >= -eps.
    ``dtype`` is the precision of the edge functions (float64 for exact coverage tests).

    Method: triangles are batched by the padded size of their pixel bounding box (``grid_side``); each batch's
    candidate pixels are tested at once by broadcasting the barycentric coefficients over the batch's offsets,
    and ``np.maximum.at`` keeps the nearest fragment per pixel.
    """
    return rasterize_fragments(xy, depth, triangles, size, cull=cull, eps=eps, centre=centre, dtype=dtype).maps()


def vertex_normals(
    points: np.ndarray, triangles: np.ndarray, *, dtype=np.float64, incidence=None, isolated=(0.0, 0.0, 1.0)
) -> np.ndarray:
    """Unit area-weighted vertex normals (float32): the sum of the (unnormalised) normals of the triangles
    around each vertex, normalised. A vertex on no proper triangle gets ``isolated``.

    ``dtype``: precision of the sums. ``incidence``: ``vertex_incidence(triangles, len(points))``, reused across
    calls with the same triangles (one sparse product instead of three weighted counts).
    """
    p = np.asarray(points, dtype=dtype)
    t = np.asarray(triangles)
    a = p[t[:, 0]]
    u, w = p[t[:, 1]] - a, p[t[:, 2]] - a
    face = np.empty_like(u)
    face[:, 0] = u[:, 1] * w[:, 2] - u[:, 2] * w[:, 1]
    face[:, 1] = u[:, 2] * w[:, 0] - u[:, 0] * w[:, 2]
    face[:, 2] = u[:, 0] * w[:, 1] - u[:, 1] * w[:, 0]
    if incidence is None:
        incidence = vertex_incidence(t, len(p))
    n = np.asarray(incidence @ face, dtype=dtype)
    length = np.sqrt(np.einsum("ij,ij->i", n, n))
    lone = np.flatnonzero(length <= 1e-20)
    n /= np.maximum(length, 1e-30)[:, None]
    n[lone] = isolated
    n = n.astype(np.float32, copy=False)
    if n.dtype != np.dtype(dtype):  # float32 rounding can leave |n| - 1 above a glTF validator's tolerance
        n /= np.sqrt(np.einsum("ij,ij->i", n, n))[:, None]
    return n


def vertex_incidence(triangles: np.ndarray, n_vertices: int):
    """Sparse (vertices, triangles) matrix with a 1 where a vertex is a corner of a triangle."""
    from scipy.sparse import csr_matrix

    t = np.asarray(triangles)
    cols = np.repeat(np.arange(len(t)), 3)
    return csr_matrix((np.ones(t.size, np.float32), (t.reshape(-1), cols)), shape=(n_vertices, len(t)))


def shade_vertices(normals_cam: np.ndarray, view: View) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex diffuse factor (ambient + Lambert) and specular (Blinn-Phong, viewer along +z)."""
    light = np.asarray(view.light, dtype=np.float32)
    light = light / np.linalg.norm(light)
    half = light + np.array([0.0, 0.0, 1.0], dtype=np.float32)
    half /= np.linalg.norm(half)
    lambert = np.clip(normals_cam @ light, 0.0, None)
    diffuse = view.ambient + view.diffuse * lambert
    spec = view.specular * np.clip(normals_cam @ half, 0.0, None) ** view.shininess * (lambert > 0)
    return diffuse.astype(np.float32), spec.astype(np.float32)


def shade_fragments(frags: Fragments, triangles: np.ndarray, diffuse, spec, colors) -> np.ndarray:
    """(P, 3) colours of the covered pixels: albedo x interpolated diffuse + interpolated specular (Gouraud).

    The per-triangle terms are gathered once per triangle seen, then once per pixel.
    """
    present = np.zeros(len(triangles), dtype=bool)
    present[frags.triangle] = True
    seen = np.flatnonzero(present)
    corners = triangles[seen]
    d, s = diffuse[corners], spec[corners]  # (n, 3 corners)
    if colors is None:
        albedo = np.full((len(seen), 3), 0.8, dtype=np.float32)
    else:
        colors = np.asarray(colors, dtype=np.float32)
        albedo = np.broadcast_to(colors, (len(seen), 3)) if colors.ndim == 1 else colors[seen]
    table = np.concatenate(
        [
            albedo,
            d[:, 2:],
            d[:, :1] - d[:, 2:],
            d[:, 1:2] - d[:, 2:],
            s[:, 2:],
            s[:, :1] - s[:, 2:],
            s[:, 1:2] - s[:, 2:],
        ],
        axis=1,
    )
    local = np.zeros(len(triangles), dtype=np.int32)
    local[seen] = np.arange(len(seen), dtype=np.int32)
    table = table[local[frags.triangle]]  # (P, 9)
    b0, b1 = frags.b0[:, None], frags.b1[:, None]
    shade = table[:, 3:4] + b0 * table[:, 4:5] + b1 * table[:, 5:6]
    gloss = table[:, 6:7] + b0 * table[:, 7:8] + b1 * table[:, 8:9]
    return table[:, :3] * shade + gloss


def to_rgb8(values: np.ndarray) -> np.ndarray:
    return (np.clip(values, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def render_frame(
    vertices: np.ndarray,
    triangles: np.ndarray,
    size,
    view: View,
    *,
    colors: np.ndarray | None = None,
    cull: bool = True,
    supersample: int = 1,
    incidence=None,
) -> np.ndarray:
    """``render`` for a resolved view and int64 triangles; ``incidence`` (``vertex_incidence``) saves its
    construction when many frames share the triangles."""
    width, height = _size(size)
    k = max(1, int(supersample))
    big = (width * k, height * k)
    cam, xy = project(vertices, view, big)
    frags = rasterize_fragments(xy, cam[:, 2], triangles, big, cull=cull)
    normals = vertex_normals(cam, triangles, dtype=np.float32, incidence=incidence)
    diffuse, spec = shade_vertices(normals, view)
    colour = shade_fragments(frags, triangles, diffuse, spec, colors)
    background = np.asarray(view.background, dtype=np.float32)
    if k == 1:
        image = np.empty((height * width, 3), dtype=np.uint8)
        image[:] = to_rgb8(background)
        image[frags.pixels] = to_rgb8(colour)
        return image.reshape(height, width, 3)
    image = np.empty((big[0] * big[1], 3), dtype=np.float32)
    image[:] = background
    image[frags.pixels] = colour
    image = image.reshape(height, k, width, k, 3).mean(axis=(1, 3))
    return to_rgb8(image)


def render(
    vertices: np.ndarray,
    triangles: np.ndarray,
    size=256,
    view: View | str | None = None,
    *,
    colors: np.ndarray | None = None,
    cull: bool = True,
    supersample: int = 1,
) -> np.ndarray:
    """Render a triangle mesh: (H, W, 3) uint8 RGB.

    ``size``: an int (square) or (width, height). ``view``: a View, or a name from NAMED_VIEWS ("front",
    "three-quarter", "left", "right") framing the given vertices; default front.
    ``colors``: albedo in [0, 1], one RGB for all, (T, 3) per triangle, or None for light grey. ``supersample``
    renders k times larger and averages k x k blocks (anti-aliasing at k^2 the cost).
    """
    vertices = np.asarray(vertices, dtype=np.float32)
    triangles = np.asarray(triangles, dtype=np.int64)
    view = resolve_view(view, vertices)
    return render_frame(vertices, triangles, size, view, colors=colors, cull=cull, supersample=supersample)


def triangle_colors(triangle_groups: np.ndarray, groups: list[dict], *, srgb: bool = True) -> np.ndarray:
    """(T, 3) albedo from a character's material groups (meta['groups'] colours are linear, as in glTF)."""
    table = np.array([g.get("color", [0.8, 0.8, 0.8, 1.0])[:3] for g in groups] or [[0.8, 0.8, 0.8]], dtype=np.float32)
    if srgb:  # the rasteriser works in display space
        table = np.where(table <= 0.0031308, 12.92 * table, 1.055 * np.power(table, 1 / 2.4) - 0.055)
    return table[np.clip(np.asarray(triangle_groups), 0, len(table) - 1)]


def face_box(landmarks: np.ndarray) -> np.ndarray:
    """(2, 3) corners of the box the "face" framing shows around landmark vertices (..., 3): the landmarks run
    from the jaw line to the brows, so the forehead and a little chin are added."""
    points = np.asarray(landmarks, dtype=np.float64).reshape(-1, 3)
    lo, hi = points.min(axis=0), points.max(axis=0)
    span = hi - lo
    return np.array([lo - span * np.array([0.15, 0.2, 0]), hi + span * np.array([0.15, 0.45, 0])])


def posed_points(
    neutral: np.ndarray,
    deltas: np.ndarray,
    ids: np.ndarray,
    weights: np.ndarray,
    rotation: np.ndarray | None,
    translation: np.ndarray | None,
    pivot: np.ndarray,
) -> np.ndarray:
    """(frames, len(ids), 3) vertices ``ids`` of every frame as ``CharacterRenderer.vertices`` poses them (eyes
    aside): morph ``weights`` (frames, M), then ``rotation`` (frames, 4) about ``pivot``, then ``translation``."""
    from stages.geometry.rotations import quat_to_matrix

    ids = np.asarray(ids)
    deltas = np.asarray(deltas, np.float64).reshape(len(deltas), -1, 3)[:, ids]
    points = np.asarray(neutral, np.float64)[ids] + np.einsum("fm,mpi->fpi", np.asarray(weights, np.float64), deltas)
    if rotation is not None:
        points = np.einsum("fij,fpj->fpi", quat_to_matrix(rotation), points - pivot) + pivot
    if translation is not None:
        points = points + np.asarray(translation, np.float64)[:, None]
    return points


class CharacterRenderer:
    """Renders a morph-target character posed by weights (and optionally a head rotation) with a fixed framing.

    ``framing``: "face" frames the 68 landmark vertices with room around them (``face_box``; ``face_points``, e.g.
    the landmarks of every posed frame of an animation (``posed_points``), instead of the neutral ones, so a head
    that nods or leans stays in the picture), "head" the whole mesh.
    """

    def __init__(
        self,
        neutral: np.ndarray,
        triangles: np.ndarray,
        deltas: np.ndarray,
        *,
        landmark_ids: np.ndarray | None = None,
        triangle_groups: np.ndarray | None = None,
        groups: list[dict] | None = None,
        size=256,
        framing: str = "face",
        yaw: float = 0.0,
        pitch: float = 0.0,
        pivot: np.ndarray | None = None,
        view: View | None = None,
        supersample: int = 1,
        eyes: list[tuple[np.ndarray, np.ndarray]] | None = None,
        face_points: np.ndarray | None = None,
    ):
        self.neutral = np.asarray(neutral, dtype=np.float32)
        #: (vertex ids, centre) of each eyeball, turned by ``eye_rotations`` about its centre
        self.eyes = [(np.asarray(ids), np.asarray(c, dtype=np.float32)) for ids, c in (eyes or [])]
        self.triangles = np.asarray(triangles, dtype=np.int64)
        self.deltas = np.asarray(deltas, dtype=np.float32).reshape(len(deltas), -1)
        self.size = size
        self.supersample = supersample
        self.pivot = np.zeros(3) if pivot is None else np.asarray(pivot, dtype=np.float64)
        self.colors = triangle_colors(triangle_groups, groups or []) if triangle_groups is not None else None
        self.incidence = vertex_incidence(self.triangles, len(self.neutral))
        if view is None:
            if framing == "face" and landmark_ids is not None:
                framed = self.neutral[np.asarray(landmark_ids)] if face_points is None else face_points
                view = View.fit(face_box(framed), yaw=yaw, pitch=pitch, margin=1.0)
            else:
                view = View.fit(self.neutral, yaw=yaw, pitch=pitch, margin=1.05)
        self.view = view

    @classmethod
    def from_artifact(cls, character, **kwargs) -> CharacterRenderer:
        """From a character artifact (ArtifactView of stages.retarget.character)."""
        meta = character.meta
        groups = character["triangle_groups"] if "triangle_groups" in character else None
        kwargs.setdefault("pivot", meta.get("pivot"))
        return cls(
            character["neutral"],
            character["triangles"],
            character["deltas"],
            landmark_ids=character["landmark_ids"],
            triangle_groups=groups,
            groups=meta.get("groups"),
            **kwargs,
        )

    def vertices(
        self,
        weights: np.ndarray | None = None,
        rotation: np.ndarray | None = None,
        translation: np.ndarray | None = None,
        eye_rotations: np.ndarray | None = None,
    ) -> np.ndarray:
        """Posed vertices: neutral + weights . deltas, each eyeball turned by its ``eye_rotations`` (n_eyes, 4)
        about its centre, then all turned by ``rotation`` (w, x, y, z) about the pivot and moved by
        ``translation``."""
        from stages.geometry.rotations import quat_to_matrix

        v = self.neutral
        if weights is not None:
            w = np.asarray(weights, dtype=np.float32)
            active = np.flatnonzero(np.abs(w) > 1e-6)
            if active.size:
                v = v + (w[active] @ self.deltas[active]).reshape(-1, 3)
        if eye_rotations is not None and self.eyes:
            v = np.array(v, copy=True)
            for (ids, center), q in zip(self.eyes, np.asarray(eye_rotations, dtype=np.float64)):
                r = quat_to_matrix(q).astype(np.float32)
                v[ids] = (v[ids] - center) @ r.T + center
        if rotation is not None:
            r = quat_to_matrix(np.asarray(rotation, dtype=np.float64)).astype(np.float32)
            v = (v - self.pivot.astype(np.float32)) @ r.T + self.pivot.astype(np.float32)
        if translation is not None:
            v = v + np.asarray(translation, dtype=np.float32)
        return v

    def __call__(
        self,
        weights: np.ndarray | None = None,
        rotation: np.ndarray | None = None,
        translation: np.ndarray | None = None,
        eye_rotations: np.ndarray | None = None,
    ) -> np.ndarray:
        """One frame, (H, W, 3) uint8."""
        return render_frame(
            self.vertices(weights, rotation, translation, eye_rotations),
            self.triangles,
            self.size,
            self.view,
            colors=self.colors,
            supersample=self.supersample,
            incidence=self.incidence,
        )
