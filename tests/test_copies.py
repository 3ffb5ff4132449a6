"""Takes of one performance found by their sound (stages.head.copies)."""

import numpy as np

from stages.head.copies import envelope_match, loudness_envelope, shared_audio_pairs, take_of

RATE = 16000


def speech_like(seconds: float, seed: int) -> np.ndarray:
    """Noise whose loudness rises and falls like syllables (random 3-6 Hz bursts and pauses)."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(seconds * RATE)) / RATE
    bursts = np.zeros_like(t)
    start = 0.0
    while start < seconds:
        length = rng.uniform(0.08, 0.3)
        bursts += np.exp(-0.5 * ((t - start - length / 2) / (length / 4)) ** 2) * rng.uniform(0.2, 1.0)
        start += length + rng.uniform(0.02, 0.4)
    return (rng.standard_normal(len(t)) * (bursts + 1e-3)).astype(np.float32)


def test_a_cropped_reencoded_copy_matches_and_other_speech_does_not():
    take = speech_like(8.0, seed=1)
    # the first 5 s, quieter, with noise of its own, starting 15 ms late (another encoding of the same sound)
    copy = 0.5 * take[240 : 240 + 5 * RATE] + 0.002 * np.random.default_rng(9).standard_normal(5 * RATE)
    envelopes = {name: loudness_envelope(x, RATE) for name, x in [("take", take), ("copy", copy)]}
    envelopes |= {f"other{k}": loudness_envelope(speech_like(6.0, seed=10 + k), RATE) for k in range(4)}
    assert envelope_match(envelopes["take"], envelopes["copy"]) > 0.95
    assert all(envelope_match(envelopes["take"], envelopes[f"other{k}"]) < 0.8 for k in range(4))
    pairs = shared_audio_pairs(envelopes)
    assert [(a, b) for a, b, _ in pairs] == [("take", "copy")]
    # takes shorter than the minimum are not compared: short envelopes match by chance
    assert shared_audio_pairs(envelopes, min_frames=len(envelopes["take"]) + 1) == []


def test_take_of_strips_piece_and_mirror_suffixes():
    assert take_of("clip#3~mirror") == take_of("clip#3") == take_of("clip~mirror") == take_of("clip") == "clip"
    assert take_of("take#a") == "take#a"  # only the pieces' numbering is a suffix
