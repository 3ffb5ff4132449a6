"""BVH reading/writing (stages.formats.bvh) and the rotation helpers the head-motion area added to stages.geometry.rotations."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from msflow import UserError
from stages.formats.bvh import BvhJoint, format_bvh, head_bvh, joint_rotation, joint_translation, parse_bvh
from stages.geometry.rotations import (
    angular_velocity,
    euler_order_to_quat,
    euler_to_quat,
    quat_mean,
    quat_multiply,
    quat_resample,
    quat_slerp,
    quat_to_euler_order,
    quat_to_matrix,
)

ORDERS = ["XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"]
AXES = {"X": np.array([1.0, 0, 0]), "Y": np.array([0, 1.0, 0]), "Z": np.array([0, 0, 1.0])}


def rotation_matrix(axis: str, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return {
        "X": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "Y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "Z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


@pytest.mark.parametrize("order", ORDERS)
def test_euler_order_composes_matrices_in_listed_order(order):
    angles = np.array([0.3, -0.4, 0.7])
    expected = (
        rotation_matrix(order[0], angles[0])
        @ rotation_matrix(order[1], angles[1])
        @ rotation_matrix(order[2], angles[2])
    )
    np.testing.assert_allclose(quat_to_matrix(euler_order_to_quat(angles, order)), expected, atol=1e-12)


def test_yxz_order_is_the_project_convention():
    yaw, pitch, roll = 0.2, -0.3, 0.1
    np.testing.assert_allclose(
        euler_order_to_quat(np.array([yaw, pitch, roll]), "YXZ"), euler_to_quat(yaw, pitch, roll), atol=1e-12
    )


@settings(max_examples=60, deadline=None)
@given(st.sampled_from(ORDERS), st.floats(-3.0, 3.0), st.floats(-1.5, 1.5), st.floats(-3.0, 3.0))
def test_euler_order_round_trip(order, a, b, c):
    angles = np.array([a, b, c])
    back = quat_to_euler_order(euler_order_to_quat(angles, order), order)
    np.testing.assert_allclose(
        quat_to_matrix(euler_order_to_quat(back, order)), quat_to_matrix(euler_order_to_quat(angles, order)), atol=1e-9
    )
    if abs(b) < 1.5:
        np.testing.assert_allclose(back, angles, atol=1e-7)


def test_bad_order_is_rejected():
    with pytest.raises(ValueError):
        euler_order_to_quat(np.zeros(3), "XXY")


def test_quat_resample_reproduces_samples_and_interpolates_on_the_great_circle():
    t = np.arange(5) * 0.1
    q = euler_to_quat(np.linspace(0, 0.8, 5), np.zeros(5), np.zeros(5))
    np.testing.assert_allclose(np.abs(np.sum(quat_resample(t, q, t) * q, axis=1)), 1.0, atol=1e-12)
    mid = quat_resample(t, q, np.array([0.05]))[0]
    np.testing.assert_allclose(np.abs(mid @ quat_slerp(q[0], q[1], 0.5)), 1.0, atol=1e-12)
    # clamped beyond the sampled range
    np.testing.assert_allclose(np.abs(quat_resample(t, q, np.array([9.0]))[0] @ q[-1]), 1.0, atol=1e-12)


def test_angular_velocity_of_a_constant_spin():
    fps, rate = 50.0, 1.3  # rad/s about y
    t = np.arange(20) / fps
    q = euler_to_quat(rate * t, np.zeros(20), np.zeros(20))
    w = angular_velocity(q, fps)
    np.testing.assert_allclose(w, np.tile([0.0, rate, 0.0], (19, 1)), atol=1e-9)


def test_quat_mean_of_symmetric_spread_is_the_centre():
    centre = euler_to_quat(0.4, 0.1, 0.0)
    offsets = euler_to_quat(np.array([0.1, -0.1, 0.0, 0.0]), np.array([0.0, 0.0, 0.1, -0.1]), np.zeros(4))
    samples = quat_multiply(centre, offsets)
    samples[1] *= -1  # sign must not matter
    assert abs(quat_mean(samples) @ centre) > 1 - 1e-4


SKELETON = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Neck
  {
    OFFSET 0 50 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT Head
    {
      OFFSET 0 10 0
      CHANNELS %d %s
      End Site
      {
        OFFSET 0 12 0
      }
    }
  }
  JOINT LeftLeg
  {
    OFFSET 10 -5 0
    CHANNELS 3 Xrotation Yrotation Zrotation
    End Site
    {
      OFFSET 0 -40 0
    }
  }
}
MOTION
Frames: %d
Frame Time: 0.0083333
%s
"""


