"""MP4 writing shared by the export's preview and the face edit's side-by-side video: frames encoded with PyAV
(FFmpeg) as H.264 (libx264) or, where PyAV's FFmpeg has no libx264, its built-in MPEG-4 Part 2 encoder.

``Mp4Writer`` takes blocks of frames as they come, RGB (F, H, W, 3) or grey (F, H, W) uint8, so memory does not
grow with the take, and optional mono audio (AAC) placed at the first video frame; ``close`` gives the file's
bytes. The same frames give the same bytes: one encoder thread, explicit timestamps and, for libx264, no
macroblock-tree rate control (each of the three made the bytes vary from run to run).
"""

from __future__ import annotations

import io
from fractions import Fraction
from typing import Literal

import numpy as np

from msflow import UserError

#: bit rate of the MPEG-4 Part 2 fallback, which has no constant-quality mode here
MPEG4_BIT_RATE = 2_000_000


def video_codec_name(requested: str = "auto") -> str:
    """The encoder to use: ``requested`` if PyAV's FFmpeg has it (else a UserError on ``params.video_codec``);
    for "auto", libx264 when PyAV's FFmpeg has it, else the built-in MPEG-4 Part 2 encoder."""
    import av

    available = av.codecs_available
    if requested != "auto":
        if requested not in available:
            raise UserError(f"video codec '{requested}' is not available in PyAV's FFmpeg", field="params.video_codec")
        return requested
    return "libx264" if "libx264" in available else "mpeg4"


class Mp4Writer:
    """Frames to MP4 bytes, written block by block.

    Parameters
    ----------
    fps : float
        Frame rate (frames per second); stored as a fraction with a denominator of at most 1001 (29.97 and the
        like stay exact).
    codec : str
        "auto" (libx264, else mpeg4: ``video_codec_name``) or an FFmpeg encoder name.
    crf : int
        libx264's constant quality (lower: better, larger); the MPEG-4 fallback runs at ``MPEG4_BIT_RATE``.
    preset : str
        libx264's preset, which trades encoding time for file size.
    pixels : {"rgb24", "gray"}
        What ``write`` takes: RGB frames (F, H, W, 3), converted to YUV 4:2:0 by FFmpeg, or grey frames (F, H, W),
        padded to even sizes (4:2:0 needs them) by repeating the last row and column and written as YUV planes
        directly (constant chroma, limited-range luma): no colour conversion.
    size : tuple of int, optional
        The video's (width, height); default: the first block's (grey: after padding). Frames of another size are
        scaled by FFmpeg.
    audio : ndarray, optional
        Mono float samples in [-1, 1] to mux as AAC, the first sample with the first video frame; None or empty:
        no audio track.
    audio_rate : int, optional
        Samples per second of ``audio`` (needed with it).

    Attributes
    ----------
    codec : str
        The encoder used (``codec`` resolved).
    count : int
        Frames written so far.
    """

    def __init__(
        self,
        fps: float,
        *,
        codec: str = "auto",
        crf: int = 23,
        preset: str = "veryfast",
        pixels: Literal["rgb24", "gray"] = "rgb24",
        size: tuple[int, int] | None = None,
        audio: np.ndarray | None = None,
        audio_rate: int | None = None,
    ):
        import av

        if pixels not in ("rgb24", "gray"):
            raise ValueError(f"pixels must be 'rgb24' or 'gray', not {pixels!r}")
        self.audio, self.audio_rate = None, None
        if audio is not None and len(audio):
            if audio_rate is None:
                raise ValueError("audio needs its audio_rate")
            self.audio, self.audio_rate = audio, int(audio_rate)
        self.codec = video_codec_name(codec)
        self.crf, self.preset, self.pixels, self.size = crf, preset, pixels, size
        self.rate = Fraction(fps).limit_denominator(1001)
        self.buffer = io.BytesIO()
        self.container = av.open(self.buffer, mode="w", format="mp4")
        self.video = self.astream = None
        self.count = 0

    def _add_streams(self, width: int, height: int) -> None:
        """The video stream and, with audio, the audio stream: both before the first packet is muxed, which
        writes the file's header."""
        video = self.container.add_stream(self.codec, rate=self.rate)
        video.width, video.height = width, height
        video.pix_fmt = "yuv420p"
        # one core, and byte-identical output from run to run and machine to machine: by default x264 picks its
        # thread count from the cores it may use, and its output depends on that count
        video.codec_context.thread_count = 1
        if self.codec == "libx264":
            # macroblock-tree rate control off: with it, x264 in PyAV's FFmpeg gave different bytes for the same
            # frames from one encode to the next (14 distinct files of 20 at 96 px); without, 20 of 20 agree
            video.options = {"crf": str(self.crf), "preset": self.preset, "x264-params": "mbtree=0"}
        else:
            video.codec_context.bit_rate = MPEG4_BIT_RATE
        if self.audio is not None:
            self.astream = self.container.add_stream("aac", rate=self.audio_rate)
            self.astream.layout = "mono"
        self.video = video

    def write(self, frames: np.ndarray) -> None:
        """Append a block of frames: (F, H, W, 3) uint8 for "rgb24", (F, H, W) uint8 for "gray"."""
        frames = np.asarray(frames)
        if frames.ndim != (4 if self.pixels == "rgb24" else 3) or frames.dtype != np.uint8:
            shape = "(F, H, W, 3)" if self.pixels == "rgb24" else "(F, H, W)"
            raise ValueError(f"{self.pixels} frames must be {shape} uint8, got {frames.shape} {frames.dtype}")
        if self.pixels == "gray":
            h, w = frames.shape[1:]
            frames = np.pad(frames, ((0, 0), (0, h % 2), (0, w % 2)), mode="edge")
        if self.video is None:
            self._add_streams(*(self.size or (frames.shape[2], frames.shape[1])))
        av_frames = video_frames(frames, self.pixels, self.count, self.rate)
        encode_frames(self.container, self.video, av_frames, flush=False)
        self.count += len(frames)

    def close(self) -> bytes:
        """Flush the encoders, mux the audio and finish the file; its bytes."""
        if self.video is None and self.size is not None:
            self._add_streams(*self.size)  # no frames: an empty video track of the given size
        if self.video is not None:
            encode_frames(self.container, self.video, ())
        if self.astream is not None:
            encode_frames(self.container, self.astream, audio_frames(self.astream, self.audio, self.audio_rate))
        self.container.close()
        return self.buffer.getvalue()


