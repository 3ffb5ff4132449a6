"""Motion blending (paper Sec. 5.4): resampling, chaining, drift correction, crossfaded joins, outputs."""
from pathlib import Path

import numpy as np
import pytest

from head_synthetic import synth_database, tracking_artifact
from msflow import UserError
from msflow.testing import artifact, run_stage
from stages.bvh import joint_rotation, joint_translation, parse_bvh
from stages.headdb import TrackedHeadDb
from stages.motion_blend import (DatabaseMotion, MotionBlend, _reference_angles, angular_acceleration,
                                 angular_speed, join_acceleration, pitch_velocity_correlation, stitch_segments,
                                 wasserstein_speed)
from stages.pitch import Pitch
from stages.rotations import euler_to_quat
from stages.trellis import Trellis

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def phrases():
    return synth_database(16, seed=21)


@pytest.fixture(scope="module")
def tracks(phrases):
    return tracking_artifact(phrases, fps=30.0)


@pytest.fixture(scope="module")
def database(tracks):
    headdb = run_stage(TrackedHeadDb, {}, {"tracks": tracks})
    return headdb, run_stage(Pitch, {}, {"source": headdb})


@pytest.fixture(scope="module")
def test_pitch(tracks):
    return run_stage(Pitch, {}, {"source": tracks})


def trellis(database, test_pitch, **params):
    return run_stage(Trellis, params, {"database": database[0], "database_pitch": database[1],
                                       "test_pitch": test_pitch})


@pytest.fixture(scope="module")
def leave_one_out(database, test_pitch):
    return trellis(database, test_pitch, exclude_source=True)


def line_database(slopes, seconds=4.0, fps=100.0):
    """One sequence per slope: every channel moves linearly, value = slope * t."""
    n = int(seconds * fps)
    t = np.arange(n) / fps
    channels = np.concatenate([np.repeat((s * t)[:, None], 6, axis=1) for s in slopes])
    frames = np.full(len(slopes), n)
    return DatabaseMotion(channels, np.arange(len(slopes)) * n, frames, fps)


# ------------------------------------------------------------------------------------------ the maths

def test_segments_are_resampled_to_the_test_length():
    db = line_database([1.0])
    times = np.arange(0, 1.0, 0.01)
    out = stitch_segments(db, np.array([[0.0, 0.5, 1.0]]), np.array([True]), np.array([0]),
                          np.array([[1.0, 1.5, 3.0]]), times, blend_window=0.0)
    # two database seconds play in one output second, from the recorded pose at 1.0
    np.testing.assert_allclose(out.channels[:, 0], 1.0 + 2.0 * times, atol=1e-9)


def test_each_segment_starts_where_the_previous_ended():
    db = line_database([1.0, -2.0])
    times = np.arange(0, 2.0, 0.01)
    test = np.array([[0.0, 0.3, 0.5], [0.5, 0.8, 1.2], [1.2, 1.5, 2.0]])
    chosen_seq = np.array([0, 1, 0])
    chosen = np.array([[0.0, 0.3, 0.5], [2.0, 2.2, 2.7], [1.0, 1.2, 1.8]])
    out = stitch_segments(db, test, np.array([True, False, False]), chosen_seq, chosen, times,
                          blend_window=0.0, drift_correction=False).channels[:, 0]
    # slopes 1, then -2 * (0.7 / 0.7), then 1 * (0.8 / 0.8): a continuous zig-zag
    expected = np.where(times < 0.5, times, np.where(times < 1.2, 0.5 - 2 * (times - 0.5), -0.9 + (times - 1.2)))
    np.testing.assert_allclose(out, expected, atol=1e-9)


def test_drift_correction_joins_sub_sentences():
    db = line_database([1.0, 0.0])
    times = np.arange(0, 2.0, 0.005)
    test = np.array([[0.0, 0.4, 0.5], [0.5, 0.8, 1.0], [1.0, 1.4, 2.0]])
    sub = np.array([True, False, True])
    chosen_seq = np.array([0, 0, 1])
    chosen = np.array([[1.0, 1.4, 1.5], [1.5, 1.8, 2.0], [0.0, 0.5, 1.0]])
    hard = dict(blend_window=0.0, break_blend_window=0.0)
    drifting = stitch_segments(db, test, sub, chosen_seq, chosen, times, drift_correction=False, **hard)
    corrected = stitch_segments(db, test, sub, chosen_seq, chosen, times, drift_correction=True, **hard)
    at = lambda curve, t: curve.channels[np.argmin(np.abs(times - t)), 0]
    # without correction the second sub-sentence jumps back to its recorded pose (0), from 2.0
    assert at(drifting, 0.995) == pytest.approx(1.995, abs=1e-6) and at(drifting, 1.0) == pytest.approx(0.0)
    # with it the first sub-sentence is warped linearly so that it ends at 0: 1 + t - 2 t = 1 - t
    np.testing.assert_allclose(corrected.channels[times < 1.0, 0], 1.0 - times[times < 1.0], atol=1e-9)
    assert at(corrected, 1.0) == pytest.approx(0.0)


