"""Rotation conventions shared by every stage that touches head motion. All functions are vectorised.

Quaternions are unit (w, x, y, z), arrays of shape (..., 4), acting on column vectors (v' = q v q*).

The head frame is glTF's: x to the viewer's right, y up, z towards the viewer (camera); the identity rotation is a
head facing the camera upright. Euler angles (radians) decompose R = Ry(yaw) @ Rx(pitch) @ Rz(roll):
yaw about +y, pitch about +x, roll about +z, right-handed. Mirroring the motion about the face's mid-plane
(x -> -x) negates yaw and roll and leaves pitch.
"""

from __future__ import annotations

import numpy as np


def quat_normalize(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a*b (apply b, then a)."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a, dtype=np.float64), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, dtype=np.float64), -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = np.moveaxis(quat_normalize(q), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) to unit quaternions with w >= 0 (Shepperd's method, branch per element)."""
    m = np.asarray(m, dtype=np.float64)
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    trace = m00 + m11 + m22
    candidates = np.stack(
        [
            np.stack(
                [1 + trace, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1
            ),
            np.stack(
                [
                    m[..., 2, 1] - m[..., 1, 2],
                    1 + m00 - m11 - m22,
                    m[..., 0, 1] + m[..., 1, 0],
                    m[..., 0, 2] + m[..., 2, 0],
                ],
                -1,
            ),
            np.stack(
                [
                    m[..., 0, 2] - m[..., 2, 0],
                    m[..., 0, 1] + m[..., 1, 0],
                    1 - m00 + m11 - m22,
                    m[..., 1, 2] + m[..., 2, 1],
                ],
                -1,
            ),
            np.stack(
                [
                    m[..., 1, 0] - m[..., 0, 1],
                    m[..., 0, 2] + m[..., 2, 0],
                    m[..., 1, 2] + m[..., 2, 1],
                    1 - m00 - m11 + m22,
                ],
                -1,
            ),
        ],
        -2,
    )
    pick = np.argmax(np.stack([trace, m00, m11, m22], -1), axis=-1)
    q = np.take_along_axis(candidates, pick[..., None, None], axis=-2)[..., 0, :]
    q = quat_normalize(q)
    return np.where(q[..., :1] < 0, -q, q)


def rotvec_to_quat(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    half = 0.5 * angle
    scale = np.where(angle > 1e-12, np.sin(half) / np.maximum(angle, 1e-300), 0.5)
    return np.concatenate([np.cos(half), v * scale], axis=-1)


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    q = quat_normalize(q)
    q = np.where(q[..., :1] < 0, -q, q)
    s = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    angle = 2 * np.arctan2(s, q[..., :1])
    scale = np.where(s > 1e-12, angle / np.maximum(s, 1e-300), 2.0)
    return q[..., 1:] * scale


def euler_to_quat(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """q = qy(yaw) * qx(pitch) * qz(roll), the module's Euler convention."""
    yaw, pitch, roll = (np.asarray(a, dtype=np.float64) for a in (yaw, pitch, roll))
    zeros = np.zeros_like(yaw + pitch + roll)
    qy = np.stack([np.cos(yaw / 2) + zeros, zeros, np.sin(yaw / 2) + zeros, zeros], -1)
    qx = np.stack([np.cos(pitch / 2) + zeros, np.sin(pitch / 2) + zeros, zeros, zeros], -1)
    qz = np.stack([np.cos(roll / 2) + zeros, zeros, zeros, np.sin(roll / 2) + zeros], -1)
    return quat_multiply(quat_multiply(qy, qx), qz)


def quat_to_euler(q: np.ndarray) -> np.ndarray:
    """(..., 3) array of (yaw, pitch, roll) with R = Ry(yaw) Rx(pitch) Rz(roll); pitch in [-pi/2, pi/2]."""
    r = quat_to_matrix(q)
    pitch = np.arcsin(np.clip(-r[..., 1, 2], -1.0, 1.0))
    yaw = np.arctan2(r[..., 0, 2], r[..., 2, 2])
    roll = np.arctan2(r[..., 1, 0], r[..., 1, 1])
    return np.stack([yaw, pitch, roll], axis=-1)


def quat_continuous(q: np.ndarray) -> np.ndarray:
    """Flip signs along axis 0 so consecutive quaternions lie in one hemisphere (smooth interpolation)."""
    q = np.array(q, dtype=np.float64, copy=True)
    if len(q) < 2:
        return q
    flips = np.sum(q[1:] * q[:-1], axis=-1) < 0
    sign = np.concatenate([[1.0], np.where(np.cumsum(flips) % 2 == 1, -1.0, 1.0)])
    return q * sign[:, None]


def quat_slerp(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Spherical interpolation between unit quaternions, shortest path, broadcasting over t."""
    a, b = quat_normalize(a), quat_normalize(b)
    t = np.asarray(t, dtype=np.float64)[..., None]
    dot = np.sum(a * b, axis=-1, keepdims=True)
    b = np.where(dot < 0, -b, b)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin = np.sin(theta)
    small = sin < 1e-8
    wa = np.where(small, 1 - t, np.sin((1 - t) * theta) / np.where(small, 1.0, sin))
    wb = np.where(small, t, np.sin(t * theta) / np.where(small, 1.0, sin))
    return quat_normalize(wa * a + wb * b)


def mirror_quat(q: np.ndarray) -> np.ndarray:
    """Mirror image of a head rotation about the x = 0 plane: negates yaw and roll, keeps pitch."""
    q = np.asarray(q, dtype=np.float64)
    return q * np.array([1.0, 1.0, -1.0, -1.0])


# --- Added by the head-motion area: arbitrary Euler orders (BVH), resampling and angular rates. ---

_AXIS_INDEX = {"X": 0, "Y": 1, "Z": 2}


def _check_order(order: str) -> tuple[int, int, int]:
    order = order.upper()
    if len(order) != 3 or set(order) != {"X", "Y", "Z"}:
        raise ValueError(f"Euler order must be a permutation of 'XYZ', got {order!r}")
    return tuple(_AXIS_INDEX[a] for a in order)  # type: ignore[return-value]


def axis_angle_quat(axis: int, angle: np.ndarray) -> np.ndarray:
    """Quaternions of rotations by ``angle`` (radians, any shape) about coordinate axis 0 (x), 1 (y) or 2 (z)."""
    angle = np.asarray(angle, dtype=np.float64)
    q = np.zeros(angle.shape + (4,))
    q[..., 0] = np.cos(angle / 2)
    q[..., 1 + axis] = np.sin(angle / 2)
    return q


def euler_order_to_quat(angles: np.ndarray, order: str) -> np.ndarray:
    """Angles (..., 3) in radians about the axes named by ``order`` (e.g. "ZXY"): R = R_Z(a0) R_X(a1) R_Y(a2).

    This is the BVH channel convention (rotations listed outermost first). ``euler_order_to_quat(a, "YXZ")`` with
    a = (yaw, pitch, roll) equals ``euler_to_quat(yaw, pitch, roll)``.
    """
    axes = _check_order(order)
    angles = np.asarray(angles, dtype=np.float64)
    q = axis_angle_quat(axes[0], angles[..., 0])
    for k in (1, 2):
        q = quat_multiply(q, axis_angle_quat(axes[k], angles[..., k]))
    return q


def quat_to_euler_order(q: np.ndarray, order: str) -> np.ndarray:
    """Inverse of ``euler_order_to_quat``: (..., 3) angles with the middle angle in [-pi/2, pi/2]."""
    i, j, k = _check_order(order)
    sign = 1.0 if (i, j, k) in ((0, 1, 2), (1, 2, 0), (2, 0, 1)) else -1.0
    r = quat_to_matrix(q)
    middle = np.arcsin(np.clip(sign * r[..., i, k], -1.0, 1.0))
    first = np.arctan2(-sign * r[..., j, k], r[..., k, k])
    last = np.arctan2(-sign * r[..., i, j], r[..., i, i])
    return np.stack([first, middle, last], axis=-1)


def quat_resample(times: np.ndarray, q: np.ndarray, new_times: np.ndarray) -> np.ndarray:
    """Rotations sampled at ``times`` (increasing), slerped at ``new_times`` (clamped to the sampled range)."""
    times = np.asarray(times, dtype=np.float64)
    q = quat_continuous(quat_normalize(q))
    new_times = np.clip(np.asarray(new_times, dtype=np.float64), times[0], times[-1])
    if len(times) == 1:
        return np.repeat(q, len(new_times), axis=0)
    idx = np.clip(np.searchsorted(times, new_times, side="right") - 1, 0, len(times) - 2)
    span = times[idx + 1] - times[idx]
    frac = np.where(span > 0, (new_times - times[idx]) / np.where(span > 0, span, 1.0), 0.0)
    return quat_continuous(quat_slerp(q[idx], q[idx + 1], frac))


def quat_mean(q: np.ndarray) -> np.ndarray:
    """Chordal L2 mean of unit quaternions (n, 4): the dominant eigenvector of sum q q^T (sign-invariant)."""
    q = quat_normalize(q)
    _, vectors = np.linalg.eigh(q.T @ q)
    mean = vectors[:, -1]
    return mean if mean[0] >= 0 else -mean


def angular_velocity(q: np.ndarray, fps: float) -> np.ndarray:
    """Body-independent angular velocity (frames - 1, 3), radians per second, from consecutive rotations:
    the rotation vector of q[t+1] q[t]^* times the frame rate."""
    q = quat_normalize(q)
    delta = quat_multiply(q[1:], quat_conjugate(q[:-1]))
    return quat_to_rotvec(delta) * fps
