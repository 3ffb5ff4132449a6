"""Expression analysis of a new sequence (paper Sec 3.3, Eq 5-6): the style and content of every frame under a
trained bilinear model, how they are classified, and how an unconverged analysis is reported.

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
CREMA-D the shape rows, dominated by speech and by postures the training takes never showed, pull held-out frames
towards the wrong expression (balanced accuracy of held-out frames 93% with weight 0, 90% with 1 for the default
training set; 84% and 80% for neutral/happy/angry; edit fidelity about the same: ``msflow sweep eval/face.yaml
-S face.analysis_shape_weight=0,1``). ``analysis_shape_weight: 1, smooth: 0`` is exactly the paper's
analysis of y.

Classification: ``classify: cosine`` is the nearest training style to e(t) by cosine (with I = S orthonormal training
styles this is the largest barycentric weight, and the same as the nearest style in Euclidean distance after the
gauge); ``fit`` is the training style that explains the frame best with its content re-solved (maximum likelihood,
Tenenbaum & Freeman's classification), always reported as ``style_fit_residual``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field

from msflow import Stage, UserError
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
    frame_converged: np.ndarray | None = None  # (F,) bool: the frame's alternation settled before max_iter

    def __post_init__(self):
        if self.frame_converged is None:
            self.frame_converged = np.full(len(self.style), bool(self.converged))


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
        frame_converged = np.ones(f, dtype=bool)
        frame_converged[active] = False
        if (smooth > 0 or smooth_content > 0) and f > 1:
            style, content, extra, converged = self._smooth(
                y_sq, wy, style, content, smooth, smooth_content, tol, max_iter
            )
            iterations += extra
            frame_converged[:] = converged
        residual = np.sum((y - synthesise(self.w, style, content)) ** 2, -1)
        return StyleContent(style, content, iterations, bool(frame_converged.all()), residual, frame_converged)

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
    options = {"smooth": smooth, "smooth_content": smooth_content, "tol": tol, "max_iter": max_iter}
    if weights is not None:
        return analyse_weighted(model, y_model, sequence, np.asarray(weights, dtype=np.float64), init, options)
    analyser = BilinearAnalyser(model.w_full, model.style)
    start = initial_content(y_model, model, init)
    if smooth == 0 and smooth_content == 0:
        return analyser.analyse(y_model, start, tol=tol, max_iter=max_iter)
    return analyse_each_take(analyser, y_model, np.asarray(sequence), start, options)


def analyse_weighted(model, y_model, sequence, weights, init: str, options: dict) -> StyleContent:
    """The style from the weighted components (``weights``), then the content (speech) from every component with that
    style fixed (Eq 6), take by take."""
    result = analyse_takes(model.weighted(weights), y_model * weights, sequence, init=init, **options)
    analyser = BilinearAnalyser(model.w_full, model.style)
    sequence = np.asarray(sequence)
    for take in np.unique(sequence):
        idx = np.flatnonzero(sequence == take)
        result.content[idx] = analyser.content_given_style(y_model[idx], result.style[idx], options["smooth_content"])
    result.residual = np.sum((y_model - synthesise(model.w_full, result.style, result.content)) ** 2, -1)
    return result


def analyse_each_take(
    analyser: BilinearAnalyser, y_model: np.ndarray, sequence: np.ndarray, start: np.ndarray, options: dict
) -> StyleContent:
    """The analysis with a temporal prior, one take (one sequence of frames) at a time, reassembled in frame order."""
    n = len(y_model)
    start = np.broadcast_to(start, (n, analyser.j_dim))
    style, content = np.zeros((n, analyser.i_dim)), np.zeros((n, analyser.j_dim))
    residual, converged = np.zeros(n), np.zeros(n, dtype=bool)
    iterations = 0
    for take in np.unique(sequence):
        idx = np.flatnonzero(sequence == take)
        part = analyser.analyse(y_model[idx], start[idx], **options)
        style[idx], content[idx], residual[idx], converged[idx] = (
            part.style,
            part.content,
            part.residual,
            part.frame_converged,
        )
        iterations = max(iterations, part.iterations)
    return StyleContent(style, content, iterations, bool(converged.all()), residual, converged)


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


# ----------------------------------------------------------------------------------------------- analysis of a take

#: mean relative residual of a take above which the analysis warns that the model does not explain the face.
#: Calibrated with eval/face.yaml on CREMA-D 1001 and seven talking-head clips of other people, the model trained on
#: three of 1001's expressions: the actor's own unseen expressions 0.10-0.38, other people's faces 0.51-0.76.
POOR_FIT_RESIDUAL = 0.45


class AnalysisParams(Stage.Params):
    """How a take is analysed (Eq 5-6); shared by the edit stage and the face evaluation."""

    init: Literal["mean", "nearest"] = "mean"
    smooth: float = Field(0.0, ge=0)
    smooth_content: float = Field(0.0, ge=0)
    analysis_shape_weight: float = Field(0.0, ge=0)
    classify: Literal["cosine", "fit"] = "cosine"
    tol: float = Field(1e-9, gt=0)
    max_iter: int = Field(200, ge=1)


@dataclass
class FrameAnalysis:
    """Everything the analysis says about each frame of one or more takes."""

    style: np.ndarray  # (F, I) e(t)
    content: np.ndarray  # (F, J) c(t)
    style_weights: np.ndarray  # (F, S) e(t) as barycentric weights over the training expressions
    cosine: np.ndarray  # (F, S) cosine of e(t) to each training style
    classes: np.ndarray  # (F,) training expression by the chosen rule (params.classify)
    fit_residual: np.ndarray  # (F, S) relative error with each training style fixed, content re-solved
    residual: np.ndarray  # (F,) relative squared error |y - e' W c|^2 / |y|^2 of the unweighted y
    converged: np.ndarray  # (F,) bool
    iterations: int


def analysis_rows(model: BilinearModel, n_shape: int, shape_weight: float) -> np.ndarray | None:
    """Component weights of the analysis (``component_weights``), or None for the paper's unweighted analysis."""
    return None if shape_weight == 1 else component_weights(n_shape, model.w_full.shape[2], shape_weight)


