"""Head-motion amplitude (beyond the paper, issue 12): how far each speaker's head moves (the spread p95 - p5 of
each angle and the translation about the rest pose), and the gains that bring database motion, or a stitched
output, to a target speaker's spread (one gain for the angles, so the head strokes stay on the voice's onsets);
and the side a speaker turns to (``mirrored_to_side``: the output mirrored when the performer turns mostly the
other way).
"""

from __future__ import annotations

import numpy as np

from stages.head.measures import reference_angles
from stages.head.stitching import DatabaseMotion


def speaker_spreads(db: DatabaseMotion, allowed: np.ndarray | None = None, duration: float | None = None) -> dict:
    """Per speaker, the spread (p95 - p5 per channel) of its motion about its rest pose, pooled over its
    ``allowed`` sequences (all when None); speakers with no allowed sequence are left out.

    The spread of a stretch of head motion grows with its length (slow postural wander adds to it), so with a
    ``duration`` (seconds) the sequences are cut into pieces of about that length, each centred on its own mean
    like a take, and the pieces pooled: the spread expected of an utterance that long. Without it each whole
    sequence (centred on its mean pose by the database) counts as it is."""
    speakers = list(db.speakers or [None] * len(db.frames))
    allowed = np.ones(len(db.frames), bool) if allowed is None else np.asarray(allowed, bool)
    piece = None if not duration else max(int(round(duration * db.fps)), 2)
    out = {}
    for speaker in dict.fromkeys(speakers):
        parts = []
        for k in np.flatnonzero(np.array([x == speaker for x in speakers]) & allowed):
            motion = db.channels[db.first[k] : db.first[k] + db.frames[k]]
            parts += centred_pieces(motion, piece) if piece else [motion]
        if parts:
            values = np.concatenate(parts)
            out[speaker] = np.percentile(values, 95, axis=0) - np.percentile(values, 5, axis=0)
    return out


