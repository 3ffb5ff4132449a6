"""Render speed on one core: the numpy z-buffer of stages.geometry.render against OpenCV fillConvexPoly per triangle in
back-to-front order (painter's algorithm), on the embedded ICT FaceKit character, plus the whole preview path
(pose + render + H.264 encode).

    OPENBLAS_NUM_THREADS=1 python bench/bench_render.py [--frames 60] [--sizes 256 384 512]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402


def painter_render(vertices, triangles, size, view, colors):
    """OpenCV alternative: cull back faces, sort by depth, fill each triangle with its flat Lambert shade."""
    import cv2

    from stages.geometry.render import project, shade_vertices, vertex_normals_fast

    cam, xy = project(vertices, view, size)
    p = xy[triangles]
    area = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (p[:, 2, 0] - p[:, 0, 0]) * (p[:, 1, 1] - p[:, 0, 1])
    front = np.flatnonzero(area < 0)
    normals = vertex_normals_fast(cam, triangles)
    diffuse, spec = shade_vertices(normals, view)
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


def timed(fn, repeats):
    """CPU seconds per call of this (single-threaded) process: the cost on one core, not inflated when other
    processes share the machine (wall-clock figures are printed for the whole preview path)."""
    fn()  # warm-up
    start = time.process_time()
    for _ in range(repeats):
        fn()
    return (time.process_time() - start) / repeats


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 384, 512])
    args = parser.parse_args()

    from msflow.testing import run_stage
    from stages.export.animation import encode_mp4
    from stages.geometry.render import CharacterRenderer, render
    from stages.retarget.character import GltfCharacter

    character = run_stage(GltfCharacter, {}, {"mesh": ROOT / "data" / "characters" / "ict-facekit.glb"}).view()
    names = character.meta["target_names"]
    rng = np.random.default_rng(0)
    weights = rng.uniform(0, 0.6, (args.frames, len(names))) * (rng.uniform(size=len(names)) < 0.3)
    n_tri = len(character["triangles"])
    print(
        f"ICT FaceKit: {len(character['neutral'])} vertices, {n_tri} triangles, {len(names)} targets; "
        f"{args.frames} frames, one core (CPU time)"
    )
    print(f"{'size':>5} {'numpy z-buffer':>16} {'+2x supersample':>16} {'opencv painter':>16} {'pose only':>10}")
    for size in args.sizes:
        renderer = CharacterRenderer.from_artifact(character, size=size)
        verts = renderer.vertices(weights[0])
        zbuf = timed(
            lambda: render(verts, renderer.triangles, size, renderer.view, colors=renderer.colors), args.frames
        )
        ss = timed(
            lambda: render(verts, renderer.triangles, size, renderer.view, colors=renderer.colors, supersample=2),
            max(args.frames // 4, 3),
        )
        painter = timed(
            lambda: painter_render(verts, renderer.triangles, size, renderer.view, renderer.colors),
            max(args.frames // 4, 3),
        )
        pose = timed(lambda: renderer.vertices(weights[1]), args.frames)
        print(f"{size:>5} {1 / zbuf:>12.1f} f/s {1 / ss:>12.1f} f/s {1 / painter:>12.1f} f/s {pose * 1e3:>7.1f} ms")
    size = 384
    renderer = CharacterRenderer.from_artifact(character, size=size)
    start, cpu = time.perf_counter(), time.process_time()
    data, codec = encode_mp4((renderer(w) for w in weights), 30.0, (size, size))
    elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu
    print(
        f"preview path at {size} px (pose + render + {codec} encode): {args.frames / cpu:.1f} frames/s of CPU "
        f"time ({args.frames / elapsed:.1f} wall-clock, load {os.getloadavg()[0]:.1f}), {len(data) / 1024:.0f} KiB"
    )


if __name__ == "__main__":
    main()
