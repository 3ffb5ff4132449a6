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
- of all the weights that meet it, the seal takes the nearest to u(t) that only *lowers* weights
  (0 <= u' <= u): min ||u' - u||^2 s.t. a.u' <= b. Its solution is u'(lambda) = clip(u - lambda a, 0, u) for the
  smallest lambda >= 0 that meets the bound (a.u'(lambda) falls as lambda grows), found by bisection for all
  frames at once. Only opening morphs (a_m > 0) move; nothing is pushed into the other lip.
"""

from __future__ import annotations

import numpy as np

from stages.retarget.keyshapes import INNER_LIP_PAIRS, inter_ocular_distance


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
    weights: np.ndarray, g0: float, slopes: np.ndarray, bound: np.ndarray, iterations: int = 60
) -> np.ndarray:
    """The weights (frames, M) nearest to ``weights`` with gap(u) <= ``bound`` (frames,), lowering weights only."""
    u0 = np.asarray(weights, np.float64)
    a = np.asarray(slopes, np.float64)
    budget = np.asarray(bound, np.float64) - g0

    def gap(lam):
        return np.clip(u0 - lam[:, None] * a, 0.0, u0) @ a

    need = gap(np.zeros(len(u0))) > budget
    if not need.any():
        return u0.copy()
    # bracket: at lambda = 1 / min positive slope every opening morph is at 0 (the most the seal can do)
    positive = a[a > 0]
    hi = np.full(len(u0), 1.0 / positive.min() if positive.size else 0.0)
    lo = np.zeros(len(u0))
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        over = gap(mid) > budget
        lo, hi = np.where(over, mid, lo), np.where(over, hi, mid)
    out = np.clip(u0 - hi[:, None] * a, 0.0, u0)
    return np.where(need[:, None], out, u0)
