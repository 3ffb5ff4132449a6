"""Audio decoding shared by tracking ingest, pitch analysis and the head-motion database: any container PyAV
(FFmpeg) reads (WAV, FLAC, MP3, AAC/M4A, OGG, and the audio track of FLV, MP4, MOV, MKV videos).

``decode_audio`` returns mono float32 at a chosen rate, optionally a window of the file (``offset`` seconds from
its first sample, ``duration`` seconds long) without decoding the rest: the demuxer seeks near the start of the
window and the samples before it are dropped, so the window starts exactly at ``offset`` (to one output sample).
``probe_audio`` reads a file's audio layout (duration, rate, channels) from its headers without decoding.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from msflow import UserError

#: windows starting later than this (seconds) seek instead of decoding from the start
SEEK_AFTER = 10.0
#: how far before the window the demuxer is asked to seek (seconds): packets hold up to ~0.1 s and seeking is
#: to the packet at or before the target, so a little margin keeps the window's first sample in what is decoded
SEEK_MARGIN = 2.0


@dataclass
class DecodedAudio:
    """Mono samples of one audio stream (or a window of it) and where they sit on the container's clock."""

    samples: np.ndarray  # (n,) float32 mono in [-1, 1]
    rate: int  # samples per second
    start: float  # time of the first sample, seconds, on the container's clock
    video_start: float | None  # time of the first video frame on the same clock (None: no video stream)

    @property
    def offset_to_video(self) -> float:
        """Start of the audio relative to the first video frame (negative: audio starts earlier)."""
        return self.start - (self.video_start or 0.0)

    @property
    def duration(self) -> float:
        return len(self.samples) / self.rate


@dataclass(frozen=True)
class AudioInfo:
    """What the headers say about a file's first audio stream; ``duration`` is 0.0 when they do not say."""

    path: Path
    duration: float
    rate: int
    channels: int
    codec: str


def media_error_reason(exc: BaseException) -> str:
    """FFmpeg's (or the OS's) reason a media file failed, for a message: "Invalid data found when processing
    input", without the errno number and file name ``str(exc)`` wraps it in (the message names the file)."""
    reason = getattr(exc, "strerror", None)
    return str(reason) if reason else str(exc)


def _open(path: Path, field: str | None):
    import av

    if not path.is_file():
        raise UserError("audio file not found", file=str(path), field=field)
    try:
        container = av.open(str(path))
    except (av.error.FFmpegError, OSError, ValueError) as exc:
        raise UserError(f"cannot open media file ({media_error_reason(exc)})", file=str(path), field=field) from None
    if not container.streams.audio:
        container.close()
        raise UserError(
            "has no audio track (set the stage's audio param to 'none' to go without)", file=str(path), field=field
        )
    return container


def _stream_duration(container, stream) -> float:
    if stream.duration is not None and stream.time_base is not None:
        return float(stream.duration * stream.time_base)
    return float(container.duration) / 1e6 if container.duration else 0.0


def probe_audio(path: str | Path, *, field: str | None = None) -> AudioInfo:
    """Duration, rate, channels and codec of the first audio stream of ``path``, from its headers.

    Raises UserError naming the file when it is missing, unreadable or holds no audio stream.
    """
    path = Path(path)
    with _open(path, field) as container:
        stream = container.streams.audio[0]
        ctx = stream.codec_context
        return AudioInfo(path, _stream_duration(container, stream), int(ctx.sample_rate), int(ctx.channels), ctx.name)


def _video_start(container) -> float | None:
    if not container.streams.video:
        return None
    vs = container.streams.video[0]
    if vs.start_time is not None and vs.time_base is not None:
        return float(vs.start_time * vs.time_base)
    return None


def _decode_resampled(container, stream, rate: int, stop: float | None, path: Path, field: str | None):
    """Resampled mono chunks from the current position, the time of the first decoded input sample, and
    whether decoding stopped early at ``stop`` (container seconds)."""
    import av

    resampler = av.AudioResampler(format="flt", layout="mono", rate=rate)
    chunks: list[np.ndarray] = []
    first = None
    try:
        for frame in container.decode(stream):
            if frame.pts is not None and frame.time_base is not None:
                t = float(frame.pts * frame.time_base)
                if first is None:
                    first = t
                if stop is not None and t > stop:
                    break
            for out in resampler.resample(frame):
                chunks.append(out.to_ndarray().reshape(-1))
        for out in resampler.resample(None):
            chunks.append(out.to_ndarray().reshape(-1))
    except av.error.FFmpegError as exc:
        raise UserError(
            f"audio stream is unreadable or truncated ({media_error_reason(exc)})", file=str(path), field=field
        ) from None
    return chunks, first


def decode_audio(
    path: str | Path,
    rate: int = 16000,
    *,
    offset: float = 0.0,
    duration: float | None = None,
    field: str | None = None,
) -> DecodedAudio:
    """Decode the first audio stream of ``path`` to mono float32 resampled to ``rate`` Hz.

    Parameters
    ----------
    path : str or Path
        Any file FFmpeg reads with an audio stream (an audio file, or a video with sound).
    rate : int
        Output sample rate (Hz).
    offset : float
        Seconds from the stream's first sample to the first returned sample (>= 0).
    duration : float, optional
        Seconds to return at most (default: to the end of the stream). Fewer samples come back when the stream
        ends first; none when ``offset`` is at or past its end (the caller decides whether that is an error).
    field : str, optional
        Where the file was named (for error messages).

    Returns
    -------
    DecodedAudio
        ``start`` is the first returned sample's time on the container's clock, so ``offset_to_video`` places it
        against the first video frame of the same file.

    Raises
    ------
    UserError
        Naming the file when it cannot be opened, has no audio stream, or its audio cannot be decoded.
    """
    if offset < 0 or not np.isfinite(offset):
        raise ValueError(f"offset must be a finite number >= 0, got {offset}")
    path = Path(path)
    seek = offset > SEEK_AFTER  # seek near the window instead of decoding everything before it
    while True:
        with _open(path, field) as container:
            stream = container.streams.audio[0]
            video_start = _video_start(container)
            origin = float(stream.start_time * stream.time_base) if stream.start_time is not None else 0.0
            if seek:
                target = origin + offset - SEEK_MARGIN
                container.seek(int(target / stream.time_base), stream=stream, backward=True, any_frame=False)
            stop = None if duration is None else origin + offset + duration + 1.0
            chunks, first = _decode_resampled(container, stream, rate, stop, path, field)
        if first is None:
            first = origin
        if not seek or first <= origin + offset:
            break
        seek = False  # the demuxer landed after the window's start: decode from the beginning instead
    samples = np.concatenate(chunks).astype(np.float32, copy=False) if chunks else np.zeros(0, np.float32)
    # resampled sample k sits at first + k / rate: drop what precedes the window, cut what follows it
    skip = max(0, int(round((origin + offset - first) * rate)))
    samples = samples[skip:]
    if duration is not None:
        samples = samples[: int(round(duration * rate))]
    if not len(samples) and offset == 0 and duration != 0:
        raise UserError("audio track holds no samples", file=str(path), field=field)
    return DecodedAudio(np.ascontiguousarray(samples), rate, first + skip / rate, video_start)
