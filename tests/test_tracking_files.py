"""Track files: OpenFace 2.0 CSV (with success = 0 rows), plain CSV, .npz and iBUG .pts, read, written and
rejected with clear errors; the TrackFile stage on synthetic tracks without video."""

import io

import numpy as np
import pytest

from msflow import UserError
from msflow.testing import run_stage
from stages.tracking import TrackFile
from stages.tracking.trackfile import format_pts, parse_pts, read_track, write_npz, write_openface_csv, write_plain_csv


def synthetic_shapes(n=40, seed=0):
    """A moving, slightly deforming 68-point shape (pixels)."""
    rng = np.random.default_rng(seed)
    base = rng.uniform(-60, 60, (68, 2))
    t = np.arange(n)[:, None, None]
    return base * (1 + 0.02 * np.sin(t / 5)) + np.array([240, 180]) + 3 * np.sin(t / 7)


def openface_header_with_extras():
    """The column layout OpenFace 2.0 FeatureExtraction writes (abridged: gaze, pose, 2D/3D landmarks, PDM, AUs)."""
    cols = ["frame", "face_id", "timestamp", "confidence", "success"]
    cols += [f"gaze_{e}_{a}" for e in (0, 1) for a in "xyz"] + ["gaze_angle_x", "gaze_angle_y"]
    cols += [f"eye_lmk_x_{i}" for i in range(56)] + [f"eye_lmk_y_{i}" for i in range(56)]
    cols += ["pose_Tx", "pose_Ty", "pose_Tz", "pose_Rx", "pose_Ry", "pose_Rz"]
    cols += [f"x_{i}" for i in range(68)] + [f"y_{i}" for i in range(68)]
    cols += [f"{a}_{i}" for a in "XYZ" for i in range(68)]
    cols += ["p_scale", "p_rx", "p_ry", "p_rz", "p_tx", "p_ty"] + [f"p_{i}" for i in range(34)]
    cols += ["AU01_r", "AU02_r", "AU45_c"]
    return cols


def write_full_openface(path, shapes, success, fps=30.0):
    cols = openface_header_with_extras()
    rng = np.random.default_rng(1)
    rows = rng.normal(size=(len(shapes), len(cols)))
    idx = {c: i for i, c in enumerate(cols)}
    rows[:, idx["frame"]] = np.arange(1, len(shapes) + 1)
    rows[:, idx["face_id"]] = 0
    rows[:, idx["timestamp"]] = np.round(np.arange(len(shapes)) / fps, 3)
    rows[:, idx["confidence"]] = np.where(success, 0.97, 0.0)
    rows[:, idx["success"]] = success
    for i in range(68):
        rows[:, idx[f"x_{i}"]] = np.where(success, shapes[:, i, 0], 0)
        rows[:, idx[f"y_{i}"]] = np.where(success, shapes[:, i, 1], 0)
    out = io.StringIO()
    out.write(", ".join(cols) + "\n")
    np.savetxt(out, rows, fmt="%.6f", delimiter=", ")
    path.write_text(out.getvalue())


def test_openface_csv_round_trip_with_failed_rows(tmp_path):
    shapes = synthetic_shapes()
    success = np.ones(len(shapes), dtype=bool)
    success[[0, 7, 8, 25]] = False
    path = tmp_path / "take.csv"
    path.write_text(write_openface_csv(shapes, success=success, fps=25.0))
    assert ", " in path.read_text().splitlines()[0]
    track = read_track(path)
    assert track.format == "openface"
    np.testing.assert_array_equal(track.valid, success)
    np.testing.assert_array_equal(track.frame, np.arange(len(shapes)))
    np.testing.assert_allclose(track.landmarks[success], shapes[success], atol=1e-6)
    assert np.isnan(track.landmarks[~success]).all()
    assert (track.confidence[~success] == 0).all()

    out = run_stage(TrackFile, {"frame_size": (480, 360)}, {"tracks": {"take": path}})
    lm, valid = out.arrays["landmarks"], out.arrays["valid"]
    np.testing.assert_array_equal(valid, success)
    np.testing.assert_allclose(lm[success], shapes[success], atol=1e-4)
    # failed rows are interpolated from their neighbours (frame 0 holds frame 1)
    np.testing.assert_allclose(lm[7], shapes[6] + (shapes[9] - shapes[6]) / 3, atol=1e-4)
    np.testing.assert_allclose(lm[0], shapes[1], atol=1e-4)
    assert out.meta["fps"] == [pytest.approx(25.0)]
    np.testing.assert_allclose(out.arrays["time"], np.arange(len(shapes)) / 25.0)
    assert out.meta["has_crops"] is False and out.arrays["crops"].shape == (len(shapes), 0, 0)
    assert "audio" not in out.arrays
    assert out.metrics["interpolated_frames"] == 4


