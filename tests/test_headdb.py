"""The head-motion database stages: tracking, BVH and CSV ingest, resampling, centring, mirroring, errors."""

from pathlib import Path

import numpy as np
import pydantic
import pytest
from head_synthetic import synth_database, synth_phrase, tracking_artifact

from msflow import UserError
from msflow.testing import artifact, run_stage
from stages.formats.bvh import head_bvh
from stages.geometry.rotations import euler_to_quat, quat_mean
from stages.head.database import BvhHeadDb, CsvHeadDb, TrackedHeadDb
from stages.head.pitch import Pitch
from stages.head.praat_files import wav_bytes


@pytest.fixture(scope="module")
def phrases():
    rng = np.random.default_rng(5)
    return [synth_phrase(rng, s, f"take{k}") for k, s in enumerate(["happy", "sad", "angry"])]


@pytest.fixture(scope="module")
def tracks60(phrases):
    return tracking_artifact(phrases, fps=60.0)


@pytest.fixture(scope="module")
def crema_tracks():
    """Three CREMA-D takes, tracked once per test session (face_fixtures)."""
    from face_fixtures import training_tracks

    return training_tracks()


def sequence_rows(run, label):
    k = run.meta["labels"].index(label)
    return run.arrays["sequence"] == k


def test_resampled_to_one_rate(phrases, tracks60):
    raw = {"mirror": False, "center": False, "jitter_cutoff": None}  # the motion as recorded, resampled only
    run = run_stage(TrackedHeadDb, {"fps": 30.0, **raw}, {"tracks": tracks60})
    assert run.meta["fps"] == 30.0 and run.meta["labels"] == ["take0", "take1", "take2"]
    for k, phrase in enumerate(phrases):
        rows = sequence_rows(run, phrase.label)
        t60, angles60, _ = phrase.motion_at(60.0)
        expected = angles60[::2]
        np.testing.assert_allclose(run.arrays["time"][rows], np.arange(len(expected)) / 30.0, atol=1e-9)
        np.testing.assert_allclose(run.arrays["angles"][rows], expected, atol=1e-9)
        assert run.meta["frames"][k] == len(expected)
    np.testing.assert_allclose(np.linalg.norm(run.arrays["rotation"], axis=1), 1.0, atol=1e-12)


def test_resampling_between_frames_slerps(tracks60, phrases):
    run = run_stage(TrackedHeadDb, {"fps": 40.0, "mirror": False, "center": False}, {"tracks": tracks60})
    rows = sequence_rows(run, "take0")
    t = run.arrays["time"][rows]
    truth = np.stack(
        [np.interp(t, np.arange(len(phrases[0].angles)) / 100.0, phrases[0].angles[:, c]) for c in range(3)], axis=1
    )
    assert np.abs(run.arrays["angles"][rows] - truth).max() < np.radians(0.2)


def test_mirror_negates_yaw_roll_and_sideways_translation(tracks60):
    plain = run_stage(TrackedHeadDb, {"mirror": False}, {"tracks": tracks60})
    both = run_stage(TrackedHeadDb, {"mirror": True}, {"tracks": tracks60})
    assert both.meta["labels"] == ["take0", "take0~mirror", "take1", "take1~mirror", "take2", "take2~mirror"]
    assert both.meta["mirrored"] == [False, True] * 3
    assert both.meta["recordings"] == ["take0", "take0", "take1", "take1", "take2", "take2"]
    for label in ("take0", "take1"):
        original = both.arrays["angles"][sequence_rows(both, label)]
        mirrored = both.arrays["angles"][sequence_rows(both, f"{label}~mirror")]
        np.testing.assert_allclose(mirrored, original * np.array([-1, 1, -1]), atol=1e-9)
        np.testing.assert_allclose(original, plain.arrays["angles"][sequence_rows(plain, label)], atol=1e-12)
        t_orig = both.arrays["translation"][sequence_rows(both, label)]
        t_mirr = both.arrays["translation"][sequence_rows(both, f"{label}~mirror")]
        np.testing.assert_allclose(t_mirr, t_orig * np.array([-1, 1, 1]), atol=1e-9)
    bounds = both.arrays["audio_bounds"]
    np.testing.assert_array_equal(bounds[0], bounds[1])  # a mirror shares its original's audio
    assert len(both.arrays["audio"]) == len(plain.arrays["audio"])


