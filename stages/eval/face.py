"""Evaluation of the face analysis (paper Sec 3: appearance model, bilinear model, analysis and edit) on labelled takes.

The stage fits the appearance and bilinear models inside each protocol with its ``aam`` and ``bilinear`` params, the
params of the pipeline's ``AamPca`` and ``BilinearFit`` stages (``-S face.bilinear.content_dim=4,8`` sweeps one). Each
take plays the expression its ``expression`` field names (else its label); ``train`` chooses the expressions the models
learn, every other take is *unseen*.

Protocols (docs/face.md explains each number):

1. temporal k-fold: each set of takes (one per expression, same sentence) is cut into ``folds`` windows of its
   content axis; a fold holds out the frames aligned to one window in every take, and drops ``guard`` frames on each
   side of them from training, so a held-out frame's near-duplicate neighbours are not training frames. Each held-out
   frame is analysed (Eq 5-6) and classified. Beside the model, a no-model baseline: the expression of the nearest
   training frame (same components of y the analysis reads). A score the baseline reaches too says the takes are
   told apart by something other than a learnt expression (session, lighting, pose).
2. leave-one-take-out, for expressions with several takes: a whole take is held out and classified by models that
   never saw it (and the baseline).
3. edit fidelity: held-out frames of the reference (neutral) take are re-synthesised in each other expression
   (Eq 7) and compared with the real frames of that expression aligned to them: landmark error (inter-ocular
   distances, mean-shape frame) and texture error (grey levels), edited->real against neutral->real.
4. unseen expressions: analysed by the models fitted on every training frame: how their frames are classified, their
   mean barycentric weights, residual, and the fidelity of their edit into each training expression against the real
   take of that expression (same sentence).

Analysis residual (relative |y - e'Wc|^2 / |y|^2) and convergence (fraction of frames whose alternation stopped at
``max_iter``) are reported for held-out and unseen frames; an unconverged analysis is also a warning.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import Field, field_validator

from msflow import Input, Output, Result, Stage, UserError
from stages.face.aam import (
    AamModel,
    AamParams,
    check_landmarks,
    fit_aam,
    generalised_procrustes,
    interocular_distance,
)
from stages.face.aam import fit_options as aam_options
from stages.face.alignment import SetAlignment, TakeSets, align_pair, align_sets, take_expressions, take_sentences
from stages.face.analysis import AnalysisParams, FrameAnalysis, analyse_frames, analysis_rows, convergence_warnings
from stages.face.bilinear import BilinearModel, BilinearParams, content_features, reference_index, training_sets
from stages.face.bilinear import fit_bilinear_model as fit_bilinear
from stages.face.bilinear import fit_options as bilinear_options

# ----------------------------------------------------------------------------------------------- data


@dataclass
class Takes:
    """The tracked takes under evaluation, with what each one is (expression, sentence) and its DTW features."""

    labels: list[str]
    sequence: np.ndarray  # (N,) take of each frame
    expressions: list[str]  # per take
    sentences: list[str]  # per take
    landmarks: np.ndarray  # (N, 68, 2)
    crops: np.ndarray  # (N, H, W)
    crop_landmarks: np.ndarray  # (N, 68, 2)
    features: list[np.ndarray]  # per take (n_t, d), for content alignment
    onsets: list[int] | None  # per take, first frame of speech (None without audio)

    @property
    def frames(self) -> list[np.ndarray]:
        return [np.flatnonzero(self.sequence == t) for t in range(len(self.labels))]


@dataclass
class Config:
    """How models are fitted (the pipeline's aam and bilinear params) and frames analysed (the eval's params)."""

    aam: AamParams
    bilinear: BilinearParams
    analysis: AnalysisParams
    styles: list[str]  # training expressions, in order
    reference: int  # index into styles of the reference (neutral) expression


def read_takes(tracks, bilinear: BilinearParams) -> Takes:
    """The tracking artifact's takes; UserError on landmarks the models cannot use."""
    labels = [str(x) for x in tracks.meta.get("labels", [])]
    fields = tracks.meta.get("fields") or {}
    sequence = np.asarray(tracks["sequence"])
    landmarks, crop_landmarks = np.asarray(tracks["landmarks"]), np.asarray(tracks["crop_landmarks"])
    check_landmarks(landmarks, sequence, labels, "inputs.tracks.landmarks")
    check_landmarks(crop_landmarks, sequence, labels, "inputs.tracks.crop_landmarks")
    aligned = generalised_procrustes(landmarks)[0] if bilinear.align == "mouth" else None
    features = content_features(bilinear.align, labels, sequence, aligned_shapes=aligned, tracks=tracks)
    onsets = speech_onsets(tracks, labels, sequence) if "audio" in tracks else None
    return Takes(
        labels,
        sequence,
        take_expressions(labels, fields),
        take_sentences(labels, fields),
        landmarks,
        np.asarray(tracks["crops"]),
        crop_landmarks,
        features,
        onsets,
    )


