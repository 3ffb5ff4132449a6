"""Tracking maths on synthetic data with known answers: BlazeFace anchors/decoding/NMS, ROI geometry, gap
filling, crops, head pose conventions, the shape model."""

import numpy as np
import pytest

from msflow import UserError
from stages.geometry.rotations import euler_to_quat, quat_to_euler, quat_to_matrix
from stages.geometry.similarity import apply_similarity, fit_similarity, invert_similarity, similarity_parameters
from stages.tracking.blazeface import (
    ANCHORS,
    box_iou,
    decode_boxes,
    letterbox_transform,
    ssd_anchor_centres,
    weighted_nms,
)
from stages.tracking.crops import apply_transforms, eye_centres, similarity_transform, similarity_transforms
from stages.tracking.face3d import DEFAULT_FACE3D, load_face3d
from stages.tracking.facemesh import Roi, invert_affine, roi_from_mesh, square_roi
from stages.tracking.gaps import fill_face_gaps, find_gaps, interpolate_gaps
from stages.tracking.landmarks68 import IBUG68_MIRROR, MAPPING_MATRIX, MESH_TO_IBUG68, mesh_to_ibug68
from stages.tracking.pose import camera_matrix, openface_pose_to_gltf, project_face, solve_head_pose
from stages.tracking.shape_model import build_shape_model, fit_shape


@pytest.fixture(scope="module")
def face3d():
    return load_face3d(DEFAULT_FACE3D)


# ---------------------------------------------------------------- BlazeFace


def test_anchor_layout_matches_the_model_output_order():
    assert ANCHORS.shape == (896, 2)
    # 16x16 map, 2 anchors per cell, row-major from the top-left cell
    np.testing.assert_allclose(ANCHORS[0], [0.5 / 16, 0.5 / 16])
    np.testing.assert_allclose(ANCHORS[1], ANCHORS[0])
    np.testing.assert_allclose(ANCHORS[2], [1.5 / 16, 0.5 / 16])
    np.testing.assert_allclose(ANCHORS[32], [0.5 / 16, 1.5 / 16])
    # then the 8x8 map shared by three stride-16 layers: 6 anchors per cell
    np.testing.assert_allclose(ANCHORS[512:518], np.tile([0.5 / 8, 0.5 / 8], (6, 1)))
    np.testing.assert_allclose(ANCHORS[-1], [7.5 / 8, 7.5 / 8])
    assert ssd_anchor_centres(128, (8, 16)).shape == (16 * 16 * 2 + 8 * 8 * 2, 2)


def test_decoding_is_anchor_relative_in_input_pixels():
    reg = np.zeros((896, 16))
    reg[100, :4] = [12.8, -6.4, 32.0, 16.0]  # centre offset and size in 128-pixel units
    reg[100, 4:6] = [-12.8, 0.0]  # first keypoint
    boxes, kps = decode_boxes(reg)
    cx, cy = ANCHORS[100] + [0.1, -0.05]
    np.testing.assert_allclose(boxes[100], [cx - 0.125, cy - 0.0625, cx + 0.125, cy + 0.0625])
    np.testing.assert_allclose(kps[100, 0], ANCHORS[100] + [-0.1, 0.0])
    np.testing.assert_allclose(kps[100, 1], ANCHORS[100])


def test_weighted_nms_merges_overlaps_and_keeps_separate_faces():
    boxes = np.array([[0.1, 0.1, 0.3, 0.3], [0.12, 0.1, 0.32, 0.3], [0.6, 0.6, 0.8, 0.8]])
    kps = np.repeat(boxes[:, None, :2], 6, axis=1)
    scores = np.array([0.9, 0.6, 0.7])
    s, b, k = weighted_nms(scores, boxes, kps, 0.3)
    assert s.tolist() == [0.9, 0.7]
    np.testing.assert_allclose(b[0], (0.9 * boxes[0] + 0.6 * boxes[1]) / 1.5)
    np.testing.assert_allclose(b[1], boxes[2])
    np.testing.assert_allclose(k[0, 0], (0.9 * boxes[0, :2] + 0.6 * boxes[1, :2]) / 1.5)
    assert weighted_nms(scores, boxes, kps, 0.3, max_faces=1)[0].tolist() == [0.9]
    assert box_iou(boxes[0], boxes[2:])[0] == 0.0


