"""Morph weights that deform a character's landmarks as a performer's face deformed (the maths of the automatic
keymorph draft, paper Sec 4.3; beyond the paper).

A regularised box-constrained least squares per keyshape (``bounded_fit``): weights in [0, 1], L2 and L1 penalties
relative to the morphs' landmark energy, left/right pairs coupled, antagonists kept from cancelling; optionally with
Huber's loss on each landmark's residual (``robust_fit``). ``LandmarkRig`` is the 2D front-view fit's view of the
character; ``stages.retarget.region_fit`` fits in 3D, region by region. Plain numpy: testable without msflow.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.formats.live_link import morph_key, split_side
from stages.geometry.nnls import solve_box_qp
from stages.retarget.regions import names_matching

#: landmarks that fix the similarity between actor and character: eyes (36-47) and nose (27-35) barely move
#: with expression, unlike the jaw line, brows and lips
STABLE_LANDMARKS = tuple(range(27, 48))
JAW_CONTOUR = tuple(range(0, 17))


def project_front(points: np.ndarray) -> np.ndarray:
    """Orthographic front view of glTF points (+y up, looking along -z at a face that looks along +z) in image
    convention (x right, y down): (x, -y)."""
    points = np.asarray(points, np.float64)
    return np.stack([points[..., 0], -points[..., 1]], axis=-1)


@dataclass
class Similarity:
    """p -> scale * rotation @ p + translation, in 2D or 3D."""

    scale: float
    rotation: np.ndarray  # (d, d)
    translation: np.ndarray  # (d,)

    def apply(self, points: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(points) @ self.rotation.T + self.translation

    def apply_linear(self, vectors: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(vectors) @ self.rotation.T

    def inverse_linear(self, vectors: np.ndarray) -> np.ndarray:
        return np.asarray(vectors) @ self.rotation / self.scale


#: the 2D name the keymorph fit has always used
Similarity2D = Similarity


def fit_similarity(source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None) -> Similarity:
    """Least-squares similarity (Umeyama 1991) mapping source points (n, d) onto target points (n, d), d = 2 or 3;
    optional non-negative per-point ``weights``. A reflection is never returned."""
    source = np.asarray(source, np.float64)
    target = np.asarray(target, np.float64)
    w = np.ones(len(source)) if weights is None else np.asarray(weights, np.float64)
    w = w / w.sum()
    mu_s, mu_t = w @ source, w @ target
    s, t = source - mu_s, target - mu_t
    u, sigma, vt = np.linalg.svd((t * w[:, None]).T @ s)
    d = np.ones(source.shape[1])
    d[-1] = np.sign(np.linalg.det(u @ vt)) or 1.0
    rotation = u @ np.diag(d) @ vt
    var = float(w @ (s**2).sum(axis=1))
    scale = float((sigma * d).sum() / var) if var > 0 else 1.0
    return Similarity(scale, rotation, mu_t - scale * rotation @ mu_s)


def symmetric_pairs(names: list[str]) -> list[tuple[int, int]]:
    """Index pairs of left/right morph targets: ``x_L``/``x_R`` (ICT), ``xLeft``/``xRight`` (ARKit)."""
    index: dict[tuple[str, str], int] = {}
    for i, name in enumerate(names):
        index.setdefault(split_side(name), i)
    return [(i, index[(stem, "R")]) for (stem, side), i in index.items() if side == "L" and (stem, "R") in index]


def antagonist_pairs(names: list[str], stems: list[tuple[str, str]]) -> list[tuple[int, int]]:
    """Index pairs of targets that oppose each other (stem pairs such as ("browDown", "browInnerUp")), matched
    on the same side of the face; a target without a side pairs with both sides."""
    parsed = [(morph_key(stem), side) for stem, side in map(split_side, names)]
    wanted = {(morph_key(a), morph_key(b)) for a, b in stems}
    pairs = []
    for i, (stem_a, side_a) in enumerate(parsed):
        for j, (stem_b, side_b) in enumerate(parsed):
            if (stem_a, stem_b) in wanted and (side_a == side_b or not side_a or not side_b):
                pairs.append((i, j))
    return pairs


def matching_targets(names: list[str], patterns: list[str]) -> np.ndarray:
    """Boolean mask of the names matching any fnmatch pattern, ignoring case and separators
    (``regions.names_matching``: ``eyeLook*`` is ``Eye_Look_Up_L`` too)."""
    return names_matching(names, patterns)


@dataclass
class LandmarkRig:
    """The character's landmark vertices as seen by the fit: projected rest pose, projected morph deltas, and
    the similarity that maps the actor's rest shape onto the character."""

    rest: np.ndarray  # (68, 2) character landmarks, projected, in character units
    deltas: np.ndarray  # (M, 68, 2) projected morph deltas of the landmark vertices
    to_character: Similarity2D  # actor (keyshape frame) -> character projection
    actor_rest: np.ndarray  # (68, 2) actor rest shape (keyshape frame)

    @classmethod
    def build(cls, neutral, deltas, landmark_ids, actor_rest) -> LandmarkRig:
        ids = np.asarray(landmark_ids, dtype=np.int64)
        rest = project_front(np.asarray(neutral, np.float64)[ids])
        projected = project_front(np.asarray(deltas, np.float64)[:, ids])
        stable = list(STABLE_LANDMARKS)
        to_character = fit_similarity(np.asarray(actor_rest, np.float64)[stable], rest[stable])
        return cls(rest, projected, to_character, np.asarray(actor_rest, np.float64))

    def target_deformation(self, keyshapes: np.ndarray, pose: np.ndarray | None = None) -> np.ndarray:
        """Keyshape deformations from the actor's rest pose, expressed in character units (K, 68, 2), less the
        part a head rotation explains (``pose``, from ``pose_effects``) when given."""
        deformation = self.to_character.apply_linear(np.asarray(keyshapes, np.float64) - self.actor_rest)
        return deformation if pose is None else deformation - pose

    def keymorph_landmarks(self, weights: np.ndarray, pose: np.ndarray | None = None) -> np.ndarray:
        """Where the keymorphs (and the head rotation, ``pose``) put the landmarks, in the keyshapes' frame."""
        deformation = np.einsum("km,mpc->kpc", np.asarray(weights, np.float64), self.deltas)
        if pose is not None:
            deformation = deformation + pose
        return self.actor_rest + self.to_character.inverse_linear(deformation)

    def pose_effects(self, neutral_landmarks: np.ndarray, rotations: np.ndarray) -> np.ndarray:
        """How much a head rotation alone moves the aligned 2D landmarks (K, 68, 2), character units.

        Tracked landmarks are aligned in 2D only (similarity), so a nod or turn of the actor's head changes them
        like an expression would (brows against eyes when nodding). ``rotations`` (K, 3, 3) turn the character's
        neutral landmarks (68, 3); the projection is similarity-aligned back onto the rest projection, as the
        aam alignment does, and what remains is the pose effect.
        """
        points = np.asarray(neutral_landmarks, np.float64)
        effects = np.empty((len(rotations), 68, 2))
        for k, rotation in enumerate(np.asarray(rotations, np.float64)):
            seen = project_front(points @ rotation.T)
            effects[k] = fit_similarity(seen, self.rest).apply(seen) - self.rest
        return effects


