"""The face evaluation stage (stages.eval.face): known answers on synthetic bilinear takes, the nearest-frame
baseline's trap and its failure, real CREMA-D takes, warnings, errors, and a sweep whose table has its metrics."""

from functools import cache

import numpy as np
import pytest
from conftest import ROOT, run_cli
from face_fixtures import CLIPS, bilinear_takes, tracked
from pydantic import ValidationError

from msflow import UserError
from msflow.testing import artifact, prepare_inputs, run_stage
from stages.eval.face import FaceEval, fold_partition, guarded_training

#: the synthetic takes' true appearance model (3 shape modes, 8 texture patterns) and content dimension; they have
#: no audio, so they are aligned by mouth shape
SYNTHETIC = {"aam": {"n_shape": 3, "n_texture": 8}, "bilinear": {"align": "mouth", "content_dim": 3}}


@cache
def evaluate(**takes):
    view, _ = bilinear_takes(**takes)
    return run_stage(FaceEval, SYNTHETIC, {"tracks": view})


def test_known_styles_are_recovered_by_every_protocol():
    run = evaluate()
    m = run.metrics
    assert m["chance"] == pytest.approx(1 / 3)
    assert m["accuracy"] >= 0.97 and m["take_accuracy"] >= 0.95 and m["takes_left_out"] == 9
    assert m["residual"] < 0.01 and m["unconverged"] == 0
    confusion = run.arrays["confusion"]
    assert confusion.sum() == 9 * 30 and np.trace(confusion) >= 0.97 * confusion.sum()
    # every frame of every take is held out by exactly one fold
    assert np.all(run.arrays["kfold_fold"] >= 0) and set(run.arrays["kfold_fold"]) == set(range(5))
    assert run.meta["styles"] == ["E0", "E1", "E2"] and len(run.meta["sets"]) == 3


def test_shuffled_labels_score_chance():
    """Control: each expression label names one take of every true style (a Latin square), so no model can learn a
    label; left-out takes then score no better than chance. Within takes (k-fold) the nearest-frame baseline still
    scores high: it recognises the take, not an expression, which is why it is reported beside the model."""
    m = evaluate(expression_of=lambda s, r: f"E{(s + r) % 3}").metrics
    assert m["take_accuracy"] <= 1 / 3 + 0.1 and m["take_baseline_accuracy"] <= 1 / 3 + 0.1
    assert m["baseline_accuracy"] >= 0.75


def test_the_baseline_fails_where_only_a_model_generalises():
    """Expressions that differ less than the speech does: a left-out take's nearest frames are the same sentence in
    another expression, so the nearest-frame baseline fails, while the bilinear model, which factors speech out,
    classifies it. Within a take (k-fold) the baseline finds same-take neighbours and scores as high as the model:
    the reason the evaluation reports it."""
    m = evaluate(style_spread=0.3, content_spread=0.5).metrics
    assert m["take_accuracy"] >= 0.9 and m["take_baseline_accuracy"] <= 0.2
    assert m["baseline_accuracy"] >= 0.95 and m["accuracy"] >= 0.95


def test_folds_partition_the_takes_and_the_guard_band_keeps_neighbours_out():
    from stages.eval.face import Takes, align_sets, model_config, ordered_sets, read_takes, training_mask

    view, _ = bilinear_takes()
    params = FaceEval.Params(folds=4, guard=3, **SYNTHETIC)
    takes: Takes = read_takes(prepare_inputs(FaceEval, {"tracks": view})["tracks"], params.bilinear)
    config = model_config(params, takes)
    groups = ordered_sets(takes, config, training_mask(takes, config))
    alignment = align_sets(takes.features, takes.frames, groups, config.reference)
    fold = fold_partition(takes, groups, alignment, config.reference, 4)
    assert np.all(fold >= 0)
    for frames in takes.frames:  # contiguous runs, in fold order, each fold non-empty
        assert np.all(np.diff(fold[frames]) >= 0) and set(fold[frames]) == {0, 1, 2, 3}
    train = guarded_training(takes, fold, 2, guard=3)
    for frames in takes.frames:
        held = frames[fold[frames] == 2]
        lo, hi = held[0] - 3, held[-1] + 3
        near = frames[(frames >= lo) & (frames <= hi)]
        assert not train[near].any() and train[np.setdiff1d(frames, near)].all()


# ----------------------------------------------------------------------------------------------- real data


@cache
def crema_d():
    """The six CREMA-D takes of actor 1001 with the fields their file names give."""
    view = tracked(*CLIPS)
    fields = {
        label: {"speaker": "1001", "sentence": "DFA", "expression": CLIPS[label]} for label in view.meta["labels"]
    }
    return artifact({k: view[k] for k in view.names}, {**view.meta, "fields": fields})


