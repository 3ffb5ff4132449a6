"""Motion blending (paper Sec. 5.4): stitch the database motion of the chosen segments into new head motion.

Each chosen segment's motion is resampled to its test segment's length and moved so that it starts where the
previous one ended. Each sub-sentence (bounded by breath pauses) starts at its own segment's recorded pose and is
warped linearly so that it ends where the next sub-sentence starts, which stops drift. Joins are crossfaded over a
short window between the two segments' real continuations in the database, so the velocity passes smoothly from
one segment's to the next's instead of jumping.

Motion is blended as (yaw, pitch, roll) angles and translation: the database is centred on each take's mean pose,
so angles stay small and far from the Euler singularity.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from msflow import Input, Output, Result, Stage, UserError
from stages.rotations import euler_to_quat, quat_to_euler


@dataclass
class DatabaseMotion:
    channels: np.ndarray    # (frames, 6): yaw, pitch, roll (radians), translation x, y, z
    first: np.ndarray       # (sequences,) first frame of each sequence
    frames: np.ndarray      # (sequences,) frame count
    fps: float

    def sample(self, sequence: int, times: np.ndarray) -> np.ndarray:
        """Channels of ``sequence`` at ``times`` (seconds), linearly interpolated, held beyond the take."""
        n = int(self.frames[sequence])
        pos = np.clip(np.asarray(times) * self.fps, 0.0, n - 1)
        below = np.floor(pos).astype(np.int64)
        above = np.minimum(below + 1, n - 1)
        w = (pos - below)[:, None]
        base = int(self.first[sequence])
        return (1 - w) * self.channels[base + below] + w * self.channels[base + above]


def smootherstep(u: np.ndarray) -> np.ndarray:
    """C2 ramp from 0 (u <= 0) to 1 (u >= 1)."""
    u = np.clip(u, 0.0, 1.0)
    return u * u * u * (u * (6 * u - 15) + 10)


@dataclass
class Stitched:
    channels: np.ndarray    # (frames, 6)
    joins: np.ndarray       # times where two chosen segments meet (all boundaries after the first segment)


def stitch_segments(db: DatabaseMotion, test_segments: np.ndarray, subsentence_start: np.ndarray,
                    db_sequence: np.ndarray, db_segments: np.ndarray, times: np.ndarray, *,
                    blend_window: float = 0.15, break_blend_window: float = 0.25,
                    drift_correction: bool = True) -> Stitched:
    """Sec. 5.4 for one utterance. ``test_segments`` (N, 3) and the chosen database segments' sequence (N,) and
    times (N, 3); ``times`` the output frame times. Returns the blended channels on ``times``.

    Joins crossfade over +-``blend_window`` seconds; joins between sub-sentences (searched independently, so
    nothing matched their boundary motion) over +-``break_blend_window``, inside the breath pause."""
    n = len(test_segments)
    out = np.zeros((len(times), db.channels.shape[1]))
    if n == 0:
        return Stitched(out, np.zeros(0))
    a, e = test_segments[:, 0], test_segments[:, 2]
    da, de = db_segments[:, 0], db_segments[:, 2]
    scale = (de - da) / np.maximum(e - a, 1e-9)          # database seconds per output second

    def raw(k: int, t: np.ndarray) -> np.ndarray:
        return db.sample(int(db_sequence[k]), da[k] + (t - a[k]) * scale[k])

    starts = np.asarray(subsentence_start, dtype=bool).copy()
    starts[0] = True
    # chain: each segment starts where the previous one ends; a sub-sentence starts at its recorded pose
    offset = np.zeros((n, out.shape[1]))
    start_value = np.stack([raw(k, a[k:k + 1])[0] for k in range(n)])
    end_value = np.stack([raw(k, e[k:k + 1])[0] for k in range(n)])
    for k in range(1, n):
        if not starts[k]:
            offset[k] = end_value[k - 1] + offset[k - 1] - start_value[k]
    # drift correction: warp each sub-sentence linearly so it ends where the next one starts
    group = np.cumsum(starts) - 1
    first_of = np.flatnonzero(starts)
    last_of = np.append(first_of[1:] - 1, n - 1)
    ramp_total = np.zeros((len(first_of), out.shape[1]))
    if drift_correction:
        for g in range(len(first_of) - 1):
            last, nxt = last_of[g], first_of[g + 1]
            ramp_total[g] = start_value[nxt] - (end_value[last] + offset[last])
    ramp_t0, ramp_t1 = a[first_of], e[last_of]

    # crossfade weights: segment k's indicator [a_k, e_k) with its edges smoothed over +-window of each join,
    # written as ramp_k - ramp_k+1 so that the weights sum to one however close the joins are
    window = np.where(starts, break_blend_window, blend_window)
    window[0] = 0.0

    def ramp(j: int, t: np.ndarray) -> np.ndarray:
        if j == 0:
            return np.ones(len(t))
        if j >= n:
            return np.zeros(len(t))
        if window[j] <= 0:
            return (t >= a[j]).astype(float)
        return smootherstep((t - a[j] + window[j]) / (2 * window[j]))

    total = np.zeros(len(times))
    for k in range(n):
        lo_t = -np.inf if k == 0 else a[k] - window[k]
        hi_t = np.inf if k == n - 1 else e[k] + window[k + 1]
        idx = np.flatnonzero((times >= lo_t) & (times <= hi_t))
        if len(idx) == 0:
            continue
        t = times[idx]
        weight = np.maximum(ramp(k, t) - ramp(k + 1, t), 0.0)
        g = group[k]
        span = max(ramp_t1[g] - ramp_t0[g], 1e-9)
        curve = raw(k, t) + offset[k] + ramp_total[g] * np.clip((t - ramp_t0[g]) / span, 0.0, 1.0)[:, None]
        out[idx] += weight[:, None] * curve
        total[idx] += weight
    out /= np.maximum(total, 1e-12)[:, None]
    return Stitched(out, a[1:].copy())


# ---------------------------------------------------------------------------------- evaluation measures

def angular_speed(angles: np.ndarray, fps: float) -> np.ndarray:
    """Angular speed (frames - 1,) in degrees per second from (yaw, pitch, roll) angles in radians."""
    from stages.rotations import angular_velocity

    q = euler_to_quat(angles[:, 0], angles[:, 1], angles[:, 2])
    return np.degrees(np.linalg.norm(angular_velocity(q, fps), axis=1))


def angular_acceleration(angles: np.ndarray, fps: float) -> np.ndarray:
    """Magnitude of angular acceleration (frames - 2,) in degrees per second^2."""
    from stages.rotations import angular_velocity

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


def wasserstein_speed(angles_a: np.ndarray, angles_b: np.ndarray, fps: float) -> float:
    """Wasserstein-1 distance (deg/s) between the angular-speed distributions of two motions."""
    from scipy.stats import wasserstein_distance

    return float(wasserstein_distance(angular_speed(angles_a, fps), angular_speed(angles_b, fps)))


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


# ---------------------------------------------------------------------------------------------- the stage

MOTION_BLEND_OUTPUTS = {
    "rotation": Output.array("f", shape=("frames", 4), dtype="float64", doc="unit quaternions (stages.rotations)"),
    "translation": Output.array("f", shape=("frames", 3), dtype="float64", doc="offset from the rest position"),
    "angles": Output.array("f", shape=("frames", 3), dtype="float64", doc="yaw, pitch, roll in radians"),
    "time": Output.array("f", shape=("frames",), dtype="float64", doc="seconds since the utterance's start"),
    "sequence": Output.array("i", shape=("frames",), dtype="int32", doc="test utterance (meta labels)"),
    "joins": Output.array("f", shape=("joins",), dtype="float64", doc="join times on each utterance's clock"),
    "join_utterance": Output.array("i", shape=("joins",), dtype="int32"),
    "bvh": Output.file(".bvh", doc="the head joint's motion, utterances back to back"),
}


def _reference_angles(view, label: str, n_labels: int, fps: float) -> np.ndarray | None:
    """The real head motion of ``label`` from a tracking or headdb artifact, centred like the database and
    resampled to ``fps``; None when it has no such sequence."""
    from stages.headdb import center_motion, resample_motion

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


def _plot_head_angles(view, inputs=None):
    """Head yaw, pitch and roll over time: synthesised (and real, when a reference was given); joins marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fps = float(view.meta["fps"])
    labels = view.meta.get("labels", [])
    mask = view["sequence"] == 0
    angles = np.degrees(view["angles"][mask])
    t = view["time"][mask]
    reference = None
    if inputs and inputs.get("reference") is not None and labels:
        ref = _reference_angles(inputs["reference"], labels[0], len(labels), fps)
        reference = None if ref is None else np.degrees(ref)
    joins = view["joins"][view["join_utterance"] == 0]
    fig, axes = plt.subplots(3, 1, figsize=(9, 6), sharex=True, constrained_layout=True)
    for c, (ax, name) in enumerate(zip(axes, ("yaw", "pitch", "roll"))):
        for j in joins:
            ax.axvline(j, color="0.85", lw=0.8, zorder=0)
        ax.plot(t, angles[:, c], color="crimson", lw=1.6, label="synthesised")
        if reference is not None:
            ax.plot(np.arange(len(reference)) / fps, reference[:, c], color="0.25", lw=1.2, label="real")
        ax.set_ylabel(f"{name} (deg)")
    axes[0].legend(loc="upper right", fontsize=8)
    axes[0].set_title(f"head angles: {labels[0] if labels else ''} (grey lines: segment joins)")
    axes[-1].set_xlabel("time (s)")
    return fig


