"""Keyshape selection (Sec 4.1, stages.retarget.keyshape_selection) and the NNLS decomposition of edited sequences
(Eq 8, stages.retarget.decomposition), stage stages.retarget.keyshapes."""

import functools
from types import SimpleNamespace

import numpy as np
import pytest
from face_fixtures import face_modes as fixture_modes
from face_fixtures import face_template
from pydantic import ValidationError

from msflow import UserError
from msflow.testing import artifact, run_stage
from stages.retarget.decomposition import decompose_into_keyshapes
from stages.retarget.face_measures import inter_ocular_distance, mouth_opening, rest_shape
from stages.retarget.keyshape_selection import select_keyshapes
from stages.retarget.keyshapes import Keyshapes
from stages.retarget.regions import BROWS


def face_modes():
    """The fixture's jaw, smile and brow modes, orthonormalised (each ~0.1 inter-ocular)."""
    modes = fixture_modes().reshape(3, -1)
    q, r = np.linalg.qr(modes.T)
    return (q * np.sign(np.diag(r))).T.reshape(3, 68, 2) * 0.5


def training_takes(seed=0, frames=(60, 50, 55), labels=("neutral", "happy", "angry"), noise=1e-3):
    """Aam-like artifact: per take, shapes = template + coefficients x modes (+ an expression offset)."""
    rng = np.random.default_rng(seed)
    template, modes = face_template(), face_modes()
    offsets = {"neutral": [0, 0, 0], "happy": [0, 0.8, 0.2], "angry": [0, -0.3, -0.6]}
    shapes, sequence = [], []
    for s, (label, n) in enumerate(zip(labels, frames)):
        coeff = rng.normal(size=(n, 3)) * [1.0, 0.4, 0.2] + np.asarray(offsets.get(label, [0, 0, 0]))
        shapes.append(template + np.einsum("nm,mpc->npc", coeff, modes) + noise * rng.normal(size=(n, 68, 2)))
        sequence += [s] * n
    return np.concatenate(shapes), np.asarray(sequence, np.int32), list(labels)


def aam_view(shapes, sequence, labels):
    return artifact(
        {"aligned_shapes": shapes.astype(np.float32), "sequence": sequence}, meta={"labels": labels, "fps": 30.0}
    )


def edit_view(shapes, targets, fps=30.0):
    return artifact(
        {"shapes": np.asarray(shapes, np.float32)}, meta={"targets": targets, "labels": targets, "fps": fps}
    )


# ------------------------------------------------------------------------------------------------ selection


def test_template_measures():
    t = face_template()
    assert inter_ocular_distance(t) == pytest.approx(1.1)
    opened = t + face_modes()[0] * 2
    assert mouth_opening(opened) > mouth_opening(t) + 0.05


def test_keyshapes_are_the_pca_extremes_in_axis_order():
    rng = np.random.default_rng(1)
    modes = face_modes()
    coeff = rng.normal(size=(80, 3)) * [3.0, 2.0, 1.0]  # known variance order: jaw, smile, brow
    shapes = face_template() + np.einsum("nm,mpc->npc", coeff, modes)
    selection = select_keyshapes(shapes, 6, dedupe_threshold=0.0)
    expected = []
    for axis in range(3):
        expected += [int(np.argmax(coeff[:, axis])), int(np.argmin(coeff[:, axis]))]
    # the PCA axis sign is arbitrary: compare each axis's pair as a set
    for axis in range(3):
        assert set(selection.frames[2 * axis : 2 * axis + 2]) == set(expected[2 * axis : 2 * axis + 2])
    np.testing.assert_array_equal(selection.axes, [0, 0, 1, 1, 2, 2])
    assert set(selection.extremes) == {1, -1}
    assert np.all(np.diff(selection.explained_variance) <= 1e-12)


def test_odd_k_takes_the_maximum_of_the_last_axis_only_and_k_caps_the_count():
    rng = np.random.default_rng(2)
    shapes = face_template() + np.einsum("nm,mpc->npc", rng.normal(size=(40, 3)) * [3, 2, 1], face_modes())
    assert len(select_keyshapes(shapes, 3, dedupe_threshold=0.0).frames) == 3
    assert list(select_keyshapes(shapes, 3, dedupe_threshold=0.0).axes) == [0, 0, 1]
    assert len(select_keyshapes(shapes, 1, dedupe_threshold=0.0).frames) == 1
    # only 3 axes carry variance: asking for 20 gives at most 6 (noise-free data has rank 3)
    many = select_keyshapes(shapes, 20, dedupe_threshold=0.0)
    assert 3 <= len(many.frames) <= 6
    # a frame that is the extreme of two axes is kept once, whatever the threshold
    assert len(set(many.frames)) == len(many.frames)
    assert len(many.frames) + len(many.dropped) == 6
    assert all(d["frame"] == d["duplicate_of"] for d in many.dropped)


