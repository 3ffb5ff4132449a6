"""Motion blending (paper Sec. 5.4): resampling, chaining, drift correction, crossfaded joins, outputs."""

import numpy as np
import pytest
from head_synthetic import synth_database, tracking_artifact
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from msflow import UserError
from msflow.testing import artifact, prepare_inputs, run_stage
from stages.formats.bvh import joint_rotation, joint_translation, parse_bvh
from stages.head.database import TrackedHeadDb
from stages.head.measures import (
    angular_acceleration,
    angular_speed,
    join_acceleration,
    pitch_velocity_correlation,
    reference_angles,
    wasserstein_speed,
)
from stages.head.motion_blend import MotionBlend, accelerations_at_joins
from stages.head.pitch import Pitch
from stages.head.stitching import DatabaseMotion, join_windows, segment_weights, stitch_segments
from stages.head.trellis import Trellis


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
def take_pitch(tracks):
    return run_stage(Pitch, {}, {"source": tracks})


def trellis(database, take_pitch, **params):
    return run_stage(
        Trellis, params, {"database": database[0], "database_pitch": database[1], "test_pitch": take_pitch}
    )


@pytest.fixture(scope="module")
def leave_one_out(database, take_pitch):
    return trellis(database, take_pitch, holdout="take")


def stage_result(cls, params, inputs):
    """The stage's own Result (with its warnings), inputs prepared as the runner would."""
    return cls(cls.__name__).run(cls.Params(**params), prepare_inputs(cls, inputs))


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
    out = stitch_segments(
        db,
        np.array([[0.0, 0.5, 1.0]]),
        np.array([True]),
        np.array([0]),
        np.array([[1.0, 1.5, 3.0]]),
        times,
        blend_window=0.0,
    )
    # two database seconds play in one output second, from the recorded pose at 1.0
    np.testing.assert_allclose(out.channels[:, 0], 1.0 + 2.0 * times, atol=1e-9)


def test_each_segment_starts_where_the_previous_ended():
    db = line_database([1.0, -2.0])
    times = np.arange(0, 2.0, 0.01)
    test = np.array([[0.0, 0.3, 0.5], [0.5, 0.8, 1.2], [1.2, 1.5, 2.0]])
    chosen_seq = np.array([0, 1, 0])
    chosen = np.array([[0.0, 0.3, 0.5], [2.0, 2.2, 2.7], [1.0, 1.2, 1.8]])
    out = stitch_segments(
        db, test, np.array([True, False, False]), chosen_seq, chosen, times, blend_window=0.0, drift_correction=False
    ).channels[:, 0]
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
    out = stitch_segments(
        db, test, np.zeros(10, bool), np.zeros(10, int), test + 0.5, np.arange(0, 1, 0.01), blend_window=0.2
    )
    np.testing.assert_allclose(out.channels, 0.3, atol=1e-12)


def test_crossfade_removes_the_velocity_step():
    db = line_database([1.0, -1.0])
    times = np.arange(0, 2.0, 0.01)
    test = np.array([[0.0, 0.5, 1.0], [1.0, 1.5, 2.0]])
    args = (db, test, np.array([True, False]), np.array([0, 1]), np.array([[1.0, 1.5, 2.0], [1.0, 1.5, 2.0]]), times)
    hard = stitch_segments(*args, blend_window=0.0).channels[:, 0]
    soft = stitch_segments(*args, blend_window=0.2).channels[:, 0]
    accel = lambda x: np.abs(np.diff(x, 2)).max() / 0.01**2
    assert accel(hard) > 150 and accel(soft) < 0.1 * accel(hard)
    # away from the join the motion is untouched
    far = np.abs(times - 1.0) > 0.25
    np.testing.assert_allclose(soft[far], hard[far], atol=1e-12)


def curve_database(functions, seconds=6.0, fps=100.0):
    """One sequence per function of time; rotation channels (yaw, pitch, roll) follow it, translation is zero."""
    n = int(seconds * fps)
    t = np.arange(n) / fps
    channels = np.concatenate(
        [np.concatenate([np.stack([f(t)] * 3, axis=1), np.zeros((n, 3))], axis=1) for f in functions]
    )
    return DatabaseMotion(channels, np.arange(len(functions)) * n, np.full(len(functions), n), fps)


def steps(x, fps):
    velocity = np.diff(x, axis=0) * fps
    return velocity, np.diff(velocity, axis=0) * fps


def test_velocity_blend_is_continuous_in_position_and_velocity_across_a_velocity_step():
    """Two segments whose velocities differ by 2 rad/s at the join: the blend keeps position and velocity
    continuous, passes the velocity monotonically from one slope to the other (no overshoot), and adds no more
    acceleration than the smoothstep bound 1.5 dv / (2 W)."""
    fps = 200.0
    db = line_database([1.0, -1.0], fps=fps)
    times = np.arange(0, 2.0, 1 / fps)
    test = np.array([[0.0, 0.5, 1.0], [1.0, 1.5, 2.0]])
    chosen = np.array([[1.0, 1.5, 2.0], [1.0, 1.5, 2.0]])
    out = stitch_segments(db, test, np.array([True, False]), np.array([0, 1]), chosen, times, blend_window=0.2)
    x = out.channels[:, 0]
    velocity, acceleration = steps(x, fps)
    assert np.abs(np.diff(x)).max() <= 1.0 / fps + 1e-9  # no position jump
    assert np.abs(np.diff(velocity)).max() < 0.025 * 2.0  # no velocity jump (a 2 rad/s step)
    assert velocity.max() <= 1.0 + 1e-9 and velocity.min() >= -1.0 - 1e-9  # never faster than either segment
    assert np.all(np.diff(velocity) <= 1e-9)  # 1 -> -1 monotonically
    assert np.abs(acceleration).max() <= 1.5 * 2.0 / 0.4 * 1.02
    np.testing.assert_allclose(out.windows, [[0.8, 1.2]])
    assert out.velocity_mismatch[0] == pytest.approx(np.degrees(2.0 * np.sqrt(3)), rel=1e-6)
    # the position crossfade over the same window overshoots the velocity and accelerates far harder
    fade = stitch_segments(
        db, test, np.array([True, False]), np.array([0, 1]), chosen, times, blend_window=0.2, smoothing="crossfade"
    ).channels[:, 0]
    fade_velocity, fade_acceleration = steps(fade, fps)
    assert fade_velocity.max() > 1.2 and np.abs(fade_acceleration).max() > 2 * np.abs(acceleration).max()


