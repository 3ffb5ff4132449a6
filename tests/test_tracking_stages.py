"""The tracking stages on the six real CREMA-D clips (FaceMesh run once per module, round-tripped through zarr)
and on synthetic videos made from them (blanked frames, no audio, truncated files)."""

import numpy as np
import pytest
from tracking_media import CLIPS, write_video

from msflow import UserError
from msflow.testing import run_stage
from stages.geometry.rotations import quat_to_euler
from stages.geometry.similarity import fit_similarity
from stages.tracking import FaceMesh, OpticalFlow, TrackFile
from stages.tracking.assemble import inter_ocular, rotation_steps_deg
from stages.tracking.crops import eye_centres
from stages.tracking.figures import FIGURES, contact_sheet_png
from stages.tracking.landmarks68 import IBUG68_MIRROR
from stages.tracking.trackfile import format_pts, write_openface_csv
from stages.tracking.video import iter_planes, read_frames


@pytest.fixture(scope="module")
def facemesh(tmp_path_factory):
    return run_stage(FaceMesh, {}, {"videos": CLIPS}, store=tmp_path_factory.mktemp("facemesh"))


@pytest.fixture(scope="module")
def flow():
    return run_stage(OpticalFlow, {}, {"videos": CLIPS})


@pytest.fixture(scope="module")
def neutral_frames():
    return read_frames(CLIPS["NEU"])


def rows_of(run, label):
    return np.flatnonzero(run.arrays["sequence"] == run.meta["labels"].index(label))


# ---------------------------------------------------------------- FaceMesh on CREMA-D


def test_every_frame_of_every_clip_has_a_face(facemesh):
    arrays, meta = facemesh.arrays, facemesh.meta
    assert meta["labels"] == list(CLIPS)
    assert meta["sources"] == [p.name for p in CLIPS.values()]
    counts = [len(read_frames(p)[0]) for p in CLIPS.values()]
    assert meta["frames"] == counts
    assert arrays["valid"].all() and len(arrays["valid"]) == sum(counts)
    assert (arrays["confidence"] > 0.5).all()
    assert meta["detector_runs"] == [1] * 6  # tracking mode: detected once, followed from then on
    assert facemesh.metrics["valid_fraction"] == 1.0


def test_outputs_follow_the_schema(facemesh):
    a, meta = facemesh.arrays, facemesh.meta
    n = len(a["valid"])
    assert a["landmarks"].shape == (n, 68, 2) and a["landmarks"].dtype == np.float32
    assert a["mesh"].shape == (n, 468, 3)
    assert a["crops"].shape == (n, 128, 128) and a["crops"].dtype == np.uint8
    assert a["rotation"].shape == (n, 4) and a["translation"].shape == (n, 3)
    np.testing.assert_allclose(np.linalg.norm(a["rotation"], axis=1), 1.0, atol=1e-9)
    assert meta["landmark_scheme"] == "ibug68" and meta["translation_units"] == "cm"
    assert meta["fields"] == {label: {} for label in CLIPS}  # plain labels: no fields
    assert meta["audio_sources"] == [p.name for p in CLIPS.values()]
    assert meta["frame_size"] == [[480, 360]] * 6
    # estimated per take (test_tracking_pose.py has the known answer), at most 4x the frame width
    assert len(meta["focal_length"]) == 6 and all(0 < f <= 4 * 480 for f in meta["focal_length"])
    for s in range(6):
        t = a["time"][a["sequence"] == s]
        assert t[0] == 0.0
        np.testing.assert_allclose(np.diff(t), 1 / meta["fps"][s], atol=0.002)
    # the 68 points lie inside the frame, the face box inside a plausible region
    assert (a["landmarks"] > 0).all() and (a["landmarks"][..., 0] < 480).all()
    assert (a["landmarks"][..., 1] < 360).all()


def test_nose_bridge_jitter_is_sub_pixel(facemesh):
    for label in CLIPS:
        lm = facemesh.arrays["landmarks"][rows_of(facemesh, label)]
        steps = np.linalg.norm(np.diff(lm[:, 27], axis=0), axis=1)
        iod = inter_ocular(lm).mean()
        assert steps.mean() < 0.02 * iod, label
        second = np.linalg.norm(lm[2:, 27] - 2 * lm[1:-1, 27] + lm[:-2, 27], axis=1) / 2
        assert second.mean() < 0.5, label
    assert facemesh.metrics["nose_jitter_px"] < 0.5


