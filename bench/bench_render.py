"""Preview speed: the software rasteriser (stages.geometry.render) and the export's whole preview path (pose + render +
H.264 encode, stages.export.preview) on the embedded ICT FaceKit character, animated by a smooth random walk of
its morph weights with head and eye motion.

    python bench/bench_render.py [--frames 600] [--sizes 192 384 512] [--jobs 1 2] [--export-frames 1800]

Prints (1) the rasteriser alone on one core, per image size: CPU milliseconds per frame and frames per CPU
second, beside OpenCV's fillConvexPoly painter's algorithm (flat shading, no z-buffer) as a reference; (2) the
preview path for each level ("low": half size, "full") and each worker count: wall-clock frames per second, CPU
milliseconds per frame (user + sys, all threads and worker processes) and the load average while it ran (other processes on the
machine slow the wall clock, not the CPU figure). The frames must be identical whatever the worker count: the
script checks it. (3) the export stage end to end on a synthetic one-minute take (1800 frames at 30 fps).
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
from pathlib import Path

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402


def cpu_seconds() -> float:
    """User + system CPU of this process and of its finished children (the preview's worker processes)."""
    return sum(
        usage.ru_utime + usage.ru_stime
        for usage in (resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN))
    )


def painter_render(vertices, triangles, size, view, colors):
    """OpenCV reference: cull back faces, sort by depth, fill each triangle with its flat shade."""
    import cv2

    from stages.geometry.render import project, shade_vertices, vertex_normals

    cam, xy = project(vertices, view, size)
    p = xy[triangles]
    area = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (p[:, 2, 0] - p[:, 0, 0]) * (p[:, 1, 1] - p[:, 0, 1])
    front = np.flatnonzero(area < 0)
    diffuse, spec = shade_vertices(vertex_normals(cam, triangles, dtype=np.float32), view)
    corners = triangles[front]
    shade = diffuse[corners].mean(axis=1)[:, None] * colors[front] + spec[corners].mean(axis=1)[:, None]
    rgb = (np.clip(shade, 0, 1) * 255).astype(np.uint8)
    order = np.argsort(cam[triangles[front], 2].mean(axis=1))  # far to near
    image = np.empty((size, size, 3), np.uint8)
    image[:] = (np.array(view.background) * 255).astype(np.uint8)
    pts = np.round(p[front] * 16).astype(np.int32)  # 4 fractional bits
    for i in order:
        cv2.fillConvexPoly(image, pts[i], rgb[i].tolist(), lineType=cv2.LINE_8, shift=4)
    return image


def cpu_per_call(fn, repeats: int) -> float:
    """Least CPU seconds of one call over ``repeats`` (the least is the least disturbed by other processes)."""
    fn()  # warm-up
    best = float("inf")
    for _ in range(repeats):
        start = time.process_time()
        fn()
        best = min(best, time.process_time() - start)
    return best


def animation(frames: int, names: list[str], seed: int = 0):
    """Smooth random morph weights (a third of the morphs move), head turns and gaze: a Poses of the export."""
    from stages.export.preview import Poses
    from stages.export.rig import gaze_rotations
    from stages.geometry.rotations import euler_to_quat

    rng = np.random.default_rng(seed)
    moving = rng.uniform(size=len(names)) < 0.33
    weights = np.clip(np.cumsum(rng.normal(0, 0.04, (frames, len(names))), axis=0), 0, 0.8) * moving
    t = np.arange(frames) / 30.0
    head = euler_to_quat(0.25 * np.sin(0.7 * t), 0.1 * np.sin(1.3 * t), 0.05 * np.sin(0.4 * t))
    gaze = np.stack([15 * np.sin(0.9 * t), 8 * np.cos(0.6 * t)], axis=-1)[:, None, :].repeat(2, axis=1)
    return Poses(weights, head, np.zeros((frames, 3)), gaze_rotations(gaze))


