"""Keymorphs (paper Sec 4.3): one morph-target weight vector G_i^(s) of the character per keyshape B_i^(s).

The paper has an artist model a keymorph that "resembles the look" of each keyshape. Two implementations share
one output schema (``keymorph_weights`` (total_k, M) in [0, 1], meta ``target_names``, the YAML as a file):

- ``KeymorphFile``: the artist's YAML, ``expression -> keyshape id -> {morph target name: weight}``, validated
  against the keyshapes and the character;
- ``KeymorphFit``: an automatic first draft (beyond the paper): per keyshape, bounded [0, 1] morph weights that
  make the character's 68 landmark vertices, seen from the front and mapped by one similarity transform into the
  keyshapes' frame, deform from their rest pose the way the keyshape deforms from the actor's rest pose
  (``rest_shape`` of the keyshapes artifact). Deformations rather than positions are matched, so the actor's
  and the character's face proportions need not agree. Regularised (L2 and L1 on the weights, left/right pairs
  coupled) so that weakly observed targets stay at 0. It writes the YAML an artist then edits.

Both write a contact sheet (the paper's Figs 3-4): per expression, each keyshape's face crop from tracking with
its landmarks beside the character rendered with its keymorph.
"""

from __future__ import annotations

import difflib
import fnmatch
import re
import textwrap
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from msflow import Input, Output, Result, Stage, UserError
from stages.geometry.nnls import solve_box_qp
from stages.retarget.keyshapes import IBUG68_CONTOURS, inter_ocular_distance
from stages.retarget.regions import RIGID

#: landmarks that fix the similarity between actor and character: eyes (36-47) and nose (27-35) barely move
#: with expression, unlike the jaw line, brows and lips
STABLE_LANDMARKS = tuple(range(27, 48))
JAW_CONTOUR = tuple(range(0, 17))


# ------------------------------------------------------------------------------------------------- geometry


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


_SIDES = (
    ("_L", "L"),
    ("_R", "R"),
    ("_l", "L"),
    ("_r", "R"),
    ("Left", "L"),
    ("Right", "R"),
    ("_left", "L"),
    ("_right", "R"),
)


def split_side(name: str) -> tuple[str, str]:
    """(stem, side) of a morph target name: "mouthSmile_L" -> ("mouthSmile", "L"), "jawOpen" -> ("jawOpen", "")."""
    for suffix, side in _SIDES:
        if name.endswith(suffix) and len(name) > len(suffix):
            return name[: -len(suffix)], side
    return name, ""


def antagonist_pairs(names: list[str], stems: list[tuple[str, str]]) -> list[tuple[int, int]]:
    """Index pairs of targets that oppose each other (stem pairs such as ("browDown", "browInnerUp")), matched
    on the same side of the face; a target without a side pairs with both sides."""
    parsed = [split_side(n) for n in names]
    pairs = []
    for i, (stem_a, side_a) in enumerate(parsed):
        for j, (stem_b, side_b) in enumerate(parsed):
            if (stem_a, stem_b) in stems and (side_a == side_b or not side_a or not side_b):
                pairs.append((i, j))
    return pairs


