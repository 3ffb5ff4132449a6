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


def test_vertices_output_poses_the_character(tmp_path):
    """Posed vertices, streamed block by block into an output sink, through a real store."""
    keyshapes, keymorphs = retarget_inputs(frames=150)
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
        {"alpha": {"neutral": 1.0}, "vertices": True, "lip_seal": False},
        {"keyshapes": keyshapes, "keymorphs": keymorphs, "character": character},
        store=tmp_path,
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
    "alpha, message",
    [
        ({"happy": 0.7, "neutral": 0.5}, "sum to 1.*1.2"),
        ({"happy": 1.2, "neutral": -0.2}, r"must be >= 0.*-0.2"),
        ({"keyframes": {0.0: {"happy": 1.0}, 1.0: {"happy": 0.5}}}, "keyframe 1: .*sum to 1"),
        ({"keyframes": {}}, "empty"),
    ],
)
def test_bad_alpha_is_rejected_with_the_params(alpha, message):
    """Checked up front (msflow status and run reject a bad -S before any stage runs), not inside run()."""
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match=message):
        Blend.Params(alpha=alpha)


def test_unknown_expression_in_alpha_is_a_user_error():
    keyshapes, keymorphs = retarget_inputs()
    with pytest.raises(UserError, match=r"unknown expressions \['surprised'\].*neutral") as err:
        run_stage(Blend, {"alpha": {"happy": 0.5, "surprised": 0.5}}, {"keyshapes": keyshapes, "keymorphs": keymorphs})
    assert err.value.field == "params.alpha"


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


# ------------------------------------------------------------------------------------------- regions, lips, eyes


def test_each_morph_follows_its_own_regions_keyshape_weights():
    keyshapes, keymorphs = retarget_inputs(frames=6)
    rng = np.random.default_rng(7)
    w = keyshapes["weights"]
    region_weights = np.stack([w * rng.random(w.shape), w * rng.random(w.shape)], axis=2).astype(np.float32)
    regions = {"mouth": [48, 49], "brows": [17, 18]}
    by_region = artifact(
        {name: keyshapes[name] for name in keyshapes.names} | {"region_weights": region_weights},
        meta=dict(keyshapes.meta, regions=regions),
    )
    morph_regions = {"jawOpen": "mouth", "mouthSmile_L": "mouth", "browDown_L": "brows"}  # the others: whole face
    tagged = artifact(
        {"keymorph_weights": keymorphs["keymorph_weights"]}, meta=dict(keymorphs.meta, morph_regions=morph_regions)
    )
    out = run_stage(Blend, {"alpha": {"happy": 1.0}}, {"keyshapes": by_region, "keymorphs": tagged})
    G = keymorphs["keymorph_weights"].astype(np.float64)
    expected = np.einsum("tfk,km->tfm", w.astype(np.float64), G)
    for m, name in enumerate(MORPHS):
        if name in morph_regions:
            r = list(regions).index(morph_regions[name])
            expected[..., m] = np.einsum("tfk,k->tf", region_weights[:, :, r].astype(np.float64), G[:, m])
    np.testing.assert_allclose(out.arrays["expression_weights"], expected, atol=1e-5)
    assert out.meta["regions"] == "by region"
    whole = run_stage(Blend, {"alpha": {"happy": 1.0}, "regions": False}, {"keyshapes": by_region, "keymorphs": tagged})
    np.testing.assert_allclose(whole.arrays["expression_weights"], per_expression(keyshapes, keymorphs), atol=1e-5)


@pytest.fixture(scope="module")
def ict():
    from stages.retarget.character import GltfCharacter

    return run_stage(GltfCharacter, {}, {"mesh": {"path": "data/characters/ict-facekit.glb"}}).view()


def single_target_inputs(weights, names, lip_gap=None):
    """Keyshapes and keymorphs whose blend is exactly ``weights`` (one target, one keyshape per frame)."""
    frames = len(weights)
    arrays = {
        "weights": np.eye(frames, dtype=np.float32)[None],
        "keyshape_expression": np.zeros(frames, np.int32),
    }
    if lip_gap is not None:
        arrays["lip_gap"] = np.asarray(lip_gap, np.float32)[None]
    keyshapes = artifact(arrays, meta={"labels": ["performance"], "targets": ["performance"], "fps": FPS})
    keymorphs = artifact({"keymorph_weights": np.asarray(weights, np.float32)}, meta={"target_names": names})
    return keyshapes, keymorphs