def test_velocity_blend_on_curves_is_c1_and_meets_both_segments_outside_the_window():
    fps = 100.0
    db = curve_database([lambda t: 0.3 * np.sin(2 * t), lambda t: 0.2 * np.cos(5 * t)], fps=fps)
    times = np.arange(0, 3.0, 1 / fps)
    test = np.array([[0.0, 1.0, 1.5], [1.5, 2.5, 3.0]])
    chosen = np.array([[1.0, 2.0, 2.5], [3.0, 4.0, 4.5]])
    out = stitch_segments(db, test, np.array([True, False]), np.array([0, 1]), chosen, times, blend_window=0.15)
    x = out.channels[:, 1]
    velocity, acceleration = steps(x, fps)
    hard = stitch_segments(db, test, np.array([True, False]), np.array([0, 1]), chosen, times, blend_window=0.0)
    hard_velocity, hard_acceleration = steps(hard.channels[:, 1], fps)
    assert np.abs(acceleration).max() < 0.2 * np.abs(hard_acceleration).max()
    # outside the window each segment moves with its own velocity
    before, after = times[1:] < 1.35, times[:-1] > 1.65
    np.testing.assert_allclose(velocity[before], hard_velocity[before], atol=1e-9)
    np.testing.assert_allclose(velocity[after], hard_velocity[after], atol=1e-9)


def test_a_segment_continued_by_its_database_successor_is_reproduced_exactly():
    """Consecutive database segments played at the same rate: every smoothing option gives back the recording."""
    fps = 100.0
    db = curve_database([lambda t: 0.3 * np.sin(2 * t) + 0.1 * np.sin(11 * t)], fps=fps)
    times = np.arange(0, 2.4, 1 / fps)
    test = np.array([[0.0, 0.3, 0.7], [0.7, 1.0, 1.3], [1.3, 1.9, 2.4]])
    chosen = test + 1.1  # the recording from 1.1 s on, in three pieces
    truth = db.sample(0, times + 1.1)
    for options in (
        {},
        {"acceleration_budget": 1.0, "max_blend_window": 0.5},
        {"preserve_speed": True},
        {"blend_window": 0.3, "preserve_speed": True, "acceleration_budget": 1.0},
    ):
        out = stitch_segments(db, test, np.array([True, False, False]), np.zeros(3, int), chosen, times, **options)
        np.testing.assert_allclose(out.channels, truth, atol=1e-9, err_msg=str(options))
        np.testing.assert_allclose(out.velocity_mismatch, 0.0, atol=1e-6)


def test_windows_widen_with_the_velocity_step_to_respect_the_acceleration_budget():
    joins = np.array([1.0, 2.0, 3.0])
    mismatch = np.array([0.0, 60.0, 600.0])  # deg/s
    left, right = join_windows(joins, np.full(3, 0.1), mismatch, acceleration_budget=100.0, max_half=0.5)
    half = (right - left) / 2
    assert half[0] == pytest.approx(0.1)  # no step: the minimum window
    assert half[1] == pytest.approx(0.75 * 60 / 100)  # 1.5 dv / (2 W) = budget
    assert half[2] == pytest.approx(0.5)  # capped
    fixed = join_windows(joins, np.full(3, 0.1), mismatch)  # no budget: fixed windows
    np.testing.assert_allclose(fixed[1] - fixed[0], 0.2)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(0.02, 0.6), min_size=2, max_size=8), st.lists(st.floats(0.0, 0.5), min_size=7, max_size=7))
def test_blend_weights_are_a_partition_of_unity_however_windows_overlap(lengths, halves):
    joins = np.cumsum(lengths)[:-1]
    half = np.array(halves[: len(joins)])
    left, right = join_windows(joins, half)
    assert np.all(left <= joins + 1e-12) and np.all(right >= joins - 1e-12)
    x = np.linspace(-1, joins[-1] + 1, 500)
    weights = np.stack([segment_weights(x, k, left, right, joins) for k in range(len(joins) + 1)])
    assert weights.min() >= 0 and weights.max() <= 1
    np.testing.assert_allclose(weights.sum(0), 1.0, atol=1e-12)


def test_every_sub_sentence_starts_at_its_recorded_pose_with_blended_joins():
    fps = 100.0
    db = curve_database([lambda t: 0.3 * np.sin(2 * t), lambda t: 0.5 + 0.2 * np.cos(3 * t)], fps=fps)
    times = np.arange(0, 3.0, 1 / fps)
    test = np.array([[0.0, 0.4, 0.8], [0.8, 1.2, 1.6], [1.6, 2.0, 2.3], [2.3, 2.6, 3.0]])
    sub = np.array([True, False, True, False])
    seqs = np.array([0, 1, 1, 0])
    chosen = np.array([[0.5, 0.9, 1.3], [2.0, 2.4, 2.8], [4.0, 4.4, 4.7], [1.0, 1.3, 1.7]])
    out = stitch_segments(db, test, sub, seqs, chosen, times, blend_window=0.15, break_blend_window=0.25)
    for k in (0, 2):
        recorded = db.sample(seqs[k], chosen[k, :1])[0]
        at = np.array([np.interp(test[k, 0], times, out.channels[:, c]) for c in range(6)])
        np.testing.assert_allclose(at, recorded, atol=1e-9)
    velocity, _ = steps(out.channels[:, 0], fps)
    assert np.abs(np.diff(velocity)).max() < 0.2  # no kink where the drift warps meet
    # the drift warp is a constant velocity within each sub-sentence: away from every window, the output moves
    # like its segment plus that constant
    drifting = stitch_segments(
        db, test, sub, seqs, chosen, times, blend_window=0.15, break_blend_window=0.25, drift_correction=False
    )
    inside = (times[1:] > 0.3) & (times[:-1] < 0.6)
    difference = np.diff(out.channels[:, 0] - drifting.channels[:, 0])[inside]
    np.testing.assert_allclose(difference, difference[0], atol=1e-12)


