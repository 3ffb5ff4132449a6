"""Held stretches eased into the face found again (stages.geometry.held_gaps): known answers."""

import numpy as np
import pytest

from stages.geometry.held_gaps import ease_into_found_face, found_again_spans
from stages.geometry.ramps import smoothstep
from stages.geometry.rotations import euler_to_quat, quat_to_euler


def test_only_the_last_frames_of_a_gap_the_face_comes_back_after_are_eased():
    """Two takes of 20 frames at 10 fps; take 0 holds frames 5-14 and finds the face at 15, take 1 holds 12-19
    and ends without it. With 0.4 s, frames 11-14 of take 0 (global 11-14) ease; take 1 stays held."""
    sequence = np.repeat([0, 1], 20)
    spans = found_again_spans(sequence, [[[5, 15]], [[12, 20]]], [10.0, 10.0], 0.4)
    assert spans == [(11, 15)]
    assert found_again_spans(sequence, [[[5, 15]], []], [10.0], 0.0) == []  # 0 s: the jump, as before
    assert found_again_spans(sequence, [[[5, 15]]], [10.0], 2.0) == [(5, 15)]  # never before the gap starts


def test_a_held_value_moves_smoothly_into_the_found_one():
    values = np.zeros((20, 2))
    values[15:] = [1.0, -2.0]  # held at 0 through the gap, found at (1, -2)
    eased = ease_into_found_face(values, [(11, 15)])
    np.testing.assert_array_equal(eased[:11], 0.0)
    np.testing.assert_array_equal(eased[15:], values[15:])
    t = smoothstep(np.arange(1, 5) / 5)
    np.testing.assert_allclose(eased[11:15], t[:, None] * [[1.0, -2.0]])
    steps = np.abs(np.diff(eased[10:16, 0]))
    assert steps.max() < 0.35  # the jump of 1.0 spread over five steps, the largest in the middle


def test_a_held_head_turns_along_the_shortest_arc():
    """A head held at 40 degrees of yaw and found at -40 turns through 0, at the smoothstep's fractions."""
    q = np.repeat(euler_to_quat(np.radians([40.0]), np.zeros(1), np.zeros(1)), 10, axis=0)
    q[8:] = euler_to_quat(np.radians([-40.0]), np.zeros(1), np.zeros(1))
    eased = ease_into_found_face(q, [(5, 8)], rotations=True)
    yaw = np.degrees(quat_to_euler(eased)[:, 0])
    np.testing.assert_allclose(yaw[5:8], 40.0 - 80.0 * smoothstep(np.arange(1, 4) / 4), atol=1e-9)
    assert yaw[:5] == pytest.approx([40.0] * 5) and yaw[8:] == pytest.approx([-40.0] * 2)