def fit_keymorph_weights(
    rig: LandmarkRig,
    keyshapes: np.ndarray,
    names: list[str],
    *,
    l2: float,
    l1: float,
    symmetry: float,
    exclude: list[str],
    contour_weight: float,
    antagonists: list[tuple[str, str]] = (),
    antagonism: float = 0.0,
    pose: np.ndarray | None = None,
    rtol: float = 1e-7,
    l1_scaling: float = 0.0,
    upper: float | np.ndarray = 1.0,
) -> tuple[np.ndarray, dict]:
    """Morph weights u in [0, ``upper``] (1, or (K, M) bounds) per keyshape minimising (Sec 4.3 keymorphs, automated)

        1/2 sum_p c_p ||sum_m u_m d_mp - delta_p||^2 + e (l2/2 ||u||^2 + l1 sum_m u_m)
            + symmetry/2 sum_(L,R pairs) e_LR (u_L - u_R)^2 + antagonism/2 sum_(antagonists a,b) e_ab u_a u_b

    with d_mp the projected landmark deltas of target m, delta_p the keyshape's deformation from rest in character
    units, c_p = ``contour_weight`` on the jaw line (2D trackers place it least reliably) and 1 elsewhere,
    e = the mean landmark energy sum_p c_p ||d_mp||^2 of the usable targets and e_LR, e_ab those of a pair (so
    the regularisers are unit-free). The antagonist term keeps opposing targets (browDown with browInnerUp, smile
    with frown) from cancelling each other to fit small landmark details; it makes the problem slightly
    non-convex, and projected gradient from zero weights finds a stationary point. Targets matching
    ``exclude`` stay 0; ``pose`` (K, 68, 2) removes what head rotation explains (``LandmarkRig.pose_effects``).
    All keyshapes share the Hessian, so they are solved as one batched box QP.
    """
    landmark_weight = np.ones(68)
    landmark_weight[list(JAW_CONTOUR)] = contour_weight
    root = np.sqrt(landmark_weight)[None, :, None]
    J = (rig.deltas * root).reshape(len(names), -1).T  # (136, M)
    targets = (rig.target_deformation(keyshapes, pose) * root).reshape(len(keyshapes), -1)
    usable = ~matching_targets(names, exclude)
    return bounded_fit(
        J, targets, names, usable, l2=l2, l1=l1, symmetry=symmetry, antagonists=antagonists,
        antagonism=antagonism, rtol=rtol, l1_scaling=l1_scaling, upper=upper,
    )  # fmt: skip