def test_lip_seal_closes_the_characters_lips_where_the_performers_close(ict):
    from stages.retarget.blend import character_landmarks
    from stages.retarget.lips import lip_gap_model

    names = ict.meta["target_names"]
    weights = np.zeros((6, len(names)))
    weights[:, names.index("jawOpen")] = 0.3
    weights[:, names.index("mouthFunnel")] = 0.2
    weights[:, names.index("mouthSmile_L")] = 0.4
    gap = np.array([0.02, 0.015, 0.2, 0.2, 0.035, 0.02])  # closed, closed, open, open, just above, closed
    keyshapes, keymorphs = single_target_inputs(weights, names, gap)
    out = run_stage(Blend, {"eyes": "keyshapes"}, {"keyshapes": keyshapes, "keymorphs": keymorphs, "character": ict})
    sealed = out.arrays["weights"].astype(np.float64)
    g0, slopes = lip_gap_model(*character_landmarks(ict))
    achieved = g0 + sealed @ slopes
    for f in (0, 1, 5):  # closed lips: the character's own closed mouth (its neutral gap)
        assert achieved[f] <= g0 + 1e-4, (f, achieved[f])
    np.testing.assert_allclose(sealed[[2, 3]], weights[[2, 3]], atol=1e-6)  # open frames untouched
    close, jaw = names.index("mouthClose"), names.index("jawOpen")
    others = [m for m in range(len(names)) if m != close]
    assert np.all(sealed[:, others] <= weights[:, others] + 1e-6)  # the seal lowers weights ...
    smile = names.index("mouthSmile_L")
    np.testing.assert_allclose(sealed[:, smile], weights[:, smile], atol=1e-6)  # ... only those that open the lips
    # ... but first raises mouthClose over the lowered jaw, which stays: lips sealed with the jaw down
    assert np.all(sealed[[0, 1, 5], close] > 0.1) and np.all(sealed[:, close] <= sealed[:, jaw] + 1e-9)
    np.testing.assert_allclose(sealed[[0, 1, 5], jaw], 0.3, atol=1e-6)
    no_corrective = run_stage(
        Blend,
        {"eyes": "keyshapes", "seal_correctives": []},
        {"keyshapes": keyshapes, "keymorphs": keymorphs, "character": ict},
    ).arrays["weights"]
    assert np.all(no_corrective <= weights + 1e-6) and np.all(no_corrective[[0, 1, 5], jaw] < 0.01)
    assert g0 < achieved[4] <= g0 + 4 * (gap[4] - 0.03) + 1e-6  # above seal_gap the seal fades out
    assert out.metrics["closed_frames"] == 3
    plain = run_stage(
        Blend,
        {"eyes": "keyshapes", "lip_seal": False},
        {"keyshapes": keyshapes, "keymorphs": keymorphs, "character": ict},
    )
    np.testing.assert_allclose(plain.arrays["weights"], weights, atol=1e-6)
    assert any("lip seal off" in w for w in warnings_of(Blend, {"eyes": "keyshapes"}, keyshapes, keymorphs))


def warnings_of(cls, params, keyshapes, keymorphs):
    """The warnings a stage attaches to its result (msflow.testing.run_stage does not return them)."""
    from msflow.testing import prepare_inputs

    inputs = prepare_inputs(cls, {"keyshapes": keyshapes, "keymorphs": keymorphs})
    return cls("blend").run(cls.Params(**params), inputs).warnings


def test_seal_is_the_nearest_weights_that_meet_the_bound():
    from stages.retarget.lips import seal_lips

    rng = np.random.default_rng(3)
    slopes = np.array([0.3, 0.1, -0.2, 0.05])
    u0 = rng.random((1, 4))
    bound = np.array([0.02 + u0[0] @ slopes - 0.05])
    sealed = seal_lips(u0, 0.02, slopes, bound)
    assert 0.02 + sealed[0] @ slopes == pytest.approx(bound[0], abs=1e-9)
    # brute force over lowered weights meeting the bound: none is nearer
    candidates = u0 * rng.random((200000, 4))
    feasible = candidates[0.02 + candidates @ slopes <= bound[0]]
    assert np.linalg.norm(sealed - u0) <= np.linalg.norm(feasible - u0, axis=1).min() + 1e-9


def tracking_with_eyes(frames, aperture=None, gaze=None):
    arrays = {"landmarks": np.zeros((frames, 68, 2), np.float32)}
    if aperture is not None:
        arrays["eye_aperture"] = np.asarray(aperture, np.float32)
    if gaze is not None:
        arrays["gaze"] = np.asarray(gaze, np.float32)
    return artifact(arrays, meta={"labels": ["take"], "fps": [FPS]})


