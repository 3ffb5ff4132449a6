"""Expression blending of the retargeted animations (paper Eq 9).

    H(t) = sum_j alpha_j(t) sum_i w_i^(j)(t) G_i^(j)

w^(j)(t): the keyshape weights of the sequence edited towards expression j (keyshapes artifact, Eq 8);
G_i^(j): the keymorph (morph-target weights) of keyshape i of expression j (keymorphs artifact, Sec 4.3);
alpha(t): barycentric coordinates over the expressions, from the params:

- constant: ``alpha: {happy: 0.5, neutral: 0.5}``;
- keyframes over time: ``alpha: {keyframes: {0.0: {neutral: 1}, 1.2: {happy: 1}}, interpolation: linear}``
  (seconds; held constant before the first and after the last keyframe);
- ``alpha: from_analysis``: alpha(t) = barycentric coordinates of the analysed expression vector e(t) (edit
  artifact ``style``) with respect to the training style vectors (bilinear artifact ``style``), projected onto
  the simplex (paper Sec 4.3: "the user-chosen barycentric coordinates of the desired output expression in
  terms of the basic expression vectors found during training").

Beyond the paper (each behind a param):

- region by region (``regions``, default on when the keyshapes and keymorphs carry regions): each morph is driven
  by the keyshape weights of its own decomposition region (mouth with jaw, eyes, brows), H_m(t) = sum_j alpha_j
  sum_i w_i^(j, r(m))(t) G_im^(j);
- lip seal (``lip_seal``, needs the character): where the decomposed shapes' lips close, the weights that open the
  character's lips are lowered until its gap is the performer's (stages.retarget.lips);
- eyes (``eyes: tracking``, needs the performer's tracking of the animated take): blink morphs from the eyelid
  aperture and eyeLook morphs from the gaze (stages.retarget.eyes); the gaze itself is the optional ``gaze``
  output, for eye joints and Live Link eye angles.

The result is clipped to [0, 1] (the range of a morph-target slider); how much was clipped is a metric.
"""

from __future__ import annotations

import difflib
from typing import Literal, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from msflow import Input, Output, Result, Stage, UserError
from stages.geometry.held_gaps import ease_into_found_face, found_again_spans
from stages.geometry.ramps import smoothstep

ALPHA_FORMS = (
    "alpha is 'from_analysis', constant weights such as {happy: 0.5, neutral: 0.5}, or "
    "{keyframes: {seconds: {expression: weight}}, interpolation: linear|step|smooth}"
)


class AlphaKeyframes(BaseModel):
    """Expression weights at times (seconds), interpolated between them."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    keyframes: dict[float, dict[str, float]]
    interpolation: Literal["linear", "step", "smooth"] = "linear"

    @field_validator("keyframes")
    @classmethod
    def _not_empty(cls, keyframes):
        if not keyframes:
            raise ValueError("alpha keyframes are empty")
        return keyframes


def check_barycentric(weights: dict[str, float], tolerance: float, where: str) -> None:
    """Alpha weights are >= 0 and sum to 1 (within ``tolerance``): a ValueError naming ``where`` otherwise."""
    negative = {name: w for name, w in weights.items() if w < 0}
    if negative:
        raise ValueError(f"{where}: alpha weights must be >= 0, got {negative}")
    total = float(sum(weights.values()))
    if abs(total - 1.0) > tolerance:
        raise ValueError(f"{where}: alpha weights must sum to 1 (barycentric), they sum to {total:g}: {weights}")


# ------------------------------------------------------------------------------------------------------ maths


def project_to_simplex(points: np.ndarray) -> np.ndarray:
    """Euclidean projection of each row onto the probability simplex (Duchi et al. 2008), vectorised."""
    v = np.atleast_2d(np.asarray(points, np.float64))
    n = v.shape[1]
    u = -np.sort(-v, axis=1)
    cumulative = np.cumsum(u, axis=1) - 1.0
    ks = np.arange(1, n + 1)
    support = u - cumulative / ks > 0
    rho = n - 1 - np.argmax(support[:, ::-1], axis=1)  # last index where the condition holds
    theta = cumulative[np.arange(len(v)), rho] / (rho + 1)
    return np.maximum(v - theta[:, None], 0.0)


def barycentric_coordinates(points: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Affine coordinates a (sum 1) with a @ vertices closest to each point (least squares; minimum-norm when
    the vertices are affinely dependent). points (n, d), vertices (S, d) -> (n, S)."""
    points = np.atleast_2d(np.asarray(points, np.float64))
    vertices = np.asarray(vertices, np.float64)
    S = len(vertices)
    if S == 1:
        return np.ones((len(points), 1))
    # a = v_0 + (differences) beta: minimise ||(V_rest - v_0)' beta - (p - v_0)||
    base = vertices[0]
    edges = vertices[1:] - base  # (S-1, d)
    beta = (points - base) @ np.linalg.pinv(edges)  # (n, S-1)
    return np.hstack([1.0 - beta.sum(axis=1, keepdims=True), beta])