def skeleton_text(head_channels: list[str], head_values: np.ndarray) -> str:
    n = len(head_values)
    rng = np.random.default_rng(1)
    rows = np.concatenate(
        [rng.normal(size=(n, 6)), rng.normal(size=(n, 3)), head_values, rng.normal(size=(n, 3))], axis=1
    )
    body = "\n".join(" ".join(f"{v:.9f}" for v in row) for row in rows)
    return SKELETON % (len(head_channels), " ".join(head_channels), n, body)


@pytest.mark.parametrize("order", ORDERS)
def test_head_joint_rotation_read_in_any_channel_order(order):
    rng = np.random.default_rng(0)
    truth = rng.uniform(-40, 40, size=(7, 3))  # degrees, in channel order
    bvh = parse_bvh(skeleton_text([f"{a}rotation" for a in order], truth), source="take.bvh")
    assert bvh.fps == pytest.approx(120.0, rel=1e-4)
    assert [j.name for j in bvh.joints] == ["Hips", "Neck", "Head", "LeftLeg"]
    assert bvh.joint("Head").parent == 1 and bvh.joint("LeftLeg").parent == 0
    np.testing.assert_allclose(bvh.joint("Head").end_site, [0, 12, 0])
    q = joint_rotation(bvh, "Head")
    np.testing.assert_allclose(
        quat_to_matrix(q), quat_to_matrix(euler_order_to_quat(np.radians(truth), order)), atol=1e-9
    )
    # no position channels: the joint's rest offset
    np.testing.assert_allclose(joint_translation(bvh, "Head"), np.tile([0, 10, 0], (7, 1)))


def test_head_joint_with_position_channels():
    values = np.array([[1.0, 2.0, 3.0, 10.0, 0.0, 0.0], [4.0, 5.0, 6.0, 0.0, 20.0, 0.0]])
    bvh = parse_bvh(
        skeleton_text(["Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation"], values)
    )
    np.testing.assert_allclose(joint_translation(bvh, "Head"), values[:, :3])


def test_missing_joint_names_the_joints():
    bvh = parse_bvh(skeleton_text(["Zrotation", "Xrotation", "Yrotation"], np.zeros((2, 3))), source="a.bvh")
    with pytest.raises(UserError) as err:
        joint_rotation(bvh, "head_jnt")
    assert "head_jnt" in str(err.value) and "Neck" in str(err.value) and err.value.file == "a.bvh"


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("nonsense", "MOTION"),
        (
            "HIERARCHY\nROOT A\n{\nOFFSET 0 0 0\nCHANNELS 3 Xrotation Yrotation Zrotation\n}\nMOTION\nFrames: 2\n"
            "Frame Time: 0.1\n0 0 0\n",
            "expected",
        ),
        (
            "HIERARCHY\nROOT A\n{\nOFFSET 0 0 0\nCHANNELS 3 Xrotation Yrotation Wrotation\n}\nMOTION\nFrames: 1\n"
            "Frame Time: 0.1\n0 0 0\n",
            "channels",
        ),
        (
            "HIERARCHY\nROOT A\n{\nOFFSET 0 0 0\nCHANNELS 3 Xrotation Yrotation Zrotation\n}\nMOTION\nFrames: 1\n"
            "Frame Time: 0\n0 0 0\n",
            "positive",
        ),
        (
            "HIERARCHY\nROOT A\n{\nOFFSET 0 0 0\nCHANNELS 3 Xrotation Yrotation Zrotation\nMOTION\nFrames: 1\n"
            "Frame Time: 0.1\n0 0 0\n",
            "braces",
        ),
    ],
)
def test_malformed_bvh_is_a_user_error(text, fragment):
    with pytest.raises(UserError) as err:
        parse_bvh(text, source="bad.bvh")
    assert fragment in str(err.value) and err.value.file == "bad.bvh"


