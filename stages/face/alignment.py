"""Content alignment of the training takes (paper Sec 3.2, Chuang et al. 2002): the takes say the same sentence in
different expressions, and the bilinear model needs observations of every expression at the same content. Each
take is time-aligned to a reference take by dynamic time warping on per-frame features:

- ``audio``: MFCCs of the take's own audio (parselmouth ``Sound.to_mfcc``) sampled at the video frame times;
  speech timing is what content means, and the audio is independent of the facial expression.
- ``mouth``: mouth-region shape parameters (PCA of the Procrustes-aligned mouth points), for takes without audio.

Features are normalised per take (mean and variance), so a constant expression offset (a smile, a louder voice)
does not pull the alignment.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from msflow import UserError

# ----------------------------------------------------------------------------------------------- DTW


def dtw_cost_matrix(reference: np.ndarray, other: np.ndarray) -> np.ndarray:
    """Euclidean frame distances (n_ref, n_other) between two feature sequences."""
    from scipy.spatial.distance import cdist

    return cdist(np.asarray(reference, dtype=np.float64), np.asarray(other, dtype=np.float64))


def dtw_path(cost: np.ndarray, band: float | None = None) -> tuple[np.ndarray, float]:
    """Minimum-cost monotone path through ``cost`` (n, m) from (0, 0) to (n-1, m-1), steps (1,1), (1,0), (0,1).

    ``band`` (fraction of the longer length) restricts the path to a Sakoe-Chiba band around the scaled
    diagonal. Each row of the accumulated cost is computed in one vectorised pass: the horizontal recursion
    D[i, j] = min(T[j], c[i, j] + D[i, j-1]) is a running minimum of T[k] - cumsum(c)[k].
    Returns the path (L, 2) of (i, j) pairs and its total cost.
    """
    cost = np.asarray(cost, dtype=np.float64)
    n, m = cost.shape
    if band is not None:
        ii, jj = np.mgrid[0:n, 0:m]
        diag = ii * (m - 1) / max(n - 1, 1)
        radius = max(band * max(n, m), abs(n - m) + 1.0)
        cost = np.where(np.abs(jj - diag) <= radius, cost, np.inf)
    acc = np.full((n, m), np.inf)
    acc[0] = np.cumsum(cost[0])
    for i in range(1, n):
        prev = acc[i - 1]
        best_above = np.minimum(prev, np.concatenate([[np.inf], prev[:-1]]))
        through = cost[i] + best_above
        finite_cost = np.where(np.isfinite(cost[i]), cost[i], 0.0)
        running = np.cumsum(finite_cost)
        candidate = np.minimum.accumulate(through - running) + running
        acc[i] = np.where(np.isfinite(cost[i]), candidate, np.inf)
    if not np.isfinite(acc[-1, -1]):
        raise ValueError("no DTW path inside the band")
    path = [(n - 1, m - 1)]
    i, j = n - 1, m - 1
    while i > 0 or j > 0:
        if i == 0:
            j -= 1
        elif j == 0:
            i -= 1
        else:
            options = (acc[i - 1, j - 1], acc[i - 1, j], acc[i, j - 1])
            step = int(np.argmin(options))
            i, j = (i - 1, j - 1) if step == 0 else (i - 1, j) if step == 1 else (i, j - 1)
        path.append((i, j))
    return np.asarray(path[::-1], dtype=np.int64), float(acc[-1, -1])


def aligned_index(path: np.ndarray, n_reference: int) -> np.ndarray:
    """For each reference frame, the middle one of the other take's frames the path pairs it with."""
    lo = np.full(n_reference, np.iinfo(np.int64).max)
    hi = np.full(n_reference, -1)
    np.minimum.at(lo, path[:, 0], path[:, 1])
    np.maximum.at(hi, path[:, 0], path[:, 1])
    return ((lo + hi) // 2).astype(np.int64)


@dataclass
class ContentAlignment:
    """Every take time-aligned to the reference take's frames, which form the content axis."""

    reference: int  # index of the reference take
    aligned_local: np.ndarray  # (S, C) frame of take s (within the take) at content position c
    paths: list[np.ndarray]  # per take (L_s, 2) pairs (reference frame, take frame)
    costs: np.ndarray  # (S,) mean cost per path step

    def paths_table(self) -> np.ndarray:
        """All warping paths as one (L, 3) int32 table of (take, reference frame, take frame)."""
        rows = [np.column_stack([np.full(len(p), s), p]) for s, p in enumerate(self.paths)]
        return np.concatenate(rows).astype(np.int32)


def align_takes(features: list[np.ndarray], reference: int, band: float | None = 0.3) -> ContentAlignment:
    """DTW-align each take's per-frame features (n_s, d) to the reference take's."""
    pairs = [align_pair(features, reference, s, band) for s in range(len(features))]
    return ContentAlignment(
        reference, np.stack([p[0] for p in pairs]), [p[1] for p in pairs], np.asarray([p[2] for p in pairs])
    )


def standardise_per_take(features: np.ndarray) -> np.ndarray:
    """Zero mean and unit variance per feature within one take (cepstral mean/variance normalisation)."""
    features = np.asarray(features, dtype=np.float64)
    std = features.std(0)
    return (features - features.mean(0)) / np.where(std < 1e-9, 1.0, std)


# ----------------------------------------------------------------------------------------------- features


def mfcc_at_frames(
    samples: np.ndarray,
    rate: float,
    frame_times: np.ndarray,
    *,
    n_coefficients: int = 12,
    window_length: float = 0.025,
    time_step: float = 0.005,
) -> np.ndarray:
    """MFCCs c1..cN of an audio signal, interpolated at the given times (seconds from the first sample).

    parselmouth's Praat MFCC (mel filter bank, DCT); c0 (overall level) is dropped so loudness, which differs
    between expressions, does not drive the alignment.
    """
    import parselmouth

    samples = np.asarray(samples, dtype=np.float64)
    min_samples = int(np.ceil(2 * window_length * rate)) + 1
    if len(samples) < min_samples:
        samples = np.pad(samples, (0, min_samples - len(samples)))
    sound = parselmouth.Sound(samples, sampling_frequency=float(rate))
    mfcc = sound.to_mfcc(number_of_coefficients=n_coefficients, window_length=window_length, time_step=time_step)
    values = mfcc.to_array()[1 : n_coefficients + 1]  # (N, frames); row 0 is c0
    times = np.asarray(mfcc.xs())
    t = np.asarray(frame_times, dtype=np.float64)
    return np.stack([np.interp(t, times, row) for row in values], axis=-1)


def audio_features(
    audio: np.ndarray,
    audio_bounds: np.ndarray,
    rate: float,
    frame_times: list[np.ndarray],
    audio_offsets: list[float],
    **mfcc_options,
) -> list[np.ndarray]:
    """Per take: standardised MFCCs at its video frame times (frame time t -> audio time t - audio_offset)."""
    out = []
    for s, (start, stop) in enumerate(np.asarray(audio_bounds)):
        times = np.asarray(frame_times[s], dtype=np.float64) - float(audio_offsets[s])
        out.append(standardise_per_take(mfcc_at_frames(audio[start:stop], rate, times, **mfcc_options)))
    return out


def mouth_features(
    aligned_shapes: np.ndarray, sequence: np.ndarray, n_takes: int, variance: float = 0.95, max_modes: int = 8
) -> list[np.ndarray]:
    """Per take: mouth-region shape parameters (PCA of the aligned mouth points over all takes), take mean removed."""
    from stages.face.aam import IBUG68_MOUTH, fit_pca

    mouth = np.asarray(aligned_shapes, dtype=np.float64)[:, IBUG68_MOUTH].reshape(len(aligned_shapes), -1)
    pca = fit_pca(mouth, variance, max_modes=max_modes)
    params = (mouth - pca.mean) @ pca.basis.T
    return [params[sequence == s] - params[sequence == s].mean(0) for s in range(n_takes)]


def check_takes(
    sequence: np.ndarray, labels: list[str], min_frames: int, why: str, field: str, only: list[int] | None = None
) -> list[np.ndarray]:
    """Frame indices of each take; UserError naming a take (of ``only``, default all) shorter than ``min_frames``."""
    sequence = np.asarray(sequence)
    takes = [np.flatnonzero(sequence == s) for s in range(len(labels))]
    for s in range(len(labels)) if only is None else only:
        label, frames = labels[s], takes[s]
        if len(frames) < min_frames:
            raise UserError(
                f"take '{label}' has {len(frames)} frames; {why} needs at least {min_frames} frames per take",
                field=field,
            )
    return takes


# ----------------------------------------------------------------------------------------------- takes and sets

#: names under which a take's expression is recognised as the neutral one (the default reference)
NEUTRAL_NAMES = ("neutral", "neu", "n")


def take_expressions(labels: list[str], fields: dict | None) -> list[str]:
    """Expression (style) of each take: its ``expression`` field when the take has one, else its label."""
    fields = fields or {}
    return [str((fields.get(label) or {}).get("expression", label)) for label in labels]


def take_sentences(labels: list[str], fields: dict | None) -> list[str]:
    """Sentence (content) of each take: its ``sentence`` field, else one shared sentence ("")."""
    fields = fields or {}
    return [str((fields.get(label) or {}).get("sentence", "")) for label in labels]


def neutral_index(styles: list[str]) -> int:
    """Index of the neutral expression among ``styles`` (by name, case-insensitive), else 0."""
    lowered = [s.lower() for s in styles]
    return next((lowered.index(n) for n in NEUTRAL_NAMES if n in lowered), 0)


@dataclass
class TakeSets:
    """Training takes grouped for the bilinear fit: which take plays which style, set by set.

    A *set* is one take per style saying the same sentence; the set's take of the reference style gives its content
    axis and the others are time-aligned to it, so the set contributes one column of observations per reference frame.
    A sentence with several takes of a style gives several sets (the r-th set uses the r-th take of each style,
    cycling through a style's takes when it has fewer), so every take is used.
    """

    styles: list[str]  # style (expression) names, in order of first appearance
    take_style: np.ndarray  # (n_takes,) style index of each take, -1 for takes left out
    sets: np.ndarray  # (n_sets, S) take index of each style in each set
    set_sentence: list[str]  # sentence of each set
    skipped: list[str]  # sentences left out because some style never says them


def group_takes(
    expressions: list[str], sentences: list[str], include: np.ndarray | None = None, order: list[str] | None = None
) -> TakeSets:
    """Group takes (their expression and sentence each) into sets; ``include`` (n_takes,) bool selects the takes,
    ``order`` the styles' order (default: as they first appear)."""
    n = len(expressions)
    include = np.ones(n, dtype=bool) if include is None else np.asarray(include, dtype=bool)
    present = list(dict.fromkeys(e for e, keep in zip(expressions, include) if keep))
    styles = present if order is None else [s for s in order if s in present]
    take_style = np.array([styles.index(e) if keep else -1 for e, keep in zip(expressions, include)], dtype=np.int64)
    sets, set_sentence, skipped = [], [], []
    for sentence in dict.fromkeys(s for s, keep in zip(sentences, include) if keep):
        by_style = [
            [t for t in range(n) if take_style[t] == s and sentences[t] == sentence] for s in range(len(styles))
        ]
        if not all(by_style):
            skipped.append(sentence)
            continue
        for r in range(max(len(takes) for takes in by_style)):
            sets.append([takes[r % len(takes)] for takes in by_style])
            set_sentence.append(sentence)
    table = np.asarray(sets, dtype=np.int64).reshape(len(sets), len(styles))
    return TakeSets(styles, take_style, table, set_sentence, skipped)


@dataclass
class SetAlignment:
    """Content columns of all sets: each column is one reference frame of one set and the frame of every style's
    take aligned to it (global frame indices into the tracking/aam frame axis)."""

    frames: np.ndarray  # (S, C) global frame of each style at each content column
    column_set: np.ndarray  # (C,) set of each column
    column_position: np.ndarray  # (C,) frame of the set's reference take at each column (within the take)
    paths: np.ndarray  # (L, 4) int32 rows (set, take, reference frame, take frame)
    costs: np.ndarray  # (S,) mean DTW cost per path step of each style over the sets


def align_pair(
    features: list[np.ndarray], reference_take: int, take: int, band: float | None, memo: dict | None = None
) -> tuple[np.ndarray, np.ndarray, float]:
    """DTW of one take against a reference take: (frame of the take at each reference frame, path (L, 2), mean
    cost per step). ``memo`` (a dict) keeps pairs already aligned, for protocols that regroup the same takes."""
    key = (reference_take, take, band)
    if memo is not None and key in memo:
        return memo[key]
    ref = features[reference_take]
    if take == reference_take:
        path, total = np.column_stack([np.arange(len(ref)), np.arange(len(ref))]), 0.0
    else:
        path, total = dtw_path(dtw_cost_matrix(ref, features[take]), band)
    result = (aligned_index(path, len(ref)), path, total / len(path))
    if memo is not None:
        memo[key] = result
    return result


def align_sets(
    features: list[np.ndarray],
    takes: list[np.ndarray],
    groups: TakeSets,
    reference: int,
    band: float | None = 0.3,
    memo: dict | None = None,
) -> SetAlignment:
    """DTW-align, in every set, each style's take to the reference style's take (as ``align_takes`` does for one
    set). ``features`` per take (n_t, d); ``takes`` the global frame indices of each take; ``memo`` see
    ``align_pair``."""
    n_styles = len(groups.styles)
    frames, column_set, column_position, paths = [], [], [], []
    costs = np.zeros((max(len(groups.sets), 1), n_styles))
    for r, members in enumerate(groups.sets):
        ref_take = int(members[reference])
        local = []
        for s, take in enumerate(int(t) for t in members):
            aligned, path, costs[r, s] = align_pair(features, ref_take, take, band, memo)
            local.append(takes[take][aligned])
            paths.append(np.column_stack([np.full(len(path), r), np.full(len(path), take), path]))
        frames.append(np.stack(local))
        column_set.append(np.full(len(takes[ref_take]), r))
        column_position.append(np.arange(len(takes[ref_take])))
    if not frames:
        empty = np.zeros(0, np.int64)
        return SetAlignment(np.zeros((n_styles, 0), np.int64), empty, empty, np.zeros((0, 4), np.int32), costs[0])
    return SetAlignment(
        np.concatenate(frames, axis=1),
        np.concatenate(column_set),
        np.concatenate(column_position),
        np.concatenate(paths).astype(np.int32),
        costs.mean(0),
    )
