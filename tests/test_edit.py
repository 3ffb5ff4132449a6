"""Expression analysis and editing (stages.face.edit, paper Eq 5-7) and the ExpressionEdit stage."""

import io
import warnings

import numpy as np
import pytest
from face_fixtures import aam_run, bilinear_run, edit_run, tracked
from pydantic import ValidationError

from msflow import UserError
from msflow.testing import artifact, run_stage
from stages.face.analysis import (
    BilinearAnalyser,
    analyse_style_content,
    classify_styles,
    initial_content,
    jitter,
    solve_temporal,
    style_barycentric,
)
from stages.face.bilinear import fit_symmetric_bilinear, synthesise, synthesise_grid
from stages.face.edit import (
    ExpressionEdit,
    Keyframe,
    check_extrapolation,
    edit_configuration,
    interpolation_path,
    keyframed_weights,
    weight_vector,
)


@pytest.fixture(scope="module")
def synthetic():
    """A bilinear model fitted exactly to synthetic data: I = S = 3 styles, J = 5, K = 40."""
    rng = np.random.default_rng(0)
    style, content, w = rng.normal(size=(3, 3)), rng.normal(size=(30, 5)), rng.normal(size=(3, 5, 40))
    fit = fit_symmetric_bilinear(synthesise_grid(w, style, content), 3, 5)
    assert fit.error < 1e-20
    return fit


def test_analysis_recovers_training_styles_and_content_exactly(synthetic):
    fit = synthetic
    s_idx, c_idx = np.meshgrid(np.arange(3), np.arange(30), indexing="ij")
    y = synthesise(fit.w, fit.style[s_idx.ravel()], fit.content[c_idx.ravel()])
    result = analyse_style_content(fit.w, fit.style, fit.content.mean(0), y, tol=1e-14, max_iter=500)
    assert result.converged
    assert np.max(result.residual / np.sum(y**2, -1)) < 1e-10
    np.testing.assert_allclose(style_barycentric(result.style, fit.style), np.eye(3)[s_idx.ravel()], atol=1e-5)
    np.testing.assert_array_equal(classify_styles(result.style, fit.style)[0], s_idx.ravel())


def test_analysis_recovers_barycentric_mixtures_and_fixes_the_gauge(synthetic):
    fit = synthetic
    rng = np.random.default_rng(1)
    alpha = rng.dirichlet(np.ones(3), 200)
    content = fit.content[rng.integers(0, 30, 200)] * rng.uniform(0.8, 1.2, (200, 1))
    y = synthesise(fit.w, alpha @ fit.style, content)
    result = analyse_style_content(
        fit.w, fit.style, initial_content(y, _model(fit), "nearest"), y, tol=1e-14, max_iter=1000
    )
    ok = result.residual / np.sum(y**2, -1) < 1e-10
    assert ok.mean() > 0.97  # rare local minima are allowed, not common
    np.testing.assert_allclose(style_barycentric(result.style, fit.style)[ok], alpha[ok], atol=1e-5)
    mean_style = fit.style.mean(0)
    np.testing.assert_allclose(result.style @ mean_style, mean_style @ mean_style, rtol=1e-10)
    np.testing.assert_allclose(synthesise(fit.w, result.style, result.content)[ok], y[ok], atol=1e-6)


def _model(fit):
    from stages.face.bilinear import BilinearModel

    return BilinearModel(fit.w, fit.style, fit.content, ["a", "b", "c"])


def test_batched_analysis_equals_frame_by_frame(synthetic):
    fit = synthetic
    rng = np.random.default_rng(2)
    y = synthesise(fit.w, rng.dirichlet(np.ones(3), 12) @ fit.style, fit.content[:12]) + rng.normal(0, 0.1, (12, 40))
    batch = analyse_style_content(fit.w, fit.style, fit.content.mean(0), y, tol=1e-13)
    for f in range(12):
        single = analyse_style_content(fit.w, fit.style, fit.content.mean(0), y[f : f + 1], tol=1e-13)
        np.testing.assert_allclose(single.style[0], batch.style[f], atol=1e-6)