def analyse_frames(
    model: BilinearModel, n_shape: int, y: np.ndarray, sequence: np.ndarray, params: AnalysisParams
) -> FrameAnalysis:
    """Analyse configuration vectors y (F, K) of the takes ``sequence`` labels (Eq 5-6) and classify every frame."""
    y = np.asarray(y, dtype=np.float64)
    y_model = model.augment(y)
    rows = analysis_rows(model, n_shape, params.analysis_shape_weight)
    result = analyse_takes(
        model,
        y_model,
        sequence,
        init=params.init,
        smooth=params.smooth,
        smooth_content=params.smooth_content,
        tol=params.tol,
        max_iter=params.max_iter,
        weights=rows,
    )
    by_cosine, cosine = classify_styles(result.style, model.style)
    by_fit, fit_residual = classify_by_fit(model, y_model, rows)
    weighted = y_model if rows is None else y_model * rows
    fit_residual = fit_residual / np.maximum(np.sum(weighted**2, -1), 1e-300)[:, None]
    residual = np.sum((y - model.synthesise(result.style, result.content)) ** 2, -1)
    return FrameAnalysis(
        result.style,
        result.content,
        style_barycentric(result.style, model.style),
        cosine,
        by_fit if params.classify == "fit" else by_cosine,
        fit_residual,
        residual / np.maximum(np.sum(y**2, -1), 1e-300),
        np.asarray(result.frame_converged, dtype=bool),
        result.iterations,
    )


def convergence_warnings(
    residual: np.ndarray,
    converged: np.ndarray,
    sequence: np.ndarray,
    labels: list[str],
    max_iter: int,
    what: str = "analysis",
) -> list[str]:
    """One warning per take whose analysis stopped at ``max_iter`` with frames unconverged, naming the take and the
    relative residual of those frames. ``residual``, ``converged`` and ``sequence`` (the take) per frame."""
    out = []
    sequence = np.asarray(sequence)
    for take in np.unique(sequence):
        frames = sequence == take
        stuck = frames & ~np.asarray(converged, dtype=bool)
        if not stuck.any():
            continue
        label = labels[int(take)] if int(take) < len(labels) else str(int(take))
        resid = np.asarray(residual)[stuck]
        out.append(
            f"{what} of take '{label}' stopped at max_iter={max_iter} with {int(stuck.sum())} of {int(frames.sum())} "
            f"frames unconverged (relative residual of those frames: mean {resid.mean():.3g}, worst "
            f"{resid.max():.3g}); raise max_iter or check the take against the training takes"
        )
    return out


def fit_warnings(residual: np.ndarray, sequence: np.ndarray, labels: list[str]) -> list[str]:
    """One warning per take whose frames the model explains poorly (mean relative residual above
    ``POOR_FIT_RESIDUAL``): typically another person's face, which the model of the training takes cannot express."""
    out = []
    sequence = np.asarray(sequence)
    for take in np.unique(sequence):
        mean = float(np.mean(np.asarray(residual)[sequence == take]))
        if mean > POOR_FIT_RESIDUAL:
            label = labels[int(take)] if int(take) < len(labels) else str(int(take))
            out.append(
                f"take '{label}' is explained poorly by the model (mean relative residual {mean:.2f}, above "
                f"{POOR_FIT_RESIDUAL}): is it the performer of the training takes? Its reading and edits are unreliable"
            )
    return out