def test_duplicate_extreme_is_dropped_from_the_lower_variance_axis():
    rng = np.random.default_rng(3)
    coeff = rng.normal(size=(50, 3)) * [3.0, 2.0, 1.0]
    coeff[7] = [20.0, 15.0, 0.0]  # frame 7 is the extreme of axis 0 and of axis 1
    shapes = face_template() + np.einsum("nm,mpc->npc", coeff, face_modes())
    selection = select_keyshapes(shapes, 4, dedupe_threshold=1e-6, scale=1.1)
    assert list(selection.frames).count(7) == 1
    assert len(selection.frames) == 3
    assert len(selection.dropped) == 1 and selection.dropped[0]["duplicate_of"] == 7
    assert selection.dropped[0]["axis"] == 1  # the later, lower-variance axis loses
    # refill goes on to axis 2 and reaches k
    refilled = select_keyshapes(shapes, 4, dedupe_threshold=1e-6, scale=1.1, refill=True)
    assert len(refilled.frames) == 4 and refilled.axes[-1] == 2


def test_frames_at_rest_get_no_weight_when_decomposed_from_rest():
    """Known answer: a face talking with the jaw, a smile and the brows about its rest, every third frame at rest.
    On the absolute shapes (the paper's Eq 8) a frame at rest is a mix of opposite extremes, both ends of an axis
    weighted (their keymorphs, a smile and a frown, never quite cancel on the character); decomposed as
    deformations from rest it gets no weight at all. Both reconstruct every frame."""
    from stages.retarget.decomposition import decompose
    from stages.retarget.face_measures import relative_rms_error

    rng = np.random.default_rng(4)
    coeff = rng.normal(size=(90, 3)) * [2.0, 1.5, 1.0]
    coeff[::3] = 0.0
    template, modes = face_template(), face_modes()
    shapes = template + np.einsum("nm,mpc->npc", coeff, modes)
    selection = select_keyshapes(shapes, 6, dedupe_threshold=0.0)
    keyshapes, groups, own = shapes[selection.frames], np.zeros(90, int), np.zeros(len(selection.frames), int)
    absolute = decompose(shapes, groups, keyshapes, own)
    from_rest = decompose(shapes, groups, keyshapes, own, None, template, template)
    at_rest = np.arange(0, 90, 3)
    assert from_rest.weights[at_rest].sum(axis=1).max() < 1e-6
    pairs = absolute.weights[at_rest].reshape(len(at_rest), 3, 2)
    assert (pairs.min(axis=2) > 0.05).any(axis=1).mean() > 0.5
    # the deformations span a cone (any non-negative mix of the extremes' deformations): every frame is
    # reconstructed; the absolute shapes reach most frames too, not all (a frame whose mix would need weights
    # summing far from 1)
    assert relative_rms_error(from_rest.reconstruction, shapes, 1.1).max() < 1e-9
    assert np.median(relative_rms_error(absolute.reconstruction, shapes, 1.1)) < 1e-9


def test_dedupe_threshold_is_a_mean_squared_distance_relative_to_scale():
    base = face_template()
    near = base + 0.01 * face_modes()[0] / np.abs(face_modes()[0]).max()
    shapes = np.stack([base, near, base + face_modes()[1], base - face_modes()[1]])
    d = ((near - base) ** 2).sum(-1).mean()
    for scale in (1.0, 3.0):
        kept = select_keyshapes(shapes * scale, 4, dedupe_threshold=0.99 * d, scale=scale)
        dropped = select_keyshapes(shapes * scale, 4, dedupe_threshold=1.01 * d, scale=scale)
        assert len(kept.frames) == 4 and not kept.dropped
        assert len(dropped.frames) == 3
        assert dropped.dropped[0]["distance"] == pytest.approx(d)


def test_constant_shapes_give_one_keyshape():
    shapes = np.repeat(face_template()[None], 5, axis=0)
    assert list(select_keyshapes(shapes, 20, dedupe_threshold=1e-3).frames) == [0]