def test_solve_temporal_equals_the_dense_normal_equations():
    rng = np.random.default_rng(3)
    f, d = 9, 3
    a = rng.normal(size=(f, d, d))
    gram = a @ a.transpose(0, 2, 1) + 0.1 * np.eye(d)
    rhs = rng.normal(size=(f, d))
    p = rng.normal(size=(f - 1, d, d))
    pair = p @ p.transpose(0, 2, 1)
    dense = np.zeros((f * d, f * d))
    for t in range(f):
        dense[t * d : (t + 1) * d, t * d : (t + 1) * d] += gram[t]
    for t in range(f - 1):
        sl, sr = slice(t * d, (t + 1) * d), slice((t + 1) * d, (t + 2) * d)
        dense[sl, sl] += pair[t]
        dense[sr, sr] += pair[t]
        dense[sl, sr] -= pair[t]
        dense[sr, sl] -= pair[t]
    expected = np.linalg.solve(dense, rhs.reshape(-1)).reshape(f, d)
    np.testing.assert_allclose(solve_temporal(gram, rhs, pair), expected, rtol=1e-6, atol=1e-8)
    scalar = solve_temporal(gram, rhs, 0.7)
    np.testing.assert_allclose(scalar, solve_temporal(gram, rhs, np.broadcast_to(0.7 * np.eye(d), (f - 1, d, d))))


def test_temporal_prior_trades_jitter_for_residual(synthetic):
    fit = synthetic
    rng = np.random.default_rng(4)
    f = 150
    t = np.linspace(0, 1, f)
    alpha = np.c_[t, 1 - t, np.zeros(f)]
    pos = np.linspace(0, 29, f)
    content = np.stack([np.interp(pos, np.arange(30), fit.content[:, j]) for j in range(5)], axis=-1)
    clean = synthesise(fit.w, alpha @ fit.style, content)
    y = clean + rng.normal(size=clean.shape) * 0.2 * clean.std()
    start = initial_content(y, _model(fit), "nearest")
    paper = analyse_style_content(fit.w, fit.style, start, y)
    plain = BilinearAnalyser(fit.w, fit.style).analyse(y, start)  # same thing through the class
    np.testing.assert_allclose(plain.style, paper.style)
    jitters, residuals, errors = [], [], []
    for lam in (0.0, 0.1, 1.0, 10.0):
        r = analyse_style_content(fit.w, fit.style, start, y, smooth=lam)
        jitters.append(jitter(r.style))
        residuals.append(float(np.sum(r.residual)))
        errors.append(float(np.mean(np.abs(style_barycentric(r.style, fit.style) - alpha))))
    assert all(a > b for a, b in zip(jitters, jitters[1:]))  # smoother with every step of lambda
    assert all(a <= b * (1 + 1e-9) for a, b in zip(residuals, residuals[1:]))  # fit to the noisy data worsens
    assert residuals[-1] < 1.2 * residuals[0]  # but only a little
    assert min(errors[1:]) < 0.5 * errors[0]  # and the style is closer to the truth


def test_classify_and_barycentric_agree_for_orthonormal_styles(synthetic):
    fit = synthetic
    alpha = np.array([[0.7, 0.2, 0.1], [0.1, 0.1, 0.8], [-0.2, 0.7, 0.5]])
    e = alpha @ fit.style
    np.testing.assert_allclose(style_barycentric(e, fit.style), alpha, atol=1e-12)
    classes, cosine = classify_styles(e, fit.style)
    np.testing.assert_array_equal(classes, [0, 2, 1])
    assert np.all(np.abs(cosine) <= 1 + 1e-12)


