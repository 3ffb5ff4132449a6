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


def _next_pow2(n: np.ndarray) -> np.ndarray:
    return (1 << np.ceil(np.log2(np.maximum(n, 1))).astype(np.int64)).astype(np.int64)


def rasterize(xy: np.ndarray, depth: np.ndarray, triangles: np.ndarray, size, *, cull: bool = True):
    """Visible triangle per pixel: (H, W) int32 triangle ids (-1: background) and (H, W, 3) barycentrics.

    ``depth`` grows towards the viewer. With ``cull``, triangles whose screen winding is clockwise (back faces of
    a counter-clockwise mesh) are skipped.
    """
    width, height = _size(size)
    tri = np.asarray(triangles)
    p = np.asarray(xy, dtype=np.float32)
    z = np.asarray(depth, dtype=np.float32)
    x0, y0 = p[tri[:, 0], 0], p[tri[:, 0], 1]
    x1, y1 = p[tri[:, 1], 0], p[tri[:, 1], 1]
    x2, y2 = p[tri[:, 2], 0], p[tri[:, 2], 1]
    area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)  # image y points down: front faces are negative
    keep = area < 0 if cull else area != 0
    # pixel (i, j) has its centre at (i + 0.5, j + 0.5)
    xmin = np.maximum(np.ceil(np.minimum(np.minimum(x0, x1), x2) - 0.5), 0).astype(np.int64)
    xmax = np.minimum(np.floor(np.maximum(np.maximum(x0, x1), x2) - 0.5), width - 1).astype(np.int64)
    ymin = np.maximum(np.ceil(np.minimum(np.minimum(y0, y1), y2) - 0.5), 0).astype(np.int64)
    ymax = np.minimum(np.floor(np.maximum(np.maximum(y0, y1), y2) - 0.5), height - 1).astype(np.int64)
    keep &= (xmax >= xmin) & (ymax >= ymin)
    ids = np.flatnonzero(keep)
    bw, bh = xmax[ids] - xmin[ids] + 1, ymax[ids] - ymin[ids] + 1
    cw, ch = _next_pow2(bw), _next_pow2(bh)
    bucket = cw * 65536 + ch
    order = np.argsort(bucket, kind="stable")
    ids, bucket = ids[order], bucket[order]
    starts = np.flatnonzero(np.r_[True, bucket[1:] != bucket[:-1]]) if len(ids) else np.zeros(0, np.int64)
    ends = np.r_[starts[1:], len(ids)]
    frag_pix, frag_z, frag_tri, frag_b0, frag_b1 = [], [], [], [], []
    # barycentrics are affine in the pixel position: b = b(corner) + A * dx + B * dy, evaluated by broadcasting
    # each triangle's coefficients over its bucket's offsets (no per-fragment gathers)
    inv = np.zeros_like(area)
    inv[ids] = 1.0 / area[ids]
    a0, c0 = (y1 - y2) * inv, (x2 - x1) * inv
    a1, c1 = (y2 - y0) * inv, (x0 - x2) * inv
    zd0 = z[tri[:, 0]] - z[tri[:, 2]]
    zd1 = z[tri[:, 1]] - z[tri[:, 2]]
    z2 = z[tri[:, 2]]
    cx, cy = xmin.astype(np.float32) + 0.5, ymin.astype(np.float32) + 0.5
    base0 = ((x1 - cx) * (y2 - cy) - (x2 - cx) * (y1 - cy)) * inv
    base1 = ((x2 - cx) * (y0 - cy) - (x0 - cx) * (y2 - cy)) * inv
    for s, e in zip(starts, ends):
        t = ids[s:e]
        gw, gh = int(bucket[s] // 65536), int(bucket[s] % 65536)
        oy, ox = np.divmod(np.arange(gw * gh, dtype=np.int64), gw)
        oxf, oyf = ox.astype(np.float32)[None, :], oy.astype(np.float32)[None, :]
        b0 = base0[t][:, None] + a0[t][:, None] * oxf + c0[t][:, None] * oyf
        b1 = base1[t][:, None] + a1[t][:, None] * oxf + c1[t][:, None] * oyf
        inside = (b0 >= -1e-5) & (b1 >= -1e-5) & (b0 + b1 <= 1 + 1e-5)
        inside &= (xmin[t][:, None] + ox[None, :] < width) & (ymin[t][:, None] + oy[None, :] < height)
        row, col = np.nonzero(inside)
        if not len(row):
            continue
        tt = t[row]
        b0, b1 = b0[row, col], b1[row, col]
        frag_pix.append((ymin[tt] + oy[col]) * width + xmin[tt] + ox[col])
        frag_tri.append(tt)
        frag_b0.append(b0)
        frag_b1.append(b1)
        frag_z.append(z2[tt] + b0 * zd0[tt] + b1 * zd1[tt])
    tri_map = np.full(width * height, -1, dtype=np.int32)
    bary = np.zeros((width * height, 3), dtype=np.float32)
    if frag_pix:
        pix = np.concatenate(frag_pix)
        fz = np.concatenate(frag_z)
        zbuf = np.full(width * height, -np.inf, dtype=np.float32)
        np.maximum.at(zbuf, pix, fz)
        win = fz >= zbuf[pix]
        pix = pix[win]
        tri_map[pix] = np.concatenate(frag_tri)[win]
        b0, b1 = np.concatenate(frag_b0)[win], np.concatenate(frag_b1)[win]
        bary[pix, 0], bary[pix, 1], bary[pix, 2] = b0, b1, 1.0 - b0 - b1
    return tri_map.reshape(height, width), bary.reshape(height, width, 3)


def vertex_normals_fast(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (float32), no guard for isolated vertices beyond a zero normal."""
    p = np.asarray(points, dtype=np.float32)
    a, b, c = p[triangles[:, 0]], p[triangles[:, 1]], p[triangles[:, 2]]
    face = np.cross(b - a, c - a)
    n = np.zeros((len(p), 3), dtype=np.float64)
    flat = triangles.reshape(-1)
    face3 = np.repeat(face, 3, axis=0)
    for axis in range(3):
        n[:, axis] = np.bincount(flat, weights=face3[:, axis], minlength=len(p))
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    return n.astype(np.float32)


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
    width, height = _size(size)
    k = max(1, int(supersample))
    big = (width * k, height * k)
    cam, xy = project(vertices, view, big)
    tri_map, bary = rasterize(xy, cam[:, 2], triangles, big, cull=cull)
    normals = vertex_normals_fast(cam, triangles)
    diffuse, spec = shade_vertices(normals, view)
    image = np.empty((big[1], big[0], 3), dtype=np.float32)
    image[:] = np.asarray(view.background, dtype=np.float32)
    hit = tri_map >= 0
    t = tri_map[hit]
    b = bary[hit]
    corners = triangles[t]
    d = (b * diffuse[corners]).sum(axis=1)
    s = (b * spec[corners]).sum(axis=1)
    if colors is None:
        albedo = np.full((len(t), 3), 0.8, dtype=np.float32)
    else:
        colors = np.asarray(colors, dtype=np.float32)
        albedo = np.broadcast_to(colors, (len(t), 3)) if colors.ndim == 1 else colors[t]
    image[hit] = albedo * d[:, None] + s[:, None]
    if k > 1:
        image = image.reshape(height, k, width, k, 3).mean(axis=(1, 3))
    return (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def triangle_colors(triangle_groups: np.ndarray, groups: list[dict], *, srgb: bool = True) -> np.ndarray:
    """(T, 3) albedo from a character's material groups (meta['groups'] colours are linear, as in glTF)."""
    table = np.array([g.get("color", [0.8, 0.8, 0.8, 1.0])[:3] for g in groups] or [[0.8, 0.8, 0.8]], dtype=np.float32)
    if srgb:  # the rasteriser works in display space
        table = np.where(table <= 0.0031308, 12.92 * table, 1.055 * np.power(table, 1 / 2.4) - 0.055)
    return table[np.clip(np.asarray(triangle_groups), 0, len(table) - 1)]


class CharacterRenderer:
    """Renders a morph-target character posed by weights (and optionally a head rotation) with a fixed framing.

    ``framing``: "face" frames the 68 landmark vertices with room around them, "head" the whole mesh.
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
        if view is None:
            if framing == "face" and landmark_ids is not None:
                pts = self.neutral[np.asarray(landmark_ids)]
                lo, hi = pts.min(axis=0), pts.max(axis=0)
                span = hi - lo  # landmarks run from the jaw line to the brows: add the forehead, a little chin
                box = np.array([lo - span * np.array([0.15, 0.2, 0]), hi + span * np.array([0.15, 0.45, 0])])
                view = View.fit(box, yaw=yaw, pitch=pitch, margin=1.0)
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
        return render(
            self.vertices(weights, rotation, translation, eye_rotations),
            self.triangles,
            self.size,
            self.view,
            colors=self.colors,
            supersample=self.supersample,
        )
