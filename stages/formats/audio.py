"""Audio decoding shared by tracking ingest and the head-motion database: any container PyAV (FFmpeg) reads.

parselmouth reads WAV/FLAC/MP3/AIFF only, so audio inside video containers (FLV, MP4, MOV) and OGG files is
decoded here to mono float32 at a chosen rate, and handed to parselmouth as a numpy array.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from msflow import UserError


@dataclass
class DecodedAudio:
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


def decode_audio(path: str | Path, rate: int = 16000, *, field: str | None = None) -> DecodedAudio:
    """Decode the first audio stream of ``path`` to mono float32 resampled to ``rate`` Hz.

    Raises UserError naming the file when it cannot be opened or has no audio stream.
    """
    import av

    path = Path(path)
    try:
        container = av.open(str(path))
    except (av.error.FFmpegError, OSError) as exc:
        raise UserError(f"cannot open media file ({exc})", file=str(path), field=field) from None
    with container:
        if not container.streams.audio:
            raise UserError(
                "has no audio track (set the stage's audio param to 'none' to go without)", file=str(path), field=field
            )
        stream = container.streams.audio[0]
        video_start = None
        if container.streams.video:
            vs = container.streams.video[0]
            if vs.start_time is not None and vs.time_base is not None:
                video_start = float(vs.start_time * vs.time_base)
        resampler = av.AudioResampler(format="flt", layout="mono", rate=rate)
        chunks: list[np.ndarray] = []
        start = None
        try:
            for frame in container.decode(stream):
                if start is None and frame.pts is not None and frame.time_base is not None:
                    start = float(frame.pts * frame.time_base)
                for out in resampler.resample(frame):
                    chunks.append(out.to_ndarray().reshape(-1))
            for out in resampler.resample(None):
                chunks.append(out.to_ndarray().reshape(-1))
        except av.error.FFmpegError as exc:
            raise UserError(f"audio stream is unreadable or truncated ({exc})", file=str(path), field=field) from None
    if not chunks:
        raise UserError("audio track holds no samples", file=str(path), field=field)
    samples = np.concatenate(chunks).astype(np.float32, copy=False)
    return DecodedAudio(samples, rate, start or 0.0, video_start)
