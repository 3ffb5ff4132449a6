"""The iris-model eye pass (stages/tracking/iris.py): crop geometry with known answers (where the corners land,
the crop map and its inverse, the half-pixel convention, the mirrored eye mapping back), the 478-point layout
it fills, and on real footage the CREMA-D sad take's blink (closed at frames 6-7, by eye) and mirror symmetry."""

import numpy as np
import pytest
from pydantic import ValidationError
from tracking_media import CLIPS, write_video

from msflow.testing import run_stage
from stages.tracking import FaceMesh
from stages.tracking.eyes import LID_PAIRS, REST_OFFSETS, angles_to_offsets, detect_blinks, offsets_to_angles
from stages.tracking.iris import (
    CONTOUR_TO_MESH,
    EYE_BOUNDARY,
    EYE_ROI_SCALE,
    IRIS_INPUT,
    IRIS_START,
    MIRRORED_IRIS_ORDER,
    crop_to_image,
    eye_crop_maps,
    image_to_crop,
    refined_points,
)
from stages.tracking.planes import BgrImage
from stages.tracking.stages import DEFAULT_EYES, FaceMeshParams
from stages.tracking.video import read_frames

HALF = IRIS_INPUT / 2
MIRROR_OF = {33: 263, 133: 362, 263: 33, 362: 133}  # the mesh's left/right eye corners


def face_corners(roll_degrees: float = 0.0, width: float = 30.0, centre=(320.0, 240.0)) -> np.ndarray:
    """(468, 3) mesh points with only the four eye corners placed (a frontal face rolled by ``roll_degrees``)."""
    p = np.zeros((468, 3))
    local = {33: (-2.0, 0.0), 133: (-1.0, 0.0), 362: (1.0, 0.0), 263: (2.0, 0.0)}  # in eye widths, x to the right
    c, s = np.cos(np.radians(roll_degrees)), np.sin(np.radians(roll_degrees))
    for vertex, (x, y) in local.items():
        p[vertex, :2] = np.array(centre) + width * np.array([c * x - s * y, s * x + c * y])
    return p


def to_crop(points_xy: np.ndarray, maps: np.ndarray) -> np.ndarray:
    """Image points to continuous crop coordinates (the inverse of ``crop_to_image``)."""
    inverse = image_to_crop(maps)  # crop pixel index = continuous - 0.5
    return points_xy @ inverse[:, :2].T + inverse[:, 2] + 0.5


@pytest.mark.parametrize("roll", [0.0, 17.0, -40.0])
def test_corners_land_level_with_the_outer_corner_on_the_left_for_both_eyes(roll):
    """Each crop is 2.3 corner distances wide, centred on the corners, rotated level; the left eye's crop is
    mirrored so its outer corner (263) lands on the crop's left like the right eye's (33)."""
    points = face_corners(roll)
    maps = eye_crop_maps(points)
    offset = HALF / EYE_ROI_SCALE  # half a corner distance, in crop pixels
    for eye, (outer, inner) in enumerate(((263, 362), (33, 133))):
        crop = to_crop(points[[outer, inner], :2], maps[eye])
        np.testing.assert_allclose(crop, [[HALF - offset, HALF], [HALF + offset, HALF]], atol=1e-9)
    assert np.linalg.det(maps[0, :, :2]) < 0 < np.linalg.det(maps[1, :, :2])  # eye 0 mirrored


def test_crop_map_and_its_inverse_round_trip():
    rng = np.random.default_rng(3)
    points = face_corners(23.0, width=41.0)
    maps = eye_crop_maps(np.stack([points, face_corners(-5.0)]))  # vectorised over frames
    assert maps.shape == (2, 2, 2, 3)
    local = rng.uniform(0, IRIS_INPUT, size=(2, 2, 7, 3))
    image = crop_to_image(local, maps)
    for f in range(2):
        for eye in range(2):
            np.testing.assert_allclose(to_crop(image[f, eye, :, :2], maps[f, eye]), local[f, eye, :, :2], atol=1e-9)
    # depth scales like a length: crop pixels are side / 64 image pixels
    side = EYE_ROI_SCALE * 41.0
    np.testing.assert_allclose(image[0, :, :, 2], local[0, :, :, 2] * side / IRIS_INPUT, rtol=1e-12)


