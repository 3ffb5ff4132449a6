"""Appearance model of the face (paper Sec 3.1, Eq 1-3): Procrustes-aligned shape PCA, shape-free texture PCA,
and the combined facial configuration vector y = [B_s b_s; b_g] that the bilinear model factors.

The maths are plain functions on numpy arrays; ``AamModel`` bundles a fitted model with ``project`` (new
sequences into the training model, never refitting) and ``reconstruct`` (parameters back to shapes and
textures). ``AamPca`` is the pipeline stage.

Shape frame ("mean-shape frame"): the generalised Procrustes gauge is fixed so that the mean shape is centred at
the origin, its eye centres are level and one unit apart (inter-ocular distance 1, iBUG 68 eyes 36-41 and 42-47),
with image orientation kept (x right, y down). Landmark errors in this frame are therefore already normalised
by the inter-ocular distance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import Field

from msflow import Input, Output, Result, Stage, UserError
from stages.face.warp import PiecewiseAffineWarp, delaunay_triangles

#: iBUG 68-point indices of the two eyes (image left, image right)
IBUG68_EYES = (np.arange(36, 42), np.arange(42, 48))
#: iBUG 68-point indices of the mouth (outer and inner lip)
IBUG68_MOUTH = np.arange(48, 68)


# ----------------------------------------------------------------------------------------------- Procrustes


def eye_centres(shapes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centres of the image-left and image-right eye (..., 2) of iBUG-68 shapes (..., 68, 2)."""
    return shapes[..., IBUG68_EYES[0], :].mean(-2), shapes[..., IBUG68_EYES[1], :].mean(-2)


def interocular_distance(shapes: np.ndarray) -> np.ndarray:
    """Distance between the eye centres of iBUG-68 shapes (...,)."""
    left, right = eye_centres(np.asarray(shapes, dtype=np.float64))
    return np.linalg.norm(right - left, axis=-1)


def canonical_pose(shape: np.ndarray) -> np.ndarray:
    """The gauge of the mean-shape frame: centroid at the origin, eyes level, inter-ocular distance 1."""
    shape = np.asarray(shape, dtype=np.float64)
    centred = shape - shape.mean(0)
    left, right = eye_centres(centred)
    axis = right - left
    z = complex(axis[0], axis[1])
    rot = np.conj(z) / abs(z) ** 2  # rotates the eye axis onto +x and scales it to length 1
    zs = (centred[:, 0] + 1j * centred[:, 1]) * rot
    return np.stack([zs.real, zs.imag], axis=-1)