def test_letterbox_keeps_aspect_and_centres():
    m = letterbox_transform(480, 360)
    corners = np.array([[0, 0, 1], [480, 360, 1]]) @ m.T
    np.testing.assert_allclose(corners, [[0, 16], [128, 112]])


# ---------------------------------------------------------------- ROI geometry


def test_roi_affine_round_trip_and_orientation():
    roi = Roi(200.0, 150.0, 120.0, np.radians(20))
    to_image = roi.input_to_image(192)
    centre = to_image @ [96, 96, 1]
    np.testing.assert_allclose(centre, [200, 150])
    # the input's x axis runs along the ROI angle in the image
    step = to_image @ [97, 96, 1] - centre
    np.testing.assert_allclose(np.arctan2(step[1], step[0]), np.radians(20))
    np.testing.assert_allclose(np.linalg.norm(step), 120 / 192)
    back = roi.image_to_input(192) @ np.append(centre, 1)
    np.testing.assert_allclose(back, [96, 96])
    np.testing.assert_allclose(invert_affine(invert_affine(to_image)), to_image)


def test_roi_from_points_is_square_scaled_and_rotated_by_the_eye_line():
    pts = np.zeros((468, 3))
    pts[:, :2] = np.random.default_rng(0).uniform([100, 50], [180, 170], (468, 2))
    pts[33, :2], pts[263, :2] = [110, 100], [170, 110]
    roi = roi_from_mesh(pts)
    assert roi.size == pytest.approx(1.5 * (pts[:, 1].max() - pts[:, 1].min()))
    assert roi.angle == pytest.approx(np.arctan2(10, 60))
    assert square_roi(0, 0, 10, 4, 0.0).size == pytest.approx(15)


# ---------------------------------------------------------------- gaps


def test_gap_filling_interpolates_linearly_and_holds_the_ends():
    valid = np.array([False, True, True, False, False, True, False])
    values = np.where(valid, np.arange(7.0) * 3, np.nan)[:, None, None] * np.ones((1, 2, 2))
    out = interpolate_gaps(values, valid)
    np.testing.assert_allclose(out[:, 0, 0], [3, 3, 6, 9, 12, 15, 15])
    assert find_gaps(valid) == [(0, 1), (3, 5), (6, 7)]
    assert find_gaps(np.ones(4, bool)) == []


def test_gap_errors_name_the_frames():
    valid = np.ones(40, bool)
    valid[10:30] = False
    with pytest.raises(UserError, match=r"frames 10-29 \(20 frames, 0\.33-0\.97 s\)") as err:
        fill_face_gaps(np.zeros((40, 68, 2)), valid, 15, np.arange(40) / 30, file="clip.mp4", field="f")
    assert err.value.file == "clip.mp4"
    out = fill_face_gaps(np.zeros((40, 68, 2)), valid, 20)
    assert out.shape == (40, 68, 2)
    with pytest.raises(UserError, match="no face found in any of its 5 frames"):
        fill_face_gaps(np.zeros((5, 68, 2)), np.zeros(5, bool), 10)


# ---------------------------------------------------------------- crops


def test_crop_transform_puts_the_eyes_level_at_fixed_positions():
    rng = np.random.default_rng(1)
    lm = rng.uniform(50, 300, (5, 68, 2))
    m = similarity_transforms(lm, 128, 0.3, 0.33)
    right, left = eye_centres(apply_transforms(lm, m))
    np.testing.assert_allclose(right, np.tile([128 * 0.35, 128 * 0.33], (5, 1)), atol=1e-9)
    np.testing.assert_allclose(left, np.tile([128 * 0.65, 128 * 0.33], (5, 1)), atol=1e-9)
    # a similarity: equal scale on both axes, no shear
    a = m[:, :, :2]
    np.testing.assert_allclose(a[:, 0, 0], a[:, 1, 1])
    np.testing.assert_allclose(a[:, 0, 1], -a[:, 1, 0])
    np.testing.assert_allclose(similarity_transform(lm[2], 128, 0.3, 0.33), m[2], atol=1e-12)


