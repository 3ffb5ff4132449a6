"""Symmetric bilinear model (stages.face.bilinear, paper Eq 4, Tenenbaum & Freeman 2000) and the BilinearFit stage."""

import numpy as np
import pytest
from face_fixtures import aam_run, bilinear_run, training_tracks
from pydantic import ValidationError

from msflow import UserError
from msflow.testing import artifact, run_stage
from stages.face.bilinear import (
    BilinearFit,
    BilinearModel,
    check_dimensions,
    fit_bilinear_model,
    fit_symmetric_bilinear,
    stack_observations,
    subspace_angles,
    synthesise,
    synthesise_grid,
    vector_transpose,
)


def true_model(seed=0, s=5, c=40, k=30, i=3, j=4):
    rng = np.random.default_rng(seed)
    style, content, w = rng.normal(size=(s, i)), rng.normal(size=(c, j)), rng.normal(size=(i, j, k))
    return style, content, w, synthesise_grid(w, style, content)


# ----------------------------------------------------------------------------------------------- algebra


def test_vector_transpose_moves_blocks_and_keeps_vectors():
    k = 3
    x = np.arange(2 * k * 4).reshape(2 * k, 4)  # 2 x 4 blocks of 3-vectors
    xt = vector_transpose(x, k)
    assert xt.shape == (4 * k, 2)
    for p in range(2):
        for q in range(4):
            np.testing.assert_array_equal(xt[q * k : (q + 1) * k, p], x[p * k : (p + 1) * k, q])
    np.testing.assert_array_equal(vector_transpose(xt, k), x)
    with pytest.raises(ValueError):
        vector_transpose(np.zeros((7, 2)), 3)


def test_stacked_form_matches_eq4():
    """Y = [W^VT A]^VT B (NOTES.md) equals y_k(s, c) = e_s' W_k c_c."""
    style, content, w, y = true_model(1, s=4, c=6, k=5, i=2, j=3)
    i, j, k = w.shape
    w_stacked = w.transpose(0, 2, 1).reshape(i * k, j)  # block row i, column j
    stacked = vector_transpose(vector_transpose(w_stacked, k) @ style.T, k) @ content.T
    np.testing.assert_allclose(stacked, stack_observations(y), atol=1e-12)
    np.testing.assert_allclose(synthesise(w, style[2], content[4]), y[2, 4], atol=1e-12)


def test_noise_free_model_is_reproduced_exactly_with_the_true_subspaces():
    style, content, w, y = true_model(2)
    fit = fit_symmetric_bilinear(y, 3, 4)
    assert fit.converged and fit.error < 1e-8
    np.testing.assert_allclose(synthesise_grid(fit.w, fit.style, fit.content), y, atol=1e-8 * np.abs(y).max())
    assert np.max(subspace_angles(fit.style.T, style.T)) < 1e-6  # column spaces over the S styles
    assert np.max(subspace_angles(fit.content.T, content.T)) < 1e-6
    np.testing.assert_allclose(fit.style.T @ fit.style, np.eye(3), atol=1e-10)  # orthonormal rows of A
    np.testing.assert_allclose(fit.content.T @ fit.content, np.eye(4), atol=1e-10)


def test_noise_degrades_the_fit_gracefully():
    style, content, w, y = true_model(3)
    rng = np.random.default_rng(3)
    previous_angle = 0.0
    for level in (1e-3, 1e-2, 1e-1):
        noisy = y + rng.normal(size=y.shape) * level * y.std()
        fit = fit_symmetric_bilinear(noisy, 3, 4)
        clean_error = np.sum((synthesise_grid(fit.w, fit.style, fit.content) - y) ** 2) / np.sum(y**2)
        angle = max(np.max(subspace_angles(fit.style.T, style.T)), np.max(subspace_angles(fit.content.T, content.T)))
        assert fit.error < 2 * level**2  # residual is about the noise energy
        assert clean_error < level**2  # and the model is closer to the truth than the data
        assert angle < 5 * level and angle > previous_angle
        previous_angle = angle


def test_alternation_is_monotone_when_style_dim_is_below_the_number_of_styles():
    style, content, w, y = true_model(4, s=6, i=2, j=3)
    noisy = y + np.random.default_rng(4).normal(size=y.shape) * 0.3 * y.std()
    fit = fit_symmetric_bilinear(noisy, 2, 3, tol=1e-14, max_iter=200)
    assert len(fit.errors) > 2
    assert np.all(np.diff(fit.errors[:-1]) <= 1e-12)