def speech_onsets(tracks, labels: list[str], sequence: np.ndarray, below_peak_db: float = 25.0) -> list[int]:
    """Per take, the first frame whose audio level (one frame period around it) is within ``below_peak_db`` of the
    take's loudest frame: where speech starts (takes often open with silence and a still face)."""
    audio = np.asarray(tracks["audio"], dtype=np.float64)
    bounds = np.asarray(tracks["audio_bounds"])
    rate = float(np.ravel([tracks.meta["audio_rate"]])[0])
    offsets = np.broadcast_to(np.asarray(tracks.meta.get("audio_offset", 0.0), dtype=np.float64), (len(labels),))
    times = np.asarray(tracks["time"], dtype=np.float64)
    fps = float(np.ravel([tracks.meta.get("fps") or 30.0])[0])
    half = max(int(rate / fps / 2), 1)
    onsets = []
    for t in range(len(labels)):
        samples = audio[bounds[t, 0] : bounds[t, 1]]
        centres = np.round((times[sequence == t] - offsets[t]) * rate).astype(int)
        power = [np.mean(samples[max(c - half, 0) : max(c + half, 1)] ** 2) if len(samples) else 0.0 for c in centres]
        db = 10 * np.log10(np.asarray(power) + 1e-20)
        onsets.append(int(np.argmax(db > db.max() - below_peak_db)))
    return onsets


def model_config(params, takes: Takes) -> Config:
    """The training expressions (``params.train``, default all) and the reference expression, with the params the
    models are fitted with."""
    present = list(dict.fromkeys(takes.expressions))
    styles = present if params.train is None else list(dict.fromkeys(params.train))
    missing = [s for s in styles if s not in present]
    if missing:
        raise UserError(
            f"train names {missing}, which no take plays; the takes' expressions are {present}", field="params.train"
        )
    if len(styles) < 2:
        raise UserError(f"the evaluation needs at least two training expressions, got {styles}", field="params.train")
    reference = reference_index(params.bilinear.reference, styles)
    return Config(params.aam, params.bilinear, params, styles, reference)


def training_mask(takes: Takes, config: Config) -> np.ndarray:
    """(n_takes,) bool: the takes whose expression the models learn."""
    return np.array([e in config.styles for e in takes.expressions])


def ordered_sets(takes: Takes, config: Config, include: np.ndarray) -> TakeSets:
    """``training_sets`` of the included takes, the styles in ``config.styles`` order."""
    return training_sets(takes, include, field="params.train", order=config.styles)


# ----------------------------------------------------------------------------------------------- models


@dataclass
class Models:
    """Appearance and bilinear models fitted on some frames, and y of the frames projected into them."""

    aam: AamModel
    bilinear: BilinearModel
    y: np.ndarray  # (N, K) for the frames in ``projected`` (other rows 0)
    projected: np.ndarray  # (N,) bool