def test_decomposition_recovers_nonnegative_mixtures_exactly():
    rng = np.random.default_rng(4)
    keyshapes = face_template() + np.einsum("km,mpc->kpc", rng.normal(size=(6, 3)) * 2, face_modes())
    keyshapes += 0.02 * rng.normal(size=keyshapes.shape)  # full rank
    true = rng.dirichlet(np.ones(6), size=30) * (rng.random((30, 6)) < 0.6)
    true[true.sum(1) == 0, 0] = 1.0
    shapes = np.einsum("nk,kpc->npc", true, keyshapes)
    weights, reconstruction, result = decompose_into_keyshapes(shapes, keyshapes)
    np.testing.assert_allclose(weights, true, atol=1e-7)
    np.testing.assert_allclose(reconstruction, shapes, atol=1e-9)
    assert result.kkt.max() < 1e-8


def test_rest_shape_has_the_mouth_closed():
    shapes, sequence, _ = training_takes()
    neutral = shapes[sequence == 0]
    rest = rest_shape(neutral)
    assert mouth_opening(rest) <= np.quantile(mouth_opening(neutral), 0.15)
    assert mouth_opening(rest) < mouth_opening(neutral.mean(axis=0))


# ----------------------------------------------------------------------------------------------------- stage


def edited_from_training(shapes, sequence, labels, frames=40, seed=9):
    """Edited sequences that the keyshapes can represent: convex mixes of each expression's own frames."""
    rng = np.random.default_rng(seed)
    out = []
    for s, _ in enumerate(labels):
        own = shapes[sequence == s]
        mix = rng.dirichlet(np.ones(len(own)) * 0.3, size=frames)
        out.append(np.einsum("fn,npc->fpc", mix, own))
    return np.stack(out)


@pytest.fixture(scope="module")
def synthetic_run(tmp_path_factory):
    shapes, sequence, labels = training_takes()
    edited = edited_from_training(shapes, sequence, labels)
    out = run_stage(
        Keyshapes,
        {"k": {"neutral": 6, "happy": 8, "angry": 8}},
        {"aam": aam_view(shapes, sequence, labels), "edit": edit_view(edited, labels)},
        store=tmp_path_factory.mktemp("keyshapes"),
    )
    return shapes, sequence, labels, edited, out


def test_stage_outputs_follow_the_schema(synthetic_run):
    shapes, sequence, labels, edited, out = synthetic_run
    a = out.arrays
    total = len(a["keyshapes"])
    assert a["weights"].shape == (3, edited.shape[1], total)
    assert out.meta["labels"] == labels and out.meta["targets"] == labels
    counts = out.meta["keyshape_counts"]
    assert sum(counts) == total and all(1 <= c for c in counts)
    assert counts[0] <= 6 and counts[1] <= 8 and counts[2] <= 8
    # keyshapes are the training frames they claim to be, of their own expression
    np.testing.assert_allclose(a["keyshapes"], shapes[a["keyshape_frame"]].astype(np.float32))
    np.testing.assert_array_equal(sequence[a["keyshape_frame"]], a["keyshape_expression"])
    for s in range(3):
        np.testing.assert_array_equal(a["keyshape_index"][a["keyshape_expression"] == s], np.arange(counts[s]))
    assert out.meta["keyshape_ids"][0] == "neutral/0"
    # the rest pose: closed-mouth frames of the neutral take
    assert np.all(sequence[a["rest_frames"]] == 0)
    np.testing.assert_allclose(a["rest_shape"], shapes[a["rest_frames"]].mean(axis=0), atol=1e-5)


def test_the_brows_can_rest_at_their_median_over_the_rest_take():
    shapes, sequence, labels = training_takes()
    edited = edited_from_training(shapes, sequence, labels, frames=10)
    inputs = {"aam": aam_view(shapes, sequence, labels), "edit": edit_view(edited, labels)}
    a = run_stage(Keyshapes, {"k": 6, "brow_rest": "median"}, inputs).arrays
    brows, others = list(BROWS), [i for i in range(68) if i not in BROWS]
    np.testing.assert_allclose(a["rest_shape"][brows], np.median(shapes[sequence == 0][:, brows], axis=0), atol=1e-5)
    np.testing.assert_allclose(a["rest_shape"][others], shapes[a["rest_frames"]][:, others].mean(axis=0), atol=1e-5)
    # not the closed-mouth frames' brows (the fixture's brow mode varies from frame to frame)
    closed = shapes[a["rest_frames"]][:, brows].mean(axis=0)
    assert np.abs(a["rest_shape"][brows] - closed).max() > 1e-3
    assert a["weights"].min() >= 0


