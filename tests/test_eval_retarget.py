"""Retargeting evaluation: known answers on a performer who *is* the character (its landmark vertices animated by
known morph weights, posed and projected like a tracked face), the calibration against a shifted animation, and the
event and audio metrics on their own."""

import cv2
import numpy as np
import pytest

from msflow import UserError
from msflow.testing import artifact, run_stage
from stages.eval.events import closure_agreement, event_agreement, eye_aperture, lip_gap, runs
from stages.eval.retarget import (
    RetargetEval,
    align_to_model,
    audio_envelope,
    character_landmarks,
    pose_and_project,
    pose_on_tracked_face,
)
from stages.retarget.character import GltfCharacter
from stages.tracking.face3d import load_face3d

ICT = "data/characters/ict-facekit.glb"
FRAMES, FPS, RATE = 90, 30.0, 16000
CAMERA = np.array([[480.0, 0, 240], [0, 480, 180], [0, 0, 1]])


@pytest.fixture(scope="module")
def character():
    return run_stage(GltfCharacter, {}, {"mesh": {"path": ICT}}).view()


def known_weights(names):
    """Jaw opening and closing (with a little funnel), lips sealed at frames 40-47, a blink at 60-62."""
    w = np.zeros((FRAMES, len(names)))
    t = np.arange(FRAMES)
    jaw = np.clip(0.6 * np.sin(2 * np.pi * t / 30.0), 0, None)
    w[:, names.index("jawOpen")] = jaw
    w[:, names.index("mouthFunnel")] = 0.2 * jaw
    w[40:48] = 0.0
    w[60:63, names.index("eyeBlink_L")] = w[60:63, names.index("eyeBlink_R")] = 1.0
    return w


def head_motion():
    """Small nods and turns, the head 60 cm in front of the camera (rotation quaternions, translation cm)."""
    from stages.geometry.rotations import euler_to_quat

    t = np.arange(FRAMES) / FPS
    translation = np.stack([1 + np.sin(t), 2 + 0 * t, -60 + np.cos(t)], axis=1)
    return euler_to_quat(0.15 * np.sin(1.3 * t), 0.1 * np.sin(0.7 * t + 1), 0.05 * np.sin(t)), translation


def opencv_projection(points, rotation, translation):
    """The same pinhole projection done by OpenCV (camera axes x right, y down, z forward) as a cross-check."""
    from stages.geometry.rotations import quat_to_matrix

    flip = np.diag([1.0, -1.0, -1.0])
    out = []
    for p, q, t in zip(points, rotation, translation):
        rvec, _ = cv2.Rodrigues(flip @ quat_to_matrix(q))
        image, _ = cv2.projectPoints(p, rvec, flip @ t, CAMERA, np.zeros(4))
        out.append(image.reshape(-1, 2))
    return np.array(out)


def facemesh_of(points, rotation, translation, orthographic=False):
    """A 468-point FaceMesh whose iBUG points are ``points`` (frames, 68, 3) posed and seen by the camera: image x,
    y and a relative depth z in pixels (away from the camera), as the tracker gives them; every other vertex rides
    rigidly on the nose tip, but for the cheek points (``movements.EXTRA_VERTICES``) when ``points`` carries them
    (frames, 68 + 12, 3). ``orthographic``: seen without perspective, every point
    scaled as the face's mean depth would be (a scaled orthographic view: a very long lens from far away)."""
    from stages.geometry.rotations import quat_to_matrix
    from stages.retarget.movements import EXTRA_VERTICES
    from stages.tracking.landmarks68 import MESH_TO_IBUG68

    cam = np.einsum("fij,fpj->fpi", quat_to_matrix(rotation), points) + translation[:, None]
    depth = -cam[..., 2]
    image = opencv_projection(points, rotation, translation)
    if orthographic:
        scale = CAMERA[0, 0] / depth.mean(axis=1, keepdims=True)
        image = np.stack([cam[..., 0] * scale, -cam[..., 1] * scale], axis=-1) + CAMERA[:2, 2]
    z = (depth - depth.mean(axis=1, keepdims=True)) * CAMERA[0, 0] / depth.mean(axis=1, keepdims=True)
    posed = np.concatenate([image, z[..., None]], axis=-1)
    mesh = np.repeat(posed[:, 30:31], 468, axis=1)
    for point, vertices in enumerate(MESH_TO_IBUG68):
        mesh[:, list(vertices)] = posed[:, point : point + 1]
    if points.shape[1] > 68:
        mesh[:, list(EXTRA_VERTICES)] = posed[:, 68:]
    return mesh