def fit_models(
    takes: Takes, config: Config, train: np.ndarray, alignment: SetAlignment, columns: np.ndarray, needed: np.ndarray
) -> Models:
    """Fit the appearance model on the frames ``train`` (N,) bool marks, the bilinear model on the content
    ``columns`` of ``alignment``, and project the frames ``needed`` marks into them."""
    aam, _ = fit_aam(takes.landmarks[train], takes.crops[train], takes.crop_landmarks[train], **aam_options(config.aam))
    frames = np.flatnonzero(needed | train)
    y = np.zeros((len(takes.sequence), aam.n_shape + aam.n_texture))
    y[frames] = aam.project(takes.landmarks[frames], takes.crops[frames], takes.crop_landmarks[frames]).y
    observed = y[alignment.frames[:, columns]]  # (S, C, K)
    if observed.shape[1] < 2:
        raise UserError(
            f"only {observed.shape[1]} aligned content frames are left for training a fold; use fewer folds or a "
            "smaller guard",
            field="params.folds",
        )
    bilinear, _ = fit_bilinear(observed, config.styles, **bilinear_options(config.bilinear))
    projected = np.zeros(len(takes.sequence), dtype=bool)
    projected[frames] = True
    return Models(aam, bilinear, y, projected)


def analyse(models: Models, config: Config, frames: np.ndarray, sequence: np.ndarray) -> FrameAnalysis:
    """Eq 5-6 for the given frames (their takes in ``sequence``), as the edit stage analyses a take."""
    return analyse_frames(models.bilinear, models.aam.n_shape, models.y[frames], sequence, config.analysis)


def nearest_frame_classes(
    models: Models, config: Config, query: np.ndarray, reference: np.ndarray, reference_style: np.ndarray
) -> np.ndarray:
    """No-model baseline: the style of the nearest reference frame to each query frame, in the components of y the
    analysis reads (texture only by default)."""
    from scipy.spatial.distance import cdist

    rows = analysis_rows(models.bilinear, models.aam.n_shape, config.analysis.analysis_shape_weight)
    weights = np.ones(models.y.shape[1]) if rows is None else rows[: models.y.shape[1]]
    distance = cdist(models.y[query] * weights, models.y[reference] * weights)
    return reference_style[np.argmin(distance, axis=1)]


# ----------------------------------------------------------------------------------------------- scores


@dataclass
class Scores:
    """Per frame of the tracking artifact, what a protocol said about it (-1 / NaN where it did not score it)."""

    predicted: np.ndarray  # (N,) style index by the model
    baseline: np.ndarray  # (N,) style index by the nearest-frame baseline
    fold: np.ndarray  # (N,) fold or left-out take that scored the frame
    weights: np.ndarray  # (N, S) barycentric weights of the analysed style
    residual: np.ndarray  # (N,) relative analysis residual
    converged: np.ndarray  # (N,) bool

    @classmethod
    def empty(cls, n: int, n_styles: int) -> Scores:
        minus = np.full(n, -1, dtype=np.int64)
        return cls(
            minus.copy(),
            minus.copy(),
            minus.copy(),
            np.full((n, n_styles), np.nan),
            np.full(n, np.nan),
            np.ones(n, dtype=bool),
        )

    def record(self, frames: np.ndarray, analysis: FrameAnalysis, baseline: np.ndarray, fold: int) -> None:
        self.predicted[frames] = analysis.classes
        self.baseline[frames] = baseline
        self.fold[frames] = fold
        self.weights[frames] = analysis.style_weights
        self.residual[frames] = analysis.residual
        self.converged[frames] = analysis.converged

    @property
    def scored(self) -> np.ndarray:
        return self.fold >= 0


def balanced_accuracy(predicted: np.ndarray, truth: np.ndarray, n_styles: int) -> tuple[float, np.ndarray]:
    """Mean over styles of the fraction of that style's frames classified as it (and the per-style fractions; NaN
    for a style with no frames). Chance is 1 / n_styles whatever the takes' lengths."""
    per_style = np.array(
        [np.mean(predicted[truth == s] == s) if np.any(truth == s) else np.nan for s in range(n_styles)]
    )
    return float(np.nanmean(per_style)) if np.any(np.isfinite(per_style)) else float("nan"), per_style


