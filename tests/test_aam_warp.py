"""Piecewise-affine warp (stages.face.warp): identity, known affine maps, inverse warp, pixel coverage."""

import numpy as np
import pytest
from face_fixtures import face_template

from stages.face.aam import canonical_pose, texture_reference
from stages.face.warp import (
    PiecewiseAffineWarp,
    barycentric,
    delaunay_triangles,
    nearest_inside_index,
    rasterise_triangles,
    triangle_signed_areas,
)


@pytest.fixture(scope="module")
def warp():
    points, size = texture_reference(canonical_pose(face_template()), 64)
    return PiecewiseAffineWarp(points, delaunay_triangles(points), size)


def linear_image(size, a=0.7, b=0.3, c=10.0):
    w, h = size
    ys, xs = np.mgrid[0:h, 0:w]
    return (a * xs + b * ys + c).astype(np.float32)


def test_triangles_are_positively_oriented_and_cover_the_hull(warp):
    from scipy.spatial import Delaunay

    corners = warp.reference[warp.triangles]
    assert np.all(triangle_signed_areas(corners) > 0)
    w, h = warp.size
    ys, xs = np.mgrid[0:h, 0:w]
    centres = np.c_[xs.ravel(), ys.ravel()].astype(float)
    inside_hull = Delaunay(warp.reference).find_simplex(centres) >= 0
    np.testing.assert_array_equal(warp.pixels.mask.ravel(), inside_hull)
    assert np.all(warp.pixels.bary >= -1e-9) and np.allclose(warp.pixels.bary.sum(1), 1)


def test_identity_warp_returns_the_reference_pixels(warp):
    image = linear_image(warp.size) + np.sin(np.arange(warp.size[0]))[None, :].astype(np.float32)
    samples = warp.warp(image[None], warp.reference[None])
    np.testing.assert_allclose(samples[0], image.ravel()[warp.pixels.pixel_index], atol=1e-3)


def test_affine_source_shape_samples_the_affine_positions(warp):
    a = np.array([[1.3, 0.2], [-0.25, 0.9]])
    t = np.array([12.0, 20.0])
    source = warp.reference @ a.T + t
    big = linear_image((160, 160), 0.5, 0.25, 3.0)
    samples = warp.warp(np.stack([big, big]), np.stack([source, source]))
    w = warp.size[0]
    pix = np.c_[warp.pixels.pixel_index % w, warp.pixels.pixel_index // w].astype(float)
    expected_pos = pix @ a.T + t
    np.testing.assert_allclose(samples[0], 0.5 * expected_pos[:, 0] + 0.25 * expected_pos[:, 1] + 3.0, atol=1e-2)
    np.testing.assert_allclose(samples[1], samples[0])


def test_a_frames_texture_does_not_depend_on_the_frames_warped_with_it(warp):
    """Each take's textures must be the same whether it is warped alone or beside other takes (the edit analyses
    each take on its own): positions summed per pixel in a fixed order, not by a matrix product over the batch,
    whose float32 rounding changed with the batch size on some CPUs (cv2.remap then rounded a grey level the
    other way)."""
    rng = np.random.default_rng(3)
    n = 300
    a = rng.uniform(0.8, 1.6, n)
    shapes = warp.reference[None] * a[:, None, None] + rng.uniform(5, 40, (n, 1, 2)) + rng.normal(0, 0.7, (n, 68, 2))
    images = rng.integers(0, 256, (n, 160, 160), dtype=np.uint8)
    together = warp.warp(images, shapes)
    for start, stop in ((0, 1), (7, 11), (100, 229), (299, 300)):
        np.testing.assert_array_equal(warp.warp(images[start:stop], shapes[start:stop]), together[start:stop])
    positions = warp.source_positions(shapes[:3])
    for f in range(3):
        np.testing.assert_allclose(positions[f], warp.pixels.positions(shapes[f]), rtol=1e-6)


def test_per_triangle_different_affines_are_piecewise_exact(warp):
    """A non-affine shape change: each pixel must land at its own triangle's barycentric combination."""
    rng = np.random.default_rng(3)
    source = warp.reference * 1.5 + 10 + rng.normal(0, 1.0, warp.reference.shape)
    big = linear_image((160, 160), 0.4, 0.6, 0.0)
    samples = warp.warp(big[None], source[None])[0]
    pos = warp.pixels.positions(source)
    np.testing.assert_allclose(samples, 0.4 * pos[:, 0] + 0.6 * pos[:, 1], atol=1e-2)
    np.testing.assert_allclose(warp.source_positions(source[None])[0], pos, atol=1e-4)


def test_inverse_warp_draws_the_texture_at_inverse_affine_positions(warp):
    texture = linear_image(warp.size, 2.0, 1.5, 5.0)
    a = np.array([[1.2, 0.3], [-0.2, 0.9]])
    t = np.array([5.0, 7.0])
    target = warp.reference @ a.T + t
    image, mask = warp.draw_on_shape(texture, target, (160, 160))
    yx = np.argwhere(mask)
    q = (yx[:, ::-1] - t) @ np.linalg.inv(a).T
    np.testing.assert_allclose(image[mask], 2.0 * q[:, 0] + 1.5 * q[:, 1] + 5.0, atol=0.05)
    # coverage: about the area of the transformed hull
    hull_area = np.abs(np.linalg.det(a)) * warp.pixels.mask.sum()
    assert abs(mask.sum() - hull_area) < 0.1 * hull_area


def test_forward_then_inverse_warp_round_trips_inside_the_face(warp):
    rng = np.random.default_rng(0)
    shape = warp.reference * 1.6 + 15 + rng.normal(0, 0.8, warp.reference.shape)
    ys, xs = np.mgrid[0:140, 0:140]
    image = (100 + 50 * np.sin(xs / 9.0) * np.cos(ys / 11.0)).astype(np.float32)
    samples = warp.warp(image[None], shape[None])
    texture = warp.fill_outside(warp.to_image(samples)[0])
    back, mask = warp.draw_on_shape(texture, shape, (140, 140))
    interior = mask & np.roll(mask, 2, 0) & np.roll(mask, -2, 0) & np.roll(mask, 2, 1) & np.roll(mask, -2, 1)
    err = np.abs(back[interior] - image[interior])
    assert np.median(err) < 1.0 and err.mean() < 2.0


def test_degenerate_and_folded_target_triangles_are_tolerated(warp):
    target = warp.reference.copy()
    target[60:68] = target[60:68].mean(0)  # inner lips collapse to a point
    image, mask = warp.draw_on_shape(np.ones(warp.size[::-1], np.float32), target, warp.size)
    assert np.isfinite(image).all() and mask.sum() > 0.9 * warp.pixels.mask.sum()
    index_map = rasterise_triangles(target, warp.triangles, warp.size)
    assert index_map.max() < len(warp.triangles)


def test_barycentric_of_corners_is_identity():
    corners = np.array([[[0, 0], [4, 0], [0, 3]]], dtype=float).repeat(3, 0)
    np.testing.assert_allclose(barycentric(corners[0], corners), np.eye(3), atol=1e-12)


def test_nearest_inside_index_keeps_inside_pixels():
    mask = np.zeros((5, 6), dtype=bool)
    mask[1:4, 2:4] = True
    idx = nearest_inside_index(mask)
    assert np.all(idx[mask.ravel()] == np.flatnonzero(mask.ravel()))
    assert mask.ravel()[idx].all()
