"""The keyshape stages: ``Keyshapes`` (keyshapes of the training expressions, the edited sequences decomposed onto
them) and ``CaptureKeyshapes`` (performance capture: each tracked take's keyshapes, every tracked frame decomposed
onto its own take's), with their params, outputs, meta and metrics, and the rest poses and 3D keyshapes they add.

The keyshape selection (paper Sec 4.1, PCA-extreme frames) is in ``stages.retarget.keyshape_selection``, the
non-negative decomposition x^(s)(t) ~ sum_i w_i(t) B_i^(s), w_i >= 0 (Eq 8) in ``stages.retarget.decomposition``.

Distances are measured in the aam mean-shape frame relative to the inter-ocular distance (outer eye corners,
iBUG points 36 and 45, the 300-W convention) of the mean training shape, so thresholds and residuals do not
depend on the aam's choice of units.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from msflow import Input, Output, Result, Stage, UserError
from stages.retarget.decomposition import DECOMPOSITION_REGIONS, decompose, decompose_targets
from stages.retarget.face_measures import (
    inter_ocular_distance,
    level,
    lip_gap_iod,
    relative_rms_error,
    rest_frames,
    rest_pose,
)
from stages.retarget.keyshape_figures import figure_keyshapes, figure_residual, figure_weights
from stages.retarget.keyshape_selection import KeyshapeSet, select_all_keyshapes

# ----------------------------------------------------------------------------------------------------- stage

KEYSHAPES_OUTPUTS = {
    "keyshapes": Output.array(
        "f",
        shape=("total_k", 68, 2),
        dtype="float32",
        doc="keyshape landmark shapes in the aam mean-shape frame (or the head frame seen from the front), "
        "grouped by expression",
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
    "region_weights": Output.array(
        "f",
        shape=("targets", "frames", "regions", "total_k"),
        dtype="float32",
        optional=True,
        doc="the same, solved region by region (meta['regions']; params.regions)",
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
    "lip_gap": Output.array(
        "f",
        shape=("targets", "frames"),
        dtype="float32",
        optional=True,
        doc="vertical inner-lip gap / inter-ocular distance of the decomposed shapes (the blend's lip seal reads it)",
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
    "keyshape_rest": Output.array(
        "f",
        shape=("total_k", 68, 2),
        dtype="float32",
        optional=True,
        doc="each keyshape's own rest pose, when the keyshapes come from several performers",
    ),
    "keyshapes3d": Output.array(
        "f",
        shape=("total_k", 68, 3),
        dtype="float32",
        optional=True,
        doc="the keyshapes in 3D from the tracked FaceMesh, head frame (pose removed), IOD units",
    ),
    "keyshape_rest3d": Output.array(
        "f",
        shape=("total_k", 68, 3),
        dtype="float32",
        optional=True,
        doc="each keyshape's rest pose in 3D (same frame)",
    ),
    "keyshape_cheeks3d": Output.array(
        "f",
        shape=("total_k", 12, 3),
        dtype="float32",
        optional=True,
        doc="the FaceMesh cheek points (stages.retarget.movements.EXTRA_VERTICES) of each 3D keyshape, same frame",
    ),
    "keyshape_cheek_rest3d": Output.array(
        "f",
        shape=("total_k", 12, 3),
        dtype="float32",
        optional=True,
        doc="the cheek points of each keyshape's rest pose in 3D (same frame)",
    ),
    "expression_mean": Output.array(
        "f", shape=("labels", 68, 2), dtype="float32", doc="mean training shape per expression"
    ),
    "sequence": Output.array(
        "i", shape=("frames",), dtype="int32", optional=True, doc="take of each decomposed frame (meta test_labels)"
    ),
}


class KeyshapeParams(Stage.Params):
    """Keyshape selection and decomposition settings shared by both implementations."""

    #: keyshapes per expression (paper: about 20); a mapping gives each expression its own count
    k: int | dict[str, int] = 20
    #: drop a candidate whose mean squared landmark distance to a chosen keyshape, in units of the squared
    #: inter-ocular distance, is below this (1e-4: 1% of the inter-ocular distance RMS)
    dedupe_threshold: float = Field(1e-4, ge=0)
    #: keep searching further PCA axes until k keyshapes are found (the paper stops at k/2 axes)
    refill: bool = False
    #: NNLS solver: exact per-frame Lawson-Hanson (scipy, the fastest at these sizes), the same batched over frames
    #: (active_set), or FISTA with a KKT stopping rule
    solver: Literal["scipy", "active_set", "fista"] = "scipy"
    #: soft sum-to-one prior on the weights (0 = off, the paper's plain NNLS)
    sum_to_one: float = Field(0.0, ge=0)
    #: temporal smoothing of the weights across frames (0 = off)
    smoothing: float = Field(0.0, ge=0)
    #: also decompose region by region (mouth with jaw, eyes, brows): each region gets its own weights, so a
    #: mouth shape is not traded against an eyebrow (false: the paper's whole-face Eq 8 only)
    regions: bool = True
    #: expression whose closed-mouth frames define the rest pose (falls back to all frames if absent)
    rest_expression: str = "neutral"
    #: where the brows rest (``rest_pose``): at the mean of the rest take's closed-mouth frames like the mouth
    #: (``closed_mouth``), or at their median over the rest take (``median``: for a neutral speaker whose brows rise
    #: at the pauses; a take that holds an expression, such as fear's raised brows, would rest in it, and its
    #: neutral frames read as the opposite: docs/retarget.md, "The rest pose")
    brow_rest: Literal["closed_mouth", "median"] = "closed_mouth"
    #: Eq 8 on the shapes as they are (``absolute``, the paper's: a frame's weights sum to about 1) or on their
    #: deformations from the rest pose, frames and keyshapes alike (``from_rest``: a frame exactly at rest gets no
    #: weight, any mix of the keyshapes' deformations is reached, but the weights are unbounded in sum; on the
    #: talking heads it moved more morphs at once and fitted slightly worse, docs/retarget.md)
    decomposition: Literal["absolute", "from_rest"] = "absolute"

    @field_validator("k")
    @classmethod
    def _positive_counts(cls, k):
        counts = {"k": k} if isinstance(k, int) else dict(k)
        bad = {name: count for name, count in counts.items() if count < 1}
        if bad:
            raise ValueError(f"k must be at least 1 for every expression, got {bad}")
        return k


def keyshape_counts(k, labels: list[str]) -> dict[str, int]:
    """Keyshapes per expression from params.k (one count, or one per expression: all and only the labels)."""
    if isinstance(k, int):
        return {label: k for label in labels}
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
    return {label: int(k[label]) for label in labels}


def _select_or_fail(
    params,
    shapes: np.ndarray,
    sequence: np.ndarray,
    labels: list[str],
    usable: np.ndarray,
    scale: float,
    *,
    field: str,
    hint: str = "",
) -> KeyshapeSet:
    """``select_all_keyshapes`` with the stage's settings; a group without usable frames is the user's error, on
    ``field`` (its message followed by ``hint``)."""
    counts = keyshape_counts(params.k, labels)
    try:
        return select_all_keyshapes(
            shapes, sequence, labels, counts, usable,
            dedupe_threshold=params.dedupe_threshold, scale=scale, refill=params.refill,
        )  # fmt: skip
    except ValueError as exc:
        raise UserError(f"{exc}{hint}", field=field) from None


def _regions_meta(params) -> dict[str, list[int]]:
    """meta['regions']: the decomposition regions' landmarks when the stage decomposes region by region."""
    return {name: list(points) for name, points in DECOMPOSITION_REGIONS.items()} if params.regions else {}


