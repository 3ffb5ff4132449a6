"""The software rasteriser: coverage, depth order, culling, shading, projection; against a brute-force reference."""

from pathlib import Path

import numpy as np
import pytest

from stages.geometry.render import CharacterRenderer, View, project, rasterize, render

ROOT = Path(__file__).resolve().parents[1]
ICT_GLB = ROOT / "data" / "characters" / "ict-facekit.glb"


def flat_view(size: int, **kw) -> View:
    """Orthographic view where world (x, y) in [0, size] maps onto pixels (x right, y up -> image y down)."""
    return View(center=(size / 2, size / 2, 0.0), extent=float(size), perspective=None, **kw)


def reference_rasterize(xy, depth, triangles, width, height, cull=True):
    """Per-pixel brute force with the same rules: pixel centres at +0.5, front faces have negative image area."""
    tri_map = np.full((height, width), -1)
    zbuf = np.full((height, width), -np.inf)
    for t, (a, b, c) in enumerate(triangles):
        (x0, y0), (x1, y1), (x2, y2) = xy[a], xy[b], xy[c]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if area == 0 or (cull and area > 0):
            continue
        for j in range(height):
            for i in range(width):
                cx, cy = i + 0.5, j + 0.5
                b0 = ((x1 - cx) * (y2 - cy) - (x2 - cx) * (y1 - cy)) / area
                b1 = ((x2 - cx) * (y0 - cy) - (x0 - cx) * (y2 - cy)) / area
                b2 = 1 - b0 - b1
                if min(b0, b1, b2) < -1e-5:
                    continue
                z = b0 * depth[a] + b1 * depth[b] + b2 * depth[c]
                if z > zbuf[j, i]:
                    zbuf[j, i], tri_map[j, i] = z, t
    return tri_map, zbuf


def test_rasterize_matches_brute_force_reference():
    rng = np.random.default_rng(3)
    size, n = 24, 40
    centres = rng.uniform(0, size, (n, 1, 2))
    xy = (centres + rng.normal(0, 4.0, (n, 3, 2))).reshape(-1, 2).astype(np.float32)
    depth = rng.uniform(-1, 1, len(xy)).astype(np.float32)
    triangles = np.arange(len(xy)).reshape(-1, 3)
    for cull in (True, False):
        got, _ = rasterize(xy, depth, triangles, size, cull=cull)
        want, _ = reference_rasterize(xy, depth, triangles, size, size, cull=cull)
        assert (want >= 0).sum() > 100
        assert np.array_equal(got >= 0, want >= 0)
        assert (got == want).mean() > 0.99  # float32 vs float64 depth may flip near-ties


def test_grid_mesh_covers_every_pixel_once_without_gaps():
    size = 37
    g = np.linspace(-0.3, size + 0.3, 9)
    xs, ys = np.meshgrid(g, g)
    vertices = np.c_[xs.ravel(), ys.ravel(), np.zeros(xs.size)]
    idx = np.arange(81).reshape(9, 9)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    triangles = np.r_[np.c_[a, b, c], np.c_[a, c, d]]  # counter-clockwise seen from +z
    cam, xy = project(vertices, flat_view(size), size)
    tri_map, bary = rasterize(xy, cam[:, 2], triangles, size)
    assert (tri_map >= 0).all()
    assert np.allclose(bary.sum(axis=2), 1.0, atol=1e-5)
    assert (bary >= -1e-5).all()


def test_square_pixel_count_and_position():
    size = 32
    # square from x 8..20, y 4..12 (world, y up): 12 x 8 pixel centres inside
    v = np.array([[8, 4, 0], [20, 4, 0], [20, 12, 0], [8, 12, 0]], float)
    t = np.array([[0, 1, 2], [0, 2, 3]])
    img = render(
        v,
        t,
        size,
        flat_view(size, background=(0, 0, 0), ambient=1.0, diffuse=0.0, specular=0.0),
        colors=np.array([1.0, 1.0, 1.0]),
    )
    lit = img[..., 0] > 0
    assert lit.sum() == 12 * 8
    rows, cols = np.nonzero(lit)
    assert cols.min() == 8 and cols.max() == 19
    assert rows.min() == size - 12 and rows.max() == size - 4 - 1  # image y points down


