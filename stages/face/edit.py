"""Expression analysis and editing of a new sequence (paper Sec 3.3, Eq 5-7), and the edited face images.

Analysis factors every frame's configuration vector y (the test take projected through the training appearance
model) into a style vector e and a content vector c under the trained bilinear basis W, by the paper's
alternation (Eq 5: e = pinv([W c]^VT) y, Eq 6: c = pinv([W^VT e]^VT) y) from the mean training content (``init``
'nearest' starts each frame from its closest training observation instead), batched over all frames: each step is
a batch of small normal-equation solves built from W's precomputed quadratic forms. The pair is
only defined up to e -> s e, c -> c / s; we fix s by requiring e . m = m . m where m is the mean training style
vector. When the style dimension equals the number of training expressions (the default), this constraint is
exactly the affine hull of the training styles, so e has barycentric coordinates over them.

Beyond the paper (whose stated weakness is jitter), ``smooth`` = lambda > 0 adds a temporal prior on the style,
lambda_e * sum_t |e_t - e_{t-1}|^2 (lambda_e = lambda times the typical diagonal of the style's data Hessian, so lambda
is dimensionless); ``smooth_content`` optionally penalises the change of y caused by content changes (off by
default: speech content legitimately changes fast, and a content prior pushes that change into the style). With
the other factor fixed, each half-step is a banded (block-tridiagonal) least-squares problem over the whole take.
lambda = 0 is the paper's per-frame alternation.

Which rows of y say the expression: ``analysis_shape_weight`` weighs the shape rows (r b_s of Eq 3) when solving for
the style; the content is then solved from every component (Eq 6 with that style), so edits keep the input's speech
shapes. The default 0 reads the expression from the texture alone, as the paper observes ("the changes in the
locations of the facial features are subtle. The change in appearance is primarily due to ... the texture"): on
CREMA-D the shape rows, dominated by speech and by postures the training takes never showed, pulled held-out frames
towards the wrong expression (bench/eval_face.py: cosine accuracy neutral/happy/angry 82/86/85% of frames with
weight 1, 85/91/87% with 0; edit fidelity unchanged). ``analysis_shape_weight: 1, smooth: 0`` is exactly the paper's
analysis of y.

Classification: ``classify: cosine`` is the nearest training style to e(t) by cosine (with I = S orthonormal training
styles this is the largest barycentric weight, and the same as the nearest style in Euclidean distance after the
gauge); ``fit`` is the training style that explains the frame best with its content re-solved (maximum likelihood,
Tenenbaum & Freeman's classification), always reported as ``style_fit_residual``.

Editing replaces e by a training expression's style vector or a barycentric mix (Eq 7), constant or keyframed;
the edited y goes back through Eq 3-1 to shapes and textures, and the texture is warped onto the shape and pasted
into the test take's face crops.
"""

from __future__ import annotations

import io
import warnings
from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from msflow import Input, Output, Result, Stage, UserError
from stages.face.aam import AamModel, apply_similarity, check_landmark_scheme, check_landmarks
from stages.face.bilinear import BilinearModel, synthesise, synthesise_grid

# ----------------------------------------------------------------------------------------------- analysis


@dataclass
class StyleContent:
    """Per-frame factors of a sequence under a bilinear model."""

    style: np.ndarray  # (F, I) e(t), normalised so e . m = m . m (m: mean training style)
    content: np.ndarray  # (F, J) c(t)
    iterations: int
    converged: bool
    residual: np.ndarray  # (F,) squared reconstruction error |y - e' W c|^2 per frame


