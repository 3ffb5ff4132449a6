"""One take's tracking as a part of the stage's result (``Stage.part``, msflow/parts.py).

Tracking a take reads only its video, the models and the 3D face, so each take is stored on its own and a folder
that gains a clip tracks only the new one. A part holds the take's per-frame outputs and what the stage's
metadata needs of it (frame rate, frame size, focal length, gaps, the tracker's counters); what depends on the
label or the file's name (the take's label, source and field, its audio) is filled in from the current inputs.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from msflow import Result, iter_blocks
from stages.tracking.assemble import FrameOutputs, TakeTrack
from stages.tracking.takes import AudioSource

#: per-frame outputs a TakeTrack keeps in memory (small: no crops, no mesh)
TAKE_ARRAYS = ("time", "valid", "landmarks", "rotation", "pose_rms")
#: params a take's tracking never reads (its audio is read after the part, for the stage's audio outputs): giving a
#: new take its own audio offset must not track the others again
AUDIO_PARAMS = ("audio", "audio_rate", "audio_offset", "audio_tolerance")
#: what a take's part reads (``Stage.part``): its video, the models and the 3D face, the params but the audio's
TAKE_READS = {"labelled": ("videos",), "whole": ("face3d", "models"), "unread_params": AUDIO_PARAMS}


def take_part(take: TakeTrack, outputs: FrameOutputs) -> Result:
    """The part of one tracked take: ``outputs`` (its frames alone) and its JSON facts."""
    meta = {
        "fps": float(take.fps),
        "frame_size": [int(take.frame_size[0]), int(take.frame_size[1])],
        "focal_length": float(take.focal_length),
        "gaps": [[int(a), int(b)] for a, b in take.gaps],
        "take_meta": take.meta,
    }
    return Result(outputs.arrays(), meta=meta)


def take_from_part(
    part, outputs: FrameOutputs, label: str, path: Path, field: str, audio: AudioSource | None
) -> TakeTrack:
    """Append a part's frames to the stage's ``outputs`` block by block; the take as the metadata needs it."""
    for name, array in part.arrays.items():
        for block in iter_blocks(array):
            outputs.append({name: block})
    meta = part.meta
    small = {name: np.asarray(part.arrays[name]) for name in TAKE_ARRAYS}
    return TakeTrack(
        label, path.name, field, meta["fps"], tuple(meta["frame_size"]), meta["focal_length"], small["time"],
        small["valid"], small["landmarks"], small["rotation"], small["pose_rms"], audio,
        [tuple(g) for g in meta["gaps"]], dict(meta["take_meta"]),
    )  # fmt: skip
