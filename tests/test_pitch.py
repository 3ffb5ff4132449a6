"""Pitch extraction, cleaning, segmentation and Praat exports (paper Sec. 5.1)."""

import wave
from pathlib import Path

import numpy as np
import pytest
from head_synthetic import synth_phrase, tracking_artifact
from pydantic import ValidationError

from msflow import UserError
from msflow.testing import artifact, prepare_inputs, run_stage
from stages.head.pitch import (
    PHRASE_FEATURES,
    Pitch,
    clean_pitch,
    phrase_features,
    segment_pitch,
    semitones,
    voiced_runs,
)
from stages.head.praat_files import wav_bytes

ROOT = Path(__file__).resolve().parents[1]
CREMA = ROOT / "data" / "crema-d"


@pytest.fixture(scope="module")
def phrases():
    rng = np.random.default_rng(11)
    return [synth_phrase(rng, style, f"{style}{k}") for k, style in enumerate(["neutral", "happy", "sad", "angry"])]


@pytest.fixture(scope="module")
def phrase_pitch(phrases):
    return run_stage(Pitch, {}, {"source": tracking_artifact(phrases)})


@pytest.fixture(scope="module")
def crema_pitch():
    files = {p.name.split("_")[2]: {"path": p, "speaker": p.name.split("_")[0]} for p in sorted(CREMA.glob("*.flv"))}
    return run_stage(Pitch, {}, {"audio": files})


def rows_of(run, u):
    mask = run.arrays["segment_utterance"] == u
    return run.arrays["segments"][mask], run.arrays["subsentence_start"][mask]


def test_segments_start_at_the_synthetic_syllable_onsets(phrases, phrase_pitch):
    for u, phrase in enumerate(phrases):
        segments, sub = rows_of(phrase_pitch, u)
        assert len(segments) == len(phrase.onsets), phrase.label
        np.testing.assert_allclose(segments[:, 0], phrase.onsets, atol=0.025)
        np.testing.assert_allclose(segments[:, 1], phrase.voiced_ends, atol=0.03)
        # onset to next onset; the last segment runs to the end of the utterance
        np.testing.assert_allclose(segments[1:, 0], segments[:-1, 2])
        assert segments[-1, 2] == pytest.approx(phrase_pitch.arrays["utterance_duration"][u])
        # sub-sentences begin exactly at the sentence starts (pauses >= 0.3 s; syllable gaps are shorter)
        np.testing.assert_allclose(segments[sub, 0], phrase.sentence_starts, atol=0.025)


def test_cleaned_f0_follows_the_synthetic_contour(phrases, phrase_pitch):
    for u, phrase in enumerate(phrases):
        mask = phrase_pitch.arrays["pitch_utterance"] == u
        t, f0 = phrase_pitch.arrays["pitch_time"][mask], phrase_pitch.arrays["f0"][mask]
        control = np.arange(len(phrase.f0)) / 100.0
        truth = np.interp(t, control, np.nan_to_num(phrase.f0, nan=0.0))
        # frames 20 ms or more inside a synthetic syllable (the analysis window straddles its edges)
        inside = np.all(
            [np.interp(t + d, control, np.isfinite(phrase.f0).astype(float)) == 1.0 for d in (-0.02, 0.0, 0.02)], axis=0
        )
        both = np.isfinite(f0) & inside
        assert np.isfinite(f0[inside]).mean() > 0.95  # voicing found inside every syllable
        error = np.abs(semitones(f0[both], truth[both]))
        assert np.median(error) < 0.1 and np.percentile(error, 95) < 0.5


def test_phrase_features_rank_the_styles(phrases, phrase_pitch):
    features = phrase_pitch.arrays["phrase_features"]
    names = phrase_pitch.meta["feature_names"]
    assert names == list(PHRASE_FEATURES) and features.shape == (4, len(names))
    mean = features[:, names.index("f0_mean")]
    rate = features[:, names.index("speaking_rate")]
    labels = [p.style for p in phrases]
    # happy is higher than neutral, which is higher than sad; sad speaks slowest
    assert mean[labels.index("happy")] > mean[labels.index("neutral")] > mean[labels.index("sad")]
    assert rate[labels.index("sad")] == rate.min()
    # one speaker: semitones relative to the median over all four utterances
    assert len(set(phrase_pitch.arrays["speaker_median"])) == 1