def test_speed_preserving_gain_keeps_the_speed_of_unrelated_segments():
    """Yaw moving at 1 rad/s joined to pitch moving at 1 rad/s: the plain velocity blend slows to 1/sqrt(2) at the
    join, the speed-preserving one keeps 1 rad/s throughout."""
    fps = 100.0
    n = 600
    t = np.arange(n) / fps
    yaw = np.zeros((n, 6))
    yaw[:, 0] = t
    pitch = np.zeros((n, 6))
    pitch[:, 1] = t
    db = DatabaseMotion(np.concatenate([yaw, pitch]), np.array([0, n]), np.array([n, n]), fps)
    times = np.arange(0, 2.0, 1 / fps)
    test = np.array([[0.0, 0.5, 1.0], [1.0, 1.5, 2.0]])
    chosen = np.array([[1.0, 1.5, 2.0], [1.0, 1.5, 2.0]])
    args = (db, test, np.array([True, False]), np.array([0, 1]), chosen, times)
    plain = np.linalg.norm(np.diff(stitch_segments(*args, blend_window=0.2).channels[:, :3], axis=0), axis=1) * fps
    kept = (
        np.linalg.norm(
            np.diff(stitch_segments(*args, blend_window=0.2, preserve_speed=True).channels[:, :3], axis=0), axis=1
        )
        * fps
    )
    assert plain.min() == pytest.approx(1 / np.sqrt(2), abs=0.01)
    np.testing.assert_allclose(kept, 1.0, atol=0.01)


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
    bumps[30:, 0] = 0.1 * (t[30:] - t[30])  # a velocity step at 1 s
    assert join_acceleration(bumps, fps, np.array([1.0, 0.3]), 0.1)[0] > 100
    assert join_acceleration(bumps, fps, np.array([1.0, 0.3]), 0.1)[1] == 0.0


# ---------------------------------------------------------------------------------------- the stage


def test_an_utterance_found_in_the_database_gets_its_own_motion_back(phrases, tracks):
    """The paper's settings (motion as recorded, uniform resampling, amplitude as recorded) give a take found in
    the database back exactly."""
    headdb = run_stage(TrackedHeadDb, {"mirror": False, "jitter_cutoff": None}, {"tracks": tracks})
    db_pitch = run_stage(Pitch, {}, {"source": headdb})
    test_tracks = tracking_artifact(phrases[3:4], fps=30.0)
    take_pitch = run_stage(Pitch, {}, {"source": test_tracks})
    tr = run_stage(Trellis, {}, {"database": headdb, "database_pitch": db_pitch, "test_pitch": take_pitch})
    paper = {"timing": "segment", "amplitude": "database", "output_cutoff": None}
    run = run_stage(MotionBlend, paper, {"trellis": tr, "database": headdb, "reference": test_tracks})
    real = reference_angles(test_tracks, phrases[3].label, 1, 30.0)
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
    np.testing.assert_allclose(
        np.abs(np.sum(joint_rotation(bvh, "Head") * run.arrays["rotation"], axis=1)), 1.0, atol=1e-9
    )
    np.testing.assert_allclose(joint_translation(bvh, "Head"), run.arrays["translation"], atol=1e-5)
    # joins sit at the test segments' starts
    seg = leave_one_out.arrays["segments"][leave_one_out.arrays["segment_utterance"] == 0]
    np.testing.assert_allclose(run.arrays["joins"][run.arrays["join_utterance"] == 0], seg[1:, 0])
    assert {"speed_wasserstein", "max_join_acceleration", "real_acceleration_p99"} <= set(run.metrics)