class MotionBlend(Stage):
    """Stitch, drift-correct and crossfade the chosen database motion (Sec. 5.4); head rotation, translation and
    a BVH of the head joint at the output rate."""

    class Params(Stage.Params):
        fps: float | None = None          # output rate; None: the test take's video rate, else the database's
        blend_window: float = 0.15        # seconds either side of a join to crossfade over
        break_blend_window: float = 0.25  # the same at joins between sub-sentences (breath pauses)
        drift_correction: bool = True     # warp each sub-sentence to meet the next
        translation: bool = True          # False: rotation only (translation zero)
        bvh_joint: str = "Head"
        bvh_order: str = "ZXY"            # Euler channel order written to the BVH

    inputs = {
        "trellis": Input.artifact("segments", "chosen", "db_segments", "db_segment_sequence"),
        "database": Input.artifact("angles", "translation", "sequence", doc="the headdb artifact searched"),
        "reference": Input.artifact("rotation", "sequence", optional=True,
                                    doc="real motion of the test take (tracking artifact) for the figure and "
                                        "metrics"),
    }
    outputs = MOTION_BLEND_OUTPUTS
    figures = {"head_angles": _plot_head_angles}

    def run(self, params, inputs):
        from stages.bvh import head_bvh

        trellis, database = inputs["trellis"], inputs["database"]
        db_labels = list(database.meta.get("labels") or [])
        if trellis.meta.get("db_labels") is not None and list(trellis.meta["db_labels"]) != db_labels:
            raise UserError("the trellis was searched over a different database than the one given",
                            field="inputs.database")
        if params.blend_window < 0 or params.break_blend_window < 0:
            raise UserError("blend_window must be >= 0", field="params.blend_window")
        db = database_motion(database, use_translation=params.translation)
        labels = list(trellis.meta.get("labels") or [])
        test_fps = [f for f in (trellis.meta.get("fps") or []) if f]
        fps = float(params.fps or (test_fps[0] if test_fps else db.fps))
        if not fps > 0:
            raise UserError(f"fps must be positive, got {fps}", field="params.fps")
        synth = synthesise(trellis, db, fps, blend_window=params.blend_window,
                           break_blend_window=params.break_blend_window, drift_correction=params.drift_correction)
        angles = np.concatenate([s[0][:, :3] for s in synth]) if synth else np.zeros((0, 3))
        translation = np.concatenate([s[0][:, 3:] for s in synth]) if synth else np.zeros((0, 3))
        rotation = euler_to_quat(angles[:, 0], angles[:, 1], angles[:, 2])
        arrays = {
            "rotation": rotation, "translation": translation, "angles": angles,
            "time": np.concatenate([np.arange(len(s[0])) / fps for s in synth]),
            "sequence": np.concatenate([np.full(len(s[0]), u, np.int32) for u, s in enumerate(synth)]),
            "joins": np.concatenate([s[1] for s in synth]),
            "join_utterance": np.concatenate([np.full(len(s[1]), u, np.int32) for u, s in enumerate(synth)]),
            "bvh": head_bvh(rotation, translation, fps, joint=params.bvh_joint, order=params.bvh_order).encode(),
        }
        metrics = motion_metrics(arrays, fps, params.blend_window, inputs.get("reference"), labels)
        meta = {"fps": fps, "labels": labels, "frames": [len(s[0]) for s in synth],
                "translation_units": database.meta.get("translation_units", "unknown"),
                "bvh_joint": params.bvh_joint, "db_labels": db_labels}
        return Result(arrays, meta, metrics)


