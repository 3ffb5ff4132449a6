"""Small media files for the tracking tests, written with PyAV: videos from frames (optionally with an audio
track, optionally with irregular timestamps) and audio files (WAV, FLAC, MP3) from samples."""

from fractions import Fraction
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CLIPS = {e: ROOT / "data" / "crema-d" / f"1001_DFA_{e}_XX.flv" for e in ("NEU", "HAP", "ANG", "SAD", "DIS", "FEA")}
AUDIO_CODECS = {".wav": "pcm_s16le", ".flac": "flac", ".mp3": "libmp3lame"}


def encode_audio(out, stream, samples: np.ndarray, rate: int) -> None:
    """Mux mono float samples through an open audio stream, 1024 samples per frame."""
    import av

    fmt = stream.codec_context.format.name if stream.codec_context.format else "flt"
    for k in range(0, len(samples), 1024):
        chunk = samples[None, k : k + 1024].astype(np.float32)
        frame = av.AudioFrame.from_ndarray(chunk, format="flt", layout="mono")
        frame.sample_rate = rate
        frame.pts = k
        if fmt != "flt":
            frame = av.AudioResampler(format=fmt, layout="mono", rate=rate).resample(frame)[0]
            frame.pts = k
        for packet in stream.encode(frame):
            out.mux(packet)
    for packet in stream.encode():
        out.mux(packet)


def write_video(path, frames, fps=30, audio=None, rate=16000, times=None, display=None):
    """Encode BGR frames (MPEG-4 part 2) and optional mono float audio (AAC) with PyAV; ``times`` (seconds per
    frame) makes a variable-frame-rate file; ``display``: a display matrix (nine integers, FFmpeg's layout) for
    players to turn the stored frames by."""
    import av

    with av.open(str(path), "w") as out:
        video = out.add_stream("mpeg4", rate=fps)
        video.height, video.width = frames[0].shape[:2]
        video.pix_fmt = "yuv420p"
        video.bit_rate = 2_000_000
        if display is not None:
            video.set_display_matrix(list(display))
        if times is not None:
            video.codec_context.time_base = Fraction(1, 1000)
        sound = out.add_stream("aac", rate=rate) if audio is not None else None
        for i, frame in enumerate(frames):
            picture = av.VideoFrame.from_ndarray(frame, format="bgr24")
            if times is not None:
                picture.pts = int(round(times[i] * 1000))
                picture.time_base = Fraction(1, 1000)
            for packet in video.encode(picture):
                out.mux(packet)
        for packet in video.encode():
            out.mux(packet)
        if sound is not None:
            encode_audio(out, sound, np.asarray(audio), rate)
    return path


def write_untimed_video(path, frames, fps=25):
    """BGR frames as H.264 whose every frame has timestamp 0 (a file re-encoded without timestamps; FFmpeg's
    average rate is then frames over one frame's duration, the declared rate still ``fps``)."""
    import av

    with av.open(str(path), "w") as out:
        video = out.add_stream("libx264", rate=fps)
        video.height, video.width = frames[0].shape[:2]
        video.pix_fmt = "yuv420p"
        for frame in frames:
            picture = av.VideoFrame.from_ndarray(frame, format="bgr24")
            picture.pts = 0
            for packet in video.encode(picture):
                out.mux(packet)
        for packet in video.encode():
            out.mux(packet)
    return path


def write_audio(path, samples, rate=48000):
    """A mono audio file in the codec its suffix names (.wav, .flac, .mp3)."""
    import av

    path = Path(path)
    with av.open(str(path), "w") as out:
        stream = out.add_stream(AUDIO_CODECS[path.suffix], rate=rate)
        stream.layout = "mono"
        encode_audio(out, stream, np.asarray(samples, dtype=np.float32), rate)
    return path


def first_frames(clip, n):
    """The first ``n`` BGR frames of a clip."""
    from stages.tracking.video import iter_frames

    frames = []
    for _, frame in iter_frames(clip):
        frames.append(frame)
        if len(frames) == n:
            break
    return frames