def test_leave_one_out_motion_is_plausible_and_smooth_at_joins(leave_one_out, database, tracks):
    """Velocity blending makes joins smoother than hard cuts and than the position crossfade, join by join (mean and
    90th percentile over the ~200 joins). Not by the single worst join: on this synthetic database it can fall on a
    head stroke of the database motion itself, where every variant accelerates alike (about 800-940 deg/s^2, the
    real motion's 99th percentile 832), so it measures the motion, not the join."""
    soft = run_stage(MotionBlend, {}, {"trellis": leave_one_out, "database": database[0]})
    hard = run_stage(
        MotionBlend,
        {"blend_window": 0.0, "break_blend_window": 0.0, "join_acceleration": 0.0},
        {"trellis": leave_one_out, "database": database[0]},
    )
    fade = run_stage(MotionBlend, {"join_smoothing": "crossfade"}, {"trellis": leave_one_out, "database": database[0]})
    smooth = accelerations_at_joins(soft.arrays, 30.0)
    assert smooth.max() == pytest.approx(soft.metrics["max_join_acceleration"])
    for rough in (accelerations_at_joins(hard.arrays, 30.0), accelerations_at_joins(fade.arrays, 30.0)):
        assert len(rough) == len(smooth) > 50
        assert smooth.mean() < 0.8 * rough.mean()
        assert np.percentile(smooth, 90) < 0.8 * np.percentile(rough, 90)
    assert smooth.max() <= hard.metrics["max_join_acceleration"]
    # windows are at least the minimum, wider where the velocity step is large
    widths = np.diff(soft.arrays["join_window"], axis=1)[:, 0]
    step = soft.arrays["join_velocity_step"]
    assert widths.min() >= 2 * 0.15 - 1e-9 and np.isfinite(step).all()
    assert np.median(widths[step > np.median(step)]) > np.median(widths[step <= np.median(step)])
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
    quiet = artifact(
        {"audio": audio, "audio_bounds": np.array([[0, 24000]])},
        {"labels": ["quiet"], "sources": ["quiet.wav"], "audio_rate": 16000},
    )
    pitch = stage_result(Pitch, {}, {"source": quiet})
    assert pitch.warnings and "no voiced speech in 'quiet'" in pitch.warnings[0]
    tr = run_stage(
        Trellis,
        {},
        {"database": database[0], "database_pitch": database[1], "test_pitch": artifact(pitch.arrays, pitch.meta)},
    )
    run = stage_result(MotionBlend, {}, {"trellis": tr, "database": database[0]})
    assert run.meta["frames"] == [45] and run.meta["fps"] == database[0].meta["fps"]
    np.testing.assert_allclose(run.arrays["rotation"], np.tile([1.0, 0, 0, 0], (45, 1)))
    assert len(run.arrays["joins"]) == 0
    assert run.warnings == ["'quiet' has no voiced speech: its head stays at the rest pose"]


@pytest.mark.parametrize(
    "params, field",
    [
        ({"join_acceleration": -1.0}, "join_acceleration"),
        ({"max_blend_window": -0.1}, "max_blend_window"),
        ({"blend_window": -0.1}, "blend_window"),
    ],
)
def test_bad_blend_settings_are_rejected_by_the_params(params, field):
    with pytest.raises(ValidationError) as err:
        MotionBlend.Params(**params)
    assert err.value.errors()[0]["loc"] == (field,)


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
    """The default pipeline's takes, tracked once per test session (face_fixtures)."""
    from face_fixtures import tracked, training_tracks

    return training_tracks(), tracked("sad")


def test_crema_d_end_to_end(crema):
    """The default pipeline's head branch on real data: three tracked takes in, the sad take's audio drives."""
    train, test = crema
    headdb = run_stage(TrackedHeadDb, {"speaker": "1001"}, {"tracks": train})
    db_pitch = run_stage(Pitch, {}, {"source": headdb})
    take_pitch = run_stage(Pitch, {}, {"source": test})
    tr = run_stage(Trellis, {}, {"database": headdb, "database_pitch": db_pitch, "test_pitch": take_pitch})
    run = run_stage(MotionBlend, {}, {"trellis": tr, "database": headdb, "reference": test})
    assert run.meta["fps"] == pytest.approx(test.meta["fps"][0])
    assert run.meta["frames"] == [len(test["rotation"])]
    angles = np.degrees(run.arrays["angles"])
    assert np.abs(angles).max() < 30
    # the synthesis moves, and not wildly faster than the real take
    assert (
        0.2 * run.metrics["real_mean_angular_speed"]
        < run.metrics["mean_angular_speed"]
        < 5 * run.metrics["real_mean_angular_speed"]
    )


# ------------------------------------------------------------------------------------ beyond the paper


def test_timing_knots_move_database_events_onto_test_events():
    from stages.head.stitching import segment_knots, warp_time

    # a 1 s test segment drawn from a 2 s database segment: uniform rate 2
    knots_t, knots_d = segment_knots(
        (10.0, 11.0), (4.0, 6.0), np.array([10.35, 10.8]), np.array([4.5, 5.9]), tolerance=0.15, max_stretch=2.0
    )
    # 4.5 would land at 10.25: moved onto 10.35; 5.9 would land at 10.95, next to 10.8: too fast a piece after it
    np.testing.assert_allclose(knots_t, [10.0, 10.35, 11.0])
    np.testing.assert_allclose(knots_d, [4.0, 4.5, 6.0])
    t = np.linspace(9.5, 11.5, 2001)
    for kind in ("monotone", "linear"):
        mapped = warp_time(t, knots_t, knots_d, kind)
        assert np.all(np.diff(mapped) > 0)  # monotone, continuous
        np.testing.assert_allclose(warp_time(np.array([10.0, 10.35, 11.0]), knots_t, knots_d, kind), [4.0, 4.5, 6.0])
    linear = warp_time(np.array([9.5, 11.5]), knots_t, knots_d, "linear")
    np.testing.assert_allclose(linear, [3.0, 7.0])  # beyond: the average rate
    # the monotone map's rate changes smoothly (the linear one steps from 500/350 to 1500/650 at 10.35) and goes on
    # beyond the ends at the end pieces' own rates
    rate = np.diff(warp_time(t, knots_t, knots_d)) / np.diff(t)
    assert np.abs(np.diff(rate)).max() < 0.01
    assert rate[0] == pytest.approx(0.5 / 0.35) and rate[-1] == pytest.approx(1.5 / 0.65)
    lin_rate = np.diff(warp_time(t, knots_t, knots_d, "linear")) / np.diff(t)
    assert np.abs(np.diff(lin_rate)).max() > 0.5
    # two knots: both maps are the uniform one
    np.testing.assert_allclose(warp_time(t, knots_t[[0, -1]], knots_d[[0, -1]]), 4.0 + (t - 10.0) * 2.0)
    far = segment_knots((10.0, 11.0), (4.0, 6.0), np.array([10.6]), np.array([4.5]), tolerance=0.15, max_stretch=2.0)
    np.testing.assert_allclose(far[0], [10.0, 11.0])  # 0.35 s away: left alone


