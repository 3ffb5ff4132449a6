"""Takes as data: which audio goes with each tracked video, and the checks that keep picture and sound together.

A take is one labelled video (``inputs.videos``) and, in the order tried:

1. a separate audio file with the same label (``inputs.audio``: WAV, FLAC, MP3, or any file FFmpeg reads),
   ``params.audio_offset`` seconds into it being the moment of the video's first frame (one number for every
   take, or ``{label: seconds}``); the audio is cut to the video's length, so in the artifact it starts at the
   first frame (``meta["audio_offset"]`` 0);
2. the video's own audio track, placed as its container says (``meta["audio_offset"]``: start of the audio
   relative to the first frame, e.g. -0.027 s for the CREMA-D FLVs);
3. no audio (a silent take: face only), allowed when ``params.audio`` is ``optional``.

Checks (each a UserError naming the file, and the input or param at fault): an audio file whose label has no
video; an offset at or past the end of the audio file; audio that ends more than ``params.audio_tolerance``
seconds before the video does; a take without audio when ``params.audio`` is ``required``; audio files given
while ``params.audio`` is ``none``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from msflow import UserError


@dataclass(frozen=True)
class AudioSource:
    """Where one take's audio comes from: a separate file (``separate``) or the video's own track."""

    path: Path
    field: str  # the input naming the file, for messages
    offset: float  # seconds into the file at the take's first frame (separate files only)
    offset_field: str  # the param naming the offset, for messages
    separate: bool


@dataclass(frozen=True)
class TakeAudio:
    """One take's decoded audio: mono samples, and their start relative to the first video frame (seconds)."""

    samples: np.ndarray
    offset_to_video: float
    source: str  # file name


def labels_fields(*inputs) -> dict[str, dict[str, str]]:
    """``{label: {field: value}}`` of labelled file inputs (``msflow.Files``), earlier inputs first; labels with
    no fields map to ``{}``. Every label of the first input appears."""
    first = inputs[0] or {}
    out: dict[str, dict[str, str]] = {str(label): {} for label in first}
    for files in inputs:
        for label, values in (getattr(files, "fields", None) or {}).items():
            if label in out:
                out[label].update({str(k): str(v) for k, v in values.items()})
    return out


def offset_for(label: str, offsets: float | dict[str, float]) -> tuple[float, str]:
    """This take's audio offset and the param field that set it."""
    if isinstance(offsets, dict):
        return float(offsets.get(label, 0.0)), f"params.audio_offset.{label}"
    return float(offsets), "params.audio_offset"


def audio_sources(
    takes: dict, audio_files: dict | None, params, takes_input: str = "inputs.videos"
) -> dict[str, AudioSource | None]:
    """Each take's audio source (None: nothing to take audio from), after checking that every audio file and
    every per-label offset belongs to a take. ``takes`` maps each label to its video (None: no video)."""
    audio_files = dict(audio_files or {})
    orphans = [label for label in audio_files if label not in takes]
    if orphans:
        label = orphans[0]
        raise UserError(
            f"audio file for label '{label}', but {takes_input} has no take with that label (labels: {sorted(takes)})",
            file=str(audio_files[label]),
            field=f"inputs.audio.{label}",
        )
    if audio_files and params.audio == "none":
        raise UserError("audio files are given but params.audio is 'none'", field="inputs.audio")
    if isinstance(params.audio_offset, dict):
        stray = sorted(set(params.audio_offset) - set(audio_files))
        if stray:
            raise UserError(
                f"an offset for '{stray[0]}', which has no separate audio file (offsets apply to inputs.audio; "
                f"audio files: {sorted(audio_files)})",
                field=f"params.audio_offset.{stray[0]}",
            )
    if params.audio == "none":
        return {label: None for label in takes}
    sources: dict[str, AudioSource | None] = {}
    for label, video in takes.items():
        if label in audio_files:
            offset, offset_field = offset_for(label, params.audio_offset)
            sources[label] = AudioSource(Path(audio_files[label]), f"inputs.audio.{label}", offset, offset_field, True)
        elif video is not None:
            sources[label] = AudioSource(Path(video), f"inputs.videos.{label}", 0.0, "", False)
        else:
            sources[label] = None
    return sources


