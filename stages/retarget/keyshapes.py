"""Keyshape selection (paper Sec 4.1) and the non-negative keyshape decomposition of edited sequences (Eq 8).

Per training expression s, PCA of that expression's aligned landmark shapes; from the first (largest-variance)
axis on, the frames with the maximum and the minimum projection are keyshapes B^(s), k_s of them from the first
k_s/2 axes; a candidate within ``dedupe_threshold`` of an already chosen keyshape is dropped (being chosen
later, it comes from the lower-variance axis). Every frame x^(s)(t) of the sequence edited towards expression s
is then written as x^(s)(t) ~ sum_i w_i(t) B_i^(s), w_i >= 0, solved for all frames at once (stages.geometry.nnls).

Distances are measured in the aam mean-shape frame relative to the inter-ocular distance (outer eye corners,
iBUG points 36 and 45, the 300-W convention) of the mean training shape, so thresholds and residuals do not
depend on the aam's choice of units.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from msflow import Input, Output, Result, Stage, UserError
from stages.geometry.nnls import batched_nnls

#: iBUG-68 polylines (point ranges; closed ones repeat their first point) for drawing shapes
IBUG68_CONTOURS: tuple[tuple[int, ...], ...] = (
    tuple(range(0, 17)),
    tuple(range(17, 22)),
    tuple(range(22, 27)),
    tuple(range(27, 31)),
    tuple(range(31, 36)),
    tuple(range(36, 42)) + (36,),
    tuple(range(42, 48)) + (42,),
    tuple(range(48, 60)) + (48,),
    tuple(range(60, 68)) + (60,),
)
OUTER_EYE_CORNERS = (36, 45)
INNER_LIP_PAIRS = ((61, 67), (62, 66), (63, 65))


def inter_ocular_distance(shapes: np.ndarray) -> np.ndarray:
    """Distance between the outer eye corners (iBUG 36, 45) of each (..., 68, 2) shape."""
    shapes = np.asarray(shapes, np.float64)
    return np.linalg.norm(shapes[..., OUTER_EYE_CORNERS[1], :] - shapes[..., OUTER_EYE_CORNERS[0], :], axis=-1)


def mouth_opening(shapes: np.ndarray) -> np.ndarray:
    """Mean gap between the inner lips (iBUG 61-67, 62-66, 63-65) of each (..., 68, 2) shape."""
    shapes = np.asarray(shapes, np.float64)
    upper = shapes[..., [a for a, _ in INNER_LIP_PAIRS], :]
    lower = shapes[..., [b for _, b in INNER_LIP_PAIRS], :]
    return np.linalg.norm(lower - upper, axis=-1).mean(axis=-1)


def mean_squared_landmark_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Mean over landmarks of the squared point distance between shapes a (..., 68, 2) and b (..., 68, 2)."""
    return ((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2).sum(axis=-1).mean(axis=-1)


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
    n = shapes.shape[0]
    if n == 0:
        raise ValueError("select_keyshapes: no shapes")
    flat = shapes.reshape(n, -1)
    centred = flat - flat.mean(axis=0)
    _, singular, axes_t = np.linalg.svd(centred, full_matrices=False)
    variance = singular**2 / max(n - 1, 1)
    rank = int((singular > singular.max(initial=0.0) * 1e-9).sum()) if n > 1 else 0
    projections = centred @ axes_t[: max(rank, 1)].T

    chosen: list[int] = []
    axes: list[int] = []
    extremes: list[int] = []
    dropped: list[dict] = []
    if rank == 0:  # every frame identical: the one shape is the only keyshape
        return KeyshapeSelection(np.array([0]), np.array([0]), np.array([1]), variance, dropped)
    threshold = dedupe_threshold * scale**2
    candidates_tried = 0
    for axis in range(rank):
        for sign in (1, -1):
            if not refill and candidates_tried >= k:
                break
            if len(chosen) >= k:
                break
            candidates_tried += 1
            frame = int(np.argmax(sign * projections[:, axis]))
            if chosen:
                distance = mean_squared_landmark_distance(shapes[chosen], shapes[frame])
                nearest = int(np.argmin(distance))
                # the same frame again (an extreme of several axes) is always a duplicate
                if distance[nearest] < threshold or frame in chosen:
                    dropped.append(
                        {
                            "frame": frame,
                            "axis": axis,
                            "extreme": sign,
                            "duplicate_of": chosen[nearest],
                            "distance": float(distance[nearest] / scale**2),
                        }
                    )
                    continue
            chosen.append(frame)
            axes.append(axis)
            extremes.append(sign)
    return KeyshapeSelection(
        np.array(chosen, dtype=np.int64),
        np.array(axes, dtype=np.int64),
        np.array(extremes, dtype=np.int64),
        variance,
        dropped,
    )


def decompose_into_keyshapes(shapes: np.ndarray, keyshapes: np.ndarray, **nnls_options):
    """Non-negative weights w (n, k) with shapes ~ sum_i w_i keyshapes_i for every frame (paper Eq 8).

    shapes (n, 68, 2), keyshapes (k, 68, 2); returns (weights, reconstruction (n, 68, 2), NnlsResult).
    """
    shapes = np.asarray(shapes, np.float64)
    keyshapes = np.asarray(keyshapes, np.float64)
    n = shapes.shape[0]
    dictionary = keyshapes.reshape(keyshapes.shape[0], -1).T
    result = batched_nnls(dictionary, shapes.reshape(n, -1), **nnls_options)
    reconstruction = (result.weights @ dictionary.T).reshape(shapes.shape)
    return result.weights, reconstruction, result


def relative_rms_error(shapes: np.ndarray, reference: np.ndarray, scale: float) -> np.ndarray:
    """RMS over landmarks of the point error between two (..., 68, 2) shape sets, divided by ``scale``."""
    return np.sqrt(mean_squared_landmark_distance(shapes, reference)) / scale


def rest_frames(shapes: np.ndarray, quantile: float = 0.1) -> np.ndarray:
    """Indices of a closed-mouth rest pose: the frames whose inner-lip gap is in the lowest ``quantile``.

    The plain mean of a talking face has its mouth half open; retargeting measures deformations from a rest
    pose that matches a character's closed-mouth neutral.
    """
    gap = mouth_opening(shapes)
    count = max(1, int(np.ceil(quantile * len(gap))))
    return np.sort(np.argsort(gap, kind="stable")[:count])


def rest_shape(shapes: np.ndarray, quantile: float = 0.1) -> np.ndarray:
    """The mean shape of ``rest_frames``."""
    shapes = np.asarray(shapes, np.float64)
    return shapes[rest_frames(shapes, quantile)].mean(axis=0)


# ---------------------------------------------------------------------------------------------------- figures


def plot_shape(ax, shape: np.ndarray, **style):
    """Draw one iBUG-68 shape as polylines on a matplotlib axis (image convention: y down)."""
    for contour in IBUG68_CONTOURS:
        pts = shape[list(contour)]
        ax.plot(pts[:, 0], pts[:, 1], **style)


def plot_keyshape_grid(layers, expression, labels, title, caption):
    """Grid of shapes, one row per expression; ``layers`` = [(shapes (k, 68, 2), line style), ...] drawn over each
    other, ``caption(index, column)`` titles each cell. Shapes are in the aam mean-shape frame (y down)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    expression = np.asarray(expression)
    cols = max(int(np.bincount(expression, minlength=len(labels)).max(initial=1)), 1)
    fig, axes = plt.subplots(len(labels), cols, figsize=(1.2 * cols, 1.4 * len(labels)), squeeze=False)
    first = layers[0][0]
    lo, hi = first.reshape(-1, 2).min(0), first.reshape(-1, 2).max(0)
    for s, label in enumerate(labels):
        mine = np.flatnonzero(expression == s)
        for c in range(cols):
            ax = axes[s, c]
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_aspect("equal")
            if c >= len(mine):
                ax.axis("off")
                continue
            for shapes, style in layers:
                plot_shape(ax, shapes[mine[c]], **style)
            ax.set_xlim(lo[0], hi[0])
            ax.set_ylim(hi[1], lo[1])
            ax.set_title(caption(mine[c], c), fontsize=6)
        axes[s, 0].set_ylabel(label)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def plot_keyshapes(keyshapes, expression, labels, frames):
    """Grid of keyshapes: one row per expression, with each keyshape's source frame."""
    return plot_keyshape_grid(
        [(keyshapes, {"color": "k", "lw": 0.8})],
        expression,
        labels,
        "Keyshapes per expression (PCA extremes, Sec 4.1)",
        lambda i, c: f"{c} (f{int(frames[i])})",
    )


def plot_residual(residual, targets, fps):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3))
    time = np.arange(residual.shape[1]) / fps if fps else np.arange(residual.shape[1])
    for t, name in enumerate(targets):
        ax.plot(time, 100 * residual[t], label=name)
    ax.axhline(3.0, color="r", ls="--", lw=0.8, label="3% goal")
    ax.set_xlabel("time (s)" if fps else "frame")
    ax.set_ylabel("RMS residual (% inter-ocular)")
    ax.set_title("Keyshape decomposition residual (Eq 8)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def plot_weights(weights, targets, keyshape_ids):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(targets), 1, figsize=(8, 2.2 * len(targets)), squeeze=False)
    for t, name in enumerate(targets):
        mine = np.flatnonzero(np.any(weights[t] != 0, axis=0))
        ax = axes[t, 0]
        ax.imshow(weights[t][:, mine].T, aspect="auto", interpolation="nearest", cmap="magma")
        ax.set_yticks(range(len(mine)))
        ax.set_yticklabels([keyshape_ids[i] for i in mine], fontsize=5)
        ax.set_title(f"NNLS keyshape weights, target '{name}'", fontsize=8)
    axes[-1, 0].set_xlabel("frame")
    fig.tight_layout()
    return fig


def figure_keyshapes(view, inputs):
    """The keyshapes of every expression as landmark drawings."""
    return plot_keyshapes(view["keyshapes"], view["keyshape_expression"], view.meta["labels"], view["keyshape_frame"])


def figure_residual(view, inputs):
    """Per-frame decomposition residual against the 3% goal."""
    return plot_residual(view["residual"], view.meta["targets"], view.meta.get("fps"))


def figure_weights(view, inputs):
    """NNLS weights over time per target."""
    return plot_weights(view["weights"], view.meta["targets"], view.meta["keyshape_ids"])


# ----------------------------------------------------------------------------------------------------- stage

KEYSHAPES_OUTPUTS = {
    "keyshapes": Output.array(
        "f",
        shape=("total_k", 68, 2),
        dtype="float32",
        doc="keyshape landmark shapes in the aam mean-shape frame, grouped by expression",
    ),
    "keyshape_expression": Output.array(
        "i", shape=("total_k",), dtype="int32", doc="index into meta['labels'] of each keyshape's expression"
    ),
    "keyshape_index": Output.array(
        "i",
        shape=("total_k",),
        dtype="int32",
        doc="keyshape id within its expression (0..k_s-1), the id keymorph files use",
    ),
    "keyshape_frame": Output.array(
        "i", shape=("total_k",), dtype="int32", doc="source frame in the aam/tracking frame axis"
    ),
    "keyshape_axis": Output.array(
        "i",
        shape=("total_k",),
        dtype="int32",
        doc="PCA axis (0 = largest variance) of which the keyshape is an extreme",
    ),
    "keyshape_extreme": Output.array("i", shape=("total_k",), dtype="int8", doc="+1 maximum, -1 minimum projection"),
    "weights": Output.array(
        "f",
        shape=("targets", "frames", "total_k"),
        dtype="float32",
        doc="non-negative weights per edited frame (zero outside the target's own keyshapes)",
    ),
    "reconstruction": Output.array(
        "f",
        shape=("targets", "frames", 68, 2),
        dtype="float32",
        doc="sum_i w_i B_i: the edited shapes as the keyshapes represent them",
    ),
    "residual": Output.array(
        "f",
        shape=("targets", "frames"),
        dtype="float32",
        doc="per-frame RMS landmark error of the decomposition / inter-ocular distance",
    ),
    "rest_shape": Output.array(
        "f",
        shape=(68, 2),
        dtype="float32",
        doc="closed-mouth rest pose of meta['rest_expression'] (keymorph fits measure deformation from it)",
    ),
    "rest_frames": Output.array(
        "i", shape=("rest",), dtype="int32", doc="frames (aam/tracking axis) averaged into rest_shape"
    ),
    "expression_mean": Output.array(
        "f", shape=("labels", 68, 2), dtype="float32", doc="mean training shape per expression"
    ),
}


class Keyshapes(Stage):
    """Keyshapes per training expression (PCA extremes, Sec 4.1) and NNLS weights of the edited sequences (Eq 8).

    Inputs: ``aam`` (aligned_shapes, sequence, meta labels) gives the training shapes of each expression;
    ``edit`` (shapes (targets, frames, 68, 2), meta targets) the sequences edited towards each expression.
    Each edited target is decomposed into the keyshapes of the training expression of the same name.
    """

    class Params(Stage.Params):
        #: keyshapes per expression (paper: about 20); a mapping gives each expression its own count
        k: int | dict[str, int] = 20
        #: drop a candidate whose mean squared landmark distance to a chosen keyshape, in units of the squared
        #: inter-ocular distance, is below this (1e-4: 1% of the inter-ocular distance RMS)
        dedupe_threshold: float = 1e-4
        #: keep searching further PCA axes until k keyshapes are found (the paper stops at k/2 axes)
        refill: bool = False
        #: NNLS solver: exact vectorised active set, or FISTA with a KKT stopping rule
        solver: Literal["active_set", "fista"] = "active_set"
        #: soft sum-to-one prior on the weights (0 = off, the paper's plain NNLS)
        sum_to_one: float = 0.0
        #: temporal smoothing of the weights across frames (0 = off)
        smoothing: float = 0.0
        #: expression whose closed-mouth frames define the rest pose (falls back to all frames if absent)
        rest_expression: str = "neutral"

    inputs = {
        "aam": Input.artifact("aligned_shapes", "sequence", doc="aam artifact of the training takes"),
        "edit": Input.artifact("shapes", doc="edit artifact: shapes (targets, frames, 68, 2), meta targets"),
    }
    outputs = KEYSHAPES_OUTPUTS

    def run(self, params, inputs):
        aam, edit = inputs["aam"], inputs["edit"]
        labels = [str(x) for x in aam.meta.get("labels", [])]
        aligned = np.asarray(aam["aligned_shapes"], np.float64)
        sequence = np.asarray(aam["sequence"]).astype(np.int64)
        if aligned.ndim != 3 or aligned.shape[1:] != (68, 2):
            raise UserError(f"aligned_shapes has shape {aligned.shape}, expected (frames, 68, 2)", field="inputs.aam")
        if not labels:
            raise UserError("the aam artifact has no meta['labels'] (expression names)", field="inputs.aam")
        usable = np.isfinite(aligned).all(axis=(1, 2))
        if "valid" in aam:
            usable &= np.asarray(aam["valid"]).astype(bool)
        counts = self._counts(params.k, labels)
        if params.dedupe_threshold < 0:
            raise UserError("dedupe_threshold must be >= 0", field="params.dedupe_threshold")
        scale = float(inter_ocular_distance(aligned[usable].mean(axis=0)))
        if not scale > 0:
            raise UserError("the mean training shape has zero inter-ocular distance", field="inputs.aam")

        keyshape_frames, keyshape_expr, keyshape_axis, keyshape_ext, keyshape_idx = [], [], [], [], []
        dropped, variance_covered, expression_means = {}, {}, []
        for s, label in enumerate(labels):
            frames = np.flatnonzero((sequence == s) & usable)
            if frames.size == 0:
                raise UserError(f"expression '{label}' has no usable training frames", field="inputs.aam")
            expression_means.append(aligned[frames].mean(axis=0))
            selection = select_keyshapes(
                aligned[frames],
                counts[label],
                dedupe_threshold=params.dedupe_threshold,
                scale=scale,
                refill=params.refill,
            )
            keyshape_frames += frames[selection.frames].tolist()
            keyshape_expr += [s] * len(selection.frames)
            keyshape_idx += list(range(len(selection.frames)))
            keyshape_axis += selection.axes.tolist()
            keyshape_ext += selection.extremes.tolist()
            dropped[label] = [
                dict(d, frame=int(frames[d["frame"]]), duplicate_of=int(frames[d["duplicate_of"]]))
                for d in selection.dropped
            ]
            used_axes = int(selection.axes.max()) + 1
            total = selection.explained_variance.sum()
            variance_covered[label] = float(selection.explained_variance[:used_axes].sum() / total) if total else 1.0
        keyshape_frames = np.asarray(keyshape_frames, dtype=np.int64)
        keyshape_expr = np.asarray(keyshape_expr, dtype=np.int64)
        keyshapes = aligned[keyshape_frames]

        targets, edited = self._edited(edit, labels)
        n_frames = edited.shape[1]
        weights = np.zeros((len(targets), n_frames, len(keyshapes)))
        reconstruction = np.zeros_like(edited)
        kkt = 0.0
        for t, name in enumerate(targets):
            mine = np.flatnonzero(keyshape_expr == labels.index(name))
            w, recon, result = decompose_into_keyshapes(
                edited[t],
                keyshapes[mine],
                method=params.solver,
                sum_to_one=params.sum_to_one,
                smoothing=params.smoothing,
            )
            weights[t][:, mine] = w
            reconstruction[t] = recon
            kkt = max(kkt, float(result.kkt.max(initial=0.0)) if params.smoothing == 0 else 0.0)
        residual = relative_rms_error(reconstruction, edited, scale)

        train_residual = []
        for s, label in enumerate(labels):  # how well each expression's own training frames are represented
            frames = np.flatnonzero((sequence == s) & usable)
            mine = np.flatnonzero(keyshape_expr == s)
            _, recon, _ = decompose_into_keyshapes(aligned[frames], keyshapes[mine])
            train_residual.append(relative_rms_error(recon, aligned[frames], scale))
        train_residual = np.concatenate(train_residual)

        rest_label = params.rest_expression if params.rest_expression in labels else None
        candidates = np.flatnonzero(usable & ((sequence == labels.index(rest_label)) if rest_label else True))
        rest_idx = candidates[rest_frames(aligned[candidates])]
        rest = aligned[rest_idx].mean(axis=0)

        metrics = {
            "residual_rms_iod": float(np.sqrt(np.mean(residual**2))) if residual.size else 0.0,
            "residual_max_iod": float(residual.max(initial=0.0)),
            "train_residual_rms_iod": float(np.sqrt(np.mean(train_residual**2))),
            "keyshapes": int(len(keyshapes)),
            "duplicates_dropped": int(sum(len(v) for v in dropped.values())),
            "kkt_max": kkt,
        }
        for t, name in enumerate(targets):
            metrics[f"residual_rms_iod_{name}"] = float(np.sqrt(np.mean(residual[t] ** 2)))
        meta = {
            "labels": labels,
            "targets": targets,
            "target_expression": [labels.index(name) for name in targets],
            "keyshape_counts": [int((keyshape_expr == s).sum()) for s in range(len(labels))],
            "keyshape_ids": [f"{labels[e]}/{i}" for e, i in zip(keyshape_expr, keyshape_idx)],
            "inter_ocular_distance": scale,
            "dropped": dropped,
            "variance_covered": variance_covered,
            "rest_expression": rest_label,
            "fps": edit.meta.get("fps", aam.meta.get("fps")),
        }
        return Result(
            {
                "keyshapes": keyshapes.astype(np.float32),
                "keyshape_expression": keyshape_expr.astype(np.int32),
                "keyshape_index": np.asarray(keyshape_idx, dtype=np.int32),
                "keyshape_frame": keyshape_frames.astype(np.int32),
                "keyshape_axis": np.asarray(keyshape_axis, dtype=np.int32),
                "keyshape_extreme": np.asarray(keyshape_ext, dtype=np.int8),
                "weights": weights.astype(np.float32),
                "reconstruction": reconstruction.astype(np.float32),
                "residual": residual.astype(np.float32),
                "rest_shape": rest.astype(np.float32),
                "rest_frames": rest_idx.astype(np.int32),
                "expression_mean": np.asarray(expression_means, dtype=np.float32),
            },
            meta=meta,
            metrics=metrics,
        )

    @staticmethod
    def _counts(k, labels: list[str]) -> dict[str, int]:
        if isinstance(k, int):
            counts = {label: k for label in labels}
        else:
            unknown = sorted(set(k) - set(labels))
            if unknown:
                raise UserError(
                    f"k names unknown expressions {unknown}; the training expressions are {labels}", field="params.k"
                )
            missing = [label for label in labels if label not in k]
            if missing:
                raise UserError(
                    f"k gives no count for {missing}; give every expression of {labels} a count or use one integer",
                    field="params.k",
                )
            counts = {label: int(k[label]) for label in labels}
        bad = {label: c for label, c in counts.items() if c < 1}
        if bad:
            raise UserError(f"k must be at least 1 for every expression, got {bad}", field="params.k")
        return counts

    @staticmethod
    def _edited(edit, labels: list[str]) -> tuple[list[str], np.ndarray]:
        shapes = np.asarray(edit["shapes"], np.float64)
        if shapes.ndim != 4 or shapes.shape[2:] != (68, 2):
            raise UserError(
                f"edit shapes have shape {shapes.shape}, expected (targets, frames, 68, 2)", field="inputs.edit"
            )
        targets = [str(x) for x in edit.meta.get("targets", edit.meta.get("labels", labels))]
        if len(targets) != shapes.shape[0]:
            raise UserError(
                f"edit meta['targets'] names {len(targets)} expressions but shapes has {shapes.shape[0]} targets",
                field="inputs.edit",
            )
        unknown = [name for name in targets if name not in labels]
        if unknown:
            raise UserError(
                f"edited targets {unknown} are not training expressions of the aam ({labels}); "
                "keyshapes exist only for training expressions",
                field="inputs.edit",
            )
        if not np.isfinite(shapes).all():
            raise UserError("edit shapes contain NaN or Inf", field="inputs.edit")
        return targets, shapes

    figures = {"keyshapes": figure_keyshapes, "residual": figure_residual, "weights": figure_weights}