def matching_targets(names: list[str], patterns: list[str]) -> np.ndarray:
    """Boolean mask of the names matching any fnmatch pattern (case-sensitive)."""
    return np.array([any(fnmatch.fnmatchcase(n, p) for p in patterns) for n in names], dtype=bool)


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
) -> tuple[np.ndarray, dict]:
    """Morph weights u in [0, 1]^M per keyshape minimising (Sec 4.3 keymorphs, automated)

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
        antagonism=antagonism, rtol=rtol, l1_scaling=l1_scaling,
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


# ------------------------------------------------------------------------------------ 3D, region by region


class FitRegion(BaseModel):
    """One region of the 3D keymorph fit: the landmarks that show it and the morphs (fnmatch patterns,
    case-insensitive) that move it; ``decomposition`` names the keyshape-decomposition region whose weights
    drive these morphs in the blend (``stages.retarget.keyshapes.DECOMPOSITION_REGIONS``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    name: str
    landmarks: list[int] = Field(min_length=1)
    morphs: list[str] = Field(min_length=1)
    decomposition: Literal["mouth", "eyes", "brows"]

    @field_validator("landmarks")
    @classmethod
    def _ibug_ids(cls, landmarks):
        bad = [i for i in landmarks if not 0 <= i < 68]
        if bad:
            raise ValueError(f"landmark ids must lie in 0..67 (iBUG-68), got {bad}")
        return landmarks


#: The mouth (jaw and lips together, on the chin and the lips), then eyelids, brows, and cheeks and nose with what
#: the eyelids left (the lower lids are the eyes' before they are the cheeks'). Jaw and lips are one region: lips
#: parted by a dropped jaw and by rounded lips look alike from the front, and apart in 3D only jointly (the jaw
#: moves the chin down and back and the lower lip with it, rounding pushes both lips forward and the corners in,
#: never the chin); fitted one after the other, the jaw's landmarks already move with the lips' morphs. The chin's
#: sides (iBUG 4, 5, 11, 12) and the face contour are left out: FaceMesh's contour there follows the cheeks and the
#: silhouette more than the jaw.
DEFAULT_FIT_REGIONS = [
    FitRegion(
        name="mouth",
        landmarks=[6, 7, 8, 9, 10, *range(48, 68)],
        morphs=["jaw*", "mouth*", "cheekPuff*"],
        decomposition="mouth",
    ),
    FitRegion(
        name="eyes", landmarks=list(range(36, 48)), morphs=["eyeBlink*", "eyeSquint*", "eyeWide*"], decomposition="eyes"
    ),
    FitRegion(name="brows", landmarks=list(range(17, 27)), morphs=["brow*"], decomposition="brows"),
    FitRegion(
        name="cheeks", landmarks=[31, 32, 33, 34, 35, 40, 41, 46, 47], morphs=["cheek*", "nose*"], decomposition="mouth"
    ),
]


def matching_any_case(names: list[str], patterns: list[str]) -> np.ndarray:
    """Boolean mask of the names matching any fnmatch pattern, ignoring case."""
    return np.array([any(fnmatch.fnmatchcase(n.lower(), p.lower()) for p in patterns) for n in names], dtype=bool)


@dataclass
class Rig3D:
    """The character's 68 landmark vertices in 3D (its own units and axes) and their morph deltas."""

    rest: np.ndarray  # (68, 3)
    deltas: np.ndarray  # (M, 68, 3)

    @classmethod
    def build(cls, neutral, deltas, landmark_ids) -> Rig3D:
        ids = np.asarray(landmark_ids, dtype=np.int64)
        return cls(np.asarray(neutral, np.float64)[ids], np.asarray(deltas, np.float64)[:, ids])

    @property
    def iod(self) -> float:
        return float(inter_ocular_distance(self.rest))

    def to_character(self, rest: np.ndarray) -> Similarity:
        """The 3D similarity carrying a performer's rest shape (head frame) onto the character (rigid points)."""
        return fit_similarity(np.asarray(rest)[list(RIGID)], self.rest[list(RIGID)])

    def deformations(self, keyshapes: np.ndarray, rests: np.ndarray) -> np.ndarray:
        """Each keyshape's deformation from its performer's rest, in character units and axes (K, 68, 3)."""
        keyshapes, rests = np.asarray(keyshapes, np.float64), np.asarray(rests, np.float64)
        out = np.empty_like(keyshapes)
        unique, inverse = np.unique(rests.reshape(len(rests), -1), axis=0, return_inverse=True)
        for u, rest in enumerate(unique.reshape(-1, 68, 3)):
            rows = np.flatnonzero(inverse.reshape(-1) == u)
            out[rows] = self.to_character(rest).apply_linear(keyshapes[rows] - rest)
        return out

    def motion(self, weights: np.ndarray) -> np.ndarray:
        """Landmark motion (K, 68, 3) of morph weights (K, M)."""
        return np.einsum("km,mpc->kpc", np.asarray(weights, np.float64), self.deltas)


def corrective_pairs(names: list[str], correctives) -> list[tuple[int, int]]:
    """(corrective, base) morph index pairs the character has, e.g. (mouthClose, jawOpen)."""
    lower = [n.lower() for n in names]
    return [
        (lower.index(c.lower()), lower.index(b.lower()))
        for c, b in correctives
        if c.lower() in lower and b.lower() in lower
    ]


def fit_region(
    rig: Rig3D, targets: np.ndarray, points: list[int], columns: np.ndarray, names, pairs, regularisers, passes=8
):
    """One region's bounded fit (``bounded_fit``) with correctives bounded by their base morph: a first pass
    without the correctives gives the base weights, each further pass bounds every corrective by its base's weight
    from the pass before (a joint bound u_c <= u_b is not a box), until the weights settle; a corrective is
    finally clipped to its base's final weight."""
    K = len(targets)
    J = rig.deltas[columns][:, points].reshape(len(columns), -1).T
    local = {int(c): i for i, c in enumerate(columns)}
    sub_names = [names[c] for c in columns]
    mine = [(local[c], local.get(b)) for c, b in pairs if c in local]
    upper = np.ones((K, len(columns)))
    for c, _ in mine:
        upper[:, c] = 0.0
    sub, info = robust_fit(J, targets, sub_names, np.ones(len(columns), bool), upper=upper, **regularisers)
    if not mine:
        return sub, info
    for _ in range(passes):  # the bound u_c <= u_b, fixed from the last pass, until the base stops moving
        upper = np.ones((K, len(columns)))
        for c, b in mine:
            upper[:, c] = sub[:, b] if b is not None else 0.0
        previous = sub
        sub, info = robust_fit(J, targets, sub_names, np.ones(len(columns), bool), upper=upper, **regularisers)
        if np.abs(sub - previous).max(initial=0.0) < 1e-3:
            break
    for c, b in mine:
        sub[:, c] = np.minimum(sub[:, c], sub[:, b] if b is not None else 0.0)
    return sub, info


def fit_regions_3d(
    rig: Rig3D,
    deformation: np.ndarray,
    names: list[str],
    regions: list[FitRegion],
    *,
    exclude: list[str],
    correctives: list[tuple[str, str]] = (),
    robust_iod: float | None = None,
    **regularisers,
) -> tuple[np.ndarray, dict]:
    """Keymorph weights fitted in 3D, region by region (issue 13.1), each region's morphs to its landmarks'
    deformation less what the regions fitted before it already move there (``fit_region``, all keyshapes at
    once). A morph belongs to the first region whose patterns match it; a corrective whose base is fitted in an
    earlier region is bounded by the base's weight there. Returns weights (K, M) and per region the morphs it
    fitted."""
    K = len(deformation)
    weights = np.zeros((K, len(names)))
    explained = np.zeros_like(deformation)
    assigned = matching_any_case(names, exclude)
    pairs = corrective_pairs(names, correctives)
    info = {"regions": {}, "morph_regions": {}, "iterations": 0, "kkt_max": 0.0}
    regularisers = {**regularisers, "huber": None if robust_iod is None else robust_iod * rig.iod}
    for region in regions:
        columns = np.flatnonzero(matching_any_case(names, region.morphs) & ~assigned)
        assigned[columns] = True
        if not columns.size:
            info["regions"][region.name] = []
            continue
        points = list(region.landmarks)
        targets = (deformation - explained)[:, points].reshape(K, -1)
        # a base fitted earlier acts as a fixed bound: pass it in as a pseudo-column the region does not fit
        region_pairs = [(c, b) for c, b in pairs if c in columns and (b in columns or assigned[b])]
        sub, sub_info = fit_region(
            rig, targets, points, columns, names, [p for p in region_pairs if p[1] in columns], regularisers
        )
        for c, b in region_pairs:
            if b not in columns:
                i = list(columns).index(c)
                sub[:, i] = np.minimum(sub[:, i], weights[:, b])
        weights[:, columns] = sub
        explained += np.einsum("km,mpc->kpc", sub, rig.deltas[columns])
        info["regions"][region.name] = sub_info["usable_targets"]
        info["morph_regions"].update({names[c]: region.decomposition for c in columns})
        info["iterations"] = max(info["iterations"], sub_info["iterations"])
        info["kkt_max"] = max(info["kkt_max"], sub_info["kkt_max"])
    return weights, info


# ------------------------------------------------------------------------------------------------------ YAML

_PLAIN = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")
_YAML_WORDS = {"true", "false", "yes", "no", "on", "off", "null", "y", "n", "~"}


def _yaml_key(name: str) -> str:
    if _PLAIN.match(name) and name.lower() not in _YAML_WORDS:
        return name
    return "'" + name.replace("'", "''") + "'"


def format_keymorph_yaml(
    labels: list[str],
    keyshape_expression: np.ndarray,
    keyshape_index: np.ndarray,
    weights: np.ndarray,
    names: list[str],
    *,
    comments: list[str] | None = None,
    header: str = "",
    decimals: int | None = 3,
) -> str:
    """The keymorph YAML: ``expression -> keyshape id -> {morph target: weight}``, one keyshape per line.

    Weights are rounded to ``decimals`` (None: written exactly) and zeros left out, so the file stays short
    enough to edit by hand. ``comments`` (one per keyshape) go at the end of each line.
    """
    lines = [f"# {line}" if line else "#" for line in header.splitlines()]
    for s, label in enumerate(labels):
        mine = np.flatnonzero(np.asarray(keyshape_expression) == s)
        lines.append(f"{_yaml_key(label)}:" + ("  {}" if not mine.size else ""))
        for k in mine:
            w = np.asarray(weights[k], np.float64)
            if decimals is not None:
                w = np.round(w, decimals)
            items = ", ".join(f"{_yaml_key(names[m])}: {_number(w[m], decimals)}" for m in np.flatnonzero(w > 0))
            note = f"  # {comments[k]}" if comments else ""
            lines.append(f"  {int(keyshape_index[k])}: {{{items}}}{note}")
    return "\n".join(lines) + "\n"


def _number(value: float, decimals: int | None) -> str:
    if decimals is None:
        return repr(float(value))
    return f"{value:.{decimals}f}".rstrip("0").rstrip(".")


def rounded_weights(weights: np.ndarray, decimals: int = 3) -> np.ndarray:
    """The weights exactly as ``format_keymorph_yaml`` writes them."""
    return np.clip(np.round(np.asarray(weights, np.float64), decimals), 0.0, 1.0)


def _suggest(name: str, valid: list[str]) -> str:
    close = difflib.get_close_matches(name, valid, n=1)
    return f" (did you mean '{close[0]}'?)" if close else ""


def parse_keymorph_yaml(
    text: str, labels: list[str], counts: list[int], names: list[str], *, file: str, allow_missing: bool = False
) -> np.ndarray:
    """Keymorph weights (total_k, M) from the YAML text; every mistake is a UserError naming the valid choices.

    Keyshape ids are each expression's own ids 0..k_s-1 (``keyshape_index`` of the keyshapes artifact), the
    rows come out in the keyshapes artifact's order (grouped by expression).
    """
    import yaml

    field = "inputs.keymorphs"
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise UserError(f"keymorph file is not valid YAML: {exc}", file=file, field=field) from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise UserError(
            "keymorph file must map expression names to keyshape ids to {morph target: weight}, "
            f"found a {type(data).__name__} at the top level",
            file=file,
            field=field,
        )
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(int)
    weights = np.zeros((int(offsets[-1]), len(names)))
    seen = np.zeros(int(offsets[-1]), dtype=bool)
    index = {name: m for m, name in enumerate(names)}
    for expression, keymorphs in data.items():
        expression = str(expression)
        if expression not in labels:
            raise UserError(
                f"unknown expression '{expression}'{_suggest(expression, labels)}; the keyshapes have "
                f"expressions: {', '.join(labels)}",
                file=file,
                field=field,
            )
        s = labels.index(expression)
        if keymorphs is None:
            keymorphs = {}
        if not isinstance(keymorphs, dict):
            raise UserError(
                f"'{expression}' must map keyshape ids (0..{counts[s] - 1}) to {{morph target: weight}}",
                file=file,
                field=field,
            )
        for key, morphs in keymorphs.items():
            local = (
                int(key)
                if isinstance(key, int) and not isinstance(key, bool)
                else int(key)
                if isinstance(key, str) and key.strip().isdigit()
                else -1
            )
            if not 0 <= local < counts[s]:
                raise UserError(
                    f"{expression}: unknown keyshape id '{key}'; valid ids for '{expression}' are 0..{counts[s] - 1}",
                    file=file,
                    field=field,
                )
            row = offsets[s] + local
            if seen[row]:
                raise UserError(f"{expression}: keyshape id {local} is given twice", file=file, field=field)
            seen[row] = True
            if morphs is None:
                morphs = {}
            if not isinstance(morphs, dict):
                raise UserError(
                    f"{expression}/{local}: expected {{morph target: weight}}, found {type(morphs).__name__}",
                    file=file,
                    field=field,
                )
            for name, value in morphs.items():
                name = str(name)
                if name not in index:
                    raise UserError(
                        f"{expression}/{local}: unknown morph target '{name}'{_suggest(name, names)}; "
                        f"the character's targets are: {', '.join(names)}",
                        file=file,
                        field=field,
                    )
                if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
                    raise UserError(
                        f"{expression}/{local}: weight of '{name}' must be a number, got {value!r}",
                        file=file,
                        field=field,
                    )
                if not 0.0 <= value <= 1.0:
                    raise UserError(
                        f"{expression}/{local}: weight of '{name}' is {value}, outside [0, 1]", file=file, field=field
                    )
                weights[row, index[name]] = float(value)
    if not allow_missing and not seen.all():
        missing = {}
        for s, label in enumerate(labels):
            ids = [i for i in range(counts[s]) if not seen[offsets[s] + i]]
            if ids:
                missing[label] = ids
        raise UserError(
            f"keymorph file has no entry for keyshapes {missing} (an empty {{}} means the neutral "
            "face; or set allow_missing to treat missing ones as neutral)",
            file=file,
            field=field,
        )
    return weights


# ---------------------------------------------------------------------------------------------- contact sheet


def draw_landmarks(image: np.ndarray, points: np.ndarray, color=(40, 200, 40)) -> np.ndarray:
    """RGB copy of a grayscale or RGB image with the iBUG-68 contours and points drawn."""
    import cv2

    out = cv2.cvtColor(image, cv2.COLOR_GRAY2RGB) if image.ndim == 2 else image.copy()
    shift = 4  # sub-pixel drawing
    pts = np.round(np.asarray(points, np.float64) * (1 << shift)).astype(np.int32)
    for contour in IBUG68_CONTOURS:
        cv2.polylines(out, [pts[list(contour)].reshape(-1, 1, 2)], False, color, 1, cv2.LINE_AA, shift)
    for p in pts:
        cv2.circle(out, (int(p[0]), int(p[1])), 1 << shift, color, -1, cv2.LINE_AA, shift)
    return out


def landmark_tile(points: np.ndarray, size: int) -> np.ndarray:
    """A white tile with a landmark drawing, for when no tracking crops are available."""
    pts = np.asarray(points, np.float64)
    lo, hi = pts.min(0), pts.max(0)
    scale = 0.8 * size / max(float((hi - lo).max()), 1e-9)
    pts = (pts - (lo + hi) / 2) * scale + size / 2
    return draw_landmarks(np.full((size, size), 255, np.uint8), pts, color=(30, 30, 30))


def face_crop_tile(crop: np.ndarray, landmarks: np.ndarray, size: int) -> np.ndarray:
    """The tracking crop with its landmarks, square-cropped around the face and resized to ``size``."""
    import cv2

    crop = np.asarray(crop)
    h, w = crop.shape[:2]
    pts = np.asarray(landmarks, np.float64)
    centre = (pts.min(0) + pts.max(0)) / 2
    half = 0.62 * float((pts.max(0) - pts.min(0)).max())
    x0, y0 = int(round(centre[0] - half)), int(round(centre[1] - half))
    side = max(int(round(2 * half)), 1)
    padded = cv2.copyMakeBorder(crop, side, side, side, side, cv2.BORDER_CONSTANT, value=0)
    window = padded[y0 + side : y0 + 2 * side, x0 + side : x0 + 2 * side]
    tile = cv2.resize(window, (size, size), interpolation=cv2.INTER_AREA)
    return draw_landmarks(tile, (pts - [x0, y0]) * (size / side))


def render_keymorph_tiles(character, weights: np.ndarray, size: int, supersample: int = 2) -> list[np.ndarray]:
    """The character's face from the front (stages.geometry.render, "face" framing) posed by each row of ``weights``."""
    from stages.geometry.render import CharacterRenderer, View

    # frame the landmarks tightly (brows to chin), like the tracking crops beside them
    points = np.asarray(character["neutral"], np.float64)[np.asarray(character["landmark_ids"])]
    lo, hi = points.min(axis=0), points.max(axis=0)
    pad = 0.12 * (hi - lo)
    view = View.fit(np.array([lo - pad, hi + pad * [1, 2, 0]]), margin=1.0)
    renderer = CharacterRenderer.from_artifact(character, size=size, view=view, supersample=supersample)
    return [np.ascontiguousarray(renderer(w)[..., :3]) for w in np.asarray(weights, np.float32)]


def compose_contact_sheet(
    labels: list[str],
    keyshape_expression: np.ndarray,
    keyshape_index: np.ndarray,
    keyshape_frame: np.ndarray,
    keyshape_tiles: list[np.ndarray],
    keymorph_tiles: list[np.ndarray],
    size: int,
    notes: list[str] | None = None,
) -> np.ndarray:
    """Paper Figs 3-4 as one RGB image: per expression a header, a row of keyshapes, a row of keymorphs."""
    import cv2

    expression = np.asarray(keyshape_expression)
    cols = max(int(np.bincount(expression, minlength=len(labels)).max(initial=1)), 1)
    header, caption = 22, 14
    block = header + 2 * (size + caption)
    sheet = np.full((block * len(labels), cols * size, 3), 255, np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    for s, label in enumerate(labels):
        top = s * block
        sheet[top : top + header] = (225, 225, 235)
        cv2.putText(
            sheet,
            f"{label}: keyshapes (top) and keymorphs (bottom)",
            (4, top + 16),
            font,
            0.5,
            (20, 20, 20),
            1,
            cv2.LINE_AA,
        )
        for c, k in enumerate(np.flatnonzero(expression == s)):
            x = c * size
            y = top + header
            sheet[y : y + size, x : x + size] = keyshape_tiles[k]
            cv2.putText(
                sheet,
                f"#{int(keyshape_index[k])} f{int(keyshape_frame[k])}",
                (x + 3, y + size + 11),
                font,
                0.35,
                (20, 20, 20),
                1,
                cv2.LINE_AA,
            )
            y += size + caption
            sheet[y : y + size, x : x + size] = keymorph_tiles[k]
            if notes:
                cv2.putText(sheet, notes[k], (x + 3, y + size + 11), font, 0.35, (20, 20, 20), 1, cv2.LINE_AA)
    return sheet


def encode_png(image: np.ndarray) -> bytes:
    import cv2

    ok, data = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2BGR))
    if not ok:  # pragma: no cover - OpenCV failure
        raise RuntimeError("PNG encoding failed")
    return data.tobytes()


