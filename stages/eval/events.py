"""Retargeting evaluation, the events compared frame by frame: runs of frames, lip gaps and closures, eye apertures
and blinks, how two lists of events agree (``stages.eval.retarget`` compares the performer's with the
character's), and the correlation of two per-frame series."""

from __future__ import annotations

import numpy as np


def runs(mask: np.ndarray, sequence: np.ndarray, min_length: int = 1) -> list[tuple[int, int]]:
    """[start, stop) of the runs of True at least ``min_length`` frames long, never across a take boundary."""
    mask = np.asarray(mask, bool)
    sequence = np.asarray(sequence)
    edges = np.diff(np.r_[0, mask.astype(np.int8), 0])
    cut = np.r_[False, sequence[1:] != sequence[:-1]]
    out = []
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    for a, b in zip(starts, stops):
        breaks = np.flatnonzero(cut[a + 1 : b]) + a + 1
        for lo, hi in zip(np.r_[a, breaks], np.r_[breaks, b]):
            if hi - lo >= min_length:
                out.append((int(lo), int(hi)))
    return out


def lip_gap(shapes: np.ndarray) -> np.ndarray:
    """Vertical inner-lip gap per frame (iBUG 61-67, 62-66, 63-65 mean, across the eye line) / inter-ocular
    distance: the same measure the lip seal works with (``stages.retarget.face_measures.lip_gap_iod``)."""
    from stages.retarget.face_measures import level, lip_gap_iod

    return lip_gap_iod(level(shapes))


def eye_aperture(shapes: np.ndarray) -> np.ndarray:
    """(frames, 2) lid gap / eye-corner distance from iBUG landmarks; index 0 = the performer's left eye
    (iBUG 42-47, ARKit ``_L``), 1 = right (36-41), as tracking's ``eye_aperture``."""
    from stages.retarget.eyes import eye_aperture_2d

    return eye_aperture_2d(shapes)


def blink_frames(aperture: np.ndarray, sequence: np.ndarray, ratio: float, open_quantile: float = 0.9) -> np.ndarray:
    """Frames whose aperture (mean of both eyes) is below ``ratio`` x the take's open aperture (its 90th
    percentile: the eyes' usual opening, whatever the expression narrows them to for a while)."""
    mean = np.asarray(aperture, np.float64).reshape(len(sequence), -1).mean(axis=1)
    closed = np.zeros(len(mean), dtype=bool)
    for take in np.unique(sequence):
        rows = sequence == take
        closed[rows] = mean[rows] < ratio * np.quantile(mean[rows], open_quantile)
    return closed


def blink_frame_limits(fps: list[float], sequence: np.ndarray, seconds: float) -> np.ndarray:
    """Per take, the most frames a blink may last."""
    takes = int(np.max(sequence, initial=0)) + 1
    return np.array([max(1, int(round(seconds * (fps[i] if i < len(fps) else fps[-1])))) for i in range(takes)])


def blink_events(aperture, sequence, ratio: float, narrow: float, longest: np.ndarray) -> list[tuple[int, int]]:
    """Blinks: quick dips. A run of frames narrowed below ``narrow`` x open, no longer than its take's
    ``longest``, that reaches below ``ratio`` x open somewhere (a longer narrowing is a squint or closed eyes, and
    a squint hovering about the threshold is not a string of blinks)."""
    closed = blink_frames(aperture, sequence, ratio)
    narrowed = blink_frames(aperture, sequence, narrow)
    return [(a, b) for a, b in runs(narrowed, sequence) if b - a <= longest[sequence[a]] and closed[a:b].any()]


def event_agreement(reference: list[tuple[int, int]], predicted: list[tuple[int, int]], tolerance: int) -> dict:
    """Recall (reference events overlapped by a predicted one, within ``tolerance`` frames) and the false rate
    (predicted events that overlap no reference event)."""

    def overlaps(a, b):
        return a[0] - tolerance < b[1] and b[0] - tolerance < a[1]

    found = sum(any(overlaps(r, p) for p in predicted) for r in reference)
    false = sum(not any(overlaps(p, r) for r in reference) for p in predicted)
    return {
        "reference": len(reference),
        "predicted": len(predicted),
        "found": int(found),
        "false": int(false),
        "recall": found / len(reference) if reference else 1.0,
        "false_rate": false / len(predicted) if predicted else 0.0,
    }


def closure_agreement(
    performer_gap: np.ndarray, character_gap: np.ndarray, sequence: np.ndarray, *, gap: float, frames: int, ratio: float
) -> list[dict]:
    """Each performer lip closure (gap < ``gap`` for >= ``frames`` frames) with the mean gaps of performer and
    character over it, and whether the character's is at most ``ratio`` times the performer's."""
    out = []
    for a, b in runs(performer_gap < gap, sequence, frames):
        p, c = float(performer_gap[a:b].mean()), float(character_gap[a:b].mean())
        out.append({"start": a, "stop": b, "performer_gap": p, "character_gap": c, "reproduced": c <= ratio * p})
    return out


def pearson(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation; 0 when either series is constant."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    a, b = a - a.mean(), b - b.mean()
    denominator = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / denominator) if denominator > 0 else 0.0