def test_amplitude_gains_bring_every_speaker_to_the_target_spread():
    from stages.head.amplitude import amplitude_gains, amplitude_target, speaker_spreads

    t = np.linspace(0, 4 * np.pi, 400)
    quiet = np.repeat(np.sin(t)[:, None], 6, axis=1)
    channels = np.concatenate([quiet, 3 * quiet, 10 * quiet])
    db = DatabaseMotion(channels, np.array([0, 400, 800]), np.array([400, 400, 400]), 100.0, ["ann", "bob", "bob"])
    spreads = speaker_spreads(db)
    np.testing.assert_allclose(spreads["bob"] / spreads["ann"], 10.0 * np.ones(6), rtol=0.05)  # pooled: 10x wins p95
    np.testing.assert_allclose(amplitude_gains(db, spreads, amplitude_target(spreads, "ann"))[0], [1.0] * 6)
    # bob's third take held out (say, the test take): his target comes from his other take only
    held_out = speaker_spreads(db, np.array([True, True, False]))
    np.testing.assert_allclose(amplitude_target(held_out, "bob"), 3 * spreads["ann"])
    np.testing.assert_allclose(
        amplitude_gains(db, held_out, amplitude_target(held_out, "bob"))[:2], [[3.0] * 6, [1.0] * 6]
    )
    # a speaker the database does not know: the median speaker's spread
    np.testing.assert_allclose(amplitude_target(held_out, "cid"), 2 * spreads["ann"])
    scaled = db.scaled(amplitude_gains(db, held_out, amplitude_target(held_out, "cid")))
    spread = lambda x: np.percentile(x, 95, axis=0) - np.percentile(x, 5, axis=0)
    np.testing.assert_allclose(spread(scaled.channels[:400]), spread(scaled.channels[400:800]))


def test_per_angle_source_gains_bring_each_angle_to_the_target():
    """source_gain 'per_angle': a speaker moving (1, 2, 4) in (yaw, pitch, roll) brought to a target of (2, 2, 2)
    gets gains (2, 1, 0.5); the common gain (their geometric mean ratio) is 1 and keeps the proportions."""
    from stages.head.amplitude import amplitude_gains, speaker_spreads

    t = np.linspace(0, 4 * np.pi, 400)
    wave = np.sin(t)[:, None] * np.array([1.0, 2.0, 4.0, 1.0, 1.0, 1.0])
    db = DatabaseMotion(wave, np.array([0]), np.array([400]), 100.0, ["ann"])
    spreads = speaker_spreads(db)
    target = spreads["ann"] * np.array([2.0, 1.0, 0.5, 1.0, 1.0, 1.0])
    np.testing.assert_allclose(amplitude_gains(db, spreads, target, per_angle=True)[0], [2, 1, 0.5, 1, 1, 1])
    np.testing.assert_allclose(amplitude_gains(db, spreads, target)[0], [1.0] * 6)


def test_the_reference_target_can_come_from_an_enrolment_stretch():
    """reference_seconds: the target spread is that of the first seconds of the performer's take only."""
    from stages.head.amplitude import reference_spreads

    phrase = synth_database(1, seed=3)[0]
    tracks = tracking_artifact([phrase], fps=30.0)
    angles = reference_angles(tracks, phrase.label, 1, 30.0)
    first = angles[:30] - angles[:30].mean(axis=0)
    whole = angles - angles.mean(axis=0)
    spread = lambda a: (np.percentile(a, 95, axis=0) - np.percentile(a, 5, axis=0)).tolist()
    assert reference_spreads(tracks, [phrase.label], 30.0, 1.0)[0] == pytest.approx(spread(first))
    assert reference_spreads(tracks, [phrase.label], 30.0)[0] == pytest.approx(spread(whole))
    assert reference_spreads(tracks, ["elsewhere", phrase.label], 30.0)[0] is None


def test_matched_amplitude_is_centred_with_the_target_spread():
    from stages.head.amplitude import match_amplitude
    from stages.head.beats import kinematic_beats

    t = np.arange(600) / 30.0
    motion = np.zeros((600, 6))
    motion[:, 0] = 0.3 + 0.1 * np.sin(t)  # yaw: spread about 0.2, off the rest pose
    motion[:, 1] = 0.02 * np.sin(3 * t + 1)  # pitch: spread about 0.04
    spread = lambda x: np.percentile(x, 95, axis=0) - np.percentile(x, 5, axis=0)
    target = np.array([0.1, 0.08, 0.05, 1.0, 1.0, 1.0])
    out = match_amplitude(motion, target, max_gain=3.0)
    np.testing.assert_allclose(out.mean(axis=0), 0.0, atol=1e-12)  # on the rest pose
    # one gain for the angles, the geometric mean of yaw's and pitch's ratios (roll and translation do not move)
    ratios = target[:2] / spread(motion)[:2]
    np.testing.assert_allclose(spread(out)[:2], spread(motion)[:2] * np.sqrt(ratios.prod()))
    assert np.all(out[:, 2:] == 0.0)
    # a common gain keeps the head strokes (maxima of the angular speed) where they were
    np.testing.assert_array_equal(kinematic_beats(out[:, :3], 30.0), kinematic_beats(motion[:, :3], 30.0))
    # and it is limited: a motion far smaller than the target grows by max_gain only
    small = match_amplitude(0.01 * motion, target, max_gain=3.0)
    np.testing.assert_allclose(spread(small)[:2], 0.03 * spread(motion)[:2])


