"""Stitching (paper Sec. 5.4): the database motion of the chosen segments joined into new head motion.

Each chosen segment's motion is resampled to its test segment's length and moved so that it starts where the
previous one ended. Each sub-sentence (bounded by breath pauses) starts at its own segment's recorded pose and is
warped linearly so that it ends where the next sub-sentence starts, which stops drift. Finally "the end positions
where the segments are connected are smoothed to minimize high frequency artifact caused by a mismatch in the
velocity" -- the paper does not say how; here (``join_smoothing="velocity"``, the default):

- the blend works on velocities, not positions: the output's frame-to-frame increments are a smoothstep
  partition-of-unity mix of the joined segments' own increments (each segment continued by its real database
  continuation), integrated from the anchors. Position is continuous by construction and the velocity passes from
  one segment's to the next's along a smoothstep, so the acceleration stays continuous and the velocity never
  overshoots. The earlier position crossfade (``join_smoothing="crossfade"``, kept for comparison) matched position
  at the join but overshot the velocity inside its window by w'(t) (x_next - x_prev), which added about
  2 x 1.875 dv / (2 W) of acceleration at every join -- what made synthesised joins rougher than real motion;
- each join's window is chosen from its velocity step dv (the same parabola-fit velocities that the trellis's H
  compares): at least +-``blend_window``, widened so that the step adds at most ``join_acceleration`` (default:
  half the database's median angular acceleration), up to +-``max_blend_window``;
- the linear drift warp is a constant velocity added to a sub-sentence's segments, blended at its ends like any
  other velocity, so it adds no velocity kink at sub-sentence boundaries;
- optionally (``preserve_speed``) the blended velocity is rescaled to keep the speed of the joined segments where
  their motions are unrelated (a plain average of two unrelated velocities is slower than either).

Head strokes moved onto the test audio's onsets (``warp_time``, ``segment_knots``) are here too; the amplitude
match is in ``stages.head.amplitude``, the stage in ``stages.head.motion_blend``.

Motion is blended as (yaw, pitch, roll) angles and translation: the database is centred on each take's mean pose,
so angles stay small and far from the Euler singularity, where angle rates are close to the angular velocity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.geometry.ramps import smoothstep
from stages.head.measures import angular_acceleration


@dataclass
class DatabaseMotion:
    channels: np.ndarray  # (frames, 6): yaw, pitch, roll (radians), translation x, y, z
    first: np.ndarray  # (sequences,) first frame of each sequence
    frames: np.ndarray  # (sequences,) frame count
    fps: float
    speakers: list | None = None  # (sequences,) speaker labels, when known

    def sample(self, sequence: int, times: np.ndarray) -> np.ndarray:
        """Channels of ``sequence`` at ``times`` (seconds), linearly interpolated, held beyond the take."""
        n = int(self.frames[sequence])
        pos = np.clip(np.asarray(times) * self.fps, 0.0, n - 1)
        below = np.floor(pos).astype(np.int64)
        above = np.minimum(below + 1, n - 1)
        w = (pos - below)[:, None]
        base = int(self.first[sequence])
        return (1 - w) * self.channels[base + below] + w * self.channels[base + above]

    def typical_acceleration(self) -> float:
        """Median angular acceleration of the database motion (deg/s^2), the yardstick for what a join may add."""
        values = []
        for first, n in zip(self.first, self.frames):
            if n >= 3:
                values.append(angular_acceleration(self.channels[first : first + n, :3], self.fps))
        return float(np.median(np.concatenate(values))) if values else 0.0

    def sequence_of_frames(self) -> np.ndarray:
        return np.repeat(np.arange(len(self.frames)), self.frames)

    def scaled(self, gains: np.ndarray) -> DatabaseMotion:
        """The database with each sequence's channels multiplied by its row of ``gains`` (sequences, channels)."""
        channels = self.channels * gains[self.sequence_of_frames()]
        return DatabaseMotion(channels, self.first, self.frames, self.fps, self.speakers)


JOIN_BUDGET_OF_MEDIAN = 0.5  # default acceleration a join's velocity step may add, as a fraction of the
#                               database's median angular acceleration (bench/eval_head.py: with it the largest
#                               join acceleration stays below the held-out real motion's 99th percentile)