def test_centring_removes_the_resting_pose(phrases):
    turned = tracking_artifact(phrases[:1], fps=30.0)
    rotation = turned["rotation"]
    offset = euler_to_quat(0.5, -0.2, 0.1)
    from stages.geometry.rotations import quat_multiply

    shifted = artifact(
        {**{k: turned[k] for k in turned.names}, "rotation": quat_multiply(offset, rotation)}, turned.meta
    )
    run = run_stage(TrackedHeadDb, {"mirror": False}, {"tracks": shifted})
    assert abs(quat_mean(run.arrays["rotation"])[0]) > 1 - 1e-6
    np.testing.assert_allclose(run.arrays["translation"].mean(axis=0), 0.0, atol=1e-9)
    # motion relative to the mean pose keeps its shape: spread of yaw as in the source
    raw = run_stage(TrackedHeadDb, {"mirror": False, "center": False}, {"tracks": turned})
    assert np.std(run.arrays["angles"][:, 0]) == pytest.approx(np.std(raw.arrays["angles"][:, 0]), rel=0.05)


def test_nan_in_motion_names_the_take(tracks60):
    rotation = tracks60["rotation"].copy()
    rows = np.flatnonzero(tracks60["sequence"] == 1)
    rotation[rows[30]] = np.nan
    bad = artifact({**{k: tracks60[k] for k in tracks60.names}, "rotation": rotation}, tracks60.meta)
    with pytest.raises(UserError) as err:
        run_stage(TrackedHeadDb, {}, {"tracks": bad})
    assert "take1" in str(err.value) and "NaN" in str(err.value) and "0.500 s" in str(err.value)


def test_audio_and_motion_lengths_must_agree(tracks60):
    audio = tracks60["audio"]
    bounds = tracks60["audio_bounds"].copy()
    longer = np.concatenate([audio, np.zeros(16000, np.float32)])
    bounds[-1, 1] += 16000
    bad = artifact({**{k: tracks60[k] for k in tracks60.names}, "audio": longer, "audio_bounds": bounds}, tracks60.meta)
    with pytest.raises(UserError) as err:
        run_stage(TrackedHeadDb, {}, {"tracks": bad})
    assert "take2" in str(err.value) and "max_length_mismatch" in str(err.value)
    run_stage(TrackedHeadDb, {"max_length_mismatch": 1.5}, {"tracks": bad})


def test_tracking_without_audio_and_unknown_labels(tracks60):
    silent = artifact({k: tracks60[k] for k in tracks60.names if k not in ("audio", "audio_bounds")}, tracks60.meta)
    with pytest.raises(UserError, match="no audio"):
        run_stage(TrackedHeadDb, {}, {"tracks": silent})
    with pytest.raises(UserError, match="nope"):
        run_stage(TrackedHeadDb, {"labels": ["nope"]}, {"tracks": tracks60})
    only = run_stage(TrackedHeadDb, {"labels": ["take1"], "mirror": False}, {"tracks": tracks60})
    assert only.meta["labels"] == ["take1"]


def write_bvh_and_wav(phrases, folder: Path, order: str, fps: float = 60.0):
    motion, audio = {}, {}
    for p in phrases:
        _, angles, translation = p.motion_at(fps)
        q = euler_to_quat(angles[:, 0], angles[:, 1], angles[:, 2])
        (folder / f"{p.label}.bvh").write_text(head_bvh(q, translation, fps, joint="head_jnt", order=order))
        (folder / f"{p.label}.wav").write_bytes(wav_bytes(p.audio, p.audio_rate))
        motion[p.label], audio[p.label] = folder / f"{p.label}.bvh", folder / f"{p.label}.wav"
    return motion, audio