def performance(character, weights, audio_gain=None, mesh=True, motion=None):
    """A tracking artifact of the character itself: landmarks = its landmark vertices under ``weights`` (and a
    FaceMesh made of them), the head moving as ``motion`` says (rotations, translations; ``head_motion()``)."""
    rotation, translation = head_motion() if motion is None else motion
    model = load_face3d().neutral
    neutral = character_landmarks(character["neutral"], character["deltas"], character["landmark_ids"], weights[:1] * 0)
    points = align_to_model(neutral[0], model).apply(
        character_landmarks(character["neutral"], character["deltas"], character["landmark_ids"], weights)
    )
    landmarks = opencv_projection(points, rotation, translation)
    arrays = {
        "landmarks": landmarks.astype(np.float32),
        "rotation": rotation,
        "translation": translation,
        "sequence": np.zeros(FRAMES, np.int32),
    }
    if mesh:
        arrays["mesh"] = facemesh_of(points, rotation, translation).astype(np.float32)
    meta = {"labels": ["take"], "fps": [FPS], "frame_size": [[480, 360]], "focal_length": [480.0]}
    if audio_gain is not None:
        rng = np.random.default_rng(0)
        gain = np.repeat(audio_gain, RATE // int(FPS))
        arrays["audio"] = (gain * rng.normal(size=gain.size)).astype(np.float32)
        arrays["audio_bounds"] = np.array([[0, gain.size]])
        meta.update(audio_rate=[RATE], audio_offset=[0.0])
    return artifact(arrays, meta=meta)


def evaluate(character, tracks, weights, **params):
    blend = artifact({"weights": weights.astype(np.float32)}, meta={"target_names": character.meta["target_names"]})
    return run_stage(RetargetEval, params, {"tracks": tracks, "blend": blend, "character": character})


@pytest.fixture(scope="module")
def truth(character):
    names = character.meta["target_names"]
    weights = known_weights(names)
    tracks = performance(character, weights, audio_gain=0.05 + weights[:, names.index("jawOpen")])
    return weights, tracks, evaluate(character, tracks, weights)


# ------------------------------------------------------------------------------------------------ known answers


def test_projection_matches_opencv(character, truth):
    weights, tracks, _ = truth
    rotation, translation = head_motion()
    points = np.random.default_rng(1).normal(scale=5.0, size=(FRAMES, 7, 3))
    np.testing.assert_allclose(
        pose_and_project(points, rotation, translation, CAMERA),
        opencv_projection(points, rotation, translation),
        atol=1e-6,
    )


def test_the_characters_own_animation_scores_zero(truth):
    _, _, out = truth
    m = out.metrics
    for region in ("mouth", "eyes", "brows", "jaw"):
        assert m[f"{region}_error_iod"] < 1e-4, region
        assert m[f"{region}_motion_error_iod"] < 1e-4, region
    assert m["pose_rms_px"] < 1e-3
    # the lips sealed at 40-47 (and at the jaw's closed half-periods) are found and reproduced
    assert m["closures"] >= 1 and m["closures_reproduced"] == m["closures"]
    assert any(c["start"] <= 40 and c["stop"] >= 48 for c in out.meta["closures"])
    # the blink at 60-62 is found in the performer and in the character
    assert m["blinks"] == 1 and m["blink_recall"] == 1.0 and m["false_blink_rate"] == 0.0
    assert out.meta["blinks"]["performer"][0][0] in (59, 60, 61)
    assert m["jaw_over_funnel_fraction"] == 1.0 and m["jaw_minus_funnel"] > 0.3
    # mouth opening follows an audio envelope made from it, for the performer and the character alike
    assert m["envelope_r_character"] > 0.8
    assert abs(m["envelope_r_character"] - m["envelope_r_performer"]) < 1e-6
    # the smiles never moved, and neither did the performer's mouth corners: dead, but not where they moved
    assert "mouthSmile_L" in out.meta["dead_morphs"]
    columns = out.meta["arkit_columns"]
    assert "JawOpen" in columns and "MouthSmileLeft" in columns
    assert columns["JawOpen"]["moved"] == ["take"] and "dead_moved" not in columns["JawOpen"]
    assert columns["MouthSmileLeft"].get("dead_not_moved") == ["take"]
    assert m["dead_arkit_moved"] == 0 and m["movements_missed"] == 0
    assert columns["EyeBlinkLeft"]["moved"] == ["take"]
    assert "TongueOut" not in columns


def test_a_shifted_animation_scores_badly(character, truth):
    """Calibration: the same animation half a take late is far from the performer, on the same data."""
    weights, tracks, out = truth
    late = evaluate(character, tracks, np.roll(weights, FRAMES // 2, axis=0))
    assert late.metrics["mouth_motion_error_iod"] > 0.03
    assert late.metrics["mouth_motion_error_iod"] == pytest.approx(out.metrics["mouth_motion_error_iod_shifted"])
    assert late.metrics["blink_recall"] == 0.0 and late.metrics["false_blink_rate"] == 1.0
    assert late.metrics["envelope_r_character"] < 0.3


def test_a_silent_take_has_no_envelope_correlation(character, truth):
    """A take tracked without sound (the tracking's ``audio: optional``) has empty audio bounds. It has no
    envelope to correlate with, so it gives no envelope r, instead of an r of 0 pooled with the other takes'."""
    weights, tracks, _ = truth
    arrays = {name: np.asarray(tracks[name]) for name in tracks.names}
    arrays["audio_bounds"] = np.array([[arrays["audio"].size, arrays["audio"].size]])
    silent = artifact(arrays, meta={**tracks.meta, "has_audio": [False]})
    out = evaluate(character, silent, weights)
    assert not [key for key in out.metrics if key.startswith("envelope_r")]
    assert any("no audio in take" in warning for warning in out.warnings)
    assert out.metrics["mouth_motion_error_iod"] < 1e-4  # the rest is scored as before


def test_the_silent_takes_warning_names_the_first_five():
    """A folder tracked without sound (``audio: none``) warns once, naming five takes and counting the rest."""
    from stages.eval.retarget import evaluation_warnings

    labels = [f"take{i}" for i in range(7)]
    data = {"mesh": np.zeros(1), "names": ["jawOpen", "mouthFunnel"], "labels": labels, "audio": None}
    (warning,) = evaluation_warnings(data)
    assert warning.startswith("no audio in take0, take1, take2, take3, take4 and 2 more takes:")
    data["audio"] = [(np.ones(8), 16000.0, 0.0)] * 7
    assert evaluation_warnings(data) == []


def test_pose_on_tracked_face_recovers_a_known_similarity():
    """Head-frame points seen through a known similarity (FaceMesh image axes: y down, z away) come back exactly."""
    from stages.geometry.rotations import euler_to_quat, quat_to_matrix

    rng = np.random.default_rng(2)
    points = rng.normal(scale=3.0, size=(5, 68, 3))
    rotation = quat_to_matrix(euler_to_quat(rng.normal(0, 0.3, 5), rng.normal(0, 0.3, 5), rng.normal(0, 0.3, 5)))
    scale, shift = rng.uniform(5, 20, size=(5, 1, 1)), rng.normal(0, 100, size=(5, 1, 3))
    image = scale * np.einsum("fij,fpj->fpi", rotation, points) * np.array([1.0, -1.0, -1.0]) + shift
    np.testing.assert_allclose(pose_on_tracked_face(points, image), image[..., :2], atol=1e-8)


def test_the_own_face_pose_does_not_depend_on_the_pose_model(character, truth):
    """A tracked head pose 5 degrees off in pitch (what a generic pose model fitted to a face of other
    proportions gives) moves the character's projected mouth away from the performer's; posed on the performer's
    own FaceMesh, the same animation scores the same. Its own animation scores within the weak-perspective error
    of a head 60 cm from a 53-degree camera; the animation half a take late scores far worse."""
    from stages.geometry.rotations import euler_to_quat, quat_multiply

    weights, tracks, out = truth
    arrays = {k: np.asarray(tracks[k]) for k in tracks.names}
    tilt = euler_to_quat(np.zeros(1), np.full(1, np.radians(5.0)), np.zeros(1))
    arrays["rotation"] = quat_multiply(arrays["rotation"], np.repeat(tilt, FRAMES, axis=0))
    tilted = evaluate(character, artifact(arrays, meta=tracks.meta), weights)
    assert tilted.metrics["mouth_error_iod"] > out.metrics["mouth_error_iod"] + 0.03
    assert tilted.metrics["mouth_face_posed_error_iod"] == pytest.approx(out.metrics["mouth_face_posed_error_iod"])
    assert out.metrics["mouth_face_posed_error_iod"] < 0.02
    late = evaluate(character, tracks, np.roll(weights, FRAMES // 2, axis=0))
    assert late.metrics["mouth_face_posed_error_iod"] > 3 * out.metrics["mouth_face_posed_error_iod"]


def test_open_lips_at_a_closure_are_not_a_seal(character, truth):
    weights, tracks, _ = truth
    names = character.meta["target_names"]
    opened = weights.copy()
    opened[40:48, names.index("jawOpen")] = 0.3
    out = evaluate(character, tracks, opened)
    sealed = [c for c in out.meta["closures"] if c["start"] <= 40 and c["stop"] >= 48]
    assert sealed and not sealed[0]["reproduced"]
    assert out.metrics["closures_reproduced"] < out.metrics["closures"]


def test_funnel_instead_of_jaw_is_caught(character, truth):
    weights, tracks, _ = truth
    names = character.meta["target_names"]
    swapped = weights.copy()
    swapped[:, names.index("jawOpen")] = 0.2 * weights[:, names.index("jawOpen")]
    swapped[:, names.index("mouthFunnel")] = weights[:, names.index("jawOpen")]
    out = evaluate(character, tracks, swapped)
    assert out.metrics["jaw_over_funnel_fraction"] == 0.0 and out.metrics["jaw_minus_funnel"] < 0


def test_the_widest_jaw_frames_are_the_jaws_not_the_heads_turn(character):
    """A jaw opened at frames 10-18 with the head facing the camera, the mouth closed at 50-80 while the head turns
    40 degrees aside: in the image, the turn narrows the eyes' distance and so lengthens the chin-to-nose-bridge
    distance over it more than the jaw does; the chin's drop in the head frame picks the open jaw."""
    from stages.geometry.rotations import euler_to_quat

    names = character.meta["target_names"]
    weights = np.zeros((FRAMES, len(names)))
    weights[10:19, names.index("jawOpen")] = 0.4
    t = np.arange(FRAMES)
    yaw = np.radians(40.0) * np.sin(np.pi * (t - 50) / 30.0) * ((t >= 50) & (t < 80))
    translation = np.tile([0.0, 0.0, -60.0], (FRAMES, 1))
    tracks = performance(character, weights, motion=(euler_to_quat(yaw, 0 * t, 0 * t), translation))
    opened = set(range(10, 19))
    by_head = evaluate(character, tracks, weights)
    by_image = evaluate(character, tracks, weights, widest_by="image")
    assert set(by_head.meta["widest_jaw_frames"]) <= opened
    assert by_head.metrics["jaw_over_funnel_fraction"] == 1.0
    assert not set(by_image.meta["widest_jaw_frames"]) & opened
    assert by_image.metrics["jaw_over_funnel_fraction"] == 0.0
    assert [by_head.meta["takes"]["take"]["widest_by"], by_image.meta["takes"]["take"]["widest_by"]] == [
        "head_frame",
        "image",
    ]


def test_a_press_over_open_lips_is_counted(character, truth):
    """The character's own animation presses no lips; a press added over the performer's open-lip frames is
    counted there (and only there: a press while the lips are closed is contact)."""
    weights, tracks, out = truth
    names = character.meta["target_names"]
    assert out.metrics["press_apart_fraction"] == 0.0
    apart = lip_gap(np.asarray(tracks["landmarks"], np.float64)) > 0.1
    assert 0 < apart.sum() < FRAMES
    pressed = weights.copy()
    pressed[:, names.index("mouthPress_L")] = np.where(apart, 0.5, 0.0)
    assert evaluate(character, tracks, pressed).metrics["press_apart_fraction"] == 1.0
    closed_only = weights.copy()
    closed_only[:, names.index("mouthPress_R")] = np.where(apart, 0.0, 0.5)
    assert evaluate(character, tracks, closed_only).metrics["press_apart_fraction"] == 0.0


def test_tracking_eye_aperture_is_preferred(character, truth):
    weights, tracks, _ = truth
    aperture = np.full((FRAMES, 2), 0.3, np.float32)
    aperture[20:22] = 0.05  # a blink the landmarks do not show
    arrays = {k: tracks[k] for k in tracks.names}
    with_aperture = artifact(dict(arrays, eye_aperture=aperture), meta=tracks.meta)
    out = evaluate(character, with_aperture, weights)
    assert out.meta["blink_source"] == "tracking eye_aperture"
    assert out.meta["blinks"]["performer"] == [[20, 22]] or out.meta["blinks"]["performer"] == [(20, 22)]
    assert out.metrics["blink_recall"] == 0.0 and out.metrics["false_blink_rate"] == 1.0


def test_a_movement_the_animation_never_makes_is_a_dead_column_where_moved(character, truth):
    """The performer smiles on the left while talking (frames 0-12); an animation without the smile leaves
    MouthSmileLeft dead where the performer moved it, and the right side, which did not smile, dead where it did
    not."""
    weights, _, _ = truth
    names = character.meta["target_names"]
    smiling = weights.copy()
    smiling[0:13, names.index("mouthSmile_L")] = 0.7
    out = evaluate(character, performance(character, smiling), weights)
    columns = out.meta["arkit_columns"]
    assert columns["MouthSmileLeft"]["dead_moved"] == ["take"]
    assert columns["MouthSmileRight"]["dead_not_moved"] == ["take"]
    assert out.metrics["dead_arkit_moved"] == 1 and out.metrics["movements_missed"] > 0
    # the animation with the smile has no such column
    assert evaluate(character, performance(character, smiling), smiling).metrics["dead_arkit_moved"] == 0


def test_a_movement_the_performer_never_made_is_a_false_movement(character, truth):
    """The converse of a dead column: the performer talks without smiling, the animation smiles on the left
    (mouthSmile_L 0.7, frames 0-12). The character's face, read by the performer's probes, makes MouthSmileLeft
    where the performer did not: a false movement, the right side none. The performer's own animation has none."""
    weights, tracks, exact = truth
    names = character.meta["target_names"]
    smiling = weights.copy()
    smiling[0:13, names.index("mouthSmile_L")] = 0.7
    out = evaluate(character, tracks, smiling)
    false = out.meta["takes"]["take"]["columns"]["made_not_moved"]
    assert "MouthSmileLeft" in false and "MouthSmileRight" not in false
    assert out.metrics["false_movements"] == len(false) and out.metrics["false_movement_rate"] > 0
    assert out.meta["arkit_columns"]["MouthSmileLeft"]["made_not_moved"] == ["take"]
    assert exact.metrics["false_movements"] == 0 and exact.metrics["false_movement_rate"] == 0
    assert "false_movement_rate_shuffled" not in exact.metrics  # one take: no other take to pair it with


def test_chance_levels_pair_each_take_with_the_others():
    """Known answers: take a's performer and character both move X, take b's both move Y (each animation leaves the
    other's column dead), and Z is read but never moved. Right pairs: no false movement, no movement missed. Wrong
    pairs: a's character against b's performer makes X where b did not (1 of X, Z) and b's Y where a did not
    (1 of Y, Z): false movements by chance 0.5; each performer's one movement is dead in the other animation:
    missed by chance 1."""
    from stages.eval.columns import pooled_false_movements, pooled_missed

    def take(moved, dead):
        read = {c: [0.03 if c == moved else 0.0, 0.02] for c in "XYZ"}
        columns = {"moved": [moved], "made": [moved], "dead_moved": [], "dead_not_moved": [dead, "Z"]}
        return {"columns": {**columns, "dead_unmeasured": []}, "movements": read, "character_movements": read}

    takes = {"a": take("X", "Y"), "b": take("Y", "X")}
    out = pooled_false_movements(takes)
    assert out == {"false_movements": 0.0, "false_movement_rate": 0.0, "false_movement_rate_shuffled": 0.5}
    assert pooled_missed(takes) == {"movements_missed": 0.0, "movements_missed_shuffled": 1.0}
    assert pooled_missed({"a": takes["a"]}) == {"movements_missed": 0.0}  # one take: no chance level


def test_a_movement_other_morphs_make_is_told_from_one_missing(character, truth):
    """The performer raises its left upper lip (mouthUpperUp_L 0.8, frames 0-12), which lifts the nostril wing
    with it: NoseSneerLeft's probe moves. An animation with the same weights leaves the NoseSneerLeft column dead
    where the performer moved it, but the character's face makes the movement (through mouthUpperUp): made, not
    missing. Without the lip raise the movement is missing."""
    weights, _, _ = truth
    names = character.meta["target_names"]
    raised = weights.copy()
    raised[0:13, names.index("mouthUpperUp_L")] = 0.8
    tracks = performance(character, raised)
    made = evaluate(character, tracks, raised)
    take = made.meta["takes"]["take"]["columns"]
    assert "NoseSneerLeft" in take["dead_moved"] and "NoseSneerLeft" in take["dead_moved_made"]
    assert made.metrics["dead_arkit_moved"] >= 1 and made.metrics["dead_arkit_moved_missing"] == 0
    missing = evaluate(character, tracks, weights)
    take = missing.meta["takes"]["take"]["columns"]
    assert "NoseSneerLeft" in take["dead_moved"] and "NoseSneerLeft" not in take["dead_moved_made"]
    assert missing.metrics["dead_arkit_moved_missing"] >= 1


def test_movement_gain_is_the_share_of_the_performers_movement(character, truth):
    """Known answers: the character's own animation makes every movement the performer (the character itself)
    made as large (gain 1); the same animation at half its weights makes each half as large."""
    weights, _, _ = truth
    names = character.meta["target_names"]
    moving = weights.copy()
    moving[0:13, names.index("mouthUpperUp_L")] = 0.8
    moving[50:66, names.index("mouthSmile_R")] = 0.6
    tracks = performance(character, moving)
    for share in (1.0, 0.5):
        out = evaluate(character, tracks, moving * share)
        gains = out.meta["takes"]["take"]["movement_gains"]
        assert {"JawOpen", "MouthUpperUpLeft", "MouthSmileLeft"} <= gains.keys(), gains
        np.testing.assert_allclose(list(gains.values()), share, rtol=0.07, err_msg=str(gains))
        assert out.metrics["movement_gain_median"] == pytest.approx(share, rel=0.02)
        assert share < 1.0 or out.metrics["movement_gain_below_half"] == 0.0


def test_movement_gain_leaves_blinks_out(character, truth, monkeypatch):
    """The performer widens its eyes (frames 2-12); the animation does so too and blinks once more (36-38), as a
    character whose lids follow the eye aperture closes them further than FaceMesh's lids go. Outside the blinks
    the widening is as large (gain 1); over every frame the extra blink would read as a larger movement."""
    import stages.eval.retarget as evaluation

    weights, _, _ = truth
    names = character.meta["target_names"]
    wide = weights.copy()
    wide[2:13, [names.index("eyeWide_L"), names.index("eyeWide_R")]] = 0.8
    blinking = wide.copy()
    blinking[36:39, [names.index("eyeBlink_L"), names.index("eyeBlink_R")]] = 1.0
    tracks = performance(character, wide)
    gains = evaluate(character, tracks, blinking).meta["takes"]["take"]["movement_gains"]
    assert gains["EyeWideLeft"] == pytest.approx(1.0, abs=0.03) and gains["EyeWideRight"] == pytest.approx(
        1.0, abs=0.03
    )
    monkeypatch.setattr(evaluation, "outside_blinks", lambda blinks, frames: np.ones(frames, bool))
    assert evaluate(character, tracks, blinking).meta["takes"]["take"]["movement_gains"]["EyeWideLeft"] > 1.1


def test_without_a_facemesh_only_the_eyes_are_probed(character, truth):
    weights, _, _ = truth
    out = evaluate(character, performance(character, weights, mesh=False), weights)
    assert out.meta["movement_source"] == "2D landmarks" and any("no FaceMesh" in w for w in out.warnings)
    assert out.meta["takes"]["take"]["widest_by"] == "image"  # asked head_frame, which needs the FaceMesh
    assert "dead_not_moved" not in out.meta["arkit_columns"].get("MouthSmileLeft", {})
    assert out.meta["arkit_columns"]["MouthSmileLeft"]["dead_unmeasured"] == ["take"]
    assert out.meta["arkit_columns"]["EyeBlinkLeft"]["moved"] == ["take"]
    assert "false_movements" not in out.metrics  # the face is not read: no count, rather than a count of 0


def test_blink_narrowing_must_lie_above_the_dip():
    with pytest.raises(ValueError, match="blink_narrow_ratio"):
        RetargetEval.Params(blink_ratio=0.6, blink_narrow_ratio=0.5)


def test_frame_count_mismatch_is_a_user_error(character, truth):
    weights, tracks, _ = truth
    with pytest.raises(UserError, match="frames"):
        evaluate(character, tracks, weights[:-3])


# ------------------------------------------------------------------------------------------------ parts


#: a morph of the character and the ARKit column whose probe must see it (stages.retarget.movements)
PROBED = {
    "jawLeft": "JawLeft", "jawForward": "JawForward", "mouthClose": "MouthClose", "mouthSmile_L": "MouthSmileLeft",
    "mouthFrown_R": "MouthFrownRight", "mouthDimple_L": "MouthDimpleLeft", "mouthPress_L": "MouthPressLeft",
    "mouthRollLower": "MouthRollLower", "mouthRollUpper": "MouthRollUpper", "mouthShrugLower": "MouthShrugLower",
    "mouthPucker": "MouthPucker", "mouthStretch_R": "MouthStretchRight", "noseSneer_L": "NoseSneerLeft",
    "browDown_L": "BrowDownLeft", "browOuterUp_R": "BrowOuterUpRight", "eyeSquint_L": "EyeSquintLeft",
    "eyeWide_R": "EyeWideRight",
}  # fmt: skip


def test_the_probes_focal_length_is_found_in_the_take(character, truth):
    """The probes take the perspective out with the focal length that leaves the rigid points most rigid: the
    synthetic head filmed by a 480 px pinhole gets 480 back, whether tracking guessed 480 or twice that, and the
    same head seen without perspective gets none (infinite) taken out. The evaluation uses and reports it."""
    from stages.retarget.shapes3d import estimate_focal

    weights, tracks, out = truth
    mesh = np.asarray(tracks["mesh"], np.float64)
    assert estimate_focal(mesh, CAMERA)[0] == pytest.approx(480.0)
    guessed = CAMERA.copy()
    guessed[0, 0] = guessed[1, 1] = 960.0
    assert estimate_focal(mesh, guessed)[0] == pytest.approx(480.0)
    model = load_face3d().neutral
    neutral = character_landmarks(character["neutral"], character["deltas"], character["landmark_ids"], weights[:1] * 0)
    points = align_to_model(neutral[0], model).apply(
        character_landmarks(character["neutral"], character["deltas"], character["landmark_ids"], weights)
    )
    flat = facemesh_of(points, *head_motion(), orthographic=True)
    assert estimate_focal(flat, CAMERA)[0] == np.inf
    # a still head (or a single frame) cannot tell: tracking's guess stays
    assert estimate_focal(np.repeat(mesh[:1], 20, axis=0), guessed)[0] == pytest.approx(960.0)
    assert estimate_focal(mesh[:1], guessed)[0] == pytest.approx(960.0)
    assert out.meta["takes"]["take"]["probe_focal_length"] == pytest.approx(480.0)


def test_probes_see_each_movement_and_not_the_jaw(character):
    """Known answers: the character's own landmark vertices (head frame, IOD units) talking with the jaw, and in
    a burst (frames 30-45) one more morph at 0.6. Each probe moves for its own morph; the talking jaw alone moves
    none but JawOpen (its chin drop is taken out of the others: a dropped jaw is not a frown or a pucker)."""
    from stages.retarget.face_measures import lip_gap_iod
    from stages.retarget.movements import MovedLevels, landmark_probes, moved
    from stages.retarget.shapes3d import front_view

    names = character.meta["target_names"]
    ids = character["landmark_ids"]
    rest = character["neutral"][ids].astype(np.float64)
    deltas = character["deltas"][:, ids].astype(np.float64)
    iod = np.linalg.norm(rest[45] - rest[36])
    t = np.arange(90)

    def moved_columns(extra):
        w = np.zeros((len(t), len(names)))
        w[:, names.index("jawOpen")] = np.clip(0.5 * np.sin(2 * np.pi * t / 20), 0, None)
        if extra:
            w[30:46, names.index(extra)] = 0.6
        shapes = (rest + np.einsum("fm,mpc->fpc", w, deltas)) / iod
        probes = landmark_probes(shapes, rest / iod, lip_gap_iod(front_view(shapes)), 0.03)
        return {c for c, v in moved(probes, MovedLevels()).items() if v["moved"]}

    assert moved_columns(None) == {"JawOpen"}
    for morph, column in PROBED.items():
        assert column in moved_columns(morph), morph


def test_another_face_is_read_with_the_performers_regressions():
    """Known answers for ``probes_read_on``: the performer's own motion read this way gives its probes exactly. A
    face whose jaw lowers the lip corners by 0.44 of the chin's drop, where the performer's lowers them by 0.6,
    reads by its own regression as making no corner movement; read with the performer's, its corners rise by
    0.16 of the chin's drop above where the performer's jaw would put them (what the performer's probe reads)."""
    from stages.retarget.movements import landmark_probes, probes_read_on

    frames = 60
    chin = 0.15 * np.clip(np.sin(2 * np.pi * np.arange(frames) / 20), 0, None)
    rest = np.random.default_rng(0).normal(scale=0.3, size=(68, 3))

    def talking(corner_share):
        d = np.zeros((frames, 68, 3))
        d[:, 8, 1] = -chin
        d[:, [48, 54], 1] = -corner_share * chin[:, None]
        return rest + d

    performer, other = talking(0.6), talking(0.44)
    own = landmark_probes(performer, rest, chin, 0.03)
    same = probes_read_on(performer, rest, chin, 0.03, performer - rest, chin)
    assert same.keys() == own.keys()
    for column in own:
        np.testing.assert_allclose(same[column], own[column], atol=1e-12, err_msg=column)
    assert np.abs(landmark_probes(other, rest, chin, 0.03)["MouthSmileLeft"]).max() < 1e-9
    read = probes_read_on(performer, rest, chin, 0.03, other - rest, chin)
    np.testing.assert_allclose(read["MouthSmileLeft"], 0.16 * chin, atol=1e-9)
    np.testing.assert_allclose(read["MouthSmileRight"], 0.16 * chin, atol=1e-9)


def test_the_cheek_a_smile_lifts_is_no_cheek_squint():
    """Known answer: the skin below the lids rising with the lip corners by SMILE_CHEEK_LIFT of their rise (what a
    smile, FACS AU12, does to it) moves MouthSmile and not CheekSquint; rising a further 0.03 IOD (a cheek raise,
    AU6) moves CheekSquint. Before, the smile's share was a cheek squint: every smiling take 'moved' its cheeks."""
    from stages.retarget.movements import (
        EXTRA_VERTICES,
        SIDE_POINTS,
        SMILE_CHEEK_LIFT,
        MovedLevels,
        cheek_probes,
        moved,
    )

    frames, points = 90, 68 + len(EXTRA_VERTICES)
    burst = np.zeros(frames)
    burst[30:46] = 1.0
    cheeks = [68 + i for i in range(len(EXTRA_VERTICES))]

    def moved_columns(corner_rise, cheek_raise):
        d = np.zeros((frames, points, 3))
        d[:, SIDE_POINTS["Left"]["corner"], 1] = corner_rise * burst
        d[:, cheeks, 1] = (SMILE_CHEEK_LIFT * corner_rise + cheek_raise) * burst[:, None]
        probes = cheek_probes(d, np.zeros(frames))
        probes["MouthSmileLeft"] = d[:, SIDE_POINTS["Left"]["corner"], 1]
        return {c for c, v in moved(probes, MovedLevels()).items() if v["moved"]}

    smile = moved_columns(0.1, 0.0)
    assert "MouthSmileLeft" in smile and "CheekSquintLeft" not in smile
    assert "CheekSquintLeft" in moved_columns(0.1, 0.03)
    assert "CheekSquintLeft" in moved_columns(0.0, 0.03)


def test_runs_stop_at_take_boundaries():
    mask = np.array([0, 1, 1, 1, 1, 0, 1, 1, 0, 1], bool)
    sequence = np.array([0, 0, 0, 1, 1, 1, 1, 1, 1, 1])
    assert runs(mask, sequence) == [(1, 3), (3, 5), (6, 8), (9, 10)]
    assert runs(mask, sequence, 2) == [(1, 3), (3, 5), (6, 8)]


def test_event_agreement_counts_found_and_false():
    result = event_agreement([(10, 12), (30, 33)], [(12, 13), (50, 52)], tolerance=1)
    assert result["found"] == 1 and result["false"] == 1
    assert result["recall"] == 0.5 and result["false_rate"] == 0.5
    assert event_agreement([], [], 1)["recall"] == 1.0


def test_closure_needs_two_frames_and_compares_gaps():
    performer = np.array([0.1, 0.02, 0.1, 0.02, 0.02, 0.02, 0.1])
    character = np.array([0.1, 0.0, 0.1, 0.03, 0.03, 0.02, 0.1])
    closures = closure_agreement(performer, character, np.zeros(7), gap=0.03, frames=2, ratio=1.2)
    assert [(c["start"], c["stop"]) for c in closures] == [(3, 6)]
    assert not closures[0]["reproduced"]  # 0.0267 > 1.2 * 0.02
    assert closure_agreement(performer, character, np.zeros(7), gap=0.03, frames=2, ratio=1.2 * 1.2)[0]["reproduced"]


def test_gaps_and_apertures_of_a_drawn_face():
    shape = np.zeros((1, 68, 2))
    shape[0, 36], shape[0, 45] = [0, 0], [100, 0]  # IOD 100
    for a, b in ((61, 67), (62, 66), (63, 65)):
        shape[0, a], shape[0, b] = [40, 50], [40, 56]
    for corner_a, corner_b, upper, lower in (
        ((36, 39), None, (37, 38), (41, 40)),
        ((42, 45), None, (43, 44), (47, 46)),
    ):
        x0 = shape[0, corner_a[0], 0] if corner_a[0] != 42 else 70
        shape[0, corner_a[0]] = [x0, 0]
        shape[0, corner_a[1]] = [x0 + 30, 0]
        for u, lo in zip(upper, lower):
            shape[0, u], shape[0, lo] = [x0 + 10, -4.5], [x0 + 10, 4.5]
    shape[0, 45] = [100, 0]
    assert lip_gap(shape)[0] == pytest.approx(0.06)
    np.testing.assert_allclose(eye_aperture(shape)[0], [9 / 30, 9 / 30])


def test_audio_envelope_is_the_frame_rms():
    # frame i is centred on sample 100 i and averages the 100 samples around it
    samples = np.r_[np.full(50, 0.5), np.full(100, 2.0), np.full(100, 1.0)]
    assert audio_envelope(samples, rate=100.0, offset=0.0, fps=1.0, frames=3) == pytest.approx([0.5, 2.0, 1.0])
    # audio starting one second after the first frame: frame 0 is silent
    late = audio_envelope(samples, rate=100.0, offset=1.0, fps=1.0, frames=3)
    assert late[0] == 0.0 and late[1] == pytest.approx(0.5) and late[2] == pytest.approx(2.0)
    # a variable frame rate: the second frame dropped, the third at 2 s, where the audio is 1.0
    dropped = audio_envelope(samples, rate=100.0, offset=0.0, fps=1.0, frames=2, times=np.array([0.0, 2.0]))
    assert dropped == pytest.approx([0.5, 1.0])


# ------------------------------------------------------------------------------------------------ the pipeline


def test_eval_pipeline_runs_on_a_folder_of_takes(tmp_path):
    """eval/retarget.yaml from a fresh copy, pointed at another folder by one variable: the capture branch."""
    import shutil
    from pathlib import Path

    import msflow

    root = Path(__file__).resolve().parents[1]
    project = tmp_path / "project"
    project.mkdir()
    for name in ("eval", "stages", "data"):
        shutil.copytree(root / name, project / name, ignore=shutil.ignore_patterns("__pycache__", ".msflow"))
    shutil.copy2(root / "pyproject.toml", project)
    takes = tmp_path / "takes"
    takes.mkdir()
    shutil.copy2(root / "data" / "crema-d" / "1001_DFA_NEU_XX.flv", takes / "neutral_take.flv")
    (takes / "notes.txt").write_text("not a video")
    result = msflow.run(project / "eval" / "retarget.yaml", ["vars.takes=../../takes"], until="capture_eval")
    view = result.artifact("capture_eval")
    assert len(view.meta["labels"]) == 1 and "neutral_take" in view.meta["labels"][0]
    m = view.metrics
    # a take retargeted onto the character follows its performer far better than the same animation out of time
    assert m["mouth_motion_error_iod"] < 0.5 * m["mouth_motion_error_iod_shifted"]
    assert m["keyshape_residual_rms_iod"] < 0.03
    assert "paper_eval" not in result.executed
    from msflow.summary import summary_lines

    # what `msflow run` ends with: every capture entry a metric it gave (paper_eval did not run: left out)
    patterns = list(result.session.pipeline.summary)
    lines, warnings = summary_lines(patterns, result.record["stages"])
    capture = [p for p in patterns if p.startswith("capture_eval.")]
    assert capture and warnings == [] and len(lines) >= len(capture)
    assert not any(line.startswith("paper_eval.") for line in lines)


def capture_project(root, project):
    """A fresh copy of the project for pipelines/capture.yaml: its code, data and pipelines, no store or locks."""
    import shutil

    project.mkdir()
    for name in ("pipelines", "stages", "data"):
        shutil.copytree(root / name, project / name, ignore=shutil.ignore_patterns("__pycache__", ".msflow", "*.lock"))
    shutil.copy2(root / "pyproject.toml", project)
    return project


def test_capture_pipeline_turns_a_clip_into_animation_files(tmp_path):
    """pipelines/capture.yaml from a fresh copy: a clip in, GLB and Live Link CSV out, with the clip's own head
    motion (the tracking as the head input) and a mouth that follows the clip."""
    import csv
    from pathlib import Path

    import msflow

    root = Path(__file__).resolve().parents[1]
    project = capture_project(root, tmp_path / "project")
    result = msflow.run(project / "pipelines" / "capture.yaml", ["vars.name=happy", "export.video_size=96"])
    from msflow.summary import summary_entries

    summary, problems = summary_entries(list(result.session.pipeline.summary), result.record["stages"])
    assert problems == [] and dict(summary)["track.valid_fraction"] == 1.0  # what `msflow run` ends with
    rows = list(csv.reader((project / "out" / "happy_live_link.csv").open()))
    frames = len(result.load("track.landmarks"))
    assert len(rows) - 1 == frames and (project / "out" / "happy.glb").read_bytes()[:4] == b"glTF"
    jaw = [float(r[rows[0].index("JawOpen")]) for r in rows[1:]]
    assert max(jaw) > 0.2 and min(jaw) < 0.05  # the mouth opens and closes
    yaw = np.array([float(r[rows[0].index("HeadYaw")]) for r in rows[1:]])
    assert np.ptp(yaw) > 0  # the tracked head moves
    assert result.artifact("export").meta["head"]["head_fps"] == pytest.approx(result.artifact("blend").meta["fps"])


def test_a_silent_clip_is_captured_with_a_silent_preview(tmp_path):
    """A clip without a sound track (a silent reference recording) still becomes an animation: the capture reads
    only the face, so the files come out, and the preview, with nothing to play, is silent and says so."""
    from pathlib import Path

    import av
    from tracking_media import first_frames, write_video

    import msflow

    root = Path(__file__).resolve().parents[1]
    project = capture_project(root, tmp_path / "project")
    frames = first_frames(root / "data" / "crema-d" / "1001_DFA_HAP_XX.flv", 30)
    write_video(project / "silent.mp4", frames, fps=30)  # no audio stream
    result = msflow.run(
        project / "pipelines" / "capture.yaml", ["vars.take=../silent.mp4", "vars.name=silent", "export.video_size=96"]
    )
    rows = (project / "out" / "silent_live_link.csv").read_text().splitlines()
    assert len(rows) - 1 == len(frames)
    assert any("no audio" in w and "silent" in w for w in result.warnings.get("export", []))
    with av.open(str(project / "out" / "silent_preview.mp4")) as preview:
        assert preview.streams.video and not preview.streams.audio


def test_a_face_found_after_a_long_gap_is_eased_into_not_jumped_to(tmp_path):
    """20 black frames (longer than the tracker's max_gap_frames, 15: the face is held through them) before the
    face comes back smiling. With the default ease the last quarter second of the gap moves into the found face;
    with 0 the smile and the head jump in one frame. The frames before the ease and the found face itself are the
    same either way."""
    import csv
    from pathlib import Path

    from tracking_media import first_frames, write_video

    import msflow

    root = Path(__file__).resolve().parents[1]
    project = capture_project(root, tmp_path / "project")
    frames = first_frames(root / "data" / "crema-d" / "1001_DFA_HAP_XX.flv", 50)
    frames[15:35] = [frame * 0 for frame in frames[15:35]]  # the face is found again at frame 35
    write_video(project / "gap.mp4", frames, fps=30)

    def columns(ease: str, name: str) -> dict[str, np.ndarray]:
        overrides = [f"blend.held_gap_ease={ease}", f"export.held_gap_ease={ease}", "export.video_size=96"]
        msflow.run(project / "pipelines" / "capture.yaml", ["vars.take=../gap.mp4", f"vars.name={name}", *overrides])
        rows = list(csv.reader((project / "out" / f"{name}_live_link.csv").open()))
        return {c: np.array([float(r[rows[0].index(c)]) for r in rows[1:]]) for c in ("MouthSmileLeft", "HeadPitch")}

    jumped, eased = columns("0", "jumped"), columns("0.25", "eased")
    smile = jumped["MouthSmileLeft"]
    assert smile[35] - smile[34] > 0.3 and np.all(smile[15:35] == smile[14])  # held, then the pop
    for column in ("MouthSmileLeft", "HeadPitch"):
        jump = abs(jumped[column][35] - jumped[column][34])
        assert np.abs(np.diff(eased[column][25:36])).max() < 0.4 * jump, column  # up to the found face
    np.testing.assert_allclose(eased["MouthSmileLeft"][:27], smile[:27], atol=1e-6)  # before the last 0.25 s
    np.testing.assert_allclose(eased["MouthSmileLeft"][35:], smile[35:], atol=1e-6)


def test_columns_follow_the_movements_they_name(character, truth):
    """The character's own animation follows every movement the performer made (the probes measure what the
    morphs did: jaw r 1.0, blinks 0.98); the same animation half a take late does not (median -0.04)."""
    weights, tracks, out = truth
    following = out.meta["takes"]["take"]["following"]
    assert {"JawOpen", "EyeBlinkLeft"} <= set(following)
    assert following["JawOpen"][0] > 0.9 and following["EyeBlinkLeft"][0] > 0.8
    assert out.metrics["following_r_median"] > 0.8 and out.metrics["following_weak"] == 0.0
    assert out.metrics["following_r_median_shifted"] < 0.5
    late = evaluate(character, tracks, np.roll(weights, FRAMES // 2, axis=0))
    assert late.metrics["following_r_median"] < 0.5 and late.metrics["following_weak"] > 0.5


def test_the_ceiling_fit_recovers_the_characters_own_weights_in_the_head_frame(character, monkeypatch):
    """bench/retarget_ceiling.py's frame-by-frame fit (the basis's ceiling) on a performer who is the character
    (its cheek points too: vertices of the character's cheeks), seen without perspective. With the morphs as the
    head frame sees them, every frame's jaw and funnel come back as animated and no other morph
    moves. With the deltas as they are (the keymorph fit's model) the jaw comes back short: it lowers the
    nostrils, rigid points, and the head frame takes part of that out of the performer's face but not out of the
    morph. (No blink: the eye corners it moves are rigid points too.)"""
    from conftest import ROOT

    monkeypatch.syspath_prepend(str(ROOT / "bench"))
    from retarget_ceiling import take_frame_fit

    from stages.retarget.movements import EXTRA_VERTICES
    from stages.retarget.shapes3d import head_frame_shapes

    names = character.meta["target_names"]
    weights = known_weights(names)
    weights[:, [names.index("eyeBlink_L"), names.index("eyeBlink_R")]] = 0.0
    data = {k: np.asarray(character[k]) for k in ("neutral", "deltas", "landmark_ids")} | {"names": names}
    rest = data["neutral"][data["landmark_ids"]]
    # each side's cheek points: vertices between the lower lid, the nostril, the lip corner and the jaw line
    between = [(41, 48), (40, 48), (40, 31), (48, 4), (48, 3), (31, 2), (46, 54), (47, 54), (47, 35), (54, 12)]
    between += [(54, 13), (35, 14)]
    assert len(between) == len(EXTRA_VERTICES)
    cheeks = [int(np.argmin(((data["neutral"] - (rest[a] + rest[b]) / 2) ** 2).sum(1))) for a, b in between]
    ids = np.concatenate([data["landmark_ids"], cheeks])
    points = align_to_model(rest, load_face3d().neutral).apply(
        character_landmarks(data["neutral"], data["deltas"], ids, weights)
    )
    mesh = facemesh_of(points, *head_motion(), orthographic=True)
    rest_shape = head_frame_shapes(mesh, EXTRA_VERTICES)[40:48].mean(axis=0)  # frames 40-47: every weight 0
    usable = np.array([not n.lower().startswith("eyelook") for n in names])
    moving = [names.index(n) for n in ("jawOpen", "mouthFunnel")]
    still = [i for i in range(len(names)) if i not in moving]

    fitted = take_frame_fit(data, mesh, rest_shape, usable, head_frame=True)
    np.testing.assert_allclose(fitted[:, moving], weights[:, moving], atol=0.02)
    assert np.abs(fitted[:, still]).max() < 0.025  # the head frame's share, to first order

    as_they_are = take_frame_fit(data, mesh, rest_shape, usable)
    jaw = names.index("jawOpen")
    widest = weights[:, jaw] > 0.5
    assert np.all(as_they_are[widest, jaw] < weights[widest, jaw] - 0.005)