def test_the_amplitude_target_never_comes_from_the_held_out_take(phrases):
    """Leave one take out on a database where one take moves far more than its speaker's other takes: its matched
    synthesis moves about as much as the other takes (overall: the geometric mean of the three angles' spreads, the
    size a common gain sets), not like itself."""
    loud = [phrases[0].label]
    tracks = tracking_artifact(phrases[:8], fps=30.0)
    rotation = np.asarray(tracks["rotation"]).copy()
    sequence = np.asarray(tracks["sequence"])
    for k, label in enumerate(tracks.meta["labels"]):
        if label in loud:
            rotation[sequence == k, 1:] *= 8.0
    rotation /= np.linalg.norm(rotation, axis=1, keepdims=True)
    tracks = artifact({**{k: tracks[k] for k in tracks.names}, "rotation": rotation}, tracks.meta)
    headdb = run_stage(TrackedHeadDb, {}, {"tracks": tracks})
    db_pitch = run_stage(Pitch, {}, {"source": headdb})
    test_pitch = run_stage(Pitch, {}, {"source": tracks})
    inputs = {"database": headdb, "database_pitch": db_pitch, "test_pitch": test_pitch}
    tr = run_stage(Trellis, {"holdout": "take", "test_speaker": "own"}, inputs)
    run = run_stage(MotionBlend, {"amplitude": "match"}, {"trellis": tr, "database": headdb})
    spread = lambda a: np.prod(np.percentile(a, 95, axis=0)[:3] - np.percentile(a, 5, axis=0)[:3]) ** (1 / 3)
    angles, seq = run.arrays["angles"], run.arrays["sequence"]
    quiet_real = spread(np.concatenate([reference_angles(tracks, x, 8, 30.0) for x in tracks.meta["labels"][1:]]))
    loud_real = spread(reference_angles(tracks, loud[0], 8, 30.0))
    assert loud_real > 3 * quiet_real
    assert spread(angles[seq == 0]) == pytest.approx(quiet_real, rel=0.1)


def each_take_searched_without_itself(tracks):
    """The head database of ``tracks`` and the trellis that searches it for each of its takes, leaving the take
    itself out (every take labelled as the database's speaker)."""
    headdb = run_stage(TrackedHeadDb, {}, {"tracks": tracks})
    inputs = {
        "database": headdb,
        "database_pitch": run_stage(Pitch, {}, {"source": headdb}),
        "test_pitch": run_stage(Pitch, {}, {"source": tracks}),
    }
    return headdb, run_stage(Trellis, {"holdout": "take", "test_speaker": "own"}, inputs)


def test_the_amplitude_target_from_the_reference_is_the_performers_own(phrases):
    """``amplitude_target="reference"``: a performer the database does not know (held out, moving 8x more than
    every database take) gets its own amplitude, read from its tracked take, not the database's; a take missing
    from the reference keeps the database's, with a warning."""
    tracks = tracking_artifact(phrases[:8], fps=30.0)
    rotation = np.asarray(tracks["rotation"]).copy()
    loud = np.asarray(tracks["sequence"]) == 0
    rotation[loud, 1:] *= 8.0
    rotation /= np.linalg.norm(rotation, axis=1, keepdims=True)
    tracks = artifact({**{k: tracks[k] for k in tracks.names}, "rotation": rotation}, tracks.meta)
    headdb, tr = each_take_searched_without_itself(tracks)
    spread = lambda a: np.prod(np.percentile(a, 95, axis=0)[:3] - np.percentile(a, 5, axis=0)[:3]) ** (1 / 3)
    loud_real = spread(reference_angles(tracks, tracks.meta["labels"][0], 8, 30.0))
    params = {"amplitude": "match", "amplitude_target": "reference"}
    run = stage_result(MotionBlend, params, {"trellis": tr, "database": headdb, "reference": tracks})
    angles, seq = run.arrays["angles"], run.arrays["sequence"]
    assert spread(angles[seq == 0]) == pytest.approx(loud_real, rel=0.1)
    assert run.meta["stitch"]["targets"][0] == pytest.approx(
        list(np.percentile(reference_angles(tracks, tracks.meta["labels"][0], 8, 30.0), 95, axis=0)
             - np.percentile(reference_angles(tracks, tracks.meta["labels"][0], 8, 30.0), 5, axis=0))
    )  # fmt: skip
    default = run_stage(MotionBlend, {"amplitude": "match"}, {"trellis": tr, "database": headdb, "reference": tracks})
    assert spread(default.arrays["angles"][default.arrays["sequence"] == 0]) < loud_real / 3
    partial = artifact({**{k: tracks[k] for k in tracks.names}}, {**tracks.meta, "labels": ["other"] * 8})
    missing = stage_result(MotionBlend, params, {"trellis": tr, "database": headdb, "reference": partial})
    assert any("is not in the reference" in w for w in missing.warnings)
    np.testing.assert_allclose(missing.arrays["angles"], default.arrays["angles"])


def test_the_mirror_image_is_the_head_motion_seen_in_a_mirror_and_turns_it_to_the_targets_side():
    """MIRROR negates yaw, roll and the sideways translation: the rotation seen in a mirror (M R M with M =
    diag(-1, 1, 1)). ``mirrored_to_side`` mirrors a motion that turns mostly one way when the target turns mostly
    the other, keeps it when the target turns its way, and changes no angular speed."""
    from scipy.spatial.transform import Rotation

    from stages.head.amplitude import MIRROR, mirrored_to_side
    from stages.head.measures import angular_speed

    t = np.arange(600) / 30.0
    motion = np.zeros((600, 6))
    motion[:, 0] = -0.2 * np.sin(1.3 * t) ** 4  # yaw: mostly at rest, turns to one side only
    motion[:, 1] = 0.05 * np.sin(2.1 * t)
    motion[:, 2] = -0.05 * np.sin(0.9 * t + 1) ** 4  # roll: one side only
    motion[:, 3:] = np.column_stack([np.sin(t), np.cos(t), 0.5 * np.sin(2 * t)])
    matrix = lambda a: Rotation.from_euler("YXZ", a[:, :3]).as_matrix()
    flip = np.diag([-1.0, 1.0, 1.0])
    np.testing.assert_allclose(matrix(motion * MIRROR), flip @ matrix(motion) @ flip, atol=1e-12)

    def sides(m):
        return np.percentile(m[:, :3] - m[:, :3].mean(axis=0), [5, 95], axis=0).tolist()

    np.testing.assert_array_equal(mirrored_to_side(motion, sides(motion * MIRROR)), motion * MIRROR)
    np.testing.assert_array_equal(mirrored_to_side(motion, sides(motion)), motion)
    np.testing.assert_allclose(angular_speed(motion * MIRROR, 30.0), angular_speed(motion, 30.0), atol=1e-9)


