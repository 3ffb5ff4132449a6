"""Head-motion evaluation: beats and beat alignment with known answers, the evaluation stage on synthetic takes
whose answer is known, and the evaluation pipeline on the embedded CREMA-D takes from a fresh copy."""

from pathlib import Path

import numpy as np
import pytest
from conftest import copy_project
from head_synthetic import pitch_driven, synth_database, tracking_artifact
from pydantic import ValidationError

from msflow import UserError
from msflow.testing import artifact, prepare_inputs, run_stage
from stages.eval.head import (
    MOTIONS,
    HeadMotionEval,
    bootstrap_ratio,
    evaluation_windows,
    phase_randomised,
    reflect_index,
    scored_windows,
    shifted_motion,
)
from stages.head.beats import (
    audio_onsets,
    beat_alignment,
    chance_alignment,
    kinematic_beats,
    nearest_distance,
    pitch_accents,
)
from stages.head.database import TrackedHeadDb
from stages.head.measures import angular_speed, linear_drift, percentile_range, reference_angles
from stages.head.motion_blend import MotionBlend
from stages.head.pitch import Pitch
from stages.head.trellis import Trellis

ROOT = Path(__file__).resolve().parents[1]
FPS = 30.0


def strokes(times: np.ndarray, seconds: float, fps: float = FPS, width: float = 0.08) -> np.ndarray:
    """Head motion (frames, 3) made of nods whose angular speed peaks exactly at ``times``: the head pitch angle
    is a sum of smooth steps, each the integral of a Gaussian velocity pulse centred on one time."""
    from scipy.special import erf

    t = np.arange(int(round(seconds * fps))) / fps
    sign = np.where(np.arange(len(times)) % 2 == 0, 1.0, -1.0)  # nod down, then up: the head stays near rest
    pitch = (sign[:, None] * 0.05 * (1 + erf((t[None, :] - times[:, None]) / (np.sqrt(2) * width)))).sum(axis=0)
    return np.stack([np.zeros_like(t), pitch, np.zeros_like(t)], axis=1)


# ------------------------------------------------------------------------------------------------ beats


def test_head_beats_on_the_audio_beats_score_one():
    onsets = np.arange(1, 20) * 0.5 + 0.1
    motion = strokes(onsets, 10.4)
    beats = kinematic_beats(motion, FPS, kind="peaks", smoothing=0.05)
    np.testing.assert_allclose(beats, onsets, atol=0.5 / FPS)
    assert beat_alignment(beats, onsets, 0.1) > 0.99
    # the stops fall halfway between the strokes, as far from the onsets as they can be
    stops = kinematic_beats(motion, FPS, kind="minima", smoothing=0.05)
    assert beat_alignment(stops, onsets, 0.1) < 0.1  # exp(-(0.25 / 0.1)^2 / 2) = 0.044 at exactly halfway


def test_head_beats_at_a_random_phase_score_chance():
    period, sigma = 0.5, 0.1
    onsets = np.arange(0, 60, period)
    scores = []
    for phase in (np.arange(400) + 0.5) / 400 * period:  # uniform phases, evenly spread
        beats = np.arange(1, 100) * period + phase
        scores.append(beat_alignment(beats, onsets, sigma))
    assert np.mean(scores) == pytest.approx(chance_alignment(period, sigma), abs=1e-3)
    assert 0.4 < chance_alignment(period, sigma) < 0.6


def test_phase_shifted_motion_loses_its_alignment_with_the_shift():
    """The same nods, exactly on the onsets and then shifted in time: the score falls as exp(-d^2 / 2 sigma^2)
    with the shift d while it is under half the onset period, and the aligned motion beats every shifted copy."""
    period, sigma = 0.5, 0.1
    onsets = np.arange(1, 20) * period + 0.1
    score = lambda shift: beat_alignment(
        kinematic_beats(strokes(onsets + shift, 10.4), FPS, smoothing=0.05), onsets, sigma
    )
    aligned = score(0.0)
    for frames in (2, 4, 6):  # shifts of whole frames, so the beats land exactly on the shifted times
        shift = frames / FPS
        assert score(shift) == pytest.approx(np.exp(-(shift**2) / (2 * sigma**2)), abs=0.02)
        assert score(shift) < aligned
    assert aligned > 0.99 and score(period / 2) < 0.1


def test_beat_alignment_edge_cases():
    assert beat_alignment(np.zeros(0), np.array([1.0]), 0.1) == 0.0  # a still head aligns with nothing
    assert beat_alignment(np.array([1.0]), np.zeros(0), 0.1) == 0.0
    np.testing.assert_allclose(nearest_distance(np.array([0.0, 1.2, 5.0]), np.array([1.0, 2.0])), [1.0, 0.2, 3.0])
    still = np.zeros((60, 3))
    assert len(kinematic_beats(still, FPS)) == 0


