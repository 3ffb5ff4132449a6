"""Eyes from the 478-point landmark model: aperture and gaze conventions on synthetic faces with known answers
(eyes placed, turned and blinked by construction, then the whole head turned), and on real footage (the CREMA-D
sad take's blink at frames 6-8, which eye is the performer's left, mirror symmetry)."""

import numpy as np
import pytest
from tracking_media import CLIPS, write_video

from msflow.testing import run_stage
from stages.geometry.rotations import euler_to_quat, quat_to_matrix
from stages.tracking import FaceMesh
from stages.tracking.eyes import (
    CHIN,
    EYE_CORNERS,
    EYEBALL_RADIUS,
    FOREHEAD,
    IRIS_CENTRE,
    LID_PAIRS,
    detect_blinks,
    eye_aperture,
    eye_offsets,
    gaze_angles,
    rest_offsets,
)
from stages.tracking.video import read_frames

WIDTH = 30.0  # eye width, pixels


def synthetic_face(yaw=(0.0, 0.0), pitch=(0.0, 0.0), aperture=(0.3, 0.3), head=(0.0, 0.0, 0.0)):
    """(478, 3) points in the model's image convention (x right, y down, z smaller towards the camera) of a face
    whose eyes look (yaw, pitch) degrees per eye [left, right] with lid gaps ``aperture`` x eye width, the head
    turned by ``head`` = (yaw, pitch, roll) degrees. Head frame: x the performer's left, y up, z out of the face;
    only the points the eye measures use are placed."""
    p = np.zeros((478, 3))
    for eye, centre_x in ((0, 1.5 * WIDTH), (1, -1.5 * WIDTH)):
        mid = np.array([centre_x, 0.0, 0.0])
        outer, inner, right_side, left_side = EYE_CORNERS[eye]
        p[left_side], p[right_side] = mid + [WIDTH / 2, 0, 0], mid - [WIDTH / 2, 0, 0]
        gap = aperture[eye] * WIDTH
        for k, (up, low) in enumerate(LID_PAIRS[eye]):
            x = (k - 1) * WIDTH / 4
            p[up], p[low] = mid + [x, gap / 2, 0], mid + [x, -gap / 2, 0]
        rest = rest_offsets()[eye] * WIDTH
        radius = EYEBALL_RADIUS * WIDTH
        centre = mid + [rest[0], rest[1], -radius]
        y, t = np.radians(yaw[eye]), np.radians(pitch[eye])
        p[IRIS_CENTRE[eye]] = centre + radius * np.array([np.sin(y) * np.cos(t), np.sin(t), np.cos(y) * np.cos(t)])
    p[FOREHEAD], p[CHIN] = [0, 3 * WIDTH, 0], [0, -5 * WIDTH, 0]
    r = quat_to_matrix(euler_to_quat(*np.radians(np.array(head, dtype=float))))
    p = p @ r.T
    return p * np.array([1.0, -1.0, -1.0]) + np.array([320.0, 240.0, 0.0])  # head frame -> image axes


def test_gaze_angles_are_recovered_whatever_the_head_does():
    for head in ((0, 0, 0), (25, -10, 8), (-30, 15, -5)):
        face = synthetic_face(yaw=(12.0, -20.0), pitch=(5.0, -8.0), head=head)
        gaze = gaze_angles(face[None])[0]
        np.testing.assert_allclose(gaze, [[12.0, 5.0], [-20.0, -8.0]], atol=1e-3)
    straight = gaze_angles(synthetic_face()[None])[0]
    np.testing.assert_allclose(straight, 0.0, atol=1e-4)


def test_gaze_signs_follow_the_performers_left_and_up():
    """A face seen from the front: eyes turned to the performer's left move the irises to the image's right."""
    face = synthetic_face(yaw=(15.0, 15.0))
    rest = synthetic_face()
    assert (face[[IRIS_CENTRE[0], IRIS_CENTRE[1]], 0] > rest[[IRIS_CENTRE[0], IRIS_CENTRE[1]], 0]).all()
    assert (gaze_angles(face[None])[0, :, 0] > 14).all()
    up = synthetic_face(pitch=(10.0, 10.0))
    assert (up[[IRIS_CENTRE[0], IRIS_CENTRE[1]], 1] < rest[[IRIS_CENTRE[0], IRIS_CENTRE[1]], 1]).all()  # image y down
    assert (gaze_angles(up[None])[0, :, 1] > 9).all()
    assert face[EYE_CORNERS[0][0], 0] > face[EYE_CORNERS[1][0], 0]  # eye 0 (left) is on the image's right


