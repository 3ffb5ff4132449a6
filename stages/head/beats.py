"""Beats of speech and of head motion, and how well they line up (the "beat align" measure of talking-head work).

Audio beats are onsets: peaks of the spectral flux (the summed rise of the log-magnitude spectrum from one frame to
the next), picked like a percussive onset detector (a local maximum, above the local mean by ``delta``, at least
``min_gap`` after the previous one). Pitch accents are the local maxima of the voice pitch (semitones) whose
prominence is at least ``prominence`` semitones, inside voiced runs.

Head beats are kinematic beats of the head's angular speed after Gaussian smoothing: its local maxima (the strokes of
nods and turns, ``kind="peaks"``) or its local minima (the moments a movement stops or reverses, ``"minima"``, the
dance-motion convention). On real talking-head footage the strokes line up with speech onsets and pitch accents
and the stops do not (docs/head.md, calibration). The beat alignment of a motion with a set of audio beats is

    BA = 1/|B_head| sum_{b in B_head} exp(-d(b)^2 / (2 sigma^2)),   d(b) = distance to the nearest audio beat,

as in Li et al. (AI Choreographer, ICCV 2021) and the talking-head work that adopted it for head pose: 1 when every
head beat falls on an audio beat, and a chance level set by the density of audio beats when their timing is
unrelated (``chance_alignment`` gives it for a regular grid). A motion without beats (a still head) scores 0.
"""

from __future__ import annotations

import numpy as np

# ------------------------------------------------------------------------------------------------- audio


#: frames of the spectral flux computed at once: a long take's (frames, window) matrix of samples and its spectrum
#: would grow with the take (about 1 GB for 10 minutes at 16 kHz); by blocks the result is the same, bit for bit
FLUX_BLOCK_FRAMES = 4096


def spectral_flux(
    samples: np.ndarray, rate: int, *, hop: float = 0.01, window: float = 0.04, max_frequency: float = 4000.0
) -> tuple[np.ndarray, np.ndarray]:
    """Onset strength of a mono signal: frame centre times (seconds from the first sample) and the spectral flux,
    sum over frequency bins up to ``max_frequency`` of max(0, log(1 + 100 |X_t|) - log(1 + 100 |X_t-1|)),
    Hann-windowed frames of ``window`` seconds every ``hop`` seconds. Vectorised over blocks of frames
    (``FLUX_BLOCK_FRAMES``), so memory does not grow with the signal's length."""
    samples = np.asarray(samples, dtype=np.float64)
    hop_n = max(1, int(round(hop * rate)))
    win_n = max(hop_n, int(round(window * rate)))
    if len(samples) < win_n:
        return np.zeros(0), np.zeros(0)
    n_frames = 1 + (len(samples) - win_n) // hop_n
    bins = np.fft.rfftfreq(win_n, 1.0 / rate) <= max_frequency
    hann = np.hanning(win_n)[None, :]
    flux, previous = np.zeros(n_frames), None
    for start, stop in flux_blocks(n_frames, FLUX_BLOCK_FRAMES):
        index = np.arange(win_n)[None, :] + hop_n * np.arange(start, stop)[:, None]
        log_mag = np.log1p(100.0 * np.abs(np.fft.rfft(samples[index] * hann, axis=1))[:, bins])
        rows = log_mag if previous is None else np.concatenate([previous, log_mag])  # the block's first diff
        flux[start + (previous is None) : stop] = np.maximum(np.diff(rows, axis=0), 0.0).sum(axis=1)
        previous = log_mag[-1:]
    times = (np.arange(n_frames) * hop_n + win_n / 2) / rate
    return times, flux


def flux_blocks(n_frames: int, block: int) -> list[tuple[int, int]]:
    """[start, stop) blocks of about ``block`` frames in which every block yields at least two flux differences
    (numpy sums a single row by another path, a rounding apart), so the flux is bit for bit the whole take's."""
    block = max(block, 3)
    bounds = list(range(0, n_frames, block)) + [n_frames]
    if len(bounds) > 2 and bounds[-1] - bounds[-2] < 2:
        bounds.pop(-2)  # a last block of one frame joins the one before
    return list(zip(bounds[:-1], bounds[1:]))


def pick_peaks(
    signal: np.ndarray,
    step: float,
    *,
    delta: float = 0.07,
    local: float = 0.1,
    average: float = 0.3,
    min_gap: float = 0.1,
) -> np.ndarray:
    """Indices of onset peaks of a strength curve sampled every ``step`` seconds: the curve is scaled to [0, 1]; a
    frame is a peak when it is the maximum within +-``local`` seconds, exceeds the mean over +-``average`` seconds
    by ``delta``, and comes at least ``min_gap`` seconds after the previous peak."""
    from scipy.ndimage import maximum_filter1d, uniform_filter1d

    x = np.asarray(signal, dtype=np.float64)
    if len(x) < 3 or np.ptp(x) <= 0:
        return np.zeros(0, dtype=np.int64)
    x = (x - x.min()) / np.ptp(x)
    size = lambda seconds: max(1, 2 * int(round(seconds / step)) + 1)
    is_max = x >= maximum_filter1d(x, size(local), mode="nearest")
    above = x >= uniform_filter1d(x, size(average), mode="nearest") + delta
    candidates = np.flatnonzero(is_max & above & (x > 0))
    return thin_peaks(candidates, x, max(1, int(round(min_gap / step))))