@pytest.mark.parametrize("order", ["ZXY", "XYZ"])
def test_bvh_database_matches_the_tracking_database(phrases, tracks60, tmp_path, order):
    motion, audio = write_bvh_and_wav(phrases, tmp_path, order)
    labelled = {label: {"path": path, "speaker": "synthetic"} for label, path in motion.items()}
    bvh = run_stage(BvhHeadDb, {"joint": "head_jnt", "fps": 30.0}, {"motion": labelled, "audio": audio})
    tracked = run_stage(TrackedHeadDb, {"fps": 30.0}, {"tracks": tracks60})
    assert bvh.meta["labels"] == tracked.meta["labels"]
    assert bvh.meta["speakers"] == tracked.meta["speakers"] == ["synthetic"] * len(bvh.meta["labels"])
    np.testing.assert_allclose(bvh.arrays["angles"], tracked.arrays["angles"], atol=1e-5)
    np.testing.assert_allclose(bvh.arrays["translation"], tracked.arrays["translation"], atol=1e-4)
    assert bvh.meta["sources"][0] == "take0.bvh"
    # one pitch code path for either database
    pitch_bvh = run_stage(Pitch, {}, {"source": bvh})
    pitch_tracked = run_stage(Pitch, {}, {"source": tracked})
    np.testing.assert_allclose(pitch_bvh.arrays["segments"], pitch_tracked.arrays["segments"], atol=0.011)


def test_bvh_without_the_joint(phrases, tmp_path):
    motion, audio = write_bvh_and_wav(phrases[:1], tmp_path, "ZXY")
    with pytest.raises(UserError) as err:
        run_stage(BvhHeadDb, {"joint": "Head"}, {"motion": motion, "audio": audio})
    assert "head_jnt" in str(err.value) and err.value.file.endswith("take0.bvh")


def test_motion_and_audio_labels_must_pair(phrases, tmp_path):
    motion, audio = write_bvh_and_wav(phrases[:2], tmp_path, "ZXY")
    audio.pop("take1")
    with pytest.raises(UserError, match="take1"):
        run_stage(BvhHeadDb, {"joint": "head_jnt"}, {"motion": motion, "audio": audio})


def write_csv(
    path: Path, phrase, degrees: bool, fps: float = 50.0, columns=("time", "rx", "ry", "rz", "tx", "ty", "tz")
):
    t, angles, translation = phrase.motion_at(fps)
    yaw, pitch, roll = angles.T
    scale = 180 / np.pi if degrees else 1.0
    values = {
        "time": t,
        "rx": pitch * scale,
        "ry": yaw * scale,
        "rz": roll * scale,
        "tx": translation[:, 0],
        "ty": translation[:, 1],
        "tz": translation[:, 2],
    }
    lines = [",".join(columns)] + [",".join(f"{values[c][i]:.10f}" for c in columns) for i in range(len(t))]
    path.write_text("\n".join(lines) + "\n")


def test_csv_degrees_and_radians_agree_with_the_truth(phrases, tmp_path):
    audio = {}
    for p in phrases[:2]:
        (tmp_path / f"{p.label}.wav").write_bytes(wav_bytes(p.audio, p.audio_rate))
        audio[p.label] = tmp_path / f"{p.label}.wav"
        write_csv(tmp_path / f"{p.label}_deg.csv", p, True)
        write_csv(tmp_path / f"{p.label}_rad.csv", p, False, columns=("rz", "time", "tx", "ty", "tz", "rx", "ry"))
    deg = run_stage(
        CsvHeadDb,
        {"angle_unit": "degrees", "center": False, "mirror": False, "jitter_cutoff": None},
        {"motion": {p.label: tmp_path / f"{p.label}_deg.csv" for p in phrases[:2]}, "audio": audio},
    )
    rad = run_stage(
        CsvHeadDb,
        {"angle_unit": "radians", "center": False, "mirror": False, "jitter_cutoff": None},
        {"motion": {p.label: tmp_path / f"{p.label}_rad.csv" for p in phrases[:2]}, "audio": audio},
    )
    assert deg.meta["fps"] == pytest.approx(50.0)
    np.testing.assert_allclose(deg.arrays["angles"], rad.arrays["angles"], atol=1e-8)
    _, truth, _ = phrases[0].motion_at(50.0)
    np.testing.assert_allclose(deg.arrays["angles"][deg.arrays["sequence"] == 0], truth, atol=1e-8)