def check_tracks(keyshapes, tracks) -> None:
    """The tracking input must be the one the keyshapes' source frames index (a UserError otherwise)."""
    frames = np.asarray(keyshapes["keyshape_frame"])
    count = len(tracks["crop_landmarks"]) if tracks is not None and "crop_landmarks" in tracks else None
    if count is not None and frames.max(initial=0) >= count:
        raise UserError(
            f"keyshape source frame {int(frames.max())} is beyond the {count} frames of the "
            "tracking input: wire the training tracking (the one the aam was built from)",
            field="inputs.tracks",
        )


def build_contact_sheet(
    keyshapes, character, tracks, weights: np.ndarray, size: int, notes: list[str] | None = None
) -> np.ndarray:
    labels = list(keyshapes.meta["labels"])
    frames = np.asarray(keyshapes["keyshape_frame"])
    if tracks is not None:
        check_tracks(keyshapes, tracks)
        crops, crop_landmarks = tracks["crops"], tracks["crop_landmarks"]
        left = [face_crop_tile(crops[f], crop_landmarks[f], size) for f in frames]
    else:
        left = [landmark_tile(shape, size) for shape in keyshapes["keyshapes"]]
    right = render_keymorph_tiles(character, weights, size)
    return compose_contact_sheet(
        labels, keyshapes["keyshape_expression"], keyshapes["keyshape_index"], frames, left, right, size, notes
    )


