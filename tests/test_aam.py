"""Appearance model (stages.face.aam, paper Eq 1-3): Procrustes, PCA, texture sampling, project/reconstruct, stage."""

import numpy as np
import pytest
from face_fixtures import aam_run, face_template, synthetic_faces, tracked, training_tracks
from pydantic import ValidationError

from msflow import UserError
from msflow.testing import artifact, run_stage
from stages.face.aam import (
    AamModel,
    AamPca,
    apply_similarity,
    canonical_pose,
    choose_modes,
    eye_centres,
    fit_aam,
    fit_pca,
    generalised_procrustes,
    heldout_pca_error,
    interocular_distance,
    project,
    reconstruct,
    similarity_align,
    temporal_folds,
)


def subspace_angle(a, b):
    from scipy.linalg import subspace_angles

    return float(np.max(subspace_angles(np.asarray(a).T, np.asarray(b).T)))


# ----------------------------------------------------------------------------------------------- Procrustes


def test_similarity_align_recovers_a_known_similarity():
    target = canonical_pose(face_template())
    sim = np.array([[37.0, 0.2, 60.0, 70.0], [2.0, -1.0, -5.0, 3.0]])
    shapes = apply_similarity(np.stack([target, target]), sim)
    aligned, found = similarity_align(shapes, target)
    np.testing.assert_allclose(aligned, np.stack([target, target]), atol=1e-10)
    np.testing.assert_allclose(found[:, 0], sim[:, 0], rtol=1e-10)
    np.testing.assert_allclose(np.angle(np.exp(1j * (found[:, 1] - sim[:, 1]))), 0, atol=1e-10)
    np.testing.assert_allclose(apply_similarity(aligned, found), shapes, atol=1e-9)


def test_canonical_pose_gauge():
    shape = apply_similarity(face_template()[None], np.array([[25.0, 0.7, 3.0, -4.0]]))[0]
    canon = canonical_pose(shape)
    left, right = eye_centres(canon)
    np.testing.assert_allclose(canon.mean(0), 0, atol=1e-12)
    assert abs(right[1] - left[1]) < 1e-12 and right[0] > left[0]
    assert interocular_distance(canon) == pytest.approx(1.0)
    np.testing.assert_allclose(canon, canonical_pose(face_template()), atol=1e-12)


def test_generalised_procrustes_removes_pose_and_keeps_the_deformation():
    shapes, coef, similarity, local = synthetic_faces(60, seed=1)
    aligned, mean, found = generalised_procrustes(shapes)
    np.testing.assert_allclose(apply_similarity(aligned, found), shapes, atol=1e-8)
    assert interocular_distance(mean) == pytest.approx(1.0)
    # poses vary by +-0.3 rad and 30-45x scale; once aligned, the shapes are (to first order in the small
    # deformations) a linear function of the three true mode coefficients
    flat = aligned.reshape(60, -1)
    design = np.c_[coef, np.ones(60)]
    residual = flat - design @ np.linalg.lstsq(design, flat, rcond=None)[0]
    assert np.sum(residual**2) < 0.03 * np.sum((flat - flat.mean(0)) ** 2)
    pca = fit_pca(flat)
    assert pca.eigenvalues[:3].sum() / pca.total_variance > 0.97
    # without the alignment the same regression explains little: pose dominates
    raw = (shapes - shapes.mean(1, keepdims=True)).reshape(60, -1)
    raw_residual = raw - design @ np.linalg.lstsq(design, raw, rcond=None)[0]
    assert np.sum(raw_residual**2) > 0.5 * np.sum((raw - raw.mean(0)) ** 2)


def test_fit_pca_gram_trick_matches_svd():
    rng = np.random.default_rng(2)
    low = rng.normal(size=(12, 4)) @ rng.normal(size=(4, 300)) + rng.normal(0, 0.01, (12, 300))
    gram = fit_pca(low, n_modes=4)  # 12 frames < 300 dims: Gram matrix path
    svd = fit_pca(np.vstack([low] * 30), n_modes=4)  # 360 rows >= 300: SVD path, same variance directions
    assert subspace_angle(gram.basis, svd.basis) < 1e-6
    np.testing.assert_allclose(gram.basis @ gram.basis.T, np.eye(4), atol=1e-10)
    centred = low - low.mean(0)
    np.testing.assert_allclose(gram.eigenvalues, np.linalg.svd(centred, compute_uv=False)[:4] ** 2 / 11, rtol=1e-8)