def test_the_output_turns_to_the_performers_side(phrases):
    """``side="performer"`` (the default) with the performer's own amplitude: the same performer filmed in a
    mirror (yaw and roll negated) gets the mirror image of the motion, so the head turns the way the performer's
    does; ``side="as_stitched"`` gives both the same motion (their spreads are equal)."""
    from stages.geometry.rotations import euler_to_quat, quat_to_euler

    tracks = tracking_artifact(phrases[:8], fps=30.0)
    angles = quat_to_euler(np.asarray(tracks["rotation"]))
    mirrored = artifact(
        {**{k: tracks[k] for k in tracks.names}, "rotation": euler_to_quat(-angles[:, 0], angles[:, 1], -angles[:, 2])},
        tracks.meta,
    )
    headdb, tr = each_take_searched_without_itself(tracks)
    runs = {}
    for side in ("performer", "as_stitched"):
        params = {"amplitude": "match", "amplitude_target": "reference", "side": side}
        for name, reference in (("as filmed", tracks), ("mirrored", mirrored)):
            runs[side, name] = run_stage(
                MotionBlend, params, {"trellis": tr, "database": headdb, "reference": reference}
            )
    filmed, seen = runs["performer", "as filmed"].arrays, runs["performer", "mirrored"].arrays
    assert np.abs(filmed["angles"][:, 0]).max() > 0.01
    np.testing.assert_allclose(seen["angles"], filmed["angles"] * [-1, 1, -1], atol=1e-9)
    np.testing.assert_allclose(seen["translation"], filmed["translation"] * [-1, 1, 1], atol=1e-9)
    np.testing.assert_allclose(
        runs["as_stitched", "mirrored"].arrays["angles"], runs["as_stitched", "as filmed"].arrays["angles"], atol=1e-9
    )


def test_the_automatic_amplitude_target_reads_only_performers_the_database_does_not_know(phrases):
    """``amplitude_target="auto"`` (the default): a performer the database does not know (moving 8x more than the
    database's speaker) gets its own amplitude from its tracked take, each angle its own (``source_gain="auto"``:
    per angle where the target is the performer's), and so does an unlabelled one; the same take labelled as the
    database's speaker gets that speaker's amplitude from the database."""
    from stages.head.amplitude import knows_speaker

    spread = lambda a: np.prod(np.percentile(a, 95, axis=0)[:3] - np.percentile(a, 5, axis=0)[:3]) ** (1 / 3)
    headdb = run_stage(TrackedHeadDb, {}, {"tracks": tracking_artifact(phrases[8:16], fps=30.0, speaker="ann")})
    db_pitch = run_stage(Pitch, {}, {"source": headdb})

    def first_take(speaker, gains=(8.0, 8.0, 8.0), **params):
        """The synthesis of the first of two test takes whose quaternion's vector part is scaled by ``gains``,
        and its real motion."""
        tracks = tracking_artifact(phrases[:2], fps=30.0, speaker=speaker)
        rotation = np.asarray(tracks["rotation"]).copy()
        rotation[:, 1:] *= gains
        rotation /= np.linalg.norm(rotation, axis=1, keepdims=True)
        tracks = artifact({**{k: tracks[k] for k in tracks.names}, "rotation": rotation}, tracks.meta)
        pitch = run_stage(Pitch, {"median_over": "utterance"} if speaker is None else {}, {"source": tracks})
        inputs = {"database": headdb, "database_pitch": db_pitch, "test_pitch": pitch}
        tr = run_stage(Trellis, {"test_speaker": "own"}, inputs)
        run = run_stage(
            MotionBlend, {"amplitude": "match", **params}, {"trellis": tr, "database": headdb, "reference": tracks}
        )
        return run.arrays["angles"][run.arrays["sequence"] == 0], reference_angles(
            tracks, tracks.meta["labels"][0], 2, 30.0
        )

    def first_take_spread(speaker, **params):
        return tuple(spread(a) for a in first_take(speaker, **params))

    synth, real = first_take_spread("ben")
    assert synth == pytest.approx(real, rel=0.1)
    assert first_take_spread("ben", amplitude_target="database")[0] < real / 3
    known, _ = first_take_spread("ann")
    assert known < real / 3
    assert known == pytest.approx(first_take_spread("ann", amplitude_target="database")[0])
    assert first_take_spread(None)[0] == pytest.approx(real, rel=0.1)
    # the performer's own proportions between the angles (one angle 8x, the others as recorded): per angle
    spans = lambda a: np.percentile(a, 95, axis=0)[:3] - np.percentile(a, 5, axis=0)[:3]
    synth, real = first_take("ben", gains=(8.0, 1.0, 1.0))
    # refine_proportions (the default) stitches again with the gains corrected by the first output's proportions:
    # every angle then lands near the performer's; stitched once, blending left one angle 2x off
    np.testing.assert_allclose(spans(synth), spans(real), rtol=0.2)
    once, _ = first_take("ben", gains=(8.0, 1.0, 1.0), refine_proportions=False)
    assert np.max(np.abs(np.log(spans(once) / spans(real)))) > np.log(1.5)
    common, _ = first_take("ben", gains=(8.0, 1.0, 1.0), source_gain="common")
    proportion = lambda a: spans(a)[1] / spans(a)[0]  # the angle made 8x larger over another one
    assert proportion(real) > 2
    assert proportion(synth) == pytest.approx(proportion(real), rel=0.25)
    assert proportion(common) < proportion(real) / 2
    assert knows_speaker({"ann": 1, "ben": 2}, "ann") and not knows_speaker({"ann": 1}, "ben")
    assert not knows_speaker({"ann": 1}, None) and not knows_speaker({None: 1}, None)


