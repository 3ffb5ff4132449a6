"""Keyshape selection (paper Sec 4.1): the PCA-extreme frames of each training expression.

Per training expression s, PCA of that expression's aligned landmark shapes; from the first (largest-variance)
axis on, the frames with the maximum and the minimum projection are keyshapes B^(s), k_s of them from the first
k_s/2 axes; a candidate within ``dedupe_threshold`` of an already chosen keyshape is dropped (being chosen
later, it comes from the lower-variance axis).

Distances are measured relative to a ``scale`` (the stages pass the inter-ocular distance of the mean training
shape, ``stages.retarget.face_measures``), so the threshold does not depend on the shapes' units. The frames are
decomposed onto the keyshapes in ``stages.retarget.decomposition`` (Eq 8); the stages are in
``stages.retarget.keyshapes``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from stages.retarget.face_measures import mean_squared_landmark_distance


@dataclass
class KeyshapeSelection:
    """Keyshapes of one expression: source frames (indices into the shapes given), their PCA axis and end."""

    frames: np.ndarray  # (k,) int
    axes: np.ndarray  # (k,) int, PCA axis the keyshape is an extreme of (0 = largest variance)
    extremes: np.ndarray  # (k,) int, +1 maximum / -1 minimum projection
    explained_variance: np.ndarray  # (n_axes,) variance along each PCA axis
    dropped: list[dict] = field(default_factory=list)  # candidates removed as duplicates


def select_keyshapes(
    shapes: np.ndarray, k: int, *, dedupe_threshold: float, scale: float = 1.0, refill: bool = False
) -> KeyshapeSelection:
    """Pick up to ``k`` keyshapes among ``shapes`` (n, 68, 2) by PCA extremes (paper Sec 4.1).

    Candidates in order: axis 0 max, axis 0 min, axis 1 max, ... (the first ceil(k/2) axes, the k-th candidate
    last). A candidate whose mean squared landmark distance to an already chosen keyshape, divided by
    ``scale**2``, is below ``dedupe_threshold`` is dropped. With ``refill`` the search continues on further
    axes until k keyshapes are found (the paper stops at k/2 axes, so duplicates leave fewer than k).
    """
    shapes = np.asarray(shapes, np.float64)
    if shapes.shape[0] == 0:
        raise ValueError("select_keyshapes: no shapes")
    variance, rank, projections = _principal_projections(shapes)
    if rank == 0:  # every frame identical: the one shape is the only keyshape
        return KeyshapeSelection(np.array([0]), np.array([0]), np.array([1]), variance, [])
    chosen, axes, extremes, dropped = _pick_extremes(
        shapes, projections, rank, k, threshold=dedupe_threshold * scale**2, scale=scale, refill=refill
    )
    return KeyshapeSelection(
        np.array(chosen, dtype=np.int64),
        np.array(axes, dtype=np.int64),
        np.array(extremes, dtype=np.int64),
        variance,
        dropped,
    )


def _principal_projections(shapes: np.ndarray) -> tuple[np.ndarray, int, np.ndarray]:
    """PCA of ``shapes`` (n, 68, d): the variance along each axis, the rank (0 when every frame is the same) and
    each frame's projection on the first ``rank`` axes (n, max(rank, 1))."""
    n = shapes.shape[0]
    flat = shapes.reshape(n, -1)
    centred = flat - flat.mean(axis=0)
    _, singular, axes_t = np.linalg.svd(centred, full_matrices=False)
    variance = singular**2 / max(n - 1, 1)
    rank = int((singular > singular.max(initial=0.0) * 1e-9).sum()) if n > 1 else 0
    return variance, rank, centred @ axes_t[: max(rank, 1)].T


