"""Expression blending (Eq 9): alpha from constants, keyframes or the analysed style; clipping; errors."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from msflow import UserError
from msflow.testing import artifact, run_stage
from stages.retarget.blend import (
    Blend,
    alpha_from_analysis,
    barycentric_coordinates,
    interpolate_keyframes,
    project_to_simplex,
)

TARGETS = ["neutral", "happy", "angry"]
MORPHS = ["jawOpen", "mouthSmile_L", "mouthSmile_R", "browDown_L", "browDown_R"]
FPS = 30.0


def retarget_inputs(frames=24, seed=0, counts=(2, 3, 2), scale=0.4):
    """Keyshapes and keymorphs artifacts with random non-negative weights (zero outside own keyshapes)."""
    rng = np.random.default_rng(seed)
    expression = np.repeat(np.arange(3), counts).astype(np.int32)
    total = len(expression)
    weights = np.zeros((3, frames, total), np.float32)
    for t in range(3):
        own = expression == t
        weights[t][:, own] = rng.random((frames, own.sum())) * scale
    G = rng.random((total, len(MORPHS))).astype(np.float32)
    ids = [f"{TARGETS[e]}/{i}" for e, i in zip(expression, np.concatenate([np.arange(c) for c in counts]))]
    keyshapes = artifact(
        {"weights": weights, "keyshape_expression": expression},
        meta={"labels": TARGETS, "targets": TARGETS, "fps": FPS, "keyshape_ids": ids},
    )
    keymorphs = artifact({"keymorph_weights": G}, meta={"target_names": MORPHS, "keyshape_ids": ids})
    return keyshapes, keymorphs


def per_expression(keyshapes, keymorphs):
    return np.einsum(
        "tfk,km->tfm", keyshapes["weights"].astype(np.float64), keymorphs["keymorph_weights"].astype(np.float64)
    )


# ------------------------------------------------------------------------------------------------------ maths


@settings(max_examples=60, deadline=None)
@given(arrays(np.float64, st.tuples(st.integers(1, 6), st.integers(1, 6)), elements=st.floats(-5, 5, allow_nan=False)))
def test_simplex_projection_is_the_nearest_simplex_point(points):
    projected = project_to_simplex(points)
    assert np.all(projected >= 0)
    np.testing.assert_allclose(projected.sum(axis=1), 1.0, atol=1e-9)
    np.testing.assert_allclose(project_to_simplex(projected), projected, atol=1e-9)  # idempotent
    # optimality: no random simplex point is closer
    rng = np.random.default_rng(0)
    others = rng.dirichlet(np.ones(points.shape[1]), size=50)
    for p, q in zip(points, projected):
        assert np.linalg.norm(p - q) <= np.linalg.norm(others - p, axis=1).min() + 1e-9


def test_barycentric_coordinates_recover_mixtures():
    rng = np.random.default_rng(1)
    vertices = rng.normal(size=(3, 5))
    true = rng.dirichlet(np.ones(3), size=20)
    np.testing.assert_allclose(barycentric_coordinates(true @ vertices, vertices), true, atol=1e-10)
    np.testing.assert_allclose(alpha_from_analysis(vertices, vertices), np.eye(3), atol=1e-10)
    # outside the triangle: affine coordinates go negative, the projection brings them back
    outside = 1.5 * vertices[1] - 0.5 * vertices[0]
    coords = barycentric_coordinates(outside[None], vertices)[0]
    np.testing.assert_allclose(coords, [-0.5, 1.5, 0.0], atol=1e-10)
    np.testing.assert_allclose(alpha_from_analysis(outside[None], vertices)[0], [0, 1, 0], atol=1e-10)


def test_keyframe_interpolation():
    key_t = np.array([1.0, 0.0, 2.0])  # unsorted on purpose
    key_v = np.array([[0, 1, 0], [1, 0, 0], [0, 0, 1]], float)
    t = np.array([-1.0, 0.0, 0.5, 1.0, 1.5, 2.0, 3.0])
    lin = interpolate_keyframes(t, key_t, key_v, "linear")
    np.testing.assert_allclose(
        lin, [[1, 0, 0], [1, 0, 0], [0.5, 0.5, 0], [0, 1, 0], [0, 0.5, 0.5], [0, 0, 1], [0, 0, 1]]
    )
    step = interpolate_keyframes(t, key_t, key_v, "step")
    np.testing.assert_allclose(step[[2, 4]], [[1, 0, 0], [0, 1, 0]])
    smooth = interpolate_keyframes(np.array([0.25]), key_t, key_v, "smooth")
    np.testing.assert_allclose(smooth, [[1 - 0.15625, 0.15625, 0]])
    np.testing.assert_allclose(interpolate_keyframes(t, np.array([0.7]), key_v[:1]), np.repeat(key_v[:1], 7, 0))


# ------------------------------------------------------------------------------------------------------ stage


def test_constant_alpha_is_the_weighted_sum_of_the_expression_animations():
    keyshapes, keymorphs = retarget_inputs()
    out = run_stage(
        Blend, {"alpha": {"happy": 0.25, "neutral": 0.75}}, {"keyshapes": keyshapes, "keymorphs": keymorphs}
    )
    per = per_expression(keyshapes, keymorphs)
    expected = np.clip(0.75 * per[0] + 0.25 * per[1], 0, 1)
    np.testing.assert_allclose(out.arrays["weights"], expected, atol=1e-6)
    np.testing.assert_allclose(out.arrays["alpha"], np.tile([0.75, 0.25, 0.0], (24, 1)))
    np.testing.assert_allclose(out.arrays["expression_weights"], per, atol=1e-6)
    np.testing.assert_allclose(out.arrays["time"], np.arange(24) / FPS)
    assert out.meta["target_names"] == MORPHS and out.meta["fps"] == FPS
    assert out.meta["alpha_mode"] == "constant"
    assert out.metrics["mean_alpha_neutral"] == pytest.approx(0.75)


def test_one_hot_alpha_selects_one_expression_and_clipping_is_measured():
    keyshapes, keymorphs = retarget_inputs(scale=1.0)  # big weights: some sums exceed 1
    per = per_expression(keyshapes, keymorphs)
    out = run_stage(Blend, {"alpha": {"angry": 1.0}}, {"keyshapes": keyshapes, "keymorphs": keymorphs})
    w = out.arrays["weights"]
    assert w.min() >= 0 and w.max() <= 1
    np.testing.assert_allclose(w, np.clip(per[2], 0, 1), atol=1e-6)
    assert out.metrics["clipped_fraction"] == pytest.approx((per[2] > 1 + 1e-6).mean())
    assert out.metrics["clipped_fraction"] > 0
    assert out.metrics["max_weight_unclipped"] == pytest.approx(per[2].max(), rel=1e-6)
    small = run_stage(
        Blend, {"alpha": {"angry": 1.0}}, dict(zip(("keyshapes", "keymorphs"), retarget_inputs(scale=0.05)))
    )
    assert small.metrics["clipped_fraction"] == 0


def test_keyframed_alpha_moves_between_expressions():
    keyshapes, keymorphs = retarget_inputs(frames=31)
    params = {"alpha": {"keyframes": {0.0: {"neutral": 1.0}, 1.0: {"happy": 0.5, "angry": 0.5}}}}
    out = run_stage(Blend, params, {"keyshapes": keyshapes, "keymorphs": keymorphs})
    alpha = out.arrays["alpha"]
    np.testing.assert_allclose(alpha[0], [1, 0, 0])
    np.testing.assert_allclose(alpha[15], [0.5, 0.25, 0.25], atol=1e-6)
    np.testing.assert_allclose(alpha[30], [0, 0.5, 0.5], atol=1e-6)
    per = per_expression(keyshapes, keymorphs)
    np.testing.assert_allclose(
        out.arrays["weights"][15], np.clip(0.5 * per[0, 15] + 0.25 * per[1, 15] + 0.25 * per[2, 15], 0, 1), atol=1e-6
    )
    step = run_stage(
        Blend, {"alpha": dict(params["alpha"], interpolation="step")}, {"keyshapes": keyshapes, "keymorphs": keymorphs}
    )
    np.testing.assert_allclose(step.arrays["alpha"][29], [1, 0, 0])


def analysis_inputs(frames=24, seed=3):
    """Edit/bilinear artifacts whose analysed style is a known mixture of the training styles."""
    rng = np.random.default_rng(seed)
    training = rng.normal(size=(3, 3))
    t = np.linspace(0, 1, frames)
    true_alpha = np.c_[1 - t, t * 0.7, t * 0.3]
    style = true_alpha @ training
    edit = artifact({"style": style.astype(np.float32)}, meta={"labels": TARGETS, "fps": FPS})
    bilinear = artifact({"style": training.astype(np.float32)}, meta={"labels": TARGETS})
    return edit, bilinear, true_alpha


def test_alpha_from_analysis_recovers_the_mixture():
    keyshapes, keymorphs = retarget_inputs()
    edit, bilinear, true_alpha = analysis_inputs()
    out = run_stage(Blend, {}, {"keyshapes": keyshapes, "keymorphs": keymorphs, "edit": edit, "bilinear": bilinear})
    np.testing.assert_allclose(out.arrays["alpha"], true_alpha, atol=1e-5)
    assert out.meta["alpha_mode"] == "from_analysis"
    smoothed = run_stage(
        Blend,
        {"alpha_smoothing": 0.2},
        {"keyshapes": keyshapes, "keymorphs": keymorphs, "edit": edit, "bilinear": bilinear},
    )
    np.testing.assert_allclose(smoothed.arrays["alpha"].sum(axis=1), 1.0, atol=1e-5)
    assert smoothed.arrays["alpha"].min() >= 0


def test_alpha_from_analysis_uses_only_edited_expressions_in_training_order():
    keyshapes, keymorphs = retarget_inputs()
    edit, bilinear, _ = analysis_inputs()
    # the bilinear model lists its styles in another order and has one more expression than was edited
    training = bilinear["style"]
    order = [2, 0, 1]
    extra = np.vstack([training[order], training.mean(0, keepdims=True) + 5])
    shuffled = artifact({"style": extra}, meta={"labels": [TARGETS[i] for i in order] + ["sad"]})
    a = run_stage(Blend, {}, {"keyshapes": keyshapes, "keymorphs": keymorphs, "edit": edit, "bilinear": bilinear})
    b = run_stage(Blend, {}, {"keyshapes": keyshapes, "keymorphs": keymorphs, "edit": edit, "bilinear": shuffled})
    np.testing.assert_allclose(a.arrays["alpha"], b.arrays["alpha"], atol=1e-5)


def test_vertices_output_poses_the_character():
    keyshapes, keymorphs = retarget_inputs(frames=5)
    rng = np.random.default_rng(4)
    character = artifact(
        {
            "neutral": rng.normal(size=(10, 3)).astype(np.float32),
            "deltas": rng.normal(size=(len(MORPHS), 10, 3)).astype(np.float32),
        },
        meta={"target_names": MORPHS},
    )
    out = run_stage(
        Blend,
        {"alpha": {"neutral": 1.0}, "vertices": True},
        {"keyshapes": keyshapes, "keymorphs": keymorphs, "character": character},
    )
    expected = character["neutral"] + np.einsum("fm,mvc->fvc", out.arrays["weights"], character["deltas"])
    np.testing.assert_allclose(out.arrays["vertices"], expected, atol=1e-5)
    plain = run_stage(Blend, {"alpha": {"neutral": 1.0}}, {"keyshapes": keyshapes, "keymorphs": keymorphs})
    assert "vertices" not in plain.arrays
    with pytest.raises(UserError, match="needs the character"):
        run_stage(
            Blend, {"alpha": {"neutral": 1.0}, "vertices": True}, {"keyshapes": keyshapes, "keymorphs": keymorphs}
        )


def test_round_trip_through_the_store_and_figures(tmp_path):
    from matplotlib.figure import Figure

    keyshapes, keymorphs = retarget_inputs()
    out = run_stage(Blend, {"alpha": {"happy": 1.0}}, {"keyshapes": keyshapes, "keymorphs": keymorphs}, store=tmp_path)
    assert out.arrays["weights"].dtype == np.float32
    for name, figure in Blend.figures.items():
        assert isinstance(figure(out.view(), {}), Figure), name


@pytest.mark.parametrize(
    "alpha, message, field",
    [
        ({"happy": 0.7, "neutral": 0.5}, "sum to 1.*1.2", "params.alpha"),
        ({"happy": 1.2, "neutral": -0.2}, r"must be >= 0.*-0.2", "params.alpha"),
        ({"happy": 0.5, "surprised": 0.5}, r"unknown expressions \['surprised'\].*neutral", "params.alpha"),
        ({"keyframes": {0.0: {"happy": 1.0}, 1.0: {"happy": 0.5}}}, "sum to 1", "params.alpha.keyframes.1"),
        ({"keyframes": {}}, "empty", "params.alpha.keyframes"),
    ],
)
def test_bad_alpha_is_a_user_error(alpha, message, field):
    keyshapes, keymorphs = retarget_inputs()
    with pytest.raises(UserError, match=message) as err:
        run_stage(Blend, {"alpha": alpha}, {"keyshapes": keyshapes, "keymorphs": keymorphs})
    assert err.value.field == field


def test_alpha_sum_tolerance():
    keyshapes, keymorphs = retarget_inputs()
    out = run_stage(
        Blend,
        {"alpha": {"happy": 0.3334, "neutral": 0.3333, "angry": 0.3333}},
        {"keyshapes": keyshapes, "keymorphs": keymorphs},
    )
    np.testing.assert_allclose(out.arrays["alpha"].sum(axis=1), 1.0, atol=1e-6)


def test_inconsistent_inputs_are_user_errors():
    keyshapes, keymorphs = retarget_inputs()
    edit, bilinear, _ = analysis_inputs()
    with pytest.raises(UserError, match="needs the edit and bilinear"):
        run_stage(Blend, {}, {"keyshapes": keyshapes, "keymorphs": keymorphs})
    with pytest.raises(UserError, match="needs the bilinear"):
        run_stage(Blend, {}, {"keyshapes": keyshapes, "keymorphs": keymorphs, "edit": edit})
    fast_edit = artifact({"style": edit["style"]}, meta={"fps": 25.0})
    with pytest.raises(UserError, match="frame-rate mismatch"):
        run_stage(Blend, {"alpha": {"happy": 1}}, {"keyshapes": keyshapes, "keymorphs": keymorphs, "edit": fast_edit})
    short_edit = artifact({"style": edit["style"][:10]}, meta={"fps": FPS})
    with pytest.raises(UserError, match="frame-count mismatch"):
        run_stage(Blend, {"alpha": {"happy": 1}}, {"keyshapes": keyshapes, "keymorphs": keymorphs, "edit": short_edit})
    other_keyshapes, other_keymorphs = retarget_inputs(counts=(3, 3, 2))
    with pytest.raises(UserError, match="made for other keyshapes"):
        run_stage(Blend, {"alpha": {"happy": 1}}, {"keyshapes": other_keyshapes, "keymorphs": keymorphs})
    renamed = artifact(
        {"keymorph_weights": keymorphs["keymorph_weights"]}, meta={"target_names": MORPHS, "keyshape_ids": ["x"] * 7}
    )
    with pytest.raises(UserError, match="different keyshapes"):
        run_stage(Blend, {"alpha": {"happy": 1}}, {"keyshapes": keyshapes, "keymorphs": renamed})
    wrong_style = artifact({"style": np.ones((3, 4))}, meta={"labels": TARGETS})
    with pytest.raises(UserError, match="style vectors do not match"):
        run_stage(Blend, {}, {"keyshapes": keyshapes, "keymorphs": keymorphs, "edit": edit, "bilinear": wrong_style})
    no_fps = artifact(
        {"weights": keyshapes["weights"], "keyshape_expression": keyshapes["keyshape_expression"]},
        meta={"labels": TARGETS, "targets": TARGETS},
    )
    with pytest.raises(UserError, match="no frame rate"):
        run_stage(Blend, {"alpha": {"happy": 1}}, {"keyshapes": no_fps, "keymorphs": keymorphs})


# ------------------------------------------------------------------------------------------- real data (CREMA-D)


def test_crema_blend_carries_the_expression_into_the_morph_weights():
    from test_keyshapes import crema_face_branch

    from stages.retarget.character import GltfCharacter
    from stages.retarget.keymorphs import KeymorphFit

    branch = crema_face_branch()
    character = run_stage(GltfCharacter, {}, {"mesh": {"path": "data/characters/ict-facekit.glb"}}).view()
    keymorphs = run_stage(
        KeymorphFit,
        {"contact_sheet": False},
        {"keyshapes": branch.keyshapes, "character": character, "tracks": branch.train},
    )
    inputs = {
        "keyshapes": branch.keyshapes,
        "keymorphs": keymorphs.view(),
        "edit": branch.edit,
        "bilinear": branch.bilinear,
    }
    names = character.meta["target_names"]
    smile = [names.index(n) for n in ("mouthSmile_L", "mouthSmile_R")]
    brow = [names.index(n) for n in ("browDown_L", "browDown_R")]
    out = {e: run_stage(Blend, {"alpha": {e: 1.0}}, inputs) for e in ("happy", "angry")}
    happy, angry = out["happy"].arrays["weights"], out["angry"].arrays["weights"]
    assert happy[:, smile].mean() > angry[:, smile].mean()
    assert angry[:, brow].mean() > happy[:, brow].mean()
    for run in out.values():
        assert run.metrics["clipped_fraction"] < 0.05
        assert len(run.arrays["weights"]) == len(branch.edit["style"])
    analysed = run_stage(Blend, {}, inputs)
    alpha = analysed.arrays["alpha"]
    assert alpha.min() >= 0 and np.allclose(alpha.sum(axis=1), 1, atol=1e-5)
    assert analysed.meta["fps"] == pytest.approx(branch.edit.meta["fps"])


def test_alpha_param_forms_are_explained():
    from pydantic import ValidationError

    keyshapes, keymorphs = retarget_inputs()
    for bad in ("from_anlysis", {"happy": "lots"}):
        with pytest.raises(ValidationError, match="alpha is 'from_analysis', constant weights"):
            run_stage(Blend, {"alpha": bad}, {"keyshapes": keyshapes, "keymorphs": keymorphs})
    with pytest.raises(ValidationError):
        run_stage(
            Blend,
            {"alpha": {"keyframes": {0.0: {"happy": 1.0}}, "interpolation": "cubic"}},
            {"keyshapes": keyshapes, "keymorphs": keymorphs},
        )


def test_several_test_takes_keep_their_own_clock():
    keyshapes, keymorphs = retarget_inputs(frames=20)
    edit, bilinear, _ = analysis_inputs(frames=20)
    sequence = np.repeat([0, 1], [12, 8]).astype(np.int32)
    two_takes = artifact(
        {"style": edit["style"], "sequence": sequence},
        meta={"labels": TARGETS, "fps": FPS, "test_labels": ["sad", "fear"]},
    )
    params = {"alpha": {"keyframes": {0.0: {"neutral": 1.0}, 0.2: {"happy": 1.0}}}}
    out = run_stage(Blend, params, {"keyshapes": keyshapes, "keymorphs": keymorphs, "edit": two_takes})
    np.testing.assert_allclose(out.arrays["time"], np.r_[np.arange(12), np.arange(8)] / FPS)
    np.testing.assert_array_equal(out.arrays["sequence"], sequence)
    assert out.meta["labels"] == ["sad", "fear"]
    np.testing.assert_allclose(out.arrays["alpha"][12], [1, 0, 0])  # the second take starts at its own t = 0