def test_real_openface_layout_is_read_by_column_name(tmp_path):
    shapes = synthetic_shapes(30, seed=2)
    success = np.ones(30, dtype=bool)
    success[12:14] = False
    path = tmp_path / "of.csv"
    write_full_openface(path, shapes, success)
    track = read_track(path)
    np.testing.assert_allclose(track.landmarks[success], shapes[success], atol=1e-5)
    np.testing.assert_array_equal(track.valid, success)
    assert track.openface_pose.shape == (30, 6)
    out = run_stage(TrackFile, {"frame_size": (480, 360), "pose_source": "file"}, {"tracks": {"a": path}})
    np.testing.assert_allclose(np.linalg.norm(out.arrays["rotation"], axis=1), 1.0)


def test_openface_missing_columns_and_wrong_point_count(tmp_path):
    shapes = synthetic_shapes(5)
    text = write_openface_csv(shapes)
    lines = text.splitlines()
    header = lines[0].split(", ")
    keep = [i for i, c in enumerate(header) if c != "success"]
    bad = tmp_path / "nosuccess.csv"
    bad.write_text("\n".join(", ".join(np.array(ln.split(", "))[keep]) for ln in lines) + "\n")
    with pytest.raises(UserError, match="missing columns success") as err:
        read_track(bad, "openface")
    assert err.value.file == str(bad)

    cut = tmp_path / "no_y67.csv"
    keep = [i for i, c in enumerate(header) if c != "y_67"]
    cut.write_text("\n".join(", ".join(np.array(ln.split(", "))[keep]) for ln in lines) + "\n")
    with pytest.raises(UserError, match="missing landmark columns: y_67"):
        read_track(cut)

    five = tmp_path / "five.csv"
    cols = ["frame"] + [f"x_{i}" for i in range(5)] + [f"y_{i}" for i in range(5)]
    five.write_text(",".join(cols) + "\n" + ",".join(["0"] + ["1.0"] * 10) + "\n")
    with pytest.raises(UserError, match="5 landmarks"):
        read_track(five)
    with pytest.raises(UserError, match="5 landmarks"):
        run_stage(TrackFile, {"frame_size": (480, 360), "fps": 30}, {"tracks": {"x": five}})


def test_plain_csv_npz_and_pts_round_trips(tmp_path):
    shapes = synthetic_shapes(12, seed=3)
    plain = tmp_path / "plain.csv"
    plain.write_text(write_plain_csv(shapes))
    t = read_track(plain)
    assert t.format == "csv" and t.valid.all()
    np.testing.assert_allclose(t.landmarks, shapes, atol=1e-6)

    npz = tmp_path / "track.npz"
    valid = np.ones(12, dtype=bool)
    valid[4] = False
    npz.write_bytes(write_npz(shapes, valid=valid, fps=np.float64(24.0), frame_size=np.array([640, 480])))
    t = read_track(npz)
    assert t.fps == 24.0 and t.frame_size == (640, 480)
    np.testing.assert_array_equal(t.valid, valid)
    out = run_stage(TrackFile, {}, {"tracks": {"n": npz}})
    assert out.meta["frame_size"] == [[640, 480]] and out.meta["fps"] == [24.0]

    seq = tmp_path / "pts"
    seq.mkdir()
    for i, s in enumerate(shapes):
        (seq / f"frame_{i}.pts").write_text(format_pts(s))  # natural order: frame_10 after frame_9
    t = read_track(seq)
    np.testing.assert_allclose(t.landmarks, shapes, atol=1e-3)
    single = read_track(seq / "frame_3.pts")
    np.testing.assert_allclose(single.landmarks[0], shapes[3], atol=1e-3)