def test_edit_configuration_is_eq7(synthetic):
    fit = synthetic
    c = fit.content[:4]
    half = edit_configuration(fit.w, fit.style, np.array([0.5, 0.5, 0.0]), c)
    np.testing.assert_allclose(
        half, 0.5 * synthesise(fit.w, fit.style[[0]], c) + 0.5 * synthesise(fit.w, fit.style[[1]], c)
    )
    np.testing.assert_allclose(
        edit_configuration(fit.w, fit.style, np.eye(3)[[2] * 4], c), synthesise_grid(fit.w, fit.style, c)[2]
    )


def test_weights_validation_and_keyframes():
    labels = ["neutral", "happy", "angry"]
    np.testing.assert_allclose(weight_vector({"happy": 0.25, "angry": 0.75}, labels, "params.mix"), [0, 0.25, 0.75])
    with pytest.raises(UserError, match="sum to 1"):
        weight_vector({"happy": 0.5}, labels, "params.mix")
    with pytest.raises(UserError, match="unknown expression"):
        weight_vector({"sad": 1.0}, labels, "params.mix")
    keys = [Keyframe(time=1.0, weights={"angry": 1.0}), Keyframe(time=0.0, weights={"happy": 1.0})]
    weights = keyframed_weights(keys, labels, np.array([-1.0, 0.0, 0.25, 1.0, 2.0]), "params.keyframes")
    np.testing.assert_allclose(weights, [[0, 1, 0], [0, 1, 0], [0, 0.75, 0.25], [0, 0, 1], [0, 0, 1]])
    with pytest.raises(UserError, match="distinct"):
        keyframed_weights([keys[0], keys[0]], labels, np.zeros(2), "params.keyframes")


def test_extrapolation_bound():
    assert not check_extrapolation(np.array([0.2, 0.8]), 0.3, "params.mix")
    with pytest.warns(UserWarning, match="extrapolate"):
        assert check_extrapolation(np.array([-0.2, 1.2]), 0.3, "params.mix")
    with pytest.raises(UserError, match="max_extrapolation"):
        check_extrapolation(np.array([-0.5, 1.5]), 0.3, "params.mix")


def test_interpolation_path_visits_every_expression_once():
    weights, names = interpolation_path(["happy", "neutral", "angry"], ["neutral", "happy", "angry"], 4)
    assert len(weights) == 7 and names[0] == "happy" and names[3] == "neutral" and names[-1] == "angry"
    np.testing.assert_allclose(weights.sum(1), 1)
    np.testing.assert_allclose(weights[3], [1, 0, 0])


# ----------------------------------------------------------------------------------------------- stage


def test_edit_stage_outputs_follow_the_contract(tmp_path):
    run = edit_run()
    a, meta = run.arrays, run.meta
    frames = len(tracked("sad")["landmarks"])
    labels = meta["labels"]
    assert labels == ["neutral", "happy", "angry"] and meta["targets"] == labels
    assert a["shapes"].shape == (3, frames, 68, 2) and a["shapes"].dtype == np.float32
    assert a["style"].shape[0] == frames and a["content"].shape[0] == frames
    assert a["weights"].shape == (3, frames, 3) and a["frames"].shape[:2] == (frames, 3)
    assert meta["mixes"] == [] and "mixed_shapes" not in a
    np.testing.assert_array_equal(a["sequence"], 0)
    np.testing.assert_allclose(a["time"], tracked("sad")["time"])
    assert meta["fps"] == pytest.approx(29.97, abs=0.01)
    np.testing.assert_allclose(a["style_weights"].sum(1), 1, atol=1e-8)
    assert sum(meta["classified_as"].values()) == frames
    # edited shapes live in the mean-shape frame (inter-ocular distance 1) and are the synthesis of y
    from stages.face.aam import AamModel, interocular_distance

    model = AamModel.from_view(aam_run().view())
    np.testing.assert_allclose(a["shapes"], model.reconstruct_shapes(model.split(a["y"])[0]), atol=1e-5)
    assert np.all(np.abs(interocular_distance(a["shapes"]) - 1) < 0.2)
    assert run.metrics["mean_residual"] < 0.5
    # store round trip keeps the file outputs
    stored = run_stage(
        ExpressionEdit,
        {"video": False},
        {"model": bilinear_run(), "aam": aam_run(), "tracks": tracked("sad")},
        store=tmp_path,
    )
    assert "video" not in stored.arrays and stored.arrays["strip"].dtype == np.uint8


