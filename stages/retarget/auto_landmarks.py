"""A character's 68 landmark vertices found by the tracker itself: its neutral face rendered from the front, tracked
as one video frame, and each landmark given the visible skin vertex under it.

A character from elsewhere (an avatar exported from Blender, a scan) does not say which of its vertices are the iBUG
points the retargeting fits and the evaluation measures; picking 68 vertices by hand is slow and each artist would
pick differently. The tracker that reads the performer has its own idea of where each point lies (the inner lip
line, the lid margin, the brow's upper edge), so the character's points are taken from the same tracker on the
character's own face: both faces' points then mean the same thing (docs/retarget.md, "Landmarks of a new
character").

Steps (``place_landmarks``):
1. the neutral mesh rendered from the front (glTF: the face looks along +z), orthographic, lit from above the
   camera, framed on the mesh, then again framed on the face found (as large as in a close-up);
2. FaceMesh (the tracking stage's default models) on the render and on its mirror image, averaged: one reading
   leans to one side; the 68 points by the tracking's mapping;
3. each point's vertex: the *visible skin* vertex nearest in 3D to the rendered surface under the point. Skin is
   the material group under the nose tip (landmark 30), so eyeballs, teeth and the mouth's inside are never
   chosen; visible means not behind the rendered surface (the depth buffer);
4. the closed lips' line: the inner upper lip (61-63) and inner lower lip (65-67) meet on a neutral face, so each
   takes, of the skin vertices around it, the nearest on its own lip, told by the jaw-opening morph (it lowers
   the lower lip's vertices at least half as far as the most lowered one, the upper lip's less).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: image side in pixels of the renders the tracker reads
RENDER_SIZE = 768
#: supersampling of those renders (anti-aliased edges read like a camera's)
SUPERSAMPLE = 2
#: the face's share of the second render's height (a close-up)
FACE_SHARE = 0.6
#: iBUG points of the inner upper and lower lip (the corners 60 and 64 are shared)
INNER_UPPER = (61, 62, 63)
INNER_LOWER = (65, 66, 67)
#: the renders' light, from above the camera: light from one side leans the tracker's points towards it
FRONT_LIGHT = (0.0, 0.45, 1.0)
#: the nose tip, always skin
NOSE_TIP = 30
#: search radius for the lip line's vertices, in inter-ocular distances
LIP_RADIUS_IOD = 0.04
#: a vertex counts as visible when it is at most this far (inter-ocular distances) behind the rendered surface
VISIBLE_DEPTH_IOD = 0.02


@dataclass
class Placement:
    """Landmark vertices found on a character, with what they rest on."""

    ids: np.ndarray  #: (68,) vertex ids
    score: float  #: the landmark model's presence score on the render
    pixel_error: np.ndarray  #: (68,) image distance from each tracked point to its vertex, in inter-ocular distances


class NoFaceFound(Exception):
    """The tracker found no face on the character's render."""


def front_view(points: np.ndarray, *, margin: float = 1.1):
    """An orthographic front view framing ``points`` (the camera looks along -z at the face), lit from above it."""
    from stages.geometry.render import View

    return View.fit(points, perspective=None, margin=margin, light=FRONT_LIGHT)


def face_view(view, pixels: np.ndarray, size: int):
    """The view re-centred on tracked image points, zoomed so they fill ``FACE_SHARE`` of the image height."""
    rot = np.asarray(view.rotation, dtype=np.float64)
    lo, hi = pixels.min(axis=0), pixels.max(axis=0)
    centre_px = 0.5 * (lo + hi)
    per_px = view.extent / size
    offset_cam = np.array([(centre_px[0] - 0.5 * size) * per_px, -(centre_px[1] - 0.5 * size) * per_px, 0.0])
    centre = np.asarray(view.center, dtype=np.float64) + offset_cam @ rot  # camera offset back into world axes
    extent = max(hi - lo) * per_px / FACE_SHARE
    return view.with_(center=tuple(float(v) for v in centre), extent=float(extent))


def ibug_mirror() -> np.ndarray:
    """(68,) the iBUG point that each point becomes in the mirror image (left and right swapped)."""
    pairs = [(i, 16 - i) for i in range(8)] + [(17 + i, 26 - i) for i in range(5)] + [(31, 35), (32, 34)]
    pairs += [(36, 45), (37, 44), (38, 43), (39, 42), (40, 47), (41, 46)]
    pairs += [(48, 54), (49, 53), (50, 52), (55, 59), (56, 58), (60, 64), (61, 63), (65, 67)]
    mirror = np.arange(68)
    for a, b in pairs:
        mirror[a], mirror[b] = b, a
    return mirror


def track_once(image: np.ndarray, tracker) -> tuple[np.ndarray, float]:
    """(68, 2) iBUG points and the presence score of the tracker on one RGB render; NoFaceFound when none."""
    from stages.tracking.landmarks68 import mesh_to_ibug68

    tracker.reset()
    points, score = tracker.step(np.ascontiguousarray(image[..., ::-1]))  # the tracker reads BGR, like OpenCV
    if points is None:
        raise NoFaceFound("no face found on the character's front render")
    return mesh_to_ibug68(points[None, :468, :2])[0].astype(np.float64), float(score)