# ---------------------------------------------------------------------------------------------------- figures


def figure_contact_sheet(view, inputs):
    """Keyshape crops above keymorph renders, per expression (the paper's Figs 3-4): the one the stage wrote
    (``params.contact_sheet``), else rendered now from the stage's inputs (a run need not pay for it)."""
    if "contact_sheet" in view:
        return view.bytes("contact_sheet")
    if inputs and inputs.get("keyshapes") is not None and inputs.get("character") is not None:
        notes = [f"err {100 * e:.1f}%" for e in view["landmark_error"]]
        weights = np.asarray(view["keymorph_weights"], np.float64)
        sheet = build_contact_sheet(inputs["keyshapes"], inputs["character"], inputs.get("tracks"), weights, 128, notes)
        return encode_png(sheet)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(4, 1))
    ax.axis("off")
    ax.text(0.5, 0.5, "no contact sheet: neither stored (params.contact_sheet) nor inputs", ha="center", va="center")
    return fig


def figure_landmark_fit(view, inputs):
    """Keyshape landmarks (black) against the landmarks the keymorph gives the character (red), per keyshape
    (the 3D fit: both in the head frame, seen from the front)."""
    from stages.retarget.keyshapes import plot_keyshape_grid

    keyshapes = inputs["keyshapes"]
    reference = keyshapes["keyshapes"]
    if view.meta.get("space") == "3d" and "keyshapes3d" in keyshapes:
        from stages.retarget.shapes3d import front_view

        reference = front_view(keyshapes["keyshapes3d"])
    errors = view["landmark_error"]
    return plot_keyshape_grid(
        [(reference, {"color": "k", "lw": 0.7}), (view["keymorph_landmarks"], {"color": "r", "lw": 0.7})],
        keyshapes["keyshape_expression"],
        list(keyshapes.meta["labels"]),
        "Keyshape (black) vs keymorph landmarks (red), RMS error % inter-ocular",
        lambda i, c: f"{c}: {100 * errors[i]:.1f}%",
    )