def test_edit_stage_writes_a_side_by_side_video_and_a_strip():
    import av
    import cv2

    run = edit_run()
    crops = tracked("sad")["crops"]
    frames, h, w = crops.shape
    with av.open(io.BytesIO(run.arrays["video"].tobytes())) as container:
        stream = container.streams.video[0]
        decoded = [f.to_ndarray(format="gray") for f in container.decode(stream)]
    assert len(decoded) == frames
    assert decoded[0].shape[0] >= h and decoded[0].shape[1] >= 4 * w
    strip = cv2.imdecode(run.arrays["strip"], cv2.IMREAD_UNCHANGED)
    assert strip.shape[0] == h and strip.shape[1] >= 7 * w
    # the input panel of the video is the input crop (up to H.264 loss and the caption)
    assert np.mean(np.abs(decoded[10][20:h, :w].astype(float) - crops[10][20:h].astype(float))) < 6


def test_edited_frames_change_the_face_and_keep_the_background():
    run = edit_run()
    crops = tracked("sad")["crops"].astype(float)
    happy = run.arrays["frames"][:, run.meta["targets"].index("happy")].astype(float)
    shapes = run.arrays["crop_shapes"][0]
    h, w = crops.shape[1:]
    ys, xs = np.mgrid[0:h, 0:w]
    face = np.zeros(crops.shape, dtype=bool)
    for f, shape in enumerate(shapes):
        lo, hi = shape.min(0) - 3, shape.max(0) + 3
        face[f] = (xs >= lo[0]) & (xs <= hi[0]) & (ys >= lo[1]) & (ys <= hi[1])
    assert np.mean(np.abs(happy - crops)[~face]) < 0.5
    assert np.mean(np.abs(happy - crops)[face]) > 2


def test_edit_stage_mix_and_keyframes():
    times = tracked("sad")["time"]
    params = {
        "targets": ["happy"],
        "mix": {"happy": 0.5, "angry": 0.5},
        "video": False,
        "keyframes": [{"time": 0.0, "weights": {"happy": 1.0}}, {"time": float(times[-1]), "weights": {"angry": 1.0}}],
    }
    run = run_stage(ExpressionEdit, params, {"model": bilinear_run(), "aam": aam_run(), "tracks": tracked("sad")})
    assert run.meta["targets"] == ["happy"] and run.meta["mixes"] == ["mix", "keyframed"]
    assert run.arrays["shapes"].shape[0] == 1 and run.arrays["mixed_shapes"].shape[0] == 2
    keyed = run.arrays["mixed_weights"][1]
    np.testing.assert_allclose(keyed[0], [0, 1, 0])
    np.testing.assert_allclose(keyed[-1], [0, 0, 1])
    np.testing.assert_allclose(run.arrays["mixed_weights"][0], np.broadcast_to([0, 0.5, 0.5], keyed.shape))
    # the keyframed edit starts as the pure happy edit, the constant mix is the average of happy and angry
    np.testing.assert_allclose(run.arrays["mixed_y"][1][0], run.arrays["y"][0][0], atol=1e-8)
    both = run_stage(
        ExpressionEdit,
        {"targets": ["happy", "angry"], "video": False},
        {"model": bilinear_run(), "aam": aam_run(), "tracks": tracked("sad")},
    )
    np.testing.assert_allclose(run.arrays["mixed_y"][0], both.arrays["y"].mean(0), atol=1e-8)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = run_stage(
            ExpressionEdit,
            {"mix": {"happy": 1.2, "neutral": -0.2}, "video": False},
            {"model": bilinear_run(), "aam": aam_run(), "tracks": tracked("sad")},
        )
    assert out.meta["extrapolated"] and any("extrapolate" in str(w.message) for w in caught)
    with pytest.raises(ValidationError, match="max_extrapolation"):
        ExpressionEdit.Params(mix={"happy": 2.0, "neutral": -1.0})


