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

This module holds the two stages; the fit's maths is in ``stages.retarget.morph_fit`` (2D, and the bounded and
robust solvers) and ``stages.retarget.region_fit`` (3D, region by region), the YAML in
``stages.retarget.keymorph_yaml``, the contact sheet and figures in ``stages.retarget.contact_sheet``.
"""

from __future__ import annotations

import textwrap
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field

from msflow import Input, Output, Result, Stage, UserError
from stages.retarget.contact_sheet import (
    build_contact_sheet,
    check_tracks,
    encode_png,
    figure_contact_sheet,
    figure_landmark_fit,
)
from stages.retarget.face_measures import inter_ocular_distance, lip_gap_iod
from stages.retarget.keymorph_yaml import format_keymorph_yaml, parse_keymorph_yaml, rounded_weights
from stages.retarget.morph_fit import LandmarkRig, fit_keymorph_weights, landmark_errors, matching_targets
from stages.retarget.region_fit import (
    DEFAULT_FIT_REGIONS,
    FitRegion,
    Rig3D,
    fit_regions_3d,
    matching_any_case,
    points_not_in_keyshapes,
    regions_by_motion,
)

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


def contact_bounds(lip_gaps: np.ndarray, names: list[str], contact_morphs: list[str], gap: float | None) -> np.ndarray:
    """Upper bounds (K, M) of the keymorph weights: 1, but 0 for the lip-contact morphs (``contact_morphs``,
    fnmatch patterns) of the keyshapes whose inner-lip gap ``lip_gaps`` (K,) / IOD is above ``gap`` (lips apart:
    nothing to press). ``gap`` None bounds nothing."""
    bounds = np.ones((len(lip_gaps), len(names)))
    if gap is not None:
        bounds[np.ix_(np.asarray(lip_gaps) > gap, matching_any_case(names, contact_morphs))] = 0.0
    return bounds


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
            diff = (self.rig3d.motion(weights) - self.deformation)[:, :68]
            return np.sqrt((diff**2).sum(-1).mean(-1)) / self.rig3d.iod
        return landmark_errors(self.rig, self.shapes, weights, self.scale, self.pose)

    def landmarks(self, weights: np.ndarray) -> np.ndarray:
        """The character's landmarks under each keymorph in the keyshapes' frame (3D: head frame from the front)."""
        if self.space != "3d":
            return self.rig.keymorph_landmarks(weights, self.pose)
        from stages.retarget.shapes3d import front_view

        motion = self.rig3d.motion(weights)[:, :68]
        out = np.empty_like(motion)
        for k, rest in enumerate(self.rests3d[:, :68]):
            out[k] = rest + self.rig3d.to_character(rest).inverse_linear(motion[k])
        return front_view(out)

    def lip_gaps(self) -> np.ndarray:
        """Each keyshape's inner-lip gap / IOD (``lip_gap_iod``, in 3D seen from the front)."""
        return lip_gap_iod(self.reference())

    def reference(self) -> np.ndarray:
        """The keyshapes as ``landmarks`` draws them."""
        if self.space != "3d":
            return self.shapes
        from stages.retarget.shapes3d import front_view

        return front_view(self.keyshapes3d[:, :68])