def track_render(image: np.ndarray, tracker) -> tuple[np.ndarray, float]:
    """``track_once`` on the image and on its mirror image, averaged (the mirror's points flipped back and
    renumbered): the landmark model reads a symmetric render 0.015-0.03 eye distances to one side (the ICT head:
    mouth corners, nostrils, brows), a lean the average cancels whatever the character's own asymmetry."""
    width = image.shape[1]
    direct, score = track_once(image, tracker)
    mirrored, mirror_score = track_once(image[:, ::-1], tracker)
    mirrored = mirrored[ibug_mirror()]
    mirrored[:, 0] = width - mirrored[:, 0]  # pixel x measured from the left edge (centres at +0.5)
    return 0.5 * (direct + mirrored), min(score, mirror_score)


@dataclass
class Surface:
    """What the front render shows: each vertex's camera-space depth and image point, and per pixel the nearest
    triangle (-1: background) and the surface's depth."""

    depth: np.ndarray  #: (V,) camera z (grows towards the viewer)
    xy: np.ndarray  #: (V, 2) image points
    triangle: np.ndarray  #: (H, W) triangle ids
    surface_depth: np.ndarray  #: (H, W) depth of the rendered surface (-inf: background)

    def pixel_of(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rows, columns) of the pixels holding image points (clipped to the image)."""
        h, w = self.triangle.shape
        col = np.clip(np.floor(points[:, 0]).astype(int), 0, w - 1)
        row = np.clip(np.floor(points[:, 1]).astype(int), 0, h - 1)
        return row, col

    def visible(self, tolerance: float) -> np.ndarray:
        """(V,) bool: vertices in the image and at most ``tolerance`` behind the rendered surface."""
        h, w = self.triangle.shape
        row, col = self.pixel_of(self.xy)
        inside = (self.xy[:, 0] >= 0) & (self.xy[:, 0] < w) & (self.xy[:, 1] >= 0) & (self.xy[:, 1] < h)
        return inside & (self.depth >= self.surface_depth[row, col] - tolerance)


def rendered_surface(vertices: np.ndarray, triangles: np.ndarray, view, size: int) -> Surface:
    """The depth buffer and triangle map of the front view (the rasteriser's, without shading)."""
    from stages.geometry.render import project, rasterize_fragments

    cam, xy = project(vertices, view, size)
    tri_map, bary = rasterize_fragments(xy, cam[:, 2], triangles, size).maps()
    surface_depth = np.full(tri_map.shape, -np.inf)
    covered = tri_map >= 0
    surface_depth[covered] = (cam[triangles[tri_map[covered]], 2] * bary[covered]).sum(axis=1)
    return Surface(cam[:, 2].astype(np.float64), xy.astype(np.float64), tri_map, surface_depth)


def skin_vertices(triangles: np.ndarray, triangle_groups: np.ndarray | None, surface: Surface, nose: np.ndarray):
    """(V,) bool: vertices of the material group under the nose tip (all of them when the mesh has no groups)."""
    n_vertices = len(surface.depth)
    if triangle_groups is None or len(np.unique(triangle_groups)) < 2:
        return np.ones(n_vertices, dtype=bool)
    row, col = surface.pixel_of(nose[None])
    under = surface.triangle[row[0], col[0]]
    if under < 0:
        return np.ones(n_vertices, dtype=bool)
    skin = np.zeros(n_vertices, dtype=bool)
    skin[triangles[np.asarray(triangle_groups) == triangle_groups[under]].ravel()] = True
    return skin


def vertex_under(points: np.ndarray, surface: Surface, allowed: np.ndarray, pixels_per_unit: float) -> np.ndarray:
    """For each image point, the allowed vertex nearest in 3D to the rendered surface there (the point's pixel and
    the depth buffer); off the surface (the jaw line's points just beyond the silhouette), the nearest in the
    image. Nearest in the image alone would take, at a lid's corner or a nostril, a vertex deeper in the fold."""
    ids = np.flatnonzero(allowed)
    row, col = surface.pixel_of(points)
    depth = surface.surface_depth[row, col]
    out = np.empty(len(points), dtype=np.int64)
    for k, (p, z) in enumerate(zip(points, depth)):
        d2 = ((surface.xy[ids] - p) ** 2).sum(axis=1)
        if np.isfinite(z):
            d2 = d2 + ((surface.depth[ids] - z) * pixels_per_unit) ** 2
        out[k] = ids[np.argmin(d2)]
    return out


def vertices_around(points: np.ndarray, xy: np.ndarray, allowed: np.ndarray, radius: float) -> list[np.ndarray]:
    """For each image point, the allowed vertices within ``radius`` pixels (the nearest one if none is)."""
    ids = np.flatnonzero(allowed)
    out = []
    for p in points:
        d = np.linalg.norm(xy[ids] - p, axis=1)
        out.append(ids[d <= radius] if (d <= radius).any() else ids[[np.argmin(d)]])
    return out


def lip_line_vertex(candidates: np.ndarray, point: np.ndarray, xy: np.ndarray, drop: np.ndarray, upper: bool) -> int:
    """Of the vertices around a point of the closed lips' line, the nearest one on the upper lip (``upper``: the
    jaw-opening morph lowers it less than half as far as the most lowered candidate) or on the lower lip."""
    lowered = drop[candidates] > 0.5 * drop[candidates].max()
    side = candidates[~lowered] if upper else candidates[lowered]
    if len(side) == 0:
        side = candidates
    return int(side[np.argmin(np.linalg.norm(xy[side] - point, axis=1))])


def place_landmarks(
    vertices: np.ndarray,
    triangles: np.ndarray,
    tracker,
    *,
    triangle_groups: np.ndarray | None = None,
    colors: np.ndarray | None = None,
    jaw_open: np.ndarray | None = None,
    size: int = RENDER_SIZE,
) -> Placement:
    """The 68 landmark vertices of a neutral mesh (module docstring). ``jaw_open``: (V, 3) offsets of the morph
    that opens the jaw (y up), to tell the closed lips apart; None: the nearest vertex there too."""
    from stages.geometry.render import render_frame

    v = np.asarray(vertices, dtype=np.float32)
    t = np.asarray(triangles, dtype=np.int64)
    view = front_view(v)
    first, _ = track_render(render_frame(v, t, size, view, colors=colors, supersample=SUPERSAMPLE), tracker)
    view = face_view(view, first, size)
    image = render_frame(v, t, size, view, colors=colors, supersample=SUPERSAMPLE)
    pixels, score = track_render(image, tracker)
    iod_px = float(np.linalg.norm(pixels[36:42].mean(axis=0) - pixels[42:48].mean(axis=0)))
    surface = rendered_surface(v, t, view, size)
    world_per_px = view.extent / size
    allowed = surface.visible(VISIBLE_DEPTH_IOD * iod_px * world_per_px)
    allowed &= skin_vertices(t, triangle_groups, surface, pixels[NOSE_TIP])
    if not allowed.any():
        raise NoFaceFound("no visible vertex of the face's skin on the character's front render")
    ids = vertex_under(pixels, surface, allowed, 1.0 / world_per_px)
    if jaw_open is not None:
        drop = -np.asarray(jaw_open, dtype=np.float64)[:, 1]  # how far the jaw-opening morph lowers each vertex
        lips = (*INNER_UPPER, *INNER_LOWER)
        around = vertices_around(pixels[list(lips)], surface.xy, allowed, radius=LIP_RADIUS_IOD * iod_px)
        for k, candidates in zip(lips, around):
            ids[k] = lip_line_vertex(candidates, pixels[k], surface.xy, drop, upper=k in INNER_UPPER)
    error = np.linalg.norm(surface.xy[ids] - pixels, axis=1) / iod_px
    return Placement(ids, score, error)


#: the morph that opens the jaw, by its usual names in order of preference (compared by ``regions.morph_key``)
JAW_OPEN_NAMES = ("jawOpen", "jawDrop", "mouthOpen")


def jaw_open_target(names: list[str]) -> int | None:
    """Index of the jaw-opening morph among ``names`` (ARKit ``jawOpen``, ``Jaw_Drop``, ``mouthOpen``), or None."""
    from stages.retarget.regions import find_morph

    found = (find_morph(names, wanted) for wanted in JAW_OPEN_NAMES)
    return next((index for index in found if index is not None), None)


def track_character_landmarks(mesh) -> tuple[np.ndarray, dict, list[str]]:
    """(ids, meta, warnings) of a ``stages.formats.gltf.MorphMesh``'s landmarks placed by ``place_landmarks``
    with the tracking stage's default FaceMesh models; NoFaceFound when the tracker sees no face."""
    from stages.geometry.render import triangle_colors
    from stages.tracking.stages import FaceMeshParams, new_tracker

    groups = [{"name": g.name, "color": list(g.color)} for g in mesh.groups]
    colors = triangle_colors(mesh.triangle_groups, groups)
    jaw = jaw_open_target(list(mesh.target_names))
    warnings = []
    if jaw is None:
        warnings.append(
            "no jaw-opening morph (jawOpen, jawDrop or mouthOpen) to tell the closed lips apart: the inner lip "
            "points are the vertices nearest the lip line, upper or lower"
        )
    tracker = new_tracker(FaceMeshParams(eyes=False), None)
    placement = place_landmarks(
        mesh.positions,
        mesh.triangles,
        tracker,
        triangle_groups=mesh.triangle_groups,
        colors=colors,
        jaw_open=None if jaw is None else mesh.deltas[jaw],
    )
    meta = {
        "from": "tracked",
        "presence": round(placement.score, 4),
        "largest_offset_iod": round(float(placement.pixel_error.max()), 4),
        "jaw_open_target": None if jaw is None else mesh.target_names[jaw],
    }
    return placement.ids, meta, warnings