def bounded_fit(
    J: np.ndarray,
    targets: np.ndarray,
    names: list[str],
    usable: np.ndarray,
    *,
    l2: float,
    l1: float,
    symmetry: float,
    antagonists: list[tuple[str, str]] = (),
    antagonism: float = 0.0,
    upper: float | np.ndarray = 1.0,
    rtol: float = 1e-7,
    l1_scaling: float = 0.0,
    data_weights: np.ndarray | None = None,
    start: np.ndarray | None = None,
) -> tuple[np.ndarray, dict]:
    """The regularised bounded least squares of ``fit_keymorph_weights`` for a Jacobian J (D, M) of the morphs'
    landmark motion and target motions (K, D): weights (K, M) in [0, ``upper``] (a number or (K, M) bounds), 0 for
    morphs not ``usable`` or that move none of the landmarks. ``l1_scaling`` = g > 0 lowers the L1 penalty of a
    morph that moves the landmarks less than the mean, e_m < e, to e l1 (e_m / e)^g (``l1_weights``).
    ``data_weights`` (K, D) weigh each target's coordinates in the data term (``robust_fit``); the penalties keep
    their scale, the morphs' energies in J. ``start`` (K, M) warm-starts the solver."""
    M = len(names)
    usable = np.asarray(usable, bool) & (np.abs(J).max(axis=0, initial=0.0) > 0)
    column_energy = (J**2).sum(axis=0)
    energy = float(column_energy[usable].mean()) if usable.any() else 1.0
    R = l2 * energy * np.eye(M)
    for i, j in symmetric_pairs(names):
        coupling = np.zeros(M)
        coupling[i], coupling[j] = 1.0, -1.0
        # relative to the pair's own energy, so a faint pair (eyelids) is coupled as firmly as a strong one
        R += symmetry * 0.5 * (column_energy[i] + column_energy[j]) * np.outer(coupling, coupling)
    for i, j in antagonist_pairs(names, list(antagonists)):
        strength = antagonism * 0.5 * (column_energy[i] + column_energy[j])
        R[i, j] += 0.5 * strength
        R[j, i] += 0.5 * strength
    penalty = l1 * energy * l1_weights(column_energy, energy, l1_scaling)
    idx = np.flatnonzero(usable)
    weights = np.zeros((len(targets), M))
    if not idx.size:
        return weights, {"iterations": 0, "kkt_max": 0.0, "usable_targets": [], "energy": energy}
    Ju = J[:, idx]
    if data_weights is None:
        H, F = Ju.T @ Ju + R[np.ix_(idx, idx)], targets @ Ju - penalty[idx]
    else:
        H = np.einsum("dm,kd,dn->kmn", Ju, data_weights, Ju) + R[np.ix_(idx, idx)]
        F = (targets * data_weights) @ Ju - penalty[idx]
    bound = upper if np.isscalar(upper) else np.asarray(upper, np.float64)[:, idx]
    W0 = None if start is None else np.asarray(start, np.float64)[:, idx]
    sub, iterations, kkt = solve_box_qp(H, F, lower=0.0, upper=bound, rtol=rtol, W0=W0)
    weights[:, idx] = sub
    return weights, {
        "iterations": int(iterations),
        "kkt_max": float(np.max(kkt, initial=0.0)),
        "usable_targets": [names[i] for i in idx],
        "energy": energy,
    }


