"""Pitch segments and their distance, the matching of the head-motion search (paper Sec. 5.2, Eq. 10-12).

A segment runs from a voiced onset to the next. ``SegmentTable`` holds, per segment, its voiced pitch contour resampled
to a common length in the matching unit (Hz, semitones relative to the speaker's median, or those over the speaker's
spread), the contour's geometric features G (``GEOMETRY_FEATURES``), its loudness contour and its onset rate.

Two distances:
1. phrase stage: Euclidean distance of z-normalised phrase features (Dellaert-style prosody), ``phrase_distances``;
2. segment stage: D = b G_d + c P_d + (1 - b - c) L_d (Eq. 10-12), plus e E_d + o O_d (loudness and rhythm, beyond
   the paper), ``segment_distances``.

The search over these distances (Eq. 13-15) is ``stages.head.search``; the stage is ``stages.head.trellis``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