def test_bad_npz_and_pts_are_user_errors(tmp_path):
    obj = tmp_path / "obj.npz"
    np.savez(obj, landmarks=np.array([{"a": 1}], dtype=object))
    with pytest.raises(UserError, match="object arrays"):
        read_track(obj)
    wrong = tmp_path / "wrong.npz"
    np.savez(wrong, landmarks=np.zeros((3, 49, 2)))
    with pytest.raises(UserError, match="49 landmarks"):
        read_track(wrong)
    with pytest.raises(UserError, match="no 'landmarks'"):
        np.savez(tmp_path / "none.npz", shapes=np.zeros((3, 68, 2)))
        read_track(tmp_path / "none.npz")
    with pytest.raises(UserError, match="has 5 points"):
        parse_pts(format_pts(np.zeros((5, 2))))
    with pytest.raises(UserError, match="n_points says 68"):
        parse_pts("version: 1\nn_points: 68\n{\n1 2\n}\n")
    bad_dir = tmp_path / "seq"
    bad_dir.mkdir()
    (bad_dir / "0001.pts").write_text(format_pts(np.zeros((68, 2))))
    (bad_dir / "0002.pts").write_text(format_pts(np.zeros((51, 2))))
    with pytest.raises(UserError, match="51 points") as err:
        read_track(bad_dir)
    assert err.value.file.endswith("0002.pts")


def test_trackfile_needs_timing_and_frame_size_without_video(tmp_path):
    seq = tmp_path / "pts"
    seq.mkdir()
    for i, s in enumerate(synthetic_shapes(6)):
        (seq / f"{i:03d}.pts").write_text(format_pts(s))
    with pytest.raises(UserError, match="frame rate unknown"):
        run_stage(TrackFile, {"frame_size": (480, 360)}, {"tracks": {"s": seq}})
    with pytest.raises(UserError, match="frame size unknown"):
        run_stage(TrackFile, {"fps": 30}, {"tracks": {"s": seq}})
    with pytest.raises(UserError, match="audio is required"):
        run_stage(TrackFile, {"fps": 30, "frame_size": (480, 360), "audio": "required"}, {"tracks": {"s": seq}})
    out = run_stage(TrackFile, {"fps": 30, "frame_size": (480, 360)}, {"tracks": {"s": seq}})
    assert out.arrays["landmarks"].shape == (6, 68, 2) and out.meta["labels"] == ["s"]


def test_frames_must_increase_and_gaps_over_the_limit_fail(tmp_path):
    shapes = synthetic_shapes(40)
    frames = np.arange(40)
    frames[5] = 4
    path = tmp_path / "dup.csv"
    path.write_text(write_plain_csv(shapes, frames))
    with pytest.raises(UserError, match="frame numbers must increase"):
        read_track(path)
    success = np.ones(40, dtype=bool)
    success[10:30] = False
    path = tmp_path / "gap.csv"
    path.write_text(write_openface_csv(shapes, success=success))
    with pytest.raises(UserError, match="frames 10-29") as err:
        run_stage(TrackFile, {"frame_size": (480, 360), "long_gaps": "error"}, {"tracks": {"g": path}})
    assert err.value.field == "inputs.tracks.g"
    out = run_stage(TrackFile, {"frame_size": (480, 360), "max_gap_frames": 20}, {"tracks": {"g": path}})
    assert not out.arrays["valid"][10:30].any()
    held = run_stage(TrackFile, {"frame_size": (480, 360)}, {"tracks": {"g": path}})  # long_gaps: hold
    np.testing.assert_array_equal(held.arrays["landmarks"][10:30], np.repeat(held.arrays["landmarks"][9:10], 20, 0))
    assert held.meta["gaps"] == [[[10, 30]]] and "frames 10-29" in held.warnings[0]


def test_a_custom_3d_face_scales_the_head_distance(tmp_path):
    import json

    from stages.tracking.face3d import DEFAULT_FACE3D

    shapes = synthetic_shapes(8)
    path = tmp_path / "t.csv"
    path.write_text(write_plain_csv(shapes))
    params = {"fps": 30, "frame_size": (480, 360)}
    base = run_stage(TrackFile, params, {"tracks": {"t": path}})
    data = json.loads(DEFAULT_FACE3D.read_text())
    data["neutral"] = (np.array(data["neutral"]) * 2).tolist()
    big = tmp_path / "big_face.json"
    big.write_text(json.dumps(data))
    scaled = run_stage(TrackFile, params, {"tracks": {"t": path}, "face3d": {"face": big}})
    np.testing.assert_allclose(scaled.arrays["translation"], 2 * base.arrays["translation"], rtol=1e-5)
    np.testing.assert_allclose(
        np.abs(np.sum(scaled.arrays["rotation"] * base.arrays["rotation"], axis=1)), 1, atol=1e-8
    )
    assert scaled.meta["pose_model"] == "big_face.json"
    bad = tmp_path / "bad_face.json"
    bad.write_text(json.dumps({"neutral": [[0, 0, 0]] * 5}))
    with pytest.raises(UserError, match="68 points") as err:
        run_stage(TrackFile, params, {"tracks": {"t": path}, "face3d": {"face": bad}})
    assert err.value.field == "inputs.face3d.face"