def keyshape_arrays(selection: KeyshapeSet, shapes: np.ndarray) -> dict[str, np.ndarray]:
    """The selection as output arrays (the keyshapes' own shapes from ``shapes``)."""
    return {
        "keyshapes": shapes[selection.frames].astype(np.float32),
        "keyshape_expression": selection.expression.astype(np.int32),
        "keyshape_index": selection.index.astype(np.int32),
        "keyshape_frame": selection.frames.astype(np.int32),
        "keyshape_axis": selection.axes.astype(np.int32),
        "keyshape_extreme": selection.extremes.astype(np.int8),
    }


def selection_meta(selection: KeyshapeSet, labels: list[str], scale: float) -> dict:
    return {
        "labels": labels,
        "keyshape_counts": [int((selection.expression == s).sum()) for s in range(len(labels))],
        "keyshape_ids": [f"{labels[e]}/{i}" for e, i in zip(selection.expression, selection.index)],
        "inter_ocular_distance": scale,
        "dropped": selection.dropped,
        "variance_covered": selection.variance_covered,
    }


def decomposition_metrics(residual: np.ndarray, targets: list[str], kkt: float, selection: KeyshapeSet) -> dict:
    metrics = {
        "residual_rms_iod": float(np.sqrt(np.mean(residual**2))) if residual.size else 0.0,
        "residual_max_iod": float(residual.max(initial=0.0)),
        "keyshapes": int(len(selection.frames)),
        "duplicates_dropped": int(sum(len(v) for v in selection.dropped.values())),
        "kkt_max": kkt,
    }
    for t, name in enumerate(targets):
        metrics[f"residual_rms_iod_{name}"] = float(np.sqrt(np.mean(residual[t] ** 2)))
    return metrics