def test_a_reference_amplitude_target_needs_scaling_and_a_reference(leave_one_out, database):
    with pytest.raises(ValidationError, match="amplitude_target"):
        MotionBlend.Params(amplitude="database", amplitude_target="reference")
    with pytest.raises(UserError, match="reference input") as err:
        stage_result(
            MotionBlend, {"amplitude_target": "reference"}, {"trellis": leave_one_out, "database": database[0]}
        )
    assert err.value.field == "inputs.reference"


def test_output_filter_keeps_strokes_and_removes_sped_up_peaks():
    """The output low-pass passes a 1.5 Hz nod unchanged in size and timing and removes an 8 Hz wobble (a 3 Hz
    nod played 2.7x faster); at or above the Nyquist rate it leaves the motion alone."""
    from stages.head.motion_blend import lowpass_channels

    fps = 30.0
    t = np.arange(300) / fps
    nod = np.radians(5.0) * np.sin(2 * np.pi * 1.5 * t)
    wobble = np.radians(1.0) * np.sin(2 * np.pi * 8.0 * t + 0.3)
    channels = np.zeros((len(t), 6))
    channels[:, 1] = nod + wobble
    out = lowpass_channels(channels, fps, 4.0)
    inner = slice(30, -30)  # away from the ends, where the filter starts up
    np.testing.assert_allclose(out[inner, 1], nod[inner], atol=np.radians(0.1))  # 8 Hz: gain 1 / (1 + 2^8)
    assert np.abs(out[:, [0, 2, 3, 4, 5]]).max() == 0.0
    np.testing.assert_array_equal(lowpass_channels(channels, 6.0, 4.0), channels)
    with pytest.raises(ValidationError):
        MotionBlend.Params(output_cutoff=0)


def test_rest_anchor_removes_slow_wander(leave_one_out, database):
    plain = run_stage(MotionBlend, {}, {"trellis": leave_one_out, "database": database[0]})
    anchored = run_stage(MotionBlend, {"rest_anchor": 1.0}, {"trellis": leave_one_out, "database": database[0]})
    from scipy.ndimage import gaussian_filter1d

    slow = lambda run: np.abs(gaussian_filter1d(run.arrays["angles"], 60, axis=0)).mean()
    assert slow(anchored) < 0.5 * slow(plain)
    assert anchored.meta["stitch"]["rest_anchor"] == 1.0


def test_stroke_timing_puts_head_strokes_on_the_test_onsets():
    """A database take whose nods stroke at known times, played onto a test segment of the same length whose
    onsets come 0.1 s later: uniform resampling keeps the strokes 0.1 s early, the stroke timing moves them on."""
    from scipy.special import erf

    from stages.head.beats import beat_alignment, kinematic_beats
    from stages.head.motion_blend import database_events, utterance_time_maps

    fps = 100.0
    t = np.arange(600) / fps
    strokes = np.array([0.8, 1.6, 2.5, 3.3, 4.2, 5.0])
    nod = sum(0.05 * (1 + erf((t - s) / (np.sqrt(2) * 0.06))) * (-1) ** k for k, s in enumerate(strokes))
    channels = np.zeros((600, 6))
    channels[:, 1] = nod
    db = DatabaseMotion(channels, np.array([0]), np.array([600]), fps)
    segment = np.array([[0.0, 5.0, 5.99]])
    onsets = strokes + 0.1
    events = database_events(None, db, "strokes")
    np.testing.assert_allclose(events[0], strokes, atol=0.011)
    maps = utterance_time_maps(segment, segment, np.array([0]), onsets, events, 0.15, 2.0)
    times = np.arange(599) / fps
    uniform = stitch_segments(db, segment, np.array([True]), np.array([0]), segment, times)
    timed = stitch_segments(db, segment, np.array([True]), np.array([0]), segment, times, time_maps=maps)
    score = lambda run: beat_alignment(kinematic_beats(run.channels[:, :3], fps, smoothing=0.02), onsets, 0.05)
    assert score(uniform) == pytest.approx(np.exp(-2.0), abs=0.05)  # 0.1 s off at sigma 0.05 s
    assert score(timed) > 0.95


def test_an_audio_file_alone_drives_the_synthesis(phrases, database, tmp_path):
    """A test take with no video (an audio file only): pitch from the file, motion at the database's rate."""
    from stages.head.praat_files import wav_bytes

    wav = tmp_path / "line.wav"
    wav.write_bytes(wav_bytes(phrases[0].audio, phrases[0].audio_rate))
    pitch = run_stage(Pitch, {}, {"audio": {"line": {"path": wav, "speaker": "synthetic"}}})
    tr = run_stage(Trellis, {}, {"database": database[0], "database_pitch": database[1], "test_pitch": pitch})
    run = run_stage(MotionBlend, {}, {"trellis": tr, "database": database[0]})
    assert run.meta["fps"] == database[0].meta["fps"] and run.meta["labels"] == ["line"]
    assert run.meta["frames"] == [int(round(phrases[0].duration * run.meta["fps"]))]
    assert np.ptp(run.arrays["angles"], axis=0).max() > 0  # it moves
