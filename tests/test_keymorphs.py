"""Keymorphs (Sec 4.3): the automatic KeymorphFit draft, the artist's KeymorphFile YAML, the contact sheet."""

import cv2
import numpy as np
import pytest

from msflow import UserError
from msflow.testing import artifact, run_stage
from stages.retarget.character import GltfCharacter
from stages.retarget.face_measures import inter_ocular_distance, lip_gap_iod
from stages.retarget.keymorph_yaml import format_keymorph_yaml, parse_keymorph_yaml
from stages.retarget.keymorphs import KeymorphFile, KeymorphFit
from stages.retarget.morph_fit import LandmarkRig, antagonist_pairs, fit_similarity, project_front, symmetric_pairs
from stages.retarget.region_fit import CHEEK_RAISE_POINTS
from stages.retarget.shapes3d import front_view

ICT = "data/characters/ict-facekit.glb"

#: keyshapes made from known ICT weights: (expression, {target: weight})
POSES = [
    ("neutral", {}),
    ("neutral", {"jawOpen": 0.5}),
    ("neutral", {"eyeBlink_L": 0.9, "eyeBlink_R": 0.9}),
    ("happy", {"mouthSmile_L": 0.8, "mouthSmile_R": 0.8}),
    ("happy", {"mouthSmile_L": 0.5, "mouthSmile_R": 0.5, "jawOpen": 0.3}),
    ("happy", {"mouthUpperUp_L": 0.5, "mouthUpperUp_R": 0.5, "mouthSmile_L": 0.6, "mouthSmile_R": 0.6}),
    ("angry", {"browDown_L": 0.8, "browDown_R": 0.8}),
    ("angry", {"browDown_L": 0.6, "browDown_R": 0.6, "jawOpen": 0.25}),
    ("angry", {"noseSneer_L": 0.5, "noseSneer_R": 0.5, "browDown_L": 0.5, "browDown_R": 0.5}),
]
LABELS = ["neutral", "happy", "angry"]


@pytest.fixture(scope="module")
def character():
    return run_stage(GltfCharacter, {}, {"mesh": {"path": ICT}}).view()


def actor_frame(points):
    """An arbitrary similarity (as the aam mean-shape frame would be): scale 11, rotation 4 degrees, shift."""
    th = np.deg2rad(4.0)
    rot = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    return points @ rot.T * 11.0 + [0.4, -0.2]


def keyshapes_from_weights(character, poses, noise=0.0, seed=0, rotations=None):
    """A keyshapes artifact whose keyshapes are the character's own landmarks under known weights, seen with
    head rotations (K, 3, 3) if given and similarity-aligned in 2D as the aam aligns tracked shapes."""
    names = character.meta["target_names"]
    truth = np.zeros((len(poses), len(names)))
    for k, (_, pose) in enumerate(poses):
        for name, w in pose.items():
            truth[k, names.index(name)] = w
    ids = character["landmark_ids"]
    rest = project_front(character["neutral"][ids])
    posed = character["neutral"][ids] + np.einsum("km,mpc->kpc", truth, character["deltas"][:, ids])
    if rotations is None:
        seen = project_front(posed)
    else:
        seen = np.stack([project_front(p @ r.T) for p, r in zip(posed, rotations)])
        seen = np.stack([fit_similarity(s, rest).apply(s) for s in seen])
    shapes = actor_frame(seen)
    shapes += noise * np.random.default_rng(seed).normal(size=shapes.shape) * inter_ocular_distance(shapes[0])
    expression = np.array([LABELS.index(e) for e, _ in poses], np.int32)
    index = np.concatenate([np.arange((expression == s).sum()) for s in range(len(LABELS))]).astype(np.int32)
    view = artifact(
        {
            "keyshapes": shapes.astype(np.float32),
            "keyshape_expression": expression,
            "keyshape_index": index,
            "keyshape_frame": np.arange(len(poses), dtype=np.int32) * 3,
            "keyshape_axis": (index // 2).astype(np.int32),
            "keyshape_extreme": np.where(index % 2, -1, 1).astype(np.int8),
            "rest_shape": actor_frame(rest).astype(np.float32),
            "rest_frames": np.array([0], np.int32),
        },
        meta={"labels": LABELS},
    )
    return view, truth


def tracks_for(keyshapes, frames=30, size=96, rotations=None):
    """A tracking-like artifact: grey crops with a bright disk where each landmark is; head rotations."""
    from stages.geometry.rotations import matrix_to_quat

    shapes = keyshapes["keyshapes"]
    rotation = np.tile([1.0, 0.0, 0.0, 0.0], (frames, 1))
    if rotations is not None:
        rotation[keyshapes["keyshape_frame"]] = matrix_to_quat(np.asarray(rotations))
    crops = np.full((frames, size, size), 90, np.uint8)
    crop_landmarks = np.zeros((frames, 68, 2), np.float32)
    for k, f in enumerate(keyshapes["keyshape_frame"]):
        p = shapes[k] - shapes[k].mean(0)
        p = p / np.abs(p).max() * size * 0.4 + size / 2
        crop_landmarks[f] = p
        for q in p:
            cv2.circle(crops[f], (int(q[0]), int(q[1])), 2, 255, -1)
    return artifact({"crops": crops, "crop_landmarks": crop_landmarks, "rotation": rotation})


# ------------------------------------------------------------------------------------------------- geometry


def test_similarity_recovers_a_known_transform():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 2))
    dst = actor_frame(src)
    sim = fit_similarity(src, dst)
    assert sim.scale == pytest.approx(11.0)
    np.testing.assert_allclose(sim.apply(src), dst, atol=1e-9)
    np.testing.assert_allclose(sim.inverse_linear(sim.apply_linear(src)), src, atol=1e-12)


def test_symmetric_pairs_in_ict_and_arkit_naming():
    names = ["mouthSmile_L", "jawOpen", "mouthSmile_R", "eyeBlinkLeft", "eyeBlinkRight", "browDown_L"]
    assert sorted(symmetric_pairs(names)) == [(0, 2), (3, 4)]


def test_antagonists_pair_on_the_same_side():
    names = ["browDown_L", "browDown_R", "browInnerUp_L", "browInnerUp_R", "browInnerUp", "browDownLeft", "jawOpen"]
    pairs = {(names[i], names[j]) for i, j in antagonist_pairs(names, [("browDown", "browInnerUp")])}
    assert pairs == {
        ("browDown_L", "browInnerUp_L"),
        ("browDown_R", "browInnerUp_R"),
        ("browDown_L", "browInnerUp"),
        ("browDown_R", "browInnerUp"),
        ("browDownLeft", "browInnerUp_L"),
        ("browDownLeft", "browInnerUp"),
    }


