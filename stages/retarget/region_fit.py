"""The keymorph fit in 3D, region by region (issue 13.1): jaw and lips, eyelids, brows, cheeks and nose, each
region's morphs fitted to its own landmarks' deformation (head frame, pose removed) less what the regions before it
explain, correctives bounded by their base morph (``robust_fit`` of ``stages.retarget.morph_fit`` per region).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from stages.retarget.face_measures import inter_ocular_distance
from stages.retarget.morph_fit import Similarity, fit_similarity, robust_fit
from stages.retarget.movements import CHEEK_VERTICES, EXTRA_VERTICES
from stages.retarget.regions import RIGID, find_morph, names_matching

#: Points of the 3D fit beyond iBUG's 68: the FaceMesh cheek vertices (``movements.EXTRA_VERTICES``) as points 68,
#: 69, ... (the keyshapes' ``keyshape_cheeks3d``); no iBUG point lies on the cheek's skin
FIT_POINTS = 68 + len(EXTRA_VERTICES)
#: the skin below each lower lid, which a cheek raise lifts (FaceMesh 346, 347, 330 / 117, 118, 101)
CHEEK_RAISE_POINTS = [68 + EXTRA_VERTICES.index(v) for side in CHEEK_VERTICES.values() for v in side["raise"]]


class FitRegion(BaseModel):
    """One region of the 3D keymorph fit: the landmarks that show it and the morphs (fnmatch patterns,
    case-insensitive) that move it; ``decomposition`` names the keyshape-decomposition region whose weights
    drive these morphs in the blend (``stages.retarget.decomposition.DECOMPOSITION_REGIONS``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    name: str
    landmarks: list[int] = Field(min_length=1)
    morphs: list[str] = Field(min_length=1)
    decomposition: Literal["mouth", "eyes", "brows"]

    @field_validator("landmarks")
    @classmethod
    def _ibug_ids(cls, landmarks):
        bad = [i for i in landmarks if not 0 <= i < FIT_POINTS]
        if bad:
            raise ValueError(
                f"landmark ids must lie in 0..67 (iBUG-68) or 68..{FIT_POINTS - 1} (the FaceMesh cheek points, "
                f"stages.retarget.movements.EXTRA_VERTICES), got {bad}"
            )
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
        name="cheeks",
        landmarks=[31, 32, 33, 34, 35, 40, 41, 46, 47, *CHEEK_RAISE_POINTS],
        morphs=["cheek*", "nose*"],
        decomposition="mouth",
    ),
]


def matching_any_case(names: list[str], patterns: list[str]) -> np.ndarray:
    """Boolean mask of the names matching any fnmatch pattern, ignoring case and separators
    (``regions.names_matching``)."""
    return names_matching(names, patterns)


#: a morph that moves no region's landmarks by this share of the eye distance (at full weight) moves none
MIN_REGION_MOTION_IOD = 0.005


def _literal_pattern(name: str) -> str:
    """An fnmatch pattern that matches ``name`` only (its wildcard characters in brackets)."""
    return "".join(f"[{ch}]" if ch in "*?[" else ch for ch in name)


def regions_by_motion(
    regions: list[FitRegion], names: list[str], deltas: np.ndarray, excluded: np.ndarray, iod: float
) -> tuple[list[FitRegion], dict[str, str]]:
    """The regions with the morphs of a character whose names match none of their patterns (``shape_07``, a
    sculptor's own names): each morph joins the region whose landmarks it moves most (RMS over the region's
    points, ``deltas`` (M, P, 3) at full weight), if at least ``MIN_REGION_MOTION_IOD`` of ``iod``. A character
    with one morph named as the patterns expect keeps the regions as given: its names are the user's to map.

    Returns the regions and {morph: region name} of the morphs placed (empty when none was)."""
    named = names_matching(names, [pattern for region in regions for pattern in region.morphs])
    if (named & ~excluded).any():
        return list(regions), {}
    points = deltas.shape[1]
    motion = np.stack(
        [
            np.sqrt((deltas[:, [i for i in region.landmarks if i < points]] ** 2).sum(-1).mean(-1))
            if any(i < points for i in region.landmarks)
            else np.zeros(len(names))
            for region in regions
        ],
        axis=1,
    )  # (M, regions)
    placed = {
        names[m]: regions[int(np.argmax(motion[m]))].name
        for m in range(len(names))
        if not excluded[m] and motion[m].max() >= MIN_REGION_MOTION_IOD * iod
    }
    grown = [
        region.model_copy(
            update={"morphs": [*region.morphs, *(_literal_pattern(n) for n, r in placed.items() if r == region.name)]}
        )
        for region in regions
    ]
    return grown, placed


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

    @classmethod
    def build_with_points_near(cls, neutral, deltas, landmark_ids, rests: np.ndarray) -> Rig3D:
        """The rig of the 68 landmark vertices followed by the character's vertices nearest to the performer's
        points beyond 68 (``rests`` (R, P, 3), head frame), each rest carried onto the character by the similarity
        of its rigid points (``to_character``) and the carried points averaged over the rests. Rests of the 68
        points alone give the rig of the 68."""
        neutral, rests = np.asarray(neutral, np.float64), np.asarray(rests, np.float64)
        landmarks = cls.build(neutral, deltas, landmark_ids)
        if rests.shape[1] <= 68:
            return landmarks
        unique = np.unique(rests.reshape(len(rests), -1), axis=0).reshape(-1, *rests.shape[1:])
        carried = np.mean([landmarks.to_character(r[:68]).apply(r[68:]) for r in unique], axis=0)
        nearest = [int(np.argmin(((neutral - p) ** 2).sum(axis=1))) for p in carried]
        return cls.build(neutral, deltas, np.concatenate([np.asarray(landmark_ids), nearest]))

    def deformations(self, keyshapes: np.ndarray, rests: np.ndarray) -> np.ndarray:
        """Each keyshape's deformation from its performer's rest, in character units and axes (K, 68, 3)."""
        keyshapes, rests = np.asarray(keyshapes, np.float64), np.asarray(rests, np.float64)
        out = np.empty_like(keyshapes)
        unique, inverse = np.unique(rests.reshape(len(rests), -1), axis=0, return_inverse=True)
        for u, rest in enumerate(unique.reshape(-1, *rests.shape[1:])):
            rows = np.flatnonzero(inverse.reshape(-1) == u)
            out[rows] = self.to_character(rest).apply_linear(keyshapes[rows] - rest)
        return out

    def motion(self, weights: np.ndarray) -> np.ndarray:
        """Landmark motion (K, 68, 3) of morph weights (K, M)."""
        return np.einsum("km,mpc->kpc", np.asarray(weights, np.float64), self.deltas)


