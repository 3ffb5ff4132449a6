"""Expression editing of a new sequence (paper Sec 3.3, Eq 7) and the edited face images; the ``ExpressionEdit``
stage, which first analyses the take (Eq 5-6, ``stages.face.analysis``).

Editing replaces e by a training expression's style vector or a barycentric mix (Eq 7), constant or keyframed;
the edited y goes back through Eq 3-1 to shapes and textures, and the texture is warped onto the shape and pasted
into the test take's face crops.

"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from msflow import Input, Output, Result, Stage, UserError
from stages.face.aam import AamModel, AamProjection, apply_similarity, check_landmark_scheme, check_landmarks
from stages.face.analysis import (
    AnalysisParams,
    FrameAnalysis,
    analyse_frames,
    convergence_warnings,
    fit_warnings,
    jitter,
)
from stages.face.bilinear import BilinearModel, synthesise
from stages.formats.video import Mp4Writer

#: frames projected, rendered and encoded at a time: bounds the memory of the image work whatever the take's length
BLOCK_FRAMES = 256


# ----------------------------------------------------------------------------------------------- edit (Eq 7)


def check_barycentric(weights: dict[str, float]) -> dict[str, float]:
    """``weights`` if they are finite and sum to 1, else ValueError (a params rule: no model needed)."""
    values = np.array([float(v) for v in weights.values()])
    if not np.all(np.isfinite(values)):
        raise ValueError("weights must be finite numbers")
    if abs(values.sum() - 1.0) > 1e-6:
        raise ValueError(f"barycentric weights must sum to 1 (got {values.sum():g}), e.g. {{happy: 0.5, angry: 0.5}}")
    return weights


def check_extrapolation_bound(weights: dict[str, float], max_extrapolation: float) -> None:
    """ValueError when a weight is below -max_extrapolation (paper Sec 3.3: too far gives invalid faces)."""
    lowest = min(weights.values(), default=0.0)
    if lowest < -max_extrapolation - 1e-12:
        raise ValueError(
            f"weights extrapolate beyond the training expressions by {-lowest:g} (a weight of {lowest:g}); "
            f"max_extrapolation is {max_extrapolation:g}"
        )


class Keyframe(BaseModel):
    """Barycentric weights over the training expressions at a time (seconds from the take's first frame)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    time: float
    weights: dict[str, float]

    @field_validator("weights")
    @classmethod
    def _barycentric(cls, weights):
        return check_barycentric(weights)


def weight_vector(weights: dict[str, float], labels: list[str], field: str) -> np.ndarray:
    """Barycentric weights (S,) from a label -> weight mapping; UserError on unknown labels or a sum != 1."""
    unknown = sorted(set(weights) - set(labels))
    if unknown:
        raise UserError(f"unknown expression(s) {unknown}; the model was trained on {labels}", field=field)
    try:
        check_barycentric(weights)
    except ValueError as exc:
        raise UserError(str(exc), field=field) from None
    return np.array([float(weights.get(label, 0.0)) for label in labels])


def keyframed_weights(keyframes: list[Keyframe], labels: list[str], times: np.ndarray, field: str) -> np.ndarray:
    """(F, S) weights interpolated linearly between keyframes (held constant before the first, after the last)."""
    if not keyframes:
        raise UserError("keyframes must not be empty", field=field)
    order = sorted(range(len(keyframes)), key=lambda i: keyframes[i].time)
    key_times = np.array([keyframes[i].time for i in order])
    if np.any(np.diff(key_times) <= 0):
        raise UserError("keyframe times must be distinct", field=field)
    key_weights = np.stack([weight_vector(keyframes[i].weights, labels, f"{field}[{i}].weights") for i in order])
    return np.stack([np.interp(times, key_times, key_weights[:, s]) for s in range(len(labels))], axis=-1)


def check_extrapolation(weights: np.ndarray, max_extrapolation: float, field: str) -> bool:
    """Weights outside the simplex extrapolate the expressions (paper Sec 3.3: too far gives invalid faces).

    UserError beyond ``max_extrapolation`` (most negative weight allowed is -max_extrapolation); a warning
    inside the bound. Returns True when the weights extrapolate.
    """
    lowest = float(np.min(weights))
    try:
        check_extrapolation_bound({"": lowest}, max_extrapolation)
    except ValueError as exc:
        raise UserError(str(exc), field=field) from None
    if lowest < -1e-12:
        warnings.warn(
            f"{field}: weights extrapolate beyond the training expressions (lowest weight {lowest:g}); "
            f"extreme extrapolation can produce invalid faces",
            UserWarning,
            stacklevel=2,
        )
        return True
    return False


def edit_configuration(
    w: np.ndarray, training_styles: np.ndarray, weights: np.ndarray, content: np.ndarray
) -> np.ndarray:
    """Eq 7: y(t) = (sum_s alpha_s(t) e_s)' W c(t) for weights (F, S) (or (S,), constant) and content (F, J)."""
    weights = np.broadcast_to(np.asarray(weights, dtype=np.float64), (len(content), len(training_styles)))
    return synthesise(w, weights @ training_styles, content)


@dataclass
class EditTargets:
    """What to synthesise: one row of Eq 7 weights per edit, over the frames."""

    names: list[str]  # one per edit: training expressions first, then "mix" and/or "keyframed"
    weights: np.ndarray  # (E, F, S)
    n_targets: int  # the first n_targets edits are pure training expressions (outputs y, shapes, ...)
    extrapolated: bool


def edit_targets(params, labels: list[str], times: np.ndarray) -> EditTargets:
    """The edits the params ask for, checked against the model's expressions (the rules that need no model are in
    ``EditParams``)."""
    names, rows = [], []
    for name in params.targets if params.targets is not None else labels:
        if name not in labels:
            raise UserError(f"target '{name}' is not a training expression {labels}", field="params.targets")
        names.append(name)
        rows.append(np.broadcast_to(np.eye(len(labels))[labels.index(name)], (len(times), len(labels))))
    n_targets = len(rows)
    extrapolated = False
    if params.mix is not None:
        vec = weight_vector(params.mix, labels, "params.mix")
        extrapolated |= check_extrapolation(vec, params.max_extrapolation, "params.mix")
        names.append("mix")
        rows.append(np.broadcast_to(vec, (len(times), len(labels))))
    if params.keyframes is not None:
        wt = keyframed_weights(params.keyframes, labels, times, "params.keyframes")
        extrapolated |= check_extrapolation(wt, params.max_extrapolation, "params.keyframes")
        names.append("keyframed")
        rows.append(wt)
    weights = np.stack(rows).astype(np.float64) if rows else np.zeros((0, len(times), len(labels)))
    return EditTargets(names, weights, n_targets, extrapolated)


# ----------------------------------------------------------------------------------------------- images


def edited_crops(
    model: AamModel,
    y: np.ndarray,
    crops: np.ndarray,
    crop_similarity: np.ndarray,
    texture_offset: np.ndarray,
    texture_scale: np.ndarray,
    feather: float = 1.5,
    jobs: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """Invert Eq 3-1 for y (F, K), warp each texture onto its shape in the frame's crop, paste over the crop.

    The frame's own similarity (mean frame -> crop) and photometric offset/scale place the synthesised face
    where the input face was. Returns (edited crops (F, H, W) uint8, shapes in crop pixels (F, 68, 2)). Frames are
    independent: ``jobs`` > 1 pastes them on that many threads (OpenCV releases the GIL), with the same result.
    """
    shapes, textures = model.reconstruct(y)
    crop_shapes = apply_similarity(shapes, crop_similarity)
    images = model.warp.fill_outside(model.texture_images(textures, texture_offset, texture_scale))
    out = np.empty_like(crops)

    def paste(f: int) -> None:
        out[f] = paste_face(model, images[f], crop_shapes[f], crops[f], feather)

    if jobs > 1 and len(y) > 1:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(jobs) as pool:
            list(pool.map(paste, range(len(y))))
    else:
        for f in range(len(y)):
            paste(f)
    return out, crop_shapes


def paste_face(model: AamModel, texture_image: np.ndarray, shape: np.ndarray, crop: np.ndarray, feather: float):
    """One texture drawn onto its shape (inverse warp) and blended into the crop with a feathered mask."""
    import cv2

    h, w = crop.shape
    drawn, covered = model.warp.draw_on_shape(texture_image, shape, (w, h))
    alpha = covered.astype(np.float32)
    if feather > 0:
        alpha = cv2.GaussianBlur(cv2.erode(alpha, np.ones((3, 3), np.uint8)), (0, 0), feather)
    blended = alpha * drawn + (1 - alpha) * crop.astype(np.float32)
    return np.clip(np.round(blended), 0, 255).astype(np.uint8)


def label_panel(image: np.ndarray, text: str) -> np.ndarray:
    import cv2

    panel = np.ascontiguousarray(image.copy())
    scale = max(panel.shape[1] / 320, 0.35)
    cv2.putText(panel, text, (4, int(14 * scale + 4)), cv2.FONT_HERSHEY_SIMPLEX, scale, 255, 1, cv2.LINE_AA)
    return panel


def side_by_side(panels: list[np.ndarray], names: list[str]) -> np.ndarray:
    """(F, H, n*W) frames: labelled panels next to each other, a 2-pixel gap between them."""
    f, h, w = panels[0].shape
    gap = 2
    out = np.zeros((f, h, len(panels) * (w + gap) - gap), dtype=np.uint8)
    for i, (panel, name) in enumerate(zip(panels, names)):
        for t in range(f):
            out[t, :, i * (w + gap) : i * (w + gap) + w] = label_panel(panel[t], name)
    return out


def encode_png(image: np.ndarray) -> bytes:
    import cv2

    ok, data = cv2.imencode(".png", np.ascontiguousarray(image))
    if not ok:  # pragma: no cover - OpenCV always encodes uint8 images
        raise RuntimeError("PNG encoding failed")
    return data.tobytes()


def interpolation_path(path: list[str], labels: list[str], steps: int) -> tuple[np.ndarray, list[str]]:
    """Barycentric weights (n, S) along a piecewise-linear path of expressions (paper Fig. 2), with captions."""
    idx = [labels.index(p) for p in path]
    rows, names = [], []
    for a, b in zip(idx[:-1], idx[1:]):
        for alpha in np.linspace(1.0, 0.0, steps)[: -1 if b != idx[-1] else None]:
            w = np.zeros(len(labels))
            w[a] += alpha
            w[b] += 1 - alpha
            rows.append(w)
            names.append(f"{labels[a]} {alpha:.2f}" if 0 < alpha < 1 else labels[a] if alpha == 1 else labels[b])
    return np.stack(rows), names


# ----------------------------------------------------------------------------------------------- stage

EDIT_OUTPUTS = {
    "style": Output.array("f", shape=("frames", None), doc="analysed e(t) (Eq 5)"),
    "content": Output.array("f", shape=("frames", None), doc="analysed c(t) (Eq 6)"),
    "style_weights": Output.array(
        "f", shape=("frames", "labels"), doc="e(t) as barycentric weights over the training expressions"
    ),
    "style_cosine": Output.array("f", shape=("frames", "labels"), doc="cosine of e(t) to each training style"),
    "classification": Output.array(
        "i",
        shape=("frames",),
        doc="nearest training style: by cosine of e(t), or by style_fit_residual (params.classify)",
    ),
    "style_fit_residual": Output.array(
        "f",
        shape=("frames", "labels"),
        doc="relative squared error of each frame explained with each training style "
        "fixed, content re-solved (analysis weights)",
    ),
    "residual": Output.array("f", shape=("frames",), doc="relative squared error of the analysed y per frame"),
    "weights": Output.array("f", shape=("targets", "frames", "labels"), doc="Eq 7 weights used per target"),
    "y": Output.array("f", shape=("targets", "frames", None), doc="edited configuration vectors"),
    "shapes": Output.array(
        "f",
        shape=("targets", "frames", 68, 2),
        dtype="float32",
        doc="edited shapes in the aam mean-shape frame, one set per meta['targets'] (training "
        "expressions only; mixes are in mixed_shapes)",
    ),
    "crop_shapes": Output.array(
        "f", shape=("targets", "frames", 68, 2), dtype="float32", doc="edited shapes in the test take's crop pixels"
    ),
    "frames": Output.array(
        "u",
        shape=("frames", "targets", None, None),
        dtype="uint8",
        doc="edited face crops (grey), frames first so they are written block by block",
    ),
    "mixed_weights": Output.array(
        "f",
        shape=("mixes", "frames", "labels"),
        optional=True,
        doc="Eq 7 weights of the mix / keyframed edits (meta['mixes'])",
    ),
    "mixed_y": Output.array("f", shape=("mixes", "frames", None), optional=True),
    "mixed_shapes": Output.array("f", shape=("mixes", "frames", 68, 2), dtype="float32", optional=True),
    "mixed_crop_shapes": Output.array("f", shape=("mixes", "frames", 68, 2), dtype="float32", optional=True),
    "mixed_frames": Output.array("u", shape=("frames", "mixes", None, None), dtype="uint8", optional=True),
    "sequence": Output.array("i", shape=("frames",), dtype="int32", doc="test take of each frame (meta test_labels)"),
    "time": Output.array("f", shape=("frames",), doc="seconds since the take's first frame"),
    "video": Output.file(".mp4", optional=True, doc="input | edited expressions side by side"),
    "strip": Output.file(".png", optional=True, doc="interpolation strip of one frame (paper Fig. 2)"),
}


class EditParams(AnalysisParams):
    """What the edit synthesises, and how the take is analysed first (``AnalysisParams``)."""

    targets: list[str] | None = None
    mix: dict[str, float] | None = None
    keyframes: list[Keyframe] | None = Field(None, min_length=1)
    max_extrapolation: float = Field(0.5, ge=0)
    video: bool = True
    strip_path: list[str] | None = Field(None, min_length=2)
    strip_steps: int = Field(4, ge=2)
    strip_frame: int | None = Field(None, ge=0)

    @field_validator("mix")
    @classmethod
    def _mix_is_barycentric(cls, mix):
        return None if mix is None else check_barycentric(mix)

    @field_validator("keyframes")
    @classmethod
    def _distinct_times(cls, keyframes):
        times = [k.time for k in keyframes or []]
        if len(set(times)) != len(times):
            raise ValueError(f"keyframe times must be distinct, got {sorted(times)}")
        return keyframes

    @model_validator(mode="after")
    def _something_within_bounds(self):
        if self.targets == [] and self.mix is None and self.keyframes is None:
            raise ValueError("nothing to synthesise: give targets, mix or keyframes")
        for weights in [self.mix or {}] + [k.weights for k in self.keyframes or []]:
            check_extrapolation_bound(weights, self.max_extrapolation)
        return self


@dataclass
class TestTake:
    """The validated inputs of the edit: models, and the test take(s) as arrays (crops possibly lazy)."""

    bilinear: BilinearModel
    model: AamModel
    labels: list[str]  # test take labels
    sequence: np.ndarray  # (F,)
    landmarks: np.ndarray  # (F, 68, 2)
    crop_landmarks: np.ndarray  # (F, 68, 2)
    crops: object  # (F, H, W) uint8, numpy or a lazy zarr array read by blocks of frames
    times: np.ndarray  # (F,) seconds
    fps: float


def check_edit_inputs(inputs) -> TestTake:
    """The models and the test take, or a UserError naming the input that does not fit."""
    bilinear = BilinearModel.from_view(inputs["model"])
    aam_view, tracks = inputs["aam"], inputs["tracks"]
    model = AamModel.from_view(aam_view)
    k = bilinear.w.shape[2]
    if model.n_shape + model.n_texture != k or len(bilinear.style) != len(bilinear.labels):
        raise UserError(
            f"the bilinear model has K={k} components but the appearance model has "
            f"{model.n_shape}+{model.n_texture}; fit both from the same aam artifact",
            field="inputs.model",
        )
    landmarks = np.asarray(tracks["landmarks"])
    labels = list(tracks.meta.get("labels", ["test"]))
    sequence = np.asarray(tracks.get("sequence", np.zeros(len(landmarks), dtype=np.int32)))
    expected = str(aam_view.meta.get("landmark_scheme", "ibug68"))
    check_landmark_scheme(landmarks, tracks.meta, "inputs.tracks.landmarks", expected=expected)
    check_landmarks(landmarks, sequence, labels, "inputs.tracks.landmarks")
    crop_landmarks = np.asarray(tracks["crop_landmarks"])
    check_landmarks(crop_landmarks, sequence, labels, "inputs.tracks.crop_landmarks")
    fps = first_number(tracks.meta.get("fps"), 30.0)
    times = np.asarray(tracks.get("time", np.arange(len(landmarks)) / fps), dtype=np.float64)
    crops = tracks.lazy("crops")
    return TestTake(bilinear, model, labels, sequence, landmarks, crop_landmarks, crops, times, fps)


def project_by_blocks(model: AamModel, take: TestTake, block: int = BLOCK_FRAMES) -> AamProjection:
    """Eq 1-3 for the test take, ``block`` frames at a time; the shape-free textures are not kept (they are only
    needed as y, and a long take's textures would not fit in memory)."""
    parts = []
    for a in range(0, len(take.landmarks), block):
        b = min(a + block, len(take.landmarks))
        part = model.project(take.landmarks[a:b], np.asarray(take.crops[a:b]), take.crop_landmarks[a:b])
        part.textures = np.empty((b - a, 0))  # not a view: that would keep the block's textures alive
        parts.append(part)
    fields = AamProjection.__dataclass_fields__
    return AamProjection(**{name: np.concatenate([getattr(p, name) for p in parts]) for name in fields})


@dataclass
class RenderedEdits:
    """Eq 7 for every edit, back through Eq 3-1 to shapes (the edited crops go to ``render_edits``' ``emit``)."""

    y: np.ndarray  # (E, F, K) edited configuration vectors
    shapes: np.ndarray  # (E, F, 68, 2) float32, mean-shape frame
    crop_shapes: np.ndarray  # (E, F, 68, 2) float32, crop pixels
    video: bytes | None  # input | edits side by side


def render_edits(
    take: TestTake,
    proj: AamProjection,
    content: np.ndarray,
    targets: EditTargets,
    video: bool,
    emit,
    block: int = BLOCK_FRAMES,
    jobs: int = 1,
) -> RenderedEdits:
    """Eq 7 and the edited crops for every edit, ``block`` frames at a time: each block's crops (b, E, H, W) go to
    ``emit`` (an output sink's append) and into the video as they come, so no whole-take image array is held."""
    from msflow.sinks import iter_blocks

    bilinear, model = take.bilinear, take.model
    n_edits, n_frames = targets.weights.shape[:2]
    y = np.zeros((n_edits, n_frames, bilinear.w.shape[2]))
    shapes = np.zeros((n_edits, n_frames, 68, 2), dtype=np.float32)
    crop_shapes = np.zeros_like(shapes)
    # grey frames as YUV planes at crf 18 (the crops' detail); libx264, else FFmpeg's MPEG-4 fallback
    encoder = Mp4Writer(take.fps, crf=18, preset="medium", pixels="gray") if video else None
    for a, crops in zip(range(0, n_frames, block), iter_blocks(take.crops, block)):
        b = a + len(crops)
        frames = np.zeros((b - a, n_edits) + crops.shape[1:], dtype=np.uint8)
        for e in range(n_edits):
            y[e, a:b] = edit_configuration(bilinear.w, bilinear.style, targets.weights[e, a:b], content[a:b])
            shapes[e, a:b] = model.reconstruct_shapes(model.split(y[e, a:b])[0])
            frames[:, e], crop_shapes[e, a:b] = edited_crops(
                model,
                y[e, a:b],
                crops,
                proj.crop_similarity[a:b],
                proj.texture_offset[a:b],
                proj.texture_scale[a:b],
                jobs=jobs,
            )
        emit(frames)
        if encoder is not None:
            encoder.write(side_by_side([crops, *frames.transpose(1, 0, 2, 3)], ["input", *targets.names]))
    return RenderedEdits(y, shapes, crop_shapes, encoder.close() if encoder is not None else None)


def render_strip(params, labels: list[str], take: TestTake, proj: AamProjection, content: np.ndarray) -> bytes:
    """The interpolation strip (paper Fig. 2): one frame of the take along a path of expressions, as PNG."""
    path = params.strip_path if params.strip_path is not None else default_strip_path(labels)
    missing = [p for p in path if p not in labels]
    if missing:
        raise UserError(
            f"strip_path {path} names {missing}, not training expressions {labels}", field="params.strip_path"
        )
    n = len(take.landmarks)
    frame = params.strip_frame if params.strip_frame is not None else n // 2
    if frame >= n:
        raise UserError(f"strip_frame {frame} is outside the take's {n} frames", field="params.strip_frame")
    wts, names = interpolation_path(path, labels, params.strip_steps)
    y = edit_configuration(
        take.bilinear.w, take.bilinear.style, wts, np.repeat(content[frame : frame + 1], len(wts), 0)
    )
    one = slice(frame, frame + 1)
    images, _ = edited_crops(
        take.model,
        y,
        np.repeat(np.asarray(take.crops[one]), len(wts), 0),
        np.repeat(proj.crop_similarity[one], len(wts), 0),
        np.repeat(proj.texture_offset[one], len(wts)),
        np.repeat(proj.texture_scale[one], len(wts)),
    )
    return encode_png(side_by_side([img[None] for img in images], names)[0])


class ExpressionEdit(Stage):
    """Analyse the test take with the trained bilinear model (Eq 5-6) and resynthesise it with other expressions
    (Eq 7), as shapes, configuration vectors and face images (MP4 and an interpolation strip)."""

    in_process = True

    Params = EditParams
    inputs = {
        "model": Input.artifact("W", "style", "content", doc="bilinear artifact"),
        "aam": Input.artifact("mean_shape", "shape_basis", "texture_basis", doc="appearance model of training"),
        "tracks": Input.artifact("landmarks", "crops", "crop_landmarks", doc="tracking of the test take(s)"),
    }
    outputs = EDIT_OUTPUTS

    def run(self, params, inputs):
        take = check_edit_inputs(inputs)
        labels = take.bilinear.labels
        targets = edit_targets(params, labels, take.times)
        proj = project_by_blocks(take.model, take)
        analysis = analyse_frames(take.bilinear, take.model.n_shape, proj.y, take.sequence, params)
        frames, emit = self.frame_sinks(targets, tuple(take.crops.shape[1:]))
        edits = render_edits(take, proj, analysis.content, targets, params.video, emit, jobs=self.jobs)
        strip = render_strip(params, labels, take, proj, analysis.content)
        return pack_edit(params, take, targets, analysis, edits, strip, frames)

    def frame_sinks(self, targets: EditTargets, size: tuple[int, int]):
        """Output sinks for the edited crops of the targets and of the mixes, and the function that fills them
        from each rendered block (b, E, H, W)."""
        n = targets.n_targets
        sinks = {"frames": self.sink("frames", dtype="uint8", row_shape=(n, *size))}
        if len(targets.names) > n:
            sinks["mixed_frames"] = self.sink("mixed_frames", dtype="uint8", row_shape=(len(targets.names) - n, *size))

        def emit(block):
            sinks["frames"].append(block[:, :n])
            if "mixed_frames" in sinks:
                sinks["mixed_frames"].append(block[:, n:])

        return sinks, emit


def pack_edit(
    params, take: TestTake, targets: EditTargets, analysis: FrameAnalysis, edits: RenderedEdits, strip, frames: dict
):
    """The ExpressionEdit artifact: analysis per frame, edits split into pure targets and mixes (their crops in the
    ``frames`` sinks), metrics, warnings."""
    n = targets.n_targets
    arrays = {
        "style": analysis.style,
        "content": analysis.content,
        "style_weights": analysis.style_weights,
        "style_cosine": analysis.cosine,
        "classification": analysis.classes.astype(np.int32),
        "residual": analysis.residual,
        "style_fit_residual": analysis.fit_residual,
        "sequence": take.sequence.astype(np.int32),
        "time": take.times,
        "strip": strip,
        "weights": targets.weights[:n],
        "y": edits.y[:n],
        "shapes": edits.shapes[:n],
        "crop_shapes": edits.crop_shapes[:n],
        **frames,
    }
    if len(targets.names) > n:
        arrays.update(
            mixed_weights=targets.weights[n:],
            mixed_y=edits.y[n:],
            mixed_shapes=edits.shapes[n:],
            mixed_crop_shapes=edits.crop_shapes[n:],
        )
    if edits.video is not None:
        arrays["video"] = edits.video
    warned = convergence_warnings(analysis.residual, analysis.converged, take.sequence, take.labels, params.max_iter)
    warned += fit_warnings(analysis.residual, take.sequence, take.labels)
    return Result(arrays, edit_meta(params, take, targets, analysis), edit_metrics(take, analysis), warned)


def edit_meta(params, take: TestTake, targets: EditTargets, analysis: FrameAnalysis) -> dict:
    labels = take.bilinear.labels
    counts = np.bincount(analysis.classes, minlength=len(labels))
    return {
        "labels": labels,
        "targets": targets.names[: targets.n_targets],
        "mixes": targets.names[targets.n_targets :],
        "fps": take.fps,
        "test_labels": take.labels,
        "smooth": params.smooth,
        "analysis_shape_weight": params.analysis_shape_weight,
        "classify": params.classify,
        "iterations": analysis.iterations,
        "converged": bool(analysis.converged.all()),
        "extrapolated": targets.extrapolated,
        "strip_path": params.strip_path if params.strip_path is not None else default_strip_path(labels),
        "classified_as": {labels[s]: int(counts[s]) for s in range(len(labels))},
    }


def edit_metrics(take: TestTake, analysis: FrameAnalysis) -> dict:
    """Residual, convergence and jitter of the analysis; the fraction of frames classified as, and the mean weight
    of, each training expression (how the take reads)."""
    labels = take.bilinear.labels
    counts = np.bincount(analysis.classes, minlength=len(labels))
    return {
        "mean_residual": float(np.mean(analysis.residual)),
        "unconverged_frames": float(np.mean(~analysis.converged)),
        "jitter": jitter(analysis.style),
        "iterations": analysis.iterations,
        **{f"fraction_{labels[s]}": float(counts[s] / len(analysis.classes)) for s in range(len(labels))},
        **{f"weight_{labels[s]}": float(np.mean(analysis.style_weights[:, s])) for s in range(len(labels))},
    }


def default_strip_path(labels: list[str]) -> list[str]:
    """Every training expression once, the neutral one in the middle (happy -> neutral -> angry for those three),
    so the strip passes through neutral as the paper's Fig. 2 does."""
    from stages.face.alignment import neutral_index

    others = [label for i, label in enumerate(labels) if i != neutral_index(labels)]
    half = (len(others) + 1) // 2
    return [*others[:half], labels[neutral_index(labels)], *others[half:]]


def first_number(value, default: float) -> float:
    if value is None:
        return default
    arr = np.ravel(np.asarray(value, dtype=np.float64))
    return float(arr[0]) if arr.size else default


def figure_style_over_time(view, inputs=None):
    """Barycentric weights of the analysed style e(t) over the training expressions, frame by frame."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    weights = np.asarray(view["style_weights"])
    labels = view.meta["labels"]
    fps = view.meta.get("fps") or 30.0
    t = np.arange(len(weights)) / fps
    fig, ax = plt.subplots(figsize=(6, 3))
    for s, label in enumerate(labels):
        ax.plot(t, weights[:, s], label=label)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("style weight")
    ax.set_title(f"analysed expression (smooth = {view.meta.get('smooth', 0)})")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def figure_strip(view, inputs=None) -> bytes:
    """The interpolation strip (paper Fig. 2) as PNG."""
    return view.bytes("strip")


ExpressionEdit.figures = {"style_over_time": figure_style_over_time, "interpolation_strip": figure_strip}
