"""Reading video frames with PyAV (FFmpeg): BGR frames with timestamps, and clear errors for broken files.

Frames and sizes are as a player shows them: a display matrix (a phone's portrait video) is applied
(stages/tracking/display.py).

A file is reported as truncated when the demuxer meets a cut-off packet or when no stream reaches the
duration the container declares (a copy that stopped early keeps its header's duration).

Frame times are the frames' timestamps. Where a timestamp is unusable (missing, or not after the previous frame's:
a file re-encoded without timestamps has every frame at 0) the frame is timed one frame at the stream's rate after
the previous one, as FFmpeg regenerates timestamps, with a warning; timestamps that increase unevenly (a phone
dropping frames, a variable frame rate) are kept.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from msflow import UserError
from stages.formats.audio import media_error_reason
from stages.tracking.display import IDENTITY, UprightPlanes, display_linear, displayed_size, show_upright

#: a stream may end this much (seconds) before the declared container duration without being called truncated
DURATION_SLACK = 0.25

#: the video packets whose timestamps ``frame_rate`` checks before trusting the stream's average rate
TIMING_PACKETS = 8


@dataclass
class VideoInfo:
    path: Path
    width: int
    height: int
    fps: float
    frames: int  # expected count (declared, or duration x fps); 0 when unknown
    duration: float  # container duration in seconds; 0 when unknown
    has_audio: bool


def _open(path: Path, field: str | None):
    import av

    if path.is_dir():
        raise UserError("is a folder, not a video file (give each clip as its own file)", file=str(path), field=field)
    if not path.is_file():
        raise UserError("video file not found", file=str(path), field=field)
    try:
        container = av.open(str(path))
    except (av.error.FFmpegError, OSError, ValueError) as exc:
        raise UserError(
            f"cannot open video: the file could not be read as a video ({media_error_reason(exc)})",
            file=str(path),
            field=field,
        ) from None
    if not container.streams.video:
        container.close()
        raise UserError("has no video stream", file=str(path), field=field)
    return container


def probe_video(path: str | Path, *, field: str | None = None) -> VideoInfo:
    """Size, frame rate and stream layout of a video, without decoding it."""
    path = Path(path)
    fps, timestamps_usable = frame_rate(path, field=field)
    with _open(path, field) as container:
        stream = container.streams.video[0]
        duration = float(container.duration) / 1e6 if container.duration else 0.0
        if stream.duration is not None and stream.time_base is not None:
            duration = float(stream.duration * stream.time_base)
        frames = int(stream.frames) if stream.frames else int(round(duration * fps))
        if not timestamps_usable and frames and fps > 0:
            duration = frames / fps  # the declared one spans the unusable timestamps (one frame when all are 0)
        width, height = displayed_size(
            _first_display(container, path, field), stream.codec_context.width, stream.codec_context.height
        )
        return VideoInfo(path, width, height, fps, frames, duration, bool(container.streams.audio))


def frame_rate(path: Path, *, field: str | None = None) -> tuple[float, bool]:
    """(frames per second, whether the first timestamps are usable) of a video's stream: its average rate, or
    when its first packets' timestamps are missing or repeated, the rate its codec declares (FFmpeg's average
    is then frames over the span of those timestamps: 125 frames all at 0 give 3125 fps). 0.0 when unknown."""
    with _open(path, field) as container:
        stream = container.streams.video[0]
        if _first_timestamps_usable(container, stream):
            return float(stream.average_rate or stream.base_rate or stream.guessed_rate or 0.0), True
        return float(stream.codec_context.framerate or stream.guessed_rate or 0.0), False


def _first_timestamps_usable(container, stream) -> bool:
    """Whether the first ``TIMING_PACKETS`` video packets all have timestamps, each a different one (packets
    come in decoding order, so they are compared as a set). A file that cannot be demuxed counts as usable:
    decoding it reports the damage."""
    import av

    stamps = []
    try:
        for packet in container.demux(stream):
            if packet.size:  # not the demuxer's empty end-of-stream packet
                stamps.append(packet.pts)
            if len(stamps) == TIMING_PACKETS:
                break
    except (av.error.FFmpegError, IndexError):
        return True
    return None not in stamps and len(set(stamps)) == len(stamps)


def _first_display(container, path: Path, field: str | None) -> np.ndarray:
    """The display matrix's 2 x 2 part of a video's first frame (identity when it has none or cannot decode: the
    decoding reports that)."""
    import av

    try:
        frame = next(container.decode(video=0))
    except (av.error.FFmpegError, StopIteration, IndexError):
        return IDENTITY
    return display_linear(frame, file=str(path), field=field)


def iter_decoded(path: str | Path, *, field: str | None = None, threads: int = 1) -> Iterator[tuple[float, object]]:
    """Yield (seconds since the first frame, PyAV VideoFrame) for every frame, in order.

    Times come from each frame's timestamp (variable frame rates are kept); a frame whose timestamp is missing
    or not after the previous frame's is timed one frame at the stream's rate after it (``FrameClock``).
    ``threads`` > 1 lets FFmpeg decode several frames at once on that many threads (frame and
    slice threading; the frames are bit-identical to single-threaded decoding).

    Raises UserError naming the file when it cannot be decoded, holds no frames, or is truncated: a damaged
    packet or a stream that ends before the duration the container declares (a copy that stopped early keeps
    its header's duration). The error comes when it is met, so a caller writing as it goes must not publish
    what it wrote.
    """

    path = Path(path)
    with _open(path, field) as container:
        video = container.streams.video[0]
        video.thread_type = "AUTO" if threads > 1 else "SLICE"
        video.thread_count = max(1, int(threads))
        declared = float(container.duration) / 1e6 if container.duration else 0.0
        clock = FrameClock(path, field, frame_rate(path, field=field)[0])
        count = 0
        stream_end = 0.0
        for packet, decoded in _packets(container, video, path, field, lambda: count):
            if packet.pts is not None and packet.time_base is not None:
                stream_end = max(stream_end, float((packet.pts + (packet.duration or 0)) * packet.time_base))
            for frame in decoded:
                t = clock.time(frame)
                count += 1
                yield t, frame
        if count == 0:
            raise UserError("video holds no decodable frames", file=str(path), field=field)
        clock.warn(count)
        start = float(container.start_time) / 1e6 if container.start_time else 0.0
        if declared > 0 and stream_end - start < declared - DURATION_SLACK:
            raise UserError(
                f"video is truncated: its streams end at {stream_end - start:.2f} s but the file "
                f"declares {declared:.2f} s ({count} frames decoded)",
                file=str(path),
                field=field,
            )


def _packets(container, video, path: Path, field: str | None, count):
    """(packet, decoded video frames) for every packet, then the decoder's flushed frames; UserError on a
    damaged packet (``count()`` frames decoded so far, for the message)."""
    import av

    packets = container.demux()
    while True:
        try:
            packet = next(packets)
            corrupt = packet.is_corrupt
            decoded = packet.decode() if packet.stream_index == video.index and not corrupt else []
        except StopIteration:
            return
        except (av.error.FFmpegError, IndexError) as exc:
            # IndexError: PyAV met a packet of a stream the header did not announce (a cut-off tag)
            raise UserError(
                f"video is unreadable or truncated after {count()} frames ({media_error_reason(exc)})",
                file=str(path),
                field=field,
            ) from None
        if corrupt:
            raise UserError(
                f"video is truncated or corrupt: a damaged packet after {count()} frames", file=str(path), field=field
            )
        yield packet, decoded


def iter_frames(
    path: str | Path, *, gray: bool = False, field: str | None = None
) -> Iterator[tuple[float, np.ndarray]]:
    """Yield (seconds since the first frame, frame) for every frame: BGR uint8 (h, w, 3) or gray (h, w).

    Gray frames are OpenCV's BGR-to-gray conversion of the BGR frames (not the raw luma plane), so every
    implementation that reads BGR frames crops alike. Errors as ``iter_decoded``.
    """
    for t, frame in iter_decoded(path, field=field):
        image = show_upright(frame.to_ndarray(format="bgr24"), display_linear(frame, file=str(path), field=field))
        yield t, (_bgr_to_gray(image) if gray else image)


def iter_planes(path: str | Path, *, field: str | None = None, threads: int = 1):
    """Yield (seconds since the first frame, ``planes.FramePlanes``) for every frame: decoded frames converted to
    BGR only where a warp reads them (see stages/tracking/planes.py). Errors as ``iter_decoded``."""
    from stages.tracking.planes import RegionConverter, frame_planes

    converter = RegionConverter()
    for t, frame in iter_decoded(path, field=field, threads=threads):
        planes, linear = frame_planes(frame, converter), display_linear(frame, file=str(path), field=field)
        yield t, (planes if np.array_equal(linear, IDENTITY) else UprightPlanes(planes, linear))


def _bgr_to_gray(image: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


class FrameClock:
    """Frame times in seconds since the first frame: each frame's timestamp, or where it is missing or not after
    the previous frame's, the previous frame's time plus one frame at ``fps`` (FFmpeg's regenerated timestamps).
    UserError naming the file when a frame needs that and there is no rate to time it by."""

    def __init__(self, path: Path, field: str | None, fps: float):
        self.path, self.field, self.fps = path, field, fps
        self.first: float | None = None
        self.anchor = 0.0  # the time of the last frame timed by its timestamp
        self.since = 0  # frames timed by the rate after it (counted, not summed: no rounding drift)
        self.last = 0.0
        self.retimed = 0

    def time(self, frame) -> float:
        stamp = _timestamp(frame)
        if self.first is None:
            self.first = stamp or 0.0
            return 0.0
        if stamp is not None and stamp - self.first > self.last:
            self.anchor = self.last = stamp - self.first
            self.since = 0
            return self.last
        if self.fps <= 0:
            raise UserError(
                "video frame timestamps are missing or repeated, and the stream declares no frame rate to time "
                "the frames by; re-encode it with timestamps (e.g. ffmpeg -i IN -r 30 OUT.mp4)",
                file=str(self.path),
                field=self.field,
            )
        self.retimed += 1
        self.since += 1
        self.last = self.anchor + self.since / self.fps
        return self.last

    def warn(self, frames: int) -> None:
        """Warn, naming the file, when frames were timed by the rate rather than by their timestamps."""
        if self.retimed:
            warnings.warn(
                f"{self.path}: {self.retimed} of {frames} frames have a timestamp that is missing or not after the "
                f"previous frame's (a raw stream, or a file re-encoded without timestamps); they are timed at the stream's "
                f"{self.fps:g} fps instead",
                UserWarning,
                stacklevel=2,
            )


def _timestamp(frame) -> float | None:
    if frame.pts is not None and frame.time_base is not None:
        return float(frame.pts * frame.time_base)
    return None


def read_frames(
    path: str | Path, *, gray: bool = False, field: str | None = None
) -> tuple[np.ndarray, list[np.ndarray]]:
    """All frames of a video in memory: (times (n,), frames)."""
    times, frames = [], []
    for t, frame in iter_frames(path, gray=gray, field=field):
        times.append(t)
        frames.append(frame)
    return np.array(times, dtype=np.float64), frames