def test_blinks_and_gaze_come_from_tracking(ict):
    """A synthetic blink in the performer's eyelid aperture closes the character's eyes by the same fraction; gaze
    turns into eyeLook weights (synthetic inputs in tracking's contract-3 shapes)."""
    from stages.retarget.blend import character_landmarks
    from stages.retarget.eyes import eye_aperture_2d

    names = ict.meta["target_names"]
    frames = 20
    aperture = np.full((frames, 2), 0.3)
    aperture[8:11] = [[0.03, 0.03], [0.02, 0.02], [0.15, 0.15]]  # a blink, both eyes
    gaze = np.zeros((frames, 2, 2))
    gaze[12:15, :, 0] = 15.0  # looking to the performer's left: out for the left eye, in for the right
    gaze[15:17, :, 1] = -30.0  # down
    keyshapes, keymorphs = single_target_inputs(np.zeros((frames, len(names))), names)
    out = run_stage(
        Blend,
        {"lip_seal": False},
        {
            "keyshapes": keyshapes,
            "keymorphs": keymorphs,
            "character": ict,
            "tracks": tracking_with_eyes(frames, aperture, gaze),
        },
    )
    w = out.arrays["weights"]
    blink = w[:, [names.index("eyeBlink_L"), names.index("eyeBlink_R")]]
    assert np.all(blink[8:10] > 0.8) and np.all(blink[:8] < 0.01) and np.all(blink[11:] < 0.01)
    rest, deltas = character_landmarks(ict)
    shapes = rest[None] + np.einsum("fm,mpc->fpc", w.astype(np.float64), deltas)
    relative = eye_aperture_2d(shapes) / eye_aperture_2d(rest[None])
    # the same fraction closed, as far as the character's blink closes (ICT's lids stop at 13% of open)
    shut = rest + deltas[names.index("eyeBlink_L")] + deltas[names.index("eyeBlink_R")]
    tightest = (eye_aperture_2d(shut[None]) / eye_aperture_2d(rest[None]))[0, 0]
    np.testing.assert_allclose(relative[8:11], np.maximum(aperture[8:11] / 0.3, tightest), atol=0.01)
    assert w[12, names.index("eyeLookOut_L")] == pytest.approx(0.5, abs=1e-6)
    assert w[12, names.index("eyeLookIn_R")] == pytest.approx(0.5, abs=1e-6)
    assert w[12, names.index("eyeLookIn_L")] == 0 and w[12, names.index("eyeLookOut_R")] == 0
    assert w[15, names.index("eyeLookDown_L")] == pytest.approx(1.0) and w[15, names.index("eyeLookUp_R")] == 0
    np.testing.assert_allclose(out.arrays["gaze"], gaze, atol=1e-6)
    assert out.meta["eyes"]["blink_source"] == "tracking eye_aperture"
    keyed = run_stage(
        Blend,
        {"eyes": "keyshapes", "lip_seal": False},
        {
            "keyshapes": keyshapes,
            "keymorphs": keymorphs,
            "character": ict,
            "tracks": tracking_with_eyes(frames, aperture, gaze),
        },
    )
    assert not keyed.arrays["weights"].any() and "gaze" not in keyed.arrays


def test_the_performers_usual_line_of_sight_becomes_straight_ahead(ict):
    """A performer looking at a lens 10 degrees below and 4 to the left of straight ahead (the right eye read 3
    degrees further in by the tracker), glancing 15 degrees left for three frames: by default the character looks
    straight ahead, at the viewer, but for the glance; with gaze_reference 'tracked' it looks down throughout."""
    names = ict.meta["target_names"]
    frames = 20
    gaze = np.zeros((frames, 2, 2))
    gaze[:, :, 0], gaze[:, :, 1] = 4.0, -10.0
    gaze[:, 1, 0] += 3.0
    gaze[12:15, :, 0] += 15.0
    keyshapes, keymorphs = single_target_inputs(np.zeros((frames, len(names))), names)
    inputs = {
        "keyshapes": keyshapes,
        "keymorphs": keymorphs,
        "character": ict,
        "tracks": tracking_with_eyes(frames, np.full((frames, 2), 0.3), gaze),
    }
    out = run_stage(Blend, {"lip_seal": False}, inputs)
    w = out.arrays["weights"]
    look = [n for n in names if n.startswith("eyeLook")]
    calm = np.r_[0:12, 15:frames]
    assert np.abs(w[np.ix_(calm, [names.index(n) for n in look])]).max() < 1e-6
    assert w[12, names.index("eyeLookOut_L")] == pytest.approx(0.5, abs=1e-6)
    assert w[12, names.index("eyeLookIn_R")] == pytest.approx(0.5, abs=1e-6)
    np.testing.assert_allclose(out.arrays["gaze"][12], [[15.0, 0.0], [15.0, 0.0]], atol=1e-6)
    assert out.meta["eyes"]["gaze_median_taken_out"] == [[[4.0, -10.0], [7.0, -10.0]]]
    tracked = run_stage(Blend, {"lip_seal": False, "gaze_reference": "tracked"}, inputs).arrays["weights"]
    assert np.allclose(tracked[calm, names.index("eyeLookDown_L")], 10.0 / 30.0, atol=1e-6)