def confusion(predicted: np.ndarray, truth: np.ndarray, n_styles: int) -> np.ndarray:
    """(S, S) counts: row = true style, column = predicted."""
    out = np.zeros((n_styles, n_styles), dtype=np.int64)
    np.add.at(out, (truth, predicted), 1)
    return out


@dataclass
class Fidelity:
    """Edit fidelity sums over compared frames: edited->real and unedited->real, landmarks (IOD) and texture."""

    edited_landmarks: float = 0.0
    unedited_landmarks: float = 0.0
    edited_texture: float = 0.0
    unedited_texture: float = 0.0
    frames: int = 0

    def add(self, other: Fidelity) -> None:
        for name in ("edited_landmarks", "unedited_landmarks", "edited_texture", "unedited_texture", "frames"):
            setattr(self, name, getattr(self, name) + getattr(other, name))

    def means(self, prefix: str) -> dict[str, float]:
        if not self.frames:
            return {}
        n = self.frames
        return {
            f"{prefix}edit_landmark_error": self.edited_landmarks / n,
            f"{prefix}unedited_landmark_error": self.unedited_landmarks / n,
            f"{prefix}edit_texture_error": self.edited_texture / n,
            f"{prefix}unedited_texture_error": self.unedited_texture / n,
        }


def edit_fidelity(
    models: Models, takes: Takes, source: np.ndarray, content: np.ndarray, real: np.ndarray, style: np.ndarray
) -> Fidelity:
    """Frames ``source`` re-synthesised with ``style`` (I,) and their analysed ``content`` (Eq 7), against the real
    frames ``real`` of that style aligned to them; the source frames themselves (unedited) for comparison."""
    aam = models.aam
    both = np.concatenate([source, real])
    proj = aam.project(takes.landmarks[both], takes.crops[both], takes.crop_landmarks[both])
    raw = proj.textures * proj.texture_scale[:, None] + proj.texture_offset[:, None]
    n = len(source)
    y_edit = models.bilinear.synthesise(np.broadcast_to(style, (n, len(style))), content)
    shapes, textures = aam.reconstruct(y_edit)
    edited_raw = textures * proj.texture_scale[:n, None] + proj.texture_offset[:n, None]
    iod = float(interocular_distance(aam.mean_shape))
    real_shapes = proj.aligned_shapes[n:]

    def landmark_error(a):
        return float(np.sum(np.mean(np.linalg.norm(a - real_shapes, axis=-1), axis=-1)) / iod)

    return Fidelity(
        landmark_error(shapes),
        landmark_error(proj.aligned_shapes[:n]),
        float(np.sum(np.mean(np.abs(edited_raw - raw[n:]), axis=-1))),
        float(np.sum(np.mean(np.abs(raw[:n] - raw[n:]), axis=-1))),
        n,
    )


# ----------------------------------------------------------------------------------------------- k-fold


def fold_partition(takes: Takes, groups: TakeSets, alignment: SetAlignment, reference: int, k: int) -> np.ndarray:
    """(N,) fold of every frame of the training takes (-1 elsewhere): each set's content axis is cut into k windows
    and each take of the set is cut at the frames aligned to the window starts, so a fold holds out the same
    speech in every expression. A take in no set is cut into k equal parts of its own frames."""
    fold = np.full(len(takes.sequence), -1, dtype=np.int64)
    frames = takes.frames
    done = set()
    for r, members in enumerate(groups.sets):
        columns = np.flatnonzero(alignment.column_set == r)
        windows = np.array_split(columns, k)
        for s, take in enumerate(int(t) for t in members):
            if take in done:
                continue
            local = alignment.frames[s, [w[0] for w in windows if len(w)]] - frames[take][0]
            local[0] = 0  # frames before the one aligned to the first reference frame belong to the first fold
            fold[frames[take]] = np.searchsorted(local, np.arange(len(frames[take])), side="right") - 1
            done.add(take)
    for take in np.flatnonzero(groups.take_style >= 0):
        if int(take) not in done:
            for f, part in enumerate(np.array_split(frames[take], k)):
                fold[part] = f
    return fold


