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
    ref = features[reference]
    aligned, paths, costs = [], [], []
    for s, feats in enumerate(features):
        if s == reference:
            path = np.column_stack([np.arange(len(ref)), np.arange(len(ref))])
            total = 0.0
        else:
            path, total = dtw_path(dtw_cost_matrix(ref, feats), band)
        paths.append(path)
        costs.append(total / len(path))
        aligned.append(aligned_index(path, len(ref)))
    return ContentAlignment(reference, np.stack(aligned), paths, np.asarray(costs))


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


def check_takes(sequence: np.ndarray, labels: list[str], min_frames: int, why: str, field: str) -> list[np.ndarray]:
    """Frame indices of each take; UserError naming a take shorter than ``min_frames``."""
    sequence = np.asarray(sequence)
    takes = [np.flatnonzero(sequence == s) for s in range(len(labels))]
    for label, frames in zip(labels, takes):
        if len(frames) < min_frames:
            raise UserError(
                f"take '{label}' has {len(frames)} frames; {why} needs at least {min_frames} frames per take",
                field=field,
            )
    return takes