def test_antagonism_keeps_opposing_targets_apart(character):
    names = character.meta["target_names"]
    both = {"browInnerUp_L": 0.6, "browInnerUp_R": 0.6, "browDown_L": 0.35, "browDown_R": 0.35}
    keyshapes, _ = keyshapes_from_weights(character, [("neutral", {}), ("happy", both), ("angry", {})])
    weights = {
        a: run_stage(
            KeymorphFit,
            {"contact_sheet": False, "antagonism": a, "l1": 0.0, "l2": 0.0},
            {"keyshapes": keyshapes, "character": character},
        ).arrays["keymorph_weights"][1]
        for a in (0.0, 5.0)
    }
    co = {a: w[names.index("browDown_L")] * w[names.index("browInnerUp_L")] for a, w in weights.items()}
    assert co[0.0] > 0.05  # without the penalty the fit finds the co-activation that made the keyshape
    assert co[5.0] < 0.3 * co[0.0]


# ---------------------------------------------------------------------------------------------- KeymorphFit


@pytest.fixture(scope="module")
def fitted(character):
    keyshapes, truth = keyshapes_from_weights(character, POSES)
    out = run_stage(KeymorphFit, {"contact_sheet": False}, {"keyshapes": keyshapes, "character": character})
    return keyshapes, truth, out


def test_fit_recovers_the_weights_that_made_the_keyshapes(fitted, character):
    _, truth, out = fitted
    w = out.arrays["keymorph_weights"]
    names = character.meta["target_names"]
    assert w.shape == truth.shape and out.meta["target_names"] == names
    assert w.min() >= 0 and w.max() <= 1
    for k, (_, pose) in enumerate(POSES):
        for name, value in pose.items():
            # regularisation shrinks a little; the right targets carry the weight
            assert value * 0.6 <= w[k, names.index(name)] <= value + 0.05, (k, name)
        others = [m for m in range(len(names)) if names[m] not in pose]
        assert w[k, others].sum() < 0.35 * max(sum(pose.values()), 0.3), (
            k,
            {names[m]: w[k, m] for m in others if w[k, m] > 0},
        )
    assert not w[0].any()  # the rest pose is the neutral face
    # landmarks follow: keymorphs reproduce the keyshapes to a small fraction of the inter-ocular distance
    assert out.arrays["landmark_error"].max() < 0.01
    assert out.metrics["landmark_error_rms_iod"] < 0.25 * out.metrics["landmark_error_neutral_rms_iod"]


def test_fit_is_unbiased_without_regularisation(character):
    keyshapes, truth = keyshapes_from_weights(character, POSES)
    out = run_stage(
        KeymorphFit,
        {"contact_sheet": False, "l2": 0, "l1": 0, "symmetry": 0, "decimals": 6},
        {"keyshapes": keyshapes, "character": character},
    )
    assert out.arrays["landmark_error"].max() < 1e-3


def test_weights_stay_in_bounds_for_exaggerated_keyshapes(character):
    poses = [
        ("neutral", {}),
        ("neutral", {"jawOpen": 1.0}),
        ("happy", {"mouthSmile_L": 1, "mouthSmile_R": 1}),
        ("angry", {"browDown_L": 1, "browDown_R": 1}),
    ]
    keyshapes, _ = keyshapes_from_weights(character, poses)
    rest = keyshapes["rest_shape"]
    exaggerated = artifact(
        dict(
            {n: keyshapes[n] for n in keyshapes.names},
            keyshapes=(rest + 2.5 * (keyshapes["keyshapes"] - rest)).astype(np.float32),
        ),
        meta=keyshapes.meta,
    )
    out = run_stage(KeymorphFit, {"contact_sheet": False}, {"keyshapes": exaggerated, "character": character})
    w = out.arrays["keymorph_weights"]
    names = character.meta["target_names"]
    assert w.max() <= 1.0 and w.min() >= 0.0
    assert w[1, names.index("jawOpen")] == 1.0


def test_symmetry_coupling_and_exclusions(character):
    names = character.meta["target_names"]
    poses = [("neutral", {}), ("happy", {"mouthSmile_L": 0.8}), ("angry", {"eyeLookDown_L": 1.0, "jawOpen": 0.3})]
    keyshapes, _ = keyshapes_from_weights(character, poses)
    loose = run_stage(
        KeymorphFit, {"contact_sheet": False, "symmetry": 0.0}, {"keyshapes": keyshapes, "character": character}
    ).arrays["keymorph_weights"]
    tight = run_stage(
        KeymorphFit, {"contact_sheet": False, "symmetry": 50.0}, {"keyshapes": keyshapes, "character": character}
    ).arrays["keymorph_weights"]
    L, R = names.index("mouthSmile_L"), names.index("mouthSmile_R")
    assert abs(tight[1, L] - tight[1, R]) < 0.3 * abs(loose[1, L] - loose[1, R])
    # gaze is excluded by default: eyeLook* stay 0 even when the keyshape was made with one
    gaze = [m for m, n in enumerate(names) if n.startswith("eyeLook") or n.startswith("PupilDilate")]
    assert not tight[:, gaze].any()
    allowed = run_stage(
        KeymorphFit, {"contact_sheet": False, "exclude": []}, {"keyshapes": keyshapes, "character": character}
    ).arrays["keymorph_weights"]
    assert allowed[2, names.index("eyeLookDown_L")] > 0.3


def test_fit_is_robust_to_landmark_noise(character):
    keyshapes, truth = keyshapes_from_weights(character, POSES, noise=0.01)
    w = run_stage(KeymorphFit, {"contact_sheet": False}, {"keyshapes": keyshapes, "character": character}).arrays[
        "keymorph_weights"
    ]
    names = character.meta["target_names"]
    for k, target in ((1, "jawOpen"), (3, "mouthSmile_L"), (6, "browDown_R")):
        assert w[k, names.index(target)] > 0.5 * truth[k, names.index(target)]
    assert (w > 0.05).sum(axis=1).max() <= 12  # sparse: a handful of targets per keymorph


# ------------------------------------------------------------------------------------------ YAML, KeymorphFile


def test_fit_yaml_round_trips_through_keymorph_file(fitted, character, tmp_path):
    keyshapes, _, out = fitted
    yaml_path = tmp_path / "keymorphs.yaml"
    yaml_path.write_bytes(out.arrays["keymorphs"].tobytes())
    text = yaml_path.read_text()
    assert text.startswith("# Keymorphs") and "neutral:" in text and "frame 3" in text
    reread = run_stage(
        KeymorphFile,
        {"contact_sheet": False},
        {"keyshapes": keyshapes, "character": character, "keymorphs": {"yaml": yaml_path}},
    )
    np.testing.assert_array_equal(reread.arrays["keymorph_weights"], out.arrays["keymorph_weights"])
    np.testing.assert_allclose(reread.arrays["landmark_error"], out.arrays["landmark_error"])


