"""The audio a pitch analysis reads, one utterance per sequence, and where each sits on the sequence clock: from
an artifact carrying audio per sequence (tracking or headdb) or from labelled audio files."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from msflow import UserError


@dataclass
class Utterance:
    """One sequence's audio and where it sits on the sequence clock."""

    label: str
    source: str
    samples: np.ndarray
    rate: int
    offset: float  # time of the first audio sample on the sequence clock (first video frame = 0)
    duration: float  # length of the sequence clock to cover (motion length if known, else audio end)
    fps: float | None
    frames: int | None
    speaker: str | None  # the take's speaker label; None when unlabelled
    audio_key: tuple  # utterances sharing audio (mirrored database copies) share this key
    field: str


def _per_sequence(value, n: int, default):
    if value is None:
        return [default] * n
    if isinstance(value, (list, tuple)):
        if len(value) != n:
            raise UserError(f"metadata list has {len(value)} entries for {n} sequences")
        return list(value)
    return [value] * n


def utterances_from_artifact(view, field: str = "inputs.source") -> list[Utterance]:
    """Audio per sequence of a tracking or headdb artifact (same conventions: audio, audio_bounds, meta)."""
    meta = view.meta
    if "audio" not in view or "audio_bounds" not in view:
        raise UserError(
            "the input artifact carries no audio (track the videos with audio, or give audio files)", field=field
        )
    audio = view["audio"]
    bounds = np.asarray(view["audio_bounds"], dtype=np.int64).reshape(-1, 2)
    labels = list(meta.get("labels") or [f"sequence{k}" for k in range(len(bounds))])
    if len(labels) != len(bounds):
        raise UserError(f"{len(labels)} labels but {len(bounds)} audio ranges", field=field)
    n = len(labels)
    rate = int(meta.get("audio_rate") or 16000)
    sources = _per_sequence(meta.get("sources"), n, None)
    offsets = _per_sequence(meta.get("audio_offset"), n, 0.0)
    fps = _per_sequence(meta.get("fps"), n, None)
    speakers = artifact_speakers(meta, labels)
    frames = [None] * n
    if "sequence" in view:
        counts = np.bincount(np.asarray(view["sequence"], dtype=np.int64), minlength=n)
        frames = [int(c) for c in counts[:n]]
    out = []
    for k, label in enumerate(labels):
        a, b = bounds[k]
        samples = np.asarray(audio[a:b], dtype=np.float32)
        offset = float(offsets[k] or 0.0)
        audio_end = offset + len(samples) / rate
        rate_k = float(fps[k]) if fps[k] else None
        n_frames = frames[k] if frames[k] else None
        duration = n_frames / rate_k if (rate_k and n_frames) else audio_end
        out.append(
            Utterance(
                str(label),
                str(sources[k] or label),
                samples,
                rate,
                offset,
                duration,
                rate_k,
                n_frames,
                speakers[k],
                (int(a), int(b), offset),
                f"{field}[{label}]",
            )
        )
    return out


def artifact_speakers(meta: dict, labels: list[str]) -> list[str | None]:
    """Speaker label per sequence: a headdb artifact's ``speakers`` list, else a tracking artifact's ``fields``
    (label -> {field: value}, the labelled-files contract), else None."""
    listed = meta.get("speakers")
    if isinstance(listed, list) and len(listed) == len(labels):
        return [None if x is None else str(x) for x in listed]
    fields = meta.get("fields") or {}
    return [(fields.get(label) or {}).get("speaker") for label in labels]


def utterances_from_files(files, rate: int, field: str = "inputs.audio") -> list[Utterance]:
    """Audio files (WAV, FLAC, MP3 or any container PyAV decodes) as utterances; speakers from the files'
    ``speaker`` fields."""
    from stages.formats.audio import decode_audio

    fields = getattr(files, "fields", {})

    out = []
    for label, path in files.items():
        decoded = decode_audio(path, rate, field=f"{field}.{label}")
        out.append(
            Utterance(
                label,
                path.name,
                decoded.samples,
                rate,
                0.0,
                decoded.duration,
                None,
                None,
                (fields.get(label) or {}).get("speaker"),
                (str(path),),
                f"{field}.{label}",
            )
        )
    return out