def test_weights_are_zero_outside_the_targets_own_keyshapes(synthetic_run):
    _, _, _, _, out = synthetic_run
    a = out.arrays
    for t, e in enumerate(out.meta["target_expression"]):
        assert not np.any(a["weights"][t][:, a["keyshape_expression"] != e])
        assert np.any(a["weights"][t][:, a["keyshape_expression"] == e])


def region_reconstruction(out):
    """rest + sum_i w_i (B_i - rest) (``from_rest``; sum_i w_i B_i for ``absolute``) with each region's landmarks
    from its own weights, the others from the whole-face weights."""
    a = out.arrays
    rest = a["rest_shape"].astype(np.float64) if out.meta["decomposition"] == "from_rest" else 0.0
    keyshapes = a["keyshapes"].astype(np.float64) - rest
    recon = np.einsum("tfk,kpc->tfpc", a["weights"].astype(np.float64), keyshapes)
    for r, points in enumerate(out.meta["regions"].values()):
        w = a["region_weights"][:, :, r].astype(np.float64)
        recon[:, :, points] = np.einsum("tfk,kpc->tfpc", w, keyshapes[:, points])
    return recon + rest


def test_weights_reconstruct_the_edited_shapes(synthetic_run):
    _, _, _, edited, out = synthetic_run
    a = out.arrays
    assert set(out.meta["regions"]) == {"mouth", "eyes", "brows"}
    recon = region_reconstruction(out)
    np.testing.assert_allclose(recon, a["reconstruction"], atol=1e-4)
    iod = out.meta["inter_ocular_distance"]
    rms = np.sqrt(((recon - edited) ** 2).sum(-1).mean(-1)) / iod
    np.testing.assert_allclose(rms, a["residual"], atol=1e-4)
    # edited shapes are mixtures of training frames; the keyshapes (PCA extremes) span them to well under 3%
    assert out.metrics["residual_rms_iod"] < 0.03
    assert out.metrics["residual_rms_iod"] == pytest.approx(np.sqrt(np.mean(a["residual"] ** 2)), rel=1e-4)


def test_more_keyshapes_never_fit_worse():
    shapes, sequence, labels = training_takes(noise=5e-3)
    edited = edited_from_training(shapes, sequence, labels)
    inputs = {"aam": aam_view(shapes, sequence, labels), "edit": edit_view(edited, labels)}
    residuals = [
        run_stage(Keyshapes, {"k": k, "refill": True}, inputs).metrics["train_residual_rms_iod"] for k in (2, 6, 20)
    ]
    assert residuals[0] >= residuals[1] >= residuals[2]
    assert residuals[2] < residuals[0]


def test_options_sum_to_one_and_smoothing_run_through_the_stage(synthetic_run):
    shapes, sequence, labels, edited, plain = synthetic_run
    inputs = {"aam": aam_view(shapes, sequence, labels), "edit": edit_view(edited, labels)}
    params = {"k": {"neutral": 6, "happy": 8, "angry": 8}}
    soft = run_stage(Keyshapes, dict(params, sum_to_one=10.0), inputs)
    gap_plain = np.abs(plain.arrays["weights"].sum(-1) - 1).mean()
    gap_soft = np.abs(soft.arrays["weights"].sum(-1) - 1).mean()
    assert gap_soft <= gap_plain + 1e-6
    smooth = run_stage(Keyshapes, dict(params, smoothing=2.0), inputs)
    jitter = lambda w: np.abs(np.diff(w, axis=1)).mean()
    assert jitter(smooth.arrays["weights"]) < jitter(plain.arrays["weights"])