def test_crossfade_weights_sum_to_one_even_for_short_segments():
    n = 400
    db = DatabaseMotion(np.full((n, 6), 0.3), np.array([0]), np.array([n]), 100.0)
    starts = np.cumsum(np.r_[0.0, np.full(9, 0.07)])
    test = np.stack([starts, starts + 0.03, np.r_[starts[1:], 1.0]], axis=1)
    out = stitch_segments(db, test, np.zeros(10, bool), np.zeros(10, int), test + 0.5, np.arange(0, 1, 0.01),
                          blend_window=0.2)
    np.testing.assert_allclose(out.channels, 0.3, atol=1e-12)


def test_crossfade_removes_the_velocity_step():
    db = line_database([1.0, -1.0])
    times = np.arange(0, 2.0, 0.01)
    test = np.array([[0.0, 0.5, 1.0], [1.0, 1.5, 2.0]])
    args = (db, test, np.array([True, False]), np.array([0, 1]), np.array([[1.0, 1.5, 2.0], [1.0, 1.5, 2.0]]),
            times)
    hard = stitch_segments(*args, blend_window=0.0).channels[:, 0]
    soft = stitch_segments(*args, blend_window=0.2).channels[:, 0]
    accel = lambda x: np.abs(np.diff(x, 2)).max() / 0.01 ** 2
    assert accel(hard) > 150 and accel(soft) < 0.1 * accel(hard)
    # away from the join the motion is untouched
    far = np.abs(times - 1.0) > 0.25
    np.testing.assert_allclose(soft[far], hard[far], atol=1e-12)


def test_measures():
    fps = 30.0
    t = np.arange(60) / fps
    spin = np.stack([0.5 * t, np.zeros(60), np.zeros(60)], axis=1)
    np.testing.assert_allclose(angular_speed(spin, fps), np.degrees(0.5), atol=1e-9)
    np.testing.assert_allclose(angular_acceleration(spin, fps), 0.0, atol=1e-6)
    assert wasserstein_speed(spin, spin, fps) == 0.0
    assert wasserstein_speed(spin, spin * 2, fps) == pytest.approx(np.degrees(0.5))
    nod = np.stack([np.zeros(60), np.sin(2 * np.pi * t), np.zeros(60)], axis=1)
    f0_t = np.arange(0, 2, 0.01)
    assert pitch_velocity_correlation(nod, fps, f0_t, np.cos(2 * np.pi * f0_t)) > 0.95
    bumps = np.zeros((60, 3))
    bumps[30:, 0] = 0.1 * (t[30:] - t[30])           # a velocity step at 1 s
    assert join_acceleration(bumps, fps, np.array([1.0, 0.3]), 0.1)[0] > 100
    assert join_acceleration(bumps, fps, np.array([1.0, 0.3]), 0.1)[1] == 0.0


# ---------------------------------------------------------------------------------------- the stage

def test_an_utterance_found_in_the_database_gets_its_own_motion_back(phrases, tracks):
    headdb = run_stage(TrackedHeadDb, {"mirror": False}, {"tracks": tracks})
    db_pitch = run_stage(Pitch, {}, {"source": headdb})
    test_tracks = tracking_artifact(phrases[3:4], fps=30.0)
    test_pitch = run_stage(Pitch, {}, {"source": test_tracks})
    tr = run_stage(Trellis, {}, {"database": headdb, "database_pitch": db_pitch, "test_pitch": test_pitch})
    run = run_stage(MotionBlend, {}, {"trellis": tr, "database": headdb, "reference": test_tracks})
    real = _reference_angles(test_tracks, phrases[3].label, 1, 30.0)
    assert run.arrays["angles"].shape == real.shape
    np.testing.assert_allclose(run.arrays["angles"], real, atol=1e-9)
    assert run.metrics["speed_wasserstein"] < 1e-9


def test_outputs_frames_rate_and_bvh(leave_one_out, database, tracks):
    run = run_stage(MotionBlend, {}, {"trellis": leave_one_out, "database": database[0], "reference": tracks})
    frames = np.bincount(tracks["sequence"])
    assert run.meta["fps"] == 30.0 and run.meta["frames"] == list(frames)
    np.testing.assert_allclose(np.linalg.norm(run.arrays["rotation"], axis=1), 1.0, atol=1e-12)
    assert np.isfinite(run.arrays["translation"]).all()
    bvh = parse_bvh(run.arrays["bvh"].tobytes().decode())
    assert bvh.frames == len(run.arrays["rotation"]) and bvh.fps == pytest.approx(30.0)
    np.testing.assert_allclose(np.abs(np.sum(joint_rotation(bvh, "Head") * run.arrays["rotation"], axis=1)), 1.0,
                               atol=1e-9)
    np.testing.assert_allclose(joint_translation(bvh, "Head"), run.arrays["translation"], atol=1e-5)
    # joins sit at the test segments' starts
    seg = leave_one_out.arrays["segments"][leave_one_out.arrays["segment_utterance"] == 0]
    np.testing.assert_allclose(run.arrays["joins"][run.arrays["join_utterance"] == 0], seg[1:, 0])
    assert {"speed_wasserstein", "max_join_acceleration", "real_acceleration_p99"} <= set(run.metrics)