def centred_pieces(motion: np.ndarray, piece: int) -> list[np.ndarray]:
    """``motion`` cut into nearly equal pieces of about ``piece`` frames (one when shorter), each minus its mean."""
    count = max(1, int(round(len(motion) / piece)))
    edges = np.linspace(0, len(motion), count + 1).round().astype(int)
    return [motion[a:b] - motion[a:b].mean(axis=0) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def amplitude_target(spreads: dict, speaker) -> np.ndarray:
    """The spread to give the synthesis of ``speaker``: that speaker's own (from its other takes) when the
    database has them, else the median over the database's speakers (the typical speaker's amplitude)."""
    if speaker in spreads:
        return spreads[speaker]
    return np.median(np.stack(list(spreads.values())), axis=0)


def knows_speaker(spreads: dict, speaker) -> bool:
    """Whether the database's motion (``spreads``: per speaker, over the sequences the search could use) is the
    test speaker's own: the test is labelled with a speaker the database holds. An unlabelled test is a performer
    the database does not know (whose own filmed motion, when given, is the better guess of its amplitude)."""
    return speaker is not None and speaker in spreads


def group_gains(target: np.ndarray, spread: np.ndarray, max_gain: float = np.inf) -> np.ndarray:
    """Per channel, the gain that brings ``spread`` to about ``target``: one gain for the three angles and one for
    the translation, each the geometric mean over its channels of target / spread (channels that do not move are
    left out; 1 when none moves), at most ``max_gain`` either way.

    One gain for all three angles keeps the direction of the angular velocity, so the speed's maxima -- the head
    strokes the timing warp placed on the voice's onsets -- stay where they are; a gain per angle would move them
    (measured on the shared clips: it cost beat alignment), at the price of keeping the source motion's
    proportions between yaw, pitch and roll."""
    target, spread = np.asarray(target, dtype=np.float64), np.asarray(spread, dtype=np.float64)
    gains = np.ones(len(spread))
    for group in (slice(0, 3), slice(3, len(spread))):
        moving = (spread[group] > 1e-12) & (target[group] > 1e-12)
        if moving.any():
            ratio = np.exp(np.mean(np.log(target[group][moving] / spread[group][moving])))
            gains[group] = np.clip(ratio, 1.0 / max_gain, max_gain)
    return gains


def amplitude_gains(db: DatabaseMotion, spreads: dict, target: np.ndarray, per_angle: bool = False) -> np.ndarray:
    """Per sequence and channel, the gains (``group_gains``; ``per_angle``: one per angle, ``angle_gains``) that
    bring its speaker's spread (``speaker_spreads``) to ``target``: every source speaker then moves about as much
    as the target speaker (1 where a speaker's spread is unknown)."""
    speakers = list(db.speakers or [None] * len(db.frames))
    gains = np.ones((len(speakers), db.channels.shape[1]))
    for k, speaker in enumerate(speakers):
        if speaker in spreads:
            gains[k] = group_gains(target, spreads[speaker])
            if per_angle:
                gains[k, :3] = angle_gains(target[:3], spreads[speaker][:3], np.inf)
    return gains


def match_amplitude(channels: np.ndarray, target: np.ndarray, max_gain: float) -> np.ndarray:
    """The motion about its mean (the rest pose of a take centred like the database), scaled (``group_gains``,
    at most ``max_gain`` either way, so a short, nearly still utterance is not blown up) so that its spread
    p95 - p5 is about ``target``'s. Blending shrinks the spread of unrelated segments, so the overall size is set
    on the output (one gain for the angles: a gain per angle here moved the strokes off the onsets, measured: 62%
    wins over random real motion instead of 83%, leave one speaker out on the shared clips)."""
    centred = channels - channels.mean(axis=0)
    if len(channels) < 2:
        return centred
    spread = np.percentile(centred, 95, axis=0) - np.percentile(centred, 5, axis=0)
    return centred * group_gains(target, spread, max_gain)


def angle_gains(target: np.ndarray, spread: np.ndarray, max_gain: float) -> np.ndarray:
    """Per angle, target / spread (1 for an angle that does not move), at most ``max_gain`` either way."""
    moving = (spread > 1e-12) & (target > 1e-12)
    ratio = np.where(moving, target / np.where(moving, spread, 1.0), 1.0)
    return np.clip(ratio, 1.0 / max_gain, max_gain)


def proportion_correction(channels: np.ndarray, target: np.ndarray, sequences: int, max_gain: float = 2.0):
    """(sequences, channels) gains that bring the proportions between the angles' spreads of a stitched output
    (``channels``) to ``target``'s: per angle target / spread, divided by their geometric mean (the output's one
    gain sets the size), at most ``max_gain`` either way; 1 for the translation."""
    spread = np.percentile(channels, 95, axis=0) - np.percentile(channels, 5, axis=0)
    ratio = angle_gains(np.asarray(target, dtype=np.float64)[:3], spread[:3], max_gain)
    gains = np.ones(channels.shape[1])
    gains[:3] = np.clip(ratio / np.exp(np.mean(np.log(ratio))), 1.0 / max_gain, max_gain)
    return np.tile(gains, (sequences, 1))


def reference_spreads(
    reference, labels: list[str], fps: float, seconds: float | None = None
) -> list[list[float] | None]:
    """Per test utterance, the spread (p95 - p5 about its mean) of each angle of the performer's real motion in
    the reference (a tracking artifact; its first ``seconds`` when given): the amplitude target of
    ``amplitude_target="reference"``; None where the reference has no such take or it is too short."""
    return range_spreads(reference_ranges(reference, labels, fps, seconds))


def range_spreads(ranges: list) -> list[list[float] | None]:
    """p95 - p5 per angle of each ``reference_ranges`` entry ([p5, p95]; None stays None)."""
    return [None if r is None else (np.asarray(r[1]) - np.asarray(r[0])).tolist() for r in ranges]


def reference_ranges(
    reference, labels: list[str], fps: float, seconds: float | None = None
) -> list[list[list[float]] | None]:
    """Per test utterance, [p5, p95] (each per angle, about its mean) of the performer's real motion in the
    reference (a tracking artifact; its first ``seconds`` when given); None where the reference has no such take
    or it is too short."""
    out: list[list[list[float]] | None] = []
    for label in labels:
        angles = reference_angles(reference, label, len(labels), fps)
        if angles is not None and seconds is not None:
            angles = angles[: int(round(seconds * fps))]
        if angles is None or len(angles) < 2:
            out.append(None)
            continue
        centred = angles - angles.mean(axis=0)
        out.append(np.percentile(centred, [5, 95], axis=0).tolist())
    return out


# The head motion seen in a mirror (the sagittal plane): with R = Ry(yaw) Rx(pitch) Rz(roll), M R M for
# M = diag(-1, 1, 1) negates yaw and roll and keeps pitch; the sideways translation changes sign.
MIRROR = np.array([-1.0, 1.0, -1.0, -1.0, 1.0, 1.0])


def mirrored_to_side(channels: np.ndarray, sides) -> np.ndarray:
    """The channels (frames, 6), or their mirror image (``MIRROR``) when that brings the yaw's and the roll's
    side closer to ``sides``' ([p5, p95] per angle about the mean, ``reference_ranges``): a speaker who turns
    mostly to one side keeps doing so. An angle's side is ``range_asymmetry`` (mirroring negates it); the
    differences of the two angles are summed, and a tie keeps the channels as they are. Mirroring changes no
    speed, so the strokes' timing stays."""
    if len(channels) < 2:
        return channels
    target = range_asymmetry(np.asarray(sides, dtype=np.float64)[:, [0, 2]])
    centred = channels[:, [0, 2]] - channels[:, [0, 2]].mean(axis=0)
    found = range_asymmetry(np.percentile(centred, [5, 95], axis=0))
    return channels * MIRROR if np.abs(-found - target).sum() < np.abs(found - target).sum() else channels


def range_asymmetry(ends: np.ndarray) -> np.ndarray:
    """Per column of ``ends`` ([p5, p95] about the mean), where the range sits: (p5 + p95) / (p95 - p5), -1..1;
    0 for a range centred on the mean (or none), positive when the motion reaches farther the positive way."""
    span = ends[1] - ends[0]
    return np.where(span > 1e-12, (ends[0] + ends[1]) / np.where(span > 1e-12, span, 1.0), 0.0)