@pytest.mark.parametrize(
    "params, message",
    [
        ({"mix": {"happy": 0.5}}, "sum to 1"),
        ({"mix": {"happy": float("nan"), "angry": 1.0}}, "finite"),
        ({"keyframes": []}, "at least 1"),
        ({"keyframes": [{"time": 0.0, "weights": {"happy": 1}}] * 2}, "distinct"),
        ({"keyframes": [{"time": 0.0, "weights": {"happy": 0.9}}]}, "sum to 1"),
        ({"keyframes": [{"time": 0.0, "weights": {"happy": 1.8, "angry": -0.8}}]}, "max_extrapolation"),
        ({"targets": []}, "nothing to synthesise"),
        ({"strip_path": ["happy"]}, "at least 2"),
        ({"strip_steps": 1}, "greater than or equal to 2"),
        ({"strip_frame": -1}, "greater than or equal to 0"),
    ],
)
def test_edit_params_are_checked_before_the_stage_runs(params, message):
    """Every rule that needs no model is a params rule, so `msflow status` and `run` reject it up front."""
    with pytest.raises(ValidationError, match=message):
        ExpressionEdit.Params(**params)


def test_edit_stage_errors():
    sad = tracked("sad")
    inputs = {"model": bilinear_run(), "aam": aam_run()}
    arrays = {k: np.array(sad[k]) for k in sad.names}
    other_scheme = artifact(arrays, {**sad.meta, "landmark_scheme": "openface68"})
    with pytest.raises(UserError, match="landmark scheme 'openface68' differs"):
        run_stage(ExpressionEdit, {"video": False}, {**inputs, "tracks": other_scheme})
    broken = dict(arrays)
    broken["landmarks"] = arrays["landmarks"].copy()
    broken["landmarks"][3, 10] = np.nan
    with pytest.raises(UserError, match="NaN"):
        run_stage(ExpressionEdit, {"video": False}, {**inputs, "tracks": artifact(broken, dict(sad.meta))})
    # a bilinear model from another appearance model (different K)
    model_view = bilinear_run().view()
    wrong = {k: model_view[k] for k in model_view.names}
    wrong["W"] = wrong["W"][..., :-1]
    with pytest.raises(UserError, match="same aam artifact"):
        run_stage(
            ExpressionEdit,
            {"video": False},
            {"model": artifact(wrong, dict(model_view.meta)), "aam": aam_run(), "tracks": sad},
        )
    with pytest.raises(UserError, match="not a training expression"):
        run_stage(ExpressionEdit, {"targets": ["sad"], "video": False}, {**inputs, "tracks": sad})
    with pytest.raises(ValidationError):
        ExpressionEdit.Params(smooth=-1)


def test_edit_figures_render():
    run = edit_run()
    for name, fig in ExpressionEdit.figures.items():
        out = fig(run.view(), {})
        assert isinstance(out, bytes) or hasattr(out, "savefig"), name


def test_smoothing_in_the_stage_treats_each_take_as_its_own_sequence():
    two = tracked("happy", "sad")
    params = {"smooth": 1.0, "video": False, "targets": ["neutral"]}
    inputs = {"model": bilinear_run(), "aam": aam_run()}
    both = run_stage(ExpressionEdit, params, {**inputs, "tracks": two})
    sad_only = run_stage(ExpressionEdit, params, {**inputs, "tracks": tracked("sad")})
    is_sad = two["sequence"] == 1
    np.testing.assert_allclose(both.arrays["style"][is_sad], sad_only.arrays["style"], atol=1e-6)
    assert both.meta["test_labels"] == ["happy", "sad"]