def test_artist_edits_take_effect(fitted, character, tmp_path):
    keyshapes, _, out = fitted
    text = out.arrays["keymorphs"].tobytes().decode()
    edited = text.replace("  0: {}", "  0: {mouthSmile_L: 0.25, mouthSmile_R: 0.25}", 1)
    assert edited != text
    path = tmp_path / "edited.yaml"
    path.write_text(edited)
    w = run_stage(
        KeymorphFile,
        {"contact_sheet": False},
        {"keyshapes": keyshapes, "character": character, "keymorphs": {"yaml": path}},
    ).arrays["keymorph_weights"]
    names = character.meta["target_names"]
    assert w[0, names.index("mouthSmile_L")] == pytest.approx(0.25)
    np.testing.assert_array_equal(w[1:], out.arrays["keymorph_weights"][1:])


NAMES = ["jawOpen", "mouthSmile_L", "mouthSmile_R", "browDown_L"]


def parse(text, allow_missing=False):
    return parse_keymorph_yaml(text, ["neutral", "happy"], [2, 1], NAMES, file="k.yaml", allow_missing=allow_missing)


def test_parse_maps_ids_and_names():
    w = parse("neutral:\n  0: {}\n  1: {jawOpen: 0.5}\nhappy:\n  '0': {mouthSmile_L: 1, mouthSmile_R: 0.75}\n")
    np.testing.assert_array_equal(w, [[0, 0, 0, 0], [0.5, 0, 0, 0], [0, 1, 0.75, 0]])
    text = format_keymorph_yaml(["neutral", "happy"], np.array([0, 0, 1]), np.array([0, 1, 0]), w, NAMES)
    np.testing.assert_array_equal(parse(text), w)


@pytest.mark.parametrize(
    "text, message",
    [
        ("sad:\n  0: {}\n", r"unknown expression 'sad'.*neutral, happy"),
        ("happi:\n  0: {}\n", r"did you mean 'happy'"),
        ("neutral:\n  0: {}\n  2: {}\nhappy:\n  0: {}\n", r"unknown keyshape id '2'.*0\.\.1"),
        ("neutral:\n  x: {}\n", r"unknown keyshape id 'x'"),
        (
            "neutral:\n  0: {mouthSmileLeft: 0.2}\n  1: {}\nhappy:\n  0: {}\n",
            r"unknown morph target 'mouthSmileLeft'.*did you mean 'mouthSmile_L'.*jawOpen, mouthSmile_L, mouthSmile_R",
        ),
        ("neutral:\n  0: {jawOpen: 1.5}\n", r"outside \[0, 1\]"),
        ("neutral:\n  0: {jawOpen: -0.1}\n", r"outside \[0, 1\]"),
        ("neutral:\n  0: {jawOpen: lots}\n", r"must be a number"),
        ("neutral:\n  0: {jawOpen: .nan}\n", r"must be a number"),
        ("neutral:\n  0: [jawOpen]\n", r"expected \{morph target: weight\}"),
        ("- neutral\n", r"top level"),
        ("neutral: {0: {}, '0': {}}\n", r"given twice"),
        ("neutral:\n  0: {jawOpen: 0.1\n", r"not valid YAML"),
        ("neutral:\n  0: {}\nhappy:\n  0: {}\n", r"no entry for keyshapes \{'neutral': \[1\]\}"),
    ],
)
def test_parse_errors_name_the_valid_choices(text, message):
    with pytest.raises(UserError, match=message) as err:
        parse(text)
    assert err.value.file == "k.yaml" and err.value.field == "inputs.keymorphs"


def test_missing_keyshapes_can_be_allowed():
    w = parse("happy:\n  0: {mouthSmile_L: 0.4}\n", allow_missing=True)
    assert w.shape == (3, 4) and w[2, 1] == 0.4 and not w[:2].any()


def test_keymorph_file_stage_errors(fitted, character, tmp_path):
    keyshapes, _, _ = fitted
    bad = tmp_path / "bad.yaml"
    bad.write_text("angry:\n  7: {}\n")
    with pytest.raises(UserError, match=r"unknown keyshape id '7'.*0\.\.2") as err:
        run_stage(
            KeymorphFile,
            {"contact_sheet": False, "allow_missing": True},
            {"keyshapes": keyshapes, "character": character, "keymorphs": {"yaml": bad}},
        )
    assert err.value.file.endswith("bad.yaml")
    with pytest.raises(UserError, match="exactly one"):
        run_stage(KeymorphFile, {}, {"keyshapes": keyshapes, "character": character, "keymorphs": {"a": bad, "b": bad}})


def test_character_problems_are_user_errors(fitted, character):
    keyshapes, _, _ = fitted
    arrays = {n: character[n] for n in character.names}
    broken = dict(arrays, landmark_ids=np.full(68, len(arrays["neutral"]) + 5, np.int32))
    with pytest.raises(UserError, match="landmark ids"):
        run_stage(
            KeymorphFit,
            {"contact_sheet": False},
            {"keyshapes": keyshapes, "character": artifact(broken, meta=character.meta)},
        )
    no_targets = dict(arrays, deltas=np.zeros((0,) + arrays["neutral"].shape, np.float32))
    with pytest.raises(UserError, match="no morph targets"):
        run_stage(
            KeymorphFit,
            {"contact_sheet": False},
            {"keyshapes": keyshapes, "character": artifact(no_targets, meta=dict(character.meta, target_names=[]))},
        )


# ------------------------------------------------------------------------------------------- contact sheet


