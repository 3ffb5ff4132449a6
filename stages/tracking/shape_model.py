"""A 2D point distribution model of the 68 landmarks (Cootes et al. 1995) for constraining tracked shapes.

The modes come from the generic 3D face: the ICT FaceKit landmark vertices moved by random mixtures of its
expression shapes and turned by random yaw/pitch, projected orthographically and Procrustes-aligned; PCA keeps
the modes that explain ``variance`` of the spread. The mean is the tracked person's own first shape, so the
model only says how a face of that shape may deform, not what it looks like. Fitting a shape is the paper's
eigen-tracking constraint (Sec. 6, after Black & Jepson 1996): every tracked shape is replaced by its
projection onto the plausible-shape subspace, points that the tracker lost weighing nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.geometry.similarity import align_to, fit_similarity
from stages.tracking.face3d import Face3D


@dataclass(frozen=True)
class ShapeModel:
    mean: np.ndarray  # (68, 2) centred, RMS distance to the centroid 1
    basis: np.ndarray  # (136, k) orthonormal columns, x/y interleaved per point
    variances: np.ndarray  # (k,) in mean-shape units squared

    def with_mean(self, shape: np.ndarray) -> ShapeModel:
        """The same modes around another mean (e.g. the tracked person's first shape)."""
        return ShapeModel(normalise_shape(align_to(shape, self.mean)), self.basis, self.variances)


def normalise_shape(points: np.ndarray) -> np.ndarray:
    """Centre (..., n, 2) shapes and scale them to unit RMS distance from the centroid."""
    p = np.asarray(points, dtype=np.float64)
    p = p - p.mean(axis=-2, keepdims=True)
    return p / np.sqrt(np.mean(np.sum(p * p, axis=-1), axis=-1))[..., None, None]


def rotation_yx(yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    one, zero = np.ones_like(yaw), np.zeros_like(yaw)
    ry = np.stack([np.stack([cy, zero, sy], -1), np.stack([zero, one, zero], -1), np.stack([-sy, zero, cy], -1)], -2)
    rx = np.stack([np.stack([one, zero, zero], -1), np.stack([zero, cp, -sp], -1), np.stack([zero, sp, cp], -1)], -2)
    return ry @ rx


def build_shape_model(
    face3d: Face3D,
    *,
    variance: float = 0.98,
    samples: int = 3000,
    max_yaw_deg: float = 30.0,
    max_pitch_deg: float = 20.0,
    expressions_per_sample: int = 4,
    seed: int = 0,
) -> ShapeModel:
    """PCA of projected, aligned 3D face shapes under random expressions and head turns (deterministic)."""
    rng = np.random.default_rng(seed)
    names = sorted(face3d.expression_offsets)
    offsets = np.stack([face3d.expression_offsets[k] for k in names]) if names else np.zeros((0, 68, 3))
    weights = np.zeros((samples, len(offsets)))
    if len(offsets):
        for k in range(expressions_per_sample):
            pick = rng.integers(0, len(offsets), samples)
            weights[np.arange(samples), pick] = rng.uniform(0, 1, samples)
    shapes3d = face3d.neutral + np.einsum("se,epd->spd", weights, offsets)
    yaw = np.radians(rng.uniform(-max_yaw_deg, max_yaw_deg, samples))
    pitch = np.radians(rng.uniform(-max_pitch_deg, max_pitch_deg, samples))
    turned = np.einsum("sij,spj->spi", rotation_yx(yaw, pitch), shapes3d)
    image = turned[..., :2] * np.array([1.0, -1.0])  # orthographic, image y down
    reference = normalise_shape(face3d.neutral[:, :2] * np.array([1.0, -1.0]))
    for _ in range(3):  # generalised Procrustes
        aligned = align_to(image, reference)
        reference = normalise_shape(aligned.mean(axis=0))
    # tangent-space projection (Cootes & Taylor): rescale each aligned shape so its offset from the mean is
    # orthogonal to the mean; otherwise one mode would just be overall size, which the similarity already fits
    ref_flat = reference.reshape(-1)
    aligned_flat = aligned.reshape(samples, -1)
    aligned_flat = aligned_flat * (ref_flat @ ref_flat / (aligned_flat @ ref_flat))[:, None]
    flat = aligned_flat - ref_flat
    var, vectors = np.linalg.eigh(flat.T @ flat / samples)  # 136 x 136: cheaper than an SVD of the samples
    var, vectors = np.clip(var[::-1], 0, None), vectors[:, ::-1]
    k = int(np.searchsorted(np.cumsum(var) / var.sum(), variance) + 1)
    return ShapeModel(reference, np.ascontiguousarray(vectors[:, :k]), var[:k])


def fit_shape(
    model: ShapeModel,
    points: np.ndarray,
    weights: np.ndarray | None = None,
    *,
    noise: float = 0.02,
    iterations: int = 4,
    limit: float = 3.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Project a (68, 2) image shape onto the model: returns (fitted image shape, mode coefficients).

    Alternates a weighted similarity alignment with a regularised weighted least-squares solve for the mode
    coefficients b (prior b_k ~ N(0, variance_k), point noise ``noise`` in mean-shape units), clamped to
    +-``limit`` standard deviations. Points with weight 0 are predicted from the others.
    """
    points = np.asarray(points, dtype=np.float64)
    w = np.ones(len(points)) if weights is None else np.clip(np.asarray(weights, dtype=np.float64), 0, None)
    if w.sum() < 3:
        w = np.ones(len(points))
    phi, lam = model.basis, model.variances
    w2 = np.repeat(w, 2)
    b = np.zeros(len(lam))
    precision = noise**2 / lam
    for _ in range(iterations):
        shape = model.mean + (phi @ b).reshape(-1, 2)
        to_image = fit_similarity(shape, points, w)
        a = to_image[:, :2]
        local = (points - to_image[:, 2]) @ np.linalg.inv(a).T
        resid = (local - model.mean).reshape(-1)
        lhs = phi.T @ (w2[:, None] * phi) + np.diag(precision) * w.mean()
        b = np.linalg.solve(lhs, phi.T @ (w2 * resid))
        sd = np.sqrt(lam)
        b = np.clip(b, -limit * sd, limit * sd)
    shape = model.mean + (phi @ b).reshape(-1, 2)
    to_image = fit_similarity(shape, points, w)
    return shape @ to_image[:, :2].T + to_image[:, 2], b