def smootherstep(u: np.ndarray) -> np.ndarray:
    """C2 ramp from 0 (u <= 0) to 1 (u >= 1)."""
    u = np.clip(u, 0.0, 1.0)
    return u * u * u * (u * (6 * u - 15) + 10)


@dataclass
class Stitched:
    channels: np.ndarray  # (frames, 6)
    joins: np.ndarray  # times where two chosen segments meet (all boundaries after the first segment)
    windows: np.ndarray  # (joins, 2) start and end of each join's blend (seconds)
    velocity_mismatch: np.ndarray  # (joins,) angular velocity step the join had to absorb (deg/s, output clock)


def join_velocity_mismatch(
    db: DatabaseMotion,
    prev_sequence: np.ndarray,
    prev_time: np.ndarray,
    prev_scale: np.ndarray,
    next_sequence: np.ndarray,
    next_time: np.ndarray,
    next_scale: np.ndarray,
    window: float = 0.1,
) -> np.ndarray:
    """Velocity step (joins, channels) per output second between the outgoing segment's continuation (database
    ``prev_time``) and the incoming segment's start (``next_time``), each time-warped by its ``scale`` (database
    seconds per output second). Velocities are the same least-squares parabola fits over +-``window`` database
    seconds that the trellis's transition cost H uses (stages.head.search.boundary_kinematics)."""
    from stages.head.search import boundary_kinematics

    if len(prev_time) == 0:
        return np.zeros((0, db.channels.shape[1]))
    kin = lambda seq, t: boundary_kinematics(
        db.channels, db.first, db.frames, db.fps, np.asarray(seq, np.int64), np.asarray(t, np.float64), window
    )[:, 1, :]
    return (
        kin(next_sequence, next_time) * np.asarray(next_scale)[:, None]
        - kin(prev_sequence, prev_time) * np.asarray(prev_scale)[:, None]
    )


def join_windows(
    join_times: np.ndarray,
    half: np.ndarray,
    mismatch_deg: np.ndarray | None = None,
    *,
    acceleration_budget: float | None = None,
    max_half: float = 0.5,
) -> tuple[np.ndarray, np.ndarray]:
    """Start and end of each join's velocity blend.

    A smoothstep velocity blend over a window of length 2W passes a velocity step dv with an added acceleration of
    at most 1.5 dv / (2 W); with an ``acceleration_budget`` (deg/s^2) each half-window is widened from ``half`` to
    0.75 dv / budget, at most ``max_half``. The windows' starts and ends are then made non-decreasing (by widening),
    which keeps every segment's blend weight in [0, 1] however the windows overlap."""
    half = np.asarray(half, dtype=np.float64).copy()
    if acceleration_budget is not None and acceleration_budget > 0 and mismatch_deg is not None:
        wanted = 0.75 * np.asarray(mismatch_deg) / acceleration_budget
        half = np.maximum(half, np.minimum(wanted, np.maximum(max_half, half)))
    left, right = join_times - half, join_times + half
    if len(left):
        left = np.minimum.accumulate(left[::-1])[::-1]
        right = np.maximum.accumulate(right)
    return left, right


def segment_weights(x: np.ndarray, k: int, left: np.ndarray, right: np.ndarray, join_times: np.ndarray) -> np.ndarray:
    """Blend weight of segment k at times x: ramp_k - ramp_k+1, where ramp_j rises over join j's window (a step at
    join j when the window is empty). Weights of all segments sum to one."""

    def ramp(j: int) -> np.ndarray:
        if j == 0:
            return np.ones(len(x))
        if j > len(join_times):
            return np.zeros(len(x))
        lo, hi = left[j - 1], right[j - 1]
        if hi - lo <= 1e-12:
            return (x >= join_times[j - 1]).astype(float)
        return smoothstep((x - lo) / (hi - lo))

    return np.clip(ramp(k) - ramp(k + 1), 0.0, 1.0)


