"""Synthetic speech + head-motion takes with known structure, for the head-motion tests and bench scripts.

Each phrase has two or three sentences of voiced "syllables" (a harmonic complex at a chosen f0 contour) separated
by short unvoiced consonant gaps (noise) and breath pauses between sentences. Its head motion is driven by the
pitch: the head-pitch (nod) velocity follows the pitch above the speaker's base while voiced, with a spring back to
rest, plus slow yaw and roll wander (smooth noise). Four speaking styles differ in pitch level and range, syllable rate and motion
size, like the emotions of a real database. Ground truth kept per phrase: syllable onsets, sentence starts, f0.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

CONTROL_RATE = 100.0  # Hz of the f0 / voicing / motion simulation

STYLES = {
    #          base Hz, range st, syllable s,   gap s,         motion gain, wander time constant s
    "neutral": dict(base=120.0, range=2.5, syllable=(0.12, 0.25), gap=(0.05, 0.10), gain=1.0, tau=1.2),
    "happy": dict(base=150.0, range=5.0, syllable=(0.10, 0.20), gap=(0.04, 0.08), gain=1.8, tau=0.7),
    "angry": dict(base=140.0, range=4.0, syllable=(0.09, 0.18), gap=(0.04, 0.08), gain=2.2, tau=0.5),
    "sad": dict(base=105.0, range=1.5, syllable=(0.18, 0.32), gap=(0.06, 0.14), gain=0.5, tau=2.0),
}
SPEAKER_BASE = 125.0


@dataclass
class Phrase:
    label: str
    style: str
    audio: np.ndarray  # float32 mono
    audio_rate: int
    f0: np.ndarray  # Hz at CONTROL_RATE, NaN unvoiced
    onsets: np.ndarray  # syllable onset times (s)
    voiced_ends: np.ndarray  # syllable voiced end times (s)
    sentence_starts: np.ndarray  # onset times of each sentence's first syllable
    angles: np.ndarray  # (frames, 3) yaw, pitch, roll radians at CONTROL_RATE
    translation: np.ndarray  # (frames, 3) millimetres at CONTROL_RATE
    extra: dict = field(default_factory=dict)

    @property
    def duration(self) -> float:
        return len(self.audio) / self.audio_rate

    def motion_at(self, fps: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Times, angles and translation sampled at ``fps`` over the phrase."""
        n = int(np.floor(self.duration * fps))
        t = np.arange(n) / fps
        tc = np.arange(len(self.angles)) / CONTROL_RATE
        ang = np.stack([np.interp(t, tc, self.angles[:, k]) for k in range(3)], axis=1)
        tr = np.stack([np.interp(t, tc, self.translation[:, k]) for k in range(3)], axis=1)
        return t, ang, tr


def _wander(rng, n: int, tau: float, sigma: float, dt: float) -> np.ndarray:
    """Smooth random wander: white noise low-passed by a Gaussian of width tau / 3 seconds, std sigma."""
    from scipy.ndimage import gaussian_filter1d

    path = gaussian_filter1d(rng.standard_normal(n + 200), tau / 3 / dt, mode="wrap")[100:-100]
    return path / max(path.std(), 1e-12) * sigma


def synth_phrase(
    rng: np.random.Generator, style: str, label: str, *, sentences: int | None = None, audio_rate: int = 16000
) -> Phrase:
    s = STYLES[style]
    dt = 1.0 / CONTROL_RATE
    n_sent = sentences or int(rng.integers(2, 4))
    pieces = []  # (start, voiced length, f0 contour in semitones re style base)
    t = float(rng.uniform(0.25, 0.4))
    sentence_starts = []
    for k in range(n_sent):
        n_syl = int(rng.integers(4, 9))
        sentence_starts.append(t)
        for j in range(n_syl):
            length = float(rng.uniform(*s["syllable"]))
            declination = -2.0 * j / max(n_syl - 1, 1)
            amp = s["range"] * rng.uniform(0.3, 1.0) * rng.choice([-1.0, 1.0])
            shape = rng.integers(3)
            pieces.append((t, length, declination, amp, shape))
            t += length
            if j < n_syl - 1:
                t += float(rng.uniform(*s["gap"]))
        if k < n_sent - 1:
            t += float(rng.uniform(0.4, 0.7))
    duration = t + float(rng.uniform(0.3, 0.5))
    n_ctrl = int(np.ceil(duration * CONTROL_RATE)) + 1
    tc = np.arange(n_ctrl) * dt
    st = np.full(n_ctrl, np.nan)
    for start, length, declination, amp, shape in pieces:
        inside = (tc >= start) & (tc < start + length)
        u = (tc[inside] - start) / length
        contour = [amp * np.sin(np.pi * u), amp * (u - 0.5), amp * (0.5 - u) + 0.5 * amp * np.sin(2 * np.pi * u)]
        st[inside] = declination + contour[shape]
    f0 = s["base"] * 2 ** (st / 12)

    # audio: harmonic complex at f0 in voiced parts, soft noise for consonant gaps, near silence in pauses
    n_audio = int(round(duration * audio_rate))
    ta = np.arange(n_audio) / audio_rate
    f0_audio = np.interp(ta, tc, np.nan_to_num(f0, nan=0.0))
    voiced_audio = np.interp(ta, tc, np.isfinite(f0).astype(float)) > 0.5
    f0_audio = np.where(voiced_audio, f0_audio, 0.0)
    phase = 2 * np.pi * np.cumsum(f0_audio) / audio_rate
    wave = sum(np.sin(h * phase) / h for h in range(1, 13))
    ramp = int(0.01 * audio_rate)
    envelope = np.convolve(voiced_audio.astype(float), np.ones(ramp) / ramp, mode="same")
    onsets = np.array([p[0] for p in pieces])
    ends = np.array([p[0] + p[1] for p in pieces])
    in_speech = (ta >= onsets[0]) & (ta <= ends[-1])
    consonant = in_speech & ~voiced_audio
    sentence_of = np.searchsorted(np.array(sentence_starts), ta, side="right") - 1
    syl_sentence = np.searchsorted(np.array(sentence_starts), onsets, side="right") - 1
    last_end = np.array([ends[syl_sentence == k].max() for k in range(n_sent)])
    in_pause = (ta > last_end[np.clip(sentence_of, 0, n_sent - 1)]) & (sentence_of < n_sent - 1)
    consonant &= ~in_pause
    audio = 0.4 * wave * envelope + rng.standard_normal(n_audio) * (0.03 * consonant + 0.0005)
    audio = (audio / np.abs(audio).max() * 0.6).astype(np.float32)

    # motion driven by pitch: nod velocity follows the pitch above the speaker's base while voiced
    gain = s["gain"]
    st_speaker = np.where(np.isfinite(f0), 12 * np.log2(np.nan_to_num(f0, nan=SPEAKER_BASE) / SPEAKER_BASE), 0.0)
    from scipy.ndimage import gaussian_filter1d

    drive = gaussian_filter1d(np.radians(1.6) * gain * st_speaker, 0.04 * CONTROL_RATE)
    nod_noise = _wander(rng, n_ctrl, 0.3, np.radians(8.0) * gain, dt)
    # pitch[k] = pitch[k-1] + dt (drive[k] + noise[k] - pitch[k-1] / 0.6): a leaky integrator
    from scipy.signal import lfilter

    pitch = lfilter([dt], [1.0, -(1 - dt / 0.6)], drive + nod_noise)
    yaw = _wander(rng, n_ctrl, s["tau"], np.radians(4.0) * gain, dt)
    roll = _wander(rng, n_ctrl, s["tau"], np.radians(1.5) * gain, dt)
    angles = np.stack([yaw, pitch, roll], axis=1)
    translation = np.stack([60.0 * yaw, 50.0 * pitch, _wander(rng, n_ctrl, s["tau"], 3.0, dt)], axis=1)
    return Phrase(label, style, audio, audio_rate, f0, onsets, ends, np.array(sentence_starts), angles, translation)


