"""The MP4 writer (stages/formats/video.py) shared by the face edit's video and the export's preview: grey frames
give the same bytes whatever the run, the block sizes or the cores, and the MPEG-4 fallback writes them too.

RGB frames with audio (the AAC priming samples skipped, the audio starting with the first frame) are checked
through the preview in tests/test_export.py (``test_preview_video_frames_rate_and_audio_offset``).
"""

import io
import os

import av
import numpy as np
import pytest

from msflow import UserError
from stages.formats.video import Mp4Writer, video_codec_name


def moving_grey(frames: int = 48, height: int = 127, width: int = 255) -> np.ndarray:
    """(frames, height, width) uint8: a bright disc moving over a gradient, odd sizes (padded by the writer);
    large enough for x264 to use two threads when it may."""
    ys, xs = np.mgrid[0:height, 0:width]
    out = np.empty((frames, height, width), dtype=np.uint8)
    for t in range(frames):
        disc = (ys - height / 2) ** 2 + (xs - 10 - t) ** 2 < 64
        out[t] = np.where(disc, 230, 40 + xs * 3 // 4)
    return out


def write_grey(frames: np.ndarray, block: int, codec: str = "auto") -> bytes:
    writer = Mp4Writer(30.0, codec=codec, crf=18, preset="medium", pixels="gray")
    for start in range(0, len(frames), block):
        writer.write(frames[start : start + block])
    return writer.close()


def decode_grey(data: bytes) -> tuple[str, float, np.ndarray]:
    """Codec name, frame rate and the frames (F, H, W) of an MP4 file."""
    with av.open(io.BytesIO(data)) as container:
        stream = container.streams.video[0]
        frames = np.stack([f.to_ndarray(format="gray") for f in container.decode(stream)])
        return stream.codec_context.name, float(stream.average_rate), frames


def test_the_same_grey_frames_give_the_same_bytes_whatever_the_blocks():
    frames = moving_grey()
    first = write_grey(frames, block=16)
    assert write_grey(frames, block=16) == first
    assert write_grey(frames, block=48) == first and write_grey(frames, block=7) == first


def test_the_bytes_do_not_depend_on_the_cores_the_encoder_may_use():
    """x264 picks its thread count from the cores it may run on, and its output depends on that count: the
    edit's encoder, with the default threads, wrote other bytes on one core than on two (so on another machine).
    On a one-core machine both runs use the same core (the project's CI has two)."""
    frames = moving_grey()
    cores = os.sched_getaffinity(0)
    try:
        os.sched_setaffinity(0, {min(cores)})
        one_core = write_grey(frames, block=16)
    finally:
        os.sched_setaffinity(0, cores)
    assert write_grey(frames, block=16) == one_core


def test_the_mpeg4_fallback_writes_a_grey_video_of_the_right_length_and_size():
    frames = moving_grey()
    codec, rate, decoded = decode_grey(write_grey(frames, block=20, codec="mpeg4"))
    assert codec == "mpeg4" and rate == pytest.approx(30.0)
    assert decoded.shape == (48, 128, 256)  # odd sides padded to even by repeating the last row and column
    # limited-range luma, expanded back by the decoder: the frames up to MPEG-4's loss
    assert np.mean(np.abs(decoded[:, :127, :255].astype(float) - frames)) < 2


def test_the_default_codec_is_libx264_when_ffmpeg_has_it_and_mpeg4_otherwise():
    assert video_codec_name() == ("libx264" if "libx264" in av.codecs_available else "mpeg4")
    assert video_codec_name("mpeg4") == "mpeg4"
    with pytest.raises(UserError, match="video codec 'no-such-codec' is not available"):
        video_codec_name("no-such-codec")


def test_frames_of_the_wrong_shape_are_refused():
    writer = Mp4Writer(30.0, pixels="gray")
    with pytest.raises(ValueError, match=r"gray frames must be \(F, H, W\) uint8"):
        writer.write(np.zeros((2, 8, 8, 3), dtype=np.uint8))
    with pytest.raises(ValueError, match=r"rgb24 frames must be \(F, H, W, 3\) uint8"):
        Mp4Writer(30.0).write(np.zeros((2, 8, 8), dtype=np.uint8))