def l1_weights(column_energy: np.ndarray, energy: float, scaling: float) -> np.ndarray:
    """Per morph, its share of the L1 penalty: min(1, e_m / e)^scaling (1 for every morph when scaling = 0).

    The L1 term e l1 u_m costs the same per unit of weight whatever the morph, while a morph's benefit to the fit
    grows with its landmark energy e_m: a morph that moves the landmarks 1/25 as much as the mean (ICT's frown,
    lip press, lower-lip drop) would pay off only above u = l1 e / e_m = 0.5, so it stays at 0 however clearly the
    performer makes that movement. Scaled by e_m / e (scaling 1, the default) its threshold is l1 like any
    other morph's; morphs at or above the mean energy (jaw, funnel, pucker) keep the full penalty, so the jaw drop
    and lip rounding are weighed against each other as before."""
    if scaling <= 0:
        return np.ones_like(column_energy)
    return np.minimum(1.0, column_energy / max(energy, 1e-300)) ** scaling


def huber_point_weights(residual: np.ndarray, delta: float) -> np.ndarray:
    """Iteratively reweighted least squares weights (..., P) of Huber's loss on the norms of point residuals
    (..., P, d): 1 within ``delta``, delta / |r| beyond, so a point's pull grows no further past ``delta``."""
    norm = np.linalg.norm(residual, axis=-1)
    return np.minimum(1.0, delta / np.maximum(norm, 1e-300))


def robust_fit(
    J: np.ndarray,
    targets: np.ndarray,
    names: list[str],
    usable: np.ndarray,
    *,
    huber: float | None = None,
    dims: int = 3,
    rounds: int = 8,
    upper: float | np.ndarray = 1.0,
    **regularisers,
) -> tuple[np.ndarray, dict]:
    """``bounded_fit`` with Huber's loss on each landmark's residual (its ``dims`` coordinates together) instead
    of its square, beyond ``huber`` (character units; None: least squares), by reweighting (IRLS): a landmark the
    character cannot reach, or a mistracked one, keeps a bounded pull, so the fit does not recruit morphs that make
    another shape to chase it (CREMA-D fear: a funnel for a lower lip dropped 3-5 times as far as the chin). Only
    keyshapes with a landmark beyond ``huber`` are solved again, from the weights they had."""
    weights, info = bounded_fit(J, targets, names, usable, upper=upper, **regularisers)
    if huber is None:
        return weights, info
    bounds = np.broadcast_to(np.asarray(upper, np.float64), weights.shape)
    reweighted = np.zeros(len(targets), bool)
    for _ in range(rounds):
        point_weights = huber_point_weights((weights @ J.T - targets).reshape(len(targets), -1, dims), huber)
        reweighted |= (point_weights < 1.0).any(axis=1)
        rows = np.flatnonzero(reweighted)
        if not rows.size:
            break
        refit, refit_info = bounded_fit(
            J, targets[rows], names, usable, upper=bounds[rows], **regularisers,
            data_weights=np.repeat(point_weights[rows], dims, axis=1), start=weights[rows],
        )  # fmt: skip
        info["iterations"] = max(info["iterations"], refit_info["iterations"])
        info["kkt_max"] = max(info["kkt_max"], refit_info["kkt_max"])
        moved = np.abs(refit - weights[rows]).max(initial=0.0)
        weights[rows] = refit
        if moved < 1e-3:
            break
    return weights, info


def landmark_errors(
    rig: LandmarkRig, keyshapes: np.ndarray, weights: np.ndarray, scale: float, pose: np.ndarray | None = None
) -> np.ndarray:
    """Per keyshape RMS landmark distance between keyshape and keymorph (keyshape frame) / ``scale``."""
    diff = rig.keymorph_landmarks(weights, pose) - np.asarray(keyshapes, np.float64)
    return np.sqrt((diff**2).sum(-1).mean(-1)) / scale