def test_csv_errors(phrases, tmp_path):
    p = phrases[0]
    (tmp_path / "a.wav").write_bytes(wav_bytes(p.audio, p.audio_rate))
    write_csv(tmp_path / "a.csv", p, True, columns=("time", "rx", "ry", "rz", "tx", "ty"))
    with pytest.raises(UserError, match="tz"):
        run_stage(
            CsvHeadDb,
            {"angle_unit": "degrees"},
            {"motion": {"a": tmp_path / "a.csv"}, "audio": {"a": tmp_path / "a.wav"}},
        )
    with pytest.raises(pydantic.ValidationError):  # the angle unit must be declared
        run_stage(CsvHeadDb, {}, {"motion": {"a": tmp_path / "a.csv"}, "audio": {"a": tmp_path / "a.wav"}})
    (tmp_path / "b.csv").write_text("time,rx,ry,rz,tx,ty,tz\n0,1,2,3,4,5,x\n")
    with pytest.raises(UserError, match="non-numeric"):
        run_stage(
            CsvHeadDb,
            {"angle_unit": "degrees"},
            {"motion": {"a": tmp_path / "b.csv"}, "audio": {"a": tmp_path / "a.wav"}},
        )


def test_paper_sized_database():
    """67 phrases of two or three sentences (paper Sec. 6), mirrored: 134 sequences, one pitch pass."""
    phrases = synth_database(67, seed=3)
    run = run_stage(TrackedHeadDb, {}, {"tracks": tracking_artifact(phrases, fps=30.0)})
    assert len(run.meta["labels"]) == 134 and run.metrics["recordings"] == 67
    pitch = run_stage(Pitch, {}, {"source": run})
    counts = np.bincount(pitch.arrays["segment_utterance"], minlength=134)
    np.testing.assert_array_equal(counts[0::2], counts[1::2])  # a mirror has its original's segments
    expected = [len(p.onsets) for p in phrases]
    assert np.mean(counts[0::2] == expected) > 0.95
    sentences = [len(p.sentence_starts) for p in phrases]
    assert set(sentences) == {2, 3}
    subs = np.bincount(pitch.arrays["segment_utterance"][pitch.arrays["subsentence_start"]], minlength=134)[0::2]
    assert np.mean(subs == sentences) > 0.95


def test_crema_d_tracked_database(crema_tracks):
    run = run_stage(TrackedHeadDb, {"speaker": "1001"}, {"tracks": crema_tracks})
    assert run.meta["labels"] == ["neutral", "neutral~mirror", "happy", "happy~mirror", "angry", "angry~mirror"]
    assert run.meta["speakers"] == ["1001"] * 6
    assert run.meta["fps"] == pytest.approx(29.97, abs=0.01) and run.meta["translation_units"] == "cm"
    counts = np.bincount(crema_tracks["sequence"])
    assert run.meta["frames"][0::2] == list(counts)
    degrees = np.degrees(np.abs(run.arrays["angles"]))
    assert degrees.max() < 30  # small head motion of a seated actor
    assert np.abs(run.arrays["translation"]).max() < 10  # cm around the mean position
    pitch = run_stage(Pitch, {}, {"source": run})
    assert pitch.metrics["segments"] >= 10
    np.testing.assert_allclose(pitch.meta["audio_offset"], crema_tracks.meta["audio_offset"][0])


def test_unreadable_audio_names_the_file(phrases, tmp_path):
    motion, audio = write_bvh_and_wav(phrases[:1], tmp_path, "ZXY")
    fake = tmp_path / "take0.mp3"
    fake.write_text("not audio at all")
    with pytest.raises(UserError) as err:
        run_stage(BvhHeadDb, {"joint": "head_jnt"}, {"motion": motion, "audio": {"take0": fake}})
    assert "take0.mp3" in str(err.value)