def blob_image(centre, shape=(480, 640), sigma=2.0) -> np.ndarray:
    y, x = np.mgrid[: shape[0], : shape[1]]
    g = np.exp(-((x - centre[0]) ** 2 + (y - centre[1]) ** 2) / (2 * sigma**2))
    return np.repeat((255 * g).round().astype(np.uint8)[..., None], 3, axis=2)


@pytest.mark.parametrize("eye", [0, 1])
def test_a_point_drawn_in_the_image_is_where_the_map_says_in_the_crop(eye):
    """The warp samples crop pixel i at map(i + 0.5): a bright dot at image pixel p shows up (intensity
    centroid, in continuous crop coordinates) where the inverse map puts p, mirrored or not."""
    points = face_corners(12.0)
    maps = eye_crop_maps(points)
    p = points[EYE_BOUNDARY[eye][0], :2] * 0.3 + points[EYE_BOUNDARY[eye][1], :2] * 0.7 + [0.3, -4.6]
    patch = BgrImage(blob_image(p)).warp_bgr(image_to_crop(maps[eye]), IRIS_INPUT)[..., 0].astype(np.float64)
    y, x = np.mgrid[:IRIS_INPUT, :IRIS_INPUT] + 0.5
    centroid = np.array([(patch * x).sum(), (patch * y).sum()]) / patch.sum()
    np.testing.assert_allclose(centroid, to_crop(p[None], maps[eye])[0], atol=0.05)


def test_the_mirrored_left_eye_crop_is_the_right_eye_crop_of_the_mirrored_picture():
    """Mirror the picture (and the mesh corners with it): the left eye's crop of one is the right eye's crop of
    the other, pixel for pixel up to interpolation, so both eyes reach the model the same way."""
    rng = np.random.default_rng(7)
    import cv2

    image = cv2.GaussianBlur(rng.integers(0, 256, (480, 640, 3)).astype(np.uint8), (0, 0), 2.0)
    mirrored = image[:, ::-1].copy()
    points = face_corners(9.0, centre=(300.0, 250.0))
    flipped = np.zeros_like(points)
    for vertex, twin in MIRROR_OF.items():
        flipped[twin] = points[vertex] * [-1.0, 1.0, 1.0] + [640 - 1, 0.0, 0.0]  # pixel index x -> W - 1 - x
    a, b = eye_crop_maps(points), eye_crop_maps(flipped)
    left = BgrImage(image).warp_bgr(image_to_crop(a[0]), IRIS_INPUT).astype(int)
    right_of_mirror = BgrImage(mirrored).warp_bgr(image_to_crop(b[1]), IRIS_INPUT).astype(int)
    assert np.abs(left - right_of_mirror).max() <= 1


def test_refined_points_put_the_lids_and_irises_where_v2_has_them():
    rng = np.random.default_rng(1)
    mesh = rng.normal(size=(468, 3))
    contours, irises = rng.normal(size=(2, 71, 3)), rng.normal(size=(2, 5, 3))
    out = refined_points(mesh, contours, irises)
    assert out.shape == (478, 3)
    for eye, vertices in enumerate(CONTOUR_TO_MESH):
        np.testing.assert_array_equal(out[list(vertices), :2], contours[eye, :16, :2])
        np.testing.assert_array_equal(out[list(vertices), 2], mesh[list(vertices), 2])  # lids keep the depth
        order = list(MIRRORED_IRIS_ORDER) if eye == 0 else list(range(5))
        np.testing.assert_array_equal(out[IRIS_START[eye] : IRIS_START[eye] + 5, :2], irises[eye, order, :2])
        np.testing.assert_allclose(out[IRIS_START[eye] : IRIS_START[eye] + 5, 2], mesh[list(vertices), 2].mean())
    untouched = np.setdiff1d(np.arange(468), np.concatenate(CONTOUR_TO_MESH))
    np.testing.assert_array_equal(out[untouched], mesh[untouched])
    # the aperture's lid pairs and corners are all among the refined vertices
    used = {v for eye in (0, 1) for pair in LID_PAIRS[eye] for v in pair} | set(MIRROR_OF)
    assert used <= set(np.concatenate(CONTOUR_TO_MESH).tolist())