def test_dimension_errors_name_the_parameter():
    with pytest.raises(UserError, match="two expressions"):
        check_dimensions(1, 50, 20, 1, 3)
    with pytest.raises(UserError, match="style_dim 4") as exc:
        check_dimensions(3, 50, 20, 4, 3)
    assert exc.value.field == "params.style_dim"
    with pytest.raises(UserError, match="content_dim 60") as exc:
        check_dimensions(3, 50, 20, 3, 60)
    assert exc.value.field == "params.content_dim"


def test_mean_component_makes_the_model_uncentred():
    style, content, w, y = true_model(5, s=3, c=30, k=12, i=3, j=4)
    centred, _ = fit_bilinear_model(y, ["a", "b", "c"], content_dim=4, mean_weight=0.0)
    assert centred.w_mean is None and centred.w_full.shape == (3, 4, 12)
    model, fit = fit_bilinear_model(y, ["a", "b", "c"], content_dim=5, mean_weight=1.0)
    kappa = np.sqrt(np.mean(np.sum(y**2, -1)))
    assert model.mean_component == pytest.approx(kappa)
    assert model.w_full.shape == (3, 5, 13)
    aug = model.augment(y[0, :2])
    assert aug.shape == (2, 13) and np.all(aug[:, -1] == kappa)
    # every training observation reproduces the constant component too
    grid = synthesise_grid(model.w_full, model.style, model.content)
    np.testing.assert_allclose(grid[..., -1], kappa, rtol=1e-6)
    np.testing.assert_allclose(model.synthesise(model.style[:, None], model.content[None]), y, atol=1e-6 * kappa)


# ----------------------------------------------------------------------------------------------- stage


def test_bilinear_stage_on_the_crema_d_takes(tmp_path):
    aam = aam_run()
    run = run_stage(BilinearFit, {}, {"aam": aam, "tracks": training_tracks()}, store=tmp_path)
    a, meta = run.arrays, run.meta
    k = aam.arrays["y"].shape[1]
    i, j = meta["style_dim"], meta["content_dim"]
    assert a["W"].shape == (i, j, k) and a["W_mean"].shape == (i, j)
    assert a["style"].shape == (3, i) and meta["labels"] == ["neutral", "happy", "angry"]
    assert meta["reference"] == "neutral"
    n_ref = int(np.sum(aam.arrays["sequence"] == 0))
    assert a["content"].shape == (n_ref, j) and a["aligned_frames"].shape == (3, n_ref)
    # aligned frames index each take's own frames, monotonically, from its first to its last frame
    sequence = aam.arrays["sequence"]
    for s in range(3):
        frames = a["aligned_frames"][s]
        assert np.all(sequence[frames] == s) and np.all(np.diff(frames) >= 0)
        own = np.flatnonzero(sequence == s)
        assert frames[0] == own[0] and frames[-1] == own[-1]
    np.testing.assert_array_equal(a["aligned_frames"][0], np.flatnonzero(sequence == 0))
    assert run.metrics["train_error"] < 0.1
    model = BilinearModel.from_view(run.view())
    y = aam.arrays["y"][a["aligned_frames"]]
    recon = model.synthesise(model.style[:, None], model.content[None])
    assert np.sum((recon - y) ** 2) / np.sum(y**2) == pytest.approx(run.metrics["train_error"], rel=1e-6)


def test_audio_and_mouth_alignment_agree_roughly():
    audio = bilinear_run("audio").arrays["aligned_local"]
    mouth = bilinear_run("mouth").arrays["aligned_local"]
    assert np.median(np.abs(audio - mouth)) <= 3  # frames, at 30 fps