def rasteriser_table(character, sizes: list[int], repeats: int) -> None:
    from stages.geometry.render import CharacterRenderer, render

    names = character.meta["target_names"]
    poses = animation(2, names)
    print(f"\n(1) rasteriser alone, one core: CPU ms per frame (frames per CPU second), least of {repeats}")
    print(f"{'size':>5} {'numpy z-buffer':>22} {'+2x supersample':>22} {'opencv painter (flat)':>24}")
    for size in sizes:
        renderer = CharacterRenderer.from_artifact(character, size=size)
        verts = renderer.vertices(poses.weights[1], poses.rotation[1])
        cells = []
        for fn, reps in (
            (lambda: render(verts, renderer.triangles, size, renderer.view, colors=renderer.colors), repeats),
            (
                lambda: render(verts, renderer.triangles, size, renderer.view, colors=renderer.colors, supersample=2),
                max(repeats // 4, 3),
            ),
            (lambda: painter_render(verts, renderer.triangles, size, renderer.view, renderer.colors), 3),
        ):
            seconds = cpu_per_call(fn, reps)
            cells.append(f"{seconds * 1e3:7.1f} ms ({1 / seconds:6.1f} f/s)")
        print(f"{size:>5} {cells[0]:>22} {cells[1]:>22} {cells[2]:>24}")


def preview_table(character, frames: int, jobs_list: list[int], size: int) -> None:
    from stages.export.preview import PROCESS_MIN_FRAMES, encode_mp4, rendered_frames
    from stages.export.rig import find_eyes
    from stages.geometry.render import CharacterRenderer

    groups = [g["name"] for g in character.meta["groups"]]
    eyes = find_eyes(character["neutral"], character["triangles"], character["triangle_groups"], groups)
    poses = animation(frames, character.meta["target_names"])
    print(f"\n(2) preview path (pose + render + H.264 encode), {frames} frames, {os.cpu_count()} CPUs")
    pool = "processes" if frames >= PROCESS_MIN_FRAMES else "threads"
    print(f"(jobs > 1: worker {pool}, as the export stage uses them for a take of {frames} frames)")
    print(f"{'level':>5} {'px':>4} {'jobs':>4} {'wall f/s':>9} {'CPU ms/frame':>13} {'load':>5} {'MP4 KiB':>8}")
    for level, side in (("low", size // 2), ("full", size)):
        renderer = CharacterRenderer.from_artifact(character, size=side, eyes=[(e.vertices, e.center) for e in eyes])
        reference = None
        for jobs in jobs_list:
            wall, cpu = time.perf_counter(), cpu_seconds()
            data, codec = encode_mp4(rendered_frames(renderer, poses, jobs=jobs), 30.0, (side, side))
            wall, cpu = time.perf_counter() - wall, cpu_seconds() - cpu
            if reference is None:
                reference = data
            elif data != reference:
                raise SystemExit(f"preview differs between jobs={jobs_list[0]} and jobs={jobs}")
            print(
                f"{level:>5} {side:>4} {jobs:>4} {frames / wall:>9.1f} {cpu / frames * 1e3:>13.1f} "
                f"{os.getloadavg()[0]:>5.1f} {len(data) / 1024:>8.0f}"
            )
    print(f"(codec {codec}; identical videos for every worker count)")


def export_table(character, frames: int, jobs_list: list[int]) -> None:
    """The export stage end to end (GLB, CSV, BVH, preview with audio) on a synthetic take of ``frames``."""
    from msflow.testing import artifact, prepare_inputs
    from stages.export.animation import Export

    names = character.meta["target_names"]
    poses = animation(frames, names, seed=1)
    t = np.arange(frames) / 30.0
    gaze = np.stack([15 * np.sin(0.9 * t), 8 * np.cos(0.6 * t)], axis=-1)[:, None, :].repeat(2, axis=1)
    rate = 16000
    audio = (0.1 * np.sin(2 * np.pi * 220 * np.arange(int(frames / 30 * rate)) / rate)).astype(np.float32)
    inputs = {
        "character": character,
        "blend": artifact(
            {"weights": poses.weights.astype(np.float32), "gaze": gaze.astype(np.float32)},
            {"target_names": names, "fps": 30.0},
        ),
        "head": artifact(
            {"rotation": poses.rotation, "translation": np.zeros((frames, 3))}, {"fps": 30.0, "translation_units": "m"}
        ),
        "audio": artifact(
            {"audio": audio, "audio_bounds": np.array([[0, len(audio)]])},
            {"labels": ["take"], "audio_rate": rate, "fps": [30.0], "audio_offset": [0.0]},
        ),
    }
    print(f"\n(3) the export stage (GLB, Live Link CSV, BVH, 384 px preview with audio), {frames} frames")
    print(f"{'jobs':>4} {'wall s':>7} {'frames/s':>9} {'CPU s':>6} {'load':>5}")
    for jobs in jobs_list:
        stage = Export("export", jobs=jobs)
        wall, cpu = time.perf_counter(), cpu_seconds()
        stage.run(Export.Params(), prepare_inputs(Export, inputs))
        wall, cpu = time.perf_counter() - wall, cpu_seconds() - cpu
        print(f"{jobs:>4} {wall:>7.1f} {frames / wall:>9.1f} {cpu:>6.1f} {os.getloadavg()[0]:>5.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=600, help="frames of the preview path (default 600: 20 s)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[192, 384, 512])
    parser.add_argument("--jobs", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--size", type=int, default=384, help="preview size of the 'full' level")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--export-frames", type=int, default=1800, help="frames of the export stage run (0: skip)")
    args = parser.parse_args()

    from msflow.testing import run_stage
    from stages.retarget.character import GltfCharacter

    character = run_stage(GltfCharacter, {}, {"mesh": ROOT / "data" / "characters" / "ict-facekit.glb"}).view()
    n_vertices, n_triangles = len(character["neutral"]), len(character["triangles"])
    print(f"ICT FaceKit: {n_vertices} vertices, {n_triangles} triangles, {len(character.meta['target_names'])} morphs")
    rasteriser_table(character, args.sizes, args.repeats)
    preview_table(character, args.frames, args.jobs, args.size)
    if args.export_frames:
        export_table(character, args.export_frames, args.jobs)


if __name__ == "__main__":
    main()
