"""Lip seal (issue 13.2): when the performer's lips close, the character's close too.

Keyshape blending averages shapes, and an average of nearly closed mouths with a few open ones is a little open:
the character's lips would never meet. The fix acts on the blended morph weights u(t) of the frames where the
decomposed shape's inner-lip gap g(t) (IOD units) is small:

- the character's inner-lip gap is linear in the weights, gap(u) = g0 + a.u, with a_m the vertical opening that
  morph m gives the three inner-lip landmark pairs (iBUG 61-67, 62-66, 63-65; mean, character IOD units);
- the seal asks gap(u) <= b(t) = g0 + 4 max(0, g(t) - seal_gap): the character's own closed mouth (its neutral
  gap g0) wherever the performer's lips are closed (gap below ``seal_gap``), the allowed opening growing four times
  as fast as the performer's gap above it, so the seal fades out instead of snapping off. The performer's gap is
  not copied: trackers place the inner lips of a closed mouth some way apart (FaceMesh about 0.02 IOD, with the
  perspective of a close-up), where the character's neutral has them touching (ICT FaceKit 0.009);
- a closing corrective rises first, up to its base's weight (``raise_correctives``: ARKit's mouthClose up to
  jawOpen seals the lips over a lowered jaw, which keeps the jaw where the performer's chin is);
- then, of all the weights that meet the bound, the seal takes the nearest that only *lowers* weights
  (0 <= u' <= u): min ||u' - u||^2 s.t. a.u' <= b. Its solution is u'(lambda) = clip(u - lambda a, 0, u) for the
  smallest lambda >= 0 that meets the bound (a.u'(lambda) falls as lambda grows), found by bisection for all
  frames at once. Only opening morphs (a_m > 0) move; nothing is pushed into the other lip.
"""

from __future__ import annotations

import numpy as np

from stages.retarget.face_measures import INNER_LIP_PAIRS, inter_ocular_distance


def lip_gap_model(neutral_landmarks: np.ndarray, landmark_deltas: np.ndarray) -> tuple[float, np.ndarray]:
    """The character's inner-lip gap as g0 + a.u: neutral gap g0 and per-morph slopes a (M,), in character IOD
    units, from its 68 landmark vertices (68, 3) and their morph deltas (M, 68, 3). Vertical (y) openings."""
    rest = np.asarray(neutral_landmarks, np.float64)
    deltas = np.asarray(landmark_deltas, np.float64)
    upper = [a for a, _ in INNER_LIP_PAIRS]
    lower = [b for _, b in INNER_LIP_PAIRS]
    iod = float(inter_ocular_distance(rest))
    g0 = float((rest[upper, 1] - rest[lower, 1]).mean()) / iod
    slopes = (deltas[:, upper, 1] - deltas[:, lower, 1]).mean(axis=1) / iod
    return g0, slopes


def seal_bound(target_gap: np.ndarray, g0: float, seal_gap: float) -> np.ndarray:
    """b(t): the character's closed gap where the performer's lips are closed, fading out above ``seal_gap``."""
    return g0 + 4.0 * np.maximum(np.asarray(target_gap, np.float64) - seal_gap, 0.0)


def seal_lips(
    weights: np.ndarray,
    g0: float,
    slopes: np.ndarray,
    bound: np.ndarray,
    movable: np.ndarray | None = None,
    iterations: int = 60,
) -> np.ndarray:
    """The weights (frames, M) nearest to ``weights`` u with gap(u') <= ``bound`` (frames,) and 0 <= u' <= u;
    ``movable`` (frames, M) bool: the morphs the seal may lower in each frame (default all)."""
    u0 = np.asarray(weights, np.float64)
    a = np.asarray(slopes, np.float64)
    step = np.where(np.ones(u0.shape, bool) if movable is None else movable, a[None], 0.0)
    budget = np.asarray(bound, np.float64) - g0

    def moved(lam):
        return np.clip(u0 - lam[:, None] * step, 0.0, u0)

    need = moved(np.zeros(len(u0))) @ a > budget
    if not need.any():
        return u0.copy()
    # bracket: at this lambda every movable opening morph is at 0 (the most lowering can do)
    with np.errstate(divide="ignore", invalid="ignore"):
        hi = np.where(step > 0, u0 / step, 0.0).max(axis=1)
    lo = np.zeros(len(u0))
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        over = moved(mid) @ a > budget
        lo, hi = np.where(over, mid, lo), np.where(over, hi, mid)
    return np.where(need[:, None], moved(hi), u0)


def raise_correctives(
    weights: np.ndarray, g0: float, slopes: np.ndarray, bound: np.ndarray, pairs: list[tuple[int, int]]
) -> tuple[np.ndarray, np.ndarray]:
    """First step of the seal with a closing corrective c of a base morph b (mouthClose of jawOpen, a_c < 0):
    raise u_c towards the bound, up to u_b (lips sealed over a lowered jaw, the jaw kept). Returns the weights
    and which morphs the lowering step may move: where the corrective is at its cap, lowering the base would drag
    the corrective down with it, net slope a_b + a_c; when that is not positive, lowering the base cannot help,
    and neither moves there (the jaw stays, sealed)."""
    u = np.array(weights, np.float64)
    a = np.asarray(slopes, np.float64)
    movable = np.ones(u.shape, bool)
    for c, b in pairs:
        if a[c] >= 0:
            continue
        excess = u @ a + g0 - np.asarray(bound, np.float64)
        room = np.maximum(u[:, b] - u[:, c], 0.0)
        u[:, c] += np.clip(excess / -a[c], 0.0, room)
        capped = u[:, c] >= u[:, b] - 1e-12
        movable[capped, c] = False
        movable[capped, b] = a[b] + a[c] > 0
    return u, movable