def test_nearer_surface_wins_whatever_the_triangle_order():
    size = 20
    far = np.array([[2, 2, -1], [18, 2, -1], [18, 18, -1], [2, 18, -1]], float)
    near = np.array([[6, 6, 1], [14, 6, 1], [14, 14, 1], [6, 14, 1]], float)
    v = np.r_[far, near]
    quads = [np.array([[0, 1, 2], [0, 2, 3]]), np.array([[4, 5, 6], [4, 6, 7]])]
    colors = np.array([[1, 0, 0], [1, 0, 0], [0, 0, 1], [0, 0, 1]], float)
    view = flat_view(size, ambient=1.0, diffuse=0.0, specular=0.0)
    for order in ([0, 1, 2, 3], [3, 2, 1, 0], [2, 0, 3, 1]):
        tris = np.r_[quads[0], quads[1]][order]
        img = render(v, tris, size, view, colors=colors[order])
        assert img[10, 10, 2] > 200 and img[10, 10, 0] < 50  # blue square in front
        assert img[3, 3, 0] > 200 and img[3, 3, 2] < 50  # red behind, visible at the border


def test_back_faces_are_culled_unless_asked():
    size = 16
    v = np.array([[2, 2, 0], [14, 2, 0], [8, 14, 0]], float)
    front = np.array([[0, 1, 2]])
    back = front[:, ::-1]
    view = flat_view(size, background=(0, 0, 0))
    assert render(v, front, size, view).any()
    assert not render(v, back, size, view).any()
    assert render(v, back, size, view, cull=False).any()


def uv_sphere(n=24, radius=1.0):
    theta = np.linspace(0, np.pi, n)
    phi = np.linspace(0, 2 * np.pi, 2 * n, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    v = np.c_[(np.sin(t) * np.cos(p)).ravel(), np.cos(t).ravel(), (np.sin(t) * np.sin(p)).ravel()] * radius
    idx = np.arange(v.shape[0]).reshape(n, 2 * n)
    a, b = idx[:-1], np.roll(idx, -1, axis=1)[:-1]
    c, d = np.roll(idx, -1, axis=1)[1:], idx[1:]
    tris = np.r_[np.c_[a.ravel(), b.ravel(), c.ravel()], np.c_[a.ravel(), c.ravel(), d.ravel()]]
    # orient outward
    centroid = v[tris].mean(axis=1)
    normal = np.cross(v[tris[:, 1]] - v[tris[:, 0]], v[tris[:, 2]] - v[tris[:, 0]])
    flip = (normal * centroid).sum(axis=1) < 0
    tris[flip] = tris[flip][:, ::-1]
    return v, tris


def test_lambert_shading_follows_the_light():
    v, t = uv_sphere()
    left = View.fit(v, light=(-1.0, 0.0, 0.3), specular=0.0)
    right = View.fit(v, light=(1.0, 0.0, 0.3), specular=0.0)
    a, b = render(v, t, 64, left).mean(axis=2), render(v, t, 64, right).mean(axis=2)
    assert a[32, 12] > a[32, 52] + 40
    assert b[32, 52] > b[32, 12] + 40
    front = render(v, t, 64, View.fit(v, light=(0, 0, 1), specular=0.0)).mean(axis=2)
    assert front[32, 32] > front[32, 6] + 40  # the rim turns away from a frontal light


def test_perspective_makes_nearer_things_larger():
    size = 64
    square = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float)
    t = np.array([[0, 1, 2], [0, 2, 3]])
    view = View(center=(0, 0, 0), extent=8.0, perspective=3.0, background=(0, 0, 0))
    near = render(square + [0, 0, 4], t, size, view).any(axis=2).sum()
    far = render(square - [0, 0, 4], t, size, view).any(axis=2).sum()
    ortho = render(square, t, size, view.with_(perspective=None)).any(axis=2).sum()
    assert near > ortho > far


def test_named_views_and_supersampling():
    v, t = uv_sphere()
    colors = np.where((v[t].mean(axis=1)[:, 0] > 0.3)[:, None], [[1.0, 0, 0]], [[0, 0, 1.0]])
    from_left = render(v, t, 48, "left", colors=colors)  # the +x side (character's left) faces the eye
    front = render(v, t, 48, "front", colors=colors)
    red = lambda img: ((img[..., 0] > 60) & (img[..., 2] < 30)).sum()
    assert red(from_left) > 2 * red(front)
    with pytest.raises(ValueError):
        render(v, t, 48, "upside-down")
    smooth = render(v, t, (40, 30), "front", supersample=2)
    assert smooth.shape == (30, 40, 3) and smooth.dtype == np.uint8


@pytest.fixture(scope="module")
def ict():
    from msflow.testing import run_stage
    from stages.retarget.character import GltfCharacter

    return run_stage(GltfCharacter, {}, {"mesh": ICT_GLB}).view()


