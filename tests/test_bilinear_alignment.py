"""Content alignment (stages.face.alignment): DTW against a plain reference implementation, known warps, MFCC features."""

import numpy as np
import pytest

from stages.face.alignment import (
    align_takes,
    aligned_index,
    dtw_cost_matrix,
    dtw_path,
    mfcc_at_frames,
    standardise_per_take,
)


def reference_dtw(cost):
    """Textbook O(n m) dynamic programme with steps (1,1), (1,0), (0,1)."""
    n, m = cost.shape
    acc = np.full((n + 1, m + 1), np.inf)
    acc[0, 0] = 0
    for i in range(1, n + 1):
        for j in range(1, m + 1):
            acc[i, j] = cost[i - 1, j - 1] + min(acc[i - 1, j - 1], acc[i - 1, j], acc[i, j - 1])
    return acc[n, m]


@pytest.mark.parametrize("shape", [(7, 7), (12, 5), (5, 13), (1, 4), (30, 41)])
def test_vectorised_dtw_matches_the_textbook_recursion(shape):
    rng = np.random.default_rng(sum(shape))
    cost = rng.random(shape)
    path, total = dtw_path(cost)
    assert total == pytest.approx(reference_dtw(cost))
    assert tuple(path[0]) == (0, 0) and tuple(path[-1]) == (shape[0] - 1, shape[1] - 1)
    steps = np.diff(path, axis=0)
    assert np.all((steps >= 0) & (steps <= 1)) and np.all(steps.sum(1) >= 1)
    assert cost[path[:, 0], path[:, 1]].sum() == pytest.approx(total)


def test_band_constrains_the_path():
    rng = np.random.default_rng(0)
    cost = rng.random((40, 40))
    cost[:20, 25:] = -0.0  # cheap region far off the diagonal
    free, _ = dtw_path(cost)
    banded, _ = dtw_path(cost, band=0.1)
    assert np.max(np.abs(banded[:, 0] - banded[:, 1])) <= 5
    assert np.max(np.abs(free[:, 0] - free[:, 1])) >= np.max(np.abs(banded[:, 0] - banded[:, 1]))


def test_alignment_recovers_a_known_time_warp():
    rng = np.random.default_rng(1)
    reference = np.cumsum(rng.normal(size=(50, 4)), axis=0)
    # the other take: same content, slower in the middle and faster at the end, plus a constant offset
    warp = np.clip(
        np.round(np.concatenate([np.linspace(0, 20, 21), np.linspace(20.5, 35, 30), np.linspace(36, 49, 8)])).astype(
            int
        ),
        0,
        49,
    )
    other = reference[warp] + 3.0
    features = [standardise_per_take(reference), standardise_per_take(other)]
    alignment = align_takes(features, 0, band=0.5)
    found = alignment.aligned_local[1]  # frame of 'other' at each reference frame
    assert found.shape == (50,) and np.all(np.diff(found) >= 0)
    truth = np.array(
        [np.flatnonzero(warp == r)[len(np.flatnonzero(warp == r)) // 2] if np.any(warp == r) else -1 for r in range(50)]
    )
    ok = truth >= 0
    assert np.mean(np.abs(found[ok] - truth[ok]) <= 1) > 0.9
    np.testing.assert_array_equal(alignment.aligned_local[0], np.arange(50))
    table = alignment.paths_table()
    assert table.shape[1] == 3 and set(table[:, 0]) == {0, 1}


def test_aligned_index_takes_the_middle_match():
    path = np.array([[0, 0], [0, 1], [0, 2], [1, 3], [2, 3], [3, 4]])
    np.testing.assert_array_equal(aligned_index(path, 4), [1, 3, 3, 4])


def tone_sequence(durations, rate=16000):
    """Concatenated tones of distinct pitch (one per 'phone'), each lasting the given seconds."""
    freqs = [220, 440, 330, 660, 250, 520]
    parts = [
        np.sin(2 * np.pi * f * np.arange(int(d * rate)) / rate) * (0.3 + 0.1 * i)
        for i, (f, d) in enumerate(zip(freqs, durations))
    ]
    return np.concatenate(parts).astype(np.float32), np.cumsum([0] + list(durations))


def test_mfcc_alignment_matches_segments_of_differently_timed_audio():
    rate, fps = 16000, 30.0
    a, a_bounds = tone_sequence([0.3, 0.2, 0.4, 0.3, 0.2, 0.3], rate)
    b, b_bounds = tone_sequence([0.2, 0.35, 0.25, 0.45, 0.3, 0.2], rate)
    ta = np.arange(int(len(a) / rate * fps)) / fps
    tb = np.arange(int(len(b) / rate * fps)) / fps
    fa = standardise_per_take(mfcc_at_frames(a, rate, ta))
    fb = standardise_per_take(mfcc_at_frames(b, rate, tb))
    assert fa.shape == (len(ta), 12) and np.isfinite(fa).all()
    alignment = align_takes([fa, fb], 0, band=None)
    seg_a = np.searchsorted(a_bounds, ta, side="right") - 1
    seg_b = np.searchsorted(b_bounds, tb, side="right") - 1
    matched = seg_b[alignment.aligned_local[1]]
    # away from segment boundaries (one frame of MFCC window smear), every frame lands in its own segment
    interior = np.min(np.abs(ta[:, None] - a_bounds[None, :]), axis=1) > 1.5 / fps
    assert np.mean(matched[interior] == seg_a[interior]) > 0.95


def test_cost_matrix_is_euclidean():
    a = np.array([[0.0, 0.0], [3.0, 4.0]])
    np.testing.assert_allclose(dtw_cost_matrix(a, a), [[0, 5], [5, 0]])