class _KeymorphStage(Stage):
    cheap = True
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
            mesh = (character["neutral"], character["deltas"], character["landmark_ids"])
            shapes3d = np.asarray(keyshapes["keyshapes3d"], np.float64)
            rests3d = np.asarray(keyshapes["keyshape_rest3d"], np.float64)
            if "keyshape_cheeks3d" in keyshapes and "keyshape_cheek_rest3d" in keyshapes:
                shapes3d = np.concatenate([shapes3d, np.asarray(keyshapes["keyshape_cheeks3d"], np.float64)], 1)
                rests3d = np.concatenate([rests3d, np.asarray(keyshapes["keyshape_cheek_rest3d"], np.float64)], 1)
            rig3d = Rig3D.build_with_points_near(*mesh, rests3d)
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
    #: morphs that press the lips together (fnmatch patterns): held at 0 in a keyshape whose lips are apart, so
    #: they never stand in for another shape there (CREMA-D fear: mouthPress 0.25-0.45 with the lips 0.2 IOD
    #: apart, holding the chin up against the jaw; an ARKit rig shows pressed lips over an open mouth)
    contact_morphs: list[str] = ["mouthPress*"]
    #: a keyshape's lips are apart above this inner-lip gap (IOD; twice the closure gap of the evaluation); None:
    #: contact morphs everywhere, as before
    contact_gap: float | None = Field(0.06, gt=0)
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
        params, placed = self._place_unnamed_morphs(params, prepared, names)
        weights, info = self._fit(params, prepared, names)
        if not info.get("usable_targets") and not weights.any():
            raise UserError(
                f"none of the character's {len(names)} morphs moves the face's landmarks in a fit region: the face "
                "would never move (check the character's landmark vertices, or name its morphs in "
                "keymorphs.regions[].morphs)",
                field="inputs.character",
            )
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
        no_contact = [p for p in params.contact_morphs if not matching_any_case(names, [p]).any()]
        meta = {
            "fit": {
                "usable_targets": info["usable_targets"],
                "regions": info.get("regions", {}),
                "iterations": info["iterations"],
                "unmatched_exclude_patterns": unknown,
                "unmatched_contact_patterns": no_contact,
                "points_not_in_keyshapes": info.get("points_not_in_keyshapes", {}),
            },
            "morph_regions": info.get("morph_regions")
            or morph_decomposition_regions(names, list(params.regions), list(params.exclude)),
        }
        metrics = {"fit_kkt_max": info["kkt_max"], "contact_held_keyshapes": float(info["lips_apart"])}
        if placed:
            meta["fit"]["regions_by_motion"] = placed
        result = self._common(params, inputs, prepared, weights, yaml_text, metrics, meta)
        result.warnings += _placement_warnings(placed, len(names))
        return result

    @staticmethod
    def _place_unnamed_morphs(params, prepared: Prepared, names: list[str]) -> tuple[Any, dict[str, str]]:
        """``params`` with the regions grown by ``region_fit.regions_by_motion`` (3D fit only), and the placed."""
        if prepared.space != "3d":
            return params, {}
        excluded = matching_any_case(names, list(params.exclude))
        regions, placed = regions_by_motion(
            list(params.regions), names, prepared.rig3d.deltas, excluded, prepared.rig3d.iod
        )
        return (params.model_copy(update={"regions": regions}) if placed else params), placed

    @staticmethod
    def _fit(params, prepared: Prepared, names: list[str]) -> tuple[np.ndarray, dict]:
        bounds = contact_bounds(prepared.lip_gaps(), names, list(params.contact_morphs), params.contact_gap)
        if prepared.space == "3d":
            missing = points_not_in_keyshapes(params.regions, prepared.deformation.shape[1])
            for region in params.regions:
                if len(missing.get(region.name, [])) == len(region.landmarks):
                    raise UserError(
                        f"fit region '{region.name}' has none of its landmarks in the keyshapes: points 68 and up "
                        "are the FaceMesh cheek points, which these keyshapes do not carry (rerun the keyshapes "
                        "stage with the tracking's FaceMesh, or give the region iBUG points 0-67)",
                        field="params.regions",
                    )
            weights, info = fit_3d(params, prepared.rig3d, prepared.deformation, names, bounds)
            info["usable_targets"] = [n for region in info["regions"].values() for n in region]
        else:
            weights, info = fit_keymorph_weights(
                prepared.rig,
                prepared.shapes,
                names,
                exclude=list(params.exclude) + [c for c, _ in params.correctives],
                contour_weight=params.contour_weight,
                pose=prepared.pose,
                upper=bounds,
                **regularisers(params),
            )
        info["lips_apart"] = int((bounds < 1).any(axis=1).sum())
        return weights, info


def regularisers(params: KeymorphFitParams) -> dict:
    """The penalties of the keymorph fit (``morph_fit.bounded_fit``) from the stage's params."""
    return {
        "l2": params.l2,
        "l1": params.l1,
        "symmetry": params.symmetry,
        "antagonists": [tuple(p) for p in params.antagonists],
        "antagonism": params.antagonism,
    }


def fit_3d(params: KeymorphFitParams, rig3d: Rig3D, deformation: np.ndarray, names: list[str], bounds: np.ndarray):
    """The 3D keymorph fit as the stage makes it (``region_fit.fit_regions_3d`` with its regions, correctives,
    Huber's loss, L1 scaling and penalties from ``params``) of ``deformation`` (K, P, 3; character units), within
    ``bounds`` (K, M: ``contact_bounds``)."""
    return fit_regions_3d(
        rig3d,
        deformation,
        names,
        list(params.regions),
        exclude=list(params.exclude),
        correctives=[tuple(p) for p in params.correctives],
        robust_iod=params.robust_iod,
        upper=bounds,
        l1_scaling=params.l1_scaling,
        **regularisers(params),
    )


def _placement_warnings(placed: dict[str, str], morphs: int) -> list[str]:
    """The warning of a character whose morphs ``regions_by_motion`` placed ({morph: region}); [] when none."""
    if not placed:
        return []
    counts = ", ".join(f"{r} {list(placed.values()).count(r)}" for r in dict.fromkeys(placed.values()))
    return [
        f"no morph of the character is named as the fit regions expect (jaw*, mouth*, eyeBlink*, brow*, ...): "
        f"{len(placed)} of its {morphs} morphs placed by the landmarks they move ({counts}; meta "
        "fit.regions_by_motion); name them in keymorphs.regions[].morphs to choose, and map them to ARKit columns "
        "with export.arkit_aliases"
    ]


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
