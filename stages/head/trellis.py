"""Pitch matching and path search over the head-motion database (paper Sec. 5.2-5.3, Eq. 10-15).

For each test utterance:
1. phrase stage: z-normalised phrase features (Dellaert-style prosody) against every database phrase, Euclidean
   distance, keep the top M phrases (more when they hold fewer than K segments);
2. segment stage: for each test segment, D = b G_d + c P_d + (1 - b - c) L_d (Eq. 10-12) against the segments of
   those phrases, keep the top K;
3. Viterbi over the trellis of K candidates per test segment with transition cost C = w1 H + w2 R (Eq. 13-15),
   one search per sub-sentence (breath pauses bound the search, Sec. 5.4).

H compares the boundary velocity and acceleration as the blend will join them: each candidate is resampled to
its test segment's length (Sec. 5.4), so its V and A are scaled by its rate, and the pair is compared on its common
clock (``warp_boundaries``, default; see ``transition_costs``). Comparing each recording's own-clock V and A
(the earlier behaviour) mixed units whenever two candidates play at different rates; comparing on the output
clock would reward slowing motion down (it shrinks V and A), which on CREMA-D picked segments played at 65%.
Motion-blend measures its join velocity steps with the same parabola fits (``boundary_kinematics``, meta
``boundary_window``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from msflow import Input, Output, Result, Stage, UserError
from stages.head.copies import copy_warnings, take_of
from stages.head.pitch import semitones

GEOMETRY_FEATURES = ("min", "max", "range", "min_slope", "max_slope", "curvature")


# ------------------------------------------------------------------------------------------ segment features


@dataclass
class SpeakerReference:
    """Per utterance: the median f0 (Hz) and the spread (semitones) of its speaker, the reference of the unit."""

    median: np.ndarray
    spread: np.ndarray


@dataclass
class SegmentTable:
    """All pitch segments of a pitch artifact, with what the matching needs."""

    times: np.ndarray  # (n, 3) start, voiced end, end (seconds, sequence clock)
    utterance: np.ndarray  # (n,) index into the pitch artifact's utterances
    position: np.ndarray  # (n,) index of the segment within its utterance
    subsentence_start: np.ndarray  # (n,) bool
    contour: np.ndarray  # (n, L) voiced pitch resampled to L points, in the matching unit
    geometry: np.ndarray  # (n, 6) GEOMETRY_FEATURES of the contour
    energy: np.ndarray  # (n, L) loudness (dB re the take's median voiced loudness), onset to next onset
    onset_rate: np.ndarray  # (n,) audio onsets per second inside the segment

    def rows(self, index: np.ndarray) -> SegmentTable:
        return SegmentTable(*(getattr(self, f)[index] for f in self.__dataclass_fields__))

    def __len__(self) -> int:
        return len(self.times)

    @property
    def length(self) -> np.ndarray:
        return self.times[:, 2] - self.times[:, 0]


def voiced_contours(
    f0: np.ndarray,
    pitch_time: np.ndarray,
    pitch_utterance: np.ndarray,
    segments: np.ndarray,
    segment_utterance: np.ndarray,
    length: int,
) -> np.ndarray:
    """Each segment's voiced pitch (onset to voiced end) resampled to ``length`` points (Eq. 10's length
    normalisation); f0 in any unit, NaN unvoiced. Vectorised over segments."""
    n_utt = int(pitch_utterance.max()) + 1 if len(pitch_utterance) else 0
    first = np.searchsorted(pitch_utterance, np.arange(n_utt))
    count = np.bincount(pitch_utterance, minlength=n_utt)
    step = np.median(np.diff(pitch_time[:2])) if len(pitch_time) > 1 else 0.01
    t0 = pitch_time[np.minimum(first, len(pitch_time) - 1)]
    u = segment_utterance
    lo = np.round((segments[:, 0] + step / 2 - t0[u]) / step)
    hi = np.round((segments[:, 1] - step / 2 - t0[u]) / step)
    lo = np.clip(lo, 0, count[u] - 1)
    hi = np.clip(np.maximum(hi, lo), 0, count[u] - 1)
    frac = np.linspace(0.0, 1.0, length)
    index = first[u][:, None] + lo[:, None] + (hi - lo)[:, None] * frac[None, :]
    below = np.floor(index).astype(np.int64)
    above = np.minimum(below + 1, len(f0) - 1)
    w = index - below
    a, b = f0[below], f0[above]
    b = np.where(np.isfinite(b), b, a)  # never blend in an unvoiced neighbour at the run's edge
    contour = (1 - w) * a + w * b
    row_mean = (
        np.nanmean(np.where(np.isfinite(contour), contour, np.nan), axis=1, keepdims=True) if contour.size else contour
    )
    return np.where(np.isfinite(contour), contour, np.nan_to_num(row_mean))


def contour_geometry(contour: np.ndarray, voiced_length: np.ndarray) -> np.ndarray:
    """Geometric features G of each contour (Sec. 5.2): min, max, range, min and max slope (unit/s) and
    curvature (second derivative of a least-squares parabola, unit/s^2)."""
    n, length = contour.shape
    if n == 0:
        return np.zeros((0, len(GEOMETRY_FEATURES)))
    duration = np.maximum(voiced_length, 1e-3)
    dt = duration / max(length - 1, 1)
    slopes = np.diff(contour, axis=1) / dt[:, None] if length > 1 else np.zeros((n, 1))
    u = np.linspace(-1.0, 1.0, length)
    design = np.stack([u * u, u, np.ones_like(u)], axis=1)
    coeffs = np.linalg.lstsq(design, contour.T, rcond=None)[0]  # (3, n)
    curvature = 2 * coeffs[0] * (2.0 / duration) ** 2
    lo, hi = contour.min(axis=1), contour.max(axis=1)
    return np.stack([lo, hi, hi - lo, slopes.min(axis=1), slopes.max(axis=1), curvature], axis=1)


def pitch_in_unit(f0_hz: np.ndarray, unit: str, reference_hz: np.ndarray, spread: np.ndarray) -> np.ndarray:
    """Pitch in the matching unit: Hz; semitones relative to the speaker's median (``reference_hz``, per frame);
    or z-scores per speaker (those semitones divided by the speaker's ``spread``, semitones)."""
    if unit == "hz":
        return np.asarray(f0_hz, dtype=np.float64)
    st = semitones(f0_hz, reference_hz)
    return st / np.maximum(spread, 1e-6) if unit == "zscore" else st


def segment_table(view, reference: SpeakerReference, unit: str, length: int) -> SegmentTable:
    """Segments of a pitch artifact with contours in ``unit`` (``pitch_in_unit``, each utterance relative to its
    entry of ``reference``), loudness contours and onset rates."""
    utt = np.asarray(view["pitch_utterance"], dtype=np.int64)
    f0 = pitch_in_unit(np.asarray(view["f0"], dtype=np.float64), unit, reference.median[utt], reference.spread[utt])
    segments = np.asarray(view["segments"], dtype=np.float64).reshape(-1, 3)
    seg_utt = np.asarray(view["segment_utterance"], dtype=np.int64)
    pitch_time = np.asarray(view["pitch_time"])
    contour = voiced_contours(f0, pitch_time, utt, segments, seg_utt, length)
    position = np.zeros(len(segments), dtype=np.int64)
    if len(segments):
        starts = np.flatnonzero(np.concatenate([[True], seg_utt[1:] != seg_utt[:-1]]))
        position = np.arange(len(segments)) - np.repeat(starts, np.diff(np.append(starts, len(segments))))
    return SegmentTable(
        segments,
        seg_utt,
        position,
        np.asarray(view["subsentence_start"], dtype=bool),
        contour,
        contour_geometry(contour, segments[:, 1] - segments[:, 0]),
        loudness_contours(view, segments, seg_utt, length),
        onset_rates(view, segments, seg_utt),
    )


def loudness_contours(view, segments: np.ndarray, seg_utt: np.ndarray, length: int) -> np.ndarray:
    """Loudness of each segment from onset to next onset resampled to ``length`` points, in dB relative to its
    take's median loudness over voiced frames (recording levels differ between takes); zeros without ``energy``."""
    if "energy" not in view or not len(segments):
        return np.zeros((len(segments), length))
    utt = np.asarray(view["pitch_utterance"], dtype=np.int64)
    energy = np.asarray(view["energy"], dtype=np.float64)
    voiced = np.isfinite(np.asarray(view["f0"], dtype=np.float64))
    n_utt = int(utt.max()) + 1
    level = np.array([np.median(energy[(utt == u) & voiced]) if np.any((utt == u) & voiced) else 0.0
                      for u in range(n_utt)])  # fmt: skip
    span = np.stack([segments[:, 0], segments[:, 2], segments[:, 2]], axis=1)
    return voiced_contours(energy - level[utt], np.asarray(view["pitch_time"]), utt, span, seg_utt, length)


def onset_rates(view, segments: np.ndarray, seg_utt: np.ndarray) -> np.ndarray:
    """Audio onsets per second inside each segment (onset to next onset); zeros without ``onsets``."""
    if "onsets" not in view or not len(segments):
        return np.zeros(len(segments))
    onsets = np.asarray(view["onsets"], dtype=np.float64)
    owner = np.asarray(view["onset_utterance"], dtype=np.int64)
    inside = (
        (owner[None, :] == seg_utt[:, None])
        & (onsets[None, :] >= segments[:, :1])
        & (onsets[None, :] < segments[:, 2:3])
    )
    return inside.sum(axis=1) / np.maximum(segments[:, 2] - segments[:, 0], 1e-6)


# -------------------------------------------------------------------------------------------- distances


def zscore_stats(features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation per column over finite rows (std 1 where a column is constant)."""
    finite = features[np.isfinite(features).all(axis=1)]
    if len(finite) == 0:
        return np.zeros(features.shape[1]), np.ones(features.shape[1])
    sd = finite.std(axis=0)
    return finite.mean(axis=0), np.where(sd > 1e-12, sd, 1.0)


def phrase_distances(
    test_features: np.ndarray, db_features: np.ndarray, mean: np.ndarray, sd: np.ndarray
) -> np.ndarray:
    """Euclidean distance of z-normalised phrase feature vectors (Sec. 5.2, first stage); NaN rows stay NaN."""
    return np.linalg.norm((db_features - mean) / sd - (test_features - mean) / sd, axis=1)


@dataclass
class SegmentDistance:
    total: np.ndarray  # (N, S) D of Eq. 12 (plus the loudness and rhythm terms when weighted)
    geometry: np.ndarray  # G_d
    pitch: np.ndarray  # P_d, Eq. 10
    length: np.ndarray  # L_d, Eq. 11
    loudness: np.ndarray  # E_d (beyond the paper)
    rhythm: np.ndarray  # O_d (beyond the paper)


@dataclass
class SegmentWeights:
    """Weights of the segment distance: b, c of Eq. 12 (L_d gets 1 - b - c), and e, o of the loudness and rhythm
    terms added beyond the paper (0: the paper's distance)."""

    b: float
    c: float
    e: float = 0.0
    o: float = 0.0


@dataclass
class SegmentScales:
    """Database statistics that put the terms on comparable scales."""

    geometry_mean: np.ndarray
    geometry_sd: np.ndarray
    loudness_sd: float
    rhythm_sd: float


def segment_scales(db: SegmentTable) -> SegmentScales:
    """z-normalisation of the geometric features, and the spread of loudness values and of onset rates."""
    mean, sd = zscore_stats(db.geometry) if len(db) else (np.zeros(6), np.ones(6))
    loud = float(np.std(db.energy)) if db.energy.size else 1.0
    rhythm = float(np.std(db.onset_rate)) if len(db) else 1.0
    return SegmentScales(mean, sd, loud if loud > 1e-9 else 1.0, rhythm if rhythm > 1e-9 else 1.0)


def rms_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """RMS difference (N, S) between every row of ``a`` (N, L) and of ``b`` (S, L), without the (N, S, L)
    temporary: |a - b|^2 = |a|^2 + |b|^2 - 2 a.b."""
    sq = (a**2).sum(1)[:, None] + (b**2).sum(1)[None, :] - 2 * a @ b.T
    return np.sqrt(np.maximum(sq, 0.0) / a.shape[1])


def segment_distances(
    test: SegmentTable, db: SegmentTable, candidates: np.ndarray, weights: SegmentWeights, scales: SegmentScales
) -> SegmentDistance:
    """D = b G_d + c P_d + (1 - b - c) L_d (+ e E_d + o O_d) between every test segment and the ``candidates``
    database segments.

    G_d: RMS difference of the z-normalised geometric features; P_d = RMS(P_test - P_template) of the
    length-normalised contours (Eq. 10); L_d = |len_template - len_test| / len_test (Eq. 11), lengths onset to
    next onset. Beyond the paper: E_d, the RMS difference of the length-normalised loudness contours over the
    database's loudness spread; O_d, the difference of onset rates over the database's spread of onset rates.
    """
    zt = (test.geometry - scales.geometry_mean) / scales.geometry_sd
    zd = (db.geometry[candidates] - scales.geometry_mean) / scales.geometry_sd
    g = np.sqrt(np.mean((zt[:, None, :] - zd[None, :, :]) ** 2, axis=2))  # 6 features: the direct form is exact
    p = rms_rows(test.contour, db.contour[candidates])
    lt = test.length[:, None]
    ld = np.abs(db.length[candidates][None, :] - lt) / np.maximum(lt, 1e-6)
    e = rms_rows(test.energy, db.energy[candidates]) / scales.loudness_sd
    o = np.abs(test.onset_rate[:, None] - db.onset_rate[candidates][None, :]) / scales.rhythm_sd
    w = weights
    return SegmentDistance(w.b * g + w.c * p + (1 - w.b - w.c) * ld + w.e * e + w.o * o, g, p, ld, e, o)


# ----------------------------------------------------------------------------------- motion at boundaries


def boundary_kinematics(
    angles: np.ndarray,
    sequence_first: np.ndarray,
    sequence_frames: np.ndarray,
    fps: float,
    sequence: np.ndarray,
    times: np.ndarray,
    window: float,
) -> np.ndarray:
    """Position, velocity and acceleration (n, 3 [P, V, A], channels) of the motion at ``times`` of ``sequence``:
    a least-squares parabola over +-``window`` seconds of frames (robust to tracking noise), clamped to the take."""
    half = max(1, int(round(window * fps)))
    offsets = np.arange(-half, half + 1) / fps
    frame = (times[:, None] + offsets[None, :]) * fps
    last = (sequence_frames[sequence] - 1).astype(np.float64)
    frame = np.clip(frame, 0.0, last[:, None])
    below = np.floor(frame).astype(np.int64)
    above = np.minimum(below + 1, last[:, None].astype(np.int64))
    w = (frame - below)[..., None]
    base = sequence_first[sequence][:, None]
    samples = (1 - w) * angles[base + below] + w * angles[base + above]  # (n, taps, channels)
    design = np.stack([np.ones_like(offsets), offsets, 0.5 * offsets**2], axis=1)
    return np.einsum("kt,ntc->nkc", np.linalg.pinv(design), samples)


def smoothness_weights(start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """omega_P, omega_V, omega_A of Eq. 13: each term averages 1/3 over all (end of i, start of j) database
    pairs, so H averages 1 and weighs like one unit of R. Closed form of the mean over pairs."""
    weights = np.ones(3)
    for k in range(3):
        e, s = end[:, k, :], start[:, k, :]
        mean_sq = (e**2).sum(1).mean() + (s**2).sum(1).mean() - 2 * e.mean(0) @ s.mean(0)
        weights[k] = 1.0 / (3.0 * mean_sq) if mean_sq > 1e-20 else 0.0
    return weights


def warp_kinematics(kinematics: np.ndarray, scale: np.ndarray | None) -> np.ndarray:
    """P, V, A (..., 3, channels) of database motion played ``scale`` database seconds per output second
    (Sec. 5.4 resamples each segment to its test segment's length): V times scale, A times scale^2."""
    if scale is None:
        return kinematics
    powers = np.asarray(scale, dtype=np.float64)[..., None, None] ** np.arange(3)[:, None]
    return kinematics * powers


def transition_costs(
    prev: np.ndarray,
    nxt: np.ndarray,
    db_end: np.ndarray,
    db_start: np.ndarray,
    db_utterance: np.ndarray,
    db_position: np.ndarray,
    weights: np.ndarray,
    w1: float,
    w2: float,
    prev_scale: np.ndarray | None = None,
    next_scale: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """H (Eq. 13) and R (Eq. 14) between candidate sets ``prev`` (..., K) and ``nxt`` (..., K) of database
    segments: arrays (..., K, K). R = 0 when the database holds them consecutively, 2 for the same segment.

    With ``prev_scale`` / ``next_scale`` (same shapes as ``prev`` / ``nxt``: database seconds per output second of
    each candidate for its test segment), velocities and accelerations are compared as the blend will join them,
    each segment resampled to its test segment's length, on the pair's common clock: the velocity step
    V_i s_i - V_j s_j is divided by sqrt(s_i s_j) (the acceleration step by s_i s_j). When both play at the same
    rate this is Eq. 13 on the recordings' clock, so playing a pair uniformly slower is not rewarded (on the
    output clock it would be: slowing shrinks V and A, and the search then prefers slowed-down motion)."""
    end = warp_kinematics(db_end[prev], prev_scale)
    start = warp_kinematics(db_start[nxt], next_scale)
    diff = end[..., :, None, :, :] - start[..., None, :, :, :]  # (..., K, K, 3, channels)
    if prev_scale is not None and next_scale is not None:
        rate = np.asarray(prev_scale, np.float64)[..., :, None] * np.asarray(next_scale, np.float64)[..., None, :]
        common = rate[..., None, None] ** (np.arange(3)[:, None] / 2.0)  # (..., K, K, 3, 1)
        diff = diff / common
    h = np.einsum("...kc,k->...", diff**2, weights)
    same = prev[..., :, None] == nxt[..., None, :]
    consecutive = (db_utterance[prev][..., :, None] == db_utterance[nxt][..., None, :]) & (
        db_position[prev][..., :, None] + 1 == db_position[nxt][..., None, :]
    )
    r = np.where(consecutive, 0.0, np.where(same, 2.0, 1.0))
    return w1 * h, w2 * r


def viterbi(node_cost: np.ndarray, transition: np.ndarray) -> tuple[np.ndarray, float]:
    """Cheapest path through a trellis: node_cost (N, K), transition (N - 1, K, K) from column i to j.
    O(N K^2), vectorised per step. Returns the chosen column per step and the total cost."""
    n, k = node_cost.shape
    if n == 0:
        return np.zeros(0, dtype=np.int64), 0.0
    acc = node_cost[0].copy()
    back = np.zeros((n, k), dtype=np.int64)
    for t in range(1, n):
        total = acc[:, None] + transition[t - 1]
        back[t] = np.argmin(total, axis=0)
        acc = total[back[t], np.arange(k)] + node_cost[t]
    path = np.zeros(n, dtype=np.int64)
    path[-1] = int(np.argmin(acc))
    for t in range(n - 1, 0, -1):
        path[t - 1] = back[t, path[t]]
    return path, float(acc[path[-1]])


# -------------------------------------------------------------------------------------------- the search


@dataclass
class Database:
    """The motion database as the search sees it."""

    segments: SegmentTable
    features: np.ndarray  # (U, F) phrase features per sequence
    start: np.ndarray  # (S, 3, channels) P, V, A at each segment's start
    end: np.ndarray  # (S, 3, channels) at its end
    weights: np.ndarray  # omega_P, omega_V, omega_A
    labels: list[str]
    sources: list[str]
    recordings: list[str]
    speakers: list[str | None]  # per sequence
    reference: SpeakerReference  # per sequence: its speaker's median f0 and spread

    def speaker_reference(self, speaker: str | None) -> tuple[float, float] | None:
        """Median (Hz) and spread (semitones) of ``speaker`` in the database; the only speaker's when the
        database holds one and ``speaker`` is unlabelled; None when not found."""
        known = {s for s in self.speakers}
        if speaker is None and len(known) == 1:
            speaker = next(iter(known))
        if speaker not in known:
            return None
        k = self.speakers.index(speaker)
        return float(self.reference.median[k]), float(self.reference.spread[k])


@dataclass
class SearchSettings:
    """What one utterance's search needs from the stage's params."""

    top_m: int
    k: int
    weights: SegmentWeights
    w1: float
    w2: float
    warp_boundaries: bool


@dataclass
class SearchResult:
    chosen: np.ndarray  # (N,) database segment index
    rank: np.ndarray  # (N,) column of ``chosen`` among the candidates
    candidates: np.ndarray  # (N, K) database segment indices, best first
    candidate_cost: np.ndarray  # (N, K) D
    node_cost: np.ndarray  # (N,) D of the chosen
    smoothness: np.ndarray  # (N,) w1 H into each segment (0 at a sub-sentence start)
    repeat: np.ndarray  # (N,) w2 R into each segment
    phrase_distance: np.ndarray  # (U,) NaN where excluded or unusable
    phrase_selected: np.ndarray  # (U,) bool


def select_phrases(
    test_features: np.ndarray, db: Database, allowed: np.ndarray, top_m: int, k: int, feature_stats
) -> tuple[np.ndarray, np.ndarray]:
    """Phrase stage (Sec. 5.2): distance of every usable database phrase to the test phrase; the top M of them,
    extended until they hold at least K segments. Returns (distance (U,), NaN where unusable; selected (U,))."""
    n_db = len(db.labels)
    seg_count = np.bincount(db.segments.utterance, minlength=n_db)
    usable = allowed & np.isfinite(db.features).all(axis=1) & (seg_count > 0)
    available = int(seg_count[usable].sum())
    if available < k:
        raise UserError(
            f"the database has {available} segments ({int(usable.sum())} usable phrases) after "
            f"exclusions, fewer than k = {k} candidates per test segment: add takes or lower k",
            field="params.k",
        )
    distance = np.full(n_db, np.nan)
    distance[usable] = phrase_distances(test_features, db.features[usable], *feature_stats)
    order = np.flatnonzero(usable)[np.argsort(distance[usable], kind="stable")]
    cumulative = np.cumsum(seg_count[order])
    m = max(min(top_m, len(order)), int(np.searchsorted(cumulative, k)) + 1)
    selected = np.zeros(n_db, dtype=bool)
    selected[order[:m]] = True
    return distance, selected


def top_candidates(dist: SegmentDistance, pool: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The K database segments of ``pool`` nearest each test segment, best first: (indices, their D)."""
    n = dist.total.shape[0]
    if pool.size > k:
        top = np.argpartition(dist.total, k - 1, axis=1)[:, :k]
    else:
        top = np.tile(np.arange(pool.size), (n, 1))
    top = np.take_along_axis(top, np.argsort(np.take_along_axis(dist.total, top, 1), axis=1, kind="stable"), 1)
    return pool[top], np.take_along_axis(dist.total, top, 1)


def subsentence_bounds(subsentence_start: np.ndarray) -> np.ndarray:
    """First segment of each sub-sentence (the first segment always starts one)."""
    starts = np.flatnonzero(subsentence_start)
    if len(starts) == 0 or starts[0] != 0:
        starts = np.concatenate([[0], starts])
    return starts


def path_search(
    test: SegmentTable, db: Database, candidates: np.ndarray, candidate_cost: np.ndarray, settings: SearchSettings
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Viterbi over the trellis of candidates (Eq. 13-15), one search per sub-sentence (Sec. 5.4).
    Returns the chosen column per test segment and the w1 H and w2 R paid into it (0 at sub-sentence starts)."""
    n = len(test)
    # each candidate plays at its own speed once resampled to its test segment's length (Sec. 5.4)
    scale = None
    if settings.warp_boundaries:
        scale = db.segments.length[candidates] / np.maximum(test.length, 1e-6)[:, None]
    h, r = transition_costs(
        candidates[:-1],
        candidates[1:],
        db.end,
        db.start,
        db.segments.utterance,
        db.segments.position,
        db.weights,
        settings.w1,
        settings.w2,
        None if scale is None else scale[:-1],
        None if scale is None else scale[1:],
    )
    rank = np.zeros(n, dtype=np.int64)
    starts = subsentence_bounds(test.subsentence_start)
    for a, z in zip(starts, np.append(starts[1:], n)):
        rank[a:z], _ = viterbi(candidate_cost[a:z], h[a : z - 1] + r[a : z - 1])
    smooth, repeat = np.zeros(n), np.zeros(n)
    steps = np.arange(1, n)
    smooth[1:] = h[steps - 1, rank[:-1], rank[1:]]
    repeat[1:] = r[steps - 1, rank[:-1], rank[1:]]
    smooth[starts] = 0.0
    repeat[starts] = 0.0
    return rank, smooth, repeat


def search_utterance(
    test: SegmentTable,
    test_features: np.ndarray,
    db: Database,
    allowed: np.ndarray,
    settings: SearchSettings,
    scales: SegmentScales,
    feature_stats: tuple[np.ndarray, np.ndarray],
) -> SearchResult:
    """Phrase stage, segment stage and per-sub-sentence Viterbi for one test utterance's segments."""
    k = settings.k
    distance, selected = select_phrases(test_features, db, allowed, settings.top_m, k, feature_stats)
    n = len(test)
    if n == 0:
        empty = np.zeros(0)
        return SearchResult(
            np.zeros(0, np.int64),
            np.zeros(0, np.int64),
            np.zeros((0, k), np.int64),
            np.zeros((0, k)),
            empty,
            empty,
            empty,
            distance,
            selected,
        )
    pool = np.flatnonzero(selected[db.segments.utterance])
    dist = segment_distances(test, db.segments, pool, settings.weights, scales)
    candidates, candidate_cost = top_candidates(dist, pool, k)
    rank, smooth, repeat = path_search(test, db, candidates, candidate_cost, settings)
    rows = np.arange(n)
    return SearchResult(
        candidates[rows, rank],
        rank,
        candidates,
        candidate_cost,
        candidate_cost[rows, rank],
        smooth,
        repeat,
        distance,
        selected,
    )


def sequence_reference(view, field: str, *, required: bool = True) -> SpeakerReference:
    """Speaker median f0 and spread per utterance of a pitch artifact; utterances of a silent speaker take the
    others' median (their contours are empty anyway). No voice anywhere: an error when ``required`` (the
    database), else NaN (a silent test, which gets no segments)."""
    median = np.asarray(view["speaker_median"], dtype=np.float64)
    spread = np.asarray(view["speaker_spread"], dtype=np.float64) if "speaker_spread" in view else np.ones_like(median)
    if not np.isfinite(median).any():
        if not required:
            return SpeakerReference(median, np.ones_like(median))
        raise UserError(
            "no voiced speech in any take of the database: nothing to match the test's pitch against", field=field
        )
    return SpeakerReference(
        np.where(np.isfinite(median), median, np.nanmedian(median)),
        np.where(np.isfinite(spread), spread, np.nanmedian(spread)),
    )


def check_pitch_of_database(db_view, db_pitch) -> list[str]:
    """The database's sequence labels, checked against those its pitch was computed from."""
    labels = list(db_view.meta.get("labels") or [])
    pitch_labels = list(db_pitch.meta.get("labels") or [])
    if labels != pitch_labels:
        raise UserError(
            "database_pitch was not computed from this database (its labels differ: "
            f"{pitch_labels[:4]}... vs {labels[:4]}...); run pitch on the headdb artifact",
            field="inputs.database_pitch",
        )
    return labels


def sequence_layout(db_view, n_labels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Motion angles of the database (checked finite) and each sequence's first frame and frame count."""
    sequence = np.asarray(db_view["sequence"], dtype=np.int64)
    frames = np.bincount(sequence, minlength=n_labels)
    first = np.concatenate([[0], np.cumsum(frames)[:-1]])
    angles = np.asarray(db_view["angles"], dtype=np.float64)
    if not np.isfinite(angles).all():
        raise UserError("NaN in the database motion", field="inputs.database")
    return angles, first, frames


def build_database(db_view, db_pitch, *, unit: str, length: int | None, window: float) -> tuple[Database, int]:
    """Segments, phrase features and boundary kinematics of the database; returns it and the contour length."""
    labels = check_pitch_of_database(db_view, db_pitch)
    reference = sequence_reference(db_pitch, "inputs.database_pitch")
    segs = np.asarray(db_pitch["segments"]).reshape(-1, 3)
    if length is None:
        step = float(db_pitch.meta.get("time_step", 0.01))
        length = max(2, int(round((segs[:, 1] - segs[:, 0]).mean() / step))) if len(segs) else 2
    table = segment_table(db_pitch, reference, unit, length)
    angles, first, frames = sequence_layout(db_view, len(labels))
    fps = float(db_view.meta["fps"])
    start = boundary_kinematics(angles, first, frames, fps, table.utterance, table.times[:, 0], window)
    end = boundary_kinematics(angles, first, frames, fps, table.utterance, table.times[:, 2], window)
    meta = db_view.meta
    speakers = list(meta.get("speakers") or db_pitch.meta.get("speakers") or [None] * len(labels))
    return Database(
        table,
        np.asarray(db_pitch["phrase_features"], dtype=np.float64),
        start,
        end,
        smoothness_weights(start, end) if len(table) else np.ones(3),
        labels,
        list(meta.get("sources") or labels),
        list(meta.get("recordings") or labels),
        speakers,
        reference,
    ), length


TRELLIS_OUTPUTS = {
    "segments": Output.array("f", shape=("segments", 3), dtype="float64", doc="test segments (start, voiced end, end)"),
    "test_onsets": Output.array("f", shape=("test_onsets",), dtype="float64", doc="audio onsets of the test (s)"),
    "test_onset_utterance": Output.array("i", shape=("test_onsets",), dtype="int32"),
    "db_onsets": Output.array("f", shape=("db_onsets",), dtype="float64", doc="audio onsets of the database (s)"),
    "db_onset_sequence": Output.array("i", shape=("db_onsets",), dtype="int32"),
    "segment_utterance": Output.array("i", shape=("segments",), dtype="int32", doc="index into meta labels"),
    "subsentence_start": Output.array("b", shape=("segments",)),
    "chosen": Output.array("i", shape=("segments",), dtype="int32", doc="database segment per test segment"),
    "chosen_rank": Output.array("i", shape=("segments",), dtype="int32", doc="its column in candidates"),
    "candidates": Output.array("i", shape=("segments", None), dtype="int32", doc="top K database segments"),
    "candidate_cost": Output.array("f", shape=("segments", None), dtype="float64", doc="their D (Eq. 12)"),
    "node_cost": Output.array("f", shape=("segments",), dtype="float64", doc="D of the chosen segment"),
    "transition_cost": Output.array(
        "f", shape=("segments",), dtype="float64", doc="C (Eq. 15) from the previous segment; 0 at sub-sentence starts"
    ),
    "transition_smoothness": Output.array("f", shape=("segments",), dtype="float64", doc="w1 H part"),
    "transition_repeat": Output.array("f", shape=("segments",), dtype="float64", doc="w2 R part"),
    "db_segments": Output.array("f", shape=("db_segments", 3), dtype="float64", doc="database segment times"),
    "db_segment_sequence": Output.array(
        "i", shape=("db_segments",), dtype="int32", doc="database (headdb) sequence of each segment"
    ),
    "db_segment_position": Output.array("i", shape=("db_segments",), dtype="int32"),
    "phrase_distance": Output.array(
        "f", shape=("utterances", "db_sequences"), dtype="float64", doc="phrase-stage distance, NaN where excluded"
    ),
    "phrase_selected": Output.array("b", shape=("utterances", "db_sequences"), doc="phrases searched"),
}


def _plot_trellis(view, inputs=None, utterance: int = 0, max_segments: int = 40):
    """Paper Fig. 7: the K candidates per test segment (colour: D) and the chosen path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mask = np.flatnonzero(view["segment_utterance"] == utterance)[:max_segments]
    cost = view["candidate_cost"][mask]
    rank = view["chosen_rank"][mask]
    chosen = view["chosen"][mask]
    seq = view["db_segment_sequence"][chosen]
    pos = view["db_segment_position"][chosen]
    n, k = cost.shape if cost.ndim == 2 else (0, 0)
    fig, ax = plt.subplots(figsize=(max(8, 0.45 * n + 2), 5), constrained_layout=True)
    if n:
        _draw_candidates(fig, ax, cost)
        _draw_chosen_path(ax, view["subsentence_start"][mask], rank, seq, pos)
        _label_chosen(ax, rank, seq, pos, view.meta.get("db_labels", []))
    labels = view.meta.get("labels", [])
    _finish_trellis_axes(ax, k, labels[utterance] if labels else "the test")
    return fig


def _draw_candidates(fig, ax, cost: np.ndarray) -> None:
    """The trellis's nodes: every candidate (test segment, rank) coloured by its node cost, on faint grid lines."""
    n, k = cost.shape
    xs, ys = np.meshgrid(np.arange(n), np.arange(k), indexing="ij")
    for t in range(n - 1):
        for i in range(k):
            ax.plot([t, t + 1], [i, i], color="0.92", lw=0.5, zorder=0)
    sc = ax.scatter(xs.ravel(), ys.ravel(), c=cost.ravel(), cmap="viridis_r", s=40, zorder=2)
    fig.colorbar(sc, ax=ax, label="node cost D (Eq. 12)")


def _draw_chosen_path(ax, sub: np.ndarray, rank: np.ndarray, seq: np.ndarray, pos: np.ndarray) -> None:
    """Dashed lines at sub-sentence starts, and the chosen path: red, orange where it continues a database take."""
    n = len(rank)
    for t in range(n):
        if sub[t]:
            ax.axvline(t - 0.5, color="k", ls="--", lw=0.8)
    for a in range(n):
        if a + 1 < n and not sub[a + 1]:
            consecutive = seq[a] == seq[a + 1] and pos[a] + 1 == pos[a + 1]
            ax.plot(
                [a, a + 1],
                [rank[a], rank[a + 1]],
                color="crimson" if not consecutive else "orange",
                lw=2.5 if consecutive else 1.8,
                zorder=3,
            )
    ax.scatter(np.arange(n), rank, facecolors="none", edgecolors="crimson", s=120, lw=1.5, zorder=4)


def _label_chosen(ax, rank: np.ndarray, seq: np.ndarray, pos: np.ndarray, db_labels: list) -> None:
    """Each chosen node labelled with its database take and segment (take:segment)."""
    for t in range(len(rank)):
        name = db_labels[seq[t]] if seq[t] < len(db_labels) else str(seq[t])
        ax.annotate(
            f"{name}:{pos[t]}",
            (t, rank[t]),
            textcoords="offset points",
            xytext=(0, 9),
            fontsize=6,
            ha="center",
            rotation=60,
        )


def _finish_trellis_axes(ax, k: int, name: str) -> None:
    """Axis labels, ticks and the title of the trellis figure of the test take ``name``."""
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("test segment")
    ax.set_ylabel("candidate rank (0 = best D)")
    ax.set_ylim(k - 0.5 if k else 1, -2.2)  # rank 0 on top, room for the database labels above it
    ax.set_yticks(range(k))
    ax.set_title(
        f"trellis of {name}: chosen path in red, orange where "
        f"database-consecutive;\nlabels: database take:segment; dashed lines: sub-sentence starts",
        fontsize=10,
    )


class TrellisParams(Stage.Params):
    top_m: int = Field(20, ge=1, description="phrases searched (database sequences, mirrors included)")
    k: int = Field(
        3, ge=1, description="candidates per test segment (the paper gives no value; 3 tuned on the shared clips)"
    )
    b: float = Field(0.05, ge=0, le=1, description="weight of G_d (Eq. 12)")
    c: float = Field(0.3, ge=0, le=1, validate_default=True, description="weight of P_d; L_d gets 1 - b - c")
    e: float = Field(0.0, ge=0, description="weight of the loudness-contour distance E_d (beyond the paper; 0: off)")
    o: float = Field(0.0, ge=0, description="weight of the onset-rate distance O_d (beyond the paper; 0: off)")
    w1: float = Field(1.0, ge=0, description="weight of H (Eq. 15)")
    w2: float = Field(1.0, ge=0, description="weight of R (Eq. 15)")
    unit: Literal["semitones", "zscore", "hz"] = Field(
        "semitones",
        description="pitch unit of P_d and G_d: semitones relative to the speaker's median, those divided by the "
        "speaker's spread (z-scores per speaker), or Hz",
    )
    test_speaker: Literal["own", "database"] = Field(
        "database",
        description="reference of the test's pitch: its own speaker's median (from the test takes), or that "
        "speaker's median in the database (the test's speaker label, or the database's only speaker)",
    )
    contour_length: int | None = Field(None, ge=2, description="None: the database's mean voiced length in frames")
    boundary_window: float = Field(0.1, gt=0, description="seconds either side for P, V, A at segment boundaries")
    warp_boundaries: bool = Field(
        True,
        description="H as the blend joins: V, A of each candidate scaled by its resampling to the test segment's "
        "length (False: on the recordings' own clocks)",
    )
    holdout: Literal["none", "take", "speaker"] = Field(
        "none",
        description="leave out of the database, for each test take: nothing; the take itself (its source file, "
        "mirror included); or every take of its speaker",
    )
    exclude_labels: list[str] = Field([], description="database recordings (labels) to leave out")
    same_performance: list[list[str]] = Field(
        [],
        description="groups of take labels that record one performance (two cameras, a re-encoded or cropped copy): "
        "with holdout 'take', a test take also leaves out the other takes of its group (their pieces and mirrors "
        "included), since their motion and voice are its own",
    )
    speaker_motion: Literal["any", "same"] = Field(
        "any",
        description="database motion a test take may use: any speaker's (the paper), or only its own speaker's "
        "when the database holds some after the holdout (beyond the paper; any speaker's otherwise)",
    )

    @field_validator("c")
    @classmethod
    def _weights_sum(cls, value, info):
        b = info.data.get("b")
        if b is not None and b + value > 1 + 1e-12:
            raise ValueError(f"b + c must be at most 1 (got b={b}, c={value}); L_d gets 1 - b - c")
        return value


class Trellis(Stage):
    """Two-stage pitch matching and Viterbi path search (Sec. 5.2-5.3) from test pitch to database segments."""

    Params = TrellisParams
    inputs = {
        "database": Input.artifact("angles", "sequence", doc="headdb artifact (motion)"),
        "database_pitch": Input.artifact("segments", "f0", "phrase_features", doc="pitch of the headdb artifact"),
        "test_pitch": Input.artifact("segments", "f0", "phrase_features", doc="pitch of the test audio"),
    }
    outputs = TRELLIS_OUTPUTS
    figures = {"trellis": _plot_trellis}

    def run(self, params, inputs):
        db, length = build_database(
            inputs["database"],
            inputs["database_pitch"],
            unit=params.unit,
            length=params.contour_length,
            window=params.boundary_window,
        )
        result = search(db, inputs["test_pitch"], params, length, inputs["database"].meta)
        result.arrays.update(onsets_of("test", inputs["test_pitch"]) | onsets_of("db", inputs["database_pitch"]))
        if params.holdout == "take":
            result.warnings += copy_warnings(inputs["database"], params.same_performance)
        return result


def onsets_of(prefix: str, pitch) -> dict[str, np.ndarray]:
    """A pitch artifact's audio onsets and their utterance, carried through for the blend's timing (empty when the
    artifact predates onsets)."""
    has = "onsets" in pitch and "onset_utterance" in pitch
    times = np.asarray(pitch["onsets"], dtype=np.float64) if has else np.zeros(0)
    owner = np.asarray(pitch["onset_utterance"], dtype=np.int32) if has else np.zeros(0, np.int32)
    return {f"{prefix}_onsets": times, f"{prefix}_onset_{'utterance' if prefix == 'test' else 'sequence'}": owner}


def reference_for_test(test_view, db: Database, test_speaker: str) -> tuple[SpeakerReference, np.ndarray]:
    """Per test utterance: the reference of its pitch unit, and the shift (semitones) that re-expresses its level
    phrase features (computed relative to its own speaker's median) relative to that reference."""
    own = sequence_reference(test_view, "inputs.test_pitch", required=False)
    if test_speaker == "own":
        return own, np.zeros(len(own.median))
    speakers = list(test_view.meta.get("speakers") or [None] * len(own.median))
    found = [db.speaker_reference(s) for s in speakers]
    missing = [s for s, f in zip(speakers, found) if f is None]
    if missing:
        raise UserError(
            f"test speaker {missing[0]!r} is not in the database, so its pitch has no database reference; set "
            "test_speaker: own (or label the test take with a database speaker)",
            field="params.test_speaker",
        )
    reference = SpeakerReference(np.array([f[0] for f in found]), np.array([f[1] for f in found]))
    return reference, semitones(own.median, reference.median)


def allowed_sequences(db: Database, params, test_source: str, test_speaker: str | None, label: str) -> np.ndarray:
    """Database sequences one test utterance may use: not in exclude_labels, nor held out (``params.holdout``)."""
    allowed = np.array(
        [
            lab not in params.exclude_labels and rec not in params.exclude_labels
            for lab, rec in zip(db.labels, db.recordings)
        ]
    )
    if params.holdout == "take":
        allowed &= np.array([src != test_source for src in db.sources])
        linked = linked_takes(params.same_performance, take_of(label))
        allowed &= np.array([take_of(lab) not in linked for lab in db.labels])
    elif params.holdout == "speaker":
        if test_speaker is None:
            raise UserError(
                f"holdout: speaker needs the test take's speaker, and '{label}' has no speaker label",
                field="params.holdout",
            )
        allowed &= np.array([spk != test_speaker for spk in db.speakers])
    if params.speaker_motion == "same" and test_speaker is not None:
        own = allowed & np.array([spk == test_speaker for spk in db.speakers])
        allowed = own if own.any() else allowed
    return allowed


def linked_takes(groups: list[list[str]], take: str) -> set[str]:
    """The other takes recorded in one performance with ``take`` (``same_performance``)."""
    return {other for group in groups if take in group for other in group if other != take}


def test_phrase_features(test_view, shift: np.ndarray) -> np.ndarray:
    """The test's phrase features with their pitch-level features moved onto the matching reference."""
    features = np.asarray(test_view["phrase_features"], dtype=np.float64).copy()
    names = list(test_view.meta.get("feature_names") or [])
    level = [names.index(f) for f in test_view.meta.get("level_features", []) if f in names]
    features[:, level] += shift[:, None]
    return features


def search(db: Database, test_view, params, length: int, db_meta: dict) -> Result:
    """The search for every test utterance, packed as the trellis artifact."""
    test_labels = list(test_view.meta.get("labels") or [])
    _check_named_takes(db, params, test_labels)
    test_sources = list(test_view.meta.get("sources") or test_labels)
    test_speakers = list(test_view.meta.get("speakers") or [None] * len(test_labels))
    reference, shift = reference_for_test(test_view, db, params.test_speaker)
    test = segment_table(test_view, reference, params.unit, length)
    features = test_phrase_features(test_view, shift)
    weights = SegmentWeights(params.b, params.c, params.e, params.o)
    settings = SearchSettings(params.top_m, params.k, weights, params.w1, params.w2, params.warp_boundaries)
    scales = segment_scales(db.segments)
    results, excluded = [], []
    for u, label in enumerate(test_labels):
        allowed = allowed_sequences(db, params, test_sources[u], test_speakers[u], label)
        excluded.append([db.labels[i] for i in np.flatnonzero(~allowed)])
        results.append(
            search_utterance(
                test.rows(np.flatnonzero(test.utterance == u)),
                features[u],
                db,
                allowed,
                settings,
                scales,
                zscore_stats(db.features[allowed]),
            )
        )
    meta = {
        "labels": test_labels,
        "sources": test_sources,
        "speakers": test_speakers,
        **_search_meta(test_view, db, params, length, db_meta),
        "phrases_searched": [int(r.phrase_selected.sum()) for r in results],
        "excluded": excluded,
    }
    return pack_search(test, db, results, params, meta)


def _check_named_takes(db: Database, params, test_labels: list[str]) -> None:
    """Every take that ``exclude_labels`` and ``same_performance`` name is a database or test take."""
    unknown = [x for x in params.exclude_labels if x not in db.labels and x not in db.recordings]
    if unknown:
        raise UserError(f"exclude_labels {unknown} are not database labels", field="params.exclude_labels")
    takes = {take_of(x) for x in [*db.labels, *test_labels]}
    strangers = sorted({x for group in params.same_performance for x in group} - takes)
    if strangers:
        raise UserError(
            f"same_performance names {strangers}, which are neither database nor test takes",
            field="params.same_performance",
        )


def _search_meta(test_view, db: Database, params, length: int, db_meta: dict) -> dict:
    """The trellis artifact's meta that does not depend on the search: the test's clocks and the settings."""
    count = len(test_view.meta.get("labels") or [])
    return {
        "durations": [float(x) for x in np.asarray(test_view["utterance_duration"])],
        "fps": list(test_view.meta.get("fps") or [None] * count),
        "frames": list(test_view.meta.get("frames") or [None] * count),
        "db_labels": db.labels,
        "db_fps": float(db_meta["fps"]),
        "k": params.k,
        "contour_length": length,
        "boundary_window": float(params.boundary_window),
        "warp_boundaries": bool(params.warp_boundaries),
        "unit": params.unit,
        "test_speaker": params.test_speaker,
        "holdout": params.holdout,
        "smoothness_weights": db.weights.tolist(),
    }


def pack_search(test: SegmentTable, db: Database, results: list[SearchResult], params, meta: dict) -> Result:
    """Arrays and metrics of the trellis artifact from the per-utterance results."""
    k, n_db = params.k, len(db.labels)

    def cat(name, empty):
        return np.concatenate([getattr(r, name) for r in results]) if results else empty

    smooth, repeat = cat("smoothness", np.zeros(0)), cat("repeat", np.zeros(0))
    seg = db.segments
    arrays = {
        "segments": test.times,
        "segment_utterance": test.utterance.astype(np.int32),
        "subsentence_start": test.subsentence_start.astype(bool),
        "chosen": cat("chosen", np.zeros(0)).astype(np.int32),
        "chosen_rank": cat("rank", np.zeros(0)).astype(np.int32),
        "candidates": cat("candidates", np.zeros((0, k))).astype(np.int32),
        "candidate_cost": cat("candidate_cost", np.zeros((0, k))).astype(np.float64),
        "node_cost": cat("node_cost", np.zeros(0)).astype(np.float64),
        "transition_cost": (smooth + repeat).astype(np.float64),
        "transition_smoothness": smooth.astype(np.float64),
        "transition_repeat": repeat.astype(np.float64),
        "db_segments": seg.times,
        "db_segment_sequence": seg.utterance.astype(np.int32),
        "db_segment_position": seg.position.astype(np.int32),
        "phrase_distance": np.stack([r.phrase_distance for r in results]) if results else np.zeros((0, n_db)),
        "phrase_selected": np.stack([r.phrase_selected for r in results]) if results else np.zeros((0, n_db), bool),
    }
    return Result(arrays, meta, search_metrics(arrays, seg, test.subsentence_start, params.w2))


def search_metrics(arrays: dict, seg: SegmentTable, subsentence_start: np.ndarray, w2: float) -> dict:
    """Costs of the chosen path, and how often it continues a database take or repeats a segment."""
    chosen = arrays["chosen"]
    n = len(chosen)
    joins = ~np.asarray(subsentence_start, dtype=bool)
    consecutive = np.zeros(n, dtype=bool)
    if n > 1:
        consecutive[1:] = (seg.utterance[chosen[1:]] == seg.utterance[chosen[:-1]]) & (
            seg.position[chosen[1:]] == seg.position[chosen[:-1]] + 1
        )
    consecutive &= joins
    repeats = arrays["transition_repeat"][joins] == 2 * w2
    return {
        "segments": n,
        "db_segments": len(seg),
        "total_cost": float(arrays["node_cost"].sum() + arrays["transition_cost"].sum()),
        "mean_node_cost": float(arrays["node_cost"].mean()) if n else 0.0,
        "mean_transition_cost": float(arrays["transition_cost"][joins].mean()) if joins.any() else 0.0,
        "consecutive_fraction": float(consecutive[joins].mean()) if joins.any() else 0.0,
        "repeat_fraction": float(repeats.mean()) if joins.any() and w2 > 0 else 0.0,
    }