def guarded_training(takes: Takes, fold_of: np.ndarray, fold: int, guard: int) -> np.ndarray:
    """(N,) bool: frames of the training takes outside fold ``fold`` and more than ``guard`` frames from it."""
    held = fold_of == fold
    near = held.copy()
    for frames in takes.frames:
        h = held[frames]
        if guard and h.any():
            kernel = np.ones(2 * guard + 1)
            near[frames] = np.convolve(h.astype(float), kernel, mode="same") > 0
    return (fold_of >= 0) & ~near


def kfold(takes: Takes, config: Config, groups: TakeSets, alignment: SetAlignment) -> tuple[Scores, Fidelity]:
    """Temporal k-fold with a guard band (protocol 1) and the edit fidelity of held-out reference frames (3)."""
    params = config.analysis
    fold_of = fold_partition(takes, groups, alignment, config.reference, params.folds)
    truth = style_of_frames(takes, groups)
    scores = Scores.empty(len(takes.sequence), len(config.styles))
    fidelity = Fidelity()
    for f in range(params.folds):
        held = np.flatnonzero(fold_of == f)
        train = guarded_training(takes, fold_of, f, params.guard)
        columns = np.flatnonzero(train[alignment.frames].all(axis=0))
        models = fit_models(takes, config, train, alignment, columns, fold_of == f)
        analysis = analyse(models, config, held, takes.sequence[held])
        baseline = nearest_frame_classes(models, config, held, np.flatnonzero(train), truth[train])
        scores.record(held, analysis, baseline, f)
        fidelity.add(kfold_fidelity(models, takes, config, alignment, held, analysis, fold_of == f))
    return scores, fidelity


def kfold_fidelity(
    models: Models, takes: Takes, config: Config, alignment: SetAlignment, held, analysis, held_mask
) -> Fidelity:
    """Held-out reference frames edited into every other training expression against the real frames aligned to
    them (content columns whose frames are all held out)."""
    out = Fidelity()
    columns = np.flatnonzero(held_mask[alignment.frames].all(axis=0))
    if not len(columns):
        return out
    position = {int(frame): i for i, frame in enumerate(held)}
    source = alignment.frames[config.reference, columns]
    content = analysis.content[[position[int(frame)] for frame in source]]
    for s in range(len(config.styles)):
        if s != config.reference:
            real = alignment.frames[s, columns]
            out.add(edit_fidelity(models, takes, source, content, real, models.bilinear.style[s]))
    return out


def style_of_frames(takes: Takes, groups: TakeSets) -> np.ndarray:
    """(N,) training style of each frame (-1 for frames of takes the models do not learn)."""
    return groups.take_style[takes.sequence]


# ----------------------------------------------------------------------------------------------- leave one take out


def leave_one_take_out(takes: Takes, config: Config, include: np.ndarray, memo: dict) -> tuple[Scores, list[str]]:
    """Protocol 2: every training take whose expression has other training takes, held out whole and classified by
    models fitted on the other training takes (and by the nearest-frame baseline). Returns the scores and the
    labels of the takes left out."""
    scores = Scores.empty(len(takes.sequence), len(config.styles))
    left_out = []
    counts = {s: sum(include[t] and takes.expressions[t] == s for t in range(len(takes.labels))) for s in config.styles}
    for take in np.flatnonzero(include):
        if counts[takes.expressions[take]] < 2:
            continue
        others = include.copy()
        others[take] = False
        try:
            groups = ordered_sets(takes, config, others)
        except UserError:
            continue  # without this take no sentence is spoken in every expression
        alignment = align_sets(takes.features, takes.frames, groups, config.reference, config.bilinear.dtw_band, memo)
        train = others[takes.sequence]
        held = takes.sequence == take
        models = fit_models(takes, config, train, alignment, np.arange(alignment.frames.shape[1]), held)
        frames = np.flatnonzero(held)
        analysis = analyse(models, config, frames, takes.sequence[frames])
        truth = style_of_frames(takes, groups)
        baseline = nearest_frame_classes(models, config, frames, np.flatnonzero(train), truth[train])
        scores.record(frames, analysis, baseline, int(take))
        left_out.append(takes.labels[take])
    return scores, left_out


