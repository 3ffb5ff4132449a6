"""Reading video frames with PyAV (FFmpeg): BGR frames with timestamps, and clear errors for broken files.

Frames and sizes are as a player shows them: a display matrix (a phone's portrait video) is applied
(stages/tracking/display.py).

A file is reported as truncated when the demuxer meets a cut-off packet or when no stream reaches the
duration the container declares (a copy that stopped early keeps its header's duration).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from msflow import UserError
from stages.tracking.display import IDENTITY, UprightPlanes, display_linear, displayed_size, show_upright

#: a stream may end this much (seconds) before the declared container duration without being called truncated
DURATION_SLACK = 0.25


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
        raise UserError(f"cannot open video: not a readable media file ({exc})", file=str(path), field=field) from None
    if not container.streams.video:
        container.close()
        raise UserError("has no video stream", file=str(path), field=field)
    return container


def probe_video(path: str | Path, *, field: str | None = None) -> VideoInfo:
    """Size, frame rate and stream layout of a video, without decoding it."""
    path = Path(path)
    with _open(path, field) as container:
        stream = container.streams.video[0]
        fps = float(stream.average_rate or stream.base_rate or stream.guessed_rate or 0.0)
        duration = float(container.duration) / 1e6 if container.duration else 0.0
        if stream.duration is not None and stream.time_base is not None:
            duration = float(stream.duration * stream.time_base)
        frames = int(stream.frames) if stream.frames else int(round(duration * fps))
        width, height = displayed_size(
            _first_display(container, path, field), stream.codec_context.width, stream.codec_context.height
        )
        return VideoInfo(path, width, height, fps, frames, duration, bool(container.streams.audio))


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

    Times come from each frame's timestamp (variable frame rates are kept), or frame index / frame rate when a
    frame has none. ``threads`` > 1 lets FFmpeg decode several frames at once on that many threads (frame and
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
        fps = float(video.average_rate or video.guessed_rate or 0.0)
        first_pts = None
        count = 0
        stream_end = 0.0
        for packet, decoded in _packets(container, video, path, field, lambda: count):
            if packet.pts is not None and packet.time_base is not None:
                stream_end = max(stream_end, float((packet.pts + (packet.duration or 0)) * packet.time_base))
            for frame in decoded:
                t = _frame_time(frame, count, fps)
                if first_pts is None:
                    first_pts = t
                count += 1
                yield t - first_pts, frame
        if count == 0:
            raise UserError("video holds no decodable frames", file=str(path), field=field)
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
                f"video is unreadable or truncated after {count()} frames ({type(exc).__name__}: {exc})",
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


def _frame_time(frame, index: int, fps: float) -> float:
    if frame.pts is not None and frame.time_base is not None:
        return float(frame.pts * frame.time_base)
    return index / fps if fps > 0 else float(index)


def read_frames(
    path: str | Path, *, gray: bool = False, field: str | None = None
) -> tuple[np.ndarray, list[np.ndarray]]:
    """All frames of a video in memory: (times (n,), frames)."""
    times, frames = [], []
    for t, frame in iter_frames(path, gray=gray, field=field):
        times.append(t)
        frames.append(frame)
    return np.array(times, dtype=np.float64), frames