def database_motion(view, *, use_translation: bool = True) -> DatabaseMotion:
    sequence = np.asarray(view["sequence"], dtype=np.int64)
    n_seq = int(sequence.max()) + 1 if len(sequence) else 0
    frames = np.bincount(sequence, minlength=n_seq)
    translation = np.asarray(view["translation"], dtype=np.float64)
    channels = np.concatenate([np.asarray(view["angles"], dtype=np.float64),
                               translation if use_translation else np.zeros_like(translation)], axis=1)
    if not np.isfinite(channels).all():
        raise UserError("NaN in the database motion", field="inputs.database")
    return DatabaseMotion(channels, np.concatenate([[0], np.cumsum(frames)[:-1]]), frames, float(view.meta["fps"]))


def synthesise(trellis, db: DatabaseMotion, fps: float, *, blend_window: float = 0.15,
               break_blend_window: float = 0.25,
               drift_correction: bool = True) -> list[tuple[np.ndarray, np.ndarray]]:
    """Blended channels and join times per test utterance of a trellis artifact (a still head where silent)."""
    labels = list(trellis.meta.get("labels") or [])
    durations = trellis.meta.get("durations") or []
    test_fps = trellis.meta.get("fps") or [None] * len(labels)
    test_frames = trellis.meta.get("frames") or [None] * len(labels)
    segments = np.asarray(trellis["segments"]).reshape(-1, 3)
    seg_utt = np.asarray(trellis["segment_utterance"])
    chosen = np.asarray(trellis["chosen"], dtype=np.int64)
    db_seq = np.asarray(trellis["db_segment_sequence"], dtype=np.int64)
    db_segments = np.asarray(trellis["db_segments"]).reshape(-1, 3)
    out = []
    for u in range(len(labels)):
        if test_frames[u] and test_fps[u] and abs(float(test_fps[u]) - fps) < 1e-6:
            n_frames = int(test_frames[u])
        else:
            n_frames = int(round(float(durations[u]) * fps))
        rows = np.flatnonzero(seg_utt == u)
        stitched = stitch_segments(db, segments[rows], np.asarray(trellis["subsentence_start"])[rows],
                                   db_seq[chosen[rows]], db_segments[chosen[rows]], np.arange(n_frames) / fps,
                                   blend_window=blend_window, break_blend_window=break_blend_window,
                                   drift_correction=drift_correction)
        out.append((stitched.channels, stitched.joins))
    return out