def video_has_audio(path: Path) -> bool:
    import av

    try:
        with av.open(str(path)) as container:
            return bool(container.streams.audio)
    except (av.error.FFmpegError, OSError):
        return False


def check_covers_video(
    source: AudioSource, audio_end: float, video_end: float, tolerance: float, slack: float = 0.0
) -> None:
    """UserError when the audio ends more than ``tolerance`` (+ ``slack`` for durations read from headers)
    seconds before the video; both ends in seconds from the first frame."""
    if video_end - audio_end > tolerance + slack:
        raise UserError(
            f"the audio ends {video_end - audio_end:.2f} s before the video ({audio_end:.2f} s of audio "
            f"from the first frame, video {video_end:.2f} s; params.audio_tolerance = {tolerance:g} s)",
            file=str(source.path),
            field=source.field,
        )


def decode_separate(source: AudioSource, video_end: float, params) -> TakeAudio:
    """A separate audio file's window [offset, offset + video length)."""
    from stages.formats.audio import decode_audio, probe_audio

    info = probe_audio(source.path, field=source.field)
    audio = decode_audio(source.path, params.audio_rate, offset=source.offset, duration=video_end, field=source.field)
    if not len(audio.samples) or (info.duration and source.offset >= info.duration):
        length = info.duration or audio.duration
        raise UserError(
            f"audio_offset {source.offset:g} s is outside the audio ({length:.2f} s long)",
            file=str(source.path),
            field=source.offset_field,
        )
    check_covers_video(source, audio.duration, video_end, params.audio_tolerance)
    return TakeAudio(audio.samples, 0.0, source.path.name)


def decode_embedded(source: AudioSource, video_end: float, params) -> TakeAudio | None:
    """The video's own audio track; None when it has none and audio is optional."""
    from stages.formats.audio import decode_audio

    if not video_has_audio(source.path):
        if params.audio == "optional":
            return None
        label = source.field.rsplit(".", 1)[-1]
        raise UserError(
            f"the video has no audio track: give an audio file for it (inputs.audio.{label}), or set params.audio "
            "to 'optional' (silent takes allowed) or 'none'",
            file=str(source.path),
            field=source.field,
        )
    audio = decode_audio(source.path, params.audio_rate, field=source.field)
    check_covers_video(source, audio.offset_to_video + audio.duration, video_end, params.audio_tolerance)
    return TakeAudio(audio.samples, float(audio.offset_to_video), source.path.name)


def load_take_audio(source: AudioSource | None, video_end: float, params, field: str) -> TakeAudio | None:
    """The take's audio (None for a silent take when that is allowed); ``video_end`` is the end of its last
    frame in seconds from the first."""
    if params.audio == "none":
        return None
    if source is None:
        if params.audio == "required":
            raise UserError(
                "audio is required but this take has no video or audio file to take it from "
                "(set params.audio to 'optional' or 'none')",
                field=field,
            )
        return None
    if source.separate:
        return decode_separate(source, video_end, params)
    return decode_embedded(source, video_end, params)


#: header durations can be estimates (e.g. MP3 without a Xing header): the check before tracking allows this much
#: more than params.audio_tolerance; the exact check after decoding allows no more than the tolerance
HEADER_SLACK = 1.0


def preflight_audio(sources: dict[str, AudioSource | None], video_durations: dict[str, float], params) -> None:
    """Fail before any tracking when the headers already show a take's audio cannot work: a missing or
    unreadable audio file, an offset past its end, audio far shorter than the video, a video without audio
    when audio is required. ``video_durations`` are the videos' declared durations (0: unknown)."""
    from stages.formats.audio import probe_audio

    for label, source in sources.items():
        if source is None or params.audio == "none":
            continue
        video = video_durations.get(label, 0.0)
        if not source.separate:
            if not video_has_audio(source.path) and params.audio == "required":
                decode_embedded(source, video, params)  # raises the missing-track error
            continue
        info = probe_audio(source.path, field=source.field)
        if not info.duration:
            continue
        if source.offset >= info.duration + HEADER_SLACK:  # the exact check after decoding has no slack
            raise UserError(
                f"audio_offset {source.offset:g} s is outside the audio ({info.duration:.2f} s long)",
                file=str(source.path),
                field=source.offset_field,
            )
        if video:
            check_covers_video(source, info.duration - source.offset, video, params.audio_tolerance, HEADER_SLACK)