def test_choose_modes_by_variance_and_count():
    evals = np.array([5.0, 3.0, 1.0, 0.5, 0.5])
    assert choose_modes(evals, 0.5, None) == 1
    assert choose_modes(evals, 0.8, None) == 2
    assert choose_modes(evals, 0.9, None) == 3
    assert choose_modes(evals, 1.0, None) == 5
    assert choose_modes(evals, 0.5, 4) == 4


def test_heldout_error_decreases_and_vanishes_for_low_rank_data():
    rng = np.random.default_rng(4)
    data = rng.normal(size=(50, 3)) @ rng.normal(size=(3, 40))
    folds = temporal_folds(np.repeat([0, 1], 25), 5)
    err = heldout_pca_error(data, folds, 6)
    assert err[0] == pytest.approx(1.0)
    assert np.all(np.diff(err) <= 1e-12)
    assert err[3] < 1e-6


def test_temporal_folds_hold_out_one_window_of_every_take():
    sequence = np.repeat([0, 1, 2], [10, 7, 12])
    folds = temporal_folds(sequence, 3)
    assert sorted(np.concatenate(folds).tolist()) == list(range(29))
    for fold in folds:
        for take in range(3):
            frames = fold[sequence[fold] == take]
            assert len(frames) and np.all(np.diff(frames) == 1)


# ----------------------------------------------------------------------------------------------- model


def painted_crops(shapes, model_points, texture_image, size=128):
    """Crops showing the same texture (in the model's texture frame) drawn onto each shape."""
    from stages.face.warp import PiecewiseAffineWarp, delaunay_triangles

    tri = delaunay_triangles(model_points)
    warp = PiecewiseAffineWarp(model_points, tri, (texture_image.shape[1], texture_image.shape[0]))
    crops = []
    for shape in shapes:
        image, mask = warp.draw_on_shape(warp.fill_outside(texture_image), shape, (size, size))
        crops.append(np.where(mask, image, 90.0))
    return np.clip(np.round(crops), 0, 255).astype(np.uint8)


def test_fit_aam_on_synthetic_faces_recovers_shape_modes_and_a_rigid_texture():
    from stages.face.aam import texture_reference

    shapes, coef, similarity, _ = synthetic_faces(40, seed=5)
    points, size = texture_reference(canonical_pose(face_template()), 64)
    ys, xs = np.mgrid[0 : size[1], 0 : size[0]]
    texture = (110 + 50 * np.sin(xs / 6.0) * np.cos(ys / 7.0)).astype(np.float32)
    crops = painted_crops(shapes, points, texture)
    model, proj = fit_aam(shapes, crops, shapes, shape_variance=0.99)
    assert model.n_shape == 3  # three true modes; the rest is < 1% (Procrustes curvature)
    # the texture never changes (only its shape does), so the shape-free textures are nearly identical
    assert model.texture_eigenvalues.sum() < 0.05 * len(model.texture_mean)
    assert model.shape_weight == pytest.approx(np.sqrt(model.texture_eigenvalues.sum() / model.shape_eigenvalues.sum()))
    np.testing.assert_allclose(proj.y[:, : model.n_shape], model.shape_weight * proj.b_s)
    # shape_balance scales r and nothing else
    lighter, proj_lighter = fit_aam(shapes, crops, shapes, shape_variance=0.99, shape_balance=0.25)
    assert lighter.shape_weight == pytest.approx(0.25 * model.shape_weight)
    np.testing.assert_allclose(proj_lighter.b_s, proj.b_s, atol=1e-10)
    np.testing.assert_allclose(proj_lighter.y[:, : model.n_shape], 0.25 * proj.y[:, : model.n_shape], atol=1e-10)
    np.testing.assert_allclose(lighter.split(proj_lighter.y)[0], proj.b_s, atol=1e-10)
    # b_s is a linear function of the true coefficients (first order in small deformations)
    design = np.c_[coef, np.ones(len(coef))]
    fit = np.linalg.lstsq(design, proj.b_s, rcond=None)
    explained = 1 - np.sum((design @ fit[0] - proj.b_s) ** 2) / np.sum((proj.b_s - proj.b_s.mean(0)) ** 2)
    assert explained > 0.97


