"""Motion blending (paper Sec. 5.4): stitch the database motion of the chosen segments into new head motion.

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

Beyond the paper (each behind a param, the paper's behaviour available): head strokes moved onto the test audio's
onsets by a smooth time warp (``timing``, ``timing_warp``); every source speaker's motion brought to the target
speaker's amplitude and the output centred and scaled to it (``amplitude``); slow wander removed (``rest_anchor``).

Motion is blended as (yaw, pitch, roll) angles and translation: the database is centred on each take's mean pose,
so angles stay small and far from the Euler singularity, where angle rates are close to the angular velocity.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from msflow import Input, Output, Result, Stage, UserError
from stages.geometry.rotations import euler_to_quat
from stages.head.measures import (
    JOIN_MEASURE_WINDOW,
    angular_acceleration,
    angular_speed,
    join_acceleration,
    reference_angles,
    wasserstein_speed,
)


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


def speaker_spreads(db: DatabaseMotion, allowed: np.ndarray | None = None, duration: float | None = None) -> dict:
    """Per speaker, the spread (p95 - p5 per channel) of its motion about its rest pose, pooled over its
    ``allowed`` sequences (all when None); speakers with no allowed sequence are left out.

    The spread of a stretch of head motion grows with its length (slow postural wander adds to it), so with a
    ``duration`` (seconds) the sequences are cut into pieces of about that length, each centred on its own mean
    like a take, and the pieces pooled: the spread expected of an utterance that long. Without it each whole
    sequence (centred on its mean pose by the database) counts as it is."""
    speakers = list(db.speakers or [None] * len(db.frames))
    allowed = np.ones(len(db.frames), bool) if allowed is None else np.asarray(allowed, bool)
    piece = None if not duration else max(int(round(duration * db.fps)), 2)
    out = {}
    for speaker in dict.fromkeys(speakers):
        parts = []
        for k in np.flatnonzero(np.array([x == speaker for x in speakers]) & allowed):
            motion = db.channels[db.first[k] : db.first[k] + db.frames[k]]
            parts += centred_pieces(motion, piece) if piece else [motion]
        if parts:
            values = np.concatenate(parts)
            out[speaker] = np.percentile(values, 95, axis=0) - np.percentile(values, 5, axis=0)
    return out


def centred_pieces(motion: np.ndarray, piece: int) -> list[np.ndarray]:
    """``motion`` cut into nearly equal pieces of about ``piece`` frames (one when shorter), each minus its mean."""
    count = max(1, int(round(len(motion) / piece)))
    edges = np.linspace(0, len(motion), count + 1).round().astype(int)
    return [motion[a:b] - motion[a:b].mean(axis=0) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def amplitude_target(spreads: dict, speaker) -> np.ndarray:
    """The spread to give the synthesis of ``speaker``: that speaker's own (from its other takes) when the
    database has them, else the median over the database's speakers (the typical speaker's amplitude)."""
    if speaker in spreads:
        return spreads[speaker]
    return np.median(np.stack(list(spreads.values())), axis=0)


def knows_speaker(spreads: dict, speaker) -> bool:
    """Whether the database's motion (``spreads``: per speaker, over the sequences the search could use) is the
    test speaker's own: the test is labelled with a speaker the database holds. An unlabelled test is a performer
    the database does not know (whose own filmed motion, when given, is the better guess of its amplitude)."""
    return speaker is not None and speaker in spreads


def group_gains(target: np.ndarray, spread: np.ndarray, max_gain: float = np.inf) -> np.ndarray:
    """Per channel, the gain that brings ``spread`` to about ``target``: one gain for the three angles and one for
    the translation, each the geometric mean over its channels of target / spread (channels that do not move are
    left out; 1 when none moves), at most ``max_gain`` either way.

    One gain for all three angles keeps the direction of the angular velocity, so the speed's maxima -- the head
    strokes the timing warp placed on the voice's onsets -- stay where they are; a gain per angle would move them
    (measured on the shared clips: it cost beat alignment), at the price of keeping the source motion's
    proportions between yaw, pitch and roll."""
    target, spread = np.asarray(target, dtype=np.float64), np.asarray(spread, dtype=np.float64)
    gains = np.ones(len(spread))
    for group in (slice(0, 3), slice(3, len(spread))):
        moving = (spread[group] > 1e-12) & (target[group] > 1e-12)
        if moving.any():
            ratio = np.exp(np.mean(np.log(target[group][moving] / spread[group][moving])))
            gains[group] = np.clip(ratio, 1.0 / max_gain, max_gain)
    return gains


def amplitude_gains(db: DatabaseMotion, spreads: dict, target: np.ndarray, per_angle: bool = False) -> np.ndarray:
    """Per sequence and channel, the gains (``group_gains``; ``per_angle``: one per angle, ``angle_gains``) that
    bring its speaker's spread (``speaker_spreads``) to ``target``: every source speaker then moves about as much
    as the target speaker (1 where a speaker's spread is unknown)."""
    speakers = list(db.speakers or [None] * len(db.frames))
    gains = np.ones((len(speakers), db.channels.shape[1]))
    for k, speaker in enumerate(speakers):
        if speaker in spreads:
            gains[k] = group_gains(target, spreads[speaker])
            if per_angle:
                gains[k, :3] = angle_gains(target[:3], spreads[speaker][:3], np.inf)
    return gains


def match_amplitude(channels: np.ndarray, target: np.ndarray, max_gain: float) -> np.ndarray:
    """The motion about its mean (the rest pose of a take centred like the database), scaled (``group_gains``,
    at most ``max_gain`` either way, so a short, nearly still utterance is not blown up) so that its spread
    p95 - p5 is about ``target``'s. Blending shrinks the spread of unrelated segments, so the overall size is set
    on the output (one gain for the angles: a gain per angle here moved the strokes off the onsets, measured: 62%
    wins over random real motion instead of 83%, leave one speaker out on the shared clips)."""
    centred = channels - channels.mean(axis=0)
    if len(channels) < 2:
        return centred
    spread = np.percentile(centred, 95, axis=0) - np.percentile(centred, 5, axis=0)
    return centred * group_gains(target, spread, max_gain)


def angle_gains(target: np.ndarray, spread: np.ndarray, max_gain: float) -> np.ndarray:
    """Per angle, target / spread (1 for an angle that does not move), at most ``max_gain`` either way."""
    moving = (spread > 1e-12) & (target > 1e-12)
    ratio = np.where(moving, target / np.where(moving, spread, 1.0), 1.0)
    return np.clip(ratio, 1.0 / max_gain, max_gain)


JOIN_BUDGET_OF_MEDIAN = 0.5  # default acceleration a join's velocity step may add, as a fraction of the
#                               database's median angular acceleration (bench/eval_head.py: with it the largest
#                               join acceleration stays below the held-out real motion's 99th percentile)


def smoothstep(u: np.ndarray) -> np.ndarray:
    """C1 ramp from 0 (u <= 0) to 1 (u >= 1), slope 1.5 at its centre."""
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3 - 2 * u)


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
    seconds that the trellis's transition cost H uses (stages.head.trellis.boundary_kinematics)."""
    from stages.head.trellis import boundary_kinematics

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
    # chain: each segment starts where the previous one ends; a sub-sentence starts at its recorded pose
    offset = np.zeros((n, out.shape[1]))
    start_value = np.stack([raw(k, a[k : k + 1])[0] for k in range(n)])
    end_value = np.stack([raw(k, e[k : k + 1])[0] for k in range(n)])
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
    windows = np.stack([a[1:] - window[1:], a[1:] + window[1:]], axis=1)
    return Stitched(out, a[1:].copy(), windows, np.full(n - 1, np.nan))