def head_frame_keyshapes(
    tracks, frames: np.ndarray, rest: np.ndarray, brow_rest: str, typical: np.ndarray
) -> dict[str, np.ndarray]:
    """3D keyshapes and their (common) rest pose from the tracked FaceMesh at the keyshapes' source frames: the
    ``rest`` frames, the brows as ``brow_rest`` says over the ``typical`` ones (``rest_pose``). Empty without a
    mesh."""
    if tracks is None or "mesh" not in tracks:
        return {}
    from stages.retarget.movements import EXTRA_VERTICES
    from stages.retarget.shapes3d import head_frame_shapes

    mesh = np.asarray(tracks["mesh"], np.float64)
    reach = max(frames.max(initial=0), rest.max(initial=0), typical.max(initial=0))
    if reach >= len(mesh):
        raise UserError(
            f"keyshape source frames reach {int(reach)} but the tracking input has "
            f"{len(mesh)} frames: wire the training tracking the aam was built from",
            field="inputs.tracks",
        )
    shapes = head_frame_shapes(mesh, EXTRA_VERTICES)
    pose = np.broadcast_to(rest_pose(shapes, rest, brow_rest, typical), (len(frames), *shapes.shape[1:]))
    return split_cheeks(shapes[frames], pose)


def split_cheeks(keyshapes: np.ndarray, rests: np.ndarray) -> dict[str, np.ndarray]:
    """The 3D keyshape outputs from keyshapes and their rests with the cheek points after the 68 (K, 68 + 12, 3)."""
    return {
        "keyshapes3d": keyshapes[:, :68].astype(np.float32),
        "keyshape_rest3d": rests[:, :68].astype(np.float32),
        "keyshape_cheeks3d": keyshapes[:, 68:].astype(np.float32),
        "keyshape_cheek_rest3d": rests[:, 68:].astype(np.float32),
    }