def test_contact_sheet_shows_crops_beside_renders(character, tmp_path):
    keyshapes, _ = keyshapes_from_weights(character, POSES)
    tracks = tracks_for(keyshapes)
    out = run_stage(
        KeymorphFit,
        {"tile_size": 64, "contact_sheet": True},
        {"keyshapes": keyshapes, "character": character, "tracks": tracks},
        store=tmp_path,
    )
    sheet = cv2.imdecode(out.arrays["contact_sheet"], cv2.IMREAD_COLOR)
    assert sheet is not None
    cols, rows = 3, len(LABELS)  # three keyshapes per expression
    assert sheet.shape[1] == cols * 64 and sheet.shape[0] > rows * 2 * 64
    # keymorph tiles differ where the weights differ: jawOpen (neutral/1) vs rest (neutral/0)
    header, caption = 22, 14
    render_top = header + 64 + caption
    rest_tile = sheet[render_top : render_top + 64, 0:64].astype(int)
    jaw_tile = sheet[render_top : render_top + 64, 64:128].astype(int)
    assert np.abs(rest_tile - jaw_tile).mean() > 1.0
    # the crop row shows the tracking crop: bright landmark dots and green drawn landmarks
    crop_tile = sheet[header : header + 64, 0:64]
    assert (crop_tile[..., 1] > crop_tile[..., 0] + 60).any()
    fig = KeymorphFit.figures["landmark_fit"](out.view(), {"keyshapes": keyshapes})
    assert fig is not None
    assert KeymorphFit.figures["contact_sheet"](out.view(), {})[:8] == b"\x89PNG\r\n\x1a\n"


def test_contact_sheet_without_tracking_draws_the_keyshapes(character):
    keyshapes, _ = keyshapes_from_weights(character, POSES[:4])
    out = run_stage(
        KeymorphFit, {"tile_size": 48, "contact_sheet": True}, {"keyshapes": keyshapes, "character": character}
    )
    sheet = cv2.imdecode(out.arrays["contact_sheet"], cv2.IMREAD_GRAYSCALE)
    assert sheet.shape[1] == 3 * 48


def test_contact_sheet_is_rendered_on_demand_by_default(character):
    """A run stores no contact sheet unless asked (it costs a render per keyshape); the figure makes it from the
    stage's inputs, the same picture the stored one would be."""
    keyshapes, _ = keyshapes_from_weights(character, POSES[:4])
    inputs = {"keyshapes": keyshapes, "character": character}
    lazy = run_stage(KeymorphFit, {}, inputs)
    assert "contact_sheet" not in lazy.arrays
    png = KeymorphFit.figures["contact_sheet"](lazy.view(), inputs)
    stored = run_stage(KeymorphFit, {"contact_sheet": True}, inputs).arrays["contact_sheet"]
    assert png == stored.tobytes()


def test_tracking_that_does_not_match_the_keyshapes_is_a_user_error(character):
    keyshapes, _ = keyshapes_from_weights(character, POSES)
    short = artifact({"crops": np.zeros((4, 32, 32), np.uint8), "crop_landmarks": np.zeros((4, 68, 2), np.float32)})
    with pytest.raises(UserError, match="beyond the 4 frames"):
        run_stage(KeymorphFit, {"tile_size": 32}, {"keyshapes": keyshapes, "character": character, "tracks": short})


def test_pose_correction_discounts_head_rotation(character):
    from stages.geometry.rotations import euler_to_quat, quat_to_matrix

    poses = [
        ("neutral", {}),
        ("neutral", {}),
        ("neutral", {}),
        ("happy", {"mouthSmile_L": 0.6, "mouthSmile_R": 0.6}),
        ("angry", {"browDown_L": 0.6, "browDown_R": 0.6}),
    ]
    # nods and turns of 8-12 degrees: the 2D landmarks move as if brows and mouth moved
    euler = np.radians([[0, 0, 0], [0, 10, 0], [12, -8, 0], [8, 8, 3], [-10, 9, 0]])
    rotations = quat_to_matrix(euler_to_quat(euler[:, 0], euler[:, 1], euler[:, 2]))
    keyshapes, truth = keyshapes_from_weights(character, poses, rotations=rotations)
    tracks = tracks_for(keyshapes, rotations=rotations)
    inputs = {"keyshapes": keyshapes, "character": character, "tracks": tracks}
    corrected = run_stage(KeymorphFit, {"contact_sheet": False}, inputs)
    naive = run_stage(KeymorphFit, {"contact_sheet": False, "pose_correction": False}, inputs)
    assert corrected.meta["pose_correction"] == "applied"
    assert naive.meta["pose_correction"].startswith("off")
    wc, wn = corrected.arrays["keymorph_weights"], naive.arrays["keymorph_weights"]
    # head rotation alone: no expression once the pose is discounted, spurious targets without
    assert wc[1:3].sum() < 0.1 and wn[1:3].sum() > 3 * max(wc[1:3].sum(), 0.05)
    assert np.abs(wc - truth).sum() < 0.6 * np.abs(wn - truth).sum()
    # what remains is the small interaction of rotation and expression (deltas are fitted unrotated)
    assert corrected.metrics["landmark_error_rms_iod"] < 0.01
    assert corrected.metrics["pose_effect_rms_iod"] > 0.01
    no_tracks = run_stage(KeymorphFit, {"contact_sheet": False}, {"keyshapes": keyshapes, "character": character})
    assert no_tracks.meta["pose_correction"].startswith("not applied")


def test_rig_maps_keyshapes_into_character_units(character):
    keyshapes, truth = keyshapes_from_weights(character, POSES)
    rig = LandmarkRig.build(
        character["neutral"], character["deltas"], character["landmark_ids"], keyshapes["rest_shape"]
    )
    assert rig.to_character.scale == pytest.approx(1 / 11.0, rel=1e-5)
    np.testing.assert_allclose(rig.keymorph_landmarks(truth), keyshapes["keyshapes"], atol=1e-4)


# ---------------------------------------------------------------------------------------------- 3D, by region

#: open vowels and rounded lips, alone and mixed, plus a blink and brows
POSES_3D = [
    ("neutral", {}),
    ("neutral", {"jawOpen": 0.5}),
    ("neutral", {"mouthFunnel": 0.6}),
    ("neutral", {"jawOpen": 0.3, "mouthFunnel": 0.4}),
    ("happy", {"jawOpen": 0.25, "mouthSmile_L": 0.6, "mouthSmile_R": 0.6}),
    ("happy", {"mouthPucker": 0.7}),
    ("angry", {"browDown_L": 0.7, "browDown_R": 0.7, "eyeBlink_L": 0.8, "eyeBlink_R": 0.8}),
    ("angry", {"jawOpen": 0.6, "browDown_L": 0.5, "browDown_R": 0.5}),
]