# ---------------------------------------------------------------- landmarks table


def test_mapping_table_is_68_points_of_one_or_two_mesh_vertices():
    assert len(MESH_TO_IBUG68) == 68
    assert all(1 <= len(v) <= 2 and all(0 <= i < 468 for i in v) for v in MESH_TO_IBUG68)
    np.testing.assert_allclose(MAPPING_MATRIX.sum(axis=1), 1.0)
    mesh = np.random.default_rng(2).normal(size=(3, 468, 3))
    out = mesh_to_ibug68(mesh)
    np.testing.assert_allclose(out[:, 49], (mesh[:, 40] + mesh[:, 39]) / 2)
    np.testing.assert_allclose(out[:, 30], mesh[:, 4])
    assert sorted(IBUG68_MIRROR.tolist()) == list(range(68))
    assert (IBUG68_MIRROR[IBUG68_MIRROR] == np.arange(68)).all()


# ---------------------------------------------------------------- head pose


def test_face3d_is_in_the_gltf_head_frame(face3d):
    n = face3d.neutral
    assert n.shape == (68, 3)
    assert n[36, 0] < n[45, 0]  # subject's right eye on the viewer's left (-x)
    assert n[19, 1] > n[57, 1]  # brows above the mouth (+y up)
    assert n[30, 2] > n[0, 2]  # nose tip out of the face (+z)


def test_pose_round_trip_and_sign_conventions(face3d):
    cam = camera_matrix(640, 480)
    euler = np.radians([[20, -10, 5], [0, 0, 0], [-15, 12, -8]])
    q = euler_to_quat(euler[:, 0], euler[:, 1], euler[:, 2])
    t = np.array([[3.0, -2.0, -70.0], [0, 0, -60.0], [-5, 4, -90.0]])
    image = project_face(face3d.neutral, q, t, cam)
    # identity: frontal and upright in the image
    frontal = image[1]
    assert frontal[36, 0] < frontal[45, 0] and frontal[19, 1] < frontal[57, 1]
    # positive yaw turns the nose to the viewer's right, positive pitch tips it down (glTF right-handed)
    jaw_mid = (image[:, 0] + image[:, 16]) / 2
    assert image[0, 30, 0] - jaw_mid[0, 0] > frontal[30, 0] - (frontal[0, 0] + frontal[16, 0]) / 2 + 5
    rot, trans, rms = solve_head_pose(image, face3d.neutral, cam)
    np.testing.assert_allclose(quat_to_euler(rot), euler, atol=1e-4)
    np.testing.assert_allclose(trans, t, atol=1e-3)
    assert rms.max() < 1e-3
    rigid = np.array(face3d.rigid)
    rot2, _, _ = solve_head_pose(image, face3d.neutral, cam, rigid)
    np.testing.assert_allclose(quat_to_euler(rot2), euler, atol=1e-4)


def test_pitch_sign_looks_down(face3d):
    cam = camera_matrix(640, 480)
    q = euler_to_quat(np.zeros(2), np.radians([0, 15]), np.zeros(2))
    image = project_face(face3d.neutral, q, np.tile([0, 0, -60.0], (2, 1)), cam)
    nose_below_eyes = image[:, 30, 1] - (image[:, 36, 1] + image[:, 45, 1]) / 2
    assert nose_below_eyes[1] > nose_below_eyes[0] + 3