def _pick_extremes(
    shapes: np.ndarray, projections: np.ndarray, rank: int, k: int, *, threshold: float, scale: float, refill: bool
) -> tuple[list[int], list[int], list[int], list[dict]]:
    """The candidates of ``select_keyshapes`` in order (axis 0 max, axis 0 min, axis 1 max, ...), each kept unless
    it duplicates one already chosen: the chosen frames, their axes and extremes, and the dropped candidates."""
    chosen: list[int] = []
    axes: list[int] = []
    extremes: list[int] = []
    dropped: list[dict] = []
    candidates_tried = 0
    for axis in range(rank):
        for sign in (1, -1):
            if not refill and candidates_tried >= k:
                break
            if len(chosen) >= k:
                break
            candidates_tried += 1
            frame = int(np.argmax(sign * projections[:, axis]))
            duplicate = _duplicate_of(shapes, chosen, frame, threshold, scale)
            if duplicate is not None:
                dropped.append({"frame": frame, "axis": axis, "extreme": sign, **duplicate})
                continue
            chosen.append(frame)
            axes.append(axis)
            extremes.append(sign)
    return chosen, axes, extremes, dropped


def _duplicate_of(shapes: np.ndarray, chosen: list[int], frame: int, threshold: float, scale: float) -> dict | None:
    """The chosen keyshape nearest to ``frame`` and its distance (per ``scale**2``) when ``frame`` is within
    ``threshold`` of it (mean squared landmark distance), else None."""
    if not chosen:
        return None
    distance = mean_squared_landmark_distance(shapes[chosen], shapes[frame])
    nearest = int(np.argmin(distance))
    # the same frame again (an extreme of several axes) is always a duplicate
    if distance[nearest] < threshold or frame in chosen:
        return {"duplicate_of": chosen[nearest], "distance": float(distance[nearest] / scale**2)}
    return None


@dataclass
class KeyshapeSet:
    """The keyshapes of every expression (or take): source frames and where each comes from."""

    frames: np.ndarray  # (K,) frame index into the shapes given
    expression: np.ndarray  # (K,) group (expression or take) index
    index: np.ndarray  # (K,) id within the group
    axes: np.ndarray  # (K,) PCA axis
    extremes: np.ndarray  # (K,) +1 / -1
    dropped: dict  # label -> duplicates dropped (frame indices global)
    variance_covered: dict  # label -> fraction of the group's variance on the axes used


def select_all_keyshapes(
    shapes: np.ndarray,
    groups: np.ndarray,
    labels: list[str],
    counts: dict[str, int],
    usable: np.ndarray,
    *,
    dedupe_threshold: float,
    scale: float,
    refill: bool,
) -> KeyshapeSet:
    """``select_keyshapes`` for every group (expression or take) of frames; frames not ``usable`` are never
    keyshapes. Returns global frame indices."""
    parts = {key: [] for key in ("frames", "expression", "index", "axes", "extremes")}
    dropped, covered = {}, {}
    for s, label in enumerate(labels):
        frames = np.flatnonzero((groups == s) & usable)
        if frames.size == 0:
            raise ValueError(f"expression '{label}' has no usable frames")
        selection = select_keyshapes(
            shapes[frames], counts[label], dedupe_threshold=dedupe_threshold, scale=scale, refill=refill
        )
        parts["frames"].append(frames[selection.frames])
        parts["expression"].append(np.full(len(selection.frames), s))
        parts["index"].append(np.arange(len(selection.frames)))
        parts["axes"].append(selection.axes)
        parts["extremes"].append(selection.extremes)
        dropped[label] = [
            dict(d, frame=int(frames[d["frame"]]), duplicate_of=int(frames[d["duplicate_of"]]))
            for d in selection.dropped
        ]
        total = selection.explained_variance.sum()
        used = int(selection.axes.max()) + 1
        covered[label] = float(selection.explained_variance[:used].sum() / total) if total else 1.0
    joined = {key: np.concatenate(value).astype(np.int64) for key, value in parts.items()}
    return KeyshapeSet(**joined, dropped=dropped, variance_covered=covered)