def alpha_from_analysis(style: np.ndarray, training_styles: np.ndarray) -> np.ndarray:
    """alpha(t): barycentric coordinates of e(t) w.r.t. the training style vectors, projected on the simplex."""
    return project_to_simplex(barycentric_coordinates(style, training_styles))


def interpolate_keyframes(
    times: np.ndarray, key_times: np.ndarray, key_values: np.ndarray, interpolation: str = "linear"
) -> np.ndarray:
    """Values (n, S) at ``times`` from keyframes (K,) -> (K, S); held constant outside the keyed range.

    Linear and smoothstep interpolation of simplex points stay on the simplex (convex combinations).
    """
    order = np.argsort(key_times, kind="stable")
    key_times = np.asarray(key_times, np.float64)[order]
    key_values = np.asarray(key_values, np.float64)[order]
    times = np.asarray(times, np.float64)
    if len(key_times) == 1:
        return np.repeat(key_values[:1], len(times), axis=0)
    seg = np.clip(np.searchsorted(key_times, times, side="right") - 1, 0, len(key_times) - 2)
    t0, t1 = key_times[seg], key_times[seg + 1]
    u = np.clip((times - t0) / np.maximum(t1 - t0, 1e-12), 0.0, 1.0)
    if interpolation == "step":
        u = (times >= t1).astype(np.float64)
    elif interpolation == "smooth":
        u = smoothstep(u)
    return key_values[seg] * (1.0 - u)[:, None] + key_values[seg + 1] * u[:, None]


def frame_times(sequence: np.ndarray, fps) -> np.ndarray:
    """Seconds since the first frame of each frame's own take (takes are concatenated along frames); ``fps`` one
    rate, or one per take (indexed by the sequence value)."""
    sequence = np.asarray(sequence)
    index = np.arange(len(sequence))
    starts = np.r_[0, np.flatnonzero(np.diff(sequence) != 0) + 1]
    first = starts[np.searchsorted(starts, index, side="right") - 1]
    rate = np.asarray(fps, np.float64)
    return (index - first) / (rate[sequence] if rate.ndim else float(rate))


def smooth_in_time(values: np.ndarray, sigma_frames: float) -> np.ndarray:
    """Gaussian smoothing along frames (edges held); rows of a simplex stay on it."""
    if sigma_frames <= 0:
        return values
    from scipy.ndimage import gaussian_filter1d

    return gaussian_filter1d(values, sigma_frames, axis=0, mode="nearest")


def retarget_expressions(
    keyshape_weights: np.ndarray,
    keymorph_weights: np.ndarray,
    region_weights: np.ndarray | None = None,
    morph_region: np.ndarray | None = None,
) -> np.ndarray:
    """sum_i w_i^(j)(t) G_i^(j) for every target expression j: (targets, frames, total_k) x (total_k, M).

    With ``region_weights`` (targets, frames, regions, total_k) and ``morph_region`` (M,) (region index, -1 none),
    each morph takes its own region's keyshape weights; morphs of no region the whole-face ones."""
    G = np.asarray(keymorph_weights, np.float64)
    out = np.einsum("tfk,km->tfm", np.asarray(keyshape_weights, np.float64), G)
    if region_weights is not None and morph_region is not None:
        for r in range(region_weights.shape[2]):
            columns = np.flatnonzero(np.asarray(morph_region) == r)
            out[..., columns] = np.einsum("tfk,km->tfm", np.asarray(region_weights[:, :, r], np.float64), G[:, columns])
    return out