# ----------------------------------------------------------------------------------------------- weighted analysis


def test_component_weights_and_the_weighted_model():
    from stages.face.analysis import component_weights
    from stages.face.bilinear import BilinearModel

    np.testing.assert_array_equal(component_weights(2, 5, 0.25), [0.25, 0.25, 1, 1, 1])
    rng = np.random.default_rng(7)
    model = BilinearModel(
        rng.normal(size=(3, 4, 6)),
        rng.normal(size=(3, 3)),
        rng.normal(size=(10, 4)),
        ["a", "b", "c"],
        rng.normal(size=(3, 4)),
        2.5,
    )
    d = component_weights(2, 7, 0.3)
    weighted = model.weighted(d)
    y = rng.normal(size=(5, 6))
    np.testing.assert_allclose(weighted.augment(y * d[:6]), model.augment(y) * d)
    np.testing.assert_allclose(weighted.w_full, model.w_full * d)
    with pytest.raises(ValueError):
        model.weighted(np.ones(4))


def test_weighted_analysis_reads_the_style_from_the_weighted_rows_and_the_content_from_all(synthetic):
    """With the first rows weighted 0, their values cannot change the style; the content is Eq 6 on every row."""
    from stages.face.analysis import analyse_takes, component_weights

    fit = synthetic
    model = _model(fit)
    rng = np.random.default_rng(8)
    alpha = rng.dirichlet(np.ones(3), 20)
    clean = synthesise(fit.w, alpha @ fit.style, fit.content[:20])
    d = component_weights(8, 40, 0.0)
    seq = np.zeros(20, dtype=int)
    exact = analyse_takes(model, clean, seq, init="nearest", weights=d, tol=1e-14, max_iter=500)
    np.testing.assert_allclose(exact.style, alpha @ fit.style, atol=1e-6)  # noise-free: still exact
    np.testing.assert_allclose(exact.residual, 0, atol=1e-8 * np.sum(clean**2, -1).max())
    disturbed = clean.copy()
    disturbed[:, :8] += rng.normal(size=(20, 8)) * clean.std()
    moved = analyse_takes(model, disturbed, seq, init="nearest", weights=d, tol=1e-14, max_iter=500)
    np.testing.assert_allclose(moved.style, exact.style, atol=1e-6)  # the weighted-out rows do not count
    # ... but the content solves Eq 6 with every row, given that style
    expected = BilinearAnalyser(fit.w, fit.style).content_given_style(disturbed, moved.style)
    np.testing.assert_allclose(moved.content, expected, atol=1e-10)
    assert not np.allclose(moved.content, exact.content, atol=1e-3)
    np.testing.assert_allclose(
        moved.residual, np.sum((disturbed - synthesise(fit.w, moved.style, moved.content)) ** 2, -1)
    )
    # unit weights are the paper's analysis
    paper = analyse_takes(model, disturbed, seq, init="nearest")
    unit = analyse_takes(model, disturbed, seq, init="nearest", weights=np.ones(40))
    np.testing.assert_allclose(unit.style, paper.style, atol=1e-8)
    np.testing.assert_allclose(unit.content, paper.content, atol=1e-6)