def monotone_slopes(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Knot slopes of a monotone C1 cubic through increasing knots (Fritsch & Butland 1984): inside, the weighted
    harmonic mean of the two neighbouring secants, which lies between them and keeps the cubic monotone; at the
    ends, the end piece's own secant."""
    h, m = np.diff(x), np.diff(y) / np.maximum(np.diff(x), 1e-12)
    d = np.empty(len(x))
    d[0], d[-1] = m[0], m[-1]
    w1, w2 = 2 * h[1:] + h[:-1], h[1:] + 2 * h[:-1]
    d[1:-1] = (w1 + w2) / (w1 / np.maximum(m[:-1], 1e-12) + w2 / np.maximum(m[1:], 1e-12))
    return d


def warp_time(t: np.ndarray, test_knots: np.ndarray, db_knots: np.ndarray, kind: str = "monotone") -> np.ndarray:
    """Database time of output times ``t`` under a map through the knots (test time -> database time).

    ``kind="monotone"``: a monotone C1 cubic (``monotone_slopes``), continued beyond the first and last knot at its
    end slopes, so the playback rate changes smoothly and a moved stroke adds no velocity step (a piecewise-linear
    map changes the rate abruptly at each knot, which steps the velocity by v times the rate change: an
    acceleration spike at the very stroke it moved). ``"linear"``: piecewise linear, continued at the segment's
    average rate (the earlier map, kept for comparison). With two knots both are the uniform map."""
    t = np.asarray(t, dtype=np.float64)
    x, y = np.asarray(test_knots, dtype=np.float64), np.asarray(db_knots, dtype=np.float64)
    if kind == "linear" or len(x) == 2:
        rate = (y[-1] - y[0]) / max(x[-1] - x[0], 1e-9)
        before, after = rate, rate
        inside = np.interp(t, x, y)
    else:
        from scipy.interpolate import CubicHermiteSpline

        slopes = monotone_slopes(x, y)
        before, after = slopes[0], slopes[-1]
        inside = CubicHermiteSpline(x, y, slopes)(np.clip(t, x[0], x[-1]))
    return np.where(t < x[0], y[0] + (t - x[0]) * before, np.where(t > x[-1], y[-1] + (t - x[-1]) * after, inside))


def segment_knots(
    test_segment: tuple[float, float],
    db_segment: tuple[float, float],
    test_events: np.ndarray,
    db_events: np.ndarray,
    *,
    tolerance: float,
    max_stretch: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Knots of a time map that keeps the segment's ends (Sec. 5.4: onset to onset) and moves each database event
    inside it onto the nearest test event, when that is within ``tolerance`` seconds of where uniform resampling
    would put it and no piece of the map plays faster or slower than ``max_stretch`` times the uniform rate.
    Events are matched in time order, each test event at most once."""
    (a, e), (da, de) = test_segment, db_segment
    rate = (de - da) / max(e - a, 1e-9)
    knots_t, knots_d = [a], [da]
    free = np.sort(np.asarray(test_events, dtype=np.float64))
    for tau in np.sort(np.asarray(db_events, dtype=np.float64)):
        if not da < tau < de:
            continue
        uniform = a + (tau - da) / rate
        options = free[(free > knots_t[-1]) & (free < e) & (np.abs(free - uniform) <= tolerance)]
        if not len(options):
            continue
        t = float(options[np.argmin(np.abs(options - uniform))])
        before = (tau - knots_d[-1]) / max(t - knots_t[-1], 1e-9)
        after = (de - tau) / max(e - t, 1e-9)
        if all(rate / max_stretch <= r <= rate * max_stretch for r in (before, after)):
            knots_t.append(t)
            knots_d.append(float(tau))
    knots_t.append(e)
    knots_d.append(de)
    return np.array(knots_t), np.array(knots_d)


def stitch_segments(
    db: DatabaseMotion,
    test_segments: np.ndarray,
    subsentence_start: np.ndarray,
    db_sequence: np.ndarray,
    db_segments: np.ndarray,
    times: np.ndarray,
    *,
    blend_window: float = 0.15,
    break_blend_window: float = 0.25,
    drift_correction: bool = True,
    smoothing: str = "velocity",
    acceleration_budget: float | None = None,
    max_blend_window: float = 0.5,
    preserve_speed: bool = False,
    boundary_window: float = 0.1,
    time_maps: list[tuple[np.ndarray, np.ndarray]] | None = None,
    warp: str = "monotone",
) -> Stitched:
    """Sec. 5.4 for one utterance. ``test_segments`` (N, 3) and the chosen database segments' sequence (N,) and
    times (N, 3); ``times`` the output frame times (increasing). Returns the blended channels on ``times``.

    Each segment's motion is resampled to its test segment's length; each segment starts where the previous one
    ended; each sub-sentence starts at its first segment's recorded pose and (``drift_correction``) is warped
    linearly so that it ends where the next sub-sentence starts.

    ``smoothing="velocity"`` (default) smooths the joins in the velocity domain: the output's frame-to-frame
    increments are a partition-of-unity blend of the segments' own increments (each segment continued by its real
    database continuation), integrated from the anchors. Position is continuous by construction, velocity passes
    from one segment's to the next's along a smoothstep (so acceleration stays continuous), and a segment that is
    the database continuation of the previous one at the same time scale is reproduced exactly. The linear warp of
    each sub-sentence is a constant velocity added to its segments, blended at its ends like any other velocity.
    Windows are +-``blend_window`` (+-``break_blend_window`` at sub-sentence joins, inside the breath pause), widened
    up to ``max_blend_window`` where the velocity step would otherwise add more than ``acceleration_budget``
    (deg/s^2; None: fixed windows).

    ``smoothing="crossfade"`` is the earlier position crossfade (kept for comparison): it matches position at the
    join but overshoots the velocity inside the window, adding about 2 * 1.875 dv / (2 W) of acceleration."""
    if smoothing == "crossfade":
        return crossfade_segments(
            db,
            test_segments,
            subsentence_start,
            db_sequence,
            db_segments,
            times,
            blend_window=blend_window,
            break_blend_window=break_blend_window,
            drift_correction=drift_correction,
        )
    if smoothing != "velocity":
        raise ValueError(f"unknown join smoothing {smoothing!r}")
    times = np.asarray(times, dtype=np.float64)
    out = np.zeros((len(times), db.channels.shape[1]))
    if len(test_segments) == 0:
        return Stitched(out, np.zeros(0), np.zeros((0, 2)), np.zeros(0))
    chosen = ChosenMotion(db, test_segments, db_segments, np.asarray(db_sequence, dtype=np.int64), time_maps, warp)
    starts = np.asarray(subsentence_start, dtype=bool).copy()
    starts[0] = True
    joins, left, right, dv_deg = velocity_blend_windows(
        chosen, starts, blend_window, break_blend_window, acceleration_budget, max_blend_window, boundary_window
    )
    windows = np.stack([left, right], axis=1)
    if len(times) < 2:
        out[:1] = chosen.raw(0, times)[:1]
        return Stitched(out, joins, windows, dv_deg)
    base, drift = blended_increments(chosen, times, starts, left, right, joins, preserve_speed)
    out = anchor_subsentences(chosen, times, starts, base, drift, drift_correction)
    return Stitched(out, joins, windows, dv_deg)


@dataclass
class ChosenMotion:
    """The chosen database segments of one utterance, each resampled onto its test segment (Sec. 5.4)."""

    db: DatabaseMotion
    test_segments: np.ndarray  # (N, 3) start, voiced end, end (output seconds)
    db_segments: np.ndarray  # (N, 3) the same in database seconds
    sequence: np.ndarray  # (N,) database sequence of each
    time_maps: list | None = None  # per segment (test knots, database knots); None: uniform
    warp: str = "monotone"  # interpolation of the time maps (warp_time)

    @property
    def scale(self) -> np.ndarray:
        """Database seconds per output second of each segment's uniform resampling."""
        return (self.db_segments[:, 2] - self.db_segments[:, 0]) / np.maximum(
            self.test_segments[:, 2] - self.test_segments[:, 0], 1e-9
        )

    def raw(self, k: int, t: np.ndarray) -> np.ndarray:
        """Channels of segment ``k``'s database motion at output times ``t`` (continued beyond its ends)."""
        if self.time_maps is None:
            db_time = self.db_segments[k, 0] + (t - self.test_segments[k, 0]) * self.scale[k]
        else:
            db_time = warp_time(t, *self.time_maps[k], kind=self.warp)
        return self.db.sample(int(self.sequence[k]), db_time)


def velocity_blend_windows(
    chosen: ChosenMotion,
    starts: np.ndarray,
    blend_window: float,
    break_blend_window: float,
    acceleration_budget: float | None,
    max_blend_window: float,
    boundary_window: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Join times (each segment's start after the first), their blend windows (left, right) sized from the
    velocity step each join absorbs (``join_windows``), and that step (deg/s)."""
    a, da, de, scale, seq = (
        chosen.test_segments[:, 0],
        chosen.db_segments[:, 0],
        chosen.db_segments[:, 2],
        chosen.scale,
        chosen.sequence,
    )
    joins = a[1:].copy()
    dv = join_velocity_mismatch(chosen.db, seq[:-1], de[:-1], scale[:-1], seq[1:], da[1:], scale[1:], boundary_window)
    dv_deg = np.degrees(np.linalg.norm(dv[:, :3], axis=1))
    half = np.where(starts[1:], break_blend_window, blend_window)
    left, right = join_windows(joins, half, dv_deg, acceleration_budget=acceleration_budget, max_half=max_blend_window)
    return joins, left, right, dv_deg


def blended_increments(
    chosen: ChosenMotion,
    times: np.ndarray,
    starts: np.ndarray,
    left: np.ndarray,
    right: np.ndarray,
    joins: np.ndarray,
    preserve_speed: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """The integrated blend of the segments' own frame-to-frame increments, weighted by a smoothstep partition of
    unity over the join windows (``base``, frames x channels, 0 at the first frame), and per sub-sentence the
    integrated time its weight was active (``drift``, frames x sub-sentences: what a constant drift velocity of that
    sub-sentence adds by each frame)."""
    mid = 0.5 * (times[1:] + times[:-1])
    step = np.diff(times)
    channels = chosen.db.channels.shape[1]
    group = np.cumsum(starts) - 1
    increments = np.zeros((len(mid), channels))
    group_weight = np.zeros((len(mid), int(group[-1]) + 1))
    bounds_lo = np.concatenate([[-np.inf], left])
    bounds_hi = np.concatenate([right, [np.inf]])
    parts = []  # (first step, weights, increments) per segment
    for k in range(len(chosen.sequence)):
        idx = np.flatnonzero((mid >= bounds_lo[k]) & (mid <= bounds_hi[k]))
        if len(idx) == 0:
            parts.append((0, np.zeros(0), np.zeros((0, channels))))
            continue
        w = segment_weights(mid[idx], k, left, right, joins)
        delta = chosen.raw(k, times[idx + 1]) - chosen.raw(k, times[idx])
        parts.append((int(idx[0]), w, delta))
        increments[idx] += w[:, None] * delta
        group_weight[idx, group[k]] += w * step[idx]
    if preserve_speed:
        increments *= speed_preserving_gain(parts, len(mid))[:, None]
    base = np.concatenate([np.zeros((1, channels)), np.cumsum(increments, axis=0)])
    drift = np.concatenate([np.zeros((1, group_weight.shape[1])), np.cumsum(group_weight, axis=0)])
    return base, drift


def anchor_subsentences(
    chosen: ChosenMotion,
    times: np.ndarray,
    starts: np.ndarray,
    base: np.ndarray,
    drift: np.ndarray,
    drift_correction: bool,
) -> np.ndarray:
    """Place the integrated blend so that every sub-sentence starts at its first segment's recorded pose: with
    ``drift_correction``, x = c + base + sum_g d_g drift_g, one constant and one drift velocity per sub-sentence
    but the last (Sec. 5.4's linear warp, as a velocity); without it, each sub-sentence is offset on its own and the
    head jumps between sub-sentences."""
    n_groups = drift.shape[1]
    first_of = np.flatnonzero(starts)
    anchor_t = chosen.test_segments[first_of, 0]
    target = np.stack([chosen.raw(k, anchor_t[i : i + 1])[0] for i, k in enumerate(first_of)])

    def at(curve):
        return np.stack([np.interp(anchor_t, times, curve[:, c]) for c in range(curve.shape[1])], axis=1)

    base_at = at(base)
    if drift_correction:
        system = np.concatenate([np.ones((n_groups, 1)), at(drift)[:, : n_groups - 1]], axis=1)
        solution = np.linalg.lstsq(system, target - base_at, rcond=None)[0]  # (groups, channels)
        return solution[0][None, :] + base + drift[:, : n_groups - 1] @ solution[1:]
    frame_group = np.clip(np.searchsorted(anchor_t, times, side="right") - 1, 0, n_groups - 1)
    return base + (target - base_at)[frame_group]


def speed_preserving_gain(parts: list[tuple[int, np.ndarray, np.ndarray]], steps: int) -> np.ndarray:
    """Gain (steps,) that keeps the blended velocity as fast as the segments' own inside blend windows.

    Blending velocities v = sum_k w_k v_k of segments whose motion is unrelated shrinks the speed (two
    uncorrelated halves give 1/sqrt(2) of it), and with joins a syllable apart the windows cover most of the
    utterance, so the synthesis would move more slowly than its sources. The expected squared speed of the blend is
    sum_kl w_k w_l rho_kl E|v|^2, with rho_kl the correlation of the increments of segments k and l over their
    common window (clamped to [0, 1]; non-neighbours take the product along the chain), so the gain is
    1 / sqrt(sum_kl w_k w_l rho_kl): 1 wherever one segment has all the weight or the joined segments move alike
    (a segment continued by its database successor is reproduced exactly), at most sqrt(2) for two unrelated
    ones. It is smooth wherever the weights are, so it keeps the blend C1."""

    def span(k):
        first, w, _ = parts[k]
        return first, first + len(w)

    rho = np.ones(len(parts))  # rho[k]: segment k-1 with segment k
    for k in range(1, len(parts)):
        lo = max(span(k - 1)[0], span(k)[0])
        hi = min(span(k - 1)[1], span(k)[1])
        if hi - lo < 2:
            rho[k] = 1.0
            continue
        a = parts[k - 1][2][lo - span(k - 1)[0] : hi - span(k - 1)[0], :3]
        b = parts[k][2][lo - span(k)[0] : hi - span(k)[0], :3]
        norm = np.sqrt((a * a).sum() * (b * b).sum())
        rho[k] = float(np.clip((a * b).sum() / norm, 0.0, 1.0)) if norm > 1e-300 else 1.0
    energy = np.zeros(steps)
    for k in range(len(parts)):
        first, w, _ = parts[k]
        if len(w) == 0:
            continue
        energy[first : first + len(w)] += w * w
        chain = 1.0
        for m in range(k - 1, -1, -1):
            chain *= rho[m + 1]
            lo, hi = max(span(m)[0], first), min(span(m)[1], first + len(w))
            if hi <= lo:
                if span(m)[1] <= first:
                    break
                continue
            energy[lo:hi] += 2 * chain * parts[m][1][lo - span(m)[0] : hi - span(m)[0]] * w[lo - first : hi - first]
    return 1.0 / np.sqrt(np.clip(energy, 0.5, 1.0))


def crossfade_segments(
    db: DatabaseMotion,
    test_segments: np.ndarray,
    subsentence_start: np.ndarray,
    db_sequence: np.ndarray,
    db_segments: np.ndarray,
    times: np.ndarray,
    *,
    blend_window: float = 0.15,
    break_blend_window: float = 0.25,
    drift_correction: bool = True,
) -> Stitched:
    """The position crossfade (smoothing="crossfade" of ``stitch_segments``): each segment's chained, drift-warped
    curve, weighted by a smootherstep partition of unity over +-window of each join."""
    n = len(test_segments)
    out = np.zeros((len(times), db.channels.shape[1]))
    if n == 0:
        return Stitched(out, np.zeros(0), np.zeros((0, 2)), np.zeros(0))
    a, e = test_segments[:, 0], test_segments[:, 2]
    da, de = db_segments[:, 0], db_segments[:, 2]
    scale = (de - da) / np.maximum(e - a, 1e-9)  # database seconds per output second

    def raw(k: int, t: np.ndarray) -> np.ndarray:
        return db.sample(int(db_sequence[k]), da[k] + (t - a[k]) * scale[k])

    starts = np.asarray(subsentence_start, dtype=bool).copy()
    starts[0] = True
    start_value = np.stack([raw(k, a[k : k + 1])[0] for k in range(n)])
    end_value = np.stack([raw(k, e[k : k + 1])[0] for k in range(n)])
    offset = _chain_offsets(start_value, end_value, starts)
    drift = _drift_ramps(start_value, end_value, offset, starts, a, e, drift_correction)
    # crossfade weights: segment k's indicator [a_k, e_k) with its edges smoothed over +-window of each join,
    # written as ramp_k - ramp_k+1 so that the weights sum to one however close the joins are
    window = np.where(starts, break_blend_window, blend_window)
    window[0] = 0.0
    total = np.zeros(len(times))
    for k in range(n):
        lo_t = -np.inf if k == 0 else a[k] - window[k]
        hi_t = np.inf if k == n - 1 else e[k] + window[k + 1]
        idx = np.flatnonzero((times >= lo_t) & (times <= hi_t))
        if len(idx) == 0:
            continue
        t = times[idx]
        weight = np.maximum(_crossfade_ramp(k, t, a, window) - _crossfade_ramp(k + 1, t, a, window), 0.0)
        out[idx] += weight[:, None] * (raw(k, t) + offset[k] + drift.at(k, t))
        total[idx] += weight
    out /= np.maximum(total, 1e-12)[:, None]
    windows = np.stack([a[1:] - window[1:], a[1:] + window[1:]], axis=1)
    return Stitched(out, a[1:].copy(), windows, np.full(n - 1, np.nan))


def _chain_offsets(start_value: np.ndarray, end_value: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Offset of each segment's curve so that it starts where the previous one ended; a sub-sentence's first
    segment keeps its recorded pose (offset 0)."""
    offset = np.zeros(start_value.shape)
    for k in range(1, len(start_value)):
        if not starts[k]:
            offset[k] = end_value[k - 1] + offset[k - 1] - start_value[k]
    return offset


@dataclass
class _DriftRamps:
    """Per sub-sentence, the linear warp that makes its chained curve end where the next sub-sentence starts."""

    group: np.ndarray  # (segments,) sub-sentence of each segment
    total: np.ndarray  # (sub-sentences, channels) correction reached at the sub-sentence's end
    t0: np.ndarray  # (sub-sentences,) start of the ramp (its first segment's start)
    t1: np.ndarray  # (sub-sentences,) end of the ramp (its last segment's end)

    def at(self, k: int, t: np.ndarray) -> np.ndarray:
        """The correction added to segment ``k``'s curve at times ``t``."""
        g = self.group[k]
        span = max(self.t1[g] - self.t0[g], 1e-9)
        return self.total[g] * np.clip((t - self.t0[g]) / span, 0.0, 1.0)[:, None]


def _drift_ramps(
    start_value: np.ndarray,
    end_value: np.ndarray,
    offset: np.ndarray,
    starts: np.ndarray,
    a: np.ndarray,
    e: np.ndarray,
    drift_correction: bool,
) -> _DriftRamps:
    """The drift correction's ramps (all zero without ``drift_correction``): each sub-sentence warped linearly so
    that it ends where the next one starts."""
    n = len(start_value)
    group = np.cumsum(starts) - 1
    first_of = np.flatnonzero(starts)
    last_of = np.append(first_of[1:] - 1, n - 1)
    total = np.zeros((len(first_of), start_value.shape[1]))
    if drift_correction:
        for g in range(len(first_of) - 1):
            last, nxt = last_of[g], first_of[g + 1]
            total[g] = start_value[nxt] - (end_value[last] + offset[last])
    return _DriftRamps(group, total, a[first_of], e[last_of])


def _crossfade_ramp(j: int, t: np.ndarray, a: np.ndarray, window: np.ndarray) -> np.ndarray:
    """Rise of segment j's crossfade weight at times ``t``: a smootherstep over +-window[j] of its start (a step
    when the window is empty), 1 for the first segment, 0 past the last."""
    if j == 0:
        return np.ones(len(t))
    if j >= len(a):
        return np.zeros(len(t))
    if window[j] <= 0:
        return (t >= a[j]).astype(float)
    return smootherstep((t - a[j] + window[j]) / (2 * window[j]))
