"""Takes as data: a video with its own audio, a video plus a separate audio file (WAV, FLAC, MP3, with an offset
per take), a silent video; labels' fields in the artifact; every mismatch between picture and sound a clear user
error naming the file and the field. Audio files carry signals whose value says where in the file a sample came
from (a ramp, a tone burst), so the cut the stage made can be read off its output."""

import numpy as np
import pytest
from conftest import run_cli
from pydantic import ValidationError
from tracking_media import CLIPS, first_frames, write_audio, write_video

from msflow import UserError
from msflow.testing import run_stage
from stages.formats.audio import decode_audio, probe_audio
from stages.tracking import FaceMesh, TrackFile
from stages.tracking.trackfile import write_openface_csv

RATE = 48000
FPS = 30


def ramp(seconds, rate=RATE, slope=0.2):
    """A slow ramp: sample value 0.1 + slope t tells the time t it was taken at."""
    return (0.1 + slope * np.arange(int(seconds * rate)) / rate).astype(np.float32)


def burst(seconds, onset, rate=RATE):
    """Silence, then a 440 Hz tone from ``onset`` seconds on (for lossy codecs, where a ramp does not survive)."""
    t = np.arange(int(seconds * rate)) / rate
    return (0.3 * np.sin(2 * np.pi * 440 * t) * (t >= onset)).astype(np.float32)


def onset(samples, rate=16000):
    return np.argmax(np.abs(samples) > 0.05) / rate


@pytest.fixture(scope="module")
def media(tmp_path_factory):
    """A 1 s silent video (30 frames of the neutral clip), the same with a 0.5 s audio track, and audio files."""
    root = tmp_path_factory.mktemp("takes")
    frames = first_frames(CLIPS["NEU"], FPS)
    return {
        "silent": write_video(root / "silent.mp4", frames, fps=FPS),
        "short_track": write_video(root / "short_track.mp4", frames, fps=FPS, audio=burst(0.5, 0.0, 16000)),
        "wav": write_audio(root / "ramp.wav", ramp(3.0)),
        "flac": write_audio(root / "ramp.flac", ramp(3.0)),
        "mp3": write_audio(root / "burst.mp3", burst(3.0, 1.5)),
        "short_wav": write_audio(root / "short.wav", ramp(0.5)),
        "nearly_wav": write_audio(root / "nearly.wav", ramp(0.8)),
        "long_wav": write_audio(root / "long.wav", ramp(15.0, slope=0.05)),
    }


def track(params, videos, audio=None, **more):
    inputs = {"videos": videos, **more}
    if audio is not None:
        inputs["audio"] = audio
    return run_stage(FaceMesh, {"output_mesh": False, "eyes": False, **params}, inputs)


def take_audio(out, label):
    s = out.meta["labels"].index(label)
    start, stop = out.arrays["audio_bounds"][s]
    return out.arrays["audio"][start:stop]


# ------------------------------------------------------------------------------------- decode_audio


def test_decode_audio_window_is_sample_exact(media):
    rate = 16000
    cases = ((media["wav"], 0.5, 0.2), (media["flac"], 1.25, 0.2), (media["long_wav"], 12.0, 0.05))  # 12 s: seeks
    for path, offset, slope in cases:
        audio = decode_audio(path, rate, offset=offset, duration=1.0)
        assert len(audio.samples) == rate and audio.rate == rate
        t = offset + np.arange(rate) / rate
        np.testing.assert_allclose(audio.samples[:-8], (0.1 + slope * t)[:-8], atol=2e-4)
    whole = decode_audio(media["wav"], rate)
    assert abs(whole.duration - 3.0) < 1e-3 and whole.start == 0.0
    assert len(decode_audio(media["wav"], rate, offset=3.5).samples) == 0  # past the end: empty, caller decides
    tail = decode_audio(media["wav"], rate, offset=2.5, duration=5.0)
    assert abs(tail.duration - 0.5) < 1e-3
    mp3 = decode_audio(media["mp3"], rate, offset=1.0)
    assert abs(onset(mp3.samples) - 0.5) < 0.005  # the encoder's priming delay is compensated
    info = probe_audio(media["flac"])
    assert (info.rate, info.channels, info.codec) == (RATE, 1, "flac") and abs(info.duration - 3.0) < 1e-3
    with pytest.raises(UserError, match="has no audio track") as err:
        probe_audio(media["silent"], field="inputs.audio.x")
    assert err.value.file == str(media["silent"]) and err.value.field == "inputs.audio.x"


# ------------------------------------------------------------------------------------- take forms


def test_silent_video_plus_audio_files_with_offsets(media):
    """Two takes of one silent video: a FLAC 0.25 s in and an MP3 1.0 s in, offsets given per label."""
    out = track(
        {"audio_offset": {"a": 0.25, "b": 1.0}},
        {"a": media["silent"], "b": media["silent"]},
        {"a": media["flac"], "b": media["mp3"]},
    )
    meta = out.meta
    assert meta["has_audio"] == [True, True] and meta["audio_offset"] == [0.0, 0.0]
    assert meta["audio_sources"] == ["ramp.flac", "burst.mp3"] and meta["sources"] == ["silent.mp4"] * 2
    a, b = take_audio(out, "a"), take_audio(out, "b")
    assert len(a) == len(b) == 16000  # cut to the video's 30 frames at 30 fps
    t = 0.25 + np.arange(16000) / 16000
    np.testing.assert_allclose(a[:-8], (0.1 + 0.2 * t)[:-8], atol=2e-4)
    assert abs(onset(b) - 0.5) < 0.005  # the tone starts 1.5 s into the file: 0.5 s after the first frame