def test_head_pose_is_plausible_and_smooth(facemesh):
    a = facemesh.arrays
    euler = np.degrees(quat_to_euler(a["rotation"]))
    assert np.abs(euler[:, 0]).max() < 30 and np.abs(euler[:, 1]).max() < 30 and np.abs(euler[:, 2]).max() < 20
    for s in range(6):
        rows = a["sequence"] == s
        assert rotation_steps_deg(a["rotation"][rows]).max() < 3.0
        distance = -a["translation"][rows, 2]  # glTF camera axes: the head is at negative z
        # cm; the focal length is estimated (up to a lens 4x the frame width), so a head may stand metres away
        assert (distance > 30).all() and (distance < 600).all()
    assert (a["pose_rms"] < 6).all()


def test_crops_are_the_frames_warped_eyes_level(facemesh, neutral_frames):
    import cv2

    a = facemesh.arrays
    rows = rows_of(facemesh, "NEU")
    times, frames = neutral_frames
    np.testing.assert_allclose(a["time"][rows], times)
    planes = [image for _, image in iter_planes(CLIPS["NEU"])]
    for i in (0, 30, 60):
        # the crop is the frame's luma plane warped, mapped to full-range gray: exactly
        np.testing.assert_array_equal(a["crops"][rows[i]], planes[i].warp_gray(a["crop_transforms"][rows[i]], 128))
        # ...which is OpenCV's gray of the BGR frame (FFmpeg's fast converter made it ~1.4 levels darker) up to
        # rounding and the converters' chroma handling at edges
        gray = cv2.cvtColor(frames[i], cv2.COLOR_BGR2GRAY)
        expect = cv2.warpAffine(
            gray, a["crop_transforms"][rows[i]], (128, 128), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
        diff = a["crops"][rows[i]].astype(int) - expect
        assert np.abs(diff).max() <= 12 and 0 <= diff.mean() < 2.5
    right, left = eye_centres(a["crop_landmarks"].astype(np.float64))
    np.testing.assert_allclose(right, np.tile([128 * 0.35, 128 * 0.33], (len(right), 1)), atol=0.01)
    np.testing.assert_allclose(left, np.tile([128 * 0.65, 128 * 0.33], (len(left), 1)), atol=0.01)
    m = a["crop_transforms"]
    lm = a["landmarks"].astype(np.float64)
    mapped = np.einsum("fij,fnj->fni", m[..., :2], lm) + m[:, None, :, 2]
    np.testing.assert_allclose(mapped, a["crop_landmarks"], atol=1e-3)
    # the whole face (jaw, brows) stays inside the crop
    assert (a["crop_landmarks"] > 0).all() and (a["crop_landmarks"] < 128).all()


def test_audio_is_resampled_and_placed(facemesh):
    a, meta = facemesh.arrays, facemesh.meta
    assert meta["audio_rate"] == 16000 and meta["has_audio"] == [True] * 6
    bounds = a["audio_bounds"]
    assert bounds[0, 0] == 0 and (bounds[1:, 0] == bounds[:-1, 1]).all() and bounds[-1, 1] == len(a["audio"])
    for s, (start, stop) in enumerate(bounds):
        seconds = (stop - start) / 16000
        video_seconds = meta["frames"][s] / meta["fps"][s]
        assert abs(seconds - video_seconds) < 0.1
        assert np.abs(a["audio"][start:stop]).max() > 0.05  # speech, not silence
    assert all(abs(o + 0.027) < 1e-6 for o in meta["audio_offset"])  # FLV: audio 27 ms before the first frame


def test_mapping_table_is_symmetric_and_evenly_spaced_on_real_faces(facemesh):
    lm = facemesh.arrays["landmarks"].astype(np.float64)
    iod = inter_ocular(lm)
    residuals = []
    for shape, d in zip(lm[::5], iod[::5]):
        mirrored = shape[IBUG68_MIRROR] * np.array([-1.0, 1.0])
        t = fit_similarity(mirrored, shape)
        residuals.append(np.linalg.norm(mirrored @ t[:, :2].T + t[:, 2] - shape, axis=1) / d)
    per_point = np.mean(residuals, axis=0)
    assert per_point.max() < 0.06 and per_point.mean() < 0.03  # a face is nearly symmetric; a wrong pair is not
    # in-between points of each contour sit at roughly equal spacing (the iBUG annotation rule)
    contours = [
        range(0, 17),
        range(17, 22),
        range(22, 27),
        range(27, 31),
        range(48, 55),
        [54, 55, 56, 57, 58, 59, 48],
        [36, 37, 38, 39],
        [39, 40, 41, 36],
        [42, 43, 44, 45],
        [45, 46, 47, 42],
    ]
    for contour in contours:
        seg = np.linalg.norm(np.diff(lm[:, list(contour)], axis=1), axis=2).mean(axis=0)
        assert seg.max() < 2.4 * seg.min(), list(contour)  # the brows: about 2.1 (tip segments are long)


def test_contact_sheet_and_figures(facemesh):
    import cv2

    view = facemesh.view()
    png = contact_sheet_png(view, {"videos": CLIPS})
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    per_clip = [-(-n // 10) for n in facemesh.meta["frames"]]  # every 10th frame
    assert image.shape == (6 * 200, max(per_clip) * 200, 3)
    from_crops = cv2.imdecode(np.frombuffer(contact_sheet_png(view, {}), np.uint8), cv2.IMREAD_COLOR)
    assert from_crops.shape == image.shape
    for name in ("head_pose", "confidence", "eyes"):
        fig = FIGURES[name](view, {"videos": CLIPS})
        assert len(fig.axes) >= 2
    assert FaceMesh.figures is FIGURES


# ---------------------------------------------------------------- OpticalFlow


def test_optical_flow_stays_within_five_percent_of_facemesh(flow, facemesh):
    assert flow.meta["init"] == ["facemesh"] * 6 and flow.arrays["valid"].all()
    for label in CLIPS:
        rows = rows_of(facemesh, label)
        ref = facemesh.arrays["landmarks"][rows]
        dist = np.linalg.norm(flow.arrays["landmarks"][rows] - ref, axis=2).mean(axis=1) / inter_ocular(ref)
        assert dist.mean() < 0.05, label
        assert dist[0] < 1e-6  # starts exactly on FaceMesh's first frame
    assert set(flow.arrays) >= {"crops", "rotation", "audio", "crop_landmarks"}


def test_optical_flow_from_a_pts_file(tmp_path, facemesh):
    rows = rows_of(facemesh, "SAD")
    start = facemesh.arrays["landmarks"][rows[0]]
    pts = tmp_path / "sad.pts"
    pts.write_text(format_pts(start))
    out = run_stage(
        OpticalFlow, {"audio": "none", "shape_model": False}, {"videos": {"SAD": CLIPS["SAD"]}, "init": {"SAD": pts}}
    )
    assert out.meta["init"] == ["file"] and "audio" not in out.arrays
    ref = facemesh.arrays["landmarks"][rows]
    dist = np.linalg.norm(out.arrays["landmarks"] - ref, axis=2).mean(axis=1) / inter_ocular(ref)
    assert dist.mean() < 0.05
    with pytest.raises(UserError, match="no video"):
        run_stage(OpticalFlow, {}, {"videos": {"SAD": CLIPS["SAD"]}, "init": {"sad": pts}})


# ---------------------------------------------------------------- TrackFile with video


def test_trackfile_with_video_matches_facemesh(tmp_path, facemesh):
    rows = rows_of(facemesh, "NEU")
    lm = facemesh.arrays["landmarks"][rows].astype(np.float64)
    success = np.ones(len(rows), dtype=bool)
    success[[10, 11]] = False
    csv = tmp_path / "neu.csv"
    csv.write_text(write_openface_csv(lm, time=facemesh.arrays["time"][rows], success=success))
    out = run_stage(TrackFile, {}, {"tracks": {"NEU": csv}, "videos": {"NEU": CLIPS["NEU"]}})
    np.testing.assert_allclose(out.arrays["landmarks"][success], lm[success], atol=1e-4)
    assert not out.arrays["valid"][10:12].any()
    keep = success
    diff = np.abs(out.arrays["crops"][keep].astype(int) - facemesh.arrays["crops"][rows][keep])
    assert diff.max() <= 2
    np.testing.assert_allclose(out.arrays["time"], facemesh.arrays["time"][rows])
    bounds = facemesh.arrays["audio_bounds"][0]
    np.testing.assert_array_equal(out.arrays["audio"], facemesh.arrays["audio"][bounds[0] : bounds[1]])
    long_track = tmp_path / "long.csv"
    long_track.write_text(write_openface_csv(np.concatenate([lm, lm[:5]])))
    with pytest.raises(UserError, match="video has 61 frames"):
        run_stage(TrackFile, {}, {"tracks": {"NEU": long_track}, "videos": {"NEU": CLIPS["NEU"]}})


# ---------------------------------------------------------------- errors and gaps on synthetic videos


@pytest.fixture(scope="module")
def gap_video(tmp_path_factory, neutral_frames):
    """The neutral clip with frames 20-29 replaced by a blank grey picture, with a tone as audio."""
    frames = [f.copy() for f in neutral_frames[1]]
    for i in range(20, 30):
        frames[i][:] = 128
    tone = 0.1 * np.sin(np.arange(int(16000 * len(frames) / 30)) * 2 * np.pi * 220 / 16000)
    return write_video(tmp_path_factory.mktemp("gap") / "gap.mp4", frames, audio=tone)


def test_short_gaps_are_flagged_and_interpolated(gap_video):
    out = run_stage(FaceMesh, {"max_gap_frames": 12}, {"videos": {"gap": gap_video}})
    valid = out.arrays["valid"]
    assert not valid[20:30].any() and valid[:20].all() and valid[30:].all()
    lm = out.arrays["landmarks"]
    assert np.isfinite(lm).all() and (out.arrays["confidence"][20:30] == 0).all()
    expected = lm[19] + (lm[30] - lm[19]) * (np.arange(1, 11) / 11)[:, None, None]
    np.testing.assert_allclose(lm[20:30], expected, atol=1e-3)
    assert out.arrays["crops"].shape[0] == len(valid)
    assert out.meta["detector_runs"][0] > 10  # the detector searched every blank frame
    assert out.metrics["interpolated_frames"] == 10


def test_long_gaps_fail_with_the_frame_range(gap_video):
    with pytest.raises(UserError, match=r"no face in frames 20-29 \(10 frames") as err:
        run_stage(FaceMesh, {"max_gap_frames": 5, "long_gaps": "error"}, {"videos": {"gap": gap_video}})
    assert err.value.file == str(gap_video) and err.value.field == "inputs.videos.gap"


def test_a_video_without_a_face_fails(tmp_path):
    blank = write_video(tmp_path / "blank.mp4", [np.full((120, 160, 3), 90, np.uint8)] * 8)
    with pytest.raises(UserError, match="no face found in any of its 8 frames"):
        run_stage(FaceMesh, {"audio": "none"}, {"videos": {"b": blank}})


def test_missing_audio_track(tmp_path, neutral_frames):
    silent = write_video(tmp_path / "silent.mp4", neutral_frames[1][:12])
    with pytest.raises(UserError, match="no audio track") as err:
        run_stage(FaceMesh, {}, {"videos": {"s": silent}})
    assert "silent.mp4" in str(err.value)
    out = run_stage(FaceMesh, {"audio": "none"}, {"videos": {"s": silent}})
    assert "audio" not in out.arrays and out.meta["audio_rate"] is None
    out = run_stage(FaceMesh, {"audio": "optional", "output_mesh": False}, {"videos": {"s": silent}})
    assert out.meta["has_audio"] == [False] and "mesh" not in out.arrays


def test_truncated_and_unreadable_videos_name_the_file(tmp_path):
    data = CLIPS["ANG"].read_bytes()
    cut = tmp_path / "cut.flv"
    cut.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(UserError, match="truncated") as err:
        run_stage(FaceMesh, {}, {"videos": {"ang": cut}})
    assert err.value.file == str(cut) and "cut.flv" in str(err.value)
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    with pytest.raises(UserError, match="cannot open video") as err:
        run_stage(FaceMesh, {}, {"videos": {"j": junk}})
    assert err.value.file == str(junk)
    text = tmp_path / "notes.mp4"  # a text file given a video's name: FFmpeg's reason, not its errno number
    text.write_text("not a video\n" * 100)
    with pytest.raises(UserError, match=r"could not be read as a video \(Invalid data found") as err:
        run_stage(FaceMesh, {}, {"videos": {"t": text}})
    assert "Errno" not in str(err.value) and err.value.file == str(text)
    with pytest.raises(UserError, match="not found"):
        run_stage(FaceMesh, {}, {"videos": {"x": tmp_path / "missing.mp4"}})


def test_model_inputs_are_checked(tmp_path):
    with pytest.raises(UserError, match="unknown model labels"):
        run_stage(FaceMesh, {}, {"videos": {"a": CLIPS["NEU"]}, "models": {"detektor": CLIPS["NEU"]}})
    fake = tmp_path / "fake.tflite"
    fake.write_bytes(b"not a model")
    with pytest.raises(UserError, match="cannot load TFLite model") as err:
        run_stage(FaceMesh, {}, {"videos": {"a": CLIPS["NEU"]}, "models": {"landmarks": fake}})
    assert err.value.file == str(fake)