def test_angles_to_offsets_inverts_offsets_to_angles():
    angles = np.array([[[12.0, 5.0], [-20.0, -8.0]], [[0.0, 0.0], [35.0, 25.0]]])
    for rest in REST_OFFSETS.values():
        np.testing.assert_allclose(
            offsets_to_angles(angles_to_offsets(angles, rest=rest), rest=rest), angles, atol=1e-9
        )


def test_the_eyes_param():
    assert FaceMeshParams(eyes=True).eyes == DEFAULT_EYES
    assert FaceMeshParams(eyes=False).eyes is False
    assert FaceMeshParams(eyes="iris").eyes == "iris"
    with pytest.raises(ValidationError):
        FaceMeshParams(eyes="irises")


@pytest.fixture(scope="module")
def sad_iris(tmp_path_factory):
    """FaceMesh with the iris eye pass on the sad take and on its mirror image."""
    times, frames = read_frames(CLIPS["SAD"])
    mirrored = write_video(tmp_path_factory.mktemp("mirror") / "mirror.mp4", [f[:, ::-1].copy() for f in frames])
    params = {"audio": "none", "eyes": "iris"}
    return run_stage(FaceMesh, params, {"videos": {"sad": CLIPS["SAD"]}}), run_stage(
        FaceMesh, params, {"videos": {"mirror": mirrored}}
    )


def test_the_sad_takes_blink_with_the_iris_pass(sad_iris):
    """By eye: the actor's eyes close over frames 6-7 and open at 8 (and are open everywhere else)."""
    run = sad_iris[0]
    assert run.meta["eye_model"] == "iris"
    aperture = run.arrays["eye_aperture"]
    (start, stop), *others = detect_blinks(aperture, run.arrays["valid"])
    assert not others and start == 6 and stop in (8, 9)
    opened = np.median(aperture.mean(axis=1))
    assert (aperture[6:8].mean(axis=1) < 0.6 * opened).all() and 0.2 < opened < 0.4
    rest = np.r_[0:5, 10 : len(aperture)]
    assert (aperture[rest].mean(axis=1) > 0.7 * opened).all()
    assert run.arrays["gaze"].shape == (len(aperture), 2, 2) and run.arrays["iris"].shape == (len(aperture), 10, 3)


def test_the_iris_pass_is_mirror_symmetric_on_real_footage(sad_iris):
    """Mirroring the picture swaps the eyes and the sign of the gaze's yaw; the irises stay in their eyes."""
    out, mirror = sad_iris
    iris = out.arrays["iris"]
    assert (iris[:, 5, 0] > iris[:, 0, 0]).all()  # iris points 5-9 (left eye) on the image's right
    for eye, start in enumerate(IRIS_START):  # each iris centre between its eye's corners
        k = 5 * (start == 473)
        corners = out.arrays["mesh"][:, list(EYE_BOUNDARY[eye]), 0]
        assert ((iris[:, k, 0] > corners.min(axis=1)) & (iris[:, k, 0] < corners.max(axis=1))).all()
    assert np.abs(mirror.arrays["eye_aperture"][:, ::-1] - out.arrays["eye_aperture"]).mean() < 0.015
    # the iris centre's offsets from the corners' midpoint (the gaze before the rest position is taken off)
    e = angles_to_offsets(out.arrays["gaze"], rest=REST_OFFSETS["iris"])
    flipped = angles_to_offsets(mirror.arrays["gaze"], rest=REST_OFFSETS["iris"])[:, ::-1] * np.array([-1.0, 1.0])
    assert np.abs(np.median(e[:, :, 0], axis=0)).min() > 0.03  # the irises sit off the corners' midpoints...
    # ...mirrored with the picture, up to how differently the model sees the two eyes (0.02 eye widths, 3 degrees,
    # on this take); a wrong eye index or sign would be off by twice the offsets, about 0.13
    assert np.abs(flipped - e).mean(axis=0).max() < 0.04
    assert np.abs(np.median(out.arrays["gaze"], axis=0)).max() < 10  # the actor looks about at the camera