def test_unknown_expressions_are_user_errors():
    shapes, sequence, labels = training_takes(frames=(20, 20, 20))
    edited = edited_from_training(shapes, sequence, labels, frames=5)
    inputs = {"aam": aam_view(shapes, sequence, labels), "edit": edit_view(edited, labels)}
    with pytest.raises(UserError, match="unknown expressions.*surprised") as err:
        run_stage(Keyshapes, {"k": {"neutral": 4, "happy": 4, "angry": 4, "surprised": 4}}, inputs)
    assert err.value.field == "params.k"
    with pytest.raises(UserError, match="no count for"):
        run_stage(Keyshapes, {"k": {"neutral": 4}}, inputs)
    # checked up front with the params (msflow status sees it), not inside run()
    with pytest.raises(ValidationError, match="at least 1"):
        Keyshapes.Params(k=0)
    with pytest.raises(ValidationError, match="at least 1"):
        Keyshapes.Params(k={"neutral": 2, "happy": 0})
    with pytest.raises(ValidationError):
        Keyshapes.Params(dedupe_threshold=-1)
    bad_edit = edit_view(edited, ["neutral", "happy", "sad"])
    with pytest.raises(UserError, match="sad") as err:
        run_stage(Keyshapes, {}, {"aam": inputs["aam"], "edit": bad_edit})
    assert err.value.field == "inputs.edit"
    with pytest.raises(UserError, match="names 2 expressions"):
        run_stage(Keyshapes, {}, {"aam": inputs["aam"], "edit": edit_view(edited, ["neutral", "happy"])})
    nan_edit = edited.copy()
    nan_edit[0, 0, 0, 0] = np.nan
    with pytest.raises(UserError, match="NaN"):
        run_stage(Keyshapes, {}, {"aam": inputs["aam"], "edit": edit_view(nan_edit, labels)})


def test_invalid_training_frames_are_never_keyshapes():
    shapes, sequence, labels = training_takes(frames=(30, 30, 30))
    shapes = shapes.copy()
    shapes[5] = face_template() + 50 * face_modes()[0]  # a wild (interpolated) frame: the obvious axis-0 extreme
    valid = np.ones(len(shapes), bool)
    valid[5] = False
    edited = edited_from_training(shapes[valid], sequence[valid], labels, frames=5)
    aam = artifact(
        {"aligned_shapes": shapes.astype(np.float32), "sequence": sequence, "valid": valid}, meta={"labels": labels}
    )
    out = run_stage(Keyshapes, {"k": 4}, {"aam": aam, "edit": edit_view(edited, labels)})
    assert 5 not in out.arrays["keyshape_frame"]


def test_figures_render(synthetic_run):
    from matplotlib.figure import Figure

    _, _, _, _, out = synthetic_run
    for name, figure in Keyshapes.figures.items():
        assert isinstance(figure(out.view(), {}), Figure), name


# ------------------------------------------------------------------------------------------- real data (CREMA-D)


@functools.lru_cache(maxsize=1)
def crema_face_branch():
    """CREMA-D actor 1001 through the face branch (FaceMesh tracking, aam, bilinear, edit of the SAD take towards
    every training expression) and the keyshapes: computed once per test session, shared by the retargeting
    test modules (they import this function)."""
    from stages.face.aam import AamPca
    from stages.face.bilinear import BilinearFit
    from stages.face.edit import ExpressionEdit
    from stages.tracking import FaceMesh

    clip = "data/crema-d/1001_DFA_{}_XX.flv"
    train = run_stage(
        FaceMesh,
        {},
        {"videos": {"neutral": clip.format("NEU"), "happy": clip.format("HAP"), "angry": clip.format("ANG")}},
    ).view()
    test = run_stage(FaceMesh, {}, {"videos": {"sad": clip.format("SAD")}}).view()
    aam = run_stage(AamPca, {}, {"tracks": train}).view()
    bilinear = run_stage(BilinearFit, {}, {"aam": aam, "tracks": train}).view()
    edit = run_stage(ExpressionEdit, {"video": False}, {"model": bilinear, "aam": aam, "tracks": test}).view()
    keyshapes = run_stage(Keyshapes, {}, {"aam": aam, "edit": edit}).view()
    return SimpleNamespace(train=train, test=test, aam=aam, bilinear=bilinear, edit=edit, keyshapes=keyshapes)