def keyshapes3d_from_weights(character, poses, cheek_ids=()):
    """A keyshapes artifact whose 3D keyshapes are the character's landmark vertices under known weights, carried
    into another frame (inter-ocular distance 1, turned 11 and 6 degrees, shifted) as the head-frame FaceMesh would
    be; the rest pose is the neutral face in that frame. With ``cheek_ids`` (12 vertices), those vertices are the
    keyshapes' cheek points (``keyshape_cheeks3d``, as the FaceMesh's after the 68)."""
    from stages.geometry.rotations import euler_to_quat, quat_to_matrix
    from stages.retarget.shapes3d import front_view

    keyshapes, truth = keyshapes_from_weights(character, poses)
    ids = np.concatenate([character["landmark_ids"], np.asarray(cheek_ids, np.int64)])
    rest = character["neutral"][ids].astype(np.float64)
    posed = rest + np.einsum("km,mpc->kpc", truth, character["deltas"][:, ids])
    turn = quat_to_matrix(euler_to_quat(np.array(0.2), np.array(0.1), np.array(0.0)))
    scale = 1.0 / inter_ocular_distance(rest)

    def performer(points):
        return scale * points @ turn.T + [0.3, -0.1, 2.0]

    arrays = {name: keyshapes[name] for name in keyshapes.names}
    shapes3d, rests3d = performer(posed), np.repeat(performer(rest)[None], len(poses), axis=0)
    arrays.update(
        keyshapes3d=shapes3d[:, :68].astype(np.float32),
        keyshape_rest3d=rests3d[:, :68].astype(np.float32),
        keyshapes=front_view(shapes3d[:, :68]).astype(np.float32),
        rest_shape=front_view(performer(rest)[:68]).astype(np.float32),
    )
    if len(cheek_ids):
        arrays.update(keyshape_cheeks3d=shapes3d[:, 68:].astype(np.float32))
        arrays.update(keyshape_cheek_rest3d=rests3d[:, 68:].astype(np.float32))
    return artifact(arrays, meta=keyshapes.meta), truth


@pytest.fixture(scope="module")
def fitted_3d(character):
    keyshapes, truth = keyshapes3d_from_weights(character, POSES_3D)
    out = run_stage(KeymorphFit, {"contact_sheet": False}, {"keyshapes": keyshapes, "character": character})
    return keyshapes, truth, out


def test_3d_fit_tells_jaw_drop_from_lip_rounding(fitted_3d, character):
    """Known answer (issue 13.1): keyshapes made by jawOpen, by mouthFunnel and by both are told apart."""
    _, truth, out = fitted_3d
    names = character.meta["target_names"]
    w = out.arrays["keymorph_weights"]
    assert out.meta["space"] == "3d"
    jaw, funnel = names.index("jawOpen"), names.index("mouthFunnel")
    for k, (_, pose) in enumerate(POSES_3D):
        for m in (jaw, funnel):
            assert w[k, m] == pytest.approx(truth[k, m], abs=0.08), (k, names[m], w[k, m], truth[k, m])
    # an open vowel is carried by the jaw, rounded lips by the funnel
    assert w[1, jaw] > 0.4 and w[1, funnel] < 0.05
    assert w[2, funnel] > 0.5 and w[2, jaw] < 0.05
    assert out.metrics["landmark_error_rms_iod"] < 0.01
    assert not w[0].any()


def test_3d_fit_recovers_every_known_weight(fitted_3d, character):
    _, truth, out = fitted_3d
    names = character.meta["target_names"]
    w = out.arrays["keymorph_weights"]
    for k, (_, pose) in enumerate(POSES_3D):
        for name, value in pose.items():
            assert value * 0.75 <= w[k, names.index(name)] <= value + 0.08, (k, name, w[k, names.index(name)])
    # each morph is credited to the decomposition region that will drive it in the blend
    regions = out.meta["morph_regions"]
    assert regions["jawOpen"] == regions["mouthFunnel"] == "mouth"
    assert regions["eyeBlink_L"] == "eyes" and regions["browDown_R"] == "brows"
    assert "eyeLookIn_L" not in regions


def test_3d_fit_does_not_price_small_morphs_out(character):
    """A frown, a lip press or a lower-lip drop moves the landmarks 1/25 as much as the mean mouth morph: with one
    L1 penalty for all they stay at 0 whatever the performer does (the dead ARKit columns of issue 13); scaled by
    their energy (l1_scaling, default 1) they are recovered."""
    small = {"mouthFrown_L": 0.6, "mouthFrown_R": 0.6, "mouthLowerDown_L": 0.6, "mouthLowerDown_R": 0.6}
    poses = [("neutral", {}), ("neutral", dict(small, jawOpen=0.3)), ("happy", {"mouthPress_L": 0.7}), ("angry", {})]
    keyshapes, _ = keyshapes3d_from_weights(character, poses)
    names = character.meta["target_names"]

    def fit(scaling):
        params = {"contact_sheet": False, "l1_scaling": scaling}
        return run_stage(KeymorphFit, params, {"keyshapes": keyshapes, "character": character}).arrays[
            "keymorph_weights"
        ]

    scaled, flat = fit(1.0), fit(0.0)
    for name, value in small.items():
        assert 0.6 * value <= scaled[1, names.index(name)] <= value + 0.08, (name, scaled[1, names.index(name)])
        assert flat[1, names.index(name)] < 0.3 * value, name
    assert scaled[1, names.index("jawOpen")] == pytest.approx(0.3, abs=0.05)
    assert scaled[2, names.index("mouthPress_L")] > 0.4 > flat[2, names.index("mouthPress_L")]


def test_mouth_close_never_exceeds_the_jaw(character):
    """ARKit's mouthClose is a corrective on top of jawOpen: the 3D fit bounds it by the fitted jaw."""
    poses = [("neutral", {}), ("neutral", {"jawOpen": 0.4, "mouthClose": 0.35}), ("happy", {}), ("angry", {})]
    keyshapes, _ = keyshapes3d_from_weights(character, poses)
    names = character.meta["target_names"]
    w = run_stage(KeymorphFit, {"contact_sheet": False}, {"keyshapes": keyshapes, "character": character}).arrays[
        "keymorph_weights"
    ]
    assert w[1, names.index("jawOpen")] == pytest.approx(0.4, abs=0.06)
    assert 0.2 < w[1, names.index("mouthClose")] <= w[1, names.index("jawOpen")] + 1e-6


def test_space_2d_is_the_front_view_fit(character):
    keyshapes, _ = keyshapes3d_from_weights(character, POSES_3D)
    out = run_stage(
        KeymorphFit, {"contact_sheet": False, "space": "2d"}, {"keyshapes": keyshapes, "character": character}
    )
    assert out.meta["space"] == "2d"
    no_depth, _ = keyshapes_from_weights(character, POSES_3D)
    with pytest.raises(UserError, match="space: 3d needs keyshapes in 3D") as err:
        run_stage(KeymorphFit, {"contact_sheet": False, "space": "3d"}, {"keyshapes": no_depth, "character": character})
    assert err.value.field == "params.space"


# ------------------------------------------------------------------------------------------- real data (CREMA-D)