def corrective_pairs(names: list[str], correctives) -> list[tuple[int, int]]:
    """(corrective, base) morph index pairs the character has, e.g. (mouthClose, jawOpen)."""
    found = [(find_morph(names, c), find_morph(names, b)) for c, b in correctives]
    return [(c, b) for c, b in found if c is not None and b is not None]


def points_not_in_keyshapes(regions: list[FitRegion], available: int) -> dict[str, list[int]]:
    """Per region listing points the keyshapes lack (ids >= ``available``: the cheek points, which 2D or older
    keyshapes do not carry), those points."""
    missing = {region.name: [p for p in region.landmarks if p >= available] for region in regions}
    return {name: points for name, points in missing.items() if points}


def fit_region(
    rig: Rig3D,
    targets: np.ndarray,
    points: list[int],
    columns: np.ndarray,
    names,
    pairs,
    regularisers,
    bounds,
    passes=8,
):
    """One region's bounded fit (``bounded_fit``, weights in [0, ``bounds``], (K, columns)) with correctives
    bounded by their base morph: a first pass without the correctives gives the base weights, each further pass
    bounds every corrective by its base's weight from the pass before (a joint bound u_c <= u_b is not a box),
    until the weights settle; a corrective is finally clipped to its base's final weight."""
    J = rig.deltas[columns][:, points].reshape(len(columns), -1).T
    local = {int(c): i for i, c in enumerate(columns)}
    sub_names = [names[c] for c in columns]
    mine = [(local[c], local.get(b)) for c, b in pairs if c in local]
    upper = bounds.copy()
    for c, _ in mine:
        upper[:, c] = 0.0
    sub, info = robust_fit(J, targets, sub_names, np.ones(len(columns), bool), upper=upper, **regularisers)
    if not mine:
        return sub, info
    for _ in range(passes):  # the bound u_c <= u_b, fixed from the last pass, until the base stops moving
        upper = bounds.copy()
        for c, b in mine:
            upper[:, c] = np.minimum(bounds[:, c], sub[:, b]) if b is not None else 0.0
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
    upper: np.ndarray | None = None,
    **regularisers,
) -> tuple[np.ndarray, dict]:
    """Keymorph weights fitted in 3D, region by region (issue 13.1), each region's morphs to its landmarks'
    deformation less what the regions fitted before it already move there (``fit_region``, all keyshapes at
    once), within [0, ``upper``] ((K, M) bounds; None: 1). A morph belongs to the first region whose patterns match it; a corrective whose base is fitted in an
    earlier region is bounded by the base's weight there. Returns weights (K, M) and per region the morphs it
    fitted."""
    K = len(deformation)
    bounds = np.ones((K, len(names))) if upper is None else np.asarray(upper, np.float64)
    weights = np.zeros((K, len(names)))
    explained = np.zeros_like(deformation)
    assigned = matching_any_case(names, exclude)
    pairs = corrective_pairs(names, correctives)
    info = {"regions": {}, "morph_regions": {}, "iterations": 0, "kkt_max": 0.0}
    info["points_not_in_keyshapes"] = points_not_in_keyshapes(regions, deformation.shape[1])
    regularisers = {**regularisers, "huber": None if robust_iod is None else robust_iod * rig.iod}
    for region in regions:
        columns = np.flatnonzero(matching_any_case(names, region.morphs) & ~assigned)
        assigned[columns] = True
        if not columns.size:
            info["regions"][region.name] = []
            continue
        points = [p for p in region.landmarks if p < deformation.shape[1]]
        if not points:  # KeymorphFit says so as a user error before fitting
            raise ValueError(
                f"region '{region.name}' has none of its points in the keyshapes (points 68 and up are the "
                "FaceMesh cheek points, which keyshapes from 2D tracking or older runs do not carry)"
            )
        targets = (deformation - explained)[:, points].reshape(K, -1)
        # a base fitted earlier acts as a fixed bound: pass it in as a pseudo-column the region does not fit
        region_pairs = [(c, b) for c, b in pairs if c in columns and (b in columns or assigned[b])]
        sub, sub_info = fit_region(
            rig, targets, points, columns, names, [p for p in region_pairs if p[1] in columns], regularisers,
            bounds[:, columns],
        )  # fmt: skip
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