# ---------------------------------------------------------------------------------------------- the stage

MOTION_BLEND_OUTPUTS = {
    "rotation": Output.array(
        "f", shape=("frames", 4), dtype="float64", doc="unit quaternions (stages.geometry.rotations)"
    ),
    "translation": Output.array("f", shape=("frames", 3), dtype="float64", doc="offset from the rest position"),
    "angles": Output.array("f", shape=("frames", 3), dtype="float64", doc="yaw, pitch, roll in radians"),
    "time": Output.array("f", shape=("frames",), dtype="float64", doc="seconds since the utterance's start"),
    "sequence": Output.array("i", shape=("frames",), dtype="int32", doc="test utterance (meta labels)"),
    "joins": Output.array("f", shape=("joins",), dtype="float64", doc="join times on each utterance's clock"),
    "join_utterance": Output.array("i", shape=("joins",), dtype="int32"),
    "join_window": Output.array(
        "f", shape=("joins", 2), dtype="float64", doc="start and end of each join's blend (seconds, utterance clock)"
    ),
    "join_velocity_step": Output.array(
        "f",
        shape=("joins",),
        dtype="float64",
        doc="angular velocity step between the joined segments (deg/s; NaN for the crossfade)",
    ),
    "bvh": Output.file(".bvh", doc="the head joint's motion, utterances back to back"),
}


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
        ref = reference_angles(inputs["reference"], labels[0], len(labels), fps)
        reference = None if ref is None else np.degrees(ref)
    joins = view["joins"][view["join_utterance"] == 0]
    windows = view["join_window"][view["join_utterance"] == 0] if "join_window" in view else np.zeros((0, 2))
    fig, axes = plt.subplots(3, 1, figsize=(9, 6), sharex=True, constrained_layout=True)
    for c, (ax, name) in enumerate(zip(axes, ("yaw", "pitch", "roll"))):
        for lo, hi in windows:
            ax.axvspan(lo, hi, color="0.5", alpha=0.06, lw=0, zorder=0)
        for j in joins:
            ax.axvline(j, color="0.85", lw=0.8, zorder=0)
        ax.plot(t, angles[:, c], color="crimson", lw=1.6, label="synthesised")
        if reference is not None:
            ax.plot(np.arange(len(reference)) / fps, reference[:, c], color="0.25", lw=1.2, label="real")
        ax.set_ylabel(f"{name} (deg)")
    axes[0].legend(loc="upper right", fontsize=8)
    axes[0].set_title(
        f"head angles: {labels[0] if labels else ''} (grey lines: segment joins, shaded: their blend windows)"
    )
    axes[-1].set_xlabel("time (s)")
    return fig