def test_audio_onsets_at_tone_bursts():
    rate = 16000
    truth = np.array([0.3, 0.9, 1.4, 2.2, 2.7])
    t = np.arange(int(3.2 * rate)) / rate
    audio = 1e-4 * np.random.default_rng(0).standard_normal(len(t))
    for start in truth:
        inside = (t >= start) & (t < start + 0.2)
        audio[inside] += 0.5 * np.sin(2 * np.pi * 180 * t[inside]) * np.hanning(inside.sum())
    found = audio_onsets(audio.astype(np.float32), rate, offset=0.5, delta=0.15, min_gap=0.25)
    assert len(found) == len(truth)
    np.testing.assert_allclose(found, truth + 0.5, atol=0.04)  # on the sequence clock


def test_pitch_accents_at_the_contour_peaks():
    times = np.arange(200) * 0.01
    st = 3 * np.sin(2 * np.pi * times)  # peaks at 0.25 s and 1.25 s
    st[90:110] = np.nan  # an unvoiced gap splits the runs
    np.testing.assert_allclose(pitch_accents(times, st, prominence=1.0), [0.25, 1.25], atol=0.011)
    assert len(pitch_accents(times, st, prominence=10.0)) == 0


# ---------------------------------------------------------------------------------------- the helpers


def test_windows_baselines_and_pooling():
    assert evaluation_windows(300, 30.0, 3.4) == [(0, 100), (100, 200), (200, 300)]
    assert evaluation_windows(50, 30.0, 10.0) == [(0, 50)]
    # scored from skip_seconds on: the windows of the rest, at their place in the take; none when nothing is left
    assert scored_windows(300, 30.0, 3.4, 0.0) == evaluation_windows(300, 30.0, 3.4)
    assert scored_windows(300, 30.0, 3.4, 5.0) == [(150, 300)]
    assert scored_windows(300, 30.0, 3.4, 10.0) == []
    np.testing.assert_array_equal(reflect_index(np.arange(-2, 8), 4), [2, 1, 0, 1, 2, 3, 2, 1, 0, 1])
    rng = np.random.default_rng(0)
    motion = np.cumsum(rng.standard_normal((300, 3)) * 0.01, axis=0)
    shifted = shifted_motion(motion, 30.0, 1.0, rng)
    assert {tuple(row) for row in shifted} <= {tuple(row) for row in motion}  # frames of the real motion
    assert np.abs(np.diff(shifted, axis=0)).max() <= np.abs(np.diff(motion, axis=0)).max() + 1e-12  # no jump
    noise = phase_randomised(motion, rng)
    np.testing.assert_allclose(
        np.abs(np.fft.rfft(noise - noise[:1], axis=0))[1:20].sum(),
        np.abs(np.fft.rfft(motion - motion[:1], axis=0))[1:20].sum(),
        rtol=0.3,
    )
    groups = np.repeat(np.arange(5), 2)
    estimate, lo, hi = bootstrap_ratio(np.full(10, 0.5), np.full(10, 1.0), np.zeros(10), groups, 200, rng)
    assert estimate == 0.5 and lo == 0.5 and hi == 0.5
    assert linear_drift(np.stack([np.radians(np.arange(31.0)), np.zeros(31), np.zeros(31)], axis=1), 30.0) == (
        pytest.approx(30.0)
    )
    np.testing.assert_allclose(percentile_range(np.radians(np.tile(np.arange(101.0)[:, None], 3))), [[5] * 3, [95] * 3])


def test_range_fit_cannot_be_met_by_shrinking_the_motion():
    from stages.eval.head import halves_range_fit, range_fit

    t = np.arange(3000) / 30.0
    real = np.radians(np.stack([8 * np.sin(1.3 * t), 4 * np.sin(0.7 * t + 1), 3 * np.sin(2.1 * t + 2)], axis=1))
    r = percentile_range(real)
    fit = lambda motion: range_fit(percentile_range(motion), r, 1.5, 0.25)
    assert fit(real).all() and fit(0.7 * real).all() and fit(1.4 * real).all()  # within the span tolerance
    assert not fit(0.5 * real).any() and not fit(np.zeros_like(real)).any()  # shrunk or still: inside, but too small
    assert not fit(1.6 * real).any()  # too large
    offset = real + np.radians([5.0, 0.0, 0.0])  # off-centre by more than a quarter of the yaw's 16 degree span
    np.testing.assert_array_equal(fit(offset), [False, True, True])
    np.testing.assert_array_equal(halves_range_fit(real, 1.5, 0.25), [1.0, 1.0, 1.0])  # a stationary motion
    calm_then_wild = np.concatenate([real, 3 * real])
    np.testing.assert_array_equal(halves_range_fit(calm_then_wild, 1.5, 0.25), [0.0, 0.0, 0.0])


