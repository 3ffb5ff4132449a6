"""Rotation conventions shared by every stage that touches head motion. All functions are vectorised.

Quaternions are unit (w, x, y, z), arrays of shape (..., 4), acting on column vectors (v' = q v q*).

The head frame is glTF's: x to the viewer's right, y up, z towards the viewer (camera); the identity rotation is a
head facing the camera upright. Euler angles (radians) decompose R = Ry(yaw) @ Rx(pitch) @ Rz(roll):
yaw about +y, pitch about +x, roll about +z, right-handed. Mirroring the motion about the face's mid-plane
(x -> -x) negates yaw and roll and leaves pitch.

Conversions and products go through ``scipy.spatial.transform.Rotation`` (scalar-first quaternions; its
intrinsic upper-case Euler sequences are this module's orders: "YXZ" is R = Ry Rx Rz). Its results equal the
closed forms this module used before to within 1e-14, signs included; at gimbal lock (pitch = +-pi/2) scipy sets
the last angle to 0 and its warning is silenced. Interpolation (slerp, resampling), sign continuity and
mirroring stay here.
"""

from __future__ import annotations

import warnings

import numpy as np


def _rotation(q: np.ndarray):
    """scipy Rotation of (..., 4) (w, x, y, z) quaternions (normalised by scipy)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(np.asarray(q, dtype=np.float64), scalar_first=True)


def _quat(rotation) -> np.ndarray:
    return rotation.as_quat(scalar_first=True)


def _euler(rotation, order: str) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Gimbal lock detected", category=UserWarning)
        return rotation.as_euler(order)


def quat_normalize(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a*b (apply b, then a), broadcasting over leading axes."""
    a, b = np.broadcast_arrays(np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64))
    from scipy.spatial.transform import Rotation

    # Rotation composition normalises; the product of unit quaternions is unit anyway, and for exactness with
    # non-unit inputs the norms are multiplied back
    norms = np.linalg.norm(a, axis=-1, keepdims=True) * np.linalg.norm(b, axis=-1, keepdims=True)
    product = Rotation.from_quat(a, scalar_first=True) * Rotation.from_quat(b, scalar_first=True)
    return _quat(product) * norms


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices of (..., 4) quaternions (normalised first)."""
    return _rotation(q).as_matrix()


def matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) to unit quaternions with w >= 0."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(m, dtype=np.float64)).as_quat(scalar_first=True, canonical=True)


def rotvec_to_quat(v: np.ndarray) -> np.ndarray:
    """Unit quaternions of rotation vectors (axis times angle in radians), (..., 3) -> (..., 4)."""
    from scipy.spatial.transform import Rotation

    return _quat(Rotation.from_rotvec(np.asarray(v, dtype=np.float64)))


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    """Rotation vectors of quaternions, the angle in [0, pi] (q and -q give the same vector)."""
    return _rotation(q).as_rotvec()


def euler_to_quat(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """q = qy(yaw) * qx(pitch) * qz(roll), the module's Euler convention."""
    from scipy.spatial.transform import Rotation

    angles = np.stack(np.broadcast_arrays(*(np.asarray(v, dtype=np.float64) for v in (yaw, pitch, roll))), axis=-1)
    return _quat(Rotation.from_euler("YXZ", angles))


def quat_to_euler(q: np.ndarray) -> np.ndarray:
    """(..., 3) array of (yaw, pitch, roll) with R = Ry(yaw) Rx(pitch) Rz(roll); pitch in [-pi/2, pi/2]."""
    return _euler(_rotation(q), "YXZ")


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
    from scipy.spatial.transform import Rotation

    _check_order(order)
    return _quat(Rotation.from_euler(order.upper(), np.asarray(angles, dtype=np.float64)))


def quat_to_euler_order(q: np.ndarray, order: str) -> np.ndarray:
    """Inverse of ``euler_order_to_quat``: (..., 3) angles with the middle angle in [-pi/2, pi/2]."""
    _check_order(order)
    return _euler(_rotation(q), order.upper())


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
    """Chordal L2 mean of unit quaternions (n, 4): the dominant eigenvector of sum q q^T (sign-invariant),
    with w >= 0."""
    mean = _quat(_rotation(q).mean())
    return mean if mean[0] >= 0 else -mean


def angular_velocity(q: np.ndarray, fps: float) -> np.ndarray:
    """Body-independent angular velocity (frames - 1, 3), radians per second, from consecutive rotations:
    the rotation vector of q[t+1] q[t]^* times the frame rate."""
    rotations = _rotation(q)
    return (rotations[1:] * rotations[:-1].inv()).as_rotvec() * fps