def test_character_renderer_shows_the_face_and_its_expressions(ict):
    names = ict.meta["target_names"]
    renderer = CharacterRenderer.from_artifact(ict, size=256)
    neutral = renderer(np.zeros(len(names)))
    assert neutral.shape == (256, 256, 3)
    foreground = np.abs(neutral.astype(int) - np.array(renderer.view.background) * 255).sum(axis=2) > 30
    assert 0.3 < foreground.mean() < 0.95
    w = np.zeros(len(names))
    w[names.index("jawOpen")] = 1.0
    opened = renderer(w)
    changed = np.abs(opened.astype(int) - neutral.astype(int)).sum(axis=2) > 30
    rows = np.nonzero(changed)[0]
    assert changed.mean() > 0.01
    assert rows.mean() > 256 * 0.55  # the jaw is in the lower half of the face framing
    from stages.geometry.rotations import euler_to_quat

    turned = renderer(np.zeros(len(names)), rotation=euler_to_quat(0.4, 0.0, 0.0))
    assert np.abs(turned.astype(int) - neutral.astype(int)).mean() > 5


def test_eyes_are_found_by_their_parts_names_too(ict):
    """ICT FaceKit's own OBJs name the eyeball groups ``M_ScleraLeft`` and ``M_IrisLeft`` (no "eye"): the same eyes
    as the embedded GLB's ``M_EyeScleraLeft``...; the skin around the eye stays out."""
    from stages.export.rig import eye_side, find_eyes

    groups = [g["name"] for g in ict.meta["groups"]]
    as_in_the_objs = [
        name.replace("M_Eye", "M_") if "Eye" in name and "Occlusion" not in name else name for name in groups
    ]
    assert "M_ScleraLeft" in as_in_the_objs
    ours = find_eyes(ict["neutral"], ict["triangles"], ict["triangle_groups"], groups)
    theirs = find_eyes(ict["neutral"], ict["triangles"], ict["triangle_groups"], as_in_the_objs)
    assert [e.side for e in theirs] == [0, 1]
    for a, b in zip(ours, theirs):
        assert np.array_equal(a.vertices, b.vertices) and np.allclose(a.center, b.center)
    assert [eye_side(n) for n in ("M_IrisRight", "Cornea.L", "M_EyeOcclusion", "M_EyeLashes", "iris_lid_L")] == [
        1,
        0,
        None,
        None,
        None,
    ]


def test_eyes_turn_about_their_centres(ict):
    """An eye rotation from gaze turns the eyeball: yaw towards the character's left (+x) moves the iris to the
    image's right (the camera faces the character), pitch up moves it up; the rest of the face stays."""
    from stages.export.rig import find_eyes, gaze_rotations

    groups = [g["name"] for g in ict.meta["groups"]]
    eyes = find_eyes(ict["neutral"], ict["triangles"], ict["triangle_groups"], groups)
    assert [e.side for e in eyes] == [0, 1]
    renderer = CharacterRenderer.from_artifact(ict, size=256, eyes=[(e.vertices, e.center) for e in eyes])
    zeros = np.zeros(len(ict.meta["target_names"]))
    iris = [g for g, name in enumerate(groups) if "Iris" in name or "Pupil" in name]
    iris_vertices = np.unique(ict["triangles"][np.isin(ict["triangle_groups"], iris)])

    def iris_centre(gaze):
        v = renderer.vertices(zeros, eye_rotations=gaze_rotations(np.array(gaze, float))[None][0])
        _, xy = project(v[iris_vertices], renderer.view, 256)
        return xy.mean(axis=0), v

    (x0, y0), still = iris_centre([[0, 0], [0, 0]])
    (x1, y1), turned = iris_centre([[25, 0], [25, 0]])
    (x2, y2), _ = iris_centre([[0, 15], [0, 15]])
    assert x1 > x0 + 2 and abs(y1 - y0) < 0.5  # towards the image's right
    assert y2 < y0 - 1.5 and abs(x2 - x0) < 0.5  # up (image y points down)
    others = np.setdiff1d(np.arange(len(still)), np.concatenate([e.vertices for e in eyes]))
    assert np.array_equal(still[others], turned[others])
    # the eyeball turns about its centre: its vertices keep their distance to it
    for e in eyes:
        assert np.allclose(
            np.linalg.norm(turned[e.vertices] - e.center, axis=1),
            np.linalg.norm(still[e.vertices] - e.center, axis=1),
            atol=1e-6,
        )
    image = renderer(zeros, eye_rotations=gaze_rotations(np.array([[25.0, 0], [25.0, 0]])))
    assert np.abs(image.astype(int) - renderer(zeros).astype(int)).sum(axis=2).max() > 60
