"""Symmetric bilinear model of expression (style) and speech (content), paper Sec 3.2 Eq 4:
y_k(s, c) = e_s' W_k c_c, fitted with Tenenbaum & Freeman's (2000) SVD-based alternating algorithm
(see docs/face.md for the stacked notation and the vector transpose).

Arrays here use a 3-D layout instead of the stacked matrices: observations Y[s, c, k], basis W[i, j, k],
style vectors as rows style[s] (= a^s), content vectors as rows content[c] (= b^c). ``vector_transpose``
converts between the stacked matrices the algorithm is written in.

The stage first time-aligns the training takes (stages.face.alignment, DTW) so that column c of Y holds the same speech
content in every expression, then fits the model. One addition to the paper: the configuration vectors are centred
PCA coordinates, so the model also sees the mean face as a constant extra component (``BilinearModel``,
``mean_weight``); without it, frames near the mean face have no defined style and the out-of-sample analysis
collapses (with mean_weight 0 the synthetic known-answer takes of tests/test_eval_face.py are classified at
chance).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field

from msflow import Input, Output, Result, Stage, UserError
from stages.face.alignment import (
    TakeSets,
    align_sets,
    audio_features,
    check_takes,
    group_takes,
    mouth_features,
    neutral_index,
    take_expressions,
    take_sentences,
)

# ----------------------------------------------------------------------------------------------- algebra


def vector_transpose(x: np.ndarray, k: int) -> np.ndarray:
    """Vector transpose X^VT: X is (P*K, Q), P x Q blocks that are K-vectors; returns (Q*K, P) with the blocks
    transposed and each K-vector kept intact (Tenenbaum & Freeman 2000; Marimont & Wandell 1992)."""
    pk, q = x.shape
    if pk % k:
        raise ValueError(f"vector_transpose: {pk} rows are not a multiple of K={k}")
    p = pk // k
    return x.reshape(p, k, q).transpose(2, 1, 0).reshape(q * k, p)


def stack_observations(y: np.ndarray) -> np.ndarray:
    """Y[s, c, k] (S, C, K) to the stacked SK x C matrix (block row s, column c holds y^{sc})."""
    s, c, k = y.shape
    return y.transpose(0, 2, 1).reshape(s * k, c)


def synthesise(w: np.ndarray, style: np.ndarray, content: np.ndarray) -> np.ndarray:
    """Eq 4 for every pair: y[..s, ..c, k] = sum_ij style[s, i] W[i, j, k] content[c, j].

    ``style`` (..., I) and ``content`` (..., J) broadcast against each other if they share leading axes
    (e.g. style (F, I) and content (F, J) give y (F, K), one pair per frame).
    """
    return np.einsum("...i,ijk,...j->...k", style, w, content)


def synthesise_grid(w: np.ndarray, style: np.ndarray, content: np.ndarray) -> np.ndarray:
    """Eq 4 for all combinations: style (S, I) x content (C, J) -> y (S, C, K)."""
    return np.einsum("si,ijk,cj->sck", style, w, content, optimize=True)


@dataclass
class BilinearSolution:
    w: np.ndarray  # (I, J, K)
    style: np.ndarray  # (S, I), rows of an orthonormal I x S matrix
    content: np.ndarray  # (C, J), rows of an orthonormal J x C matrix
    errors: np.ndarray  # relative squared training error per iteration
    converged: bool

    @property
    def error(self) -> float:
        return float(self.errors[-1])


def fit_symmetric_bilinear(
    y: np.ndarray, style_dim: int, content_dim: int, *, tol: float = 1e-10, max_iter: int = 500
) -> BilinearSolution:
    """Tenenbaum & Freeman's symmetric bilinear fit of observations y (S, C, K).

    B starts from the leading right singular vectors of the stacked Y; then alternately
    A <- first I rows of V' in SVD([Y B']^VT) and B <- first J rows of V' in SVD([Y^VT A']^VT), until the relative
    squared error changes by less than ``tol``. Finally W = [[Y B']^VT A']^VT. A and B keep orthonormal rows, which
    makes each update the least-squares optimum for its factor.
    """
    y = np.asarray(y, dtype=np.float64)
    n_style, n_content, k = y.shape
    i_dim, j_dim = int(style_dim), int(content_dim)
    stacked = stack_observations(y)  # SK x C
    stacked_vt = vector_transpose(stacked, k)  # CK x S
    norm = max(float(np.sum(stacked**2)), 1e-300)
    b = np.linalg.svd(stacked, full_matrices=False)[2][:j_dim]  # J x C
    errors: list[float] = []
    converged = False
    for _ in range(max_iter):
        yb_vt = vector_transpose(stacked @ b.T, k)  # JK x S
        a = np.linalg.svd(yb_vt, full_matrices=False)[2][:i_dim]  # I x S
        ya_vt = vector_transpose(stacked_vt @ a.T, k)  # IK x C
        b = np.linalg.svd(ya_vt, full_matrices=False)[2][:j_dim]  # J x C
        # with orthonormal A, B the fitted Y is the projection of Y onto both row spaces: error = 1 - captured
        core = vector_transpose(stacked_vt @ a.T, k) @ b.T  # IK x J = W
        errors.append(max(1.0 - float(np.sum(core**2)) / norm, 0.0))
        if len(errors) > 1 and abs(errors[-2] - errors[-1]) < tol:
            converged = True
            break
    w_stacked = vector_transpose(vector_transpose(stacked @ b.T, k) @ a.T, k)  # IK x J
    w = w_stacked.reshape(i_dim, k, j_dim).transpose(0, 2, 1)  # (I, J, K)
    # the error from the captured energy loses precision near zero: report the direct residual
    residual = y - synthesise_grid(w, a.T, b.T)
    errors[-1] = float(np.sum(residual**2)) / norm
    return BilinearSolution(w, a.T.copy(), b.T.copy(), np.asarray(errors), converged)


def subspace_angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Principal angles (radians) between the row spaces of a and b."""
    from scipy.linalg import subspace_angles as angles

    return angles(np.asarray(a).T, np.asarray(b).T)


def check_dimensions(
    n_style: int, n_content: int, k: int, style_dim: int, content_dim: int, field_prefix: str = "params"
) -> None:
    """UserError when I or J exceed what the data allows: I <= S, J <= C, I <= J K, J <= I K."""
    if n_style < 2:
        raise UserError(f"the bilinear model needs at least two expressions, got {n_style}", field="inputs.aam")
    if not 1 <= style_dim <= n_style:
        raise UserError(
            f"style_dim {style_dim} must be between 1 and the number of expressions ({n_style})",
            field=f"{field_prefix}.style_dim",
        )
    if not 1 <= content_dim <= n_content:
        raise UserError(
            f"content_dim {content_dim} must be between 1 and the number of aligned content frames ({n_content})",
            field=f"{field_prefix}.content_dim",
        )
    if content_dim > style_dim * k or style_dim > content_dim * k:
        raise UserError(
            f"style_dim {style_dim} and content_dim {content_dim} are inconsistent with K={k} "
            f"components (need I <= J*K and J <= I*K)",
            field=f"{field_prefix}.content_dim",
        )


def choose_content_dim(y: np.ndarray, variance: float, maximum: int) -> int:
    """Fewest content dimensions whose singular values capture ``variance`` of the stacked observations."""
    sing = np.linalg.svd(stack_observations(np.asarray(y, dtype=np.float64)), compute_uv=False)
    frac = np.cumsum(sing**2) / max(float(np.sum(sing**2)), 1e-300)
    return int(min(np.searchsorted(frac, variance - 1e-12) + 1, maximum))


# ----------------------------------------------------------------------------------------------- model


@dataclass
class BilinearModel:
    """A fitted expression model as later stages use it (``from_view`` reads the bilinear artifact).

    The configuration vectors y are PCA coordinates centred on the mean face, so a frame close to the mean face
    has y close to 0 and, in a bias-free bilinear model, no defined style (c -> 0 leaves e arbitrary). Like
    Tenenbaum & Freeman, who fit uncentred observations, the model therefore sees the mean face too: each y gets
    one constant extra component ``mean_component`` (kappa), with basis ``w_mean``. kappa = 0 is the centred fit.
    """

    w: np.ndarray  # (I, J, K) basis of the y components
    style: np.ndarray  # (S, I), one row per training expression
    content: np.ndarray  # (C, J), aligned training content
    labels: list[str]
    w_mean: np.ndarray | None = None  # (I, J) basis of the constant mean-face component
    mean_component: float = 0.0  # kappa: the mean-face component's value in every observation

    @property
    def mean_content(self) -> np.ndarray:
        return self.content.mean(0)

    @property
    def w_full(self) -> np.ndarray:
        """(I, J, K+1) with the mean-face component last (or W itself for a centred fit)."""
        if self.w_mean is None or self.mean_component == 0:
            return self.w
        return np.concatenate([self.w, self.w_mean[..., None]], axis=-1)

    def augment(self, y: np.ndarray) -> np.ndarray:
        """y (..., K) with the constant mean-face component appended, matching ``w_full``."""
        y = np.asarray(y, dtype=np.float64)
        if self.w_mean is None or self.mean_component == 0:
            return y
        return np.concatenate([y, np.full(y.shape[:-1] + (1,), self.mean_component)], axis=-1)

    def synthesise(self, style: np.ndarray, content: np.ndarray) -> np.ndarray:
        """Eq 4: y (..., K) for paired style (..., I) and content (..., J)."""
        return synthesise(self.w, style, content)

    def weighted(self, weights: np.ndarray) -> BilinearModel:
        """The same model seen through component weights (K,) or (K+1,) (mean-face component last):
        ``weighted(d).augment(y * d[:K]) == augment(y) * d`` and ``weighted(d).w_full == w_full * d``. Styles and
        content vectors are unchanged, so an analysis of weighted vectors is a weighted least squares."""
        weights = np.asarray(weights, dtype=np.float64)
        k = self.w.shape[2]
        if weights.shape not in ((k,), (self.w_full.shape[2],)):
            raise ValueError(f"weights {weights.shape} do not match the model's {self.w_full.shape[2]} components")
        mean_weight = float(weights[k]) if len(weights) > k else 1.0
        return BilinearModel(
            self.w * weights[:k],
            self.style,
            self.content,
            list(self.labels),
            None if self.w_mean is None else self.w_mean * mean_weight,
            self.mean_component * mean_weight,
        )

    @classmethod
    def from_view(cls, view) -> BilinearModel:
        w_mean = view.get("W_mean")
        return cls(
            np.asarray(view["W"], dtype=np.float64),
            np.asarray(view["style"], dtype=np.float64),
            np.asarray(view["content"], dtype=np.float64),
            list(view.meta["labels"]),
            None if w_mean is None else np.asarray(w_mean, dtype=np.float64),
            float(view.meta.get("mean_component", 0.0)),
        )


def fit_bilinear_model(
    y: np.ndarray,
    labels: list[str],
    *,
    style_dim: int | None = None,
    content_dim: int | None = None,
    content_variance: float = 0.98,
    mean_weight: float = 1.0,
    tol: float = 1e-10,
    max_iter: int = 500,
) -> tuple[BilinearModel, BilinearSolution]:
    """Fit Eq 4 to aligned observations y (S, C, K) (one row of content positions per expression).

    ``mean_weight`` sets kappa = mean_weight * RMS |y| (see ``BilinearModel``); ``content_dim`` None picks the
    fewest dimensions capturing ``content_variance`` of the (augmented) observations.
    """
    y = np.asarray(y, dtype=np.float64)
    n_style, n_content, k = y.shape
    style_dim = n_style if style_dim is None else int(style_dim)
    kappa = float(mean_weight) * float(np.sqrt(np.mean(np.sum(y**2, -1))))
    model = BilinearModel(
        np.zeros((0, 0, k)),
        np.zeros((n_style, 0)),
        np.zeros((n_content, 0)),
        list(labels),
        np.zeros((0, 0)) if kappa > 0 else None,
        kappa,
    )
    augmented = model.augment(y)
    k_full = augmented.shape[2]
    if content_dim is None:
        check_dimensions(n_style, n_content, k_full, style_dim, 1)
        content_dim = choose_content_dim(augmented, content_variance, min(n_content, style_dim * k_full))
    check_dimensions(n_style, n_content, k_full, style_dim, content_dim)
    solution = fit_symmetric_bilinear(augmented, style_dim, content_dim, tol=tol, max_iter=max_iter)
    model.w = solution.w[..., :k]
    model.w_mean = solution.w[..., k] if kappa > 0 else None
    model.style, model.content = solution.style, solution.content
    return model, solution


# ----------------------------------------------------------------------------------------------- stage

BILINEAR_OUTPUTS = {
    "W": Output.array("f", ndim=3, doc="(I, J, K) bilinear basis, Eq 4"),
    "style": Output.array("f", ndim=2, doc="(S, I) style vector per training expression (meta labels order)"),
    "content": Output.array("f", shape=("content", None), doc="(C, J) content vectors of the aligned frames"),
    "aligned_frames": Output.array(
        "i",
        shape=(None, "content"),
        doc="(S, C) frame index into the aam/tracking frame axis, per expression and content column",
    ),
    "aligned_local": Output.array(
        "i", shape=(None, "content"), doc="(S, C) the same frames counted within their own take"
    ),
    "content_set": Output.array("i", shape=("content",), doc="(C,) set (meta sets) each content column comes from"),
    "dtw_paths": Output.array(
        "i", shape=(None, 4), doc="warping path steps (set, take, reference frame, take frame); take: meta takes"
    ),
    "fit_errors": Output.array("f", ndim=1, doc="relative squared training error per iteration"),
    "residual_per_style": Output.array("f", ndim=1, doc="(S,) relative squared training error of each expression"),
    "W_mean": Output.array(
        "f", ndim=2, optional=True, doc="(I, J) basis of the constant mean-face component (meta mean_component)"
    ),
}


def figure_alignment(view, inputs=None):
    """DTW warping paths of every take against its set's reference take, and the fitted style vectors."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = view.meta["labels"]
    takes = view.meta.get("takes", labels)
    paths = np.asarray(view["dtw_paths"])
    style = np.asarray(view["style"])
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(9, 3.6), gridspec_kw={"width_ratios": [1.4, 1]})
    for r, t in sorted({(int(r), int(t)) for r, t in paths[:, :2]}):
        p = paths[(paths[:, 0] == r) & (paths[:, 1] == t)]
        ax.plot(p[:, 2], p[:, 3], label=takes[t] if len(view.meta.get("sets", [])) < 2 else f"{takes[t]} (set {r})")
    ax.set_xlabel(f"{view.meta['reference']} frame (content axis)")
    ax.set_ylabel("take frame")
    ax.set_title(f"content alignment ({view.meta['align']})")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    im = bx.imshow(style, cmap="coolwarm", vmin=-np.abs(style).max(), vmax=np.abs(style).max())
    bx.set_yticks(range(len(labels)), labels)
    bx.set_xticks(range(style.shape[1]))
    bx.set_xlabel("style dimension")
    bx.set_title("style vectors e_s")
    fig.colorbar(im, ax=bx, shrink=0.8)
    fig.tight_layout()
    return fig


class BilinearParams(Stage.Params):
    """How the training takes are aligned and the bilinear model fitted (shared with stages.eval.face's refits)."""

    align: Literal["audio", "mouth"] = "audio"
    reference: str | None = None
    dtw_band: float | None = Field(0.3, gt=0)
    style_dim: int | None = Field(None, ge=1)
    content_dim: int | None = Field(None, ge=1)
    content_variance: float = Field(0.98, gt=0, le=1)
    mean_weight: float = Field(1.0, ge=0)
    tol: float = Field(1e-10, gt=0)
    max_iter: int = Field(500, ge=1)


@dataclass
class TrainingTakes:
    """The takes of an aam artifact as the bilinear fit sees them: labels, frames, expression and sentence."""

    labels: list[str]
    sequence: np.ndarray  # (N,) take of each frame
    expressions: list[str]  # per take: fields["expression"], else the label
    sentences: list[str]  # per take: fields["sentence"], else ""

    @property
    def frames(self) -> list[np.ndarray]:
        return [np.flatnonzero(self.sequence == t) for t in range(len(self.labels))]

    @classmethod
    def from_views(cls, aam, tracks=None) -> TrainingTakes:
        labels = [str(x) for x in aam.meta.get("labels", [])]
        fields = aam.meta.get("fields") or (tracks.meta.get("fields") if tracks is not None else None) or {}
        return cls(
            labels, np.asarray(aam["sequence"]), take_expressions(labels, fields), take_sentences(labels, fields)
        )


def training_sets(
    takes: TrainingTakes, include: np.ndarray | None = None, field: str = "inputs.aam", order: list[str] | None = None
) -> TakeSets:
    """The takes grouped into sets (``group_takes``); UserError with fewer than two expressions or no complete set."""
    groups = group_takes(takes.expressions, takes.sentences, include, order)
    if len(groups.styles) < 2:
        raise UserError(
            f"the bilinear model needs at least two training expressions, got {groups.styles} "
            f"(takes {takes.labels}; a take's expression is its 'expression' field, else its label)",
            field=field,
        )
    if not len(groups.sets):
        raise UserError(
            f"no sentence is spoken in every expression {groups.styles} (sentences {groups.skipped}); the bilinear "
            "model needs the same content in each expression",
            field=field,
        )
    return groups


def fit_options(params: BilinearParams) -> dict:
    """Keyword arguments of ``fit_bilinear_model`` from the stage params."""
    return {
        "style_dim": params.style_dim,
        "content_dim": params.content_dim,
        "content_variance": params.content_variance,
        "mean_weight": params.mean_weight,
        "tol": params.tol,
        "max_iter": params.max_iter,
    }


def fit_warning(fit: BilinearSolution, labels: list[str], max_iter: int) -> list[str]:
    """A warning when the alternation stopped at ``max_iter`` before its error settled."""
    if fit.converged:
        return []
    change = abs(fit.errors[-2] - fit.errors[-1]) if len(fit.errors) > 1 else float("nan")
    return [
        f"bilinear fit of {labels} stopped at max_iter={max_iter} before converging (relative training error "
        f"{fit.error:.4g}, last change {change:.2g}); raise max_iter or lower style_dim/content_dim"
    ]


class BilinearFit(Stage):
    """Content alignment (DTW on audio MFCCs or mouth shape) and the symmetric bilinear fit (Eq 4).

    Each take plays the expression its ``expression`` field names (from the tracking artifact's meta fields), else
    its label; takes of one expression saying the same sentence are aligned set by set (``TakeSets``).
    """

    cheap = True

    Params = BilinearParams
    inputs = {
        "aam": Input.artifact("y", "sequence", "aligned_shapes", doc="appearance model of the training takes"),
        "tracks": Input.artifact(optional=True, doc="tracking artifact of the same takes (audio for align=audio)"),
    }
    outputs = BILINEAR_OUTPUTS
    figures = {"alignment": figure_alignment}

    def run(self, params, inputs):
        aam, tracks = inputs["aam"], inputs.get("tracks")
        takes = TrainingTakes.from_views(aam, tracks)
        groups = training_sets(takes)
        reference = reference_index(params.reference, groups.styles)
        frames = takes_with_frames(takes, groups, params.content_dim)
        features = content_features(
            params.align, takes.labels, takes.sequence, aligned_shapes=aam["aligned_shapes"], tracks=tracks
        )
        alignment = align_sets(features, frames, groups, reference, params.dtw_band)
        y = np.asarray(aam["y"], dtype=np.float64)[alignment.frames]  # (S, C, K)
        model, fit = fit_bilinear_model(y, groups.styles, **fit_options(params))
        return pack_bilinear(params, takes, groups, reference, alignment, y, model, fit)


def takes_with_frames(takes: TrainingTakes, groups: TakeSets, content_dim: int | None) -> list[np.ndarray]:
    """Frames of each take; UserError naming a take in a set shorter than the fit needs."""
    used = sorted({int(t) for t in groups.sets.reshape(-1)})
    min_frames = max(content_dim or 2, 2)
    why = f"content_dim {content_dim}" if content_dim else "content alignment"
    field = "params.content_dim" if content_dim else "inputs.aam"
    return check_takes(takes.sequence, takes.labels, min_frames, why, field, only=used)


def pack_bilinear(params, takes, groups, reference, alignment, y, model, fit) -> Result:
    """The BilinearFit artifact: arrays, meta (with the params the eval refits with), metrics, warnings."""
    residual = y - model.synthesise(model.style[:, None, :], model.content[None, :, :])
    per_style = np.sum(residual**2, axis=(1, 2)) / np.maximum(np.sum(y**2, axis=(1, 2)), 1e-300)
    starts = np.array([np.flatnonzero(takes.sequence == t)[0] for t in range(len(takes.labels))])
    styles = groups.styles
    meta = {
        "labels": styles,
        "takes": takes.labels,
        "take_expression": {label: takes.expressions[t] for t, label in enumerate(takes.labels)},
        "sets": [[takes.labels[int(t)] for t in members] for members in groups.sets],
        "skipped_sentences": groups.skipped,
        "reference": styles[reference],
        "align": params.align,
        "style_dim": model.style.shape[1],
        "content_dim": model.content.shape[1],
        "K": y.shape[2],
        "converged": fit.converged,
        "iterations": len(fit.errors),
        "mean_component": model.mean_component,
        "mean_weight": params.mean_weight,
        "params": params.model_dump(),
    }
    metrics = {
        "train_error": float(np.sum(residual**2) / max(float(np.sum(y**2)), 1e-300)),
        "iterations": len(fit.errors),
        "content_dim": model.content.shape[1],
        "style_dim": model.style.shape[1],
        **{f"dtw_cost_{styles[s]}": float(alignment.costs[s]) for s in range(len(styles))},
    }
    arrays = {
        "W": model.w,
        "style": model.style,
        "content": model.content,
        "aligned_frames": alignment.frames.astype(np.int64),
        "aligned_local": (alignment.frames - starts[takes.sequence[alignment.frames]]).astype(np.int64),
        "content_set": alignment.column_set.astype(np.int64),
        "dtw_paths": alignment.paths,
        "fit_errors": fit.errors,
        "residual_per_style": per_style,
    }
    if model.w_mean is not None:
        arrays["W_mean"] = model.w_mean
    return Result(arrays, meta=meta, metrics=metrics, warnings=fit_warning(fit, styles, params.max_iter))


def reference_index(reference: str | None, styles: list[str]) -> int:
    """The expression whose takes form the content axis: ``reference``, else the neutral one, else the first."""
    if reference is None:
        return neutral_index(styles)
    if reference not in styles:
        raise UserError(
            f"reference expression '{reference}' is not one of the training expressions {styles}",
            field="params.reference",
        )
    return styles.index(reference)


def content_features(
    align: str, labels: list[str], sequence: np.ndarray, *, aligned_shapes: np.ndarray | None = None, tracks=None
) -> list[np.ndarray]:
    """Per-take features for DTW: 'audio' (MFCCs of the tracking artifact's audio at the video frame times) or
    'mouth' (mouth-region shape parameters of the Procrustes-aligned shapes)."""
    if align == "mouth":
        return mouth_features(aligned_shapes, sequence, len(labels))
    check_audio_tracks(tracks, labels, sequence)
    meta = tracks.meta
    bounds = np.asarray(tracks["audio_bounds"])
    rate = float(np.ravel([meta["audio_rate"]])[0])
    offsets = np.broadcast_to(np.asarray(meta.get("audio_offset", 0.0), dtype=np.float64), (len(labels),))
    times = np.asarray(tracks["time"], dtype=np.float64)
    frame_times = [times[sequence == s] for s in range(len(labels))]
    for s, (start, stop) in enumerate(bounds):
        if stop - start < rate * 0.1:
            raise UserError(
                f"take '{labels[s]}' has {stop - start} audio samples (< 0.1 s); use align: mouth",
                field="inputs.tracks.audio",
            )
    return audio_features(tracks["audio"], bounds, rate, frame_times, list(offsets))


def check_audio_tracks(tracks, labels: list[str], sequence: np.ndarray) -> None:
    """UserError unless ``tracks`` is the tracking artifact of these takes, each with audio."""
    if tracks is None or "audio" not in tracks or "audio_bounds" not in tracks:
        raise UserError(
            "align: audio needs the tracking artifact with audio (input 'tracks'); use align: mouth "
            "for takes without audio",
            field="inputs.tracks",
        )
    meta = tracks.meta
    if list(meta.get("labels", [])) != list(labels):
        raise UserError(
            f"tracking labels {meta.get('labels')} differ from the appearance model's {labels}", field="inputs.tracks"
        )
    if not np.array_equal(np.asarray(tracks["sequence"]), sequence):
        raise UserError(
            "the tracking artifact's frames differ from the appearance model's (different takes?)",
            field="inputs.tracks",
        )
    has_audio = meta.get("has_audio", [True] * len(labels))
    if isinstance(has_audio, dict):
        has_audio = [has_audio.get(label, True) for label in labels]
    silent = [label for label, flag in zip(labels, has_audio) if not flag]
    if silent:
        raise UserError(f"take(s) {silent} have no audio; use align: mouth", field="inputs.tracks.audio")
