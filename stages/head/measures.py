"""Measures of head motion shared by the blend's own metrics and the evaluation stage (stages.eval.head).

Motion is (frames, 3) yaw, pitch, roll in radians at ``fps``, centred on the take's mean pose (the database's
convention), so angle rates are close to the angular velocity.
"""

from __future__ import annotations

import numpy as np

from stages.geometry.rotations import angular_velocity, euler_to_quat, quat_to_euler

JOIN_MEASURE_WINDOW = 0.15  # seconds either side of a join over which join acceleration is measured (fixed, so
#                              that every smoothing method and parameter is measured alike)


def reference_angles(view, label: str, n_labels: int, fps: float) -> np.ndarray | None:
    """The real head motion of ``label`` from a tracking or headdb artifact, centred like the database and
    resampled to ``fps``; None when it has no such sequence."""
    from stages.head.database import center_motion, resample_motion

    labels = list(view.meta.get("labels") or [])
    if label in labels:
        k = labels.index(label)
    elif len(labels) <= 1 and n_labels == 1:
        k = 0
    else:
        return None
    mask = np.asarray(view["sequence"]) == k
    rotation = np.asarray(view["rotation"])[mask]
    translation = np.asarray(view["translation"])[mask] if "translation" in view else np.zeros((mask.sum(), 3))
    if "time" in view:
        time = np.asarray(view["time"])[mask]
    else:
        src_fps = view.meta.get("fps")
        src_fps = src_fps[k] if isinstance(src_fps, list) else src_fps
        time = np.arange(mask.sum()) / float(src_fps or fps)
    if len(time) < 2:
        return None
    _, rot, trans = resample_motion(time, rotation, translation, fps)
    rot, _ = center_motion(rot, trans)
    return quat_to_euler(rot)


def lowpass_angles(angles: np.ndarray, fps: float, cutoff: float) -> np.ndarray:
    """(yaw, pitch, roll) angles low-passed at ``cutoff`` Hz with the database's jitter filter
    (stages.head.database.lowpass_motion, on the quaternions)."""
    from stages.head.database import lowpass_motion

    q = euler_to_quat(angles[:, 0], angles[:, 1], angles[:, 2])
    filtered, _ = lowpass_motion(q, np.zeros((len(q), 3)), fps, cutoff)
    return quat_to_euler(filtered)


def angular_speed(angles: np.ndarray, fps: float) -> np.ndarray:
    """Angular speed (frames - 1,) in degrees per second from (yaw, pitch, roll) angles in radians."""
    q = euler_to_quat(angles[:, 0], angles[:, 1], angles[:, 2])
    return np.degrees(np.linalg.norm(angular_velocity(q, fps), axis=1))


def angular_acceleration(angles: np.ndarray, fps: float) -> np.ndarray:
    """Magnitude of angular acceleration (frames - 2,) in degrees per second^2."""
    q = euler_to_quat(angles[:, 0], angles[:, 1], angles[:, 2])
    w = angular_velocity(q, fps)
    return np.degrees(np.linalg.norm(np.diff(w, axis=0) * fps, axis=1))


def join_acceleration(angles: np.ndarray, fps: float, joins: np.ndarray, window: float) -> np.ndarray:
    """Largest angular acceleration within +-``window`` seconds of each join (deg/s^2), one value per join."""
    acc = angular_acceleration(angles, fps)
    if len(acc) == 0 or len(joins) == 0:
        return np.zeros(0)
    t = (np.arange(len(acc)) + 1) / fps
    inside = np.abs(t[None, :] - np.asarray(joins)[:, None]) <= window
    return np.where(inside, acc[None, :], 0.0).max(axis=1)


def wasserstein(a: np.ndarray, b: np.ndarray) -> float:
    """Wasserstein-1 distance between two samples of a scalar (their distributions' earth mover's distance)."""
    from scipy.stats import wasserstein_distance

    if len(a) == 0 or len(b) == 0:
        return float("nan")
    return float(wasserstein_distance(a, b))


def wasserstein_speed(angles_a: np.ndarray, angles_b: np.ndarray, fps: float) -> float:
    """Wasserstein-1 distance (deg/s) between the angular-speed distributions of two motions."""
    return wasserstein(angular_speed(angles_a, fps), angular_speed(angles_b, fps))


def percentile_range(angles: np.ndarray, low: float = 5.0, high: float = 95.0) -> np.ndarray:
    """(2, 3) the ``low`` and ``high`` percentiles of each angle, in degrees."""
    return np.percentile(np.degrees(angles), [low, high], axis=0)


def linear_drift(angles: np.ndarray, fps: float) -> float:
    """Largest change over the motion of a least-squares line through any one angle (degrees): how far the motion
    wanders off in one direction (slope times duration)."""
    n = len(angles)
    if n < 2:
        return 0.0
    t = np.arange(n) / fps
    t = t - t.mean()
    slope = (t @ (np.degrees(angles) - np.degrees(angles).mean(axis=0))) / (t @ t)
    return float(np.abs(slope).max() * (n - 1) / fps)


def pitch_velocity_correlation(angles: np.ndarray, fps: float, f0_time: np.ndarray, f0_semitones: np.ndarray) -> float:
    """Pearson correlation between the voice pitch (semitones, voiced frames only) and the head-pitch velocity
    at the same times. NaN when fewer than 3 voiced frames overlap the motion."""
    velocity = np.gradient(angles[:, 1]) * fps
    t = np.arange(len(angles)) / fps
    ok = np.isfinite(f0_semitones) & (f0_time >= t[0]) & (f0_time <= t[-1])
    if ok.sum() < 3:
        return float("nan")
    v = np.interp(f0_time[ok], t, velocity)
    p = f0_semitones[ok]
    if v.std() < 1e-12 or p.std() < 1e-12:
        return 0.0
    return float(np.corrcoef(p, v)[0, 1])
