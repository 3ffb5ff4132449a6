"""Takes of one performance in a motion database: two cameras on one take, or a copy re-encoded or cropped.

Leaving one such take out of the search (``trellis.holdout: take``) while its twin stays in lets the search find the
held-out voice itself and replay its real motion. Twins share their sound, so they are found by their loudness
envelopes: the shorter take's envelope slid along the longer one's, the largest normalised correlation over the
lags (the same line spoken twice by the same person, a different performance, stays well below it: on the embedded
CREMA-D takes of one sentence in six emotions 0.87 at most, against 0.98 for a clip and its cropped copy).
"""

from __future__ import annotations

import re

import numpy as np

ENVELOPE_HOP = 0.02  # seconds per envelope frame
SHARED_AUDIO_R = 0.95  # normalised correlation of the log-loudness envelopes that marks one performance
MIN_OVERLAP = 2.0  # seconds: shorter takes are not compared (short envelopes match by chance)


def loudness_envelope(samples: np.ndarray, rate: int, hop: float = ENVELOPE_HOP) -> np.ndarray:
    """Log mean power of ``hop``-second frames of a mono signal (float32, for the template matching)."""
    step = max(1, int(round(hop * rate)))
    n = len(samples) // step
    frames = np.asarray(samples[: n * step], dtype=np.float64).reshape(n, step)
    return np.log(np.mean(frames * frames, axis=1) + 1e-10).astype(np.float32)


def envelope_match(a: np.ndarray, b: np.ndarray) -> float:
    """The largest normalised correlation of the shorter envelope against every position inside the longer."""
    import cv2

    long, short = (a, b) if len(a) >= len(b) else (b, a)
    if len(short) < 2 or np.ptp(short) == 0 or np.ptp(long) == 0:
        return 0.0
    return float(cv2.matchTemplate(long[None, :], short[None, :], cv2.TM_CCOEFF_NORMED).max())


def shared_audio_pairs(
    envelopes: dict[str, np.ndarray],
    threshold: float = SHARED_AUDIO_R,
    min_frames: int = int(MIN_OVERLAP / ENVELOPE_HOP),
) -> list[tuple[str, str, float]]:
    """Pairs of takes (by label) whose envelopes match at least ``threshold``, with the match; takes shorter than
    ``min_frames`` are not compared."""
    names = [n for n, e in envelopes.items() if len(e) >= min_frames]
    found = []
    for i, first in enumerate(names):
        for second in names[i + 1 :]:
            r = envelope_match(envelopes[first], envelopes[second])
            if r >= threshold:
                found.append((first, second, r))
    return found


def take_of(label: str) -> str:
    """The take a database or test sequence label comes from: without the suffixes of its piece (``#k``,
    stages.head.database.cut_recording) and its mirror image (``~mirror``)."""
    return re.sub(r"(#\d+)?(~mirror)?$", "", label)


def take_envelopes(view) -> dict[str, np.ndarray]:
    """Per take of a headdb artifact, the loudness envelope of its audio (its pieces' audio laid end to end, which
    is the take's; mirror images left out: they share their original's audio)."""
    meta = view.meta
    labels = list(meta.get("labels") or [])
    mirrored = list(meta.get("mirrored") or [False] * len(labels))
    if "audio" not in view or "audio_bounds" not in view or not labels:
        return {}
    audio, bounds = view["audio"], np.asarray(view["audio_bounds"]).reshape(-1, 2)
    pieces: dict[str, list[np.ndarray]] = {}
    for k, label in enumerate(labels):
        if not mirrored[k]:
            pieces.setdefault(take_of(label), []).append(np.asarray(audio[bounds[k, 0] : bounds[k, 1]]))
    rate = int(meta.get("audio_rate") or 16000)
    return {take: loudness_envelope(np.concatenate(parts), rate) for take, parts in pieces.items()}


def copy_warnings(view, groups: list[list[str]]) -> list[str]:
    """A warning for each pair of database takes that share their sound but are not grouped in ``groups``
    (``trellis.same_performance``)."""
    grouped = {(a, b) for group in groups for a in group for b in group}
    return [
        f"database takes '{a}' and '{b}' share their sound (loudness envelopes match at r = {r:.2f}): if they "
        "record one performance, list them together in same_performance, or leaving one out keeps its own voice "
        "and motion in the database"
        for a, b, r in shared_audio_pairs(take_envelopes(view))
        if (a, b) not in grouped
    ]