def test_leave_one_out_motion_is_plausible_and_smooth_at_joins(leave_one_out, database, tracks):
    soft = run_stage(MotionBlend, {}, {"trellis": leave_one_out, "database": database[0]})
    hard = run_stage(MotionBlend, {"blend_window": 0.0, "break_blend_window": 0.0},
                     {"trellis": leave_one_out, "database": database[0]})
    assert soft.metrics["max_join_acceleration"] < 0.8 * hard.metrics["max_join_acceleration"]
    db_angles = database[0].arrays["angles"]
    assert np.abs(soft.arrays["angles"]).max() < 2 * np.abs(db_angles).max()
    # the synthesis moves about as fast as the database does
    db_speed = np.mean(angular_speed(db_angles[database[0].arrays["sequence"] == 0], 30.0))
    assert 0.3 * db_speed < soft.metrics["mean_angular_speed"] < 3 * db_speed


def test_output_rate_parameter(leave_one_out, database):
    run = run_stage(MotionBlend, {"fps": 60.0}, {"trellis": leave_one_out, "database": database[0]})
    durations = leave_one_out.meta["durations"]
    assert run.meta["frames"] == [int(round(d * 60.0)) for d in durations]


def test_a_silent_test_take_gives_a_still_head(database):
    audio = (np.random.default_rng(0).standard_normal(24000) * 1e-4).astype(np.float32)
    quiet = artifact({"audio": audio, "audio_bounds": np.array([[0, 24000]])},
                     {"labels": ["quiet"], "sources": ["quiet.wav"], "audio_rate": 16000})
    pitch = run_stage(Pitch, {"on_silence": "still"}, {"source": quiet})
    tr = run_stage(Trellis, {}, {"database": database[0], "database_pitch": database[1], "test_pitch": pitch})
    run = run_stage(MotionBlend, {}, {"trellis": tr, "database": database[0]})
    assert run.meta["frames"] == [45] and run.meta["fps"] == database[0].meta["fps"]
    np.testing.assert_allclose(run.arrays["rotation"], np.tile([1.0, 0, 0, 0], (45, 1)))
    assert len(run.arrays["joins"]) == 0


def test_trellis_from_another_database_is_an_error(leave_one_out, phrases):
    other = run_stage(TrackedHeadDb, {"mirror": False}, {"tracks": tracking_artifact(phrases[:3])})
    with pytest.raises(UserError, match="different database"):
        run_stage(MotionBlend, {}, {"trellis": leave_one_out, "database": other})


def test_head_angles_figure(leave_one_out, database, tracks):
    run = run_stage(MotionBlend, {}, {"trellis": leave_one_out, "database": database[0]})
    fig = MotionBlend.figures["head_angles"](run.view(), {"reference": tracks})
    assert len(fig.axes) == 3 and len(fig.axes[0].get_lines()) > 2


@pytest.fixture(scope="module")
def crema():
    from stages.tracking import FaceMesh

    files = {p.name.split("_")[2]: p for p in sorted((ROOT / "data" / "crema-d").glob("*.flv"))}
    train = run_stage(FaceMesh, {}, {"videos": {k: files[k] for k in ("NEU", "HAP", "ANG")}})
    test = run_stage(FaceMesh, {}, {"videos": {"SAD": files["SAD"]}})
    return train, test


def test_crema_d_end_to_end(crema):
    """The default pipeline's head branch on real data: three tracked takes in, the sad take's audio drives."""
    train, test = crema
    headdb = run_stage(TrackedHeadDb, {}, {"tracks": train})
    db_pitch = run_stage(Pitch, {}, {"source": headdb})
    test_pitch = run_stage(Pitch, {}, {"source": test})
    tr = run_stage(Trellis, {}, {"database": headdb, "database_pitch": db_pitch, "test_pitch": test_pitch})
    run = run_stage(MotionBlend, {}, {"trellis": tr, "database": headdb, "reference": test})
    assert run.meta["fps"] == pytest.approx(test.meta["fps"][0])
    assert run.meta["frames"] == [len(test.arrays["rotation"])]
    angles = np.degrees(run.arrays["angles"])
    assert np.abs(angles).max() < 30
    # the synthesis moves, and not wildly faster than the real take
    assert 0.2 * run.metrics["real_mean_angular_speed"] < run.metrics["mean_angular_speed"] < \
        5 * run.metrics["real_mean_angular_speed"]