# ----------------------------------------------------------------------------------------------- unseen


@dataclass
class Unseen:
    """What the models fitted on every training frame say about the takes of expressions they never saw."""

    predicted: np.ndarray  # (N,) style index (-1 outside unseen takes)
    weights: np.ndarray  # (N, S)
    residual: np.ndarray  # (N,)
    converged: np.ndarray  # (N,) bool
    fidelity: dict[str, Fidelity]  # per unseen expression


def unseen_takes(
    takes: Takes, config: Config, groups: TakeSets, alignment: SetAlignment, include: np.ndarray, memo: dict
) -> Unseen:
    """Protocol 4: analyse every take outside ``include`` with models fitted on all training frames."""
    n, n_styles = len(takes.sequence), len(config.styles)
    out = Unseen(np.full(n, -1), np.full((n, n_styles), np.nan), np.full(n, np.nan), np.ones(n, bool), {})
    unseen = [t for t in range(len(takes.labels)) if not include[t]]
    if not unseen:
        return out
    train = include[takes.sequence]
    models = fit_models(takes, config, train, alignment, np.arange(alignment.frames.shape[1]), ~train)
    for take in unseen:
        frames = np.flatnonzero(takes.sequence == take)
        analysis = analyse(models, config, frames, takes.sequence[frames])
        out.predicted[frames], out.weights[frames] = analysis.classes, analysis.style_weights
        out.residual[frames], out.converged[frames] = analysis.residual, analysis.converged
        fidelity = out.fidelity.setdefault(takes.expressions[take], Fidelity())
        fidelity.add(unseen_fidelity(models, takes, config, groups, alignment, take, frames, analysis, memo))
    return out


def unseen_fidelity(models, takes, config, groups, alignment, take, frames, analysis, memo) -> Fidelity:
    """An unseen take edited into every training expression against the real take of that expression (the first set
    saying the same sentence; none: nothing to compare)."""
    out = Fidelity()
    same = [r for r, sentence in enumerate(groups.set_sentence) if sentence == takes.sentences[take]]
    if not same:
        return out
    r = same[0]
    ref_take = int(groups.sets[r, config.reference])
    aligned, _, _ = align_pair(takes.features, ref_take, int(take), config.bilinear.dtw_band, memo)
    columns = np.flatnonzero(alignment.column_set == r)
    source = frames[aligned]
    content = analysis.content[aligned]
    for s in range(len(config.styles)):
        real = alignment.frames[s, columns]
        out.add(edit_fidelity(models, takes, source, content, real, models.bilinear.style[s]))
    return out


# ----------------------------------------------------------------------------------------------- stage


class FaceEvalParams(AnalysisParams):
    """The evaluation protocol; how frames are analysed (``AnalysisParams``, as in the edit stage); how the models
    are fitted (``aam`` and ``bilinear``: the params of the AamPca and BilinearFit stages)."""

    train: list[str] | None = Field(None, min_length=2)
    folds: int = Field(5, ge=2)
    guard: int = Field(5, ge=0)
    leave_one_take_out: bool = True
    aam: AamParams = AamParams()
    bilinear: BilinearParams = BilinearParams()

    @field_validator("train")
    @classmethod
    def two_different_expressions(cls, train: list[str] | None) -> list[str] | None:
        """``[NEU, NEU]`` is one expression: rejected up front, not after tracking."""
        if train is not None and len(set(train)) < 2:
            raise ValueError(f"needs at least two different training expressions, got {train}")
        return train