# ----------------------------------------------------------------------------------------------------- stages

KEYMORPHS_OUTPUTS = {
    "keymorph_weights": Output.array(
        "f",
        shape=("total_k", "targets"),
        dtype="float32",
        doc="morph target weights in [0, 1] per keyshape (meta['target_names'])",
    ),
    "keymorph_landmarks": Output.array(
        "f",
        shape=("total_k", 68, 2),
        dtype="float32",
        doc="the character's landmarks under each keymorph, in the keyshape frame",
    ),
    "landmark_error": Output.array(
        "f",
        shape=("total_k",),
        dtype="float32",
        doc="RMS landmark distance keyshape vs keymorph / inter-ocular distance",
    ),
    "keymorphs": Output.file(".yaml", doc="the keymorphs as an editable YAML (KeymorphFile reads it)"),
    "contact_sheet": Output.file(".png", optional=True, doc="keyshape crops beside keymorph renders (Figs 3-4)"),
}

_INPUTS = {
    "keyshapes": Input.artifact(
        "keyshapes", "keyshape_expression", "keyshape_index", "keyshape_frame", "rest_shape", doc="keyshapes artifact"
    ),
    "character": Input.artifact("neutral", "triangles", "deltas", "landmark_ids", doc="character artifact"),
    "tracks": Input.artifact(
        "crops",
        "crop_landmarks",
        optional=True,
        doc="training tracking artifact: face crops of the keyshapes' source frames for the "
        "contact sheet (landmark drawings instead when absent) and head rotations for "
        "the pose correction",
    ),
}


def morph_decomposition_regions(names: list[str], regions: list[FitRegion], exclude: list[str]) -> dict[str, str]:
    """Morph name -> the decomposition region whose keyshape weights drive it in the blend (first region whose
    patterns match; excluded and unmatched morphs are left out: the whole-face weights drive them)."""
    out: dict[str, str] = {}
    free = ~matching_any_case(names, exclude)
    for region in regions:
        for m in np.flatnonzero(matching_any_case(names, region.morphs) & free):
            out.setdefault(names[m], region.decomposition)
    return out