class Keyshapes(Stage):
    """Keyshapes per training expression (PCA extremes, Sec 4.1) and NNLS weights of the edited sequences (Eq 8).

    Inputs: ``aam`` (aligned_shapes, sequence, meta labels) gives the training shapes of each expression;
    ``edit`` (shapes (targets, frames, 68, 2), meta targets) the sequences edited towards each expression; optional
    ``tracks``, the training tracking with its FaceMesh, gives the keyshapes in 3D for the keymorph fit. Each
    edited target is decomposed into the keyshapes of the training expression of the same name.

    The edited frames stay 2D: the edit re-expresses 2D shapes, and their depth is the one their keyshape
    combination implies (each keyshape is a real tracked frame with FaceMesh depth, and its keymorph was fitted
    in 3D), so no 2D-to-3D regression is learned.
    """

    cheap = True

    Params = KeyshapeParams
    inputs = {
        "aam": Input.artifact("aligned_shapes", "sequence", doc="aam artifact of the training takes"),
        "edit": Input.artifact("shapes", doc="edit artifact: shapes (targets, frames, 68, 2), meta targets"),
        "tracks": Input.artifact(
            "mesh", optional=True, doc="training tracking (FaceMesh): 3D keyshapes for the keymorph fit"
        ),
    }
    outputs = KEYSHAPES_OUTPUTS

    def run(self, params, inputs):
        aligned, sequence, labels, usable, scale = self._training(inputs["aam"])
        targets, edited = self._edited(inputs["edit"], labels)
        selection = _select_or_fail(params, aligned, sequence, labels, usable, scale, field="inputs.aam")
        keyshapes = aligned[selection.frames]
        rest_label, candidates, rest_idx, rest = self._rest(params, aligned, sequence, labels, usable)
        offset = rest if params.decomposition == "from_rest" else 0.0
        groups = np.repeat(np.array([labels.index(t) for t in targets])[:, None], edited.shape[1], axis=1)
        weights, region_weights, reconstruction, residual, kkt = decompose_targets(
            edited, groups, keyshapes, selection, params, scale, rests=(offset, offset)
        )
        train = decompose(aligned[usable], sequence[usable], keyshapes, selection.expression, None, offset, offset)
        train_residual = relative_rms_error(train.reconstruction, aligned[usable], scale)
        arrays = keyshape_arrays(selection, aligned)
        arrays.update(
            weights=weights.astype(np.float32),
            reconstruction=reconstruction.astype(np.float32),
            residual=residual.astype(np.float32),
            lip_gap=lip_gap_iod(edited).astype(np.float32),
            rest_shape=rest.astype(np.float32),
            rest_frames=rest_idx.astype(np.int32),
            expression_mean=np.stack([aligned[(sequence == s) & usable].mean(0) for s in range(len(labels))]).astype(
                np.float32
            ),
            **head_frame_keyshapes(inputs.get("tracks"), selection.frames, rest_idx, params.brow_rest, candidates),
        )
        if region_weights is not None:
            arrays["region_weights"] = region_weights.astype(np.float32)
        metrics = decomposition_metrics(residual, targets, kkt, selection)
        metrics["train_residual_rms_iod"] = float(np.sqrt(np.mean(train_residual**2)))
        meta = self._meta(params, inputs, selection, labels, scale, targets, rest_label)
        return Result(arrays, meta=meta, metrics=metrics)

    @staticmethod
    def _rest(params, aligned, sequence, labels, usable):
        """The rest pose of the training shapes: the rest expression's label (None when it is not a training
        expression: then every usable frame is a candidate), the candidate frames, the closed-mouth rest frames
        among them and their pose."""
        rest_label = params.rest_expression if params.rest_expression in labels else None
        candidates = np.flatnonzero(usable & ((sequence == labels.index(rest_label)) if rest_label else True))
        rest_idx = candidates[rest_frames(aligned[candidates])]
        rest = rest_pose(aligned, rest_idx, params.brow_rest, candidates)
        return rest_label, candidates, rest_idx, rest

    @staticmethod
    def _meta(params, inputs, selection, labels, scale, targets, rest_label) -> dict:
        """The stage's meta: the selection's, then the targets and the settings the decomposition used."""
        meta = selection_meta(selection, labels, scale)
        meta.update(
            targets=targets,
            target_expression=[labels.index(name) for name in targets],
            rest_expression=rest_label,
            decomposition=params.decomposition,
            regions=_regions_meta(params),
            fps=inputs["edit"].meta.get("fps", inputs["aam"].meta.get("fps")),
            space="2d",
        )
        return meta

    @staticmethod
    def _training(aam):
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
        scale = float(inter_ocular_distance(aligned[usable].mean(axis=0)))
        if not scale > 0:
            raise UserError("the mean training shape has zero inter-ocular distance", field="inputs.aam")
        return aligned, sequence, labels, usable, scale

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