def test_two_corpora_pool_into_one_database_with_their_speakers(phrases):
    ann = tracking_artifact(phrases[:2], speaker="ann")
    bob = tracking_artifact(phrases[2:], speaker="bob")
    run = run_stage(TrackedHeadDb, {"mirror": False}, {"tracks": ann, "more_tracks": bob})
    assert run.meta["labels"] == [p.label for p in phrases] and run.meta["speakers"] == ["ann", "ann", "bob"]
    alone = run_stage(TrackedHeadDb, {"mirror": False}, {"tracks": tracking_artifact(phrases)})
    np.testing.assert_allclose(run.arrays["angles"], alone.arrays["angles"])
    # per-speaker pitch: each speaker's median from its own takes only
    pitch = run_stage(Pitch, {}, {"source": run})
    bob_alone = run_stage(Pitch, {}, {"source": bob})
    assert pitch.arrays["speaker_median"][2] == pytest.approx(bob_alone.arrays["speaker_median"][0])
    assert pitch.arrays["speaker_median"][0] != pitch.arrays["speaker_median"][2]
    with pytest.raises(UserError, match="both tracking artifacts"):
        run_stage(TrackedHeadDb, {}, {"tracks": ann, "more_tracks": ann})
    with pytest.raises(UserError, match="nobody"):
        run_stage(TrackedHeadDb, {"labels": ["nobody"]}, {"tracks": ann, "more_tracks": bob})


def test_a_silent_take_cannot_enter_the_database(phrases):
    tracks = tracking_artifact(phrases[:2])
    bounds = np.asarray(tracks["audio_bounds"]).copy()
    bounds[1, 1] = bounds[1, 0]  # the second take has no audio
    meta = {**tracks.meta, "has_audio": [True, False]}
    silent = artifact({**{k: tracks[k] for k in tracks.names}, "audio_bounds": bounds}, meta)
    with pytest.raises(UserError, match="no audio") as err:
        run_stage(TrackedHeadDb, {}, {"tracks": silent})
    assert err.value.field == f"inputs.tracks[{phrases[1].label}]"


def jittery(phrases, sd=0.004, seed=0):
    """The first phrase tracked at 30 fps, clean and with about 0.5 degree of white jitter on the quaternion."""
    clean = tracking_artifact(phrases[:1], fps=30.0)
    rotation = np.asarray(clean["rotation"]).copy()
    rotation[:, 1:] += np.random.default_rng(seed).normal(0, sd, (len(rotation), 3))
    rotation /= np.linalg.norm(rotation, axis=1, keepdims=True)
    return clean, artifact({**{k: clean[k] for k in clean.names}, "rotation": rotation}, clean.meta)


def test_smoothing_removes_tracking_jitter_and_keeps_the_motion(phrases):
    from stages.head.measures import angular_acceleration

    clean, noisy = jittery(phrases)
    raw = {"mirror": False, "jitter_cutoff": None}
    truth = run_stage(TrackedHeadDb, raw, {"tracks": clean}).arrays["angles"]
    rough = run_stage(TrackedHeadDb, raw, {"tracks": noisy}).arrays["angles"]
    smooth = run_stage(TrackedHeadDb, {**raw, "smoothing": 0.05}, {"tracks": noisy}).arrays["angles"]
    acc = lambda a: np.percentile(angular_acceleration(a, 30.0), 99)
    assert acc(smooth) < 0.3 * acc(rough)
    assert np.abs(smooth - truth).mean() < 0.7 * np.abs(rough - truth).mean()  # closer to the motion than the jitter