FACE_EVAL_OUTPUTS = {
    "expression": Output.array("i", shape=("frames",), doc="index into meta expressions of each frame's take"),
    "kfold_fold": Output.array("i", shape=("frames",), doc="fold that held the frame out (-1: not a training take)"),
    "kfold_predicted": Output.array("i", shape=("frames",), doc="training expression (meta styles) by the model"),
    "kfold_baseline": Output.array("i", shape=("frames",), doc="training expression of the nearest training frame"),
    "loto_predicted": Output.array("i", shape=("frames",), doc="leave-one-take-out prediction (-1: not scored)"),
    "loto_baseline": Output.array("i", shape=("frames",), doc="leave-one-take-out nearest-frame baseline"),
    "weights": Output.array("f", shape=("frames", "styles"), doc="barycentric style weights of each frame's analysis"),
    "residual": Output.array("f", shape=("frames",), doc="relative analysis residual (held-out or unseen frames)"),
    "converged": Output.array("b", shape=("frames",), doc="the frame's analysis converged before max_iter"),
    "confusion": Output.array("i", shape=("styles", "styles"), doc="k-fold counts, row true, column predicted"),
    "baseline_confusion": Output.array("i", shape=("styles", "styles"), doc="the same for the baseline"),
}


class FaceEval(Stage):
    """Style classification (temporal k-fold with a guard band, leave-one-take-out) beside a nearest-frame baseline,
    edit fidelity, analysis residual and convergence, and how unseen expressions are analysed."""

    in_process = True

    Params = FaceEvalParams
    inputs = {
        "tracks": Input.artifact(
            "landmarks", "crops", "crop_landmarks", "sequence", doc="tracking artifact of the labelled takes"
        ),
    }
    outputs = FACE_EVAL_OUTPUTS

    def run(self, params, inputs):
        takes = read_takes(inputs["tracks"], params.bilinear)
        config = model_config(params, takes)
        include = training_mask(takes, config)
        groups = ordered_sets(takes, config, include)
        memo: dict = {}
        alignment = align_sets(takes.features, takes.frames, groups, config.reference, config.bilinear.dtw_band, memo)
        scores, fidelity = kfold(takes, config, groups, alignment)
        loto, left_out = (
            leave_one_take_out(takes, config, include, memo)
            if params.leave_one_take_out
            else (Scores.empty(len(takes.sequence), len(config.styles)), [])
        )
        unseen = unseen_takes(takes, config, groups, alignment, include, memo)
        return pack_eval(takes, config, groups, scores, fidelity, loto, left_out, unseen)


# ----------------------------------------------------------------------------------------------- pack


def kfold_metrics(takes: Takes, config: Config, groups: TakeSets, scores: Scores, fidelity: Fidelity) -> dict:
    """Balanced accuracy of the model and the baseline (all frames, and from the speech onset on), per expression,
    analysis residual and convergence of held-out frames, edit fidelity."""
    truth = style_of_frames(takes, groups)
    held = scores.scored
    n = len(config.styles)
    accuracy, per_style = balanced_accuracy(scores.predicted[held], truth[held], n)
    metrics = {
        "accuracy": accuracy,
        "baseline_accuracy": balanced_accuracy(scores.baseline[held], truth[held], n)[0],
        "chance": 1.0 / n,
        **{f"accuracy_{config.styles[s]}": float(per_style[s]) for s in range(n) if np.isfinite(per_style[s])},
        "residual": float(np.mean(scores.residual[held])),
        "unconverged": float(np.mean(~scores.converged[held])),
        **fidelity.means(""),
    }
    if takes.onsets is not None:
        local = np.arange(len(takes.sequence)) - np.array([f[0] for f in takes.frames])[takes.sequence]
        speech = held & (local >= np.asarray(takes.onsets)[takes.sequence])
        metrics["speech_accuracy"] = balanced_accuracy(scores.predicted[speech], truth[speech], n)[0]
        metrics["speech_baseline_accuracy"] = balanced_accuracy(scores.baseline[speech], truth[speech], n)[0]
    return metrics