def test_lids_that_follow_the_gaze_are_not_closed_twice(ict):
    """Known answer: ICT FaceKit's eyeLookDown lowers the lids with the eyes (the upper lid 0.1 IOD per unit), as a
    performer's do. A performer looking down 30 degrees whose eyes narrow by exactly that much has made no blink:
    the character's eyes narrow by the same fraction through eyeLookDown alone, blink 0. Solved before the gaze was
    set, the blink closed them that far and the gaze closed them again (eyes error 1.18% -> 1.0% IOD on the
    talking heads, one false blink fewer)."""
    from stages.retarget.blend import character_landmarks
    from stages.retarget.eyes import eye_aperture_2d

    names = ict.meta["target_names"]
    rest, deltas = character_landmarks(ict)
    look_down = rest + deltas[names.index("eyeLookDown_L")] + deltas[names.index("eyeLookDown_R")]
    narrowed = (eye_aperture_2d(look_down[None]) / eye_aperture_2d(rest[None]))[0]
    assert (narrowed < 0.8).all()  # the lids follow the gaze that far
    frames = 12
    aperture = np.full((frames, 2), 0.3)
    gaze = np.zeros((frames, 2, 2))
    aperture[4:8], gaze[4:8, :, 1] = 0.3 * narrowed, -30.0  # looking down, the lids with the eyes
    keyshapes, keymorphs = single_target_inputs(np.zeros((frames, len(names))), names)
    inputs = {"keyshapes": keyshapes, "keymorphs": keymorphs, "character": ict}
    tracks = tracking_with_eyes(frames, aperture, gaze)
    w = run_stage(Blend, {"lip_seal": False}, {**inputs, "tracks": tracks}).arrays["weights"].astype(np.float64)
    blink = w[:, [names.index("eyeBlink_L"), names.index("eyeBlink_R")]]
    assert np.all(blink < 0.01), blink[4:8]
    assert w[5, names.index("eyeLookDown_L")] == pytest.approx(1.0)
    shapes = rest[None] + np.einsum("fm,mpc->fpc", w, deltas)
    relative = eye_aperture_2d(shapes) / eye_aperture_2d(rest[None])
    np.testing.assert_allclose(relative[4:8], np.broadcast_to(narrowed, (4, 2)), atol=0.01)
    # a blink while looking down still closes the eyes the rest of the way
    aperture[6] = 0.02
    blinked = run_stage(Blend, {"lip_seal": False}, {**inputs, "tracks": tracking_with_eyes(frames, aperture, gaze)})
    assert (blinked.arrays["weights"][6, [names.index("eyeBlink_L"), names.index("eyeBlink_R")]] > 0.5).all()


def test_seal_follows_the_tracked_performer_over_the_edited_shapes(ict):
    """Lip closures are speech, not expression: with the performer's tracking the seal follows their lips even when
    the re-expressed shapes have them apart."""
    names = ict.meta["target_names"]
    weights = np.zeros((4, len(names)))
    weights[:, names.index("jawOpen")] = 0.3
    keyshapes, keymorphs = single_target_inputs(weights, names, np.full(4, 0.2))  # the edit: lips apart
    from stages.retarget.face_measures import level, lip_gap_iod

    rng = np.random.default_rng(0)
    landmarks = rng.normal(size=(4, 68, 2)) * 5 + 100
    landmarks[:, 36], landmarks[:, 45] = [70, 100], [130, 100]  # eye line level, IOD 60
    for a, b in ((61, 67), (62, 66), (63, 65)):
        landmarks[:, a, 1] = 150
        landmarks[:, b, 1] = [150.6, 150.6, 160, 160]  # closed (0.01 IOD) twice, then open
    tracks = artifact({"landmarks": landmarks.astype(np.float32)}, meta={"labels": ["take"], "fps": [FPS]})
    assert lip_gap_iod(level(landmarks))[:2] == pytest.approx(0.01, abs=1e-3)
    out = run_stage(
        Blend,
        {"eyes": "keyshapes"},
        {"keyshapes": keyshapes, "keymorphs": keymorphs, "character": ict, "tracks": tracks},
    )
    from stages.retarget.blend import character_landmarks
    from stages.retarget.lips import lip_gap_model

    g0, slopes = lip_gap_model(*character_landmarks(ict))
    gap = g0 + out.arrays["weights"].astype(np.float64) @ slopes
    assert np.all(gap[:2] <= g0 + 1e-4) and np.all(gap[2:] > g0 + 0.05)  # sealed where the performer's lips met
    assert out.meta["lip_seal_source"] == "tracking"