@pytest.fixture(scope="module")
def crema_keymorphs(character):
    from test_keyshapes import crema_face_branch

    branch = crema_face_branch()
    out = run_stage(
        KeymorphFit,
        {"tile_size": 48, "contact_sheet": True},
        {"keyshapes": branch.keyshapes, "character": character, "tracks": branch.train},
    )
    return branch, out


def test_crema_keymorph_drafts_match_the_keyshapes(crema_keymorphs, character):
    branch, out = crema_keymorphs
    ks = branch.keyshapes
    w = out.arrays["keymorph_weights"]
    assert w.shape == (len(ks["keyshapes"]), len(character.meta["target_names"]))
    assert out.meta["pose_correction"] == "applied"
    # the drafts explain most of the landmark deformation, with a handful of targets each
    assert out.metrics["landmark_error_rms_iod"] < 0.6 * out.metrics["landmark_error_neutral_rms_iod"]
    assert out.metrics["mean_active_targets"] < 20
    # expression semantics survive: happy keymorphs smile more than angry ones, angry ones lower the brows more
    names = character.meta["target_names"]
    smile = [names.index(n) for n in ("mouthSmile_L", "mouthSmile_R")]
    brow = [names.index(n) for n in ("browDown_L", "browDown_R")]
    mean = {label: w[ks["keyshape_expression"] == s].mean(axis=0) for s, label in enumerate(ks.meta["labels"])}
    assert mean["happy"][smile].mean() > 2 * mean["angry"][smile].mean()
    assert mean["angry"][brow].mean() > 2 * mean["happy"][brow].mean()
    sheet = cv2.imdecode(out.arrays["contact_sheet"], cv2.IMREAD_COLOR)
    assert sheet.shape[1] == max(ks.meta["keyshape_counts"]) * 48


def test_a_stretched_open_mouth_is_no_funnel(character):
    """Known answer (issue 13, CREMA-D fear): an open jaw with the lips stretched and the lower lip pulled down
    beyond what the character's mouthLowerDown reaches. Without the funnel/stretch antagonism the fit lowered
    that lip with a funnel, its corners drawn in, cancelled by the stretch; the performer rounded nothing."""
    names = character.meta["target_names"]
    pose = {"jawOpen": 0.4, "mouthStretch_L": 0.5, "mouthStretch_R": 0.5}
    pose.update(mouthLowerDown_L=1.0, mouthLowerDown_R=1.0)
    keyshapes, _ = keyshapes3d_from_weights(
        character, [("neutral", {}), ("neutral", pose), ("happy", {}), ("angry", {})]
    )
    lower_lip = [55, 56, 57, 58, 59, 64, 65, 66, 67]
    shapes = np.array(keyshapes["keyshapes3d"])
    shapes[1, lower_lip, 1] -= 0.1  # the performer's lower lip 0.1 IOD further down (the keyshapes have IOD 1)
    arrays = {name: keyshapes[name] for name in keyshapes.names}
    arrays["keyshapes3d"] = shapes.astype(np.float32)
    keyshapes = artifact(arrays, meta=keyshapes.meta)
    jaw, funnel, stretch = (names.index(n) for n in ("jawOpen", "mouthFunnel", "mouthStretch_L"))

    def fit(**params):
        inputs = {"keyshapes": keyshapes, "character": character}
        return run_stage(KeymorphFit, {"contact_sheet": False, **params}, inputs).arrays["keymorph_weights"][1]

    w = fit()
    assert w[funnel] < 0.05 and w[jaw] > 0.4 and w[stretch] > 0.3, (w[jaw], w[funnel], w[stretch])
    before = [p for p in KeymorphFit.Params().antagonists if tuple(p) != ("mouthFunnel", "mouthStretch")]
    old = fit(antagonists=before)
    assert old[funnel] > 0.1 and old[stretch] > 0.3, (old[funnel], old[stretch])


def cheek_skin_vertices(character):
    """Twelve vertices standing in for the FaceMesh cheek points (stages.retarget.movements.EXTRA_VERTICES): per
    side, three where a puff bulges most and three of the skin a cheek raise lifts most that the lids' morphs leave
    still (not the lid itself)."""
    names, deltas = character.meta["target_names"], np.asarray(character["deltas"], np.float64)

    def most(morph, side, away_from=()):
        moved = deltas[names.index(f"{morph}_{side}")]
        score = np.linalg.norm(moved, axis=1) if morph == "cheekPuff" else moved[:, 1]
        lids = sum(np.abs(deltas[names.index(f"{m}_{side}")]).sum(axis=1) for m in away_from)
        return np.argsort(np.where(lids < 0.1 * score.max(), score, -np.inf) if away_from else score)[-3:].tolist()

    lids = ("eyeBlink", "eyeLookUp")
    return [v for side in "LR" for v in most("cheekPuff", side) + most("cheekSquint", side, lids)]


def test_the_cheeks_skin_tells_a_cheek_raise_from_lids_that_follow_the_gaze(character):
    """Known answer (issue 13.4): the cheek region is fitted on the skin below the lids too (the FaceMesh cheek
    points after the 68). Lids raised by a look up (eyeLookUp, which the fit leaves out) are no cheek raise, nor is
    the cheek a smile lifts; a cheek raise is found. On the lids and nose alone (no cheek points) the look up was a
    cheek raise and the cheek raise mostly missed: the ARKit CheekSquint moved with the gaze."""
    poses = [
        ("neutral", {}),
        ("neutral", {"eyeLookUp_L": 0.8, "eyeLookUp_R": 0.8}),
        ("happy", {"cheekSquint_L": 0.6, "cheekSquint_R": 0.6}),
        ("happy", {"mouthSmile_L": 0.6, "mouthSmile_R": 0.6}),
    ]
    names = character.meta["target_names"]
    squint = [names.index("cheekSquint_L"), names.index("cheekSquint_R")]
    weights = {}
    for label, cheeks in (("skin", cheek_skin_vertices(character)), ("lids", ())):
        keyshapes, _ = keyshapes3d_from_weights(character, poses, cheeks)
        out = run_stage(KeymorphFit, {"contact_sheet": False}, {"keyshapes": keyshapes, "character": character})
        weights[label] = out.arrays["keymorph_weights"][:, squint]
    skin, lids = weights["skin"], weights["lids"]
    assert skin[1].max() < 0.05 and skin[3].max() < 0.05, skin
    assert skin[2].min() > 0.4, skin  # the lower lid's share goes to eyeSquint, fitted first
    # the failures the cheek points mend: on the lids alone the look up raised the cheek (0.11) and the cheek
    # raise was found at a sixth of its weight
    assert lids[1].min() > 0.08 and lids[2].max() < 0.2, lids


