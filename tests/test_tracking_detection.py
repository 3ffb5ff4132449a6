"""Detection beyond a close-up: faces too small for the detector's whole-frame pass (a medium or wide shot), found
by its tile search (stages/tracking/blazeface.py), and a face lost for a moment in a shot with two, found again
where it was (stages/tracking/facemesh.py)."""

from pathlib import Path

import numpy as np
import pytest
from tracking_media import CLIPS, first_frames, write_video

from msflow.testing import run_stage
from stages.tracking import FaceMesh
from stages.tracking.blazeface import INPUT_SIZE, BlazeFaceDetector, tile_transforms

MODEL = Path(__file__).resolve().parents[1] / "data" / "models" / "mediapipe-face" / "face_detection_short_range.tflite"


def tile_rects(width, height):
    """(x0, y0, side) of each tile."""
    return [(-t[0, 2] / t[0, 0], -t[1, 2] / t[1, 1], INPUT_SIZE / t[0, 0]) for t in tile_transforms(width, height)]


@pytest.mark.parametrize("width,height", [(1280, 720), (720, 1280), (640, 480), (300, 200)])
def test_every_face_up_to_half_a_tile_lies_whole_in_a_tile(width, height):
    rects = tile_rects(width, height)
    sides = sorted({round(side, 6) for _, _, side in rects})
    rng = np.random.default_rng(0)
    for side in sides:
        face = side / 2
        for x, y in rng.uniform([0, 0], [width - face, height - face], size=(200, 2)):
            assert any(
                x0 - 1e-6 <= x and x + face <= x0 + s + 1e-6 and y0 - 1e-6 <= y and y + face <= y0 + s + 1e-6
                for x0, y0, s in rects
                if round(s, 6) == side
            )
    for x0, y0, side in rects:  # inside the frame
        assert x0 >= 0 and y0 >= 0 and x0 + side <= width + 1e-6 and y0 + side <= height + 1e-6


@pytest.fixture(scope="module")
def take():
    return first_frames(CLIPS["HAP"], 12)