def blend_expressions(per_expression: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """H(t) = sum_j alpha_j(t) per_expression_j(t) (paper Eq 9): (targets, frames, M), (frames, targets)."""
    return np.einsum("ft,tfm->fm", np.asarray(alpha, np.float64), per_expression)


# ---------------------------------------------------------------------------------------------------- figures


def figure_weights(view, inputs):
    """Morph-target weights over time (the targets that move)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    weights = view["weights"]
    names = view.meta["target_names"]
    time = view["time"]
    active = np.flatnonzero(weights.max(axis=0) > 0.02)
    order = active[np.argsort(-weights[:, active].max(axis=0))]
    fig, ax = plt.subplots(figsize=(9, 0.18 * max(len(order), 8) + 1.2))
    extent = (time[0], time[-1] if len(time) > 1 else 1.0, len(order) - 0.5, -0.5)
    ax.imshow(
        weights[:, order].T, aspect="auto", interpolation="nearest", cmap="viridis", vmin=0, vmax=1, extent=extent
    )
    ax.set_yticks(range(len(order)))
    ax.set_yticklabels([names[i] for i in order], fontsize=6)
    ax.set_xlabel("time (s)")
    ax.set_title(f"Blended morph weights (Eq 9), clipped fraction {view.metrics.get('clipped_fraction', 0):.3f}")
    fig.tight_layout()
    return fig


def figure_alpha(view, inputs):
    """Expression weights alpha_j(t)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    alpha = view["alpha"]
    fig, ax = plt.subplots(figsize=(7, 2.5))
    ax.stackplot(view["time"], alpha.T, labels=view.meta["expressions"])
    ax.set_ylim(0, 1)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("alpha")
    ax.set_title(f"Expression weights ({view.meta.get('alpha_mode')})")
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    return fig


# ------------------------------------------------------------------------------------------------------ stage

BLEND_OUTPUTS = {
    "weights": Output.array(
        "f",
        shape=("frames", "morphs"),
        dtype="float32",
        doc="morph-target weights per frame in [0, 1] (meta['target_names']), blink and gaze morphs included",
    ),
    "alpha": Output.array(
        "f",
        shape=("frames", "expressions"),
        dtype="float32",
        doc="expression weights alpha_j(t) (meta['expressions']), on the simplex",
    ),
    "expression_weights": Output.array(
        "f",
        shape=("expressions", "frames", "morphs"),
        dtype="float32",
        doc="the retargeted animation of each expression before blending (unclipped)",
    ),
    "time": Output.array("f", shape=("frames",), dtype="float64", doc="seconds from the first frame of the take"),
    "sequence": Output.array(
        "i",
        shape=("frames",),
        dtype="int32",
        doc="test take of each frame, index into meta['labels'] (several takes concatenated)",
    ),
    "gaze": Output.array(
        "f",
        shape=("frames", 2, 2),
        dtype="float32",
        optional=True,
        doc="eye directions, degrees [eye (0 = left)][yaw (> 0 to the performer's left), pitch (> 0 up)], "
        "from tracking: for eye joints and Live Link eye angles",
    ),
    "vertices": Output.array(
        "f",
        shape=("frames", None, 3),
        dtype="float32",
        optional=True,
        doc="posed character vertices per frame (params.vertices)",
    ),
}


class BlendParams(Stage.Params):
    #: allowed deviation of the alpha sum from 1 (before alpha: its check reads it)
    tolerance: float = Field(1e-3, gt=0)
    #: "from_analysis", constant weights {expression: weight}, or {keyframes: {seconds: {expression: w}},
    #: interpolation: linear|step|smooth}; weights must be >= 0 and sum to 1
    alpha: Union[Literal["from_analysis"], dict[str, float], AlphaKeyframes] = "from_analysis"
    #: Gaussian smoothing of alpha over time, sigma in seconds (the analysed e(t) jitters, paper Sec 7)
    alpha_smoothing: float = Field(0.0, ge=0)
    #: drive each morph by its own region's keyshape weights when the keyshapes and keymorphs carry regions
    regions: bool = True
    #: close the character's lips where the performer's close (needs the character, and the tracks input or the
    #: keyshapes' lip_gap)
    lip_seal: bool = True
    #: the seal acts below this inner-lip gap (IOD) and fades out above it
    seal_gap: float = Field(0.03, gt=0)
    #: (corrective, base) pairs the seal may raise, each up to its base's weight (lips sealed over a lowered jaw)
    seal_correctives: list[tuple[str, str]] = [("mouthClose", "jawOpen")]
    #: blinks and gaze from the performer's tracking (needs the tracks input), or from the keymorphs alone
    eyes: Literal["tracking", "keyshapes"] = "tracking"
    #: gaze angle (degrees) that an eyeLook weight of 1 stands for
    gaze_full_degrees: float = Field(30.0, gt=0)
    #: "median": the gaze relative to its median over each take: the performer's usual line of sight (the lens, for
    #: a talking head) becomes straight ahead, so the character, whose head the export levels the same way
    #: (export.head_rotation: relative), looks at the viewer; "tracked": relative to the head's straight ahead, as
    #: the tracker reads it (pair it with export.head_rotation: absolute)
    gaze_reference: Literal["median", "tracked"] = "median"
    #: where the tracker held the face through a long gap (tracks' meta gaps) and found it again, the last this many
    #: seconds of the gap ease from the held face into the found one instead of jumping in one frame; 0: the jump
    held_gap_ease: float = Field(0.25, ge=0, le=10)
    #: also output posed vertices per frame (needs the character input)
    vertices: bool = False

    @field_validator("alpha", mode="before")
    @classmethod
    def _alpha_form(cls, value):
        # one clear message instead of pydantic's per-branch union errors
        if isinstance(value, str) and value != "from_analysis":
            raise ValueError(ALPHA_FORMS)
        if isinstance(value, dict) and "keyframes" not in value:
            bad = {k: v for k, v in value.items() if isinstance(v, bool) or not isinstance(v, (int, float))}
            if bad:
                raise ValueError(f"{ALPHA_FORMS}; these weights are not numbers: {bad}")
        return value

    @field_validator("alpha")
    @classmethod
    def _alpha_is_barycentric(cls, alpha, info):
        tolerance = info.data.get("tolerance", 1e-3)
        if isinstance(alpha, AlphaKeyframes):
            for t, weights in alpha.keyframes.items():
                check_barycentric(weights, tolerance, f"keyframe {t:g}")
        elif isinstance(alpha, dict):
            check_barycentric(alpha, tolerance, "alpha")
        return alpha


class Blend(Stage):
    """Blend the per-expression retargeted animations with barycentric expression weights (paper Eq 9)."""

    cheap = True

    Params = BlendParams
    inputs = {
        "keyshapes": Input.artifact("weights", "keyshape_expression", doc="keyshapes artifact (Eq 8 weights)"),
        "keymorphs": Input.artifact("keymorph_weights", doc="keymorphs artifact (G per keyshape)"),
        "edit": Input.artifact(
            "style", optional=True, doc="edit artifact: analysed style e(t) for alpha from_analysis, and fps"
        ),
        "bilinear": Input.artifact(
            "style", optional=True, doc="bilinear artifact: training style vectors for alpha from_analysis"
        ),
        "character": Input.artifact(
            "neutral", "deltas", optional=True, doc="character: lip seal, blink mapping and params.vertices"
        ),
        "tracks": Input.artifact(
            "landmarks",
            optional=True,
            doc="tracking of the performance the blend animates: eyelid aperture (eye_aperture, else the landmarks) "
            "and gaze",
        ),
    }
    outputs = BLEND_OUTPUTS
    figures = {"weights": figure_weights, "alpha": figure_alpha}

    def run(self, params, inputs):
        data = self._validate(params, inputs)
        alpha, alpha_meta = self._alpha(params, inputs, data)
        per_expression = retarget_expressions(
            data["w"], data["G"], data["region_weights"], data["morph_region"] if params.regions else None
        )
        raw = blend_expressions(per_expression, alpha)
        result = finish_weights(params, data, raw, alpha)
        return self._pack(params, inputs, data, result, alpha, alpha_meta, per_expression, raw)

    # ---------------------------------------------------------------------------------------------- validate
    def _validate(self, params, inputs) -> dict:
        keyshapes, keymorphs, edit = inputs["keyshapes"], inputs["keymorphs"], inputs.get("edit")
        labels = list(keyshapes.meta.get("labels", []))
        targets = list(keyshapes.meta.get("targets", labels))
        w = np.asarray(keyshapes["weights"], np.float64)
        G = np.asarray(keymorphs["keymorph_weights"], np.float64)
        names = list(keymorphs.meta.get("target_names", []))
        self._check_consistency(keyshapes, keymorphs, w, G, names, targets)
        n_frames = w.shape[1]
        fps = self._fps(keyshapes, edit, n_frames)
        sequence, take_labels = self._takes(keyshapes, edit, n_frames)
        take_fps = keyshapes.meta.get("take_fps")
        time = frame_times(sequence, take_fps if take_fps and len(take_fps) > sequence.max(initial=0) else fps)
        character = inputs.get("character")
        if character is not None and len(character["deltas"]) != len(names):
            raise UserError(
                f"the character has {len(character['deltas'])} morph targets but the keymorphs were made for "
                f"{len(names)}",
                field="inputs.character",
            )
        tracks = inputs.get("tracks")
        if tracks is not None and len(tracks["landmarks"]) != n_frames:
            raise UserError(
                f"the tracking has {len(tracks['landmarks'])} frames, the keyshape weights {n_frames}: wire the "
                "tracking of the take the blend animates",
                field="inputs.tracks",
            )
        return {
            "w": w,
            "G": G,
            "names": names,
            "targets": targets,
            "fps": fps,
            "sequence": sequence,
            "take_labels": take_labels,
            "time": time,
            "character": character,
            "tracks": tracks,
            "target_gap": np.asarray(keyshapes["lip_gap"], np.float64) if "lip_gap" in keyshapes else None,
            **self._regions(keyshapes, keymorphs, names),
        }

    @staticmethod
    def _regions(keyshapes, keymorphs, names) -> dict:
        """Region weights and each morph's region index, when both artifacts carry regions."""
        regions = list((keyshapes.meta.get("regions") or {}).keys())
        morph_regions = keymorphs.meta.get("morph_regions") or {}
        if "region_weights" not in keyshapes or not regions or not morph_regions:
            return {"region_weights": None, "morph_region": None}
        index = np.array([regions.index(morph_regions[n]) if morph_regions.get(n) in regions else -1 for n in names])
        return {"region_weights": np.asarray(keyshapes["region_weights"], np.float64), "morph_region": index}

    @staticmethod
    def _takes(keyshapes, edit, n_frames) -> tuple[np.ndarray, list[str]]:
        """Which take each frame belongs to (the edit may analyse several, concatenated; capture keyshapes
        decompose every tracked take)."""
        for source in (edit, keyshapes):
            if source is not None and "sequence" in source:
                sequence = np.asarray(source["sequence"]).astype(np.int64)
                labels = list(source.meta.get("test_labels", []))
                if len(sequence) == n_frames:
                    return sequence, labels or [f"take{i}" for i in range(int(sequence.max(initial=0)) + 1)]
        labels = list(edit.meta.get("test_labels", [])) if edit is not None else []
        return np.zeros(n_frames, dtype=np.int64), labels[:1] or ["take"]

    @staticmethod
    def _check_consistency(keyshapes, keymorphs, w, G, names, targets):
        if w.ndim != 3:
            raise UserError(
                f"keyshapes weights have shape {w.shape}, expected (targets, frames, total_k)", field="inputs.keyshapes"
            )
        if G.ndim != 2 or G.shape[0] != w.shape[2]:
            raise UserError(
                f"the keymorphs have {G.shape[0] if G.ndim else 0} rows but the keyshapes artifact has "
                f"{w.shape[2]} keyshapes: the keymorphs were made for other keyshapes (re-run or "
                "re-author them)",
                field="inputs.keymorphs",
            )
        if len(names) != G.shape[1]:
            raise UserError(
                f"keymorphs meta['target_names'] has {len(names)} names for {G.shape[1]} columns",
                field="inputs.keymorphs",
            )
        ids, morph_ids = keyshapes.meta.get("keyshape_ids"), keymorphs.meta.get("keyshape_ids")
        if ids is not None and morph_ids is not None and list(ids) != list(morph_ids):
            raise UserError(
                "the keymorphs were made for different keyshapes (keyshape ids differ): re-run the "
                "keymorph stage on these keyshapes",
                field="inputs.keymorphs",
            )
        if len(targets) != w.shape[0]:
            raise UserError(
                f"keyshapes meta['targets'] names {len(targets)} expressions for {w.shape[0]} weight sets",
                field="inputs.keyshapes",
            )
        if not np.isfinite(w).all() or not np.isfinite(G).all():
            raise UserError("keyshape or keymorph weights contain NaN/Inf", field="inputs.keyshapes")

    @staticmethod
    def _fps(keyshapes, edit, n_frames) -> float:
        fps = keyshapes.meta.get("fps")
        if edit is not None:
            edit_fps = edit.meta.get("fps")
            if fps is not None and edit_fps is not None and abs(float(fps) - float(edit_fps)) > 1e-6 * float(fps):
                raise UserError(
                    f"frame-rate mismatch: keyshapes at {fps} fps, edit at {edit_fps} fps (they must "
                    "come from the same edited take)",
                    field="inputs.edit",
                )
            fps = fps if fps is not None else edit_fps
            style = edit["style"]
            if len(style) != n_frames:
                raise UserError(
                    f"frame-count mismatch: the edit has {len(style)} frames, the keyshape weights "
                    f"{n_frames} (they must come from the same edited take)",
                    field="inputs.edit",
                )
        if fps is None or not float(fps) > 0:
            raise UserError(
                "no frame rate: neither the keyshapes nor the edit artifact has meta['fps']", field="inputs.keyshapes"
            )
        return float(fps)

    # ----------------------------------------------------------------------------------------------- alpha
    def _alpha(self, params, inputs, data):
        spec, targets, time = params.alpha, data["targets"], data["time"]
        if spec == "from_analysis":
            alpha, meta = self._alpha_from_analysis(inputs, targets)
        elif isinstance(spec, AlphaKeyframes):
            key_times = np.array(sorted(spec.keyframes), dtype=np.float64)
            key_values = np.stack(
                [self._weights_vector(spec.keyframes[t], targets, f"params.alpha.keyframes.{t:g}") for t in key_times]
            )
            alpha = interpolate_keyframes(time, key_times, key_values, spec.interpolation)
            meta = {"alpha_mode": "keyframes", "alpha_interpolation": spec.interpolation}
        else:
            vector = self._weights_vector(spec, targets, "params.alpha")
            alpha = np.repeat(vector[None], len(time), axis=0)
            meta = {"alpha_mode": "constant", "alpha_constant": dict(zip(targets, vector.tolist()))}
        sequence = data["sequence"]
        for take in np.unique(sequence):  # smooth within each take, never across a cut
            rows = sequence == take
            alpha[rows] = smooth_in_time(alpha[rows], params.alpha_smoothing * data["fps"])
        return alpha, meta

    @staticmethod
    def _weights_vector(weights: dict[str, float], targets: list[str], field: str) -> np.ndarray:
        """The alpha vector over the edited expressions (the params already checked it is barycentric)."""
        unknown = [name for name in weights if name not in targets]
        if unknown:
            close = difflib.get_close_matches(unknown[0], targets, n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            raise UserError(f"unknown expressions {unknown}{hint}; the edited expressions are {targets}", field=field)
        vector = np.array([float(weights.get(name, 0.0)) for name in targets])
        return vector / vector.sum()

    @staticmethod
    def _alpha_from_analysis(inputs, targets):
        edit, bilinear = inputs.get("edit"), inputs.get("bilinear")
        if len(targets) == 1 and edit is None:  # one animation (performance capture): nothing to analyse
            n_frames = len(np.asarray(inputs["keyshapes"]["weights"])[0])
            return np.ones((n_frames, 1)), {"alpha_mode": "single target"}
        if edit is None or bilinear is None:
            missing = [n for n, v in (("edit", edit), ("bilinear", bilinear)) if v is None]
            raise UserError(
                f"alpha 'from_analysis' needs the {' and '.join(missing)} input(s) (analysed style e(t) "
                "and the training style vectors); wire them, or give constant weights such as "
                f"alpha: {{{targets[0]}: 1.0}}",
                field="params.alpha",
            )
        style = np.asarray(edit["style"], np.float64)
        training = np.asarray(bilinear["style"], np.float64)
        training_labels = list(bilinear.meta.get("labels", edit.meta.get("labels", [])))
        if training.ndim != 2 or style.ndim != 2 or training.shape[1] != style.shape[1]:
            raise UserError(
                f"style vectors do not match: edit style {style.shape}, bilinear style {training.shape}",
                field="inputs.bilinear",
            )
        if len(training_labels) != len(training):
            raise UserError(
                f"bilinear meta['labels'] names {len(training_labels)} expressions for {len(training)} style vectors",
                field="inputs.bilinear",
            )
        usable = [name for name in targets if name in training_labels]
        if not usable:
            raise UserError(
                f"none of the edited expressions {targets} is a training expression of the bilinear "
                f"model ({training_labels})",
                field="inputs.bilinear",
            )
        vertices = training[[training_labels.index(name) for name in usable]]
        coords = alpha_from_analysis(style, vertices)
        alpha = np.zeros((len(style), len(targets)))
        alpha[:, [targets.index(name) for name in usable]] = coords
        return alpha, {"alpha_mode": "from_analysis", "alpha_basis": usable}

    # ---------------------------------------------------------------------------------------------- pack
    def _pack(self, params, inputs, data, result, alpha, alpha_meta, per_expression, raw) -> Result:
        weights = result["weights"]
        excess = np.abs(raw - np.clip(raw, 0.0, 1.0))
        arrays = {
            "weights": weights.astype(np.float32),
            "alpha": alpha.astype(np.float32),
            "expression_weights": per_expression.astype(np.float32),
            "time": data["time"],
            "sequence": data["sequence"].astype(np.int32),
        }
        if result.get("gaze") is not None:
            arrays["gaze"] = result["gaze"].astype(np.float32)
        if params.vertices:
            character = data["character"]
            if character is None:
                raise UserError("params.vertices needs the character input", field="inputs.character")
            arrays["vertices"] = self._posed_vertices(character, weights)
        metrics = {
            "clipped_fraction": float((excess > 1e-6).mean()) if excess.size else 0.0,
            "clipped_amount": float(excess.mean()) if excess.size else 0.0,
            "max_weight_unclipped": float(raw.max(initial=0.0)),
            "min_weight_unclipped": float(raw.min(initial=0.0)),
            **result["metrics"],
        }
        for j, name in enumerate(data["targets"]):
            metrics[f"mean_alpha_{name}"] = float(alpha[:, j].mean()) if len(alpha) else 0.0
        meta = {
            "target_names": data["names"],
            "fps": data["fps"],
            "expressions": data["targets"],
            "labels": data["take_labels"],
            "regions": "by region" if params.regions and data["morph_region"] is not None else "whole face",
            **alpha_meta,
            **result["meta"],
        }
        return Result(arrays, meta=meta, metrics=metrics, warnings=result["warnings"])

    def _posed_vertices(self, character, weights: np.ndarray, block: int = 64):
        """Posed vertices streamed into an output sink block by block of frames: a long take's (frames, V, 3) never
        sits in memory whole (26,000 vertices are 0.3 MB a frame)."""
        deltas = np.asarray(character["deltas"], np.float32)
        neutral = np.asarray(character["neutral"], np.float32)
        sink = self.sink("vertices", dtype="float32", row_shape=neutral.shape)
        for start in range(0, len(weights), block):
            rows = weights[start : start + block].astype(np.float32)
            sink.append(neutral[None] + np.tensordot(rows, deltas, axes=1))
        return sink


# ------------------------------------------------------------------------------------------------ lips and eyes


def finish_weights(params, data, raw: np.ndarray, alpha: np.ndarray) -> dict:
    """Clip to [0, 1], then the lip seal and the eyes (each when asked for and its inputs are there)."""
    weights = np.clip(raw, 0.0, 1.0)
    out = {"metrics": {}, "meta": {}, "warnings": [], "gaze": None}
    character, tracks, names = data["character"], data["tracks"], data["names"]
    if params.lip_seal:
        gap, source = performer_lip_gap(tracks, data["target_gap"], alpha)
        if character is None or gap is None:
            out["warnings"].append(
                "lip seal off: it needs the character input, and the performer's tracking or the keyshapes' lip_gap"
            )
        else:
            correctives = corrective_columns(data["names"], params.seal_correctives)
            weights, seal = apply_lip_seal(weights, character, gap, params.seal_gap, correctives)
            out["metrics"].update(seal)
            out["meta"]["lip_seal_source"] = source
    if params.eyes == "tracking":
        if tracks is None:
            out["warnings"].append("eyes from tracking: no tracks input, blinks and gaze come from the keymorphs only")
        else:
            weights, gaze, eyes_meta, eyes_warnings = apply_eyes(
                weights, names, character, tracks, data["sequence"], params.gaze_full_degrees, params.gaze_reference
            )
            out["gaze"], out["meta"]["eyes"] = gaze, eyes_meta
            out["warnings"] += eyes_warnings
    spans = held_gap_spans(tracks, params.held_gap_ease)
    if spans:
        weights = ease_into_found_face(weights, spans)
        out["gaze"] = None if out["gaze"] is None else ease_into_found_face(out["gaze"], spans)
        out["meta"]["held_gaps_eased"] = [list(span) for span in spans]
    out["weights"] = weights
    return out


def held_gap_spans(tracks, seconds: float) -> list[tuple[int, int]]:
    """The frames that ease into a face the tracker found again after holding it (``stages.geometry.held_gaps``),
    from the tracking's meta; none without tracks or gaps."""
    if tracks is None or not tracks.meta.get("gaps") or "sequence" not in tracks:
        return []
    fps = tracks.meta.get("fps") or [30.0]
    return found_again_spans(np.asarray(tracks["sequence"]), tracks.meta["gaps"], list(fps), seconds)


def character_landmarks(character) -> tuple[np.ndarray, np.ndarray]:
    """The character's 68 landmark vertices (68, 3) and their morph deltas (M, 68, 3)."""
    ids = np.asarray(character["landmark_ids"], dtype=np.int64)
    return np.asarray(character["neutral"], np.float64)[ids], np.asarray(character["deltas"], np.float64)[:, ids]


def performer_lip_gap(tracks, target_gap, alpha) -> tuple[np.ndarray | None, str]:
    """The inner-lip gap (frames,) the seal follows: the tracked performer's, when the blend has the tracking of
    the take it animates (lip closures are speech, not expression: a re-expressed take keeps its performer's), else
    the decomposed shapes' (keyshapes ``lip_gap``) blended by alpha."""
    from stages.retarget.face_measures import level, lip_gap_iod

    if tracks is not None:
        with np.errstate(invalid="ignore", divide="ignore"):  # a frame without a face: NaN, never sealed
            return lip_gap_iod(level(np.asarray(tracks["landmarks"], np.float64))), "tracking"
    if target_gap is not None:
        return np.einsum("ft,tf->f", alpha, target_gap), "keyshapes lip_gap"
    return None, "none"


def corrective_columns(names: list[str], pairs) -> list[tuple[int, int]]:
    """(corrective, base) morph indices of the pairs the character has."""
    from stages.retarget.regions import find_morph

    found = [(find_morph(names, c), find_morph(names, b)) for c, b in pairs]
    return [(c, b) for c, b in found if c is not None and b is not None]


def apply_lip_seal(weights, character, gap, seal_gap, correctives=()) -> tuple[np.ndarray, dict]:
    """The sealed weights and how much the seal did (stages.retarget.lips); ``gap`` (frames,) the performer's
    inner-lip gap; ``correctives`` (corrective, base) columns the seal may raise up to the base's weight."""
    from stages.retarget.lips import lip_gap_model, raise_correctives, seal_bound, seal_lips

    if "landmark_ids" not in character:
        raise UserError("the lip seal needs the character's landmark_ids", field="inputs.character")
    g0, slopes = lip_gap_model(*character_landmarks(character))
    bound = seal_bound(gap, g0, seal_gap)
    raised, movable = raise_correctives(weights, g0, slopes, bound, list(correctives))
    sealed = seal_lips(raised, g0, slopes, bound, movable)
    for c, b in correctives:  # a base lowered anyway (net slope > 0) takes its corrective down with it
        sealed[:, c] = np.minimum(sealed[:, c], sealed[:, b])
    before, after = g0 + weights @ slopes, g0 + sealed @ slopes
    closed = gap < seal_gap
    return sealed, {
        "sealed_frames": int((np.abs(sealed - weights).max(axis=1) > 1e-6).sum()),
        "closed_frames": int(closed.sum()),
        "lip_gap_at_closures_before": float(before[closed].mean()) if closed.any() else 0.0,
        "lip_gap_at_closures_after": float(after[closed].mean()) if closed.any() else 0.0,
        "performer_gap_at_closures": float(gap[closed].mean()) if closed.any() else 0.0,
    }


def gaze_about_median(gaze: np.ndarray, sequence: np.ndarray) -> tuple[np.ndarray, list]:
    """The gaze (frames, 2, 2) degrees less each take's median per eye and angle (``sequence``: the take of each
    frame), and the medians taken out (takes, 2, 2) as lists. A performer speaking to a camera mostly looks at its
    lens, so the median is that line of sight (and the tracker's bias for this face's eyes, up to 14 degrees
    between the two eyes of one talking-head clip)."""
    gaze = np.array(gaze, np.float64)
    medians = []
    for take in np.unique(sequence):
        rows = sequence == take
        median = np.nanmedian(gaze[rows], axis=0)
        gaze[rows] -= np.nan_to_num(median)
        medians.append(np.round(median, 3).tolist())
    return gaze, medians


def apply_eyes(weights, names, character, tracks, sequence, full_degrees, reference: str = "median"):
    """Blink morphs from the eyelid aperture, eyeLook morphs from the gaze (about its median per take, or as
    tracked: ``reference``); returns (weights, gaze or None, meta, warnings)."""
    from stages.retarget.eyes import (
        blink_for_aperture,
        closure,
        eye_aperture_2d,
        gaze_morphs,
        gaze_weights,
    )
    from stages.retarget.regions import find_side_morph

    weights = weights.copy()
    meta, warnings = {}, []
    gaze = np.asarray(tracks["gaze"], np.float64) if "gaze" in tracks else None
    if gaze is None:
        meta["gaze_source"] = "none (tracking has no gaze)"
    else:
        if reference == "median":
            gaze, meta["gaze_median_taken_out"] = gaze_about_median(gaze, np.asarray(sequence))
        morphs = gaze_morphs(names)
        if morphs:
            looked = gaze_weights(gaze, morphs, full_degrees, len(names))
            columns = list(morphs.values())
            weights[:, columns] = looked[:, columns]
        else:
            warnings.append("the character has no eyeLook morphs: gaze goes to the blend's gaze output only")
        meta["gaze_source"] = "tracking gaze"
    blinks = [find_side_morph(names, "eyeBlink", side) for side in ("L", "R")]
    if "eye_aperture" in tracks:
        aperture, meta["blink_source"] = np.asarray(tracks["eye_aperture"], np.float64), "tracking eye_aperture"
    else:
        aperture, meta["blink_source"] = eye_aperture_2d(tracks["landmarks"]), "tracking landmarks"
    if character is None or "landmark_ids" not in character:
        warnings.append("blinks from tracking need the character input (its eyelid landmarks); blinks left as keyed")
    elif any(b is None for b in blinks):
        warnings.append("the character has no eyeBlink_L/R morphs: the performer's blinks are dropped")
    else:
        rest, deltas = character_landmarks(character)
        c = closure(aperture, sequence)
        weights[:, blinks] = 0.0
        others = np.einsum("fm,mpc->fpc", weights, deltas)  # everything but the blink: squint, brows, gaze
        opened = eye_aperture_2d(rest[None])[0]  # the character's open eye: its neutral's
        for eye, m in enumerate(blinks):
            weights[:, m] = blink_for_aperture(rest, others, deltas[m], eye, opened[eye] * (1.0 - c[:, eye]))
        meta["blink_peak"] = [float(weights[:, m].max(initial=0.0)) for m in blinks]
    return weights, gaze, meta, warnings