# ------------------------------------------------------------------------------------------ performance capture


def speaker_groups(labels: list[str], fields: dict) -> list[str]:
    """Who performs each take: the take's ``speaker`` field, else the take itself."""
    return [str((fields.get(label) or {}).get("speaker", f"take:{label}")) for label in labels]


def capture_rest_frames(
    shapes: np.ndarray, sequence: np.ndarray, usable: np.ndarray, labels: list[str], fields: dict, rest_expression: str
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per take, the rest frames of its performer: the closed-mouth frames of the performer's take whose
    ``expression`` field is ``rest_expression`` when there is one, else of all the performer's takes; and the
    frames they were picked from (where the brows' rest is taken, ``rest_pose``)."""
    speakers = speaker_groups(labels, fields)
    rests, typical = [], []
    for s in range(len(labels)):
        mine = [i for i, speaker in enumerate(speakers) if speaker == speakers[s]]
        neutral = [i for i in mine if (fields.get(labels[i]) or {}).get("expression") == rest_expression]
        candidates = np.flatnonzero(np.isin(sequence, neutral or mine) & usable)
        rests.append(candidates[rest_frames(shapes[candidates])])
        typical.append(candidates)
    return rests, typical


class CaptureKeyshapes(Stage):
    """Performance capture without the edit: keyshapes of each tracked take (PCA extremes, Sec 4.1) and every
    tracked frame decomposed into its own take's keyshapes (Eq 8), in 3D when the tracking has a FaceMesh (head
    frame, pose removed; ``stages.retarget.shapes3d``), else on the 2D landmarks aligned by similarity.

    One target, ``performance``: all takes' frames in tracking order. Each take's keymorphs measure deformation
    from its performer's rest (``speaker`` field of the takes; the ``rest_expression`` take of a performer when
    the takes carry ``expression`` fields).
    """

    cheap = True

    class Params(KeyshapeParams):
        #: fit in 3D from the FaceMesh (auto: when the tracking has one) or on the 2D landmarks
        space: Literal["auto", "3d", "2d"] = "auto"

    inputs = {
        "tracks": Input.artifact("landmarks", "sequence", doc="tracking artifact of the takes to animate"),
    }
    outputs = KEYSHAPES_OUTPUTS
    figures = {"keyshapes": figure_keyshapes, "residual": figure_residual, "weights": figure_weights}

    def run(self, params, inputs):
        tracks = inputs["tracks"]
        points, flat, sequence, labels, usable, space = self._shapes(params, tracks)
        shapes = points[:, :68]  # 3D: the cheek points after the 68 are for the keymorph fit only
        fields = dict(tracks.meta.get("fields") or {})
        selection = _select_or_fail(
            params, shapes, sequence, labels, usable, 1.0, field="inputs.tracks", hint=" (no tracked face)"
        )
        keyshapes = shapes[selection.frames]
        rests, typical = capture_rest_frames(shapes, sequence, usable, labels, fields, params.rest_expression)
        rest_points = np.stack([rest_pose(points, r, params.brow_rest, u) for r, u in zip(rests, typical)])
        poses = rest_points[:, :68]
        from_rest = params.decomposition == "from_rest"
        weights, region_weights, reconstruction, residual, kkt = decompose_targets(
            shapes[None], sequence[None], keyshapes, selection, params, 1.0,
            rests=(poses[sequence][None], poses[selection.expression]) if from_rest else (0.0, 0.0),
        )  # fmt: skip
        arrays = self._pack_arrays(
            selection, points, flat, space, rest_points, rests, params.brow_rest, typical, sequence
        )  # fmt: skip
        arrays.update(
            weights=weights.astype(np.float32),
            reconstruction=flat_view(reconstruction, space).astype(np.float32),
            residual=residual.astype(np.float32),
            lip_gap=lip_gap_iod(level(tracks["landmarks"]))[None].astype(np.float32),
        )
        if region_weights is not None:
            arrays["region_weights"] = region_weights.astype(np.float32)
        meta = self._meta(params, tracks, selection, labels, space, fields)
        metrics = decomposition_metrics(residual, ["performance"], kkt, selection)
        metrics["invalid_frames"] = int((~usable).sum())
        return Result(arrays, meta=meta, metrics=metrics)

    @staticmethod
    def _meta(params, tracks, selection, labels, space, fields) -> dict:
        """The stage's meta: the selection's, then the one ``performance`` target over the takes, the settings
        the decomposition used and the takes' frame rates and fields."""
        fps = [float(f) for f in (tracks.meta.get("fps") or [30.0])]
        meta = selection_meta(selection, labels, 1.0)
        meta.update(
            targets=["performance"],
            target_expression=[-1],
            test_labels=labels,
            rest_expression=params.rest_expression,
            decomposition=params.decomposition,
            regions=_regions_meta(params),
            fps=fps[0],
            take_fps=fps,
            space=space,
            fields=fields,
        )
        return meta

    @staticmethod
    def _shapes(params, tracks):
        """(shapes (F, 68, d) in IOD units, in 3D with the FaceMesh cheek points after the 68; their 2D front
        view, sequence, labels, usable, space)."""
        from stages.retarget.shapes3d import front_view, head_frame_shapes, remove_pose

        landmarks = np.asarray(tracks["landmarks"], np.float64)
        sequence = np.asarray(tracks["sequence"]).astype(np.int64)
        labels = [str(x) for x in tracks.meta.get("labels") or []] or [
            f"take{i}" for i in range(int(sequence.max(initial=0)) + 1)
        ]
        if params.space == "3d" and "mesh" not in tracks:
            raise UserError(
                "space: 3d needs the tracking's FaceMesh (output 'mesh'); use FaceMesh tracking or space: 2d",
                field="params.space",
            )
        space = "3d" if params.space != "2d" and "mesh" in tracks else "2d"
        usable = np.asarray(tracks["valid"]).astype(bool) if "valid" in tracks else np.ones(len(landmarks), bool)
        usable &= np.isfinite(landmarks).all(axis=(1, 2))
        if space == "3d":
            from stages.retarget.movements import EXTRA_VERTICES

            shapes = head_frame_shapes(np.asarray(tracks["mesh"], np.float64), EXTRA_VERTICES)
            return shapes, front_view(shapes[:, :68]), sequence, labels, usable, space
        shapes = remove_pose(landmarks)
        return shapes, shapes, sequence, labels, usable, space

    @staticmethod
    def _pack_arrays(selection, points, flat, space, poses, rests, brow_rest, typical, sequence) -> dict:
        """The keyshapes' outputs from the tracked ``points`` (frames, 68 [+ cheek points in 3D], d); ``poses``
        (takes, same points, d) each take's rest pose (``rest_pose`` of its ``rests`` frames, the brows as
        ``brow_rest`` says over its ``typical`` ones) in the keyshapes' space."""
        arrays = keyshape_arrays(selection, flat)
        keyshape_rest = poses[selection.expression]
        arrays["keyshape_rest"] = flat_view(keyshape_rest[:, :68], space).astype(np.float32)
        if space == "3d":
            arrays.update(split_cheeks(points[selection.frames], keyshape_rest))
        all_rest = np.concatenate(rests)
        all_typical = np.unique(np.concatenate(typical))
        arrays["rest_shape"] = rest_pose(flat, all_rest, brow_rest, all_typical).astype(np.float32)
        arrays["rest_frames"] = all_rest.astype(np.int32)
        arrays["expression_mean"] = np.stack([flat[sequence == s].mean(0) for s in range(len(rests))]).astype(
            np.float32
        )
        arrays["sequence"] = sequence.astype(np.int32)
        return arrays


def flat_view(shapes: np.ndarray, space: str) -> np.ndarray:
    """2D shapes for drawing and the 2D outputs: 3D head-frame shapes seen from the front, 2D ones as they are."""
    if space != "3d":
        return shapes
    from stages.retarget.shapes3d import front_view

    return front_view(shapes)