def test_openface_pose_conversion_agrees_with_solvepnp(face3d):
    """OpenFace's convention (R = Rx Ry Rz on a head model in OpenCV camera axes, T in mm) projected
    independently, then recovered through solvePnP in the stages.geometry.rotations convention."""
    cam = camera_matrix(640, 480)
    euler_of = np.radians([[10, -20, 5], [-8, 15, -3]])
    t_mm = np.array([[20.0, -10.0, 700.0], [-30, 15, 650.0]])
    cv_flip = np.diag([1.0, -1.0, -1.0])
    head_of = face3d.neutral @ cv_flip * 10.0  # OpenFace head model: x right, y down, z away; mm
    images = []
    for e, t in zip(euler_of, t_mm):
        a, b, c = e
        rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
        ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
        rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
        p = head_of @ (rx @ ry @ rz).T + t
        uv = p @ cam.T
        images.append(uv[:, :2] / uv[:, 2:])
    rot, trans, _ = solve_head_pose(np.array(images), face3d.neutral, cam)
    q_of, t_of = openface_pose_to_gltf(euler_of, t_mm)
    np.testing.assert_allclose(np.abs(np.sum(rot * q_of, axis=1)), 1.0, atol=1e-8)
    np.testing.assert_allclose(trans, t_of, atol=1e-3)
    np.testing.assert_allclose(quat_to_matrix(q_of)[0] @ quat_to_matrix(q_of)[0].T, np.eye(3), atol=1e-12)


# ---------------------------------------------------------------- shape model


def test_shape_model_reproduces_model_shapes_and_predicts_lost_points(face3d):
    model = build_shape_model(face3d, variance=0.995, samples=1500, expressions_per_sample=8)
    assert model.basis.shape[0] == 136
    np.testing.assert_allclose(model.basis.T @ model.basis, np.eye(model.basis.shape[1]), atol=1e-10)
    rng = np.random.default_rng(3)
    b = np.clip(rng.normal(size=model.basis.shape[1]), -2.5, 2.5) * np.sqrt(model.variances)  # inside the +-3 sd box
    shape = model.mean + (model.basis @ b).reshape(68, 2)
    theta, scale, shift = 0.2, 140.0, np.array([240.0, 180.0])
    rot = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    image = shape @ rot.T * scale + shift
    fitted, coeffs = fit_shape(model, image, noise=1e-4)
    assert np.abs(fitted - image).max() < 0.05
    # corrupt a third of the points, give them zero weight: the model puts them back
    corrupt = image.copy()
    lost = rng.choice(68, 22, replace=False)
    corrupt[lost] += rng.normal(0, 15, (22, 2))
    weights = np.ones(68)
    weights[lost] = 0
    fitted, _ = fit_shape(model, corrupt, weights, noise=1e-3)
    assert np.abs(fitted - image)[lost].max() < 1.0


def test_weighted_similarity_fit_is_exact_for_similar_shapes():
    rng = np.random.default_rng(4)
    src = rng.normal(size=(20, 2))
    m = np.array([[1.5, -0.4], [0.4, 1.5]])
    dst = src @ m.T + [3, -2]
    t = fit_similarity(src, dst, rng.uniform(0.1, 1, 20))
    np.testing.assert_allclose(t, np.column_stack([m, [3, -2]]), atol=1e-12)
    # batched, with noise: each fit is the least-squares optimum (no small change of it does better)
    noisy = np.stack([dst + rng.normal(scale=0.05, size=dst.shape) for _ in range(3)])
    fits = fit_similarity(np.broadcast_to(src, noisy.shape), noisy)
    assert fits.shape == (3, 2, 3)
    for fit, target in zip(fits, noisy):
        best = np.sum((apply_similarity(fit, src) - target) ** 2)
        for delta in np.eye(4) * 1e-4:
            a, b, tx, ty = fit[0, 0] + delta[0], fit[1, 0] + delta[1], fit[0, 2] + delta[2], fit[1, 2] + delta[3]
            other = np.array([[a, -b, tx], [b, a, ty]])
            assert np.sum((apply_similarity(other, src) - target) ** 2) > best
    scale, angle, tx, ty = similarity_parameters(t)
    np.testing.assert_allclose([scale, angle, tx, ty], [np.hypot(1.5, 0.4), np.arctan2(0.4, 1.5), 3, -2])
    np.testing.assert_allclose(apply_similarity(invert_similarity(t), dst), src, atol=1e-12)