def test_the_jitter_free_yardstick_is_below_the_raw_one():
    from stages.eval.head import Take, speaker_acceleration_p99

    fps, t = 30.0, np.arange(900) / 30.0
    rng = np.random.default_rng(1)
    nod = np.stack([np.zeros_like(t), np.radians(5) * np.sin(2 * np.pi * 0.8 * t), np.zeros_like(t)], axis=1)
    noisy = nod + np.radians(0.3) * rng.standard_normal(nod.shape)
    take = Take("a", "ann", fps, noisy, noisy, np.zeros(0), np.zeros(0), np.zeros(0), np.ones(1, bool))
    raw, band = speaker_acceleration_p99([take])["ann"], speaker_acceleration_p99([take], 5.0)["ann"]
    # the nod alone: peak acceleration 5 (2 pi 0.8)^2 = 126 deg/s^2; white jitter of 0.3 degree adds thousands
    assert raw > 1000 and 80 < band < 400


# ------------------------------------------------------------------------------------------ the stage


def synthesis(tracks, *, holdout: str, mirror: bool = True, timing: str = "strokes", **blend):
    """The head branch on ``tracks`` as the evaluation pipeline runs it; ``timing="segment"`` with ``paper=True``
    in ``blend`` is the paper's (motion and amplitude as recorded, uniform resampling)."""
    paper = blend.pop("paper", False)
    db_params = {"mirror": mirror, **({"jitter_cutoff": None} if paper else {})}
    blend = {"timing": timing, **({"amplitude": "database", "output_cutoff": None} if paper else {}), **blend}
    headdb = run_stage(TrackedHeadDb, db_params, {"tracks": tracks})
    db_pitch = run_stage(Pitch, {}, {"source": headdb})
    test_pitch = run_stage(Pitch, {}, {"source": tracks})
    trellis = run_stage(
        Trellis,
        {"holdout": holdout, "test_speaker": "own"},
        {"database": headdb, "database_pitch": db_pitch, "test_pitch": test_pitch},
    )
    blend = run_stage(MotionBlend, blend, {"trellis": trellis, "database": headdb, "reference": tracks})
    inputs = {"synthesis": blend, "trellis": trellis, "database": headdb, "reference": tracks, "test_pitch": test_pitch}
    return inputs


def evaluate(inputs, **params):
    params = {"draws": 4, "bootstrap": 200, **params}
    return HeadMotionEval("evaluate").run(HeadMotionEval.Params(**params), prepare_inputs(HeadMotionEval, inputs))


@pytest.fixture(scope="module")
def phrases():
    return synth_database(12, seed=5)


def test_a_synthesis_equal_to_the_real_motion_scores_as_the_real_motion(phrases):
    # every take finds itself, and the paper's uniform resampling plays it back unchanged
    inputs = synthesis(tracking_artifact(phrases), holdout="none", mirror=False, timing="segment", paper=True)
    result = evaluate(inputs)
    m = result.metrics
    assert m["ba_synth"] == m["ba_real"] and m["ba_accent_synth"] == m["ba_accent_real"]
    assert m["ba_rel"] == pytest.approx(1.0) and m["ba_synth_over_real"] == pytest.approx(1.0)
    assert m["win_synth_random"] == m["win_real_random"]
    assert m["speed_w1_synth"] == pytest.approx(0.0, abs=1e-9) and m["amplitude_synth"] == pytest.approx(1.0)
    assert m["range_ok_synth"] == 1.0 and m["drift_synth"] == pytest.approx(m["drift_real"])
    assert m["range_fit_synth"] == 1.0 and m["range_fit_real"] == 1.0 and m["range_fit_still"] == 0.0
    assert m["corr_synth"] == pytest.approx(1.0) and abs(m["corr_random"]) < 0.3
    # the baselines are not the real motion, and a still head has no beats
    assert m["speed_w1_random"] > 1.0 and m["speed_w1_noise"] > 0.1 and m["ba_still"] == 0.0
    assert m["amplitude_still"] < 0.05 and m["utterances"] == m["takes"] == len(phrases)
    assert result.arrays["beat_align_onset"].shape == (len(phrases), len(MOTIONS))
    assert any("held nothing out" in w for w in result.warnings)