@cache
def crema_d_eval():
    return run_stage(FaceEval, {"train": ["NEU", "HAP", "ANG"]}, {"tracks": crema_d()})


def test_crema_d_three_expressions_and_three_unseen():
    run = crema_d_eval()
    m = run.metrics
    assert run.meta["styles"] == ["NEU", "HAP", "ANG"] and run.meta["reference"] == "NEU"
    assert sorted(run.meta["unseen"]) == ["disgust", "fear", "sad"]
    assert m["accuracy"] > 2 * m["chance"] and 0 <= m["baseline_accuracy"] <= 1
    assert "take_accuracy" not in m  # one take per expression: nothing to leave out
    # re-expressing held-out neutral frames brings them closer to the real expression than leaving them neutral
    assert m["edit_landmark_error"] < m["unedited_landmark_error"]
    assert m["edit_texture_error"] < m["unedited_texture_error"]
    for unseen in ("DIS", "FEA", "SAD"):
        fractions = [m[f"unseen_{unseen}_as_{s}"] for s in ("NEU", "HAP", "ANG")]
        assert sum(fractions) == pytest.approx(1)
        assert m[f"unseen_{unseen}_edit_landmark_error"] < m[f"unseen_{unseen}_unedited_landmark_error"]
    weights = run.arrays["weights"]
    np.testing.assert_allclose(weights.sum(1), 1, atol=1e-8)
    unseen = np.isin(run.arrays["expression"], [3, 4, 5])
    assert np.all(run.arrays["kfold_fold"][unseen] == -1) and np.all(run.arrays["kfold_fold"][~unseen] >= 0)


def test_an_unconverged_evaluation_warns_per_take():
    inputs = prepare_inputs(FaceEval, {"tracks": crema_d()})
    params = FaceEval.Params(train=["NEU", "HAP", "ANG"], max_iter=1, tol=1e-15, leave_one_take_out=False)
    result = FaceEval("face").run(params, inputs)
    assert any("k-fold analysis of take 'happy'" in w for w in result.warnings)
    assert any("unseen analysis of take 'sad'" in w for w in result.warnings)
    assert result.metrics["unconverged"] > 0


def test_evaluation_errors_name_the_field():
    inputs = {"tracks": crema_d()}
    with pytest.raises(UserError, match="no take plays") as exc:
        run_stage(FaceEval, {"train": ["NEU", "CALM"]}, inputs)
    assert exc.value.field == "params.train"
    with pytest.raises(ValidationError):
        FaceEval.Params(train=["NEU"])
    with pytest.raises(ValidationError, match="two different"):
        FaceEval.Params(train=["NEU", "NEU"])
    with pytest.raises(ValidationError):
        FaceEval.Params(folds=1)
    with pytest.raises(ValidationError):
        FaceEval.Params(guard=-1)
    with pytest.raises(ValidationError):  # the model params are the stages' own, checked up front too
        FaceEval.Params(bilinear={"align": "video"})
    with pytest.raises(ValidationError):
        FaceEval.Params(aam={"texture_width": 4})


# ----------------------------------------------------------------------------------------------- pipeline


def test_a_sweep_prints_the_evaluation_metrics_as_columns(tmp_path):
    """eval/face.yaml from a fresh copy of the project: `msflow sweep` over a model param gives a table with the
    evaluation's metrics (its `summary:`), the baseline's too although it does not vary with the swept param (three
    takes and two folds, to keep the test short)."""
    import shutil

    project = tmp_path / "project"
    project.mkdir()
    for name in ("eval", "stages", "data", "pyproject.toml"):
        src = ROOT / name
        (shutil.copytree if src.is_dir() else shutil.copy2)(src, project / name)
    out = run_cli(
        project,
        "sweep",
        "eval/face.yaml",
        "-S",
        "face.bilinear.content_dim=4,8",
        "-S",
        "vars.videos=1001_DFA_[NHA]*.flv",
        "-S",
        "face.folds=2",
        "--format",
        "md",
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    table = [line for line in out.stdout.splitlines() if line.startswith("|")]
    header = [cell.strip() for cell in table[0].strip("|").split("|")]
    assert "face.bilinear.content_dim" in header and "face.accuracy" in header and "face.baseline_accuracy" in header
    rows = [[cell.strip() for cell in line.strip("|").split("|")] for line in table[2:]]
    assert [row[header.index("face.bilinear.content_dim")] for row in rows] == ["4", "8"]
    assert all(0 <= float(row[header.index("face.accuracy")]) <= 1 for row in rows)