@dataclass
class Prepared:
    """What a keymorph stage compares keymorphs with: in 3D (head frame, per-region fit) when the keyshapes carry
    FaceMesh depth, else the 2D front projection (with the optional head-rotation correction)."""

    space: str
    rig: LandmarkRig
    shapes: np.ndarray  # (K, 68, 2) keyshapes, keyshape frame
    scale: float
    pose: np.ndarray | None = None
    pose_note: str = "off (params.pose_correction)"
    rig3d: Rig3D | None = None
    deformation: np.ndarray | None = None  # (K, 68, 3) character units
    keyshapes3d: np.ndarray | None = None
    rests3d: np.ndarray | None = None

    def errors(self, weights: np.ndarray) -> np.ndarray:
        """Per keyshape RMS landmark distance keyshape vs keymorph / inter-ocular distance."""
        if self.space == "3d":
            diff = self.rig3d.motion(weights) - self.deformation
            return np.sqrt((diff**2).sum(-1).mean(-1)) / self.rig3d.iod
        return landmark_errors(self.rig, self.shapes, weights, self.scale, self.pose)

    def landmarks(self, weights: np.ndarray) -> np.ndarray:
        """The character's landmarks under each keymorph in the keyshapes' frame (3D: head frame from the front)."""
        if self.space != "3d":
            return self.rig.keymorph_landmarks(weights, self.pose)
        from stages.retarget.shapes3d import front_view

        motion = self.rig3d.motion(weights)
        out = np.empty_like(motion)
        for k, rest in enumerate(self.rests3d):
            out[k] = rest + self.rig3d.to_character(rest).inverse_linear(motion[k])
        return front_view(out)

    def reference(self) -> np.ndarray:
        """The keyshapes as ``landmarks`` draws them."""
        if self.space != "3d":
            return self.shapes
        from stages.retarget.shapes3d import front_view

        return front_view(self.keyshapes3d)


class _KeymorphStage(Stage):
    outputs = KEYMORPHS_OUTPUTS
    figures = {"contact_sheet": figure_contact_sheet, "landmark_fit": figure_landmark_fit}

    def _prepare(self, params, inputs) -> Prepared:
        keyshapes, character = inputs["keyshapes"], inputs["character"]
        check_tracks(keyshapes, inputs.get("tracks"))
        rig = self._rig(keyshapes, character)
        shapes = np.asarray(keyshapes["keyshapes"], np.float64)
        scale = float(inter_ocular_distance(keyshapes["rest_shape"]))
        has_3d = "keyshapes3d" in keyshapes and "keyshape_rest3d" in keyshapes
        if params.space == "3d" and not has_3d:
            raise UserError(
                "space: 3d needs keyshapes in 3D: give the keyshapes stage the training tracking with its FaceMesh "
                "(inputs.tracks), or use space: 2d",
                field="params.space",
            )
        if has_3d and params.space != "2d":
            rig3d = Rig3D.build(character["neutral"], character["deltas"], character["landmark_ids"])
            shapes3d = np.asarray(keyshapes["keyshapes3d"], np.float64)
            rests3d = np.asarray(keyshapes["keyshape_rest3d"], np.float64)
            return Prepared(
                "3d", rig, shapes, scale, None, "not needed: the 3D keyshapes are in the head's frame", rig3d,
                rig3d.deformations(shapes3d, rests3d), shapes3d, rests3d,
            )  # fmt: skip
        prepared = Prepared("2d", rig, shapes, scale)
        tracks = inputs.get("tracks")
        if params.pose_correction:
            if tracks is None or "rotation" not in tracks or "rest_frames" not in keyshapes:
                prepared.pose_note = (
                    "not applied: needs the tracks input with head rotations (and keyshapes rest_frames)"
                )
            else:
                prepared.pose = self._pose_effects(rig, character, keyshapes, tracks["rotation"])
                prepared.pose_note = "applied"
        return prepared

    @staticmethod
    def _pose_effects(rig: LandmarkRig, character, keyshapes, rotation: np.ndarray) -> np.ndarray:
        from stages.geometry.rotations import quat_mean, quat_to_matrix

        frames = np.asarray(keyshapes["keyshape_frame"])
        rest = np.asarray(keyshapes["rest_frames"])
        rotation = np.asarray(rotation, np.float64)
        if max(frames.max(initial=0), rest.max(initial=0)) >= len(rotation):
            raise UserError(
                f"keyshape source frames reach {int(max(frames.max(), rest.max()))} but the tracking "
                f"input has {len(rotation)} frames: wire the training tracking the aam was built from",
                field="inputs.tracks",
            )
        # the head rotation of each keyshape's frame relative to the rest frames' mean rotation
        relative = quat_to_matrix(rotation[frames]) @ quat_to_matrix(quat_mean(rotation[rest])).T
        ids = np.asarray(character["landmark_ids"])
        return rig.pose_effects(np.asarray(character["neutral"], np.float64)[ids], relative)

    def _common(
        self, params, inputs, prepared: Prepared, weights: np.ndarray, yaml_text: str, metrics: dict, meta: dict
    ) -> Result:
        keyshapes, character = inputs["keyshapes"], inputs["character"]
        names = list(character.meta["target_names"])
        errors = prepared.errors(weights)
        baseline = prepared.errors(np.zeros_like(weights))
        arrays = {
            "keymorph_weights": weights.astype(np.float32),
            "keymorph_landmarks": prepared.landmarks(weights).astype(np.float32),
            "landmark_error": errors.astype(np.float32),
            "keymorphs": yaml_text.encode("utf-8"),
        }
        if params.contact_sheet:
            notes = [f"err {100 * e:.1f}%" for e in errors]
            sheet = build_contact_sheet(keyshapes, character, inputs.get("tracks"), weights, params.tile_size, notes)
            arrays["contact_sheet"] = encode_png(sheet)
        labels = list(keyshapes.meta["labels"])
        expression = np.asarray(keyshapes["keyshape_expression"])
        metrics = dict(metrics)
        metrics["landmark_error_rms_iod"] = float(np.sqrt(np.mean(errors**2)))
        metrics["landmark_error_neutral_rms_iod"] = float(np.sqrt(np.mean(baseline**2)))
        metrics["mean_active_targets"] = float((weights > 0).sum(axis=1).mean())
        if prepared.pose is not None:
            pose = prepared.rig.to_character.inverse_linear(prepared.pose)
            metrics["pose_effect_rms_iod"] = float(np.sqrt(np.mean((pose**2).sum(-1)) / prepared.scale**2))
        meta = dict(
            meta,
            target_names=names,
            labels=labels,
            space=prepared.space,
            pose_correction=prepared.pose_note,
            keyshape_ids=[f"{labels[e]}/{int(i)}" for e, i in zip(expression, keyshapes["keyshape_index"])],
            similarity_scale=prepared.rig.to_character.scale,
        )
        return Result(arrays, meta=meta, metrics=metrics)

    @staticmethod
    def _rig(keyshapes, character) -> LandmarkRig:
        ids = np.asarray(character["landmark_ids"])
        if ids.shape != (68,):
            raise UserError(f"character landmark_ids has shape {ids.shape}, expected (68,)", field="inputs.character")
        n_vertices = len(character["neutral"])
        if ids.min() < 0 or ids.max() >= n_vertices:
            raise UserError(f"character landmark ids must lie in 0..{n_vertices - 1}", field="inputs.character")
        if len(character["deltas"]) == 0:
            raise UserError("the character has no morph targets", field="inputs.character")
        return LandmarkRig.build(character["neutral"], character["deltas"], ids, keyshapes["rest_shape"])

    @staticmethod
    def _yaml_comments(keyshapes, errors=None) -> list[str]:
        frames = np.asarray(keyshapes["keyshape_frame"])
        axes = np.asarray(keyshapes["keyshape_axis"]) if "keyshape_axis" in keyshapes else None
        ext = np.asarray(keyshapes["keyshape_extreme"]) if "keyshape_extreme" in keyshapes else None
        comments = []
        for k, f in enumerate(frames):
            text = f"frame {int(f)}"
            if axes is not None and ext is not None:
                text += f", PCA axis {int(axes[k])} {'max' if ext[k] > 0 else 'min'}"
            if errors is not None:
                text += f", landmark fit {100 * errors[k]:.1f}% IOD"
            comments.append(text)
        return comments