def test_bilinear_stage_errors():
    aam = aam_run()
    view = aam.view()
    with pytest.raises(UserError, match="needs the tracking artifact"):
        run_stage(BilinearFit, {"align": "audio"}, {"aam": view})
    lengths = np.bincount(view["sequence"])
    shortest = int(np.argmin(lengths))
    too_many = int(lengths[shortest]) + 1
    with pytest.raises(
        UserError, match=f"take '{view.meta['labels'][shortest]}' has {lengths[shortest]} frames.*at least {too_many}"
    ) as exc:
        run_stage(BilinearFit, {"content_dim": too_many}, {"aam": view, "tracks": training_tracks()})
    assert exc.value.field == "params.content_dim"
    with pytest.raises(UserError, match="style_dim 4"):
        run_stage(BilinearFit, {"style_dim": 4, "align": "mouth"}, {"aam": view})
    one = {k: view[k] for k in view.names}
    keep = one["sequence"] == 0
    single = artifact(
        {k: (v[keep] if v.shape[:1] == keep.shape else v) for k, v in one.items()}, {**view.meta, "labels": ["neutral"]}
    )
    with pytest.raises(UserError, match="at least two"):
        run_stage(BilinearFit, {"align": "mouth"}, {"aam": single})
    with pytest.raises(UserError, match="reference expression 'sad'"):
        run_stage(BilinearFit, {"align": "mouth", "reference": "sad"}, {"aam": view})
    with pytest.raises(ValidationError):
        BilinearFit.Params(align="video")


def test_bilinear_figure_renders():
    run = bilinear_run()
    for name, fig in BilinearFit.figures.items():
        assert hasattr(fig(run.view(), {}), "savefig"), name


def test_the_fit_learns_each_takes_expression_from_its_field():
    """Nine takes, three expressions (their 'expression' field, not their labels) by three sentences: one style per
    expression, one set of aligned takes per sentence, and the model explains the takes almost exactly."""
    from face_fixtures import bilinear_takes

    from stages.face.aam import AamPca

    view, truth = bilinear_takes()
    aam = run_stage(AamPca, {"n_shape": 3, "n_texture": 8}, {"tracks": view})
    assert aam.meta["fields"] == view.meta["fields"]
    run = run_stage(BilinearFit, {"align": "mouth", "content_dim": 3}, {"aam": aam})
    meta, a = run.meta, run.arrays
    assert meta["labels"] == ["E0", "E1", "E2"] and meta["takes"] == view.meta["labels"]
    assert meta["take_expression"]["s2_r1"] == "E2" and meta["reference"] == "E0"
    assert meta["sets"] == [[f"s{s}_r{r}" for s in range(3)] for r in range(3)]
    assert a["style"].shape == (3, 3) and a["content"].shape == (3 * 30, 3)
    sequence = aam.arrays["sequence"]
    takes = np.asarray(view.meta["labels"])[sequence[a["aligned_frames"]]]
    for s in range(3):  # row s holds frames of expression s only, set by set
        assert all(label.startswith(f"s{s}_") for label in takes[s])
    np.testing.assert_array_equal(a["content_set"], np.repeat(np.arange(3), 30))
    assert run.metrics["train_error"] < 0.01
    assert meta["params"]["content_dim"] == 3 and meta["params"]["align"] == "mouth"


def test_takes_of_a_sentence_missing_an_expression_are_left_out_and_none_left_is_an_error():
    from stages.face.alignment import group_takes

    groups = group_takes(["a", "b", "a", "b", "a"], ["x", "x", "y", "y", "z"])
    assert groups.styles == ["a", "b"] and groups.skipped == ["z"]
    np.testing.assert_array_equal(groups.sets, [[0, 1], [2, 3]])
    cycled = group_takes(["a", "b", "a"], ["x", "x", "x"])  # two takes of 'a', one of 'b': b's take is reused
    np.testing.assert_array_equal(cycled.sets, [[0, 1], [2, 1]])
    ordered = group_takes(["a", "b", "c"], ["x", "x", "x"], order=["c", "a"], include=np.array([1, 0, 1], bool))
    assert ordered.styles == ["c", "a"] and ordered.take_style.tolist() == [1, -1, 0]
    from stages.face.bilinear import TrainingTakes, training_sets

    takes = TrainingTakes(["1", "2"], np.array([0, 1]), ["a", "b"], ["x", "y"])
    with pytest.raises(UserError, match="no sentence is spoken in every expression"):
        training_sets(takes)


def test_a_fit_stopped_at_max_iter_warns_with_its_error():
    # One iteration cannot converge (convergence compares two errors); two may already reach an exact fixed point
    # with some CPUs' BLAS kernels, so the test would depend on the machine.
    run = run_stage(BilinearFit, {"max_iter": 1, "tol": 1e-300, "align": "mouth"}, {"aam": aam_run()})
    assert not run.meta["converged"] and run.meta["iterations"] == 1
    assert len(run.warnings) == 1 and "max_iter=1" in run.warnings[0] and "relative training error" in run.warnings[0]
    assert bilinear_run("mouth").warnings == []