def test_clean_pitch_range_gaps_islands_and_octave_errors():
    f0 = np.full(40, 120.0)
    f0[5:7] = np.nan  # 20 ms gap: filled (< max_gap 30 ms)
    f0[15:19] = np.nan  # 40 ms gap: kept
    f0[25] = 30.0  # below the human range: dropped, then the 10 ms hole is filled
    f0[30] = 480.0  # two octaves up (an octave error): dropped, then filled
    clean = clean_pitch(f0, 0.01, human_range=(50, 800), max_deviation=10, max_gap=0.03, min_voiced=0.05)
    assert np.isfinite(clean[5:7]).all()
    assert np.isnan(clean[15:19]).all()
    assert clean[25] == pytest.approx(120.0) and clean[30] == pytest.approx(120.0)
    no_octave_check = clean_pitch(f0, 0.01, max_deviation=None, max_gap=0.03, min_voiced=0.05)
    assert no_octave_check[30] == pytest.approx(480.0)
    islands = np.full(30, np.nan)
    islands[3:6] = 150.0  # 30 ms island: dropped
    islands[10:25] = 150.0  # 150 ms: kept
    out = clean_pitch(islands, 0.01, max_gap=0.03, min_voiced=0.05)
    assert np.isnan(out[3:6]).all() and np.isfinite(out[10:25]).all()


def test_gap_fill_interpolates_in_log_frequency():
    f0 = np.array([100.0, np.nan, 400.0, 400, 400, 400, 400])
    out = clean_pitch(f0, 0.01, max_deviation=None, max_gap=0.03, min_voiced=0.0)
    assert out[1] == pytest.approx(200.0)


def test_segment_pitch_breaks_and_bounds():
    times = np.arange(100) * 0.01 + 0.005
    f0 = np.full(100, np.nan)
    f0[10:20] = f0[25:35] = f0[70:80] = 100.0  # pause 35 -> 70 is 0.35 s: a breath
    seg = segment_pitch(times, f0, 1.2, time_step=0.01, breath_pause=0.3)
    np.testing.assert_allclose(seg.segments, [[0.10, 0.20, 0.25], [0.25, 0.35, 0.70], [0.70, 0.80, 1.2]], atol=1e-9)
    np.testing.assert_array_equal(seg.subsentence_start, [True, False, True])
    empty = segment_pitch(times, np.full(100, np.nan), 1.0, time_step=0.01)
    assert empty.segments.shape == (0, 3)


def test_phrase_features_by_hand():
    times = np.arange(100) * 0.01
    f0 = np.full(100, np.nan)
    f0[0:20] = 200.0
    f0[40:60] = 100.0
    segments = np.array([[0.0, 0.2, 0.4], [0.4, 0.6, 1.0]])
    features = dict(zip(PHRASE_FEATURES, phrase_features(times, f0, segments, 100.0)))
    assert features["speaking_rate"] == pytest.approx(2 / 0.6)
    assert features["voiced_mean"] == pytest.approx(0.2) and features["voiced_std"] == pytest.approx(0.0)
    assert features["unvoiced_mean"] == pytest.approx(0.2)
    assert features["voiced_fraction"] == pytest.approx(0.4 / 0.6)
    assert features["f0_mean"] == pytest.approx(6.0) and features["f0_std"] == pytest.approx(6.0)
    assert features["f0_max"] == pytest.approx(12.0) and features["f0_min"] == pytest.approx(0.0)
    assert np.isnan(phrase_features(times, np.full(100, np.nan), np.zeros((0, 3)), 100.0)).all()


def test_voiced_runs():
    starts, stops = voiced_runs(np.array([0, 1, 1, 0, 1, 0, 0, 1], bool))
    np.testing.assert_array_equal(starts, [1, 4, 7])
    np.testing.assert_array_equal(stops, [3, 5, 8])


def test_praat_exports_open_in_praat_and_line_up(phrases, phrase_pitch, tmp_path):
    import parselmouth

    grid = tmp_path / "p.TextGrid"
    grid.write_bytes(phrase_pitch.arrays["textgrid"].tobytes())
    tier_file = tmp_path / "p.PitchTier"
    tier_file.write_bytes(phrase_pitch.arrays["pitchtier"].tobytes())
    sound_file = tmp_path / "p.wav"
    sound_file.write_bytes(phrase_pitch.arrays["sound"].tobytes())
    tg = parselmouth.read(str(grid))
    sound = parselmouth.Sound(str(sound_file))
    total = sum(p.duration for p in phrases)
    assert sound.duration == pytest.approx(total, abs=1e-3)
    assert tg.xmax == pytest.approx(sound.duration, abs=1e-3)
    assert parselmouth.praat.call(tg, "Get number of tiers") == 4
    assert parselmouth.praat.call(tg, "Get tier name...", 2) == "segment"
    labelled = [
        parselmouth.praat.call(tg, "Get label of interval...", 2, i)
        for i in range(1, parselmouth.praat.call(tg, "Get number of intervals...", 2) + 1)
    ]
    assert sum(1 for x in labelled if x) == len(phrase_pitch.arrays["segments"])
    # the second phrase's first segment sits after the first phrase's audio
    second_onset = phrases[1].onsets[0] + phrases[0].duration
    k = labelled.index("1", labelled.index("1") + 1) + 1
    assert parselmouth.praat.call(tg, "Get start time of interval...", 2, k) == pytest.approx(second_onset, abs=0.03)
    pitch_tier = parselmouth.read(str(tier_file))
    assert parselmouth.praat.call(pitch_tier, "Get number of points") == int(
        np.isfinite(phrase_pitch.arrays["f0"]).sum()
    )