class KeymorphFitParams(Stage.Params):
    #: L2 penalty on the weights, relative to the mean landmark energy of a morph target
    l2: float = Field(0.005, ge=0)
    #: L1 penalty (sparsity: only the needed targets move), same units
    l1: float = Field(0.02, ge=0)
    #: 3D fit: a morph that moves its region's landmarks less than the mean pays l1 x (its energy / the
    #: mean)^l1_scaling, so small morphs (frown, lip press) are not priced out (0: one penalty for every morph).
    #: The 2D fit keeps one penalty: seen from the front, many small morphs look alike
    l1_scaling: float = Field(1.0, ge=0)
    #: coupling of left/right pairs (x_L, x_R): penalty on their difference
    symmetry: float = Field(0.2, ge=0)
    #: penalty on using opposing targets together (product of their weights), per side of the face
    antagonism: float = Field(1.0, ge=0)
    #: opposing pairs. mouthFunnel draws the lip corners in and mouthStretch pulls them out: without the pair the
    #: fit used a funnel as a lower-lip lowerer beyond the character's mouthLowerDown, its corners cancelled by a
    #: stretch (CREMA-D fear: funnel 0.52 over jawOpen 0.51 where the performer's lips stretched and moved back;
    #: docs/retarget.md). The list before it: this one without ("mouthFunnel", "mouthStretch")
    antagonists: list[tuple[str, str]] = [
        ("browDown", "browInnerUp"),
        ("browDown", "browOuterUp"),
        ("mouthSmile", "mouthFrown"),
        ("eyeWide", "eyeBlink"),
        ("eyeWide", "eyeSquint"),
        ("jawLeft", "jawRight"),
        ("mouthLeft", "mouthRight"),
        ("mouthPucker", "mouthStretch"),
        ("mouthFunnel", "mouthStretch"),
    ]
    #: 3D fit: Huber's loss on each landmark's residual beyond this (IOD) instead of its square, so a landmark
    #: the character cannot reach, or a mistracked one, keeps a bounded pull and does not recruit morphs of another
    #: shape to chase it (CREMA-D fear: jawOpen > mouthFunnel at the widest-jaw frames 57% -> 71%; 0.015 gives 86%
    #: but leaves a sideways jaw and a frown dead where the performer made them; docs/retarget.md); None: least
    #: squares, as before
    robust_iod: float | None = Field(0.025, gt=0)
    #: 2D fit: weight of the jaw-line landmarks (0-16) relative to the others (2D trackers place it least well)
    contour_weight: float = Field(0.5, ge=0)
    #: targets the fit leaves at 0 (fnmatch patterns): gaze and pupils do not show in landmarks
    exclude: list[str] = ["eyeLook*", "PupilDilate*"]
    #: (corrective, base) pairs: the corrective's weight never exceeds the base's (ARKit's mouthClose closes the
    #: lips of an opened jaw only). The 3D fit bounds it; the 2D fit, solved jointly, leaves correctives at 0
    correctives: list[tuple[str, str]] = [("mouthClose", "jawOpen")]
    #: fit in 3D region by region when the keyshapes carry FaceMesh depth (auto), or always on the 2D front view
    space: Literal["auto", "3d", "2d"] = "auto"
    #: the regions of the 3D fit, in order (the blend drives each region's morphs with its decomposition region's
    #: keyshape weights); morphs matching no region are not fitted in 3D
    regions: list[FitRegion] = DEFAULT_FIT_REGIONS
    #: decimals of the weights in the YAML (the output weights are exactly the YAML's)
    decimals: int = Field(3, ge=0)
    #: 2D fit: discount the landmark motion that the actor's head rotation explains (needs the tracks input)
    pose_correction: bool = True
    #: also store the contact sheet (keyshape crops beside keymorph renders) as an output file; without it the
    #: ``contact_sheet`` figure renders it when asked (msflow show/report), so a run does not pay for it
    contact_sheet: bool = False
    tile_size: int = Field(128, ge=16)


