"""2-D similarity transforms (uniform scale, rotation, translation): the weighted least-squares fit of one point set
onto another, and the small algebra around it. One implementation for the whole project (tracking's shape model,
the appearance model's Procrustes alignment).

A similarity maps a point p to A p + t with A = [[a, -b], [b, a]] (scale s = |a + ib|, angle = arg(a + ib)). In
complex notation, z -> c z + t with c = a + ib: 2-D similarities are the complex affine maps. Fitting ``src`` onto
``dst`` with weights w_i (Umeyama, "Least-squares estimation of transformation parameters between two point
patterns", PAMI 1991, restricted to 2-D; or directly, least squares in c and t):

    minimise sum_i w_i |c z_i + t - d_i|^2
    => with weighted centroids mu_z, mu_d and centred points z'_i, d'_i:
       c = sum_i w_i conj(z'_i) d'_i / sum_i w_i |z'_i|^2,   t = mu_d - c mu_z.

Transforms are (..., 2, 3) arrays [A | t] (the layout ``cv2.warpAffine`` takes); every function broadcasts over
leading axes, so many shapes fit in one call.
"""

from __future__ import annotations

import numpy as np


def fit_similarity(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """The (..., 2, 3) similarity best mapping ``src`` (..., n, 2) onto ``dst`` (..., n, 2) in weighted least
    squares (closed form, module docstring). ``weights`` (..., n) default to 1; they need not sum to 1."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    w = np.ones(src.shape[:-1]) if weights is None else np.broadcast_to(np.asarray(weights, float), src.shape[:-1])
    w = w / np.sum(w, axis=-1, keepdims=True)
    mu_s = np.einsum("...n,...nd->...d", w, src)
    mu_d = np.einsum("...n,...nd->...d", w, dst)
    s, d = src - mu_s[..., None, :], dst - mu_d[..., None, :]
    var = np.einsum("...n,...n->...", w, np.sum(s * s, axis=-1))
    a = np.einsum("...n,...n->...", w, s[..., 0] * d[..., 0] + s[..., 1] * d[..., 1]) / var
    b = np.einsum("...n,...n->...", w, s[..., 0] * d[..., 1] - s[..., 1] * d[..., 0]) / var
    m = np.stack([np.stack([a, -b], axis=-1), np.stack([b, a], axis=-1)], axis=-2)
    t = mu_d - np.einsum("...ij,...j->...i", m, mu_s)
    return np.concatenate([m, t[..., None]], axis=-1)


def apply_similarity(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (..., n, 2) mapped by (..., 2, 3) transforms."""
    transform = np.asarray(transform, dtype=np.float64)
    return np.einsum("...ij,...nj->...ni", transform[..., :2], points) + transform[..., None, :, 2]


def invert_similarity(transform: np.ndarray) -> np.ndarray:
    """The inverse (..., 2, 3) similarity: A^-1 = A^T / s^2, t' = -A^-1 t."""
    transform = np.asarray(transform, dtype=np.float64)
    a = transform[..., :2]
    scale2 = a[..., 0, 0] ** 2 + a[..., 1, 0] ** 2
    inv = np.swapaxes(a, -1, -2) / scale2[..., None, None]
    return np.concatenate([inv, -np.einsum("...ij,...j->...i", inv, transform[..., 2])[..., None]], axis=-1)


def similarity_parameters(transform: np.ndarray) -> np.ndarray:
    """(..., 4) [scale, angle (radians), tx, ty] of (..., 2, 3) similarities."""
    transform = np.asarray(transform, dtype=np.float64)
    a, b = transform[..., 0, 0], transform[..., 1, 0]
    return np.stack([np.hypot(a, b), np.arctan2(b, a), transform[..., 0, 2], transform[..., 1, 2]], axis=-1)


def similarity_from_parameters(parameters: np.ndarray) -> np.ndarray:
    """(..., 2, 3) similarities from (..., 4) [scale, angle (radians), tx, ty]; the inverse of
    ``similarity_parameters``."""
    parameters = np.asarray(parameters, dtype=np.float64)
    scale, angle = parameters[..., 0], parameters[..., 1]
    a, b = scale * np.cos(angle), scale * np.sin(angle)
    rows = [np.stack([a, -b, parameters[..., 2]], axis=-1), np.stack([b, a, parameters[..., 3]], axis=-1)]
    return np.stack(rows, axis=-2)


def align_to(shapes: np.ndarray, reference: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Shapes (..., n, 2) moved by the similarity that best maps each onto ``reference`` (n, 2)."""
    shapes = np.asarray(shapes, dtype=np.float64)
    reference = np.broadcast_to(np.asarray(reference, dtype=np.float64), shapes.shape)
    return apply_similarity(fit_similarity(shapes, reference, weights), shapes)