def test_crema_keyshapes_cover_each_take_and_decompose_the_edit():
    branch = crema_face_branch()
    ks, aam = branch.keyshapes, branch.aam
    labels = ks.meta["labels"]
    assert labels == aam.meta["labels"] and ks.meta["targets"] == branch.edit.meta["targets"]
    sequence = aam["sequence"]
    counts = ks.meta["keyshape_counts"]
    assert all(5 <= c <= 20 for c in counts), counts  # k = 20 per expression, duplicates removed
    np.testing.assert_array_equal(sequence[ks["keyshape_frame"]], ks["keyshape_expression"])
    assert len(set(ks["keyshape_frame"].tolist())) == len(ks["keyshape_frame"])
    # the training frames of each expression are well inside what their keyshapes span
    assert ks.metrics["train_residual_rms_iod"] < 0.01
    # the goal: edited sequences decompose to within 3% of the inter-ocular distance (RMS)
    assert ks.metrics["residual_rms_iod"] <= 0.03
    w = ks["weights"]
    assert w.min() >= 0 and w.shape[:2] == branch.edit["shapes"].shape[:2]
    # the paper's raw-shape NNLS keeps the face's scale: the weights of a frame sum to about one
    np.testing.assert_allclose(w.sum(axis=-1), 1.0, atol=0.1)
    # decomposed from rest, they need not (and the edit is reached as well)
    from_rest = run_stage(Keyshapes, {"decomposition": "from_rest"}, {"aam": aam, "edit": branch.edit}).view()
    assert from_rest.metrics["residual_rms_iod"] <= 0.03
    assert np.abs(from_rest["weights"].sum(axis=-1) - 1.0).max() > 0.1
    assert np.all(sequence[ks["rest_frames"]] == labels.index("neutral"))


# ------------------------------------------------------------------------------------------ performance capture


def mesh_from_landmarks(points):
    """A 468-point FaceMesh (image axes: x right, y down, z away) whose iBUG-68 points are ``points`` (F, 68, 3)
    given in head axes (x right, y up, z to the viewer): the least-norm solution of the mapping table."""
    from stages.tracking.landmarks68 import MAPPING_MATRIX

    image = np.asarray(points, np.float64) * [1, -1, -1]
    solution = np.linalg.lstsq(MAPPING_MATRIX, image.transpose(1, 0, 2).reshape(68, -1), rcond=None)[0]
    return solution.reshape(468, len(points), 3).transpose(1, 0, 2)


def face3d_takes(frames=(40, 30), seed=5):
    """Two takes of a 3D face (the ICT landmarks, deformed by random mixes of jaw, smile and brow offsets), each
    frame seen under its own head pose and scale (image pixels); returns (tracking artifact, head-frame truth)."""
    from stages.geometry.rotations import euler_to_quat, quat_to_matrix
    from stages.tracking.face3d import load_face3d

    face = load_face3d()
    modes = np.stack([face.expression_offsets[n] for n in ("jawOpen", "mouthSmile_L", "browDown_R")])
    rng = np.random.default_rng(seed)
    n = sum(frames)
    truth = face.neutral + np.einsum("fm,mpc->fpc", rng.random((n, 3)) * [0.8, 0.6, 0.6], modes)
    turn = quat_to_matrix(euler_to_quat(rng.normal(0, 0.2, n), rng.normal(0, 0.1, n), rng.normal(0, 0.05, n)))
    seen = np.einsum("fij,fpj->fpi", turn, truth) * rng.uniform(5, 8, (n, 1, 1)) + rng.normal(0, 20, (n, 1, 3))
    mesh = mesh_from_landmarks(seen)
    from stages.tracking.landmarks68 import mesh_to_ibug68

    tracks = artifact(
        {
            "landmarks": mesh_to_ibug68(mesh)[..., :2].astype(np.float32),
            "mesh": mesh.astype(np.float32),
            "sequence": np.repeat(np.arange(len(frames)), frames).astype(np.int32),
        },
        meta={"labels": ["one", "two"], "fps": [30.0, 25.0]},
    )
    return tracks, truth


def test_head_frame_takes_the_pose_out_of_the_mesh():
    from stages.retarget.morph_fit import fit_similarity
    from stages.retarget.shapes3d import head_frame_shapes

    tracks, truth = face3d_takes()
    shapes = head_frame_shapes(tracks["mesh"])
    assert inter_ocular_distance(shapes.mean(axis=0)) == pytest.approx(1.0, rel=0.02)
    # one similarity carries every recovered frame onto the truth (the pose of each frame is gone)
    sim = fit_similarity(shapes.reshape(-1, 3), truth.reshape(-1, 3))
    residual = np.linalg.norm(sim.apply(shapes) - truth, axis=-1) / inter_ocular_distance(truth[0])
    # rigid points align each frame, so expression offsets at the eye corners leave a small residual
    assert residual.max() < 0.02