def motion_metrics(arrays: dict, fps: float, window: float, reference, labels: list[str]) -> dict:
    """Speed and join smoothness of the synthesis; against the real motion when a reference is given."""
    metrics = {}
    speeds, join_acc, ref_speed, ref_acc99, w1 = [], [], [], [], []
    for u in range(len(labels)):
        mask = arrays["sequence"] == u
        angles = arrays["angles"][mask]
        if len(angles) < 3:
            continue
        speeds.append(angular_speed(angles, fps))
        join_acc.append(join_acceleration(angles, fps, arrays["joins"][arrays["join_utterance"] == u],
                                          max(window, 1.0 / fps)))
        if reference is not None:
            real = _reference_angles(reference, labels[u], len(labels), fps)
            if real is not None and len(real) >= 3:
                ref_speed.append(angular_speed(real, fps))
                ref_acc99.append(np.percentile(angular_acceleration(real, fps), 99))
                w1.append(wasserstein_speed(angles, real, fps))
    if speeds:
        metrics["mean_angular_speed"] = float(np.mean(np.concatenate(speeds)))
    joins = np.concatenate(join_acc) if join_acc else np.zeros(0)
    if len(joins):
        metrics["max_join_acceleration"] = float(joins.max())
    if ref_speed:
        metrics["real_mean_angular_speed"] = float(np.mean(np.concatenate(ref_speed)))
        metrics["real_acceleration_p99"] = float(np.max(ref_acc99))
        metrics["speed_wasserstein"] = float(np.mean(w1))
    return metrics
