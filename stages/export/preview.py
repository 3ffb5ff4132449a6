"""The preview video: the character rendered (stages.geometry.render) frame by frame and encoded as H.264 MP4 with
PyAV (stages.formats.video), the take's audio muxed in.

Frames are rendered in blocks and handed to the encoder as they come, so memory does not grow with the take; with
``jobs`` > 1 the blocks are rendered by a pool of worker processes on long takes (``PROCESS_MIN_FRAMES``), else by
a pool of threads, and encoded in order. A frame's pixels depend on its pose only, so the video is the same
whatever ``jobs`` is and whichever pool drew it.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np


def encode_mp4(
    frames,
    fps: float,
    size: tuple[int, int],
    *,
    audio: np.ndarray | None = None,
    audio_rate: int | None = None,
    codec: str = "auto",
    crf: int = 23,
    preset: str = "veryfast",
) -> tuple[bytes, str]:
    """Encode RGB uint8 frames (an iterable of (H, W, 3)) and optional mono float audio into MP4 bytes, and the
    codec used (``stages.formats.video.Mp4Writer``).

    H.264 (libx264) at constant quality ``crf``; the x264 ``preset`` trades encoding time for file size (the
    default, veryfast, encodes a 384 px preview frame in about 1.5 ms, half of medium's). The same frames give
    the same bytes.
    """
    from stages.formats.video import Mp4Writer

    writer = Mp4Writer(
        fps, codec=codec, crf=crf, preset=preset, pixels="rgb24", size=size, audio=audio, audio_rate=audio_rate
    )
    for frame in frames:  # one at a time, as they are rendered
        writer.write(np.asarray(frame)[None])
    return writer.close(), writer.codec


#: output frames whose performer crops are read from the store at once
PERFORMER_BLOCK = 64


def beside_performer(frames, crops, rows: np.ndarray, size: int) -> Iterator[np.ndarray]:
    """Each rendered frame (size, size, 3) with the performer's face crop of the same moment on its left, scaled
    to ``size``: the capture beside what it was made from. ``crops``: the tracking's grey face crops, unread
    (``ArtifactView.lazy``), read a block of frames at a time; ``rows``: its row for each frame."""
    import cv2

    frames = iter(frames)
    for start in range(0, len(rows), PERFORMER_BLOCK):
        wanted = rows[start : start + PERFORMER_BLOCK]
        first = int(wanted.min())
        block = np.asarray(crops[first : int(wanted.max()) + 1])
        for row in wanted:
            face = cv2.resize(block[row - first], (size, size), interpolation=cv2.INTER_LINEAR)
            yield np.concatenate([np.repeat(face[..., None], 3, axis=-1), next(frames)], axis=1)


@dataclass
class Poses:
    """The character's pose per output frame: morph weights, head rotation (w, x, y, z) and translation (metres)
    about the renderer's pivot, and eye rotations relative to the head (frames, 2, 4); None where absent."""

    weights: np.ndarray
    rotation: np.ndarray | None = None
    translation: np.ndarray | None = None
    eyes: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.weights)

    def frame(self, i: int) -> dict:
        return {
            "weights": self.weights[i],
            "rotation": None if self.rotation is None else self.rotation[i],
            "translation": None if self.translation is None else self.translation[i],
            "eye_rotations": None if self.eyes is None else self.eyes[i],
        }

    def block(self, start: int, stop: int) -> Poses:
        """Frames start..stop-1."""
        rows = slice(start, stop)
        return Poses(
            *(None if a is None else a[rows] for a in (self.weights, self.rotation, self.translation, self.eyes))
        )


def render_poses(renderer, poses: Poses) -> list[np.ndarray]:
    """Every frame of ``poses`` as (H, W, 3) uint8 images."""
    return [renderer(**poses.frame(i)) for i in range(len(poses))]


#: shortest take (frames) rendered by worker processes when ``jobs`` > 1: a spawned worker costs about half a CPU
#: second to start (numpy, scipy, the character), which a longer take repays; shorter takes use threads
PROCESS_MIN_FRAMES = 300


def rendered_frames(
    renderer, poses: Poses, *, jobs: int = 1, block: int = 16, processes: bool | None = None
) -> Iterator[np.ndarray]:
    """Every frame in order, rendered ``block`` frames at a time.

    With ``jobs`` > 1, ``jobs`` workers render the blocks and at most 2 * jobs blocks wait for the encoder, so
    memory stays bounded whatever the take's length. The workers are processes when ``processes`` is true (default:
    takes of at least ``PROCESS_MIN_FRAMES`` frames, unless this process is a daemon, e.g. a Dask worker, which may
    not start children), else threads. Threads share the interpreter: the rasteriser's many small numpy calls
    contend for the GIL, and two threads drew 1.45x the frames of one (``bench/bench_render.py``), where two
    processes scale with the cores. A frame's image depends only on its pose, so the frames are the same whatever
    ``jobs`` and the pool are.
    """
    starts = range(0, len(poses), block)
    if jobs <= 1:
        for start in starts:
            yield from render_poses(renderer, poses.block(start, start + block))
        return
    if processes is None:
        processes = len(poses) >= PROCESS_MIN_FRAMES and not _is_daemon()
    from collections import deque

    with _render_pool(renderer, jobs, processes) as (pool, render_block):
        pending: deque = deque()
        for start in starts:
            pending.append(pool.submit(render_block, poses.block(start, start + block)))
            if len(pending) >= 2 * jobs:
                yield from pending.popleft().result()
        while pending:
            yield from pending.popleft().result()


def _is_daemon() -> bool:
    import multiprocessing

    return bool(multiprocessing.current_process().daemon)


@contextmanager
def _render_pool(renderer, jobs: int, processes: bool):
    """(executor, function rendering one block of poses) for ``jobs`` threads or spawned processes."""
    from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor

    if not processes:
        with ThreadPoolExecutor(max_workers=jobs) as pool:
            yield pool, functools.partial(render_poses, renderer)
        return
    import multiprocessing

    # spawn, not fork: the parent may run other threads (the runner's, the encoder's), which fork would copy
    # mid-operation
    context = multiprocessing.get_context("spawn")
    initargs = (renderer, os.getpid())
    with ProcessPoolExecutor(jobs, mp_context=context, initializer=_start_render_worker, initargs=initargs) as pool:
        yield pool, render_block_in_worker


#: the renderer of a worker process, set once by the pool's initializer
_worker_renderer = None


def _start_render_worker(renderer, parent_pid: int) -> None:
    """Keep the renderer; leave Ctrl-C to the parent, which shuts the pool down; and exit should the parent die
    without shutting it down (killed: the stage's worker with -j N, msflow with -j 1), as an orphan would wait for
    blocks forever, holding the run's stdout."""
    import signal

    from msflow.processes import exit_with_parent

    global _worker_renderer
    _worker_renderer = renderer
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    exit_with_parent(parent_pid)


def render_block_in_worker(poses: Poses) -> np.ndarray:
    """A block of frames (n, H, W, 3) drawn by this worker process's renderer (one array: one transfer)."""
    return np.stack(render_poses(_worker_renderer, poses))
