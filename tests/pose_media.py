"""A head turned by known angles, on video: the ICT FaceKit character (the very face the pose solver fits)
rendered neutral through the renderer's pinhole, for the head-pose known answers (tests/test_tracking_pose.py,
bench/bench_pose.py)."""

from __future__ import annotations

import functools

import numpy as np
from tracking_media import write_video

#: the renderer's pinhole: the camera stands ``View.perspective`` (4) frame heights away, so its focal length in
#: pixels is four times the frame's side
FOCAL_PER_SIDE = 4.0


def known_turns(frames: int, fps: float) -> np.ndarray:
    """(frames, 3) yaw, pitch, roll in degrees: each its own swing (20, 12 and 4 degrees), so no two move
    together."""
    t = np.arange(frames) / fps
    return np.stack(
        [20 * np.sin(2 * np.pi * t / 2.0), 12 * np.sin(2 * np.pi * t / 1.3 + 0.5), 4 * np.sin(2 * np.pi * t / 1.7)],
        axis=1,
    )


@functools.cache
def ict_character():
    """The embedded ICT FaceKit character artifact (built once per process)."""
    from msflow.testing import run_stage
    from stages.retarget.character import GltfCharacter

    return run_stage(GltfCharacter, {}, {"mesh": {"path": "data/characters/ict-facekit.glb"}}).view()


def head_renderer(size: int, supersample: int = 1):
    """(renderer, character): the ICT head framed whole, eyes in, ``size`` pixels square."""
    from stages.export.animation import character_eyes
    from stages.geometry.render import CharacterRenderer

    character = ict_character()
    eyes = [(eye.vertices, eye.center) for eye in character_eyes(character)]
    renderer = CharacterRenderer.from_artifact(character, size=size, framing="head", eyes=eyes, supersample=supersample)
    return renderer, character


def turned_head_video(path, size: int, angles: np.ndarray, fps: int, supersample: int = 1):
    """The neutral ICT head turned by ``angles`` (frames, 3; degrees) frame by frame (``head_renderer``), written
    to ``path``."""
    from stages.geometry.rotations import euler_to_quat

    renderer, _ = head_renderer(size, supersample)
    rotation = euler_to_quat(*np.radians(angles).T)
    return write_video(path, [renderer(rotation=q)[..., ::-1] for q in rotation], fps=fps)  # RGB -> BGR


def true_landmarks(size: int, angles: np.ndarray) -> np.ndarray:
    """(frames, 68, 2) image positions of the ICT head's landmark vertices under ``angles`` (what a perfect
    tracker would give for ``turned_head_video``)."""
    from stages.geometry.render import project
    from stages.geometry.rotations import euler_to_quat

    renderer, character = head_renderer(size)
    ids = np.asarray(character["landmark_ids"])
    rotation = euler_to_quat(*np.radians(angles).T)
    return np.array([project(renderer.vertices(rotation=q)[ids], renderer.view, size)[1] for q in rotation])


def pose_gains(rotation: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Tracked over true angle (least-squares slope) for yaw, pitch and roll of tracked ``rotation`` (frames, 4)."""
    from stages.geometry.rotations import quat_to_euler

    tracked = np.degrees(np.asarray(quat_to_euler(np.asarray(rotation))))
    tracked = tracked if tracked.shape[0] == len(angles) else tracked.T
    return np.array([np.polyfit(angles[:, i], tracked[:, i], 1)[0] for i in range(3)])