def test_artifact_and_files_share_one_code_path(phrases, tmp_path):
    phrase = phrases[0]
    path = tmp_path / "take.wav"
    path.write_bytes(wav_bytes(phrase.audio, phrase.audio_rate))
    from_file = run_stage(Pitch, {}, {"audio": {"take": path}})
    from_artifact = run_stage(Pitch, {}, {"source": tracking_artifact([phrase])})
    np.testing.assert_allclose(from_file.arrays["segments"][:, 0], from_artifact.arrays["segments"][:, 0], atol=0.011)
    assert from_file.meta["sources"] == ["take.wav"]


def test_audio_offset_moves_segments_onto_the_video_clock(phrases):
    phrase = phrases[0]
    base = run_stage(Pitch, {}, {"source": tracking_artifact([phrase])})
    shifted = run_stage(Pitch, {}, {"source": tracking_artifact([phrase], audio_offset=0.2)})
    np.testing.assert_allclose(shifted.arrays["segments"][:-1, :2], base.arrays["segments"][:-1, :2] + 0.2, atol=1e-9)


def test_motion_frame_count_sets_the_utterance_length(phrases):
    run = run_stage(Pitch, {}, {"source": tracking_artifact([phrases[1]], fps=25.0)})
    frames = int(np.floor(phrases[1].duration * 25.0))
    assert run.meta["frames"] == [frames] and run.meta["fps"] == [25.0]
    assert run.arrays["utterance_duration"][0] == pytest.approx(frames / 25.0)


def test_crema_d_pitch_and_segments(crema_pitch):
    run = crema_pitch
    assert run.meta["labels"] == ["ANG", "DIS", "FEA", "HAP", "NEU", "SAD"]
    assert run.meta["speakers"] == ["1001"] * 6 and len(set(run.arrays["speaker_median"])) == 1
    median = run.arrays["speaker_median"][0]
    assert 80 < median < 200  # a male voice
    durations = run.arrays["utterance_duration"]
    for u in range(6):
        segments, sub = rows_of(run, u)
        assert 1 <= len(segments) <= 8 and sub[0]
        assert (segments[:, 0] >= 0).all() and segments[-1, 2] == pytest.approx(durations[u])
        assert np.all(segments[:, 0] <= segments[:, 1]) and np.all(segments[:, 1] <= segments[:, 2])
    voiced = np.isfinite(run.arrays["f0"])
    assert 0.1 < voiced.mean() < 0.6
    # cleaning removes octave jumps: everything within 10 semitones of its utterance's raw median
    raw_outliers = 0
    for u in range(6):
        mask = run.arrays["pitch_utterance"] == u
        raw = run.arrays["f0_raw"][mask]
        reference = np.nanmedian(raw[(raw >= 50) & (raw <= 800)])
        f0 = run.arrays["f0"][mask]
        assert np.nanmax(np.abs(semitones(f0, reference))) <= 10 + 1e-4
        raw_outliers += int(np.sum(np.abs(semitones(raw, reference)) > 10))
    assert raw_outliers > 0  # Praat's raw tracks of these clips do jump octaves (about 2x and 4x f0)
    raw = run.arrays["f0_raw"]
    assert np.isfinite(raw).sum() >= voiced.sum() - 20


def test_cc_method_agrees_with_ac(phrases):
    ac = run_stage(Pitch, {"method": "ac"}, {"source": tracking_artifact([phrases[0]])})
    cc = run_stage(Pitch, {"method": "cc"}, {"source": tracking_artifact([phrases[0]])})
    assert len(cc.arrays["segments"]) == len(ac.arrays["segments"])
    np.testing.assert_allclose(cc.arrays["segments"][:, 0], ac.arrays["segments"][:, 0], atol=0.03)


def silent_artifact(seconds=1.0):
    audio = (np.random.default_rng(0).standard_normal(int(16000 * seconds)) * 1e-4).astype(np.float32)
    return artifact(
        {"audio": audio, "audio_bounds": np.array([[0, len(audio)]])},
        {"labels": ["quiet"], "sources": ["quiet.flv"], "audio_rate": 16000},
    )


def test_silence_is_an_error_naming_the_file_when_asked():
    with pytest.raises(UserError) as err:
        run_stage(Pitch, {"on_silence": "error"}, {"source": silent_artifact()})
    assert err.value.file == "quiet.flv" and "no voiced speech" in str(err.value)