def test_one_offset_for_every_take_and_a_silent_take(media):
    out = track(
        {"audio_offset": 0.5, "audio": "optional"},
        {"wav": media["silent"], "none": media["silent"], "own": CLIPS["SAD"]},
        {"wav": media["wav"]},
    )
    assert out.meta["has_audio"] == [True, False, True]
    assert out.meta["audio_sources"] == ["ramp.wav", None, CLIPS["SAD"].name]
    assert out.meta["audio_offset"][:2] == [0.0, None] and abs(out.meta["audio_offset"][2] + 0.027) < 1e-6
    start, stop = out.arrays["audio_bounds"][1]
    assert start == stop  # the silent take has an empty range
    np.testing.assert_allclose(take_audio(out, "wav")[0], 0.1 + 0.2 * 0.5, atol=2e-4)


def test_silent_take_alone_has_no_audio_output(media):
    out = track({"audio": "optional"}, {"s": media["silent"]})
    assert out.meta["has_audio"] == [False] and "audio" not in out.arrays and out.meta["audio_rate"] is None


def test_fields_of_the_labels_reach_the_metadata(media, tmp_path):
    videos = {
        "1001-sad": {"path": CLIPS["SAD"], "speaker": "1001", "expression": "sad"},
        "plain": media["silent"],
    }
    out = track({"audio": "optional"}, videos, {"plain": {"path": media["wav"], "sentence": "DFA"}})
    assert out.meta["fields"] == {"1001-sad": {"expression": "sad", "speaker": "1001"}, "plain": {"sentence": "DFA"}}
    csv = tmp_path / "t.csv"
    csv.write_text(write_openface_csv(np.tile(out.arrays["landmarks"][:1].astype(float), (5, 1, 1))))
    tracks = run_stage(TrackFile, {"fps": 30, "frame_size": (480, 360)}, {"tracks": {"t": {"path": csv, "take": "1"}}})
    assert tracks.meta["fields"] == {"t": {"take": "1"}} and tracks.meta["has_audio"] == [False]


# ------------------------------------------------------------------------------------- errors


def expect_error(match, params, videos, audio=None):
    with pytest.raises(UserError, match=match) as err:
        track(params, videos, audio)
    return err.value


def test_audio_file_without_a_video(media):
    err = expect_error("no take with that label", {}, {"a": media["silent"]}, {"a": media["wav"], "b": media["flac"]})
    assert err.field == "inputs.audio.b" and err.file == str(media["flac"])


def test_a_folder_given_as_a_video_says_so(media, tmp_path):
    """A folder of clips given where one clip is expected (``-S vars.take=clips/``) is named as a folder."""
    err = expect_error("is a folder, not a video file", {}, {"a": tmp_path})
    assert err.field == "inputs.videos.a" and err.file == str(tmp_path)


def test_offset_outside_the_audio(media):
    err = expect_error(r"audio_offset 4 s is outside the audio \(3.00 s long\)", {"audio_offset": 4.0},
                       {"a": media["silent"]}, {"a": media["wav"]})  # fmt: skip
    assert err.field == "params.audio_offset" and err.file == str(media["wav"])
    err = expect_error("outside the audio", {"audio_offset": {"a": 3.0}}, {"a": media["silent"]}, {"a": media["wav"]})
    assert err.field == "params.audio_offset.a"  # at the very end: within the header check's slack, found decoding
    err = expect_error("'zz', which has no separate audio file", {"audio_offset": {"zz": 1.0}}, {"a": media["silent"]})
    assert err.field == "params.audio_offset.zz"
    with pytest.raises(ValidationError):
        FaceMesh.Params(audio_offset=-0.5)
    with pytest.raises(ValidationError):
        FaceMesh.Params(audio_offset={"a": float("nan")})


def test_audio_shorter_than_the_video(media):
    err = expect_error(r"ends 0.50 s before the video", {}, {"a": media["silent"]}, {"a": media["short_wav"]})
    assert err.field == "inputs.audio.a" and err.file == str(media["short_wav"])
    err = expect_error(r"ends 0.4\d s before the video", {}, {"t": media["short_track"]})  # AAC pads a frame
    assert err.field == "inputs.videos.t" and err.file == str(media["short_track"])
    out = track({}, {"a": media["silent"]}, {"a": media["nearly_wav"]})  # 0.2 s short: within the tolerance
    assert len(take_audio(out, "a")) == int(0.8 * 16000)
    expect_error("ends 0.20 s before", {"audio_tolerance": 0.1}, {"a": media["silent"]}, {"a": media["nearly_wav"]})


def test_video_without_audio_when_audio_is_required(media):
    err = expect_error("has no audio track: give an audio file for it", {}, {"s": media["silent"]})
    assert err.field == "inputs.videos.s" and err.file == str(media["silent"]) and "inputs.audio.s" in err.message
    err = expect_error("audio is 'none'", {"audio": "none"}, {"a": media["silent"]}, {"a": media["wav"]})
    assert err.field == "inputs.audio"


def test_cli_reports_a_take_error_with_exit_2(media, tmp_path):
    (tmp_path / "pipeline.yaml").write_text(
        "version: 1\nstages:\n  track:\n    uses: stages.tracking:FaceMesh\n    inputs:\n"
        f"      videos: {{a: {media['silent']}}}\n      audio: {{a: {media['wav']}, b: {media['flac']}}}\n"
    )
    proc = run_cli(tmp_path, "run")
    assert proc.returncode == 2, proc.stderr
    assert "stage 'track'" in proc.stderr and "inputs.audio.b" in proc.stderr and "ramp.flac" in proc.stderr
    assert "Traceback" not in proc.stderr