def test_classification_by_fit_is_the_maximum_likelihood_style(synthetic):
    from stages.face.analysis import classify_by_fit, style_fit_residuals

    fit = synthetic
    model = _model(fit)
    rng = np.random.default_rng(9)
    labels = rng.integers(0, 3, 40)
    c = rng.normal(size=(40, 5))
    clean = synthesise(fit.w, fit.style[labels], c)
    res = style_fit_residuals(model, clean)
    np.testing.assert_allclose(res[np.arange(40), labels], 0, atol=1e-8 * np.sum(clean**2, -1).max())
    noisy = clean + rng.normal(size=clean.shape) * 0.05 * clean.std()
    classes, res = classify_by_fit(model, noisy)
    np.testing.assert_array_equal(classes, labels)
    # brute force: least squares of y on the columns of e_s' W for every style
    for s in range(3):
        basis = np.einsum("i,ijk->kj", fit.style[s], fit.w)
        coef = np.linalg.lstsq(basis, noisy.T, rcond=None)[0]
        np.testing.assert_allclose(res[:, s], np.sum((basis @ coef - noisy.T) ** 2, 0), rtol=1e-8)


def test_edit_stage_analysis_weight_one_is_the_papers_analysis():
    from stages.face.aam import AamModel
    from stages.face.bilinear import BilinearModel

    inputs = {"model": bilinear_run(), "aam": aam_run(), "tracks": tracked("sad")}
    paper = run_stage(ExpressionEdit, {"video": False, "targets": ["happy"], "analysis_shape_weight": 1.0}, inputs)
    bilinear = BilinearModel.from_view(bilinear_run().view())
    model = AamModel.from_view(aam_run().view())
    t = tracked("sad")
    y = bilinear.augment(model.project(t["landmarks"], t["crops"], t["crop_landmarks"]).y)
    direct = analyse_style_content(bilinear.w_full, bilinear.style, bilinear.mean_content, y)
    np.testing.assert_allclose(paper.arrays["style"], direct.style, atol=1e-8)
    assert paper.meta["analysis_shape_weight"] == 1.0
    default = edit_run()
    assert default.meta["analysis_shape_weight"] == 0.0 and default.meta["classify"] == "cosine"
    assert not np.allclose(default.arrays["style"], paper.arrays["style"], atol=1e-3)
    # style_fit_residual is relative, one column per training expression; classify: fit uses it
    fitres = default.arrays["style_fit_residual"]
    assert fitres.shape == (len(y), 3) and np.all((fitres >= 0) & (fitres <= 1 + 1e-9))
    by_fit = run_stage(ExpressionEdit, {"video": False, "targets": ["happy"], "classify": "fit"}, inputs)
    np.testing.assert_array_equal(by_fit.arrays["classification"], np.argmin(fitres, axis=1))
    with pytest.raises(ValidationError):
        ExpressionEdit.Params(classify="vote")
    with pytest.raises(ValidationError):
        ExpressionEdit.Params(analysis_shape_weight=-1)


# ----------------------------------------------------------------------------------------------- blocks, warnings


def edit_inputs(*labels):
    from msflow.testing import prepare_inputs

    tracks = tracked(*labels) if labels else tracked("sad")
    return prepare_inputs(ExpressionEdit, {"model": bilinear_run(), "aam": aam_run(), "tracks": tracks})