def test_silence_gives_no_segments_and_a_warning():
    inputs = prepare_inputs(Pitch, {"source": silent_artifact()})
    result = Pitch("pitch").run(Pitch.Params(), inputs)
    assert result.arrays["segments"].shape == (0, 3) and result.meta["silent"] == ["quiet"]
    assert np.isnan(result.arrays["phrase_features"]).all()
    assert result.warnings == ["no voiced speech in 'quiet' (quiet.flv): no segments, the head stays at rest there"]


def test_takes_without_a_speaker_label_are_an_error_when_pitch_is_per_speaker(phrases):
    unlabelled = tracking_artifact(phrases[:2], speaker=None)
    with pytest.raises(UserError) as err:
        run_stage(Pitch, {}, {"source": unlabelled})
    assert (
        err.value.file == f"{phrases[0].label}.flv" and err.value.field == f"inputs.source[{phrases[0].label}].speaker"
    )
    # one take alone is its own speaker; per utterance needs no labels
    assert run_stage(Pitch, {}, {"source": tracking_artifact(phrases[:1], speaker=None)}).meta["speakers"] == [None]
    per_utterance = run_stage(Pitch, {"median_over": "utterance"}, {"source": unlabelled})
    assert per_utterance.arrays["speaker_median"][0] != per_utterance.arrays["speaker_median"][1]


def test_speakers_are_normalised_apart(phrases):
    two = tracking_artifact(phrases[:2])
    two.meta["fields"] = {phrases[0].label: {"speaker": "ann"}, phrases[1].label: {"speaker": "bob"}}
    run = run_stage(Pitch, {}, {"source": two})
    alone = [run_stage(Pitch, {}, {"source": tracking_artifact([p])}) for p in phrases[:2]]
    np.testing.assert_allclose(run.arrays["speaker_median"], [a.arrays["speaker_median"][0] for a in alone])
    np.testing.assert_allclose(run.arrays["speaker_spread"], [a.arrays["speaker_spread"][0] for a in alone])
    np.testing.assert_allclose(
        run.arrays["phrase_features"], np.concatenate([a.arrays["phrase_features"] for a in alone])
    )


def test_unsupported_audio_is_a_user_error(tmp_path):
    bad = tmp_path / "notes.wav"
    bad.write_text("this is not audio")
    with pytest.raises(UserError) as err:
        run_stage(Pitch, {}, {"audio": {"notes": bad}})
    assert "notes.wav" in str(err.value)


def test_inputs_must_be_exactly_one(phrases, tmp_path):
    with pytest.raises(UserError):
        run_stage(Pitch, {}, {})
    path = tmp_path / "a.wav"
    path.write_bytes(wav_bytes(phrases[0].audio, 16000))
    with pytest.raises(UserError):
        run_stage(Pitch, {}, {"audio": {"a": path}, "source": tracking_artifact([phrases[0]])})


def test_artifact_without_audio_is_a_user_error():
    with pytest.raises(UserError) as err:
        run_stage(Pitch, {}, {"source": artifact({"rotation": np.zeros((3, 4))}, {"labels": ["a"]})})
    assert "audio" in str(err.value)


def test_wav_bytes_is_16_bit_mono(tmp_path):
    path = tmp_path / "x.wav"
    path.write_bytes(wav_bytes(np.zeros(800, np.float32), 8000))
    with wave.open(str(path)) as w:
        assert (w.getnchannels(), w.getsampwidth(), w.getframerate(), w.getnframes()) == (1, 2, 8000, 800)


def test_pitch_figure_renders(phrase_pitch):
    fig = Pitch.figures["pitch_segments"](phrase_pitch.view(), {})
    assert len(fig.axes) == 2 and fig.axes[1].get_title().startswith("cleaned")


@pytest.mark.parametrize(
    "params, field",
    [
        ({"ceiling": 3000.0}, "analysis_rate"),
        ({"floor": 600.0, "ceiling": 500.0}, "ceiling"),
        ({"human_range": (800.0, 50.0)}, "human_range"),
        ({"time_step": 0.0}, "time_step"),
        ({"on_silence": "still"}, "on_silence"),
    ],
)
def test_pitch_settings_are_checked_by_the_params(params, field):
    with pytest.raises(ValidationError) as err:
        Pitch.Params(**params)
    assert err.value.errors()[0]["loc"] == (field,)


def test_a_label_with_quotes_round_trips_through_praat(phrases, tmp_path):
    import dataclasses

    import parselmouth

    quoted = dataclasses.replace(phrases[0], label='say "hi", twice ""')
    run = run_stage(Pitch, {}, {"source": tracking_artifact([quoted])})
    grid = tmp_path / "quoted.TextGrid"
    grid.write_bytes(run.arrays["textgrid"].tobytes())
    tg = parselmouth.read(str(grid))
    assert parselmouth.praat.call(tg, "Get label of interval...", 1, 1) == quoted.label