def similarity_align(shapes: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares similarity (scale, rotation, translation) of each shape onto a centred target, by the
    project's one 2-D similarity fit (``stages.geometry.similarity``).

    shapes (F, N, 2), target (N, 2) centred. Returns the aligned shapes (F, N, 2) and the similarity mapping
    aligned -> original as (F, 4) [scale, angle, tx, ty]: original = scale * R(angle) @ aligned + t, with
    R = [[cos, -sin], [sin, cos]] (t is the shape's centroid, the target being centred).
    """
    from stages.geometry.similarity import apply_similarity as apply_transform
    from stages.geometry.similarity import fit_similarity, invert_similarity, similarity_parameters

    shapes = np.asarray(shapes, dtype=np.float64)
    transform = fit_similarity(shapes, np.broadcast_to(np.asarray(target, dtype=np.float64), shapes.shape))
    return apply_transform(transform, shapes), similarity_parameters(invert_similarity(transform))


def apply_similarity(shapes: np.ndarray, similarity: np.ndarray) -> np.ndarray:
    """Map shapes (F, N, 2) from the aligned frame through similarity (F, 4) [scale, angle, tx, ty]."""
    from stages.geometry.similarity import apply_similarity as apply_transform
    from stages.geometry.similarity import similarity_from_parameters

    return apply_transform(similarity_from_parameters(similarity), np.asarray(shapes, dtype=np.float64))


def generalised_procrustes(
    shapes: np.ndarray, tol: float = 1e-10, max_iter: int = 100
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Generalised Procrustes analysis (Cootes et al.): align all shapes to their iteratively refined mean.

    Returns (aligned (F, N, 2), mean shape (N, 2) in the canonical gauge, similarity (F, 4) aligned -> input).
    """
    shapes = np.asarray(shapes, dtype=np.float64)
    mean = canonical_pose(shapes[0])
    for _ in range(max_iter):
        aligned, similarity = similarity_align(shapes, mean)
        new_mean = canonical_pose(aligned.mean(0))
        change = np.sqrt(np.mean((new_mean - mean) ** 2))
        mean = new_mean
        if change < tol:
            break
    aligned, similarity = similarity_align(shapes, mean)
    return aligned, mean, similarity


# ----------------------------------------------------------------------------------------------- PCA


@dataclass
class Pca:
    mean: np.ndarray  # (D,)
    basis: np.ndarray  # (n, D) orthonormal rows
    eigenvalues: np.ndarray  # (n,) variance along each row
    total_variance: float  # of the data, all modes


def fit_pca(
    data: np.ndarray, variance: float | None = None, n_modes: int | None = None, max_modes: int | None = None
) -> Pca:
    """PCA of rows of ``data`` (F, D), keeping ``n_modes`` or the fewest modes explaining ``variance``.

    Uses the F x F Gram matrix when F < D (the texture case: fewer frames than pixels).
    """
    data = np.asarray(data, dtype=np.float64)
    f, d = data.shape
    mean = data.mean(0)
    centred = data - mean
    if f < d:
        gram = centred @ centred.T
        evals, evecs = np.linalg.eigh(gram)
        order = np.argsort(evals)[::-1]
        evals, evecs = np.clip(evals[order], 0, None), evecs[:, order]
        keep_rank = evals > evals[0] * 1e-12 if evals[0] > 0 else np.zeros_like(evals, dtype=bool)
        evals, evecs = evals[keep_rank], evecs[:, keep_rank]
        basis = (evecs.T @ centred) / np.sqrt(evals)[:, None]
    else:
        _, sing, vt = np.linalg.svd(centred, full_matrices=False)
        evals = sing**2
        keep_rank = evals > evals[0] * 1e-12 if evals.size and evals[0] > 0 else np.zeros_like(evals, dtype=bool)
        evals, basis = evals[keep_rank], vt[keep_rank]
    denom = max(f - 1, 1)
    eigenvalues = evals / denom
    total = float(eigenvalues.sum())
    n = choose_modes(eigenvalues, variance, n_modes)
    if max_modes is not None:
        n = min(n, max_modes)
    return Pca(mean, basis[:n], eigenvalues[:n], total)


def choose_modes(eigenvalues: np.ndarray, variance: float | None, n_modes: int | None) -> int:
    """Number of leading modes: ``n_modes`` when given, else the fewest whose variance fraction >= ``variance``."""
    available = len(eigenvalues)
    if n_modes is not None:
        return min(int(n_modes), available)
    if available == 0:
        return 0
    fraction = np.cumsum(eigenvalues) / eigenvalues.sum()
    return int(min(np.searchsorted(fraction, (variance or 1.0) - 1e-12) + 1, available))


def heldout_pca_error(data: np.ndarray, folds: list[np.ndarray], max_modes: int) -> np.ndarray:
    """Relative RMS reconstruction error of held-out rows against the number of modes (0..max_modes).

    For each fold, PCA is fitted on the other rows and the held-out rows are reconstructed with 0, 1, ... modes;
    squared errors are pooled over folds and divided by the held-out rows' squared deviation from the training
    mean (so the error is 1.0 at zero modes).
    """
    data = np.asarray(data, dtype=np.float64)
    residual_sum = np.zeros(max_modes + 1)
    total_sum = 0.0
    for held in folds:
        train = np.ones(len(data), dtype=bool)
        train[held] = False
        pca = fit_pca(data[train], n_modes=max_modes)
        centred = data[held] - pca.mean
        coef = centred @ pca.basis.T
        total = float(np.sum(centred**2))
        # the basis is orthonormal: the residual with m modes is the total minus m squared coefficients
        residual = np.maximum(total - np.concatenate([[0.0], np.cumsum(np.sum(coef**2, 0))]), 0.0)
        residual = np.concatenate([residual, np.full(max_modes + 1 - len(residual), residual[-1])])
        residual_sum += residual
        total_sum += total
    return np.sqrt(residual_sum / max(total_sum, 1e-300))


def temporal_folds(sequence: np.ndarray, k: int) -> list[np.ndarray]:
    """k folds, each holding out one contiguous window of every take (the k-th part of each take's frames)."""
    sequence = np.asarray(sequence)
    folds: list[list[int]] = [[] for _ in range(k)]
    for take in np.unique(sequence):
        frames = np.flatnonzero(sequence == take)
        for i, part in enumerate(np.array_split(frames, k)):
            folds[i].extend(part.tolist())
    return [np.asarray(f, dtype=np.int64) for f in folds if f]


# ----------------------------------------------------------------------------------------------- texture frame


def texture_reference(mean_shape: np.ndarray, width: int, margin: float = 1.0) -> tuple[np.ndarray, tuple[int, int]]:
    """The mean shape drawn in a texture image ``width`` pixels wide: (points (N, 2), size (w, h))."""
    lo, hi = mean_shape.min(0), mean_shape.max(0)
    scale = (width - 1 - 2 * margin) / (hi[0] - lo[0])
    ref = (mean_shape - lo) * scale + margin
    height = int(np.ceil((hi[1] - lo[1]) * scale + 2 * margin)) + 1
    return ref, (int(width), height)


def photometric_normalise(samples: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Zero mean, unit variance grey levels per frame (Cootes' AAM); returns (normalised, offset, scale)."""
    samples = np.asarray(samples, dtype=np.float64)
    offset = samples.mean(-1)
    scale = samples.std(-1)
    scale = np.where(scale < 1e-6, 1.0, scale)
    return (samples - offset[:, None]) / scale[:, None], offset, scale


# ----------------------------------------------------------------------------------------------- model


@dataclass
class AamProjection:
    """A sequence in model coordinates (what ``AamModel.project`` returns)."""

    aligned_shapes: np.ndarray  # (F, 68, 2) in the mean-shape frame
    similarity: np.ndarray  # (F, 4) aligned -> image (landmarks)
    crop_similarity: np.ndarray  # (F, 4) aligned -> crop (crop_landmarks)
    b_s: np.ndarray  # (F, n_s)
    b_g: np.ndarray  # (F, n_g)
    y: np.ndarray  # (F, n_s + n_g) = [r b_s; b_g]
    texture_offset: np.ndarray  # (F,) grey-level mean of the shape-free texture
    texture_scale: np.ndarray  # (F,) grey-level standard deviation
    textures: np.ndarray  # (F, P) photometrically normalised shape-free textures


@dataclass
class AamModel:
    """A fitted appearance model: Eq 1 (shape), Eq 2 (texture), Eq 3 (combined vector y)."""

    mean_shape: np.ndarray  # (68, 2)
    shape_basis: np.ndarray  # (n_s, 136), rows orthonormal, interleaved x, y
    shape_eigenvalues: np.ndarray  # (n_s,)
    texture_mean: np.ndarray  # (P,)
    texture_basis: np.ndarray  # (n_g, P)
    texture_eigenvalues: np.ndarray  # (n_g,)
    shape_weight: float  # r in B_s = r I
    texture_points: np.ndarray  # (68, 2) mean shape in texture pixels
    triangles: np.ndarray  # (T, 3)
    texture_size: tuple[int, int]  # (w, h)

    ARRAYS = (
        "mean_shape",
        "shape_basis",
        "shape_eigenvalues",
        "texture_mean",
        "texture_basis",
        "texture_eigenvalues",
        "texture_points",
        "triangles",
    )

    @property
    def n_shape(self) -> int:
        return len(self.shape_basis)

    @property
    def n_texture(self) -> int:
        return len(self.texture_basis)

    @property
    def warp(self) -> PiecewiseAffineWarp:
        cached = self.__dict__.get("_warp")
        if cached is None:
            cached = PiecewiseAffineWarp(self.texture_points, self.triangles, self.texture_size)
            self.__dict__["_warp"] = cached
        return cached

    @classmethod
    def from_view(cls, view) -> AamModel:
        """The model stored in an ``aam`` artifact (ArtifactView or dict of arrays with ``meta``)."""
        meta = view.meta
        return cls(
            **{
                name: np.asarray(view[name], dtype=np.float64)
                if name != "triangles"
                else np.asarray(view[name], dtype=np.int32)
                for name in cls.ARRAYS
            },
            shape_weight=float(meta["shape_weight"]),
            texture_size=tuple(meta["texture_size"]),
        )

    # --- Eq 1-3 forward
    def shape_params(self, aligned: np.ndarray) -> np.ndarray:
        """b_s = P_s' (x - x0) for aligned shapes (F, 68, 2) (Eq 1 inverted)."""
        flat = np.asarray(aligned, dtype=np.float64).reshape(len(aligned), -1)
        return (flat - self.mean_shape.reshape(-1)) @ self.shape_basis.T

    def texture_params(self, textures: np.ndarray) -> np.ndarray:
        """b_g = P_g' (g - g0) for normalised textures (F, P) (Eq 2 inverted)."""
        return (np.asarray(textures, dtype=np.float64) - self.texture_mean) @ self.texture_basis.T

    def combine(self, b_s: np.ndarray, b_g: np.ndarray) -> np.ndarray:
        """y = [B_s b_s; b_g] with B_s = r I (Eq 3)."""
        return np.concatenate([self.shape_weight * b_s, b_g], axis=-1)

    def split(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Inverse of Eq 3: (b_s, b_g) from y (..., K)."""
        y = np.asarray(y, dtype=np.float64)
        return y[..., : self.n_shape] / self.shape_weight, y[..., self.n_shape :]

    def project(self, landmarks: np.ndarray, crops: np.ndarray, crop_landmarks: np.ndarray) -> AamProjection:
        """Project a (new) sequence into this model: align its shapes to the mean, sample its shape-free texture."""
        landmarks = np.asarray(landmarks, dtype=np.float64)
        aligned, similarity = similarity_align(landmarks, self.mean_shape - self.mean_shape.mean(0))
        _, crop_similarity = similarity_align(
            np.asarray(crop_landmarks, dtype=np.float64), self.mean_shape - self.mean_shape.mean(0)
        )
        raw = self.warp.warp(crops, crop_landmarks)
        textures, offset, scale = photometric_normalise(raw)
        b_s = self.shape_params(aligned)
        b_g = self.texture_params(textures)
        return AamProjection(
            aligned, similarity, crop_similarity, b_s, b_g, self.combine(b_s, b_g), offset, scale, textures
        )

    # --- Eq 1-3 inverse
    def reconstruct_shapes(self, b_s: np.ndarray) -> np.ndarray:
        """x = x0 + P_s b_s as (..., 68, 2) in the mean-shape frame (Eq 1)."""
        flat = self.mean_shape.reshape(-1) + np.asarray(b_s) @ self.shape_basis
        return flat.reshape(flat.shape[:-1] + self.mean_shape.shape)

    def reconstruct_textures(self, b_g: np.ndarray) -> np.ndarray:
        """g = g0 + P_g b_g, photometrically normalised (..., P) (Eq 2)."""
        return self.texture_mean + np.asarray(b_g) @ self.texture_basis

    def reconstruct(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Shapes (..., 68, 2) in the mean-shape frame and normalised textures (..., P) from y (Eq 3-1 inverted)."""
        b_s, b_g = self.split(y)
        return self.reconstruct_shapes(b_s), self.reconstruct_textures(b_g)

    def texture_images(
        self, textures: np.ndarray, offset: np.ndarray | float = 0.0, scale: np.ndarray | float = 1.0
    ) -> np.ndarray:
        """Normalised textures (F, P) back to grey-level images (F, h, w) of the texture frame (0 outside)."""
        offset = np.asarray(offset, dtype=np.float64)
        scale = np.asarray(scale, dtype=np.float64)
        grey = np.asarray(textures) * scale[..., None] + offset[..., None]
        return self.warp.to_image(grey.astype(np.float32))


def project(model: AamModel, landmarks: np.ndarray, crops: np.ndarray, crop_landmarks: np.ndarray) -> AamProjection:
    """Project a new sequence into a fitted model (never refits). See ``AamModel.project``."""
    return model.project(landmarks, crops, crop_landmarks)


def reconstruct(model: AamModel, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shapes (mean-shape frame) and normalised textures from configuration vectors y. See ``AamModel.reconstruct``."""
    return model.reconstruct(y)


def balanced_shape_weight(shape_eigenvalues: np.ndarray, texture_eigenvalues: np.ndarray) -> float:
    """Cootes' r: r^2 = sum lambda_g / sum lambda_s, so r b_s and b_g carry equal total variance (Eq 3)."""
    return float(np.sqrt(np.sum(texture_eigenvalues) / max(float(np.sum(shape_eigenvalues)), 1e-300)))


def fit_aam(
    landmarks: np.ndarray,
    crops: np.ndarray,
    crop_landmarks: np.ndarray,
    *,
    shape_variance: float = 0.98,
    n_shape: int | None = None,
    texture_variance: float = 0.95,
    n_texture: int | None = None,
    texture_width: int = 64,
    shape_balance: float = 1.0,
) -> tuple[AamModel, AamProjection]:
    """Fit Eq 1-3 on training frames; returns the model and the training frames projected into it.

    B_s = r I with r = shape_balance * sqrt(sum lambda_g / sum lambda_s): ``shape_balance`` 1 is Cootes' balance
    (shape and texture carry equal total variance in y); below 1 the texture dominates y.
    """
    aligned, mean_shape, similarity = generalised_procrustes(landmarks)
    shape_pca = fit_pca(aligned.reshape(len(aligned), -1), shape_variance, n_shape)
    mean_shape = shape_pca.mean.reshape(mean_shape.shape)
    points, size = texture_reference(mean_shape, texture_width)
    triangles = delaunay_triangles(points)
    warp = PiecewiseAffineWarp(points, triangles, size)
    raw = warp.warp(crops, crop_landmarks)
    textures, _, _ = photometric_normalise(raw)
    texture_pca = fit_pca(textures, texture_variance, n_texture)
    shape_weight = float(shape_balance) * balanced_shape_weight(shape_pca.eigenvalues, texture_pca.eigenvalues)
    model = AamModel(
        mean_shape,
        shape_pca.basis,
        shape_pca.eigenvalues,
        texture_pca.mean,
        texture_pca.basis,
        texture_pca.eigenvalues,
        shape_weight,
        points,
        triangles,
        size,
    )
    model.__dict__["_warp"] = warp
    return model, model.project(landmarks, crops, crop_landmarks)


# ----------------------------------------------------------------------------------------------- input checks


def check_landmarks(landmarks: np.ndarray, sequence: np.ndarray, labels: list[str], field: str) -> None:
    """UserError when NaN/Inf landmarks would reach the model (tracking should interpolate gaps)."""
    bad = ~np.isfinite(np.asarray(landmarks)).all(axis=(1, 2))
    if bad.any():
        frames = np.flatnonzero(bad)
        takes = sorted({labels[int(s)] if int(s) < len(labels) else str(int(s)) for s in np.asarray(sequence)[frames]})
        raise UserError(
            f"{bad.sum()} frame(s) have NaN or missing landmarks (takes {takes}, first frames "
            f"{frames[:5].tolist()}); re-run tracking with gap interpolation or drop those frames",
            field=field,
        )


def check_landmark_scheme(landmarks: np.ndarray, meta: dict, field: str, expected: str | None = None) -> str:
    """The landmark scheme name of a tracking artifact; UserError if it is not 68-point or differs from expected."""
    scheme = str(meta.get("landmark_scheme", "ibug68"))
    n_points = np.asarray(landmarks).shape[1] if np.ndim(landmarks) == 3 else None
    if n_points != 68:
        raise UserError(
            f"landmarks have {n_points} points per frame; the face model needs the 68-point iBUG scheme", field=field
        )
    if expected is not None and scheme != expected:
        raise UserError(f"landmark scheme '{scheme}' differs from the training data's '{expected}'", field=field)
    return scheme


# ----------------------------------------------------------------------------------------------- figures


def figure_shape_modes(view, inputs=None):
    """Mean shape with its triangulation and the first shape modes at +-2 standard deviations."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mean = np.asarray(view["mean_shape"])
    basis = np.asarray(view["shape_basis"])
    evals = np.asarray(view["shape_eigenvalues"])
    tri = np.asarray(view["triangles"])
    n = min(3, len(basis))
    fig, axes = plt.subplots(1, n + 1, figsize=(3 * (n + 1), 3.2))
    axes = np.atleast_1d(axes)
    axes[0].triplot(mean[:, 0], mean[:, 1], tri, lw=0.5, color="0.5")
    axes[0].plot(mean[:, 0], mean[:, 1], ".k", ms=3)
    axes[0].set_title("mean shape")
    for i in range(n):
        for sign, colour in ((-2, "tab:blue"), (2, "tab:red")):
            shape = mean + (sign * np.sqrt(evals[i]) * basis[i]).reshape(-1, 2)
            axes[i + 1].plot(shape[:, 0], shape[:, 1], ".", color=colour, ms=3, label=f"{sign:+d} sd")
        axes[i + 1].set_title(f"mode {i + 1} ({100 * evals[i] / evals.sum():.0f}% of kept)")
    for ax in axes:
        ax.set_aspect("equal")
        ax.invert_yaxis()
        ax.axis("off")
    axes[-1].legend(loc="lower right", fontsize=7)
    fig.tight_layout()
    return fig


def figure_heldout_error(view, inputs=None):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.2))
    for name, kept, label in (
        ("heldout_shape_error", "n_shape", "shape"),
        ("heldout_texture_error", "n_texture", "texture"),
    ):
        err = np.asarray(view[name])
        (line,) = ax.plot(np.arange(len(err)), err, marker=".", label=label)
        k = view.meta.get(kept)
        if k is not None and k < len(err):
            ax.plot([k], [err[k]], "o", mfc="none", color=line.get_color(), ms=9)
    ax.set_xlabel("modes")
    ax.set_ylabel("held-out relative RMS error")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


# ----------------------------------------------------------------------------------------------- stage

AAM_OUTPUTS = {
    "mean_shape": Output.array("f", shape=(68, 2), doc="x0 in the mean-shape frame (IOD 1, eyes level)"),
    "shape_basis": Output.array("f", shape=("n_shape", 136), doc="P_s rows, interleaved x, y"),
    "shape_eigenvalues": Output.array("f", shape=("n_shape",)),
    "b_s": Output.array("f", shape=("frames", "n_shape")),
    "aligned_shapes": Output.array("f", shape=("frames", 68, 2), doc="Procrustes-aligned, mean-shape frame"),
    "similarity": Output.array("f", shape=("frames", 4), doc="[scale, angle, tx, ty] aligned -> image pixels"),
    "crop_similarity": Output.array("f", shape=("frames", 4), doc="[scale, angle, tx, ty] aligned -> crop pixels"),
    "texture_mean": Output.array("f", shape=("pixels",), doc="g0, photometrically normalised"),
    "texture_basis": Output.array("f", shape=("n_texture", "pixels")),
    "texture_eigenvalues": Output.array("f", shape=("n_texture",)),
    "texture_points": Output.array("f", shape=(68, 2), doc="mean shape in texture-image pixels"),
    "triangles": Output.array("i", shape=(None, 3), doc="Delaunay triangles of the mean shape"),
    "texture_mask": Output.array(
        "b", ndim=2, doc="texture-image pixels inside the face hull (sample order: row-major over True pixels)"
    ),
    "texture_offset": Output.array("f", shape=("frames",), doc="grey-level mean before normalisation"),
    "texture_scale": Output.array("f", shape=("frames",), doc="grey-level std before normalisation"),
    "b_g": Output.array("f", shape=("frames", "n_texture")),
    "y": Output.array("f", shape=("frames", None), doc="[r b_s; b_g] (Eq 3)"),
    "sequence": Output.array("i", shape=("frames",), doc="copied from tracking: index into meta labels"),
    "heldout_shape_error": Output.array("f", ndim=1, doc="relative RMS error of held-out shapes vs modes 0..n"),
    "heldout_texture_error": Output.array("f", ndim=1, doc="relative RMS error of held-out textures vs modes"),
}


class AamParams(Stage.Params):
    """How the appearance model is fitted (shared with stages.eval.face's refits)."""

    shape_variance: float = Field(0.98, gt=0, le=1)
    n_shape: int | None = Field(None, ge=1)
    texture_variance: float = Field(0.95, gt=0, le=1)
    n_texture: int | None = Field(None, ge=1)
    texture_width: int = Field(64, ge=16, le=1024)
    shape_balance: float = Field(1.0, gt=0)
    heldout_folds: int = Field(5, ge=2)


def fit_options(params: AamParams) -> dict:
    """Keyword arguments of ``fit_aam`` from the stage params."""
    return {
        "shape_variance": params.shape_variance,
        "n_shape": params.n_shape,
        "texture_variance": params.texture_variance,
        "n_texture": params.n_texture,
        "texture_width": params.texture_width,
        "shape_balance": params.shape_balance,
    }


def check_training_tracks(view) -> tuple[np.ndarray, list[str], str]:
    """(sequence, labels, landmark scheme) of a tracking artifact fit for the appearance model, else UserError."""
    landmarks = view["landmarks"]
    labels = [str(x) for x in view.meta.get("labels", [])]
    sequence = np.asarray(view["sequence"], dtype=np.int32)
    scheme = check_landmark_scheme(landmarks, view.meta, "inputs.tracks.landmarks")
    check_landmarks(landmarks, sequence, labels, "inputs.tracks.landmarks")
    check_landmarks(view["crop_landmarks"], sequence, labels, "inputs.tracks.crop_landmarks")
    if len(landmarks) < 3:
        raise UserError(
            f"only {len(landmarks)} training frames; the appearance model needs at least 3", field="inputs.tracks"
        )
    return sequence, labels, scheme


def heldout_errors(model: AamModel, proj: AamProjection, sequence: np.ndarray, k: int) -> tuple[np.ndarray, ...]:
    """Held-out relative RMS error of shapes and textures against the number of modes (temporal k-fold)."""
    folds = temporal_folds(sequence, min(k, int(np.bincount(sequence).max())))
    folds = [f for f in folds if 0 < len(f) < len(sequence)]
    shape_err = heldout_pca_error(proj.aligned_shapes.reshape(len(sequence), -1), folds, model.n_shape + 5)
    texture_err = heldout_pca_error(proj.textures, folds, model.n_texture + 5)
    return shape_err, texture_err


class AamPca(Stage):
    """Active-appearance-style model of the training takes (Eq 1-3): shape and texture PCA, combined y."""

    cheap = True

    Params = AamParams
    inputs = {
        "tracks": Input.artifact(
            "landmarks", "crops", "crop_landmarks", "sequence", doc="tracking artifact of the training takes"
        )
    }
    outputs = AAM_OUTPUTS
    figures = {"shape_modes": figure_shape_modes, "heldout_error": figure_heldout_error}

    def run(self, params, inputs):
        view = inputs["tracks"]
        sequence, labels, scheme = check_training_tracks(view)
        model, proj = fit_aam(view["landmarks"], view["crops"], view["crop_landmarks"], **fit_options(params))
        shape_err, texture_err = heldout_errors(model, proj, sequence, params.heldout_folds)
        return pack_aam(params, view.meta, labels, scheme, sequence, model, proj, shape_err, texture_err)


def pack_aam(params, tracks_meta, labels, scheme, sequence, model, proj, shape_err, texture_err) -> Result:
    """The AamPca artifact: the model, the training frames in it, held-out errors; meta keeps the params."""
    arrays = {name: getattr(model, name) for name in AamModel.ARRAYS}
    arrays["triangles"] = model.triangles.astype(np.int32)
    arrays.update(
        texture_mask=model.warp.pixels.mask,
        b_s=proj.b_s,
        b_g=proj.b_g,
        y=proj.y,
        aligned_shapes=proj.aligned_shapes,
        similarity=proj.similarity,
        crop_similarity=proj.crop_similarity,
        texture_offset=proj.texture_offset,
        texture_scale=proj.texture_scale,
        sequence=sequence,
        heldout_shape_error=shape_err,
        heldout_texture_error=texture_err,
    )
    meta = {
        "labels": labels,
        "fields": dict(tracks_meta.get("fields") or {}),
        "fps": tracks_meta.get("fps"),
        "landmark_scheme": scheme,
        "shape_weight": model.shape_weight,
        "shape_balance": params.shape_balance,
        "texture_width": params.texture_width,
        "texture_size": list(model.texture_size),
        "n_shape": model.n_shape,
        "n_texture": model.n_texture,
        "shape_frame": "mean-shape frame: centroid 0, eyes level, inter-ocular distance 1, y down",
        "params": params.model_dump(),
    }
    shape_resid = proj.aligned_shapes - model.reconstruct_shapes(proj.b_s)
    metrics = {
        "n_shape": model.n_shape,
        "n_texture": model.n_texture,
        "shape_weight": model.shape_weight,
        "shape_variance_kept": float(model.shape_eigenvalues.sum() / max(shape_pca_total(proj.aligned_shapes), 1e-300)),
        "train_shape_rms_iod": float(np.sqrt(np.mean(np.sum(shape_resid**2, -1)))),
        "heldout_shape_error": float(shape_err[min(model.n_shape, len(shape_err) - 1)]),
        "heldout_texture_error": float(texture_err[min(model.n_texture, len(texture_err) - 1)]),
    }
    return Result(arrays, meta=meta, metrics=metrics)


def shape_pca_total(aligned: np.ndarray) -> float:
    flat = aligned.reshape(len(aligned), -1)
    return float(np.sum((flat - flat.mean(0)) ** 2) / max(len(flat) - 1, 1))


__all__ = [
    "AamModel",
    "AamParams",
    "AamPca",
    "AamProjection",
    "fit_options",
    "fit_aam",
    "project",
    "reconstruct",
    "generalised_procrustes",
    "similarity_align",
    "apply_similarity",
    "fit_pca",
    "canonical_pose",
    "interocular_distance",
    "temporal_folds",
    "heldout_pca_error",
    "check_landmarks",
    "check_landmark_scheme",
]