def test_end_site_channels_do_not_overwrite_the_joints_channels():
    """Issue 16: a ``CHANNELS 0`` line inside an End Site used to replace its parent joint's channels."""
    text = skeleton_text(["Zrotation", "Xrotation", "Yrotation"], np.full((2, 3), 30.0))
    text = text.replace("OFFSET 0 12 0\n", "OFFSET 0 12 0\n        CHANNELS 0\n")
    bvh = parse_bvh(text)
    assert bvh.joint("Head").channels == ["Zrotation", "Xrotation", "Yrotation"]
    np.testing.assert_allclose(bvh.joint("Head").end_site, [0, 12, 0])
    np.testing.assert_allclose(bvh.channel(bvh.joint("Head"), "Xrotation"), 30.0)
    with pytest.raises(UserError, match="End Site of Head lists channels"):
        parse_bvh(text.replace("CHANNELS 0", "CHANNELS 1 Xrotation"), source="x.bvh")


@pytest.mark.parametrize("name", ["MOTION", "MOTION_capture", "Head_MOTION", "Frames:"])
def test_joint_names_holding_motion_keywords(name):
    """Issue 16: a joint named with "MOTION" used to split the file inside the HIERARCHY."""
    truth = np.array([[10.0, 20.0, 30.0], [5.0, 6.0, 7.0]])
    text = skeleton_text(["Zrotation", "Xrotation", "Yrotation"], truth).replace("JOINT Neck", f"JOINT {name}")
    bvh = parse_bvh(text)
    assert [j.name for j in bvh.joints] == ["Hips", name, "Head", "LeftLeg"] and bvh.frames == 2
    np.testing.assert_allclose(bvh.channel(bvh.joint("Head"), "Zrotation"), truth[:, 0])


def test_errors_name_the_hierarchy_line():
    text = skeleton_text(["Zrotation", "Xrotation", "Yrotation"], np.zeros((1, 3))).replace(
        "OFFSET 10 -5 0", "OFFSET 10 -5"
    )
    with pytest.raises(UserError, match=r"OFFSET of LeftLeg needs 3 numbers.*\(line 2[0-9]\)"):
        parse_bvh(text)


@pytest.mark.parametrize("order", ["ZXY", "XYZ", "YXZ"])
def test_head_bvh_round_trip(order):
    rng = np.random.default_rng(3)
    n = 40
    t = np.arange(n) / 30.0
    q = euler_to_quat(0.5 * np.sin(2 * t), 0.3 * np.cos(3 * t), 0.2 * np.sin(t))
    translation = rng.normal(size=(n, 3))
    text = head_bvh(q, translation, 30.0, joint="Head", order=order)
    back = parse_bvh(text)
    assert back.frames == n and back.fps == pytest.approx(30.0, rel=1e-6)
    assert back.joints[0].rotation_order == order
    np.testing.assert_allclose(np.abs(np.sum(joint_rotation(back, "Head") * q, axis=1)), 1.0, atol=1e-9)
    np.testing.assert_allclose(joint_translation(back, "Head"), translation, atol=1e-6)


def test_format_bvh_writes_a_skeleton_that_parses_back():
    joints = [
        BvhJoint(
            "Root", -1, np.zeros(3), ["Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation"]
        ),
        BvhJoint("Neck", 0, np.array([0.0, 5.0, 0.0]), ["Zrotation", "Xrotation", "Yrotation"]),
        BvhJoint("Head", 1, np.array([0.0, 3.0, 0.0]), ["Zrotation", "Xrotation", "Yrotation"]),
    ]
    motion = np.arange(24, dtype=float).reshape(2, 12)
    back = parse_bvh(format_bvh(joints, motion, 1 / 24))
    assert [j.name for j in back.joints] == ["Root", "Neck", "Head"]
    assert [j.parent for j in back.joints] == [-1, 0, 1]
    np.testing.assert_allclose(back.motion, motion)
    with pytest.raises(ValueError):
        format_bvh(joints, np.full((2, 12), np.nan), 1 / 24)