class MotionBlendParams(Stage.Params):
    fps: float | None = Field(
        None, gt=0, description="output rate; None: the test take's video rate, else the database's"
    )
    join_smoothing: Literal["velocity", "crossfade"] = Field(
        "velocity",
        description="velocity-domain blend, or the earlier position crossfade (overshoots the velocity inside its "
        "window)",
    )
    blend_window: float = Field(0.15, ge=0, description="seconds either side of a join to blend over (at least)")
    break_blend_window: float = Field(0.25, ge=0, description="the same at joins between sub-sentences")
    max_blend_window: float = Field(0.5, ge=0, description="widest half-window a large velocity step may get")
    join_acceleration: float | None = Field(
        None,
        ge=0,
        description="deg/s^2 a join's velocity step may add (sets its window); None: half the database's median "
        "angular acceleration; 0: fixed windows",
    )
    preserve_speed: bool = Field(False, description="keep the blended velocity as fast as the joined segments' own")
    timing: Literal["segment", "onsets", "strokes"] = Field(
        "strokes",
        description="resampling of each chosen segment onto its test segment: 'segment', uniform from onset to onset "
        "(the paper); or piecewise, moving the segment's head strokes ('strokes') or its audio onsets ('onsets') "
        "onto the test's audio onsets",
    )
    timing_tolerance: float = Field(0.15, gt=0, description="farthest (s) the timing warp moves an event")
    timing_warp: Literal["monotone", "linear"] = Field(
        "monotone",
        description="the timing warp's time map through its knots: a monotone C1 cubic (the playback rate changes "
        "smoothly) or piecewise linear (the rate steps at each moved event)",
    )
    amplitude: Literal["database", "speaker", "match"] = Field(
        "match",
        description="'database': motion amplitude as recorded (the paper); 'speaker': each source speaker's motion "
        "scaled to the target spread (the test speaker's own from its other takes, else the database's typical "
        "speaker's); 'match': that, and the output centred on the rest pose with its spread set to the target",
    )
    amplitude_target: Literal["auto", "database", "reference"] = Field(
        "auto",
        description="where 'speaker' and 'match' take the angles' target spread: the database (the test speaker's "
        "other takes, else its typical speaker's), the reference input (the performer's own tracked motion in "
        "the test take), or 'auto': the database when it holds the test's speaker (by its speaker label), else "
        "the reference when given",
    )
    max_amplitude_gain: float = Field(3.0, ge=1, description="'match': largest gain (either way) on the output")
    reference_seconds: float | None = Field(
        None,
        gt=0,
        description="amplitude_target 'reference': the target from the first this many seconds of each reference "
        "take (an enrolment stretch of the performer's motion; None: the whole take)",
    )
    source_gain: Literal["auto", "common", "per_angle"] = Field(
        "auto",
        description="'speaker', 'match': one gain per source speaker for its three angles, or one per angle (its "
        "proportions between yaw, pitch and roll brought to the target's before its strokes are timed); 'auto': "
        "per angle where the target is the performer's own motion (the reference), common where it is the "
        "database's",
    )
    refine_proportions: bool = Field(
        True,
        description="where the sources are scaled per angle (source_gain), stitch a second time with their gains "
        "corrected by the first output's proportions between yaw, pitch and roll (blending changes them)",
    )
    output_cutoff: float | None = Field(
        4.0,
        gt=0,
        description="zero-phase low-pass (Hz) of the stitched motion, against the acceleration of segments played "
        "faster than recorded (None: off, the paper)",
    )
    rest_anchor: float = Field(
        0.0, ge=0, description="remove wander slower than this many seconds, back to the rest pose (0: off)"
    )
    max_stretch: float = Field(
        2.0, ge=1, description="fastest or slowest a piece of the warp plays, x the uniform rate"
    )
    drift_correction: bool = Field(True, description="warp each sub-sentence to meet the next")
    translation: bool = Field(True, description="False: rotation only (translation zero)")
    bvh_joint: str = Field("Head", min_length=1)
    bvh_order: Literal["XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"] = Field(
        "ZXY", description="Euler channel order written to the BVH"
    )

    @model_validator(mode="after")
    def _target_needs_scaling(self):
        if self.amplitude_target == "reference" and self.amplitude == "database":
            raise ValueError("amplitude_target 'reference' needs amplitude 'speaker' or 'match' (not 'database')")
        return self