def video_frames(frames: np.ndarray, pixels: str, start: int, rate: Fraction):
    """PyAV frames of a block, numbered from ``start``, with explicit timestamps (without them x264's rate control
    sees undefined frame times and the output varies from run to run).

    RGB frames go as they are (FFmpeg converts them to the stream's YUV 4:2:0); grey frames (even sizes) become
    YUV 4:2:0 planes themselves: luma in the video (limited) range players expect, chroma constant at 128.
    """
    import av

    if pixels == "gray":
        h, w = frames.shape[1:]
        chroma = np.full((h // 2, w), 128, dtype=np.uint8)  # U and V planes (h/2 x w/2 each), grey: no colour
    for index, image in enumerate(frames, start):
        if pixels == "gray":
            luma = np.round(16 + image * (219 / 255)).astype(np.uint8)  # video (limited) range, as players expect
            frame = av.VideoFrame.from_ndarray(np.concatenate([luma, chroma]), format="yuv420p")
        else:
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="rgb24")
        frame.pts = index
        frame.time_base = 1 / rate
        yield frame


def audio_frames(stream, audio: np.ndarray, rate: int):
    """Mono float frames of the encoder's frame size with explicit timestamps, which let the encoder mark its
    priming samples; the MP4 edit list then skips them, so the first audio sample plays with the first video
    frame."""
    import av

    if not stream.codec_context.is_open:
        stream.codec_context.open()
    step = stream.codec_context.frame_size or 1024
    samples = np.asarray(audio, np.float32).reshape(1, -1)
    for start in range(0, samples.shape[1], step):
        chunk = av.AudioFrame.from_ndarray(
            np.ascontiguousarray(samples[:, start : start + step]), format="flt", layout="mono"
        )
        chunk.sample_rate = rate
        chunk.pts = start
        chunk.time_base = Fraction(1, rate)
        yield chunk


def encode_frames(container, stream, frames, *, flush: bool = True) -> None:
    """Encode and mux every frame, then (``flush``) drain the encoder: the last frames' packets."""
    for frame in frames:
        for packet in stream.encode(frame):
            container.mux(packet)
    if flush:
        for packet in stream.encode(None):
            container.mux(packet)
