"""Frames without a face: find the gaps, fill short ones by linear interpolation, refuse long ones."""

from __future__ import annotations

import numpy as np

from msflow import UserError


def find_gaps(valid: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) frame ranges where ``valid`` is False."""
    v = np.asarray(valid, dtype=bool)
    edges = np.diff(np.concatenate([[1], (~v).astype(np.int8) * -1 + 1, [1]]).astype(np.int8))
    starts = np.flatnonzero(edges == -1)
    stops = np.flatnonzero(edges == 1)
    return [(int(a), int(b)) for a, b in zip(starts, stops)]


def interpolate_gaps(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Linear interpolation over frames (axis 0) between the nearest valid frames; gaps at either end hold the
    nearest valid value. Vectorised over frames and all trailing axes."""
    values = np.asarray(values, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    n = len(values)
    if valid.all() or not valid.any():
        return values.copy()
    idx = np.arange(n)
    prev = np.maximum.accumulate(np.where(valid, idx, -1))
    nxt = np.minimum.accumulate(np.where(valid, idx, n)[::-1])[::-1]
    prev_c = np.where(prev < 0, nxt, prev)
    next_c = np.where(nxt >= n, prev_c, nxt)
    span = np.maximum(next_c - prev_c, 1)
    w = np.where(next_c == prev_c, 0.0, (idx - prev_c) / span)
    w = w.reshape((n,) + (1,) * (values.ndim - 1))
    out = (1 - w) * values[prev_c] + w * values[next_c]
    return np.where(valid.reshape(w.shape), values, out)


def fill_face_gaps(
    values: np.ndarray,
    valid: np.ndarray,
    max_gap: int,
    times: np.ndarray | None = None,
    *,
    what: str = "face",
    file: str | None = None,
    field: str | None = None,
) -> np.ndarray:
    """Interpolate over frames with no face; UserError when there is no face at all or a gap is longer than
    ``max_gap`` frames (the message lists every such frame range, 0-based, inclusive)."""
    valid = np.asarray(valid, dtype=bool)
    n = len(valid)
    if not valid.any():
        raise UserError(f"no {what} found in any of its {n} frames", file=file, field=field)
    long = [(a, b) for a, b in find_gaps(valid) if b - a > max_gap]
    if long:

        def describe(a: int, b: int) -> str:
            span = f"frames {a}-{b - 1} ({b - a} frames"
            if times is not None:
                span += f", {times[a]:.2f}-{times[b - 1]:.2f} s"
            return span + ")"

        raise UserError(
            f"no {what} in "
            + ", ".join(describe(a, b) for a, b in long)
            + f": longer than max_gap_frames = {max_gap}; raise it to interpolate, or trim the video",
            file=file,
            field=field,
        )
    return interpolate_gaps(values, valid)