def test_keyshapes_without_cheek_points_fit_on_the_68(character):
    """Keyshapes without the cheek points (older runs) fit the cheeks on the lids and nose and say which points
    they lacked; a region left with none of its points is a user error naming params.regions."""
    keyshapes, _ = keyshapes3d_from_weights(character, [("neutral", {}), ("happy", {"cheekSquint_L": 0.5})])
    out = run_stage(KeymorphFit, {"contact_sheet": False}, {"keyshapes": keyshapes, "character": character})
    assert out.meta["fit"]["points_not_in_keyshapes"] == {"cheeks": CHEEK_RAISE_POINTS}
    assert "cheekSquint_L" in out.meta["fit"]["regions"]["cheeks"]
    cheeks_only = {
        "name": "cheek skin",
        "landmarks": CHEEK_RAISE_POINTS,
        "morphs": ["cheek*"],
        "decomposition": "mouth",
    }
    params = {"contact_sheet": False, "regions": [cheeks_only]}
    with pytest.raises(UserError, match="cheek skin") as error:
        run_stage(KeymorphFit, params, {"keyshapes": keyshapes, "character": character})
    assert error.value.field == "params.regions"


def test_a_mistracked_landmark_does_not_recruit_other_morphs(character):
    """Known answer: a keyshape made by the jaw and a smile, one of its landmarks off by 0.1-0.15 IOD (a tracking
    glitch, or a lip beyond the character's reach). With squared residuals the fit chases that one point with
    other morphs (weights off by 0.19-0.42); with Huber's loss beyond 0.025 IOD (``robust_iod``, the default) every
    weight stays within 0.1 of the fit of the clean keyshape."""
    names = character.meta["target_names"]
    pose = {"jawOpen": 0.4, "mouthSmile_L": 0.5, "mouthSmile_R": 0.5}
    poses = [("neutral", {}), ("neutral", pose), ("happy", {}), ("angry", {})]
    clean, _ = keyshapes3d_from_weights(character, poses)

    def fit(keyshapes, **params):
        inputs = {"keyshapes": keyshapes, "character": character}
        return run_stage(KeymorphFit, {"contact_sheet": False, **params}, inputs).arrays["keymorph_weights"][1]

    reference = {robust: fit(clean, robust_iod=robust) for robust in (0.025, None)}
    assert reference[0.025][names.index("jawOpen")] == pytest.approx(0.4, abs=0.05)
    for point, axis, offset in ((57, 1, -0.15), (54, 0, 0.15), (62, 1, 0.1), (8, 1, -0.15)):
        shapes = np.array(clean["keyshapes3d"])
        shapes[1, point, axis] += offset
        arrays = {name: clean[name] for name in clean.names}
        arrays["keyshapes3d"] = shapes.astype(np.float32)
        glitched = artifact(arrays, meta=clean.meta)
        robust = np.abs(fit(glitched) - reference[0.025]).max()
        squared = np.abs(fit(glitched, robust_iod=None) - reference[None]).max()
        assert robust < 0.1 < 0.15 < squared, (point, robust, squared)


def talking_take_with_brows(held: bool, frames=150, seed=3):
    """A tracked take (FaceMesh in image axes) of the face model talking, the jaw opening and closing, and the
    truth weights per frame. ``held=False``: the brows rest but rise (browInnerUp and browOuterUp 0.6) at every lip
    closure, as speakers raise them at pauses, and lower (browDown 0.6) in a few frames. ``held=True``: the take
    opens on 20 frames of a neutral face, mouth shut, then holds the brows raised while it talks (fear), as CREMA-D's
    takes do."""
    from test_keyshapes import mesh_from_landmarks

    from stages.geometry.rotations import euler_to_quat, quat_to_matrix
    from stages.tracking.face3d import load_face3d
    from stages.tracking.landmarks68 import mesh_to_ibug68

    face = load_face3d()
    names = ["jawOpen", "browInnerUp_L", "browInnerUp_R", "browOuterUp_L", "browOuterUp_R", "browDown_L", "browDown_R"]
    rng = np.random.default_rng(seed)
    truth = np.zeros((frames, len(names)))
    truth[:, 0] = np.clip(0.5 * np.sin(np.arange(frames) * 0.45) + 0.1, 0.0, None)  # talking: shut a third of the time
    closed = truth[:, 0] == 0
    if held:  # the lips part while it talks: its closed-mouth frames are the neutral start
        truth[20:, 0] = np.maximum(truth[20:, 0], 0.08)
        truth[:20, 0] = 0.0
        truth[20:, 1:5] = 0.6
    else:
        truth[closed, 1:5] = 0.6
        truth[np.flatnonzero(~closed)[::9][:6], 5:7] = 0.6
    offsets = np.stack([face.expression_offsets[n] for n in names])
    points = face.neutral + np.einsum("fm,mpc->fpc", truth, offsets)
    turn = quat_to_matrix(euler_to_quat(rng.normal(0, 0.1, frames), rng.normal(0, 0.05, frames), np.zeros(frames)))
    seen = np.einsum("fij,fpj->fpi", turn, points) * 6.0 + [320.0, 240.0, 0.0]
    mesh = mesh_from_landmarks(seen)
    tracks = artifact(
        {
            "landmarks": mesh_to_ibug68(mesh)[..., :2].astype(np.float32),
            "mesh": mesh.astype(np.float32),
            "sequence": np.zeros(frames, np.int32),
        },
        meta={"labels": ["take"], "fps": [30.0]},
    )
    return tracks, truth


def brow_keymorphs(character, tracks, truth, brow_rest):
    """Per keyshape of the take: (mean browDown, largest brow raise) of its keymorph, and its truth row."""
    from stages.retarget.keyshapes import CaptureKeyshapes

    keyshapes = run_stage(CaptureKeyshapes, {"k": 10, "brow_rest": brow_rest}, {"tracks": tracks})
    out = run_stage(KeymorphFit, {"contact_sheet": False}, {"keyshapes": keyshapes.view(), "character": character})
    names = character.meta["target_names"]
    weights = out.arrays["keymorph_weights"]
    down = weights[:, [names.index("browDown_L"), names.index("browDown_R")]].mean(axis=1)
    up = weights[:, [names.index(n) for n in names if n.startswith(("browInnerUp", "browOuterUp"))]].max(axis=1)
    return down, up, truth[keyshapes.arrays["keyshape_frame"]]