def test_edit_by_blocks_of_frames_equals_the_whole_take():
    """Projection, Eq 7 and the edited crops run block by block; the result does not depend on the block size:
    the same bytes, except y of the projection, equal to 1e-12 of its scale (BLAS sums in another order)."""
    from stages.face.analysis import analyse_frames
    from stages.face.edit import EditParams, check_edit_inputs, edit_targets, project_by_blocks, render_edits

    take = check_edit_inputs(edit_inputs())
    n = len(take.landmarks)
    whole, blocks = project_by_blocks(take.model, take, block=n), project_by_blocks(take.model, take, block=7)
    np.testing.assert_allclose(blocks.y, whole.y, rtol=0, atol=1e-12 * np.abs(whole.y).max())
    for name in ("crop_similarity", "texture_offset", "texture_scale", "aligned_shapes"):
        np.testing.assert_array_equal(getattr(blocks, name), getattr(whole, name))
    params = EditParams(mix={"happy": 0.5, "angry": 0.5})
    analysis = analyse_frames(take.bilinear, take.model.n_shape, whole.y, take.sequence, params)
    targets = edit_targets(params, take.bilinear.labels, take.times)
    one_frames, many_frames = [], []
    one = render_edits(take, whole, analysis.content, targets, True, one_frames.append, block=n)
    many = render_edits(take, whole, analysis.content, targets, True, many_frames.append, block=7)
    assert len(one_frames) == 1 and len(many_frames) == -(-n // 7)
    np.testing.assert_array_equal(np.concatenate(many_frames), one_frames[0])
    for name in ("y", "shapes", "crop_shapes"):
        np.testing.assert_array_equal(getattr(many, name), getattr(one, name))
    assert many.video == one.video  # the encoder is deterministic, whatever the blocks


def test_the_edit_streams_its_crops_through_output_sinks(tmp_path):
    """In a store run the edited crops are written chunk by chunk (sinks); the stored artifact holds the same crops
    as the stage renders in memory."""
    from stages.face.edit import check_edit_inputs

    params = {"mix": {"happy": 0.5, "angry": 0.5}, "video": False}
    stage = ExpressionEdit("edit")
    result = stage.run(ExpressionEdit.Params(**params), edit_inputs())
    assert set(stage.sinks) == {"frames", "mixed_frames"}
    frames = stage.sinks["frames"].to_array()
    n = len(check_edit_inputs(edit_inputs()).landmarks)
    assert frames.shape[:2] == (n, 3) and result.arrays["frames"] is stage.sinks["frames"]
    stored = run_stage(ExpressionEdit, params, edit_inputs(), store=tmp_path)
    np.testing.assert_array_equal(stored.arrays["frames"], frames)
    np.testing.assert_array_equal(stored.arrays["mixed_frames"], stage.sinks["mixed_frames"].to_array())


def test_an_unconverged_analysis_warns_naming_the_take_and_its_residual():
    params = ExpressionEdit.Params(max_iter=1, tol=1e-15, video=False, targets=["happy"])
    result = ExpressionEdit("edit").run(params, edit_inputs("happy", "sad"))
    assert len(result.warnings) == 2 and "take 'happy'" in result.warnings[0] and "take 'sad'" in result.warnings[1]
    assert all("max_iter=1" in w and "relative residual" in w for w in result.warnings)
    assert result.metrics["unconverged_frames"] > 0 and not result.meta["converged"]
    settled = ExpressionEdit("edit").run(ExpressionEdit.Params(video=False, targets=["happy"]), edit_inputs())
    assert settled.warnings == [] and settled.metrics["unconverged_frames"] == 0


def test_a_face_the_model_cannot_express_warns():
    """The CREMA-D model analysing a synthetic face (another 'person'): a large residual, and a warning naming the
    take; the actor's own unseen take does not warn."""
    from face_fixtures import bilinear_takes

    stranger, _ = bilinear_takes(takes_per_style=1, frames=20)
    inputs = {"model": bilinear_run(), "aam": aam_run(), "tracks": stranger}
    run = run_stage(ExpressionEdit, {"video": False, "targets": ["happy"]}, inputs)
    poor = [w for w in run.warnings if "explained poorly" in w]
    assert run.metrics["mean_residual"] > 0.45 and len(poor) == 3 and "take 's0_r0'" in poor[0]
    assert not [w for w in edit_run().warnings if "explained poorly" in w]


def test_the_edit_on_two_threads_equals_one():
    """``-j 2`` pastes the edited faces on two threads; the artifact does not change (it is not in the key)."""
    params = {"targets": ["happy"], "video": True}
    one = run_stage(ExpressionEdit, params, edit_inputs())
    two = run_stage(ExpressionEdit, params, edit_inputs(), jobs=2)
    for name in ("frames", "crop_shapes", "y", "video"):
        np.testing.assert_array_equal(np.asarray(two.arrays[name]), np.asarray(one.arrays[name]))
