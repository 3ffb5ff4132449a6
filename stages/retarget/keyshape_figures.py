"""Figures of the keyshapes stages: the keyshapes per expression (the paper's Figs 3-4 left half), the
decomposition residual over time and the weights per frame.
"""

from __future__ import annotations

import numpy as np

from stages.retarget.face_measures import IBUG68_CONTOURS


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
