"""Trellis search over the head-motion database (paper Sec. 5.2-5.3, Eq. 13-15).

For each test utterance:
1. phrase stage: z-normalised phrase features (Dellaert-style prosody) against every database phrase, Euclidean
   distance, keep the top M phrases (more when they hold fewer than K segments);
2. segment stage: for each test segment, D = b G_d + c P_d + (1 - b - c) L_d (Eq. 10-12, ``stages.head.segments``)
   against the segments of those phrases, keep the top K;
3. Viterbi over the trellis of K candidates per test segment with transition cost C = w1 H + w2 R (Eq. 13-15),
   one search per sub-sentence (breath pauses bound the search, Sec. 5.4).

H compares the boundary velocity and acceleration as the blend will join them: each candidate is resampled to
its test segment's length (Sec. 5.4), so its V and A are scaled by its rate, and the pair is compared on its common
clock (``warp_boundaries``, default; see ``transition_costs``). Comparing each recording's own-clock V and A
(the earlier behaviour) mixed units whenever two candidates play at different rates; comparing on the output
clock would reward slowing motion down (it shrinks V and A), which on CREMA-D picked segments played at 65%.
Motion-blend measures its join velocity steps with the same parabola fits (``boundary_kinematics``, meta
``boundary_window``).

Also the database as the search sees it (``Database``, ``build_database``: segments, phrase features, P, V, A at
segment boundaries, omega of Eq. 13). The stage that runs the search is ``stages.head.trellis``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from msflow import UserError
from stages.head.segments import (
    SegmentDistance,
    SegmentScales,
    SegmentTable,
    SegmentWeights,
    SpeakerReference,
    phrase_distances,
    segment_distances,
    segment_table,
)

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
