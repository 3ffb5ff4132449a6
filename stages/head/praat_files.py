"""Praat's text formats for checking the pitch analysis by ear and eye: a TextGrid with the utterances, segments,
voiced runs and sub-sentences, a PitchTier of the cleaned f0 and the WAV they lie over (paper Sec. 5.1's figures, as
files Praat opens)."""

from __future__ import annotations

import io

import numpy as np

from stages.head.utterances import Utterance


def _num(value) -> str:
    return repr(float(value))


def praat_string(text: str) -> str:
    """A string literal of Praat's text formats: in double quotes, each double quote inside doubled."""
    return '"' + str(text).replace('"', '""') + '"'


def _interval_tier(name: str, xmax: float, intervals: list[tuple[float, float, str]]) -> list[str]:
    """Lines of a long-format IntervalTier; gaps between the (sorted, disjoint) intervals become empty ones."""
    filled: list[tuple[float, float, str]] = []
    cursor = 0.0
    for a, b, label in sorted(intervals):
        a, b = max(a, cursor), min(b, xmax)
        if b - a <= 1e-9:
            continue
        if a - cursor > 1e-9:
            filled.append((cursor, a, ""))
        filled.append((a, b, label))
        cursor = b
    if xmax - cursor > 1e-9 or not filled:
        filled.append((cursor, xmax, ""))
    lines = [
        '        class = "IntervalTier"',
        f"        name = {praat_string(name)}",
        "        xmin = 0",
        f"        xmax = {_num(xmax)}",
        f"        intervals: size = {len(filled)}",
    ]
    for k, (a, b, label) in enumerate(filled, 1):
        lines += [
            f"        intervals [{k}]:",
            f"            xmin = {_num(a)}",
            f"            xmax = {_num(b)}",
            f"            text = {praat_string(label)}",
        ]
    return lines


def textgrid_text(xmax: float, tiers: list[tuple[str, list[tuple[float, float, str]]]]) -> str:
    """A Praat TextGrid (long text format) with one IntervalTier per (name, intervals)."""
    lines = [
        'File type = "ooTextFile"',
        'Object class = "TextGrid"',
        "",
        "xmin = 0",
        f"xmax = {_num(xmax)}",
        "tiers? <exists>",
        f"size = {len(tiers)}",
        "item []:",
    ]
    for k, (name, intervals) in enumerate(tiers, 1):
        lines.append(f"    item [{k}]:")
        lines += _interval_tier(name, xmax, intervals)
    return "\n".join(lines) + "\n"


def pitchtier_text(xmax: float, times: np.ndarray, values: np.ndarray) -> str:
    """A Praat PitchTier (long text format) with one point per (time, Hz)."""
    lines = [
        'File type = "ooTextFile"',
        'Object class = "PitchTier"',
        "",
        "xmin = 0",
        f"xmax = {_num(xmax)}",
        f"points: size = {len(times)}",
    ]
    for k, (t, v) in enumerate(zip(times, values), 1):
        lines += [f"points [{k}]:", f"    number = {_num(t)}", f"    value = {_num(v)}"]
    return "\n".join(lines) + "\n"


def wav_bytes(samples: np.ndarray, rate: int) -> bytes:
    """16-bit PCM mono WAV of float samples in [-1, 1]."""
    import wave

    pcm = (np.clip(np.asarray(samples, dtype=np.float32), -1, 1) * 32767).astype("<i2")
    buffer = io.BytesIO()
    with wave.open(buffer, "wb") as out:
        out.setnchannels(1)
        out.setsampwidth(2)
        out.setframerate(int(rate))
        out.writeframes(pcm.tobytes())
    return buffer.getvalue()