def test_head_frame_keyshapes_carry_the_cheek_points():
    """The paper's keyshapes in 3D: the 68 points and, for the keymorph fit, the FaceMesh cheek points of the same
    frames, carried by the same alignment, with their rest (the mean of the rest frames)."""
    from stages.retarget.keyshapes import head_frame_keyshapes
    from stages.retarget.movements import EXTRA_VERTICES
    from stages.retarget.shapes3d import head_frame_shapes

    tracks, _ = face3d_takes()
    frames, rest = np.array([3, 17, 40]), np.array([0, 1, 2])
    out = head_frame_keyshapes(tracks, frames, rest, "closed_mouth", np.arange(10))
    shapes = head_frame_shapes(tracks["mesh"], EXTRA_VERTICES)
    np.testing.assert_allclose(out["keyshapes3d"], shapes[frames, :68], atol=1e-6)
    np.testing.assert_allclose(out["keyshape_cheeks3d"], shapes[frames, 68:], atol=1e-6)
    np.testing.assert_allclose(out["keyshape_cheek_rest3d"][0], shapes[rest, 68:].mean(axis=0), atol=1e-6)
    assert out["keyshape_rest3d"].shape == (3, 68, 3)


def test_capture_keyshapes_decompose_each_take_onto_its_own_keyshapes():
    from stages.retarget.keyshapes import CaptureKeyshapes

    tracks, _ = face3d_takes()
    out = run_stage(CaptureKeyshapes, {"k": 8}, {"tracks": tracks})
    a, meta = out.arrays, out.meta
    assert meta["space"] == "3d" and meta["targets"] == ["performance"] and meta["labels"] == ["one", "two"]
    assert meta["take_fps"] == [30.0, 25.0]
    sequence = tracks["sequence"]
    np.testing.assert_array_equal(a["sequence"], sequence)
    np.testing.assert_array_equal(sequence[a["keyshape_frame"]], a["keyshape_expression"])
    w = a["weights"][0]
    for take in (0, 1):
        others = a["keyshape_expression"] != take
        assert not w[sequence == take][:, others].any()
    # three expression modes: a few keyshapes per take represent every frame (3D, IOD units)
    assert out.metrics["residual_rms_iod"] < 0.01
    assert (
        a["keyshapes3d"].shape == (len(a["keyshapes"]), 68, 3) and a["keyshape_rest3d"].shape == a["keyshapes3d"].shape
    )
    # each take's rest is its own closed-mouth frames
    assert set(sequence[a["rest_frames"]]) == {0, 1}
    # the keymorph fit's cheek points: the FaceMesh's, carried by the same alignment; at rest, each take's mean
    # over its rest frames
    from stages.retarget.movements import EXTRA_VERTICES
    from stages.retarget.shapes3d import head_frame_shapes

    cheeks = head_frame_shapes(tracks["mesh"], EXTRA_VERTICES)[:, 68:]
    np.testing.assert_allclose(a["keyshape_cheeks3d"], cheeks[a["keyshape_frame"]], atol=1e-6)
    rests = [cheeks[a["rest_frames"][sequence[a["rest_frames"]] == take]].mean(axis=0) for take in (0, 1)]
    np.testing.assert_allclose(a["keyshape_cheek_rest3d"], np.stack(rests)[a["keyshape_expression"]], atol=1e-6)
    flat = run_stage(CaptureKeyshapes, {"k": 8, "space": "2d"}, {"tracks": tracks})
    assert flat.meta["space"] == "2d" and "keyshapes3d" not in flat.arrays and "keyshape_cheeks3d" not in flat.arrays
    no_mesh = artifact({n: tracks[n] for n in ("landmarks", "sequence")}, meta=tracks.meta)
    assert run_stage(CaptureKeyshapes, {"k": 8}, {"tracks": no_mesh}).meta["space"] == "2d"
    with pytest.raises(UserError, match="space: 3d needs the tracking's FaceMesh"):
        run_stage(CaptureKeyshapes, {"k": 8, "space": "3d"}, {"tracks": no_mesh})


def test_capture_keyshapes_on_crema_d():
    from stages.retarget.keyshapes import CaptureKeyshapes

    branch = crema_face_branch()
    out = run_stage(CaptureKeyshapes, {}, {"tracks": branch.train})
    assert out.meta["space"] == "3d"
    assert out.metrics["residual_rms_iod"] < 0.03  # the goal, on real takes
    assert all(5 <= c <= 20 for c in out.meta["keyshape_counts"])