def loto_metrics(takes: Takes, groups: TakeSets, config: Config, loto: Scores, left_out: list[str]) -> dict:
    """Leave-one-take-out balanced accuracy of the model and the baseline (only when takes could be left out)."""
    if not left_out:
        return {}
    truth = style_of_frames(takes, groups)
    scored = loto.scored
    n = len(config.styles)
    return {
        "take_accuracy": balanced_accuracy(loto.predicted[scored], truth[scored], n)[0],
        "take_baseline_accuracy": balanced_accuracy(loto.baseline[scored], truth[scored], n)[0],
        "takes_left_out": len(left_out),
    }


def unseen_metrics(takes: Takes, config: Config, unseen: Unseen) -> dict:
    """Per unseen expression: fraction of its frames classified as, and mean weight of, each training expression;
    residual, convergence, edit fidelity."""
    metrics = {}
    for expression in dict.fromkeys(e for e in takes.expressions if e not in config.styles):
        frames = np.isin(takes.sequence, [t for t, e in enumerate(takes.expressions) if e == expression])
        for s, style in enumerate(config.styles):
            metrics[f"unseen_{expression}_as_{style}"] = float(np.mean(unseen.predicted[frames] == s))
            metrics[f"unseen_{expression}_weight_{style}"] = float(np.mean(unseen.weights[frames, s]))
        metrics[f"unseen_{expression}_residual"] = float(np.mean(unseen.residual[frames]))
        metrics[f"unseen_{expression}_unconverged"] = float(np.mean(~unseen.converged[frames]))
        metrics.update(unseen.fidelity[expression].means(f"unseen_{expression}_"))
    return metrics


def eval_warnings(takes: Takes, config: Config, scores: Scores, loto: Scores, unseen: Unseen) -> list[str]:
    """One warning per take and protocol whose analysis stopped at max_iter with frames unconverged."""
    out = []
    for name, result in (
        ("k-fold analysis", scores),
        ("leave-one-take-out analysis", loto),
        ("unseen analysis", unseen),
    ):
        frames = np.flatnonzero(np.isfinite(result.residual))
        out += convergence_warnings(
            result.residual[frames],
            result.converged[frames],
            takes.sequence[frames],
            takes.labels,
            config.analysis.max_iter,
            name,
        )
    return out


def pack_eval(takes, config, groups, scores, fidelity, loto, left_out, unseen) -> Result:
    """The FaceEval artifact: per-frame predictions, confusion matrices, metrics, warnings."""
    truth = style_of_frames(takes, groups)
    held = scores.scored
    n = len(config.styles)
    expressions = list(dict.fromkeys(config.styles + takes.expressions))
    weights = np.where(held[:, None], scores.weights, unseen.weights)
    residual = np.where(held, scores.residual, unseen.residual)
    converged = np.where(held, scores.converged, unseen.converged)
    arrays = {
        "expression": np.array([expressions.index(e) for e in takes.expressions], dtype=np.int64)[takes.sequence],
        "kfold_fold": scores.fold,
        "kfold_predicted": scores.predicted,
        "kfold_baseline": scores.baseline,
        "loto_predicted": loto.predicted,
        "loto_baseline": loto.baseline,
        "weights": weights,
        "residual": residual,
        "converged": converged,
        "confusion": confusion(scores.predicted[held], truth[held], n),
        "baseline_confusion": confusion(scores.baseline[held], truth[held], n),
    }
    metrics = {
        **kfold_metrics(takes, config, groups, scores, fidelity),
        **loto_metrics(takes, groups, config, loto, left_out),
        **unseen_metrics(takes, config, unseen),
    }
    meta = {
        "styles": config.styles,
        "expressions": expressions,
        "labels": takes.labels,
        "take_expression": dict(zip(takes.labels, takes.expressions)),
        "sets": [[takes.labels[int(t)] for t in members] for members in groups.sets],
        "reference": config.styles[config.reference],
        "left_out": left_out,
        "unseen": [label for label, e in zip(takes.labels, takes.expressions) if e not in config.styles],
        "speech_onsets": takes.onsets,
        "aam_params": config.aam.model_dump(),
        "bilinear_params": config.bilinear.model_dump(),
    }
    return Result(arrays, meta=meta, metrics=metrics, warnings=eval_warnings(takes, config, scores, loto, unseen))