def in_wide_shot(frames, scale, at=(700, 400), size=(720, 1280)):
    import cv2

    out = []
    for frame in frames:
        canvas = np.full((*size, 3), 90, np.uint8)
        small = cv2.resize(frame, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        canvas[at[1] : at[1] + small.shape[0], at[0] : at[0] + small.shape[1]] = small
        out.append(canvas)
    return out


def test_a_face_a_tenth_of_the_frame_is_found_by_the_tile_search(take):
    detector = BlazeFaceDetector(MODEL)
    wide = in_wide_shot(take[:1], 0.3)[0]
    assert len(detector.detect(wide)) == 0  # the whole frame at the model's 128 px: the face is 6 px wide
    found = detector.detect(wide, tiles=True)
    assert len(found) == 1
    full = detector.detect(take[0])
    expected = np.asarray(full.boxes[0]) * 0.3 + [700, 400, 700, 400]
    assert np.abs(found.boxes[0] - expected).max() < 0.1 * (expected[2] - expected[0])


def test_a_medium_and_a_wide_shot_track_as_the_close_up(tmp_path, take):
    """The happy take at 0.5 and 0.3 of its size in a 1280 x 720 frame (a face a tenth and a sixteenth of its
    height): every frame tracked, the landmarks (scaled back) near the close-up's; before the tile search, no face
    was found in any frame."""
    videos = {"close": write_video(tmp_path / "close.mp4", take)}
    for name, scale in {"medium": 0.5, "wide": 0.3}.items():
        videos[name] = write_video(tmp_path / f"{name}.mp4", in_wide_shot(take, scale))
    run = run_stage(FaceMesh, {"audio": "none"}, {"videos": videos}, store=tmp_path / "store")
    labels, sequence = run.meta["labels"], run.arrays["sequence"]
    rows = {name: sequence == labels.index(name) for name in videos}
    assert run.arrays["valid"].all()
    close = run.arrays["landmarks"][rows["close"]]
    iod = np.linalg.norm(close[:, 45] - close[:, 36], axis=-1).mean()
    for name, scale, tolerance in (("medium", 0.5, 0.03), ("wide", 0.3, 0.06)):
        back = (run.arrays["landmarks"][rows[name]] - [700, 400]) / scale
        assert np.median(np.linalg.norm(back - close, axis=-1)) < tolerance * iod, name


def two_performers(take, blank=(), right_scale=1.0):
    """The happy take on the left and the angry one on the right of a 1000 x 400 picture (the right one scaled by
    ``right_scale``), the frames in ``blank`` empty."""
    import cv2

    other = first_frames(CLIPS["ANG"], len(take))
    frames = []
    for i, (left, right) in enumerate(zip(take, other)):
        canvas = np.full((400, 1000, 3), 90, np.uint8)
        if i not in blank:
            right = cv2.resize(right, None, fx=right_scale, fy=right_scale, interpolation=cv2.INTER_AREA)
            canvas[20:380, 20:500] = left
            canvas[20 : 20 + right.shape[0], 500 : 500 + right.shape[1]] = right
        frames.append(canvas)
    return frames


def test_the_face_param_picks_the_performer_among_several(tmp_path, take):
    """face: leftmost / rightmost / largest track the performer named from the first frame on (the right one
    at 0.6 of the left's size)."""
    path = write_video(tmp_path / "two.mp4", two_performers(take[:6], right_scale=0.6))
    for face, side in (("leftmost", "left"), ("rightmost", "right"), ("largest", "left")):
        run = run_stage(FaceMesh, {"audio": "none", "face": face}, {"videos": {"two": path}})
        nose = run.arrays["landmarks"][:, 30, 0]
        assert run.arrays["valid"].all() and ((nose < 500) if side == "left" else (nose > 500)).all(), face
    with pytest.raises(ValueError, match="face"):
        FaceMesh.Params(face="nearest")


def test_a_face_lost_for_a_moment_is_found_again_where_it_was(tmp_path, take):
    """Two performers side by side (the happy and the angry take), the picture blank for 5 frames: the tracker
    follows the face it started with and finds it on the frame it comes back. Before, it re-detected the more
    certain face, the other performer, and found nothing for 10 frames (the tile search waited its turn)."""
    frames = two_performers(take, blank=range(5, 8))
    run = run_stage(FaceMesh, {"audio": "none"}, {"videos": {"two": write_video(tmp_path / "two.mp4", frames)}})
    valid, nose = run.arrays["valid"], run.arrays["landmarks"][:, 30, 0]
    assert valid[:5].all() and not valid[5:8].any() and valid[8:].all()
    assert np.abs(nose[8:] - nose[:5].mean()).max() < 30  # the same performer (the faces' noses are 480 px apart)


def test_of_several_faces_the_one_nearest_where_the_performer_was_is_followed():
    """Known answer: two detections, the more certain one far from the face last seen: the near one is followed;
    with no face seen yet in the take, the most certain."""
    from stages.tracking.blazeface import Detections
    from stages.tracking.facemesh import FaceMeshTracker, Roi

    models = MODEL.parent
    tracker = FaceMeshTracker(MODEL, models / "face_landmark.tflite")
    far, near = [600.0, 100.0, 700.0, 200.0], [90.0, 110.0, 150.0, 170.0]
    found = Detections(np.array([0.95, 0.7]), np.array([far, near]), np.zeros((2, 6, 2)))
    assert tracker.follow(found) == 0
    tracker.last_seen = Roi(115.0, 135.0, 90.0, 0.0)
    assert tracker.follow(found) == 1
    tracker.reset()
    assert tracker.follow(found) == 0
    for first, expected in (("largest", 0), ("leftmost", 1), ("rightmost", 0)):
        tracker.first_face = first
        assert tracker.follow(found) == expected, first
    wide = Detections(np.array([0.9, 0.8]), np.array([near, [300.0, 50.0, 500.0, 250.0]]), np.zeros((2, 6, 2)))
    tracker.first_face = "largest"
    assert tracker.follow(wide) == 1
