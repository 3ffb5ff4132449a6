"""Stretches the tracker held through a long gap (no face found), eased into the face found after them.

The tracker interpolates a gap of at most ``max_gap_frames`` frames and holds the last face through a longer one
(``stages.tracking``, ``long_gaps: hold``; listed in the tracking's ``meta["gaps"]``). Held as it is, the animation
jumps in one frame to wherever the face is when it comes back: a pop of the head (17 degrees of yaw in one frame
after the 1.2 s of black in a test clip) and of the mouth that an animator would have to clean up. Here the last
frames of each such gap move instead from the held value to the value after the gap, along a smoothstep (values)
or a slerp (rotations). A gap a take ends in stays held: no face comes after it; one a take starts in already holds
the first face found.
"""

from __future__ import annotations

import numpy as np

from stages.geometry.ramps import smoothstep
from stages.geometry.rotations import quat_slerp


def found_again_spans(sequence: np.ndarray, gaps: list, fps: list[float], seconds: float) -> list[tuple[int, int]]:
    """The frames to ease, [first, stop) in the frames of ``sequence`` (take index per frame), from the tracking's
    ``meta["gaps"]`` (per take, [start, stop) frame ranges of the take): the last ``seconds`` of every long gap
    after which the take finds the face again (``stop`` is then the first frame with a face)."""
    sequence = np.asarray(sequence)
    spans = []
    for take, take_gaps in enumerate(gaps or []):
        rows = np.flatnonzero(sequence == take)
        frames = int(round(seconds * float(fps[take] if take < len(fps) else fps[0])))
        for start, stop in take_gaps:
            if frames > 0 and stop < len(rows):
                spans.append((int(rows[max(int(start), int(stop) - frames)]), int(rows[int(stop)])))
    return spans


def ease_into_found_face(values: np.ndarray, spans: list[tuple[int, int]], *, rotations: bool = False) -> np.ndarray:
    """``values`` (frames, ...) with each span [first, stop) of ``found_again_spans`` moved from the value before
    it to ``values[stop]``: a smoothstep, or for unit quaternions (frames, 4) a slerp along it (``rotations``)."""
    out = np.array(values, dtype=np.float64, copy=True)
    for first, stop in spans:
        before = out[first - 1] if first > 0 else out[first]
        t = smoothstep(np.arange(1, stop - first + 1) / (stop - first + 1))
        if rotations:
            out[first:stop] = quat_slerp(before[None], out[stop][None], t)
        else:
            out[first:stop] = before + t.reshape((-1,) + (1,) * (out.ndim - 1)) * (out[stop] - before)
    return out