def test_aperture_and_a_synthetic_blink():
    open_levels = np.array([0.30, 0.31, 0.29, 0.30, 0.30, 0.31, 0.30, 0.29, 0.30, 0.30, 0.31, 0.30])
    levels = open_levels.copy()
    levels[[4, 5, 6]] = [0.14, 0.04, 0.12]  # a blink: closing, shut, opening
    for head in ((20, 0, 0), (0, 0, 10)):  # turning or tilting the head does not change the aperture
        faces = np.stack([synthetic_face(aperture=(a, a), head=head) for a in levels])
        aperture = eye_aperture(faces)
        np.testing.assert_allclose(aperture, np.stack([levels, levels], 1), atol=1e-6)
    assert detect_blinks(aperture) == [(4, 7)]
    assert detect_blinks(np.stack([open_levels, open_levels], 1)) == []
    valid = np.ones(len(levels), bool)
    valid[[4, 5, 6]] = False  # frames without a face never make a blink
    assert detect_blinks(aperture, valid) == []
    one_eye = np.stack([levels, open_levels], 1)  # a wink halves the mean: still below half the open level
    assert detect_blinks(one_eye, closed_fraction=0.6) == [(5, 6)]


@pytest.fixture(scope="module")
def sad(tmp_path_factory):
    """FaceMesh with Face Landmarker v2 as the landmark model on the sad take and on its mirror image."""
    times, frames = read_frames(CLIPS["SAD"])
    mirrored = write_video(tmp_path_factory.mktemp("mirror") / "mirror.mp4", [f[:, ::-1].copy() for f in frames])
    params = {"audio": "none", "model": "face_landmarker_v2"}
    return run_stage(FaceMesh, params, {"videos": {"sad": CLIPS["SAD"]}}), run_stage(
        FaceMesh, params, {"videos": {"mirror": mirrored}}
    )


@pytest.fixture(scope="module")
def sad_default():
    """FaceMesh as configured by default: face_mesh_v1 landmarks, eyes from a Face Landmarker v2 pass."""
    return run_stage(FaceMesh, {"audio": "none", "output_mesh": False}, {"videos": {"sad": CLIPS["SAD"]}})


@pytest.mark.parametrize("which", ["default", "v2"])
def test_the_sad_takes_blink_is_found(sad, sad_default, which):
    """By eye: the actor's eyes close over frames 6-7 and open at 8 (and are open everywhere else)."""
    run = sad_default if which == "default" else sad[0]
    aperture = run.arrays["eye_aperture"]
    assert detect_blinks(aperture, run.arrays["valid"]) == [(6, 9)]
    assert (aperture[6:8].mean(axis=1) < 0.1).all()  # closed
    others = np.r_[0:5, 10 : len(aperture)]
    assert (aperture[others] > 0.2).all() and (aperture[others] < 0.4).all()
    assert run.arrays["gaze"].shape == (len(aperture), 2, 2) and run.arrays["iris"].shape == (len(aperture), 10, 3)


def test_no_eye_outputs_when_asked():
    out = run_stage(FaceMesh, {"audio": "none", "eyes": False}, {"videos": {"neu": CLIPS["NEU"]}})
    assert not {"eye_aperture", "gaze", "iris"} & set(out.arrays) and out.arrays["mesh"].shape[1] == 468


def test_eye_indices_and_mirror_symmetry_on_real_footage(sad):
    """Mirroring the picture swaps the eyes and the sign of e_x (where the iris sits between the corners, towards
    the performer's left)."""
    out, mirror = sad
    iris = out.arrays["iris"]
    assert (iris[:, 5, 0] > iris[:, 0, 0]).all()  # iris points 5-9 (left eye) on the image's right
    aperture = mirror.arrays["eye_aperture"][:, ::-1]
    assert np.abs(aperture - out.arrays["eye_aperture"]).mean() < 0.015

    def offsets(run):
        return eye_offsets(np.concatenate([run.arrays["mesh"], run.arrays["iris"]], axis=1))

    e, flipped = offsets(out), offsets(mirror)[:, ::-1] * np.array([-1.0, 1.0])
    assert np.abs(np.median(e[:, :, 0], axis=0)).min() > 0.03  # the irises sit off the corners' midpoints...
    # ...mirrored with the picture: the model places the two irises a little differently (up to 0.025 eye widths,
    # 3 degrees); a wrong eye index or sign would be off by twice the offsets, about 0.13
    assert np.abs(flipped - e).mean(axis=0).max() < 0.04
    gaze = out.arrays["gaze"]
    assert np.abs(np.median(gaze, axis=0)).max() < 10  # the actor looks about at the camera