@pytest.mark.parametrize("brow_rest", ["median", "closed_mouth"])
def test_where_the_brows_rest(character, brow_rest):
    """Known answers for ``brow_rest``. Closed-mouth frames pick the mouth's rest, not the brows'. A performer whose
    brows rise at every lip closure and rest otherwise: with the brows resting at their median the character's
    brows rest too; at the closed-mouth frames every resting-brow keyshape reads as a frown and the raise is lost.
    A take that holds raised brows after a neutral start (fear): at the closed-mouth frames (the neutral start)
    the raise is recovered; at the median the raise is the rest, lost, and the neutral start reads as a frown."""
    down, up, truth = brow_keymorphs(character, *talking_take_with_brows(held=False), brow_rest)
    resting, raised = truth[:, 1:].max(axis=1) == 0, truth[:, 1] > 0
    assert resting.sum() >= 2 and raised.any()
    held_down, held_up, held_truth = brow_keymorphs(character, *talking_take_with_brows(held=True), brow_rest)
    held_raised, neutral = held_truth[:, 1] > 0, held_truth[:, 1:].max(axis=1) == 0
    assert held_raised.sum() >= 2
    if brow_rest == "median":
        assert down[resting].max() < 0.1 and up[resting].max() < 0.1, (down, up)
        assert up[raised].min() > 0.3
        assert held_up[held_raised].max() < 0.15
        assert not neutral.any() or held_down[neutral].min() > 0.3
    else:
        assert down[resting].min() > 0.2 and up[raised].max() < 0.1
        assert held_up[held_raised].min() > 0.3 and held_down[held_raised].max() < 0.1


def test_lips_apart_are_not_pressed(character):
    """Known answer: mouthPress presses the lips together, so a keyshape whose lips are apart gets none
    (``contact_gap``), even one the character makes with a press (jawOpen 0.3 and mouthPress 0.7: the press lifts
    the chin and lower lip, the lips stay 0.09 IOD apart; CREMA-D fear used a press so, 0.25-0.45 over an open
    mouth), while a closed-lip keyshape keeps its press. ``contact_gap: null`` gives the press back (0.29: the
    jaw takes the rest of the lift)."""
    names = character.meta["target_names"]
    open_press = {"jawOpen": 0.3, "mouthPress_L": 0.7, "mouthPress_R": 0.7}
    poses = [("neutral", {}), ("neutral", open_press), ("happy", {"mouthPress_L": 0.7}), ("angry", {})]
    keyshapes, _ = keyshapes3d_from_weights(character, poses)
    gaps = lip_gap_iod(front_view(np.asarray(keyshapes["keyshapes3d"], np.float64)))
    assert gaps[1] > 0.06 > gaps[2], gaps
    press = [names.index("mouthPress_L"), names.index("mouthPress_R")]

    def fit(**params):
        inputs = {"keyshapes": keyshapes, "character": character}
        return run_stage(KeymorphFit, {"contact_sheet": False, **params}, inputs)

    held, free = fit(), fit(contact_gap=None)
    assert held.metrics["contact_held_keyshapes"] == 1 and free.metrics["contact_held_keyshapes"] == 0
    assert held.meta["fit"]["unmatched_contact_patterns"] == []
    assert fit(contact_morphs=["lipSeal*"]).meta["fit"]["unmatched_contact_patterns"] == ["lipSeal*"]
    w, w_free = held.arrays["keymorph_weights"], free.arrays["keymorph_weights"]
    assert not w[1, press].any() and (w_free[1, press] > 0.2).all(), (w[1, press], w_free[1, press])
    assert w[2, press[0]] > 0.4 and w_free[2, press[0]] > 0.4
    assert w[1, names.index("jawOpen")] > 0.2  # the open mouth is still the jaw's, and still fits
    assert held.arrays["landmark_error"][1] < 0.01
    # the 2D fit holds the same keyshape's press
    w2d = fit(space="2d").arrays["keymorph_weights"]
    assert not w2d[1, press].any()


def renamed(character, names):
    """The character with other morph names (its arrays as they are)."""
    return artifact({n: character[n] for n in character.names}, meta=dict(character.meta, target_names=names))


def test_morphs_named_as_no_region_expects_are_placed_by_what_they_move(fitted_3d, character):
    """A character whose sculptor named its morphs ``shape_00``... (no jaw*, mouth*, ...): each joins the region
    whose landmarks it moves most, so the face still moves, the jaw drop still apart from the rounded lips (before,
    no morph was fitted: a face that never moved, exit 0)."""
    keyshapes, truth, named = fitted_3d
    names = list(character.meta["target_names"])
    generic = [f"shape_{m:02d}" for m in range(len(names))]
    out = run_stage(
        KeymorphFit, {"contact_sheet": False}, {"keyshapes": keyshapes, "character": renamed(character, generic)}
    )
    placed = out.meta["fit"]["regions_by_motion"]
    assert placed[generic[names.index("jawOpen")]] == placed[generic[names.index("mouthFunnel")]] == "mouth"
    assert (
        placed[generic[names.index("eyeBlink_L")]] == "eyes" and placed[generic[names.index("browDown_R")]] == "brows"
    )
    assert any("placed by the landmarks they move" in w for w in out.warnings)
    w, w_named = out.arrays["keymorph_weights"], named.arrays["keymorph_weights"]
    for name in ("jawOpen", "mouthFunnel", "eyeBlink_L", "browDown_L"):
        m = names.index(name)
        np.testing.assert_allclose(w[:, m], w_named[:, m], atol=0.05, err_msg=name)
    assert out.meta["morph_regions"][generic[names.index("jawOpen")]] == "mouth"


def test_one_morph_named_as_expected_leaves_the_naming_to_the_user(fitted_3d, character):
    keyshapes, _, _ = fitted_3d
    names = list(character.meta["target_names"])
    mixed = [n if n == "jawOpen" else f"shape_{m:02d}" for m, n in enumerate(names)]
    out = run_stage(
        KeymorphFit, {"contact_sheet": False}, {"keyshapes": keyshapes, "character": renamed(character, mixed)}
    )
    assert "regions_by_motion" not in out.meta["fit"]
    assert out.meta["fit"]["usable_targets"] == ["jawOpen"]


def test_a_character_whose_morphs_move_no_landmark_is_a_user_error(fitted_3d, character):
    keyshapes, _, _ = fitted_3d
    arrays = {n: character[n] for n in character.names}
    arrays["deltas"] = np.zeros_like(arrays["deltas"])
    still = artifact(arrays, meta=dict(character.meta, target_names=[f"s{m}" for m in range(len(arrays["deltas"]))]))
    with pytest.raises(UserError, match="none of the character's .* morphs moves") as caught:
        run_stage(KeymorphFit, {"contact_sheet": False}, {"keyshapes": keyshapes, "character": still})
    assert caught.value.field == "inputs.character"
