"""Long takes: the per-frame work that issue 14 moved to blocks of frames gives the whole-take result, bit for bit.

(Tracking's own block tests are in test_tracking_stream.py; edit, blend and preview have theirs in their areas.)"""

import numpy as np

import stages.head.beats as beats


def whole_take_flux(samples, rate, hop=0.01, window=0.04, max_frequency=4000.0):
    """The spectral flux as one (frames, window) matrix: the definition the blocked version must reproduce."""
    hop_n, win_n = int(round(hop * rate)), int(round(window * rate))
    n_frames = 1 + (len(samples) - win_n) // hop_n
    index = np.arange(win_n)[None, :] + hop_n * np.arange(n_frames)[:, None]
    spectrum = np.abs(np.fft.rfft(samples[index] * np.hanning(win_n)[None, :], axis=1))
    log_mag = np.log1p(100.0 * spectrum[:, np.fft.rfftfreq(win_n, 1.0 / rate) <= max_frequency])
    return np.concatenate([[0.0], np.maximum(np.diff(log_mag, axis=0), 0.0).sum(axis=1)])


def test_spectral_flux_by_blocks_is_the_whole_take(monkeypatch):
    rng = np.random.default_rng(3)
    rate = 16000
    t = np.arange(3 * rate) / rate  # 297 frames: blocks of 8 and of 37 leave one frame over
    samples = rng.normal(size=len(t)) * (np.sin(2 * np.pi * 2.5 * t) > 0.3)  # bursts: onsets to find
    expected = whole_take_flux(samples, rate)
    for block in (1, 2, 7, 8, 37, 64, 10**6):
        monkeypatch.setattr(beats, "FLUX_BLOCK_FRAMES", block)
        times, flux = beats.spectral_flux(samples, rate)
        np.testing.assert_array_equal(flux, expected, err_msg=f"blocks of {block} frames")
        assert len(times) == len(expected)
    assert len(beats.audio_onsets(samples, rate)) >= 5  # the bursts are found