def test_a_database_whose_motion_is_a_function_of_pitch_gives_it_back(phrases):
    """Head pitch = 1.5 deg per semitone of the voice: the synthesis of a held-out take follows its own audio's
    function; random paths through the same database do not."""
    from stages.eval.head import random_path_trellis
    from stages.head.motion_blend import database_motion, synthesise

    tracks = tracking_artifact(pitch_driven(phrases))
    inputs = synthesis(tracks, holdout="take")
    blend, trellis = inputs["synthesis"], inputs["trellis"]
    labels = trellis.meta["labels"]
    db = database_motion(inputs["database"].view())
    allowed = [np.array([x not in ex for x in trellis.meta["db_labels"]]) for ex in trellis.meta["excluded"]]
    rng = np.random.default_rng(0)
    random = synthesise(random_path_trellis(trellis.view(), allowed, rng), db, 30.0, **blend.meta["stitch"])
    found, chance = [], []
    for u, label in enumerate(labels):
        truth = reference_angles(tracks, label, len(labels), 30.0)[:, 1]
        synth = blend.arrays["angles"][blend.arrays["sequence"] == u][:, 1]
        n = min(len(truth), len(synth))
        found.append(np.corrcoef(truth[:n], synth[:n])[0, 1])
        chance.append(np.corrcoef(truth[:n], random[u].channels[:n, 1])[0, 1])
    assert np.mean(found) > 0.5 and np.mean(chance) < 0.25
    assert np.mean(found) > np.mean(chance) + 0.4


def test_the_evaluation_pipeline_on_crema_d_from_a_fresh_copy(tmp_path):
    """eval/head.yaml as shipped, on the embedded takes: real motion is better timed to the voice than the same
    motion shifted (the calibration every beat-alignment figure rests on), and every metric is there."""
    import msflow

    project = copy_project(tmp_path / "project", names=("eval", "data", "stages", "pyproject.toml"))
    run = msflow.run(project / "eval" / "head.yaml", overrides=["evaluate.draws=5"])
    view = run.artifact("evaluate")
    m = view.metrics
    assert m["takes"] == 6 and m["utterances"] == 6 and view.meta["speakers"] == ["1001"] * 6
    assert m["ba_real"] > m["ba_shifted"] and m["z_real_shifted"] > 1.0
    assert {f"ba_{x}" for x in MOTIONS} | {"ba_rel", "ba_rel_lo", "ba_rel_hi", "join_acc_max", "drift_synth"} <= set(m)
    assert run.artifact("trellis").meta["holdout"] == "take"
    from msflow.summary import summary_lines

    patterns = list(run.session.pipeline.summary)  # what `msflow run` ends with: every entry a metric it gave
    lines, warnings = summary_lines(patterns, run.record["stages"])
    assert patterns and warnings == [] and len(lines) == len(patterns)


# ------------------------------------------------------------------------------------------ bad input


def test_mismatched_inputs_are_user_errors(phrases):
    inputs = synthesis(tracking_artifact(phrases[:6]), holdout="take")
    other = synthesis(tracking_artifact(phrases[6:]), holdout="take")
    with pytest.raises(UserError, match="labels differ") as err:
        evaluate({**inputs, "synthesis": other["synthesis"]})
    assert err.value.field == "inputs.synthesis"
    with pytest.raises(UserError, match="different database"):
        evaluate({**inputs, "database": other["database"]})
    keep = ("rotation", "translation", "time", "sequence")
    no_audio = artifact({k: inputs["reference"][k] for k in keep}, inputs["reference"].meta)
    with pytest.raises(UserError, match="no audio"):
        evaluate({**inputs, "reference": no_audio})


@pytest.mark.parametrize("params", [{"window": 0}, {"draws": 0}, {"sigma": -1}, {"head_beats": "valleys"}])
def test_bad_settings_are_rejected_by_the_params(params):
    with pytest.raises(ValidationError):
        HeadMotionEval.Params(**params)


def test_holdout_speaker_needs_labels_and_another_speaker(phrases):
    unlabelled = tracking_artifact(phrases[:4], speaker=None)
    headdb = run_stage(TrackedHeadDb, {"speaker": "ann"}, {"tracks": unlabelled})
    db_pitch = run_stage(Pitch, {}, {"source": headdb})
    test_pitch = run_stage(Pitch, {"median_over": "utterance"}, {"source": unlabelled})
    inputs = {"database": headdb, "database_pitch": db_pitch, "test_pitch": test_pitch}
    with pytest.raises(UserError, match="no speaker label") as err:
        run_stage(Trellis, {"holdout": "speaker", "test_speaker": "own"}, inputs)
    assert err.value.field == "params.holdout"
    labelled = run_stage(Pitch, {}, {"source": tracking_artifact(phrases[:4], speaker="ann")})
    with pytest.raises(UserError, match="0 segments") as err:
        run_stage(Trellis, {"holdout": "speaker", "test_speaker": "own"}, {**inputs, "test_pitch": labelled})
    assert err.value.field == "params.k"
    assert angular_speed(np.zeros((5, 3)), 30.0).max() == 0.0


def test_beat_alignment_figure(phrases):
    result = evaluate(synthesis(tracking_artifact(phrases[:4]), holdout="take"))
    fig = HeadMotionEval.figures["beat_alignment"](artifact(result.arrays, result.meta), {})
    assert len(fig.axes) == 2 and fig.axes[0].get_xticklabels()[0].get_text() == "synth"