def test_jitter_filter_keeps_head_strokes_and_removes_jitter():
    """The zero-phase low-pass passes a 1.5 Hz nod unchanged in size and timing and removes 10 Hz jitter."""
    from stages.geometry.rotations import euler_to_quat, quat_to_euler
    from stages.head.database import lowpass_motion

    fps = 30.0
    t = np.arange(300) / fps
    nod = np.radians(5.0) * np.sin(2 * np.pi * 1.5 * t)
    jitter = np.radians(0.5) * np.sin(2 * np.pi * 10.0 * t + 0.3)
    q = euler_to_quat(np.zeros_like(t), nod + jitter, np.zeros_like(t))
    shift = np.stack([np.sin(2 * np.pi * 1.5 * t), np.sin(2 * np.pi * 10.0 * t), np.zeros_like(t)], axis=1)
    rot, trans = lowpass_motion(q, shift, fps, 5.0)
    pitch = quat_to_euler(rot)[:, 1]
    inner = slice(30, -30)  # away from the ends, where the filter starts up
    np.testing.assert_allclose(pitch[inner], nod[inner], atol=np.radians(0.05))  # < 1% of the nod, no delay
    np.testing.assert_allclose(trans[inner, 0], shift[inner, 0], atol=0.01)
    assert np.abs(trans[inner, 1]).max() < 0.01  # 10 Hz: gain 1 / (1 + 2^8) = 0.004
    same, _ = lowpass_motion(q, shift, 8.0, 5.0)  # cutoff above the Nyquist rate: nothing to remove
    np.testing.assert_array_equal(same, q)


def test_jitter_filter_is_the_default_and_the_paper_keeps_the_motion(phrases):
    from stages.head.measures import angular_acceleration

    clean, noisy = jittery(phrases)
    truth = run_stage(TrackedHeadDb, {"mirror": False, "jitter_cutoff": None}, {"tracks": clean}).arrays["angles"]
    paper = run_stage(TrackedHeadDb, {"mirror": False, "jitter_cutoff": None}, {"tracks": noisy}).arrays["angles"]
    default = run_stage(TrackedHeadDb, {"mirror": False}, {"tracks": noisy}).arrays["angles"]
    acc = lambda a: np.percentile(angular_acceleration(a, 30.0), 99)
    assert acc(default) < 0.3 * acc(paper)
    assert np.abs(default - truth).mean() < 0.6 * np.abs(paper - truth).mean()
    with pytest.raises(pydantic.ValidationError):
        TrackedHeadDb.Params(jitter_cutoff=0)


def test_takes_cut_into_pieces_keep_their_motion_audio_and_speaker(phrases):
    """Each piece is a take of its own (label#k, source#k, same speaker) whose frames and audio, laid end to end,
    are exactly the whole take's."""
    tracks = tracking_artifact(phrases[:2], fps=30.0, speaker="ann")
    plain = {"mirror": False, "center": False, "jitter_cutoff": None}
    whole = run_stage(TrackedHeadDb, plain, {"tracks": tracks})
    cut = run_stage(TrackedHeadDb, {**plain, "piece": 1.0}, {"tracks": tracks})
    for k, label in enumerate(whole.meta["labels"]):
        count = int(round(whole.meta["frames"][k] / 30.0))
        names = [f"{label}#{j + 1}" for j in range(count)]
        assert [x for x in cut.meta["labels"] if x.startswith(f"{label}#")] == names
        parts = [cut.meta["labels"].index(x) for x in names]
        assert {cut.meta["sources"][j] for j in parts} == {f"{whole.meta['sources'][k]}#{j + 1}" for j in range(count)}
        assert {cut.meta["speakers"][j] for j in parts} == {"ann"}
        frames = np.concatenate([cut.arrays["angles"][cut.arrays["sequence"] == j] for j in parts])
        np.testing.assert_allclose(frames, whole.arrays["angles"][whole.arrays["sequence"] == k], atol=1e-12)
        a, b = whole.arrays["audio_bounds"][k]
        audio = np.concatenate([cut.arrays["audio"][slice(*cut.arrays["audio_bounds"][j])] for j in parts])
        np.testing.assert_array_equal(audio, whole.arrays["audio"][a:b])
        rate = cut.meta["audio_rate"]
        for j in parts:  # each piece's audio starts within one sample after its first frame
            assert 0.0 <= cut.meta["audio_offset"][j] - whole.meta["audio_offset"][k] < 1.0 / rate + 1e-9
    assert (
        run_stage(TrackedHeadDb, {**plain, "piece": 100.0}, {"tracks": tracks}).meta["labels"] == whole.meta["labels"]
    )