class BilinearAnalyser:
    """Batched solver of Eq 5-6 for a fixed W: precomputes W's quadratic forms so every iteration is a few
    matrix products and batched I x I / J x J solves, whatever the number of frames."""

    def __init__(self, w: np.ndarray, training_styles: np.ndarray):
        self.w = np.asarray(w, dtype=np.float64)
        i_dim, j_dim, _ = self.w.shape
        self.i_dim, self.j_dim = i_dim, j_dim
        # G[i, j, l, m] = sum_k W[i,j,k] W[l,m,k]: |[W c]^VT e|^2 = e' (c' G c) e, no K-sized products per frame
        g = np.einsum("ijk,lmk->ijlm", self.w, self.w)
        self.gram_for_style = g.transpose(1, 3, 0, 2).reshape(j_dim * j_dim, i_dim * i_dim)  # (jm, il)
        self.gram_for_content = g.transpose(0, 2, 1, 3).reshape(i_dim * i_dim, j_dim * j_dim)  # (il, jm)
        self.mean_style = np.asarray(training_styles, dtype=np.float64).mean(0)
        self.gauge = float(self.mean_style @ self.mean_style)
        # orthonormal complement of the mean style: e = mean_style + N z satisfies the gauge for every z
        _, _, vt = np.linalg.svd(self.mean_style[None, :])
        self.complement = vt[1:].T  # (I, I-1)

    # --- quadratic forms of one factor given the other (normal equations of Eq 5 and Eq 6)
    def style_system(self, content: np.ndarray, wy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """[W c]^VT' [W c]^VT (F, I, I) and [W c]^VT' y (F, I)."""
        f = len(content)
        outer = (content[:, :, None] * content[:, None, :]).reshape(f, -1)
        return (outer @ self.gram_for_style).reshape(f, self.i_dim, self.i_dim), np.einsum("fij,fj->fi", wy, content)

    def content_system(self, style: np.ndarray, wy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """[W^VT e]^VT' [W^VT e]^VT (F, J, J) and [W^VT e]^VT' y (F, J)."""
        f = len(style)
        outer = (style[:, :, None] * style[:, None, :]).reshape(f, -1)
        return (outer @ self.gram_for_content).reshape(f, self.j_dim, self.j_dim), np.einsum("fij,fi->fj", wy, style)

    def normalise(self, style: np.ndarray, content: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fix the scale ambiguity: e . m = m . m (and c scaled inversely, y unchanged)."""
        proj = style @ self.mean_style
        tiny = np.abs(proj) < 1e-12 * np.linalg.norm(style, axis=-1) * np.sqrt(self.gauge) + 1e-300
        factor = np.where(
            tiny,
            np.sqrt(self.gauge) / np.maximum(np.linalg.norm(style, axis=-1), 1e-300),
            self.gauge / np.where(tiny, 1.0, proj),
        )
        return style * factor[:, None], content / factor[:, None]

    def objective(self, y_sq: np.ndarray, style: np.ndarray, content: np.ndarray, wy: np.ndarray) -> np.ndarray:
        """|y - e' W c|^2 per frame, from the precomputed forms (no K-sized products)."""
        gram, rhs = self.style_system(content, wy)
        return np.maximum(y_sq - 2 * np.sum(rhs * style, -1) + np.einsum("fi,fil,fl->f", style, gram, style), 0.0)

    def analyse(
        self,
        y: np.ndarray,
        initial_content: np.ndarray,
        *,
        smooth: float = 0.0,
        smooth_content: float = 0.0,
        tol: float = 1e-9,
        max_iter: int = 200,
    ) -> StyleContent:
        """Alternate Eq 5 and Eq 6 from the initial content ((J,) for all frames, as the paper's mean training
        content, or (F, J)), each frame until its squared error changes by less than ``tol`` times |y|^2.

        Converged frames drop out of the batch, so the cost follows the slowest frames only.
        """
        y = np.asarray(y, dtype=np.float64)
        f = len(y)
        wy = np.einsum("ijk,fk->fij", self.w, y)  # y is fixed: its only K-sized product
        y_sq = np.sum(y**2, -1)
        content = np.broadcast_to(np.asarray(initial_content, dtype=np.float64), (f, self.j_dim)).copy()
        style = np.zeros((f, self.i_dim))
        error = np.full(f, np.inf)
        active = np.arange(f)
        iterations = 0
        ridge = 1e-12
        while len(active) and iterations < max_iter:
            iterations += 1
            w_act, c_act = wy[active], content[active]
            gram, rhs = self.style_system(c_act, w_act)
            e_act, c_act = self.normalise(batched_solve(gram, rhs, ridge), c_act)
            gram, rhs = self.content_system(e_act, w_act)
            c_act = batched_solve(gram, rhs, ridge)
            new_error = y_sq[active] - 2 * np.sum(rhs * c_act, -1) + np.einsum("fj,fjm,fm->f", c_act, gram, c_act)
            style[active], content[active] = e_act, c_act
            done = np.abs(error[active] - new_error) <= tol * np.maximum(y_sq[active], 1e-300)
            error[active] = new_error
            active = active[~done]
        converged = len(active) == 0
        if (smooth > 0 or smooth_content > 0) and f > 1:
            style, content, extra, converged = self._smooth(
                y_sq, wy, style, content, smooth, smooth_content, tol, max_iter
            )
            iterations += extra
        residual = np.sum((y - synthesise(self.w, style, content)) ** 2, -1)
        return StyleContent(style, content, iterations, converged, residual)

    def content_given_style(self, y: np.ndarray, style: np.ndarray, smooth_content: float = 0.0) -> np.ndarray:
        """Eq 6 with the style fixed: c = pinv([W^VT e]^VT) y per frame (F, J); with ``smooth_content`` > 0 the
        content prior of ``_smooth`` joins the frames into one banded solve."""
        y = np.asarray(y, dtype=np.float64)
        wy = np.einsum("ijk,fk->fij", self.w, y)
        gram, rhs = self.content_system(np.asarray(style, dtype=np.float64), wy)
        if smooth_content > 0 and len(y) > 1:
            return solve_temporal(gram, rhs, smooth_content * 0.5 * (gram[1:] + gram[:-1]))
        return batched_solve(gram, rhs, 1e-12)

    def _smooth(self, y_sq, wy, style, content, smooth, smooth_content, tol, max_iter):
        """Alternation with the temporal prior, started from the per-frame (paper) solution.

        Style: lambda_e |e_t - e_{t-1}|^2 on the gauge plane e . m = m . m, whose scale is that of the training
        styles; lambda_e = lambda times the mean diagonal of the style's data Hessian at the start, fixed.
        Content: (c_t - c_{t-1})' lambda P (c_t - c_{t-1}) with P the content's data Hessian [W^VT e]^VT'[W^VT e]^VT
        (mean of the two frames): the change of y the content change causes, so shrinking c while inflating e
        buys nothing. (With plain |dc|^2 the prior would move style into content, e drifting off to infinity.)
        """
        f = len(style)
        n = self.complement
        gram_e, _ = self.style_system(content, wy)
        lam_e = smooth * float(np.median(np.trace(gram_e, axis1=1, axis2=2))) / self.i_dim
        previous = np.inf
        converged = False
        iterations = 0
        for iterations in range(1, max_iter + 1):
            if self.i_dim > 1:
                # e = m + N z keeps the gauge; |N dz| = |dz| as N is orthonormal
                gram, rhs = self.style_system(content, wy)
                gz = np.einsum("ia,fil,lb->fab", n, gram, n)
                rz = np.einsum("ia,fi->fa", n, rhs - gram @ self.mean_style)
                style = self.mean_style + solve_temporal(gz, rz, lam_e) @ n.T
            else:
                style = np.broadcast_to(self.mean_style, (f, 1)).copy()
            gram, rhs = self.content_system(style, wy)
            pair_c = smooth_content * 0.5 * (gram[1:] + gram[:-1])
            content = solve_temporal(gram, rhs, pair_c)
            dc, de = np.diff(content, axis=0), np.diff(style, axis=0)
            total = float(
                np.sum(self.objective(y_sq, style, content, wy))
                + np.einsum("fj,fjm,fm->", dc, pair_c, dc)
                + lam_e * np.sum(de**2)
            )
            if abs(previous - total) <= tol * max(float(np.sum(y_sq)), 1e-300):
                converged = True
                break
            previous = total
        return style, content, iterations, converged


def batched_solve(gram: np.ndarray, rhs: np.ndarray, ridge: float) -> np.ndarray:
    """Solve gram[f] x[f] = rhs[f] for all frames; a relative ridge keeps rank-deficient systems finite."""
    d = gram.shape[-1]
    scale = np.trace(gram, axis1=1, axis2=2) / d
    reg = gram + (ridge * np.maximum(scale, 1e-300))[:, None, None] * np.eye(d)
    return np.linalg.solve(reg, rhs[..., None])[..., 0]


def solve_temporal(gram: np.ndarray, rhs: np.ndarray, pair: np.ndarray | float) -> np.ndarray:
    """argmin_x sum_t (x_t' A_t x_t - 2 b_t' x_t) + sum_t (x_{t+1} - x_t)' P_t (x_{t+1} - x_t).

    A (F, d, d), b (F, d), P (F-1, d, d) positive semi-definite (or a scalar: P = p I). The normal equations are
    block tridiagonal, a symmetric banded matrix of half-bandwidth 2d - 1 over F*d unknowns: banded Cholesky,
    linear in the number of frames.
    """
    from scipy.linalg import solveh_banded

    f, d, _ = gram.shape
    if np.isscalar(pair):
        pair = np.broadcast_to(float(pair) * np.eye(d), (max(f - 1, 0), d, d))
    pair = np.asarray(pair, dtype=np.float64)
    diag = np.array(gram, dtype=np.float64, copy=True)
    diag[:-1] += pair
    diag[1:] += pair
    scale = float(np.mean(np.trace(diag, axis1=1, axis2=2))) / d
    diag += 1e-12 * max(scale, 1e-300) * np.eye(d)
    u = 2 * d - 1
    n = f * d
    bands = np.zeros((u + 1, n))  # upper form: bands[u + row - col, col] = M[row, col]
    a_idx, b_idx = np.triu_indices(d)
    rows = (np.arange(f)[:, None] * d + a_idx).reshape(-1)
    cols = (np.arange(f)[:, None] * d + b_idx).reshape(-1)
    bands[u + rows - cols, cols] = diag[:, a_idx, b_idx].reshape(-1)
    if f > 1:
        a_all, b_all = np.meshgrid(np.arange(d), np.arange(d), indexing="ij")
        rows = (np.arange(f - 1)[:, None] * d + a_all.reshape(-1)).reshape(-1)
        cols = ((np.arange(f - 1)[:, None] + 1) * d + b_all.reshape(-1)).reshape(-1)
        bands[u + rows - cols, cols] = -pair[:, a_all.reshape(-1), b_all.reshape(-1)].reshape(-1)
    return solveh_banded(bands, rhs.reshape(-1)).reshape(f, d)


def initial_content(y: np.ndarray, model: BilinearModel, init: str = "mean") -> np.ndarray:
    """Starting content for the alternation: 'mean' (the paper: the average training content vector, (J,)) or
    'nearest' (per frame (F, J): the content of the closest training observation e_s' W c_c, which avoids the
    occasional local minimum the alternation finds from the mean). ``y`` as the model sees it (augmented)."""
    if init == "mean":
        return model.mean_content
    if init != "nearest":
        raise UserError(f"init must be 'mean' or 'nearest', got '{init}'", field="params.init")
    from scipy.spatial.distance import cdist

    grid = synthesise_grid(model.w_full, model.style, model.content)  # (S, C, K)
    nearest = np.argmin(cdist(np.asarray(y, dtype=np.float64), grid.reshape(-1, grid.shape[-1])), axis=1)
    return model.content[nearest % len(model.content)]


def analyse_style_content(
    w: np.ndarray,
    training_styles: np.ndarray,
    initial_content: np.ndarray,
    y: np.ndarray,
    *,
    smooth: float = 0.0,
    smooth_content: float = 0.0,
    tol: float = 1e-9,
    max_iter: int = 200,
) -> StyleContent:
    """Eq 5-6 for every frame of y (F, K): style e(t) and content c(t); see ``BilinearAnalyser``."""
    return BilinearAnalyser(w, training_styles).analyse(
        y, initial_content, smooth=smooth, smooth_content=smooth_content, tol=tol, max_iter=max_iter
    )


def component_weights(n_shape: int, k_model: int, shape_weight: float) -> np.ndarray:
    """Weights (K(+1),) of the model-space components in the Eq 5-6 least squares: ``shape_weight`` on the first
    ``n_shape`` (the r b_s rows of Eq 3), 1 on the texture rows and the mean-face component. 1 everywhere is the
    paper's analysis of y as Eq 3 defines it."""
    weights = np.ones(int(k_model))
    weights[: int(n_shape)] = float(shape_weight)
    return weights


def analyse_takes(
    model: BilinearModel,
    y_model: np.ndarray,
    sequence: np.ndarray,
    *,
    init: str = "mean",
    smooth: float = 0.0,
    smooth_content: float = 0.0,
    tol: float = 1e-9,
    max_iter: int = 200,
    weights: np.ndarray | None = None,
) -> StyleContent:
    """Eq 5-6 for model-space vectors (F, K(+1)) of one or more takes (``sequence`` labels each frame's take).

    Without a temporal prior all frames are one batch; with it, each take is its own sequence (the prior must not
    tie the last frame of one take to the first of the next). ``weights`` (K(+1),) weigh the components in the least
    squares (``component_weights``); the returned residual is always of the unweighted vectors.
    """
    if weights is not None:
        weights = np.asarray(weights, dtype=np.float64)
        result = analyse_takes(
            model.weighted(weights),
            y_model * weights,
            sequence,
            init=init,
            smooth=smooth,
            smooth_content=smooth_content,
            tol=tol,
            max_iter=max_iter,
        )
        # the style is what the weighted rows say; the content (speech) is then solved from every component
        analyser = BilinearAnalyser(model.w_full, model.style)
        sequence = np.asarray(sequence)
        for take in np.unique(sequence):
            idx = np.flatnonzero(sequence == take)
            result.content[idx] = analyser.content_given_style(y_model[idx], result.style[idx], smooth_content)
        result.residual = np.sum((y_model - synthesise(model.w_full, result.style, result.content)) ** 2, -1)
        return result
    analyser = BilinearAnalyser(model.w_full, model.style)
    start = initial_content(y_model, model, init)
    if smooth == 0 and smooth_content == 0:
        return analyser.analyse(y_model, start, tol=tol, max_iter=max_iter)
    sequence = np.asarray(sequence)
    start = np.broadcast_to(start, (len(y_model), model.content.shape[1]))
    parts = {}
    for take in np.unique(sequence):
        idx = np.flatnonzero(sequence == take)
        parts[int(take)] = (
            idx,
            analyser.analyse(
                y_model[idx], start[idx], smooth=smooth, smooth_content=smooth_content, tol=tol, max_iter=max_iter
            ),
        )
    style = np.zeros((len(y_model), model.style.shape[1]))
    content = np.zeros((len(y_model), model.content.shape[1]))
    residual = np.zeros(len(y_model))
    for idx, part in parts.values():
        style[idx], content[idx], residual[idx] = part.style, part.content, part.residual
    return StyleContent(
        style,
        content,
        max(p.iterations for _, p in parts.values()),
        all(p.converged for _, p in parts.values()),
        residual,
    )


def style_barycentric(style: np.ndarray, training_styles: np.ndarray) -> np.ndarray:
    """Weights (F, S) summing to 1 whose mix of the training styles is closest to each e(t) (exact when I = S)."""
    s = np.asarray(training_styles, dtype=np.float64)
    n = len(s)
    # minimise |alpha' S - e|^2 subject to sum(alpha) = 1 (KKT system, same matrix for every frame)
    kkt = np.zeros((n + 1, n + 1))
    kkt[:n, :n] = s @ s.T
    kkt[:n, n] = kkt[n, :n] = 1.0
    rhs = np.concatenate([np.asarray(style) @ s.T, np.ones((len(style), 1))], axis=1)
    return np.linalg.lstsq(kkt, rhs.T, rcond=None)[0][:n].T


def classify_styles(style: np.ndarray, training_styles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest training style by cosine: (F,) index and (F, S) cosine similarities."""
    e = np.asarray(style, dtype=np.float64)
    s = np.asarray(training_styles, dtype=np.float64)
    cos = (e @ s.T) / np.maximum(np.linalg.norm(e, axis=-1, keepdims=True) * np.linalg.norm(s, axis=-1), 1e-300)
    return np.argmax(cos, axis=-1), cos


def style_fit_residuals(model: BilinearModel, y_model: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """(F, S) squared error of each frame explained with each training style held fixed: min_c |y - e_s' W c|^2.

    The maximum-likelihood style under isotropic Gaussian noise (Tenenbaum & Freeman 2000 classify this way):
    the content is re-solved for every candidate style, instead of comparing the freely analysed e(t) with the
    training styles. ``y_model`` as the model sees it (augmented); ``weights`` as in ``analyse_takes``.
    """
    if weights is not None:
        model, y_model = model.weighted(weights), np.asarray(y_model) * weights
    y = np.asarray(y_model, dtype=np.float64)
    out = np.empty((len(y), len(model.style)))
    for s, e in enumerate(model.style):
        basis = np.einsum("i,ijk->kj", e, model.w_full)  # (K, J): content -> y in style s
        u, sing, _ = np.linalg.svd(basis, full_matrices=False)
        q = u[:, sing > sing[0] * 1e-10] if sing.size and sing[0] > 0 else u[:, :0]
        out[:, s] = np.sum(y**2, -1) - np.sum((y @ q) ** 2, -1)
    return np.maximum(out, 0.0)


def classify_by_fit(
    model: BilinearModel, y_model: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Training style that explains each frame best (``style_fit_residuals``): (F,) index, (F, S) residuals."""
    residuals = style_fit_residuals(model, y_model, weights)
    return np.argmin(residuals, axis=-1), residuals


def jitter(style: np.ndarray) -> float:
    """Mean squared second difference of e(t) (frame-to-frame acceleration of the style)."""
    style = np.asarray(style)
    if len(style) < 3:
        return 0.0
    return float(np.mean(np.sum(np.diff(style, n=2, axis=0) ** 2, -1)))


# ----------------------------------------------------------------------------------------------- edit (Eq 7)


class Keyframe(BaseModel):
    """Barycentric weights over the training expressions at a time (seconds from the take's first frame)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    time: float
    weights: dict[str, float]


def weight_vector(weights: dict[str, float], labels: list[str], field: str) -> np.ndarray:
    """Barycentric weights (S,) from a label -> weight mapping; UserError on unknown labels or a sum != 1."""
    unknown = sorted(set(weights) - set(labels))
    if unknown:
        raise UserError(f"unknown expression(s) {unknown}; the model was trained on {labels}", field=field)
    vec = np.array([float(weights.get(label, 0.0)) for label in labels])
    if not np.all(np.isfinite(vec)):
        raise UserError("weights must be finite numbers", field=field)
    if abs(vec.sum() - 1.0) > 1e-6:
        raise UserError(
            f"barycentric weights must sum to 1 (got {vec.sum():g}); e.g. {{{labels[0]}: 0.5, {labels[-1]}: 0.5}}",
            field=field,
        )
    return vec


def keyframed_weights(keyframes: list[Keyframe], labels: list[str], times: np.ndarray, field: str) -> np.ndarray:
    """(F, S) weights interpolated linearly between keyframes (held constant before the first, after the last)."""
    if not keyframes:
        raise UserError("keyframes must not be empty", field=field)
    order = sorted(range(len(keyframes)), key=lambda i: keyframes[i].time)
    key_times = np.array([keyframes[i].time for i in order])
    if np.any(np.diff(key_times) <= 0):
        raise UserError("keyframe times must be distinct", field=field)
    key_weights = np.stack([weight_vector(keyframes[i].weights, labels, f"{field}[{i}].weights") for i in order])
    return np.stack([np.interp(times, key_times, key_weights[:, s]) for s in range(len(labels))], axis=-1)


def check_extrapolation(weights: np.ndarray, max_extrapolation: float, field: str) -> bool:
    """Weights outside the simplex extrapolate the expressions (paper Sec 3.3: too far gives invalid faces).

    UserError beyond ``max_extrapolation`` (most negative weight allowed is -max_extrapolation); a warning
    inside the bound. Returns True when the weights extrapolate.
    """
    lowest = float(np.min(weights))
    if lowest < -max_extrapolation - 1e-12:
        raise UserError(
            f"weights extrapolate beyond the training expressions by {-lowest:g} (a weight of "
            f"{lowest:g}); max_extrapolation is {max_extrapolation:g}",
            field=field,
        )
    if lowest < -1e-12:
        warnings.warn(
            f"{field}: weights extrapolate beyond the training expressions (lowest weight {lowest:g}); "
            f"extreme extrapolation can produce invalid faces",
            stacklevel=2,
        )
        return True
    return False


def edit_configuration(
    w: np.ndarray, training_styles: np.ndarray, weights: np.ndarray, content: np.ndarray
) -> np.ndarray:
    """Eq 7: y(t) = (sum_s alpha_s(t) e_s)' W c(t) for weights (F, S) (or (S,), constant) and content (F, J)."""
    weights = np.broadcast_to(np.asarray(weights, dtype=np.float64), (len(content), len(training_styles)))
    return synthesise(w, weights @ training_styles, content)


# ----------------------------------------------------------------------------------------------- images


def edited_crops(
    model: AamModel,
    y: np.ndarray,
    crops: np.ndarray,
    crop_similarity: np.ndarray,
    texture_offset: np.ndarray,
    texture_scale: np.ndarray,
    feather: float = 1.5,
) -> tuple[np.ndarray, np.ndarray]:
    """Invert Eq 3-1 for y (F, K), warp each texture onto its shape in the frame's crop, paste over the crop.

    The frame's own similarity (mean frame -> crop) and photometric offset/scale place the synthesised face
    where the input face was. Returns (edited crops (F, H, W) uint8, shapes in crop pixels (F, 68, 2)).
    """
    import cv2

    shapes, textures = model.reconstruct(y)
    crop_shapes = apply_similarity(shapes, crop_similarity)
    images = model.warp.fill_outside(model.texture_images(textures, texture_offset, texture_scale))
    h, w = crops.shape[1:]
    out = np.empty_like(crops)
    for f in range(len(y)):
        drawn, covered = model.warp.draw_on_shape(images[f], crop_shapes[f], (w, h))
        alpha = covered.astype(np.float32)
        if feather > 0:
            alpha = cv2.GaussianBlur(cv2.erode(alpha, np.ones((3, 3), np.uint8)), (0, 0), feather)
        blended = alpha * drawn + (1 - alpha) * crops[f].astype(np.float32)
        out[f] = np.clip(np.round(blended), 0, 255).astype(np.uint8)
    return out, crop_shapes


def label_panel(image: np.ndarray, text: str) -> np.ndarray:
    import cv2

    panel = np.ascontiguousarray(image.copy())
    scale = max(panel.shape[1] / 320, 0.35)
    cv2.putText(panel, text, (4, int(14 * scale + 4)), cv2.FONT_HERSHEY_SIMPLEX, scale, 255, 1, cv2.LINE_AA)
    return panel


def side_by_side(panels: list[np.ndarray], names: list[str]) -> np.ndarray:
    """(F, H, n*W) frames: labelled panels next to each other, a 2-pixel gap between them."""
    f, h, w = panels[0].shape
    gap = 2
    out = np.zeros((f, h, len(panels) * (w + gap) - gap), dtype=np.uint8)
    for i, (panel, name) in enumerate(zip(panels, names)):
        for t in range(f):
            out[t, :, i * (w + gap) : i * (w + gap) + w] = label_panel(panel[t], name)
    return out


def encode_mp4(frames: np.ndarray, fps: float, crf: int = 18) -> bytes:
    """Grey frames (F, H, W) uint8 to H.264 MP4 bytes with PyAV (sizes padded to even numbers)."""
    from fractions import Fraction

    import av

    f, h, w = frames.shape
    frames = np.pad(frames, ((0, 0), (0, h % 2), (0, w % 2)), mode="edge")
    buf = io.BytesIO()
    with av.open(buf, mode="w", format="mp4") as container:
        stream = container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001))
        stream.width, stream.height = frames.shape[2], frames.shape[1]
        stream.pix_fmt = "yuv420p"
        stream.options = {"crf": str(crf), "preset": "medium"}
        for t in range(f):
            rgb = np.repeat(frames[t][:, :, None], 3, axis=2)
            for packet in stream.encode(av.VideoFrame.from_ndarray(rgb, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return buf.getvalue()


def encode_png(image: np.ndarray) -> bytes:
    import cv2

    ok, data = cv2.imencode(".png", np.ascontiguousarray(image))
    if not ok:  # pragma: no cover - OpenCV always encodes uint8 images
        raise RuntimeError("PNG encoding failed")
    return data.tobytes()


def interpolation_path(path: list[str], labels: list[str], steps: int) -> tuple[np.ndarray, list[str]]:
    """Barycentric weights (n, S) along a piecewise-linear path of expressions (paper Fig. 2), with captions."""
    idx = [labels.index(p) for p in path]
    rows, names = [], []
    for a, b in zip(idx[:-1], idx[1:]):
        for alpha in np.linspace(1.0, 0.0, steps)[: -1 if b != idx[-1] else None]:
            w = np.zeros(len(labels))
            w[a] += alpha
            w[b] += 1 - alpha
            rows.append(w)
            names.append(f"{labels[a]} {alpha:.2f}" if 0 < alpha < 1 else labels[a] if alpha == 1 else labels[b])
    return np.stack(rows), names


# ----------------------------------------------------------------------------------------------- stage

EDIT_OUTPUTS = {
    "style": Output.array("f", shape=("frames", None), doc="analysed e(t) (Eq 5)"),
    "content": Output.array("f", shape=("frames", None), doc="analysed c(t) (Eq 6)"),
    "style_weights": Output.array(
        "f", shape=("frames", "labels"), doc="e(t) as barycentric weights over the training expressions"
    ),
    "style_cosine": Output.array("f", shape=("frames", "labels"), doc="cosine of e(t) to each training style"),
    "classification": Output.array(
        "i",
        shape=("frames",),
        doc="nearest training style: by cosine of e(t), or by style_fit_residual (params.classify)",
    ),
    "style_fit_residual": Output.array(
        "f",
        shape=("frames", "labels"),
        doc="relative squared error of each frame explained with each training style "
        "fixed, content re-solved (analysis weights)",
    ),
    "residual": Output.array("f", shape=("frames",), doc="relative squared error of the analysed y per frame"),
    "weights": Output.array("f", shape=("targets", "frames", "labels"), doc="Eq 7 weights used per target"),
    "y": Output.array("f", shape=("targets", "frames", None), doc="edited configuration vectors"),
    "shapes": Output.array(
        "f",
        shape=("targets", "frames", 68, 2),
        dtype="float32",
        doc="edited shapes in the aam mean-shape frame, one set per meta['targets'] (training "
        "expressions only; mixes are in mixed_shapes)",
    ),
    "crop_shapes": Output.array(
        "f", shape=("targets", "frames", 68, 2), dtype="float32", doc="edited shapes in the test take's crop pixels"
    ),
    "frames": Output.array("u", shape=("targets", "frames", None, None), dtype="uint8", doc="edited face crops (grey)"),
    "mixed_weights": Output.array(
        "f",
        shape=("mixes", "frames", "labels"),
        optional=True,
        doc="Eq 7 weights of the mix / keyframed edits (meta['mixes'])",
    ),
    "mixed_y": Output.array("f", shape=("mixes", "frames", None), optional=True),
    "mixed_shapes": Output.array("f", shape=("mixes", "frames", 68, 2), dtype="float32", optional=True),
    "mixed_crop_shapes": Output.array("f", shape=("mixes", "frames", 68, 2), dtype="float32", optional=True),
    "mixed_frames": Output.array("u", shape=("mixes", "frames", None, None), dtype="uint8", optional=True),
    "sequence": Output.array("i", shape=("frames",), dtype="int32", doc="test take of each frame (meta test_labels)"),
    "time": Output.array("f", shape=("frames",), doc="seconds since the take's first frame"),
    "video": Output.file(".mp4", optional=True, doc="input | edited expressions side by side"),
    "strip": Output.file(".png", optional=True, doc="interpolation strip of one frame (paper Fig. 2)"),
}


class ExpressionEdit(Stage):
    """Analyse the test take with the trained bilinear model (Eq 5-6) and resynthesise it with other expressions
    (Eq 7), as shapes, configuration vectors and face images (MP4 and an interpolation strip)."""

    class Params(Stage.Params):
        targets: list[str] | None = None
        mix: dict[str, float] | None = None
        keyframes: list[Keyframe] | None = None
        max_extrapolation: float = Field(0.5, ge=0)
        init: Literal["mean", "nearest"] = "mean"
        smooth: float = Field(0.0, ge=0)
        smooth_content: float = Field(0.0, ge=0)
        analysis_shape_weight: float = Field(0.0, ge=0)
        classify: Literal["cosine", "fit"] = "cosine"
        tol: float = Field(1e-9, gt=0)
        max_iter: int = Field(200, ge=1)
        video: bool = True
        strip_path: list[str] | None = None
        strip_steps: int = Field(4, ge=2)
        strip_frame: int | None = None

    inputs = {
        "model": Input.artifact("W", "style", "content", doc="bilinear artifact"),
        "aam": Input.artifact("mean_shape", "shape_basis", "texture_basis", doc="appearance model of training"),
        "tracks": Input.artifact("landmarks", "crops", "crop_landmarks", doc="tracking of the test take(s)"),
    }
    outputs = EDIT_OUTPUTS

    def run(self, params, inputs):
        bilinear = BilinearModel.from_view(inputs["model"])
        aam_view, tracks = inputs["aam"], inputs["tracks"]
        model = AamModel.from_view(aam_view)
        labels = bilinear.labels
        k = bilinear.w.shape[2]
        if model.n_shape + model.n_texture != k or len(bilinear.style) != len(labels):
            raise UserError(
                f"the bilinear model has K={k} components but the appearance model has "
                f"{model.n_shape}+{model.n_texture}; fit both from the same aam artifact",
                field="inputs.model",
            )
        landmarks = np.asarray(tracks["landmarks"])
        test_labels = list(tracks.meta.get("labels", ["test"]))
        sequence = np.asarray(tracks.get("sequence", np.zeros(len(landmarks), dtype=np.int32)))
        check_landmark_scheme(
            landmarks,
            tracks.meta,
            "inputs.tracks.landmarks",
            expected=str(aam_view.meta.get("landmark_scheme", "ibug68")),
        )
        check_landmarks(landmarks, sequence, test_labels, "inputs.tracks.landmarks")
        check_landmarks(tracks["crop_landmarks"], sequence, test_labels, "inputs.tracks.crop_landmarks")
        crops = np.asarray(tracks["crops"])
        proj = model.project(landmarks, crops, tracks["crop_landmarks"])

        y_model = bilinear.augment(proj.y)
        rows = (
            None
            if params.analysis_shape_weight == 1
            else component_weights(model.n_shape, y_model.shape[1], params.analysis_shape_weight)
        )
        analysis = analyse_takes(
            bilinear,
            y_model,
            sequence,
            init=params.init,
            smooth=params.smooth,
            smooth_content=params.smooth_content,
            tol=params.tol,
            max_iter=params.max_iter,
            weights=rows,
        )
        classes, cosine = classify_styles(analysis.style, bilinear.style)
        by_fit, fit_residual = classify_by_fit(bilinear, y_model, rows)
        fit_residual = (
            fit_residual / np.maximum(np.sum((y_model if rows is None else y_model * rows) ** 2, -1), 1e-300)[:, None]
        )
        if params.classify == "fit":
            classes = by_fit
        bary = style_barycentric(analysis.style, bilinear.style)
        y_fit = bilinear.synthesise(analysis.style, analysis.content)
        residual = np.sum((proj.y - y_fit) ** 2, -1) / np.maximum(np.sum(proj.y**2, -1), 1e-300)

        fps = first_number(tracks.meta.get("fps"), 30.0)
        times = np.asarray(tracks.get("time", np.arange(len(landmarks)) / fps), dtype=np.float64)
        (target_names, weights), (mix_names, mix_weights), extrapolated = self.target_weights(params, labels, times)
        arrays = {
            "style": analysis.style,
            "content": analysis.content,
            "style_weights": bary,
            "style_cosine": cosine,
            "classification": classes.astype(np.int32),
            "residual": residual,
            "style_fit_residual": fit_residual,
            "sequence": sequence.astype(np.int32),
            "time": times,
        }
        panels, panel_names = [crops], ["input"]
        for prefix, names, wts in (("", target_names, weights), ("mixed_", mix_names, mix_weights)):
            if prefix and not names:
                continue
            y_edit, shapes, crop_shapes, frames = self.render(wts, bilinear, model, proj, analysis, crops)
            arrays.update(
                {
                    f"{prefix}weights": wts,
                    f"{prefix}y": y_edit,
                    f"{prefix}shapes": shapes,
                    f"{prefix}crop_shapes": crop_shapes,
                    f"{prefix}frames": frames,
                }
            )
            panels += list(frames)
            panel_names += names
        if params.video:
            arrays["video"] = encode_mp4(side_by_side(panels, panel_names), fps)
        strip_path = params.strip_path if params.strip_path is not None else default_strip_path(labels)
        arrays["strip"] = self.strip(params, strip_path, labels, bilinear, model, proj, analysis, crops)
        counts = np.bincount(classes, minlength=len(labels))
        meta = {
            "labels": labels,
            "targets": target_names,
            "mixes": mix_names,
            "fps": fps,
            "test_labels": test_labels,
            "smooth": params.smooth,
            "analysis_shape_weight": params.analysis_shape_weight,
            "classify": params.classify,
            "iterations": analysis.iterations,
            "converged": analysis.converged,
            "extrapolated": extrapolated,
            "strip_path": strip_path,
            "classified_as": {labels[s]: int(counts[s]) for s in range(len(labels))},
        }
        metrics = {
            "mean_residual": float(np.mean(arrays["residual"])),
            "jitter": jitter(analysis.style),
            "iterations": analysis.iterations,
            **{f"fraction_{labels[s]}": float(counts[s] / len(classes)) for s in range(len(labels))},
        }
        return Result(arrays, meta=meta, metrics=metrics)

    @staticmethod
    def target_weights(params, labels, times):
        """((expression targets, weights (T, F, S)), (mix names, weights (M, F, S)), extrapolated)."""
        names, rows = [], []
        for name in params.targets if params.targets is not None else labels:
            if name not in labels:
                raise UserError(f"target '{name}' is not a training expression {labels}", field="params.targets")
            names.append(name)
            rows.append(np.broadcast_to(np.eye(len(labels))[labels.index(name)], (len(times), len(labels))))
        mix_names, mix_rows = [], []
        extrapolated = False
        if params.mix is not None:
            vec = weight_vector(params.mix, labels, "params.mix")
            extrapolated |= check_extrapolation(vec, params.max_extrapolation, "params.mix")
            mix_names.append("mix")
            mix_rows.append(np.broadcast_to(vec, (len(times), len(labels))))
        if params.keyframes is not None:
            wt = keyframed_weights(params.keyframes, labels, times, "params.keyframes")
            extrapolated |= check_extrapolation(wt, params.max_extrapolation, "params.keyframes")
            mix_names.append("keyframed")
            mix_rows.append(wt)
        if not rows and not mix_rows:
            raise UserError("nothing to synthesise: give targets, mix or keyframes", field="params.targets")

        def stack(r):
            return np.stack(r).astype(np.float64) if r else np.zeros((0, len(times), len(labels)))

        return (names, stack(rows)), (mix_names, stack(mix_rows)), extrapolated

    @staticmethod
    def render(weights, bilinear, model, proj, analysis, crops):
        """Eq 7 for each row of weights (T, F, S), back to shapes and face crops: (y, shapes, crop shapes, crops)."""
        y_edit = (
            np.stack([edit_configuration(bilinear.w, bilinear.style, wt, analysis.content) for wt in weights])
            if len(weights)
            else np.zeros((0, len(crops), bilinear.w.shape[2]))
        )
        shapes = model.reconstruct_shapes(model.split(y_edit)[0]).astype(np.float32)
        frames, crop_shapes = [], []
        for y_t in y_edit:
            img, cs = edited_crops(model, y_t, crops, proj.crop_similarity, proj.texture_offset, proj.texture_scale)
            frames.append(img)
            crop_shapes.append(cs)
        frames = np.stack(frames) if frames else np.zeros((0,) + crops.shape, dtype=np.uint8)
        crop_shapes = np.stack(crop_shapes).astype(np.float32) if crop_shapes else shapes.copy()
        return y_edit, shapes, crop_shapes, frames

    @staticmethod
    def strip(params, path, labels, bilinear, model, proj, analysis, crops) -> bytes:
        missing = [p for p in path if p not in labels]
        if missing or len(path) < 2:
            raise UserError(
                f"strip_path {path} must name at least two training expressions {labels}", field="params.strip_path"
            )
        if params.strip_steps < 2:
            raise UserError("strip_steps must be at least 2", field="params.strip_steps")
        n = len(crops)
        frame = params.strip_frame if params.strip_frame is not None else n // 2
        if not 0 <= frame < n:
            raise UserError(f"strip_frame {frame} is outside the take's {n} frames", field="params.strip_frame")
        wts, names = interpolation_path(path, labels, params.strip_steps)
        content = np.repeat(analysis.content[frame : frame + 1], len(wts), axis=0)
        y = edit_configuration(bilinear.w, bilinear.style, wts, content)
        rep = np.repeat
        images, _ = edited_crops(
            model,
            y,
            rep(crops[frame : frame + 1], len(wts), 0),
            rep(proj.crop_similarity[frame : frame + 1], len(wts), 0),
            rep(proj.texture_offset[frame : frame + 1], len(wts)),
            rep(proj.texture_scale[frame : frame + 1], len(wts)),
        )
        strip = side_by_side([img[None] for img in images], names)[0]
        return encode_png(strip)


def default_strip_path(labels: list[str]) -> list[str]:
    """happy -> neutral -> angry when trained on those, else the training expressions in order."""
    wanted = ["happy", "neutral", "angry"]
    return wanted if all(w in labels for w in wanted) else list(labels)


def first_number(value, default: float) -> float:
    if value is None:
        return default
    arr = np.ravel(np.asarray(value, dtype=np.float64))
    return float(arr[0]) if arr.size else default


def figure_style_over_time(view, inputs=None):
    """Barycentric weights of the analysed style e(t) over the training expressions, frame by frame."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    weights = np.asarray(view["style_weights"])
    labels = view.meta["labels"]
    fps = view.meta.get("fps") or 30.0
    t = np.arange(len(weights)) / fps
    fig, ax = plt.subplots(figsize=(6, 3))
    for s, label in enumerate(labels):
        ax.plot(t, weights[:, s], label=label)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("style weight")
    ax.set_title(f"analysed expression (smooth = {view.meta.get('smooth', 0)})")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def figure_strip(view, inputs=None) -> bytes:
    """The interpolation strip (paper Fig. 2) as PNG."""
    return view.bytes("strip")


ExpressionEdit.figures = {"style_over_time": figure_style_over_time, "interpolation_strip": figure_strip}