class MotionBlend(Stage):
    """Stitch, drift-correct and smooth the joins of the chosen database motion (Sec. 5.4); head rotation,
    translation and a BVH of the head joint at the output rate."""

    Params = MotionBlendParams
    inputs = {
        "trellis": Input.artifact("segments", "chosen", "db_segments", "db_segment_sequence"),
        "database": Input.artifact("angles", "translation", "sequence", doc="the headdb artifact searched"),
        "reference": Input.artifact(
            "rotation",
            "sequence",
            optional=True,
            doc="real motion of the test take (tracking artifact) for the figure and metrics",
        ),
    }
    outputs = MOTION_BLEND_OUTPUTS
    figures = {"head_angles": _plot_head_angles}

    def run(self, params, inputs):
        trellis, database = inputs["trellis"], inputs["database"]
        check_same_database(trellis, database)
        db = database_motion(database, use_translation=params.translation)
        options = stitch_options(params, db, trellis)
        fps = output_rate(params, trellis, db)
        labels = list(trellis.meta.get("labels") or [])
        if params.amplitude_target == "reference" or (
            params.amplitude_target == "auto" and params.amplitude != "database" and inputs.get("reference") is not None
        ):
            if inputs.get("reference") is None:
                raise UserError(
                    "amplitude_target 'reference' needs the reference input (the test take's tracking)",
                    field="inputs.reference",
                )
            options["targets"] = reference_spreads(inputs["reference"], labels, fps, params.reference_seconds)
        synth = synthesise(trellis, db, fps, **options)
        arrays = pack_motion(synth, fps, params)
        metrics = motion_metrics(arrays, fps, JOIN_MEASURE_WINDOW, inputs.get("reference"), labels)
        metrics.update(join_metrics(arrays))
        meta = {
            "fps": fps,
            "labels": labels,
            "frames": [len(s.channels) for s in synth],
            "join_smoothing": params.join_smoothing,
            "join_acceleration_budget": float(options["acceleration_budget"] or 0.0),
            "stitch": options,
            "translation_units": database.meta.get("translation_units", "unknown"),
            "bvh_joint": params.bvh_joint,
            "db_labels": list(database.meta.get("labels") or []),
        }
        return Result(arrays, meta, metrics, rest_warnings(trellis, labels) + target_warnings(options, labels))


def check_same_database(trellis, database) -> None:
    db_labels = list(database.meta.get("labels") or [])
    if trellis.meta.get("db_labels") is not None and list(trellis.meta["db_labels"]) != db_labels:
        raise UserError(
            "the trellis was searched over a different database than the one given", field="inputs.database"
        )


def stitch_options(params, db: DatabaseMotion, trellis) -> dict:
    """Keyword arguments of ``stitch_segments`` from the stage's params (JSON, kept in the artifact's meta so the
    evaluation can stitch its baselines exactly alike)."""
    budget = (
        JOIN_BUDGET_OF_MEDIAN * db.typical_acceleration()
        if params.join_acceleration is None
        else params.join_acceleration
    )
    return {
        "smoothing": params.join_smoothing,
        "blend_window": params.blend_window,
        "break_blend_window": params.break_blend_window,
        "max_blend_window": params.max_blend_window,
        "acceleration_budget": float(budget) or None,
        "preserve_speed": params.preserve_speed,
        "drift_correction": params.drift_correction,
        "boundary_window": float(trellis.meta.get("boundary_window", 0.1)),
        "timing": params.timing,
        "timing_tolerance": params.timing_tolerance,
        "warp": params.timing_warp,
        "max_stretch": params.max_stretch,
        "amplitude": params.amplitude,
        "max_amplitude_gain": params.max_amplitude_gain,
        "source_gain": params.source_gain,
        "targets": None,  # per utterance, the angles' target spread from the reference (amplitude_target)
        "targets_for": "unknown" if params.amplitude_target == "auto" else "all",
        "refine_proportions": params.refine_proportions,
        "output_cutoff": params.output_cutoff,
        "rest_anchor": params.rest_anchor,
    }