def synth_database(n_phrases: int = 67, *, seed: int = 0, audio_rate: int = 16000) -> list[Phrase]:
    """A paper-sized database by default: 67 phrases of two or three sentences, styles in turn."""
    rng = np.random.default_rng(seed)
    styles = list(STYLES)
    return [
        synth_phrase(rng, styles[k % len(styles)], f"p{k:02d}_{styles[k % len(styles)]}", audio_rate=audio_rate)
        for k in range(n_phrases)
    ]


def tracking_artifact(
    phrases: list[Phrase], fps: float = 30.0, *, audio_offset: float = 0.0, speaker: str | None = "synthetic"
):
    """A tracking-shaped artifact (rotation, translation, time, sequence, audio, audio_bounds, meta); every take
    labelled with ``speaker`` in meta ``fields`` (the tracking contract), or unlabelled when None."""
    from msflow.testing import artifact
    from stages.geometry.rotations import euler_to_quat

    rot, trans, time, seq, audio, bounds = [], [], [], [], [], []
    cursor = 0
    for k, p in enumerate(phrases):
        t, ang, tr = p.motion_at(fps)
        rot.append(euler_to_quat(ang[:, 0], ang[:, 1], ang[:, 2]))
        trans.append(tr + np.array([0.0, 0.0, 600.0]))
        time.append(t)
        seq.append(np.full(len(t), k, np.int32))
        audio.append(p.audio)
        bounds.append((cursor, cursor + len(p.audio)))
        cursor += len(p.audio)
    meta = {
        "labels": [p.label for p in phrases],
        "sources": [f"{p.label}.flv" for p in phrases],
        "fps": [fps] * len(phrases),
        "audio_rate": phrases[0].audio_rate,
        "audio_offset": [audio_offset] * len(phrases),
        "translation_units": "mm",
        "fields": {p.label: ({"speaker": speaker} if speaker else {}) for p in phrases},
    }
    return artifact(
        {
            "rotation": np.concatenate(rot),
            "translation": np.concatenate(trans),
            "time": np.concatenate(time),
            "sequence": np.concatenate(seq),
            "audio": np.concatenate(audio),
            "audio_bounds": np.array(bounds, dtype=np.int64),
        },
        meta,
    )


def pitch_driven(phrases: list[Phrase], gain_deg_per_semitone: float = 1.5) -> list[Phrase]:
    """The same phrases with head motion that is a known function of the voice: the head pitch angle is
    ``gain`` degrees per semitone of f0 above the speaker's base (0 where unvoiced), smoothed over 40 ms; yaw and
    roll stay still. A database of such takes must give back the function for held-out audio."""
    from dataclasses import replace

    from scipy.ndimage import gaussian_filter1d

    out = []
    for p in phrases:
        st = np.where(np.isfinite(p.f0), 12 * np.log2(np.nan_to_num(p.f0, nan=SPEAKER_BASE) / SPEAKER_BASE), 0.0)
        nod = gaussian_filter1d(np.radians(gain_deg_per_semitone) * st, 0.04 * CONTROL_RATE)
        n = len(p.angles)
        angles = np.stack([np.zeros(n), nod[:n], np.zeros(n)], axis=1)
        out.append(replace(p, angles=angles, translation=np.zeros((n, 3))))
    return out
