"""Evaluation of synthesised head motion (paper Sec. 5) against the real motion and three baselines, as metrics.

The pipeline (``eval/head.yaml``) synthesises head motion for every tracked take from its own audio with that take
(``trellis.holdout: take``) or its whole speaker (``holdout: speaker``) left out of the database; this stage
scores the synthesis beside:

- ``real``: the take's own motion (the level to reach);
- ``shifted``: the same motion shifted in time by at least ``min_shift`` seconds, reflected at the take's ends (real
  motion, wrong timing);
- ``random``: random excerpts of matched length of the database motion the search was allowed to use (other real
  motion, wrong timing: the baseline the search must beat);
- ``path``: a random path through the same database segments, stitched exactly like the synthesis (what the
  search adds over chance with the same blending);
- ``noise``: the real motion with its Fourier phases randomised (the same spectrum, smooth, timing destroyed);
- ``still``: the real motion's mean pose.

Takes are cut into evaluation utterances of about ``window`` seconds. Per utterance and motion: beat alignment
(stages.head.beats) with the audio onsets and with the pitch accents; Wasserstein distances of angular speed and
acceleration to the real motion. Per speaker and motion, all its utterances pooled: each angle's p5..p95 against the
speaker's real p5..p95 (amplitude ratio, inside or not, fraction of frames inside). Per take: drift, and
the largest angular acceleration at the synthesis's joins against the speaker's real 99th percentile. Random
baselines average ``draws`` draws. Pooled: means over utterances; ``ba_rel`` = (synth - random) / (real - random)
with a bootstrap interval over takes (resampled with their utterances).

How to read it (docs/head.md): the beat-alignment signal of real motion is small (real minus shifted a few
hundredths), so a per-utterance win rate of the synthesis over random motion cannot be expected above the real
motion's own.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field

from msflow import Input, Output, Result, Stage, UserError

MOTIONS = ("synth", "real", "shifted", "random", "path", "noise", "still")
ANGLES = ("yaw", "pitch", "roll")


# ------------------------------------------------------------------------------------------------ takes


@dataclass
class Take:
    """One test take as the evaluation sees it (angles in radians at ``fps``, times in seconds from frame 0)."""

    label: str
    speaker: str
    fps: float
    real: np.ndarray  # (n, 3) the real motion, centred like the database
    synth: np.ndarray  # (n, 3)
    onsets: np.ndarray  # audio onsets
    accents: np.ndarray  # pitch accents
    joins: np.ndarray  # join times of the synthesis
    allowed: np.ndarray  # (db sequences,) bool: what the search could use for this take
    known: bool = False  # the database the search could use holds other motion of this take's speaker


def evaluation_windows(n: int, fps: float, window: float) -> list[tuple[int, int]]:
    """[start, stop) frames cutting ``n`` frames into the number of nearly equal pieces closest to ``window``
    seconds each (at least one)."""
    pieces = max(1, int(round(n / fps / window)))
    edges = np.linspace(0, n, pieces + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b - a >= 3]


def scored_windows(n: int, fps: float, window: float, skip: float) -> list[tuple[int, int]]:
    """``evaluation_windows`` of the frames from ``skip`` seconds on (none when the take is not longer)."""
    start = min(n, int(round(skip * fps)))
    return [(a + start, b + start) for a, b in evaluation_windows(n - start, fps, window)] if n > start else []


def take_audio(view, k: int) -> tuple[np.ndarray, int, float]:
    """Samples, rate and offset (time of the first sample on the take's clock) of sequence ``k``'s audio."""
    if "audio" not in view or "audio_bounds" not in view:
        raise UserError("the reference takes carry no audio (track the videos with audio)", field="inputs.reference")
    a, b = np.asarray(view["audio_bounds"]).reshape(-1, 2)[k]
    offsets = view.meta.get("audio_offset", 0.0)
    offset = offsets[k] if isinstance(offsets, list) else offsets
    return (
        np.asarray(view["audio"][a:b], dtype=np.float32),
        int(view.meta.get("audio_rate") or 16000),
        float(offset or 0),
    )


def take_accents(pitch, u: int, prominence: float) -> np.ndarray:
    """Pitch accents of test utterance ``u`` (semitones relative to its speaker's median)."""
    from stages.head.beats import pitch_accents
    from stages.head.pitch import semitones

    mask = np.asarray(pitch["pitch_utterance"]) == u
    median = float(np.asarray(pitch["speaker_median"])[u])
    if not np.isfinite(median):
        return np.zeros(0)
    st = semitones(np.asarray(pitch["f0"], dtype=np.float64)[mask], median)
    return pitch_accents(np.asarray(pitch["pitch_time"])[mask], st, prominence=prominence)


def load_takes(inputs: dict, params) -> list[Take]:
    """Real and synthesised motion, audio beats, joins and allowed database sequences of every test take."""
    from stages.head.beats import audio_onsets
    from stages.head.measures import reference_angles

    synthesis, trellis, reference = inputs["synthesis"], inputs["trellis"], inputs["reference"]
    labels = list(trellis.meta.get("labels") or [])
    if list(synthesis.meta.get("labels") or []) != labels:
        raise UserError("the synthesis was not stitched from this trellis (labels differ)", field="inputs.synthesis")
    db_labels = list(inputs["database"].meta.get("labels") or [])
    if list(trellis.meta.get("db_labels") or []) != db_labels:
        raise UserError("the trellis was searched over a different database", field="inputs.database")
    ref_labels = list(reference.meta.get("labels") or [])
    db_speakers = list(inputs["database"].meta.get("speakers") or [None] * len(db_labels))
    fps = float(synthesis.meta["fps"])
    speakers = list(trellis.meta.get("speakers") or [None] * len(labels))
    excluded = trellis.meta.get("excluded") or [[] for _ in labels]
    takes = []
    for u, label in enumerate(labels):
        if label not in ref_labels:
            raise UserError(f"the reference takes have no '{label}' to compare with", field="inputs.reference")
        real = reference_angles(reference, label, len(labels), fps)
        synth = np.asarray(synthesis["angles"])[np.asarray(synthesis["sequence"]) == u]
        n = min(len(real), len(synth))
        samples, rate, offset = take_audio(reference, ref_labels.index(label))
        onsets = audio_onsets(samples, rate, offset=offset, delta=params.onset_delta, min_gap=params.onset_min_gap)
        joins = np.asarray(synthesis["joins"])[np.asarray(synthesis["join_utterance"]) == u]
        allowed = np.array([name not in excluded[u] for name in db_labels])
        speaker = speakers[u] or label
        takes.append(
            Take(
                label,
                speaker,
                fps,
                real[:n],
                synth[:n],
                onsets,
                take_accents(inputs["test_pitch"], u, params.accent_prominence),
                joins[joins < (n - 2) / fps],
                allowed,
                bool(any(ok and x == speaker for ok, x in zip(allowed, db_speakers))),
            )
        )
    return takes


# ------------------------------------------------------------------------------------------- baselines


def random_path_trellis(trellis, allowed: list[np.ndarray], rng: np.random.Generator):
    """The trellis artifact with every chosen segment replaced by a random segment of the database phrases the
    search was allowed to use for its take."""
    from msflow.testing import artifact

    arrays = {k: np.asarray(trellis[k]) for k in trellis.names}
    chosen = arrays["chosen"].copy()
    segment_sequence = arrays["db_segment_sequence"]
    for u, mask in enumerate(allowed):
        rows = np.flatnonzero(arrays["segment_utterance"] == u)
        pool = np.flatnonzero(mask[segment_sequence])
        if len(rows) and len(pool):
            chosen[rows] = rng.choice(pool, size=len(rows))
    arrays["chosen"] = chosen
    return artifact(arrays, trellis.meta)


def random_excerpt(db, allowed: np.ndarray, n: int, fps: float, rng: np.random.Generator) -> np.ndarray:
    """``n`` frames at ``fps`` of one allowed database sequence (chosen in proportion to its length), from a random
    start; a sequence shorter than that plays forwards and backwards (its speeds and spectrum kept)."""
    sequences = np.flatnonzero(allowed)
    lengths = db.frames[sequences] / db.fps
    s = int(rng.choice(sequences, p=lengths / lengths.sum()))
    length = db.frames[s] / db.fps
    need = n / fps
    start = rng.uniform(0.0, max(length - need, 0.0))
    t = start + np.arange(n) / fps
    period = 2 * max(length - 1.0 / db.fps, 1e-9)
    t = np.mod(t, period)
    t = np.where(t > period / 2, period - t, t)  # reflect
    return db.sample(s, t)[:, :3]


def endpoint_ramp(angles: np.ndarray) -> np.ndarray:
    """The straight line from the first frame to the last: without it the motion is periodic without a jump, so
    its Fourier transform has no spurious high frequencies from the wrap-around."""
    u = np.linspace(0.0, 1.0, len(angles))[:, None]
    return angles[:1] + u * (angles[-1:] - angles[:1])


def phase_randomised(angles: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Smooth noise with the motion's own power spectrum: its Fourier phases (after removing the endpoint ramp)
    replaced by random ones, the same for every angle (which keeps the angles' cross-spectrum); ramp added back."""
    ramp = endpoint_ramp(angles)
    spectrum = np.fft.rfft(angles - ramp, axis=0)
    phase = rng.uniform(0, 2 * np.pi, len(spectrum))
    phase[0] = 0.0
    if len(angles) % 2 == 0:
        phase[-1] = 0.0
    return np.fft.irfft(spectrum * np.exp(1j * phase)[:, None], n=len(angles), axis=0) + ramp


def reflect_index(index: np.ndarray, n: int) -> np.ndarray:
    """Frame indices folded into [0, n) by reflection at both ends (the motion plays on backwards)."""
    if n < 2:
        return np.zeros_like(index)
    period = 2 * (n - 1)
    index = np.mod(index, period)
    return np.where(index >= n, period - index, index)


def shifted_motion(angles: np.ndarray, fps: float, min_shift: float, rng: np.random.Generator) -> np.ndarray:
    """The same frames, shifted in time by a random shift of at least ``min_shift`` seconds (a quarter of the take
    at most when the take is short), reflected at the take's ends: real motion with the wrong timing, continuous,
    and with exactly the take's values."""
    n = len(angles)
    lo = int(min(min_shift * fps, n / 4))
    shift = int(rng.integers(max(lo, 1), max(2 * (n - 1) - lo, lo + 1) + 1))
    return angles[reflect_index(np.arange(n) + shift, n)]


# ------------------------------------------------------------------------------------------- the scores


@dataclass
class WindowScores:
    """Per evaluation utterance (rows) and motion (columns, ``MOTIONS``)."""

    take: np.ndarray  # (W,) take index
    bounds: np.ndarray  # (W, 2) seconds
    beat_onset: np.ndarray  # (W, M) beat alignment with audio onsets
    beat_accent: np.ndarray  # (W, M) with pitch accents
    speed_w1: np.ndarray  # (W, M) deg/s, against the real motion
    accel_w1: np.ndarray  # (W, M) deg/s^2
    correlation: np.ndarray  # (W, M) Pearson correlation with the real motion, mean over the angles that move


def motion_scores(motion: np.ndarray, real: np.ndarray, fps: float, onsets, accents, params) -> list[float]:
    """Beat alignment with ``onsets`` and with ``accents`` (on the excerpt's clock), the Wasserstein distances of
    angular speed and acceleration to ``real`` and the correlation with ``real``, of one motion excerpt."""
    from stages.head.beats import beat_alignment, kinematic_beats
    from stages.head.measures import angular_acceleration, angular_speed, wasserstein

    beats = kinematic_beats(motion, fps, kind=params.head_beats, smoothing=params.beat_smoothing)
    return [
        beat_alignment(beats, onsets, params.sigma),
        beat_alignment(beats, accents, params.sigma),
        wasserstein(angular_speed(motion, fps), angular_speed(real, fps)),
        wasserstein(angular_acceleration(motion, fps), angular_acceleration(real, fps)),
        pose_correlation(motion, real),
    ]


def pose_correlation(motion: np.ndarray, real: np.ndarray) -> float:
    """Mean over the angles the real motion moves in of the Pearson correlation of ``motion`` with ``real`` (0
    where ``motion`` is constant): near 0 when the motion is not a function of the same voice, 1 for the real
    motion itself. 0 when the real motion is still."""
    a, b = motion - motion.mean(axis=0), real - real.mean(axis=0)
    moves = (b * b).sum(axis=0) > 1e-16
    if not moves.any():
        return 0.0
    norm = np.sqrt((a * a).sum(axis=0) * (b * b).sum(axis=0))
    r = np.where(norm > 1e-20, (a * b).sum(axis=0) / np.maximum(norm, 1e-300), 0.0)
    return float(r[moves].mean())


def window_motions(take: Take, a: int, b: int, shifted, paths, db, rng, params) -> dict[str, list[np.ndarray]]:
    """Every motion's excerpt(s) of frames [a, b) of one take; baselines as lists of draws."""
    n = b - a
    real = take.real[a:b]
    return {
        "synth": [take.synth[a:b]],
        "real": [real],
        "shifted": [s[a:b] for s in shifted],
        "random": [random_excerpt(db, take.allowed, n, take.fps, rng) for _ in range(params.draws)],
        "path": [p[a:b] for p in paths],
        "noise": [phase_randomised(real, rng) for _ in range(params.draws)],
        "still": [np.repeat(real.mean(axis=0, keepdims=True), n, axis=0)],
    }


def score_windows(takes: list[Take], paths: list[list[np.ndarray]], db, params) -> tuple[WindowScores, dict]:
    """``WindowScores`` of every evaluation utterance of every take (baselines averaged over their draws), and
    every motion's excerpts pooled per speaker (speaker -> motion -> list of arrays) for the range measures."""
    rng = np.random.default_rng(params.seed + 1)
    rows, pooled = [], {}
    for t, take in enumerate(takes):
        shifted = [shifted_motion(take.real, take.fps, params.min_shift, rng) for _ in range(params.draws)]
        own_paths = [p[t][: len(take.real)] for p in paths]
        for a, b in scored_windows(len(take.real), take.fps, params.window, params.skip_seconds):
            t0 = a / take.fps
            motions = window_motions(take, a, b, shifted, own_paths, db, rng, params)
            scores = []
            for name in MOTIONS:
                draws = [
                    motion_scores(m, take.real[a:b], take.fps, take.onsets - t0, take.accents - t0, params)
                    for m in motions[name]
                ]
                scores.append(np.mean(draws, axis=0))
                pooled.setdefault(take.speaker, {}).setdefault(name, []).extend(motions[name])
            rows.append((t, (t0, b / take.fps), np.array(scores)))
    table = np.array([r[2] for r in rows]).reshape(len(rows), len(MOTIONS), 5)
    windows = WindowScores(
        np.array([r[0] for r in rows], dtype=np.int32),
        np.array([r[1] for r in rows], dtype=np.float64).reshape(-1, 2),
        *(table[:, :, i] for i in range(5)),
    )
    return windows, pooled


@dataclass
class RangeScores:
    """Per speaker (rows) and motion (columns): each angle's p5..p95 against the speaker's real p5..p95."""

    speakers: list[str]
    amplitude: np.ndarray  # (S, M, 3) (p95 - p5) of the motion over (p95 - p5) of the real motion (NaN: still)
    inside: np.ndarray  # (S, M, 3) 1 where the motion's [p5, p95] lies inside the real [p5, p95]
    in_range: np.ndarray  # (S, M) fraction of frames (all angles) inside the real [p5, p95]
    fit: np.ndarray  # (S, M, 3) 1 where the motion's range fits the real one (``range_fit``)
    halves_fit: np.ndarray  # (S, 3) the same for the speaker's real motion, one half against the other
    known: np.ndarray | None = None  # (S,) the database held other motion of the speaker (its amplitude known)


def range_fit(motion: np.ndarray, real: np.ndarray, span_tolerance: float, margin: float) -> np.ndarray:
    """Per angle, whether a motion's p5..p95 fits a real p5..p95 (both (2, angles) from ``percentile_range``):
    its span p95 - p5 within a factor ``span_tolerance`` of the real span (either way), and its p5..p95 inside the
    real p5..p95 widened by ``margin`` times the real span at each end. A motion shrunk below 1 / span_tolerance
    of the real amplitude fails however well it stays inside the range; one that is large enough fails if it sits
    off-centre. An angle the real motion never moves in fits when the motion does not move either."""
    span, real_span = motion[1] - motion[0], real[1] - real[0]
    moves = real_span > 1e-6
    ratio = span / np.where(moves, real_span, 1.0)
    sized = (ratio >= 1.0 / span_tolerance) & (ratio <= span_tolerance)
    inside = (motion[0] >= real[0] - margin * real_span - 1e-9) & (motion[1] <= real[1] + margin * real_span + 1e-9)
    return np.where(moves, sized & inside, span <= 1e-6)


def halves_range_fit(real: np.ndarray, span_tolerance: float, margin: float) -> np.ndarray:
    """``range_fit`` of a speaker's real motion (frames, 3) against itself: its first half, centred on its mean,
    against the range of the second half, centred alike, and the other way round (mean of the two, per angle).
    What another stretch of the speaker's own motion achieves: the level a synthesis can be asked for."""
    from stages.head.measures import percentile_range

    half = len(real) // 2
    if half < 2:
        return np.ones(real.shape[1])
    a, b = real[:half] - real[:half].mean(axis=0), real[half:] - real[half:].mean(axis=0)
    ra, rb = percentile_range(a), percentile_range(b)
    forth, back = range_fit(ra, rb, span_tolerance, margin), range_fit(rb, ra, span_tolerance, margin)
    return 0.5 * (forth.astype(float) + back.astype(float))


def range_scores(pooled: dict[str, dict[str, list[np.ndarray]]], span_tolerance: float, margin: float) -> RangeScores:
    """``RangeScores`` from every motion's excerpts pooled per speaker (``score_windows``)."""
    from stages.head.measures import percentile_range

    speakers = sorted(pooled)
    amplitude = np.zeros((len(speakers), len(MOTIONS), 3))
    inside = np.zeros_like(amplitude)
    fit = np.zeros_like(amplitude)
    in_range = np.zeros((len(speakers), len(MOTIONS)))
    halves = np.zeros((len(speakers), 3))
    for i, speaker in enumerate(speakers):
        real_motion = np.concatenate(pooled[speaker]["real"])
        real = percentile_range(real_motion)
        spread = real[1] - real[0]
        moves = spread > 1e-6  # an angle the real motion never moves in has no amplitude to match (NaN)
        halves[i] = halves_range_fit(real_motion, span_tolerance, margin)
        for j, name in enumerate(MOTIONS):
            motion = np.concatenate(pooled[speaker][name])
            p = percentile_range(motion)
            amplitude[i, j] = np.where(moves, (p[1] - p[0]) / np.where(moves, spread, 1.0), np.nan)
            inside[i, j] = (p[0] >= real[0] - 1e-9) & (p[1] <= real[1] + 1e-9)
            fit[i, j] = range_fit(p, real, span_tolerance, margin)
            degrees = np.degrees(motion)
            in_range[i, j] = np.mean((degrees >= real[0]) & (degrees <= real[1]))
    return RangeScores(speakers, amplitude, inside, in_range, fit, halves)


def speaker_acceleration_p99(takes: list[Take], cutoff: float | None = None) -> dict[str, float]:
    """Each speaker's real 99th percentile of angular acceleration (deg/s^2) over all of that speaker's takes; with
    a ``cutoff`` (Hz), of the real motion low-passed there first (stages.head.measures.lowpass_angles): the
    acceleration of the head's own motion without the tracking jitter, which dominates the raw figure."""
    from stages.head.measures import angular_acceleration, lowpass_angles

    def motion(t):
        return t.real if cutoff is None else lowpass_angles(t.real, t.fps, cutoff)

    return {
        speaker: float(
            np.percentile(
                np.concatenate([angular_acceleration(motion(t), t.fps) for t in takes if t.speaker == speaker]), 99
            )
        )
        for speaker in {t.speaker for t in takes}
    }


def take_scores(takes: list[Take], paths: list[list[np.ndarray]], jitter_cutoff: float) -> dict[str, np.ndarray]:
    """Per take: drift of the synthesis, the real motion and the random path (deg); the largest angular
    acceleration at the synthesis's joins, of the synthesis and of the real motion at the same times (deg/s^2);
    the speaker's real 99th percentile."""
    from stages.head.measures import JOIN_MEASURE_WINDOW, join_acceleration, linear_drift

    p99 = speaker_acceleration_p99(takes)
    p99_band = speaker_acceleration_p99(takes, jitter_cutoff)
    drift = np.array(
        [
            [
                linear_drift(t.synth, t.fps),
                linear_drift(t.real, t.fps),
                np.mean([linear_drift(p[k][: len(t.real)], t.fps) for p in paths]) if paths else np.nan,
            ]
            for k, t in enumerate(takes)
        ]
    ).reshape(-1, 3)

    def at_joins(motion, take):
        return join_acceleration(motion, take.fps, take.joins, JOIN_MEASURE_WINDOW)

    def largest(motion, take):
        acc = at_joins(motion, take)
        return float(acc.max()) if len(acc) else 0.0

    def over(motion, take):
        return int(np.sum(at_joins(motion, take) > p99[take.speaker]))

    return {
        "drift": drift,
        "join_acc_max": np.array([[largest(t.synth, t), largest(t.real, t)] for t in takes]).reshape(-1, 2),
        "joins_over_p99": np.array([[over(t.synth, t), over(t.real, t), len(t.joins)] for t in takes]).reshape(-1, 3),
        "real_acc_p99": np.array([p99[t.speaker] for t in takes]),
        "real_acc_p99_band": np.array([p99_band[t.speaker] for t in takes]),
    }


# -------------------------------------------------------------------------------------------- pooling


def bootstrap_ratio(
    synth: np.ndarray, real: np.ndarray, base: np.ndarray, groups: np.ndarray, draws: int, rng
) -> tuple[float, float, float]:
    """(mean synth - mean base) / (mean real - mean base) over utterances, and its 95% interval from resampling
    the groups (takes) with replacement, each with all its utterances. NaN where real and base tie."""

    def ratio(index):
        gap = real[index].mean() - base[index].mean()
        return (synth[index].mean() - base[index].mean()) / gap if abs(gap) > 1e-12 else np.nan

    members = [np.flatnonzero(groups == g) for g in np.unique(groups)]
    estimate = ratio(np.arange(len(synth)))
    values = []
    for _ in range(draws):
        pick = rng.integers(len(members), size=len(members))
        values.append(ratio(np.concatenate([members[i] for i in pick])))
    values = np.array(values)
    values = values[np.isfinite(values)]
    if not len(values):
        return float(estimate), float("nan"), float("nan")
    return float(estimate), float(np.percentile(values, 2.5)), float(np.percentile(values, 97.5))


def paired_z(a: np.ndarray, b: np.ndarray) -> float:
    """Mean of a - b over its standard error (0 with fewer than two pairs or no spread)."""
    d = a - b
    if len(d) < 2 or d.std(ddof=1) == 0:
        return 0.0
    return float(d.mean() / (d.std(ddof=1) / np.sqrt(len(d))))


def pooled_metrics(w: WindowScores, ranges: RangeScores, per_take: dict, params) -> dict[str, float]:
    """The stage metrics: pooled means, the relative beat alignment with its interval, win rates, guards."""
    metrics = {"takes": int(len(per_take["drift"])), "utterances": int(len(w.take))}
    metrics.update(_beat_metrics(w, params))
    metrics.update(_motion_and_range_metrics(w, ranges))
    metrics.update(_drift_and_join_metrics(per_take))
    return {k: (v if np.isfinite(v) else 0.0) for k, v in metrics.items()}


def _beat_metrics(w: WindowScores, params) -> dict[str, float]:
    """Beat alignment pooled per motion, relative to the real motion over the random baseline (with its bootstrap
    interval), the win rates and the paired z-scores against the baselines."""
    col = {name: i for i, name in enumerate(MOTIONS)}
    ba, acc = w.beat_onset, w.beat_accent
    rng = np.random.default_rng(params.seed + 2)
    rel, lo, hi = bootstrap_ratio(ba[:, 0], ba[:, 1], ba[:, col["random"]], w.take, params.bootstrap, rng)
    rel_accent = bootstrap_ratio(acc[:, 0], acc[:, 1], acc[:, col["random"]], w.take, params.bootstrap, rng)
    metrics = {f"ba_{m}": float(ba[:, i].mean()) for m, i in col.items()}
    metrics.update({f"ba_accent_{m}": float(acc[:, i].mean()) for m, i in col.items()})
    metrics.update(
        {
            "ba_rel": rel,
            "ba_rel_lo": lo,
            "ba_rel_hi": hi,
            "ba_accent_rel": rel_accent[0],
            "ba_accent_rel_lo": rel_accent[1],
            "ba_accent_rel_hi": rel_accent[2],
            "ba_synth_over_real": float(ba[:, 0].mean() / max(ba[:, 1].mean(), 1e-12)),
            "win_synth_random": float(np.mean(ba[:, 0] > ba[:, col["random"]])),
            "win_real_random": float(np.mean(ba[:, 1] > ba[:, col["random"]])),
            "win_real_shifted": float(np.mean(ba[:, 1] > ba[:, col["shifted"]])),
            "win_synth_path": float(np.mean(ba[:, 0] > ba[:, col["path"]])),
            "z_real_shifted": paired_z(ba[:, 1], ba[:, col["shifted"]]),
            "z_real_random": paired_z(ba[:, 1], ba[:, col["random"]]),
            "z_synth_random": paired_z(ba[:, 0], ba[:, col["random"]]),
        }
    )
    return metrics


def _motion_and_range_metrics(w: WindowScores, ranges: RangeScores) -> dict[str, float]:
    """Per motion: speed and acceleration distances and correlation to the real motion, amplitude and how well it
    fits the speaker's range; the range fit of the real motion's halves, overall and for speakers the database
    knows."""
    metrics = {}
    for i, m in enumerate(MOTIONS):
        if m != "real":
            metrics[f"speed_w1_{m}"] = float(np.nanmean(w.speed_w1[:, i]))
            metrics[f"accel_w1_{m}"] = float(np.nanmean(w.accel_w1[:, i]))
            metrics[f"corr_{m}"] = float(w.correlation[:, i].mean())
        metrics[f"amplitude_{m}"] = (
            float(np.nanmean(ranges.amplitude[:, i])) if np.isfinite(ranges.amplitude[:, i]).any() else 0.0
        )
        metrics[f"range_ok_{m}"] = float(ranges.inside[:, i].mean())
        metrics[f"range_fit_{m}"] = float(ranges.fit[:, i].mean())
        metrics[f"in_range_{m}"] = float(ranges.in_range[:, i].mean())
    metrics["range_fit_halves"] = float(ranges.halves_fit.mean())
    known = ranges.known if ranges.known is not None else np.zeros(len(ranges.speakers), bool)
    metrics["speakers_known"] = int(known.sum())
    if known.any():
        metrics["range_fit_known_synth"] = float(ranges.fit[known, 0].mean())
        metrics["range_fit_known_halves"] = float(ranges.halves_fit[known].mean())
    return metrics


def _drift_and_join_metrics(per_take: dict) -> dict[str, float]:
    """Drift of each motion, and the acceleration at the synthesis's joins against the speakers' real 99th
    percentile (raw and in the head-motion band)."""
    drift, joins, p99 = per_take["drift"], per_take["join_acc_max"], per_take["real_acc_p99"]
    p99_band = per_take["real_acc_p99_band"]
    over = per_take["joins_over_p99"]
    return {
        "drift_synth": float(drift[:, 0].mean()),
        "drift_real": float(drift[:, 1].mean()),
        "drift_path": float(np.nanmean(drift[:, 2])) if np.isfinite(drift[:, 2]).any() else 0.0,
        "join_acc_max": float(joins[:, 0].max()) if len(joins) else 0.0,
        "join_acc_max_real": float(joins[:, 1].max()) if len(joins) else 0.0,
        "join_acc_over_p99": float((joins[:, 0] / np.maximum(p99, 1e-9)).max()) if len(joins) else 0.0,
        "joins_over_p99_synth": float(over[:, 0].sum() / max(over[:, 2].sum(), 1)),
        "joins_over_p99_real": float(over[:, 1].sum() / max(over[:, 2].sum(), 1)),
        "real_acc_p99": float(p99.min()) if len(p99) else 0.0,
        "real_acc_p99_band": float(p99_band.min()) if len(p99_band) else 0.0,
        "join_acc_over_p99_band": float((joins[:, 0] / np.maximum(p99_band, 1e-9)).max()) if len(joins) else 0.0,
    }


# ------------------------------------------------------------------------------------------- the stage

HEAD_EVAL_OUTPUTS = {
    "window_take": Output.array("i", shape=("utterances",), dtype="int32", doc="take of each evaluation utterance"),
    "window_bounds": Output.array("f", shape=("utterances", 2), dtype="float64", doc="start, end (s) in its take"),
    "beat_align_onset": Output.array(
        "f", shape=("utterances", len(MOTIONS)), dtype="float64", doc="beat alignment with audio onsets, meta motions"
    ),
    "beat_align_accent": Output.array(
        "f", shape=("utterances", len(MOTIONS)), dtype="float64", doc="beat alignment with pitch accents"
    ),
    "speed_w1": Output.array(
        "f", shape=("utterances", len(MOTIONS)), dtype="float64", doc="W1 of angular speed to the real motion, deg/s"
    ),
    "accel_w1": Output.array(
        "f", shape=("utterances", len(MOTIONS)), dtype="float64", doc="W1 of angular acceleration, deg/s^2"
    ),
    "amplitude": Output.array(
        "f",
        shape=("speakers", len(MOTIONS), 3),
        dtype="float64",
        doc="per speaker (meta range_speakers) and angle: p95 - p5 of the motion over that of the real motion",
    ),
    "correlation": Output.array(
        "f", shape=("utterances", len(MOTIONS)), dtype="float64", doc="correlation with the real motion"
    ),
    "range_ok": Output.array(
        "f",
        shape=("speakers", len(MOTIONS), 3),
        dtype="float64",
        doc="1 where the motion's p5..p95 lies inside the speaker's real p5..p95",
    ),
    "range_fit": Output.array(
        "f",
        shape=("speakers", len(MOTIONS), 3),
        dtype="float64",
        doc="1 where the motion's p5..p95 fits the speaker's real one: span within params span_tolerance, inside "
        "the real range widened by params range_margin of its span",
    ),
    "range_fit_halves": Output.array(
        "f",
        shape=("speakers", 3),
        dtype="float64",
        doc="range_fit of one half of the speaker's real motion against the other (both ways, centred)",
    ),
    "in_range": Output.array(
        "f", shape=("speakers", len(MOTIONS)), dtype="float64", doc="fraction of frames inside the real p5..p95"
    ),
    "drift": Output.array(
        "f", shape=("takes", 3), dtype="float64", doc="linear drift (deg) of synth, real, random path per take"
    ),
    "join_acc_max": Output.array(
        "f", shape=("takes", 2), dtype="float64", doc="largest acceleration at the joins: synth, real (deg/s^2)"
    ),
    "joins_over_p99": Output.array(
        "i",
        shape=("takes", 3),
        dtype="int64",
        doc="joins whose acceleration exceeds the speaker's real p99: synth, real at the same times; joins",
    ),
    "real_acc_p99": Output.array("f", shape=("takes",), dtype="float64", doc="speaker's real p99 acceleration"),
    "real_acc_p99_band": Output.array(
        "f", shape=("takes",), dtype="float64", doc="the same of the real motion low-passed at params jitter_cutoff"
    ),
}


def _plot_beat_alignment(view, inputs=None):
    """Pooled beat alignment per motion (onsets and accents) and the synthesis against the real motion per
    evaluation utterance, both relative to random real motion."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    motions = view.meta["motions"]
    onset, accent = view["beat_align_onset"], view["beat_align_accent"]
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.2), constrained_layout=True)
    x = np.arange(len(motions))
    for offset, values, name in ((-0.2, onset, "audio onsets"), (0.2, accent, "pitch accents")):
        err = values.std(axis=0, ddof=1) / np.sqrt(len(values)) if len(values) > 1 else np.zeros(len(motions))
        left.bar(x + offset, values.mean(axis=0), 0.4, yerr=err, label=name, capsize=2)
    left.set_xticks(x, motions)
    left.set_ylabel("beat alignment (mean over utterances, +-1 SE)")
    left.legend(fontsize=8)
    lo = min(onset[:, :2].min(), 0.0) if len(onset) else 0.0
    random = onset[:, motions.index("random")]
    right.scatter(onset[:, 1] - random, onset[:, 0] - random, s=14)
    span = np.abs(np.concatenate([onset[:, 0] - random, onset[:, 1] - random, [lo]])).max() + 0.02
    right.plot([-span, span], [-span, span], color="0.6", lw=0.8)
    right.axhline(0, color="0.8", lw=0.8)
    right.axvline(0, color="0.8", lw=0.8)
    right.set_xlabel("real - random (beat alignment with onsets)")
    right.set_ylabel("synthesis - random")
    right.set_title(f"{len(onset)} utterances; above 0: the synthesis beats random real motion", fontsize=9)
    return fig


class HeadEvalParams(Stage.Params):
    window: float = Field(10.0, gt=0, description="length (s) of the evaluation utterances takes are cut into")
    skip_seconds: float = Field(
        0.0,
        ge=0,
        description="score each take from this many seconds on (the stretch a synthesis used for enrolment: "
        "motion_blend.reference_seconds)",
    )
    sigma: float = Field(0.1, gt=0, description="beat alignment tolerance (s): the Gaussian's standard deviation")
    head_beats: Literal["peaks", "minima"] = Field(
        "peaks", description="head beats: maxima (strokes) or minima (stops) of the smoothed angular speed"
    )
    beat_smoothing: float = Field(0.1, ge=0, description="Gaussian smoothing (s, sd) of the angular velocity")
    onset_delta: float = Field(0.15, ge=0, le=1, description="onset peak height above the local mean (flux in 0..1)")
    onset_min_gap: float = Field(0.1, ge=0, description="shortest time (s) between two audio onsets")
    accent_prominence: float = Field(0.5, gt=0, description="semitones of prominence of a pitch accent")
    span_tolerance: float = Field(
        1.5, ge=1, description="range fit: the motion's p5..p95 span within this factor of the real span, either way"
    )
    range_margin: float = Field(
        0.25, ge=0, description="range fit: p5..p95 inside the real one widened by this fraction of its span each side"
    )
    jitter_cutoff: float = Field(
        5.0, gt=0, description="Hz: the real motion low-passed here gives the jitter-free acceleration yardstick"
    )
    draws: int = Field(20, ge=1, le=1000, description="draws averaged per random baseline")
    min_shift: float = Field(1.0, ge=0, description="smallest circular shift (s) of the 'shifted' baseline")
    bootstrap: int = Field(2000, ge=100, description="bootstrap resamples of the takes for the intervals")
    seed: int = Field(0, description="random baselines and bootstrap")


class HeadMotionEval(Stage):
    """Beat alignment, distribution distances, amplitude, drift and join acceleration of synthesised head motion
    against the real motion, shifted and random real motion, a random path, phase-randomised noise and a still
    head."""

    in_process = True

    Params = HeadEvalParams
    inputs = {
        "synthesis": Input.artifact("angles", "sequence", "joins", "join_utterance", doc="motion_blend artifact"),
        "trellis": Input.artifact("chosen", "segments", "db_segment_sequence", doc="the trellis it was stitched from"),
        "database": Input.artifact("angles", "translation", "sequence", doc="the headdb artifact searched"),
        "reference": Input.artifact("rotation", "sequence", doc="the test takes: real motion and audio (tracking)"),
        "test_pitch": Input.artifact("f0", "pitch_time", "pitch_utterance", "speaker_median", doc="their pitch"),
    }
    outputs = HEAD_EVAL_OUTPUTS
    figures = {"beat_alignment": _plot_beat_alignment}

    def run(self, params, inputs):
        from stages.head.motion_blend import database_motion, synthesise

        takes = load_takes(inputs, params)
        if not takes:
            raise UserError("no test takes to evaluate", field="inputs.trellis")
        db = database_motion(inputs["database"])
        stitch = dict(inputs["synthesis"].meta.get("stitch") or {})
        rng = np.random.default_rng(params.seed)
        allowed = [t.allowed for t in takes]
        fps = float(inputs["synthesis"].meta["fps"])
        paths = [
            [
                s.channels[:, :3]
                for s in synthesise(random_path_trellis(inputs["trellis"], allowed, rng), db, fps, **stitch)
            ]
            for _ in range(params.draws)
        ]
        windows, pooled = score_windows(takes, paths, db, params)
        ranges = range_scores(pooled, params.span_tolerance, params.range_margin)
        ranges.known = np.array([any(t.known for t in takes if t.speaker == x) for x in ranges.speakers])
        per_take = take_scores(takes, paths, params.jitter_cutoff)
        metrics = pooled_metrics(windows, ranges, per_take, params)
        return pack_evaluation(takes, windows, ranges, per_take, metrics, inputs)


def pack_evaluation(
    takes: list[Take], w: WindowScores, ranges: RangeScores, per_take: dict, metrics: dict, inputs: dict
) -> Result:
    arrays = {
        "window_take": w.take,
        "window_bounds": w.bounds,
        "beat_align_onset": w.beat_onset,
        "beat_align_accent": w.beat_accent,
        "speed_w1": w.speed_w1,
        "accel_w1": w.accel_w1,
        "correlation": w.correlation,
        "amplitude": ranges.amplitude,
        "range_ok": ranges.inside,
        "in_range": ranges.in_range,
        "range_fit": ranges.fit,
        "range_fit_halves": ranges.halves_fit,
        "drift": per_take["drift"],
        "join_acc_max": per_take["join_acc_max"],
        "joins_over_p99": per_take["joins_over_p99"].astype(np.int64),
        "real_acc_p99": per_take["real_acc_p99"],
        "real_acc_p99_band": per_take["real_acc_p99_band"],
    }
    meta = {
        "motions": list(MOTIONS),
        "labels": [t.label for t in takes],
        "speakers": [t.speaker for t in takes],
        "range_speakers": ranges.speakers,
        "fps": takes[0].fps,
        "holdout": inputs["trellis"].meta.get("holdout", "none"),
        "onsets_per_second": float(sum(len(t.onsets) for t in takes) / sum(len(t.real) / t.fps for t in takes)),
        "accents_per_second": float(sum(len(t.accents) for t in takes) / sum(len(t.real) / t.fps for t in takes)),
    }
    warnings = []
    if meta["holdout"] == "none":
        warnings.append("the trellis held nothing out: the synthesis may reuse the very takes it is scored on")
    return Result(arrays, meta, metrics, warnings)