def reference_spreads(
    reference, labels: list[str], fps: float, seconds: float | None = None
) -> list[list[float] | None]:
    """Per test utterance, the spread (p95 - p5 about its mean) of each angle of the performer's real motion in
    the reference (a tracking artifact; its first ``seconds`` when given): the amplitude target of
    ``amplitude_target="reference"``; None where the reference has no such take or it is too short."""
    from stages.head.measures import reference_angles

    out: list[list[float] | None] = []
    for label in labels:
        angles = reference_angles(reference, label, len(labels), fps)
        if angles is not None and seconds is not None:
            angles = angles[: int(round(seconds * fps))]
        if angles is None or len(angles) < 2:
            out.append(None)
            continue
        centred = angles - angles.mean(axis=0)
        out.append((np.percentile(centred, 95, axis=0) - np.percentile(centred, 5, axis=0)).tolist())
    return out


def target_warnings(options: dict, labels: list[str]) -> list[str]:
    targets = options.get("targets")
    if targets is None:
        return []
    return [
        f"'{label}' is not in the reference: its amplitude comes from the database"
        for label, target in zip(labels, targets)
        if target is None
    ]


def output_rate(params, trellis, db: DatabaseMotion) -> float:
    test_fps = [f for f in (trellis.meta.get("fps") or []) if f]
    return float(params.fps or (test_fps[0] if test_fps else db.fps))


def pack_motion(synth: list, fps: float, params) -> dict:
    """The blend's arrays: angles, rotation, translation, per-frame time and utterance, joins, BVH."""
    from stages.formats.bvh import head_bvh

    def cat(parts, empty):
        return np.concatenate(parts) if parts else empty

    angles = cat([s.channels[:, :3] for s in synth], np.zeros((0, 3)))
    translation = cat([s.channels[:, 3:] for s in synth], np.zeros((0, 3)))
    rotation = euler_to_quat(angles[:, 0], angles[:, 1], angles[:, 2])
    return {
        "rotation": rotation,
        "translation": translation,
        "angles": angles,
        "time": cat([np.arange(len(s.channels)) / fps for s in synth], np.zeros(0)),
        "sequence": cat([np.full(len(s.channels), u, np.int32) for u, s in enumerate(synth)], np.zeros(0, np.int32)),
        "joins": cat([s.joins for s in synth], np.zeros(0)),
        "join_utterance": cat([np.full(len(s.joins), u, np.int32) for u, s in enumerate(synth)], np.zeros(0, np.int32)),
        "join_window": cat([s.windows for s in synth], np.zeros((0, 2))).reshape(-1, 2),
        "join_velocity_step": cat([s.velocity_mismatch for s in synth], np.zeros(0)),
        "bvh": head_bvh(rotation, translation, fps, joint=params.bvh_joint, order=params.bvh_order).encode(),
    }


def join_metrics(arrays: dict) -> dict:
    """Mean velocity step the joins absorbed (deg/s) and mean blend window (s); none for the crossfade."""
    steps = arrays["join_velocity_step"][np.isfinite(arrays["join_velocity_step"])]
    if not len(steps):
        return {}
    widths = np.diff(arrays["join_window"], axis=1)[:, 0]
    return {"mean_join_velocity_step": float(steps.mean()), "mean_join_window": float(widths.mean())}


def rest_warnings(trellis, labels: list[str]) -> list[str]:
    """A warning per test utterance with no voiced segment: its head stays at the rest pose."""
    counts = np.bincount(np.asarray(trellis["segment_utterance"], dtype=np.int64), minlength=len(labels))
    return [
        f"'{label}' has no voiced speech: its head stays at the rest pose" for label, n in zip(labels, counts) if n == 0
    ]


def database_motion(view, *, use_translation: bool = True) -> DatabaseMotion:
    sequence = np.asarray(view["sequence"], dtype=np.int64)
    n_seq = int(sequence.max()) + 1 if len(sequence) else 0
    frames = np.bincount(sequence, minlength=n_seq)
    translation = np.asarray(view["translation"], dtype=np.float64)
    channels = np.concatenate(
        [np.asarray(view["angles"], dtype=np.float64), translation if use_translation else np.zeros_like(translation)],
        axis=1,
    )
    if not np.isfinite(channels).all():
        raise UserError("NaN in the database motion", field="inputs.database")
    first = np.concatenate([[0], np.cumsum(frames)[:-1]])
    return DatabaseMotion(channels, first, frames, float(view.meta["fps"]), view.meta.get("speakers"))


