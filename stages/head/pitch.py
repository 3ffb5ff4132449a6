"""Pitch extraction, cleaning and segmentation of speech (paper Sec. 5.1), with Praat exports for checking
(``stages.head.praat_files``).

One code path serves the test take and the motion database: the input is either an artifact carrying audio per
sequence (a tracking artifact or a headdb artifact: ``audio``, ``audio_bounds``, meta ``labels``, ``audio_rate``,
``audio_offset``) or labelled audio files (``stages.head.utterances``). Every time this stage outputs is on the sequence clock: 0 is the first
motion (video) frame, so segments slice the head motion directly.

Segments run from one voiced onset to the next (the last one to the end of the utterance); a segment whose onset
follows a pause of at least ``breath_pause`` starts a sub-sentence (paper Sec. 5.4: breaths bound the path search).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from msflow import Input, Output, Result, Stage, UserError
from stages.head.praat_files import praat_exports
from stages.head.utterances import Utterance, utterances_from_artifact, utterances_from_files

PHRASE_FEATURES = (
    "speaking_rate",
    "voiced_mean",
    "voiced_std",
    "unvoiced_mean",
    "unvoiced_std",
    "voiced_fraction",
    "f0_min",
    "f0_max",
    "f0_mean",
    "f0_std",
)
#: phrase features that move with the speaker's pitch level (semitones relative to a reference median)
LEVEL_FEATURES = ("f0_min", "f0_max", "f0_mean")


# ----------------------------------------------------------------------------------------------------- maths


def semitones(f0_hz: np.ndarray, reference_hz: float | np.ndarray) -> np.ndarray:
    """12 log2(f0 / reference): pitch in semitones relative to a reference (a speaker's median)."""
    return 12.0 * np.log2(np.asarray(f0_hz, dtype=np.float64) / reference_hz)


def praat_pitch(
    samples: np.ndarray,
    rate: int,
    *,
    method: str = "ac",
    time_step: float = 0.01,
    floor: float = 60.0,
    ceiling: float = 500.0,
    voicing_threshold: float = 0.45,
    silence_threshold: float = 0.03,
) -> tuple[np.ndarray, np.ndarray]:
    """Praat's pitch tracker (autocorrelation ``ac`` or cross-correlation ``cc``) on a mono signal.

    Returns frame centre times (seconds from the first sample) and f0 in Hz with NaN where unvoiced.
    """
    import parselmouth

    sound = parselmouth.Sound(np.asarray(samples, dtype=np.float64), sampling_frequency=float(rate))
    kwargs = dict(
        time_step=time_step,
        pitch_floor=floor,
        pitch_ceiling=ceiling,
        voicing_threshold=voicing_threshold,
        silence_threshold=silence_threshold,
    )
    pitch = sound.to_pitch_ac(**kwargs) if method == "ac" else sound.to_pitch_cc(**kwargs)
    f0 = pitch.selected_array["frequency"].astype(np.float64)
    times = pitch.x1 + pitch.dx * np.arange(pitch.n_frames)
    return times, np.where(f0 > 0, f0, np.nan)


def frame_energy(samples: np.ndarray, rate: int, times: np.ndarray, window: float = 0.04) -> np.ndarray:
    """Loudness in dB (20 log10 of the RMS, floored at -100 dB) of ``window``-second frames of a mono signal
    centred at ``times`` (seconds from the first sample). Vectorised over frames through a cumulative sum."""
    x = np.asarray(samples, dtype=np.float64)
    power = np.concatenate([[0.0], np.cumsum(x * x)])
    half = max(1, int(round(window * rate / 2)))
    centre = np.round(np.asarray(times) * rate).astype(np.int64)
    lo, hi = np.clip(centre - half, 0, len(x)), np.clip(centre + half, 0, len(x))
    mean = (power[hi] - power[lo]) / np.maximum(hi - lo, 1)
    return 10.0 * np.log10(np.maximum(mean, 1e-10))


def voiced_runs(voiced: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and stop (exclusive) indices of the runs of True in a boolean array."""
    edges = np.diff(np.concatenate([[0], np.asarray(voiced, dtype=np.int8), [0]]))
    return np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)


def clean_pitch(
    f0: np.ndarray,
    time_step: float,
    *,
    human_range: tuple[float, float] = (50.0, 800.0),
    max_deviation: float | None = 10.0,
    max_gap: float = 0.03,
    min_voiced: float = 0.05,
) -> np.ndarray:
    """Sec. 5.1 cleaning of a raw contour (Hz, NaN unvoiced), in this order:

    1. drop values outside the human range, and (``max_deviation``) values farther than that many semitones from
       the utterance's median: octave errors, which Praat makes at voicing edges;
    2. fill unvoiced gaps shorter than ``max_gap`` seconds by linear interpolation in log frequency;
    3. drop voiced islands shorter than ``min_voiced`` seconds.
    """
    f0 = np.array(f0, dtype=np.float64, copy=True)
    f0[~((f0 >= human_range[0]) & (f0 <= human_range[1]))] = np.nan
    if max_deviation is not None and np.isfinite(f0).any():
        deviation = np.abs(semitones(f0, np.nanmedian(f0)))
        f0[~(deviation <= max_deviation)] = np.nan
    voiced = np.isfinite(f0)
    starts, stops = voiced_runs(~voiced)
    interior = (starts > 0) & (stops < len(f0)) & ((stops - starts) * time_step < max_gap - 1e-9)
    if interior.any():
        idx = np.flatnonzero(voiced)
        gaps = np.concatenate([np.arange(a, b) for a, b in zip(starts[interior], stops[interior])])
        f0[gaps] = np.exp(np.interp(gaps, idx, np.log(f0[idx])))
    starts, stops = voiced_runs(np.isfinite(f0))
    short = (stops - starts) * time_step < min_voiced - 1e-9
    for a, b in zip(starts[short], stops[short]):
        f0[a:b] = np.nan
    return f0


@dataclass
class Segmentation:
    segments: np.ndarray  # (n, 3) start (voiced onset), voiced end, end (next onset or utterance end)
    subsentence_start: np.ndarray  # (n,) bool: first segment, or onset after a pause >= breath_pause


def segment_pitch(
    times: np.ndarray, f0: np.ndarray, duration: float, *, time_step: float, breath_pause: float = 0.3
) -> Segmentation:
    """Segments from one voiced onset to the next (Sec. 5.1); a frame covers time_step centred on its time."""
    starts, stops = voiced_runs(np.isfinite(f0))
    if len(starts) == 0:
        return Segmentation(np.zeros((0, 3)), np.zeros(0, dtype=bool))
    onset = np.clip(times[starts] - time_step / 2, 0.0, duration)
    voiced_end = np.clip(times[stops - 1] + time_step / 2, 0.0, duration)
    end = np.concatenate([onset[1:], [duration]])
    keep = end > onset
    onset, voiced_end, end = onset[keep], voiced_end[keep], end[keep]
    pause = onset[1:] - voiced_end[:-1]
    subsentence = np.concatenate([[True], pause >= breath_pause - 1e-9])
    return Segmentation(np.stack([onset, np.minimum(voiced_end, end), end], axis=1), subsentence)


def phrase_features(times: np.ndarray, f0: np.ndarray, segments: np.ndarray, reference_hz: float) -> np.ndarray:
    """Phrase-level prosody features (Dellaert et al. 1996; paper Sec. 5.2), order ``PHRASE_FEATURES``.

    Rhythm: speaking rate (voiced runs per second of speech, from the first onset to the last voiced end), mean
    and standard deviation of voiced and of unvoiced (between runs) lengths in seconds, voiced fraction. Pitch in
    semitones relative to ``reference_hz`` (the speaker's median): min and max (5th and 95th percentiles, robust to
    the odd tracking error), mean, standard deviation. All NaN when nothing is voiced.
    """
    voiced = np.isfinite(f0)
    if not voiced.any() or len(segments) == 0:
        return np.full(len(PHRASE_FEATURES), np.nan)
    voiced_lengths = segments[:, 1] - segments[:, 0]
    unvoiced_lengths = segments[1:, 0] - segments[:-1, 1]
    span = max(segments[-1, 1] - segments[0, 0], 1e-6)
    st = semitones(f0[voiced], reference_hz)
    return np.array(
        [
            len(segments) / span,
            voiced_lengths.mean(),
            voiced_lengths.std(),
            unvoiced_lengths.mean() if len(unvoiced_lengths) else 0.0,
            unvoiced_lengths.std() if len(unvoiced_lengths) else 0.0,
            voiced_lengths.sum() / span,
            np.percentile(st, 5),
            np.percentile(st, 95),
            st.mean(),
            st.std(),
        ]
    )


# ------------------------------------------------------------------------------------------------- the stage


PITCH_OUTPUTS = {
    "f0": Output.array("f", shape=("pitch_frames",), dtype="float32", doc="cleaned f0 in Hz, NaN where unvoiced"),
    "f0_raw": Output.array("f", shape=("pitch_frames",), dtype="float32", doc="Praat's f0 in Hz, NaN unvoiced"),
    "pitch_time": Output.array("f", shape=("pitch_frames",), dtype="float64", doc="seconds on the sequence clock"),
    "energy": Output.array("f", shape=("pitch_frames",), dtype="float32", doc="loudness (dB) of 40 ms frames"),
    "pitch_utterance": Output.array("i", shape=("pitch_frames",), dtype="int32", doc="index into meta labels"),
    "segments": Output.array(
        "f",
        shape=("segments", 3),
        dtype="float64",
        doc="start (voiced onset), voiced end, end (next onset), sequence clock seconds",
    ),
    "segment_utterance": Output.array("i", shape=("segments",), dtype="int32"),
    "subsentence_start": Output.array("b", shape=("segments",), doc="segment begins a sub-sentence"),
    "phrase_features": Output.array(
        "f",
        shape=("utterances", len(PHRASE_FEATURES)),
        dtype="float64",
        doc="meta feature_names; NaN rows for utterances without voice",
    ),
    "speaker_median": Output.array("f", shape=("utterances",), dtype="float64", doc="Hz, reference of semitones"),
    "onsets": Output.array(
        "f", shape=("onsets",), dtype="float64", doc="audio onsets (spectral-flux peaks), sequence clock seconds"
    ),
    "onset_utterance": Output.array("i", shape=("onsets",), dtype="int32", doc="index into meta labels"),
    "speaker_spread": Output.array(
        "f", shape=("utterances",), dtype="float64", doc="standard deviation of the speaker's pitch in semitones"
    ),
    "utterance_duration": Output.array("f", shape=("utterances",), dtype="float64"),
    "textgrid": Output.file(
        ".TextGrid", doc="Praat TextGrid over the 'sound' file: utterance, segment, voiced, subsentence tiers"
    ),
    "pitchtier": Output.file(".PitchTier", doc="cleaned f0 over the 'sound' file"),
    "sound": Output.file(".wav", doc="the distinct utterances' audio back to back, for opening with the TextGrid"),
}


def _plot_pitch_segments(view, inputs=None, utterance: int = 0):
    """Paper Fig. 6: raw pitch (top) and the cleaned, segmented contour (bottom) of one utterance."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = view.meta["labels"]
    mask = view["pitch_utterance"] == utterance
    t, raw, clean = view["pitch_time"][mask], view["f0_raw"][mask], view["f0"][mask]
    seg_mask = view["segment_utterance"] == utterance
    segments, breaks = view["segments"][seg_mask], view["subsentence_start"][seg_mask]
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(9, 5), sharex=True, constrained_layout=True)
    top.plot(t, raw, ".", ms=3, color="0.3")
    top.set_title(f"raw pitch: {labels[utterance]}")
    colours = plt.cm.tab10(np.arange(len(segments)) % 10)
    for k, (a, v, b) in enumerate(segments):
        bottom.axvspan(a, b, color=colours[k], alpha=0.12)
        inside = (t >= a) & (t < b)
        bottom.plot(t[inside], clean[inside], "-", lw=2, color=colours[k])
        if breaks[k]:
            bottom.axvline(a, color="k", ls="--", lw=1)
    bottom.set_title("cleaned and segmented (dashed: sub-sentence starts)")
    for ax in (top, bottom):
        ax.set_ylabel("f0 (Hz)")
    bottom.set_xlabel("time (s)")
    return fig


class PitchParams(Stage.Params):
    method: Literal["ac", "cc"] = Field("ac", description="Praat's autocorrelation or cross-correlation tracker")
    time_step: float = Field(0.01, gt=0, le=0.1, description="seconds between pitch frames")
    floor: float = Field(60.0, gt=0, description="lowest f0 Praat looks for (Hz)")
    ceiling: float = Field(
        500.0, gt=0, validate_default=True, description="highest f0 Praat looks for (Hz); above floor"
    )
    voicing_threshold: float = Field(0.45, ge=0, le=1)
    silence_threshold: float = Field(0.03, ge=0, le=1)
    human_range: tuple[float, float] = Field((50.0, 800.0), description="f0 outside (Hz) is dropped (Sec. 5.1)")
    max_deviation: float | None = Field(
        10.0, gt=0, description="semitones from the utterance's median beyond which f0 is an octave error"
    )
    max_gap: float = Field(0.03, ge=0, description="unvoiced gaps shorter than this (s) are filled")
    min_voiced: float = Field(0.05, ge=0, description="voiced islands shorter than this (s) are dropped")
    breath_pause: float = Field(0.3, gt=0, description="a pause at least this long (s) starts a sub-sentence")
    median_over: Literal["speaker", "utterance"] = Field(
        "speaker", description="semitone reference: the median f0 of each speaker's takes, or of each utterance"
    )
    on_silence: Literal["error", "warn"] = Field(
        "warn", description="an utterance without voiced speech: an error, or a warning and no segments (a still head)"
    )
    onset_delta: float = Field(0.15, ge=0, le=1, description="onset peak height above the local mean (flux in 0..1)")
    onset_min_gap: float = Field(0.1, ge=0, description="shortest time (s) between two audio onsets")
    audio_rate: int = Field(16000, ge=4000, le=192000, description="decoding rate of audio files (Hz)")
    analysis_rate: int = Field(
        8000,
        ge=1000,
        validate_default=True,
        description="audio above this rate is resampled to it for Praat (speed; f0 << 4 kHz)",
    )

    @field_validator("human_range")
    @classmethod
    def _ordered_range(cls, value):
        if not 0 < value[0] < value[1]:
            raise ValueError(f"need 0 < low < high (got {list(value)})")
        return value

    @field_validator("ceiling")
    @classmethod
    def _ceiling_above_floor(cls, value, info):
        floor = info.data.get("floor")
        if floor is not None and not value > floor:
            raise ValueError(f"ceiling {value} Hz must be above floor {floor} Hz")
        return value

    @field_validator("analysis_rate")
    @classmethod
    def _rate_for_ceiling(cls, value, info):
        ceiling = info.data.get("ceiling")
        if ceiling is not None and value < 4 * ceiling:
            raise ValueError(f"{value} Hz is too low for a pitch ceiling of {ceiling} Hz (needs at least 4x)")
        return value


class Pitch(Stage):
    """Praat pitch, Sec. 5.1 cleaning, onset-to-onset segments, sub-sentence breaks, phrase features."""

    cheap = True

    Params = PitchParams
    inputs = {
        "source": Input.artifact(optional=True, doc="tracking or headdb artifact with audio per sequence"),
        "audio": Input.files(optional=True, doc="labelled audio files: WAV, FLAC, MP3 or any container PyAV decodes"),
    }
    outputs = PITCH_OUTPUTS
    figures = {"pitch_segments": _plot_pitch_segments}

    def run(self, params, inputs):
        if (inputs.get("source") is None) == (inputs.get("audio") is None):
            raise UserError("give exactly one of 'source' (an artifact with audio) or 'audio' (files)", field="inputs")
        if inputs.get("source") is not None:
            utterances = utterances_from_artifact(inputs["source"])
        else:
            utterances = utterances_from_files(inputs["audio"], params.audio_rate)
        if not utterances:
            raise UserError("no utterances to analyse", field="inputs")
        return pitch_result(utterances, params)


def analysis_signal(samples: np.ndarray, rate: int, analysis_rate: int) -> tuple[np.ndarray, int]:
    """The signal Praat analyses: resampled down to ``analysis_rate`` (anti-aliased) when recorded faster."""
    if rate <= analysis_rate:
        return samples, rate
    from math import gcd

    from scipy.signal import resample_poly

    g = gcd(int(rate), int(analysis_rate))
    return resample_poly(np.asarray(samples, dtype=np.float64), analysis_rate // g, rate // g), int(analysis_rate)


def analyse_audio(utt: Utterance, params) -> tuple[np.ndarray, ...]:
    """Praat pitch (raw and cleaned, on the sequence clock, NaN outside the utterance), audio onsets and loudness
    (dB, at the pitch frames) of one utterance's audio."""
    from stages.head.beats import audio_onsets

    if len(utt.samples) < int(0.1 * utt.rate):
        raise UserError(
            f"audio of '{utt.label}' is too short to analyse ({len(utt.samples)} samples)",
            file=utt.source,
            field=utt.field,
        )
    samples, rate = analysis_signal(utt.samples, utt.rate, params.analysis_rate)
    tau, raw = praat_pitch(
        samples,
        rate,
        method=params.method,
        time_step=params.time_step,
        floor=params.floor,
        ceiling=params.ceiling,
        voicing_threshold=params.voicing_threshold,
        silence_threshold=params.silence_threshold,
    )
    times = tau + utt.offset
    raw = np.where((times < 0) | (times > utt.duration), np.nan, raw)
    clean = clean_pitch(
        raw,
        params.time_step,
        human_range=params.human_range,
        max_deviation=params.max_deviation,
        max_gap=params.max_gap,
        min_voiced=params.min_voiced,
    )
    onsets = audio_onsets(
        utt.samples, utt.rate, offset=utt.offset, delta=params.onset_delta, min_gap=params.onset_min_gap
    )
    energy = frame_energy(utt.samples, utt.rate, times - utt.offset)
    return times, raw, clean, onsets[(onsets >= 0) & (onsets < utt.duration)], energy


def analyse_utterances(utterances: list[Utterance], params) -> list[dict]:
    """Pitch, cleaning, segmentation and onsets per utterance; utterances sharing audio are analysed once."""
    cache: dict[tuple, tuple] = {}
    analyses = []
    for utt in utterances:
        if utt.audio_key not in cache:
            cache[utt.audio_key] = analyse_audio(utt, params)
        times, raw, clean, onsets, energy = cache[utt.audio_key]
        if not np.isfinite(clean).any() and params.on_silence == "error":
            raise UserError(
                f"no voiced speech found in '{utt.label}' (pitch floor {params.floor} Hz, ceiling "
                f"{params.ceiling} Hz); set on_silence: warn to go on with no segments (a still head)",
                file=utt.source,
                field=utt.field,
            )
        seg = segment_pitch(times, clean, utt.duration, time_step=params.time_step, breath_pause=params.breath_pause)
        analyses.append(
            {"times": times, "raw": raw, "clean": clean, "segmentation": seg, "onsets": onsets, "energy": energy}
        )
    return analyses


def speaker_keys(utterances: list[Utterance], median_over: str) -> list[str]:
    """The group whose pitch each utterance's semitone reference pools: its speaker, or itself.

    Per speaker, every take must carry a speaker label unless there is only one take (mirrored copies share their
    original's audio): pooling unlabelled takes of several speakers would give them one median."""
    if median_over == "utterance":
        return [f"utterance {k}" for k in range(len(utterances))]
    takes = {u.audio_key for u in utterances}
    unlabelled = [u for u in utterances if u.speaker is None]
    if unlabelled and len(takes) > 1:
        first = unlabelled[0]
        raise UserError(
            f"take '{first.label}' has no speaker label, and pitch is normalised per speaker over {len(takes)} "
            "takes (median_over: speaker): label every take with a speaker (a {speaker} field in the input's "
            "file pattern, 'speaker:' beside its path, or the headdb stage's speaker param), or set "
            "median_over: utterance",
            file=first.source,
            field=f"{first.field}.speaker",
        )
    return [u.speaker or "" for u in utterances]


def speaker_statistics(keys: list[str], analyses: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """Median f0 (Hz) and spread (standard deviation of semitones relative to that median) of each utterance's
    group (``speaker_keys``), every utterance of the group pooled; NaN for a group without voice."""
    stats = {}
    for key in set(keys):
        pooled = np.concatenate([a["clean"] for k, a in zip(keys, analyses) if k == key])
        pooled = pooled[np.isfinite(pooled)]
        if len(pooled) == 0:
            stats[key] = (np.nan, np.nan)
            continue
        median = float(np.median(pooled))
        stats[key] = (median, float(np.std(semitones(pooled, median))))
    return np.array([stats[k][0] for k in keys]), np.array([stats[k][1] for k in keys])


def pitch_result(utterances: list[Utterance], params) -> Result:
    """The stage's result: per-utterance analyses, pooled per speaker, laid out as the ``PITCH_OUTPUTS``."""
    keys = speaker_keys(utterances, params.median_over)
    analyses = analyse_utterances(utterances, params)
    medians, spreads = speaker_statistics(keys, analyses)
    seg_counts = [len(a["segmentation"].segments) for a in analyses]
    arrays = _pitch_arrays(utterances, analyses, medians, spreads, seg_counts)
    arrays.update(praat_exports(utterances, analyses))
    voiced = np.concatenate([np.isfinite(a["clean"]) for a in analyses])
    meta = _pitch_meta(utterances, params, seg_counts)
    metrics = {
        "segments": int(sum(seg_counts)),
        "utterances": len(utterances),
        "voiced_fraction": float(voiced.mean()) if len(voiced) else 0.0,
        "mean_segment_length": float(np.mean(np.diff(arrays["segments"][:, [0, 2]], axis=1)))
        if sum(seg_counts)
        else 0.0,
        "subsentences": int(arrays["subsentence_start"].sum()),
    }
    warnings = [
        f"no voiced speech in '{u.label}' ({u.source}): no segments, the head stays at rest there"
        for u, n in zip(utterances, seg_counts)
        if n == 0
    ]
    return Result(arrays, meta, metrics, warnings)


def _pitch_arrays(
    utterances: list[Utterance],
    analyses: list[dict],
    medians: np.ndarray,
    spreads: np.ndarray,
    seg_counts: list[int],
) -> dict[str, np.ndarray]:
    """The numeric outputs: every utterance's frames, segments and onsets concatenated (with the index of their
    utterance), and one row of phrase features and speaker statistics per utterance."""
    features = np.stack(
        [phrase_features(a["times"], a["clean"], a["segmentation"].segments, m) for a, m in zip(analyses, medians)]
    )
    return {
        "f0": np.concatenate([a["clean"] for a in analyses]).astype(np.float32),
        "f0_raw": np.concatenate([a["raw"] for a in analyses]).astype(np.float32),
        "energy": np.concatenate([a["energy"] for a in analyses]).astype(np.float32),
        "pitch_time": np.concatenate([a["times"] for a in analyses]),
        "pitch_utterance": np.concatenate([np.full(len(a["times"]), k, np.int32) for k, a in enumerate(analyses)]),
        "segments": np.concatenate([a["segmentation"].segments for a in analyses]).reshape(-1, 3),
        "segment_utterance": np.repeat(np.arange(len(analyses), dtype=np.int32), seg_counts),
        "subsentence_start": np.concatenate([a["segmentation"].subsentence_start for a in analyses]).astype(bool),
        "phrase_features": features,
        "speaker_median": medians,
        "speaker_spread": spreads,
        "onsets": np.concatenate([a["onsets"] for a in analyses]),
        "onset_utterance": np.concatenate([np.full(len(a["onsets"]), k, np.int32) for k, a in enumerate(analyses)]),
        "utterance_duration": np.array([u.duration for u in utterances]),
    }


def _pitch_meta(utterances: list[Utterance], params, seg_counts: list[int]) -> dict:
    """The per-utterance labels and clocks, what the features are, the analysis settings, the silent utterances."""
    return {
        "labels": [u.label for u in utterances],
        "sources": [u.source for u in utterances],
        "speakers": [u.speaker for u in utterances],
        "fps": [u.fps for u in utterances],
        "frames": [u.frames for u in utterances],
        "audio_offset": [u.offset for u in utterances],
        "feature_names": list(PHRASE_FEATURES),
        "level_features": list(LEVEL_FEATURES),
        "feature_unit": "semitones relative to speaker_median; seconds; voiced runs per second",
        "time_step": params.time_step,
        "method": params.method,
        "breath_pause": params.breath_pause,
        "silent": [u.label for u, n in zip(utterances, seg_counts) if n == 0],
    }