def test_project_reconstruct_round_trip_and_test_take_is_projected_not_refitted():
    view = aam_run().view()
    model = AamModel.from_view(view)
    tracks = training_tracks()
    again = project(model, tracks["landmarks"], tracks["crops"], tracks["crop_landmarks"])
    np.testing.assert_allclose(again.y, view["y"], atol=1e-8)
    shapes, textures = reconstruct(model, again.y)
    assert shapes.shape == (len(again.y), 68, 2) and textures.shape == (len(again.y), len(model.texture_mean))
    rms = np.sqrt(np.mean(np.sum((shapes - again.aligned_shapes) ** 2, -1)))
    assert rms < 0.02  # 98% shape variance kept: a few hundredths of an IOD
    # a new take: projected through the same bases, nothing refitted
    sad = tracked("sad")
    before = {k: np.array(view[k]) for k in ("mean_shape", "shape_basis", "texture_basis")}
    p = model.project(sad["landmarks"], sad["crops"], sad["crop_landmarks"])
    assert p.y.shape == (len(sad["landmarks"]), model.n_shape + model.n_texture)
    for k, v in before.items():
        np.testing.assert_array_equal(getattr(model, k), v)
    # held-out take reconstructs worse than training frames but still far better than the mean alone
    shapes_s, _ = model.reconstruct(p.y)
    err = np.mean(np.sum((shapes_s - p.aligned_shapes) ** 2, -1))
    base = np.mean(np.sum((model.mean_shape - p.aligned_shapes) ** 2, -1))
    assert err < 0.5 * base


def test_aam_stage_outputs_follow_the_contract(tmp_path):
    run = run_stage(AamPca, {}, {"tracks": training_tracks()}, store=tmp_path)
    a, meta = run.arrays, run.meta
    frames = len(training_tracks()["landmarks"])
    n_s, n_g = meta["n_shape"], meta["n_texture"]
    assert a["mean_shape"].shape == (68, 2) and a["shape_basis"].shape == (n_s, 136)
    assert a["b_s"].shape == (frames, n_s) and a["b_g"].shape == (frames, n_g)
    assert a["y"].shape == (frames, n_s + n_g) and a["aligned_shapes"].shape == (frames, 68, 2)
    assert a["similarity"].shape == (frames, 4) and a["texture_basis"].shape[0] == n_g
    np.testing.assert_array_equal(a["sequence"], training_tracks()["sequence"])
    assert meta["labels"] == ["neutral", "happy", "angry"] and meta["texture_width"] == 64
    assert a["texture_mask"].shape[1] == 64 and a["texture_mask"].sum() == a["texture_mean"].shape[0]
    # Eq 3 balance: r^2 = sum(lambda_g) / sum(lambda_s)
    assert meta["shape_weight"] ** 2 == pytest.approx(a["texture_eigenvalues"].sum() / a["shape_eigenvalues"].sum())
    # similarity maps the aligned shapes back onto the tracked landmarks
    back = apply_similarity(a["aligned_shapes"], a["similarity"])
    np.testing.assert_allclose(back, training_tracks()["landmarks"], atol=1e-3)
    assert 0 < run.metrics["heldout_shape_error"] < 0.5 and 0 < run.metrics["heldout_texture_error"] < 1
    assert run.metrics["shape_variance_kept"] >= 0.98
    for name, fig in AamPca.figures.items():
        out = fig(run.view(), {})
        assert hasattr(out, "savefig"), name


def test_aam_stage_rejects_bad_landmarks():
    tracks = training_tracks()
    arrays = {k: np.array(tracks[k]) for k in ("landmarks", "crops", "crop_landmarks", "sequence")}
    arrays["landmarks"][70, 5] = np.nan
    with pytest.raises(UserError, match="NaN.*happy"):
        run_stage(AamPca, {}, {"tracks": artifact(arrays, dict(tracks.meta))})
    arrays["landmarks"] = np.zeros((len(arrays["sequence"]), 5, 2), np.float32)
    with pytest.raises(UserError, match="68"):
        run_stage(AamPca, {}, {"tracks": artifact(arrays, dict(tracks.meta))})


def test_aam_params_are_validated():
    with pytest.raises(ValidationError):
        AamPca.Params(shape_variance=1.5)
    with pytest.raises(ValidationError):
        AamPca.Params(texture_width=4)


def test_similarity_parameters_round_trip_through_the_shared_fit():
    """aam's [scale, angle, tx, ty] similarities are the shared geometry module's (2, 3) transforms."""
    from stages.geometry.similarity import similarity_from_parameters, similarity_parameters

    params = np.array([[1.5, 0.3, 2.0, -1.0], [0.7, -2.9, 0.0, 5.0]])
    np.testing.assert_allclose(similarity_parameters(similarity_from_parameters(params)), params, atol=1e-12)
