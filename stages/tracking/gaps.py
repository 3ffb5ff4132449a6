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


#: what a frame of the output is made from (``gap_plan``): tracked itself, interpolated or held next to a short
#: gap (its crop still comes from its own picture), or held across a long gap (everything copied from the source)
TRACKED, FILLED, HELD = 0, 1, 2


def gap_plan(valid: np.ndarray, max_gap: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """How every frame's values are made from the tracked frames: value = (1 - w) v[a] + w v[b].

    Tracked frames are their own (a = b = i, w = 0). A gap of at most ``max_gap`` frames between two tracked
    frames is interpolated linearly (kind FILLED); one at the start or end of the take holds the nearest tracked
    frame (FILLED). A longer gap holds the last tracked frame before it (the first after it, at the start of a
    take) and is not interpolated across (kind HELD). Returns (a, b, w, kind), each (n,).
    """
    valid = np.asarray(valid, dtype=bool)
    n = len(valid)
    idx = np.arange(n)
    a, b, w = idx.copy(), idx.copy(), np.zeros(n)
    kind = np.full(n, TRACKED, dtype=np.int8)
    for start, stop in find_gaps(valid):
        prev = start - 1 if start > 0 else None
        nxt = stop if stop < n else None
        frames = idx[start:stop]
        if prev is None and nxt is None:
            raise ValueError("no tracked frame to fill from")
        long = stop - start > max_gap
        kind[start:stop] = HELD if long else FILLED
        if prev is not None and nxt is not None and not long:
            a[start:stop], b[start:stop] = prev, nxt
            w[start:stop] = (frames - prev) / (nxt - prev)
        else:
            source = prev if prev is not None else nxt
            a[start:stop] = b[start:stop] = source
    return a, b, w, kind


def apply_plan(values: np.ndarray, a: np.ndarray, b: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(1 - w) values[a] + w values[b] along axis 0 (exactly values[a] where w = 0)."""
    values = np.asarray(values, dtype=np.float64)
    weight = w.reshape((-1,) + (1,) * (values.ndim - 1))
    out = (1 - weight) * values[a] + weight * values[b]
    return np.where(weight == 0, values[a], out)


def long_gap_error(valid: np.ndarray, max_gap: int, times=None, *, file=None, field=None, what="face") -> UserError:
    """The error listing every gap longer than ``max_gap`` frames (for ``long_gaps: error``)."""
    long = [(a, b) for a, b in find_gaps(valid) if b - a > max_gap]

    def describe(a: int, b: int) -> str:
        span = f"frames {a}-{b - 1} ({b - a} frames"
        if times is not None:
            span += f", {times[a]:.2f}-{times[b - 1]:.2f} s"
        return span + ")"

    return UserError(
        f"no {what} in "
        + ", ".join(describe(a, b) for a, b in long)
        + f": longer than max_gap_frames = {max_gap}; raise it to interpolate, set long_gaps: hold to keep "
        "the take with those frames held and marked, or trim the video",
        file=file,
        field=field,
    )


def fill_gaps(
    values: np.ndarray,
    valid: np.ndarray,
    max_gap: int,
    long_gaps: str = "error",
    times: np.ndarray | None = None,
    *,
    file: str | None = None,
    field: str | None = None,
) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int]]]:
    """``gap_plan`` applied to whole-take values: (filled values, the frame each frame's crop comes from, long
    gaps held). UserError when no frame is valid, or a gap is long and ``long_gaps`` is 'error'."""
    valid = np.asarray(valid, dtype=bool)
    if not valid.any():
        raise UserError(f"no face found in any of its {len(valid)} frames", file=file, field=field)
    long = [(a, b) for a, b in find_gaps(valid) if b - a > max_gap]
    if long and long_gaps == "error":
        raise long_gap_error(valid, max_gap, times, file=file, field=field)
    a, b, w, kind = gap_plan(valid, max_gap)
    return apply_plan(values, a, b, w), np.where(kind == HELD, a, np.arange(len(valid))), long
