"""The non-negative decomposition of frames onto keyshapes (paper Eq 8).

Every frame x^(s)(t) of a sequence edited towards expression s is written as x^(s)(t) ~ sum_i w_i(t) B_i^(s),
w_i >= 0, over the keyshapes B^(s) of Sec 4.1 (``stages.retarget.keyshape_selection``), solved for all frames at
once (``stages.geometry.nnls``): whole face and, optionally, region by region (``DECOMPOSITION_REGIONS``), on the
absolute shapes or on their deformations from the rest pose. Residuals are relative to the inter-ocular distance.
The stages that run it are in ``stages.retarget.keyshapes``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.geometry.nnls import batched_nnls
from stages.retarget.face_measures import relative_rms_error


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


#: the regions decomposed apart (Eq 8 per region, ``regions: true``). The mouth region holds the jaw line and the
#: nostrils with the lips, so the jaw and the lips share one set of weights: a lip keymorph was fitted with its own
#: keyshape's jaw
DECOMPOSITION_REGIONS: dict[str, tuple[int, ...]] = {
    "mouth": tuple(range(0, 17)) + tuple(range(31, 36)) + tuple(range(48, 68)),
    "eyes": tuple(range(36, 48)),
    "brows": tuple(range(17, 27)),
}


@dataclass
class Decomposition:
    """Eq 8 for a set of frames: whole-face weights, optional per-region weights, and the reconstruction."""

    weights: np.ndarray  # (F, K)
    region_weights: np.ndarray | None  # (F, R, K)
    reconstruction: np.ndarray  # (F, 68, d)
    kkt: float


def decompose_groups(
    shapes: np.ndarray,
    groups: np.ndarray,
    keyshapes: np.ndarray,
    keyshape_group: np.ndarray,
    points: tuple[int, ...] | None = None,
    **nnls_options,
) -> tuple[np.ndarray, float]:
    """Eq 8 for frames that each use their own group's keyshapes: weights (F, K), zero outside the frame's group;
    ``points`` restricts the fit to those landmarks. Returns the weights and the largest KKT violation."""
    points = list(points) if points is not None else slice(None)
    weights = np.zeros((len(shapes), len(keyshapes)))
    kkt = 0.0
    for g in np.unique(groups):
        rows, mine = np.flatnonzero(groups == g), np.flatnonzero(keyshape_group == g)
        w, _, result = decompose_into_keyshapes(shapes[rows][:, points], keyshapes[mine][:, points], **nnls_options)
        weights[np.ix_(rows, mine)] = w
        if not nnls_options.get("smoothing"):
            kkt = max(kkt, float(result.kkt.max(initial=0.0)))
    return weights, kkt


def decompose(
    shapes: np.ndarray,
    groups: np.ndarray,
    keyshapes: np.ndarray,
    keyshape_group: np.ndarray,
    regions: dict[str, tuple[int, ...]] | None = None,
    rest: np.ndarray | float = 0.0,
    keyshape_rest: np.ndarray | float = 0.0,
    **nnls_options,
) -> Decomposition:
    """Eq 8, whole-face and (given ``regions``) region by region. A landmark in a region is reconstructed from
    its region's weights, any other from the whole-face weights. With ``rest`` (the frames' rest poses,
    broadcastable to ``shapes``) and ``keyshape_rest`` (the keyshapes'), the deformations from rest are decomposed
    (``decomposition: from_rest``) and the reconstruction is rest + sum_i w_i (B_i - rest_i)."""
    shapes, keyshapes = np.asarray(shapes, np.float64) - rest, np.asarray(keyshapes, np.float64) - keyshape_rest
    weights, kkt = decompose_groups(shapes, groups, keyshapes, keyshape_group, **nnls_options)
    reconstruction = np.einsum("fk,kpc->fpc", weights, keyshapes)
    if not regions:
        return Decomposition(weights, None, reconstruction + rest, kkt)
    by_region = np.zeros((len(shapes), len(regions), len(keyshapes)))
    for r, points in enumerate(regions.values()):
        by_region[:, r], region_kkt = decompose_groups(
            shapes, groups, keyshapes, keyshape_group, points, **nnls_options
        )
        kkt = max(kkt, region_kkt)
        reconstruction[:, list(points)] = np.einsum("fk,kpc->fpc", by_region[:, r], keyshapes[:, list(points)])
    return Decomposition(weights, by_region, reconstruction + rest, kkt)


def nnls_options(params) -> dict:
    return {"method": params.solver, "sum_to_one": params.sum_to_one, "smoothing": params.smoothing}


def decompose_targets(
    targets: np.ndarray, groups: np.ndarray, keyshapes: np.ndarray, selection, params, scale, rests=(0.0, 0.0)
):
    """Eq 8 for every target sequence (T, F, 68, d) with per-frame groups (T, F): weights, region weights (or
    None), reconstruction, residual / IOD, the largest KKT violation. ``rests`` = (the frames' rest poses,
    broadcastable to the targets; the keyshapes'): what ``decompose`` measures from (0: the absolute shapes)."""
    regions = DECOMPOSITION_REGIONS if params.regions else None
    rest, keyshape_rest = rests
    parts = [
        decompose(target, group, keyshapes, selection.expression, regions, r, keyshape_rest, **nnls_options(params))
        for target, group, r in zip(targets, groups, np.broadcast_to(rest, targets.shape))
    ]
    reconstruction = np.stack([p.reconstruction for p in parts])
    residual = relative_rms_error(reconstruction, targets, scale)
    region_weights = np.stack([p.region_weights for p in parts]) if params.regions else None
    return np.stack([p.weights for p in parts]), region_weights, reconstruction, residual, max(p.kkt for p in parts)