def thin_peaks(candidates: np.ndarray, strength: np.ndarray, gap: int) -> np.ndarray:
    """Keep candidates in time order, dropping any closer than ``gap`` samples to the previous kept one."""
    kept: list[int] = []
    for i in candidates:
        if not kept or i - kept[-1] >= gap:
            kept.append(int(i))
    return np.array(kept, dtype=np.int64)


def audio_onsets(samples: np.ndarray, rate: int, *, offset: float = 0.0, **picking) -> np.ndarray:
    """Onset times (seconds on the sequence clock: ``offset`` is the time of the first sample) of speech audio:
    peaks of the spectral flux (``pick_peaks`` keyword arguments: delta, local, average, min_gap)."""
    times, flux = spectral_flux(samples, rate)
    if len(flux) < 3:
        return np.zeros(0)
    return times[pick_peaks(flux, float(times[1] - times[0]), **picking)] + offset


def pitch_accents(times: np.ndarray, semitones: np.ndarray, *, prominence: float = 1.0) -> np.ndarray:
    """Times of pitch accents: local maxima of the voice pitch (semitones, NaN unvoiced) inside a voiced run (not
    at its ends), with at least ``prominence`` semitones of prominence within that run."""
    from scipy.signal import find_peaks

    voiced = np.isfinite(semitones)
    edges = np.diff(np.concatenate([[0], voiced.astype(np.int8), [0]]))
    out = []
    for a, b in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)):
        peaks, _ = find_peaks(semitones[a:b], prominence=prominence)  # interior maxima of the voiced run
        out.append(times[a + peaks])
    return np.concatenate(out) if out else np.zeros(0)


# ------------------------------------------------------------------------------------------------ motion


def smoothed_speed(angles: np.ndarray, fps: float, smoothing: float) -> np.ndarray:
    """Angular speed (deg/s) per frame (central differences of the angles, a good approximation of the angular
    velocity's norm for the small angles of a centred head), Gaussian-smoothed over ``smoothing`` seconds (sd)."""
    from scipy.ndimage import gaussian_filter1d

    angles = np.asarray(angles, dtype=np.float64)
    if len(angles) < 2:
        return np.zeros(len(angles))
    velocity = np.gradient(np.degrees(angles), axis=0) * fps
    if smoothing > 0:
        velocity = gaussian_filter1d(velocity, smoothing * fps, axis=0, mode="nearest")
    return np.linalg.norm(velocity, axis=1)


def kinematic_beats(
    angles: np.ndarray, fps: float, *, kind: str = "peaks", smoothing: float = 0.1, prominence: float = 0.0
) -> np.ndarray:
    """Times (seconds from the first frame) of head beats: local maxima (``kind="peaks"``) or minima (``"minima"``)
    of the smoothed angular speed with at least ``prominence`` deg/s of prominence. A still head has none."""
    from scipy.signal import find_peaks

    speed = smoothed_speed(angles, fps, smoothing)
    if len(speed) < 3 or np.ptp(speed) <= 1e-9:
        return np.zeros(0)
    found, _ = find_peaks(speed if kind == "peaks" else -speed, prominence=max(prominence, 1e-9))
    return found / fps


# --------------------------------------------------------------------------------------------- alignment


def nearest_distance(events: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Distance from each event to the nearest target (inf when there are no targets)."""
    events = np.asarray(events, dtype=np.float64)
    targets = np.sort(np.asarray(targets, dtype=np.float64))
    if len(targets) == 0:
        return np.full(len(events), np.inf)
    i = np.clip(np.searchsorted(targets, events), 1, max(len(targets) - 1, 1))
    left = np.abs(events - targets[i - 1])
    right = np.abs(targets[np.minimum(i, len(targets) - 1)] - events)
    return np.minimum(left, right)


def beat_alignment(head_beats: np.ndarray, audio_beats: np.ndarray, sigma: float) -> float:
    """BA = mean over head beats of exp(-d^2 / 2 sigma^2), d = distance to the nearest audio beat (seconds).
    0 when the motion has no beats."""
    if len(head_beats) == 0:
        return 0.0
    d = nearest_distance(head_beats, audio_beats)
    return float(np.mean(np.exp(-0.5 * (d / sigma) ** 2)))


def chance_alignment(period: float, sigma: float) -> float:
    """Expected BA of head beats placed independently of audio beats on a regular grid of ``period`` seconds:
    the nearest distance is uniform on [0, period/2], so E = (2/period) sigma sqrt(pi/2) erf(period / (2 sqrt 2
    sigma))."""
    from math import erf, pi, sqrt

    return 2.0 / period * sigma * sqrt(pi / 2) * erf(period / (2 * sqrt(2) * sigma))