class KeymorphFit(_KeymorphStage):
    """Automatic first-draft keymorphs: bounded [0, 1] morph weights whose landmark deformation matches each
    keyshape's (``fit_regions_3d`` in 3D, ``fit_keymorph_weights`` in 2D); writes the YAML an artist can edit and
    load with KeymorphFile."""

    Params = KeymorphFitParams
    inputs = _INPUTS

    def run(self, params, inputs):
        keyshapes, character = inputs["keyshapes"], inputs["character"]
        names = list(character.meta["target_names"])
        prepared = self._prepare(params, inputs)
        weights, info = self._fit(params, prepared, names)
        weights = rounded_weights(weights, params.decimals)
        errors = prepared.errors(weights)
        header = (
            "Keymorphs: expression -> keyshape id -> {morph target: weight in [0, 1]} (paper Sec 4.3).\n"
            "First draft fitted by KeymorphFit to the keyshapes' landmarks: edit freely and load it with\n"
            "stages.retarget.keymorphs:KeymorphFile. Targets left out are 0; {} is the neutral face.\n"
            + textwrap.fill("Character targets: " + ", ".join(names), 110, subsequent_indent="  ")
        )
        yaml_text = format_keymorph_yaml(
            list(keyshapes.meta["labels"]),
            keyshapes["keyshape_expression"],
            keyshapes["keyshape_index"],
            weights,
            names,
            comments=self._yaml_comments(keyshapes, errors),
            header=header,
            decimals=params.decimals,
        )
        unknown = [p for p in params.exclude if not matching_targets(names, [p]).any()]
        meta = {
            "fit": {
                "usable_targets": info["usable_targets"],
                "regions": info.get("regions", {}),
                "iterations": info["iterations"],
                "unmatched_exclude_patterns": unknown,
            },
            "morph_regions": info.get("morph_regions")
            or morph_decomposition_regions(names, list(params.regions), list(params.exclude)),
        }
        return self._common(params, inputs, prepared, weights, yaml_text, {"fit_kkt_max": info["kkt_max"]}, meta)

    @staticmethod
    def _fit(params, prepared: Prepared, names: list[str]) -> tuple[np.ndarray, dict]:
        regularisers = {
            "l2": params.l2,
            "l1": params.l1,
            "symmetry": params.symmetry,
            "antagonists": [tuple(p) for p in params.antagonists],
            "antagonism": params.antagonism,
        }
        if prepared.space == "3d":
            weights, info = fit_regions_3d(
                prepared.rig3d,
                prepared.deformation,
                names,
                list(params.regions),
                exclude=list(params.exclude),
                correctives=[tuple(p) for p in params.correctives],
                robust_iod=params.robust_iod,
                l1_scaling=params.l1_scaling,
                **regularisers,
            )
            info["usable_targets"] = [n for region in info["regions"].values() for n in region]
            return weights, info
        return fit_keymorph_weights(
            prepared.rig,
            prepared.shapes,
            names,
            exclude=list(params.exclude) + [c for c, _ in params.correctives],
            contour_weight=params.contour_weight,
            pose=prepared.pose,
            **regularisers,
        )


class KeymorphFile(_KeymorphStage):
    """Artist-authored keymorphs from a YAML file (``expression -> keyshape id -> {morph target: weight}``)."""

    class Params(Stage.Params):
        #: keyshapes the file does not mention get the neutral face instead of an error
        allow_missing: bool = False
        #: measure the landmark error in 3D when the keyshapes have it (auto), or on the 2D front view
        space: Literal["auto", "3d", "2d"] = "auto"
        #: measure the landmark error net of the actor's head rotation (2D; needs the tracks input)
        pose_correction: bool = True
        #: which morphs each decomposition region drives in the blend (see KeymorphFit)
        regions: list[FitRegion] = DEFAULT_FIT_REGIONS
        contact_sheet: bool = False
        tile_size: int = Field(128, ge=16)

    inputs = dict(_INPUTS, keymorphs=Input.files(doc="the keymorph YAML"))

    def run(self, params, inputs):
        files = inputs["keymorphs"] or {}
        if len(files) != 1:
            raise UserError(f"give exactly one keymorph YAML file, got {len(files)}", field="inputs.keymorphs")
        path = Path(next(iter(files.values())))
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise UserError(f"cannot read keymorph file ({exc})", file=str(path), field="inputs.keymorphs") from None
        keyshapes, character = inputs["keyshapes"], inputs["character"]
        names = list(character.meta["target_names"])
        labels = list(keyshapes.meta["labels"])
        expression = np.asarray(keyshapes["keyshape_expression"])
        counts = [int((expression == s).sum()) for s in range(len(labels))]
        weights = parse_keymorph_yaml(text, labels, counts, names, file=str(path), allow_missing=params.allow_missing)
        yaml_text = format_keymorph_yaml(
            labels,
            expression,
            keyshapes["keyshape_index"],
            weights,
            names,
            comments=self._yaml_comments(keyshapes),
            header=f"Keymorphs read from {path.name}",
            decimals=None,
        )
        meta = {"source": path.name, "morph_regions": morph_decomposition_regions(names, list(params.regions), [])}
        return self._common(params, inputs, self._prepare(params, inputs), weights, yaml_text, {}, meta)