def database_events(trellis, db: DatabaseMotion, timing: str) -> list[np.ndarray]:
    """Per database sequence, the events the timing warp moves: its audio onsets (``timing="onsets"``) or the
    strokes of its head motion (``"strokes"``: maxima of the smoothed angular speed, stages.head.beats)."""
    from stages.head.beats import kinematic_beats

    if timing == "strokes":
        return [
            kinematic_beats(db.channels[first : first + n, :3], db.fps, kind="peaks", smoothing=0.1)
            for first, n in zip(db.first, db.frames)
        ]
    times = np.asarray(trellis["db_onsets"]) if "db_onsets" in trellis else np.zeros(0)
    owner = np.asarray(trellis["db_onset_sequence"]) if "db_onset_sequence" in trellis else np.zeros(0, int)
    return [times[owner == k] for k in range(len(db.frames))]


def utterance_time_maps(
    test_segments: np.ndarray,
    db_segments: np.ndarray,
    db_sequence: np.ndarray,
    test_events: np.ndarray,
    db_events: list[np.ndarray],
    tolerance: float,
    max_stretch: float,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """``segment_knots`` of every chosen segment of one utterance."""
    return [
        segment_knots(
            (test_segments[k, 0], test_segments[k, 2]),
            (db_segments[k, 0], db_segments[k, 2]),
            test_events,
            db_events[int(db_sequence[k])],
            tolerance=tolerance,
            max_stretch=max_stretch,
        )
        for k in range(len(test_segments))
    ]


@dataclass
class TrellisPath:
    """What the blend reads from a trellis artifact: test segments, the chosen database segments, onsets."""

    labels: list[str]
    speakers: list
    segments: np.ndarray  # (N, 3) test segments
    utterance: np.ndarray  # (N,)
    subsentence_start: np.ndarray  # (N,)
    db_sequence: np.ndarray  # (N,) database sequence of the chosen segment
    db_segments: np.ndarray  # (N, 3) its times
    onsets: np.ndarray  # test audio onsets
    onset_utterance: np.ndarray
    db_labels: list[str] | None = None  # the searched database's sequences
    excluded: list[list[str]] | None = None  # per utterance, the database sequences held out of its search

    def allowed(self, u: int) -> np.ndarray | None:
        """Database sequences utterance ``u``'s search could use (None: all): its amplitude target must not come
        from the takes held out for it (its own take, or its whole speaker)."""
        if self.db_labels is None or self.excluded is None or u >= len(self.excluded):
            return None
        held_out = set(self.excluded[u])
        return np.array([name not in held_out for name in self.db_labels], dtype=bool)

    @classmethod
    def of(cls, trellis) -> TrellisPath:
        labels = list(trellis.meta.get("labels") or [])
        chosen = np.asarray(trellis["chosen"], dtype=np.int64)
        has_onsets = "test_onsets" in trellis and "test_onset_utterance" in trellis
        return cls(
            labels,
            list(trellis.meta.get("speakers") or [None] * len(labels)),
            np.asarray(trellis["segments"]).reshape(-1, 3),
            np.asarray(trellis["segment_utterance"]),
            np.asarray(trellis["subsentence_start"], dtype=bool),
            np.asarray(trellis["db_segment_sequence"], dtype=np.int64)[chosen],
            np.asarray(trellis["db_segments"]).reshape(-1, 3)[chosen],
            np.asarray(trellis["test_onsets"]) if has_onsets else np.zeros(0),
            np.asarray(trellis["test_onset_utterance"]) if has_onsets else np.zeros(0, int),
            trellis.meta.get("db_labels"),
            trellis.meta.get("excluded"),
        )


def utterance_frames(trellis, u: int, fps: float) -> int:
    """Output frames of test utterance ``u``: its own frame count at its own rate, else its duration at ``fps``."""
    test_fps = (trellis.meta.get("fps") or [None] * (u + 1))[u]
    test_frames = (trellis.meta.get("frames") or [None] * (u + 1))[u]
    if test_frames and test_fps and abs(float(test_fps) - fps) < 1e-6:
        return int(test_frames)
    return int(round(float(trellis.meta["durations"][u]) * fps))


def synthesise(
    trellis,
    db: DatabaseMotion,
    fps: float,
    *,
    timing: str = "segment",
    timing_tolerance: float = 0.15,
    max_stretch: float = 2.0,
    amplitude: str = "database",
    rest_anchor: float = 0.0,
    max_amplitude_gain: float = 3.0,
    output_cutoff: float | None = None,
    source_gain: str = "common",
    targets: list | None = None,
    targets_for: str = "all",
    refine_proportions: bool = False,
    **blend,
) -> list[Stitched]:
    """The stitched motion of each test utterance of a trellis artifact (a still head where silent). ``timing``:
    each chosen segment resampled uniformly onto its test segment (``"segment"``, the paper), or with its audio
    onsets (``"onsets"``) or its head strokes (``"strokes"``) moved onto the test's audio onsets
    (``segment_knots``). ``amplitude="speaker"`` scales every source speaker's motion to the test speaker's
    spread (``amplitude_source``), ``"match"`` also centres the output on the rest pose and scales it to that
    spread (``match_amplitude``, gain at most ``max_amplitude_gain``); ``rest_anchor`` > 0 removes wander slower
    than that many seconds (a Gaussian low-pass of that sd), so the head keeps returning to its rest pose;
    ``output_cutoff`` (Hz) low-passes the stitched motion (``lowpass_channels``); ``targets`` (per utterance, the
    angles' spread or None) replaces the database's amplitude target of the angles (``targets_for="unknown"``:
    only where the database does not know the utterance's speaker). ``refine_proportions``: where the sources
    were scaled per angle and the output is matched, stitch a second time with the per-angle gains corrected by
    the first output's proportions (``proportion_correction``). ``blend``: keyword arguments of
    ``stitch_segments``."""
    path = TrellisPath.of(trellis)
    shared_events = database_events(trellis, db, timing) if timing != "segment" else None
    finishing = {"rest_anchor": rest_anchor, "max_gain": max_amplitude_gain, "cutoff": output_cutoff}
    out = []
    for u in range(len(path.labels)):
        given = targets[u] if targets is not None and u < len(targets) else None
        duration = utterance_frames(trellis, u, fps) / fps
        source, target, per_angle = amplitude_source(
            db, path, u, duration, amplitude, given, source_gain, targets_for == "unknown"
        )
        rows = np.flatnonzero(path.utterance == u)
        times = np.arange(utterance_frames(trellis, u, fps)) / fps

        def render(source: DatabaseMotion) -> Stitched:
            events = shared_events
            if timing == "strokes" and source is not db:
                events = database_events(trellis, source, timing)  # the strokes of the motion as it will play
            maps = None
            if events is not None:
                onsets = path.onsets[path.onset_utterance == u]
                maps = utterance_time_maps(
                    path.segments[rows], path.db_segments[rows], path.db_sequence[rows], onsets, events,
                    timing_tolerance, max_stretch,
                )  # fmt: skip
            stitched = stitch_segments(
                source, path.segments[rows], path.subsentence_start[rows], path.db_sequence[rows],
                path.db_segments[rows], times, time_maps=maps, **blend,
            )  # fmt: skip
            if len(rows):
                stitched.channels = finish_channels(stitched.channels, fps, amplitude, target, **finishing)
            return stitched

        stitched = render(source)
        if refine_proportions and per_angle and amplitude == "match" and len(rows):
            stitched = render(source.scaled(proportion_correction(stitched.channels, target, len(db.frames))))
        out.append(stitched)
    return out


def finish_channels(
    channels: np.ndarray, fps: float, amplitude: str, target, *, rest_anchor: float, max_gain: float, cutoff
) -> np.ndarray:
    """The stitched channels of an utterance finished: wander slower than ``rest_anchor`` seconds removed (0:
    kept), the amplitude matched to ``target`` (``amplitude="match"``, ``match_amplitude``), low-passed at
    ``cutoff`` Hz (None: not)."""
    if rest_anchor > 0 and len(channels) > 1:
        channels = channels - low_pass(channels, rest_anchor * fps)
    if amplitude == "match":
        channels = match_amplitude(channels, target, max_gain)
    if cutoff:
        channels = lowpass_channels(channels, fps, cutoff)
    return channels


def proportion_correction(channels: np.ndarray, target: np.ndarray, sequences: int, max_gain: float = 2.0):
    """(sequences, channels) gains that bring the proportions between the angles' spreads of a stitched output
    (``channels``) to ``target``'s: per angle target / spread, divided by their geometric mean (the output's one
    gain sets the size), at most ``max_gain`` either way; 1 for the translation."""
    spread = np.percentile(channels, 95, axis=0) - np.percentile(channels, 5, axis=0)
    ratio = angle_gains(np.asarray(target, dtype=np.float64)[:3], spread[:3], max_gain)
    gains = np.ones(channels.shape[1])
    gains[:3] = np.clip(ratio / np.exp(np.mean(np.log(ratio))), 1.0 / max_gain, max_gain)
    return np.tile(gains, (sequences, 1))


def amplitude_source(
    db: DatabaseMotion,
    path: TrellisPath,
    u: int,
    duration: float,
    amplitude: str,
    angles_target=None,
    source_gain: str = "common",
    database_first: bool = False,
) -> tuple[DatabaseMotion, np.ndarray | None, bool]:
    """The database motion utterance ``u`` is stitched from and its amplitude target: as recorded
    (``amplitude="database"``), or every source speaker brought to the target spread at the utterance's
    ``duration`` (``speaker_spreads`` over the sequences its search could use, ``amplitude_target``), the angles'
    part replaced by ``angles_target`` when given (the performer's own, ``reference_spreads``; with
    ``database_first`` only when the database does not know the speaker, ``knows_speaker``). ``source_gain``:
    each source speaker scaled by one gain for its angles, by one per angle, or (``"auto"``) per angle only where
    the angles' target is the performer's own: only then are its proportions between the angles known."""
    if amplitude == "database":
        return db, None, False
    spreads = speaker_spreads(db, path.allowed(u), duration)
    target = amplitude_target(spreads, path.speakers[u])
    performers = angles_target is not None and not (database_first and knows_speaker(spreads, path.speakers[u]))
    if performers:
        target = np.array(target, dtype=np.float64)
        target[:3] = angles_target
    per_angle = source_gain == "per_angle" or (source_gain == "auto" and performers)
    return db.scaled(amplitude_gains(db, spreads, target, per_angle)), target, per_angle


def lowpass_channels(channels: np.ndarray, fps: float, cutoff: float) -> np.ndarray:
    """Zero-phase Butterworth low-pass of the output channels at ``cutoff`` Hz (the database's jitter filter,
    stages.head.database.lowpass_motion, applied to the stitched motion).

    Resampling a database segment onto a shorter test segment, and more so the timing warp that moves a stroke,
    plays the motion faster: a rate r multiplies its acceleration by r^2 and moves its frequencies up by r, so a
    nod recorded at 3 Hz comes out at 6-8 Hz where the warp plays a piece at 2-2.7x. The filter takes those
    sped-up peaks (and any velocity kink left at a join) back into the band of real head strokes; the strokes'
    timing, below the cutoff, stays."""
    from scipy.signal import butter, sosfiltfilt

    if cutoff >= 0.5 * fps or len(channels) < 3:
        return channels
    sos = butter(4, cutoff / (0.5 * fps), output="sos")
    return sosfiltfilt(sos, channels, axis=0, padlen=min(3 * (2 * len(sos) + 1), len(channels) - 1))


def low_pass(channels: np.ndarray, sd_frames: float) -> np.ndarray:
    """Gaussian low-pass along frames (edges extended with the end values)."""
    from scipy.ndimage import gaussian_filter1d

    return gaussian_filter1d(channels, sd_frames, axis=0, mode="nearest")


def accelerations_at_joins(arrays, fps: float, window: float = JOIN_MEASURE_WINDOW) -> np.ndarray:
    """The largest angular acceleration within +-``window`` s of each join (deg/s^2), utterance by utterance, of a
    MotionBlend output (``angles``, ``sequence``, ``joins``, ``join_utterance``); utterances under 3 frames have none."""
    found = [np.zeros(0)]
    for u in np.unique(arrays["sequence"]):
        angles = arrays["angles"][arrays["sequence"] == u]
        if len(angles) >= 3:
            joins = arrays["joins"][arrays["join_utterance"] == u]
            found.append(join_acceleration(angles, fps, joins, max(window, 1.0 / fps)))
    return np.concatenate(found)


def motion_metrics(arrays: dict, fps: float, window: float, reference, labels: list[str]) -> dict:
    """Speed and join smoothness of the synthesis; against the real motion when a reference is given."""
    metrics = {}
    speeds, ref_speed, ref_acc99, w1 = [], [], [], []
    for u in range(len(labels)):
        mask = arrays["sequence"] == u
        angles = arrays["angles"][mask]
        if len(angles) < 3:
            continue
        speeds.append(angular_speed(angles, fps))
        if reference is not None:
            real = reference_angles(reference, labels[u], len(labels), fps)
            if real is not None and len(real) >= 3:
                ref_speed.append(angular_speed(real, fps))
                ref_acc99.append(np.percentile(angular_acceleration(real, fps), 99))
                w1.append(wasserstein_speed(angles, real, fps))
    if speeds:
        metrics["mean_angular_speed"] = float(np.mean(np.concatenate(speeds)))
    joins = accelerations_at_joins(arrays, fps, window)
    if len(joins):
        metrics["max_join_acceleration"] = float(joins.max())
    if ref_speed:
        metrics["real_mean_angular_speed"] = float(np.mean(np.concatenate(ref_speed)))
        metrics["real_acceleration_p99"] = float(np.max(ref_acc99))
        metrics["speed_wasserstein"] = float(np.mean(w1))
    return metrics