def praat_exports(utterances: list[Utterance], analyses: list[dict]) -> dict[str, bytes]:
    """TextGrid, PitchTier and WAV over the distinct utterances' audio laid back to back."""
    rate = utterances[0].rate
    chunks, tiers, tier_times, tier_values, base = _lay_out_utterances(utterances, analyses, rate)
    xmax = max(base, 1e-3)
    times = np.concatenate(tier_times) if tier_times else np.zeros(0)
    values = np.concatenate(tier_values) if tier_values else np.zeros(0)
    inside = (times >= 0) & (times <= xmax)
    textgrid = textgrid_text(
        xmax,
        [
            ("utterance", tiers["utterance"]),
            ("segment", _clip_intervals(tiers["segment"], xmax)),
            ("voiced", _clip_intervals(tiers["voiced"], xmax)),
            ("subsentence", _clip_intervals(tiers["subsentence"], xmax)),
        ],
    )
    return {
        "textgrid": textgrid.encode("utf-8"),
        "pitchtier": pitchtier_text(xmax, times[inside], values[inside]).encode("utf-8"),
        "sound": wav_bytes(np.concatenate(chunks), rate),
    }


def _lay_out_utterances(utterances: list[Utterance], analyses: list[dict], rate: int) -> tuple:
    """The distinct utterances' audio back to back at ``rate`` (utterances sharing audio are placed once): the
    audio chunks, the TextGrid tiers' intervals and the cleaned pitch points (times, Hz), all on the wav's clock,
    and the total length in seconds."""
    chunks, tier_times, tier_values = [], [], []
    tiers: dict[str, list[tuple[float, float, str]]] = {"utterance": [], "segment": [], "voiced": [], "subsentence": []}
    placed: dict[tuple, float] = {}
    base = 0.0
    for utt, analysis in zip(utterances, analyses):
        if utt.audio_key in placed:
            continue
        samples = _samples_at_rate(utt, rate)
        placed[utt.audio_key] = base
        length = len(samples) / rate
        shift = base - utt.offset  # sequence clock -> wav time
        names = "|".join(u.label for u in utterances if u.audio_key == utt.audio_key)
        tiers["utterance"].append((base, base + length, names))
        segment, voiced, subsentence = _segment_intervals(analysis["segmentation"], shift)
        tiers["segment"] += segment
        tiers["voiced"] += voiced
        tiers["subsentence"] += subsentence
        ok = np.isfinite(analysis["clean"])
        tier_times.append(analysis["times"][ok] + shift)
        tier_values.append(analysis["clean"][ok])
        chunks.append(samples)
        base += length
    return chunks, tiers, tier_times, tier_values, base


def _samples_at_rate(utt: Utterance, rate: int) -> np.ndarray:
    """The utterance's audio at ``rate``, linearly interpolated when it was decoded at another rate."""
    samples = utt.samples
    if utt.rate != rate:
        new_n = int(round(len(samples) * rate / utt.rate))
        samples = np.interp(np.arange(new_n) * utt.rate / rate, np.arange(len(samples)), samples)
    return samples


def _segment_intervals(seg, shift: float) -> tuple[list, list, list]:
    """One utterance's segment (numbered), voiced ("V") and sub-sentence ("s1", ...) intervals, moved by
    ``shift`` from the sequence clock to the wav's; ``seg`` is a ``stages.head.pitch.Segmentation`` (not imported:
    the pitch stage imports this module)."""
    seg_tier, voiced_tier, sub_tier = [], [], []
    for k, (a, v, b) in enumerate(seg.segments):
        seg_tier.append((a + shift, b + shift, str(k + 1)))
        voiced_tier.append((a + shift, v + shift, "V"))
    starts = seg.segments[seg.subsentence_start, 0] if len(seg.segments) else np.zeros(0)
    bounds = np.concatenate([starts, [seg.segments[-1, 2]]]) if len(starts) else np.zeros(0)
    for k in range(len(starts)):
        sub_tier.append((bounds[k] + shift, bounds[k + 1] + shift, f"s{k + 1}"))
    return seg_tier, voiced_tier, sub_tier


def _clip_intervals(intervals: list[tuple[float, float, str]], xmax: float) -> list[tuple[float, float, str]]:
    """The intervals cut to [0, xmax], those left empty dropped: on the sequence clock a segment can reach before
    the first audio sample or past the last."""
    return [(max(a, 0.0), min(b, xmax), label) for a, b, label in intervals if min(b, xmax) > max(a, 0.0)]
