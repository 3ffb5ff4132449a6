"""Head pose against known answers and against the FaceMesh's own 3D rotation (docs/tracking.md, "Head pose").

    python bench/bench_pose.py                                   # the rendered head, from the project root
    python bench/bench_pose.py ../shared/data/talking-heads      # and real clips, in eval/retarget.yaml's store
    python bench/bench_pose.py --probes                          # and the movement probes on the rendered head

The known answer: the ICT FaceKit head (the very face the pose solver fits) rendered neutral at 512 px, turned by
known angles (yaw 20, pitch 12, roll 4 degrees, 240 frames; tests/pose_media.py) through a pinhole whose focal
length is 4 frame sides, tracked with each pose setting; per setting the focal length used and each angle's
tracked size over its true size (1: right); then the solver fed the landmark vertices' true image positions, and
how far the tracked landmarks slide vertically per 10 degrees of nod. The video is written to a temporary folder
and removed. ``--probes`` also reads the rendered head, which moves no muscle, with the movement probes of the
retargeting evaluation: every column that "moved" is the pose's doing.

Real clips have no ground truth: the tracked head pose is set against the rotation of the tracked FaceMesh itself
(each frame's Umeyama rotation onto the take's median mesh, perspective taken out with the take's focal length),
which reads the rendered head's angles at 0.94-1.07 of their size. Per clip: the tracked pitch and yaw over the
mesh's (slopes); the median over the clips. The clips are tracked by ``eval/retarget.yaml``'s capture branch (the
pipeline's own store), once with the defaults and once with the former ones.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]  # this checkout's msflow and stages; tests/pose_media.py
FORMER = {"focal_length": None, "pose_landmarks": "rigid"}  # the defaults until 2026-12-03


def settings(true_focal: float) -> dict[str, dict]:
    """The pose settings the known-answer table compares (FaceMesh params beyond the defaults)."""
    return {
        "former defaults (frame width, ICT rigid subset with the jaw ends)": FORMER,
        "true focal length, ICT rigid subset": {"focal_length": true_focal, "pose_landmarks": "rigid"},
        "frame width, eyes and nose": {"focal_length": None, "pose_landmarks": "eyes_nose"},
        "defaults (estimated focal length, eyes and nose)": {},
    }


def rendered(size: int = 512, frames: int = 240, fps: int = 30) -> None:
    """The known-answer table."""
    from pose_media import FOCAL_PER_SIDE, known_turns, pose_gains, turned_head_video

    from msflow.testing import run_stage
    from stages.tracking import FaceMesh

    angles = known_turns(frames, fps)
    with tempfile.TemporaryDirectory() as work:
        video = turned_head_video(Path(work) / "turned.mp4", size, angles, fps, supersample=2)
        print(
            f"| pose setting (true focal length {FOCAL_PER_SIDE * size:.0f} px) | focal length used | yaw / pitch / roll read at |"
        )
        print("|---|---|---|")
        for name, setting in settings(FOCAL_PER_SIDE * size).items():
            run = run_stage(FaceMesh, {"audio": "none", **setting}, {"videos": {"turned": str(video)}})
            gains = pose_gains(run.arrays["rotation"], angles)
            print(f"| {name} | {run.meta['focal_length'][0]:.0f} | {' / '.join(f'{g:.2f}' for g in gains)} |")
        perfect_tracker(size, angles, run.arrays["landmarks"])


def perfect_tracker(size: int, angles: np.ndarray, tracked: np.ndarray) -> None:
    """The same angles from the landmark vertices' true image positions (the solver's own error), and how far the
    tracked landmarks slide vertically per 10 degrees of pitch against the true ones (IOD)."""
    from pose_media import FOCAL_PER_SIDE, pose_gains, true_landmarks

    from stages.eval.retarget import DEFAULT_FACE3D
    from stages.tracking.face3d import load_face3d
    from stages.tracking.pose import camera_matrix, solve_head_pose

    true = true_landmarks(size, angles)
    face = load_face3d(DEFAULT_FACE3D)
    camera = camera_matrix(size, size, FOCAL_PER_SIDE * size)
    rotation, _, _ = solve_head_pose(true, face.neutral, camera, np.asarray(face.rigid))
    gains = pose_gains(rotation, angles)
    print(
        f"| the true landmark positions, true focal length, ICT rigid subset | {camera[0, 0]:.0f} | {' / '.join(f'{g:.2f}' for g in gains)} |"
    )
    iod = np.linalg.norm(true[:, 45] - true[:, 36], axis=1).mean()
    slide = {}
    for name, point in (
        ("jaw line's ends (0, 16)", [0, 16]),
        ("nose tip (30)", [30]),
        ("eye corners (36, 45)", [36, 45]),
    ):
        dy = (np.asarray(tracked, np.float64)[:, point, 1] - true[:, point, 1]).mean(axis=1)
        slide[name] = abs(np.polyfit(angles[:, 1], dy / iod, 1)[0]) * 10
    print(
        "\ntracked landmarks' vertical slide against the true ones, IOD per 10 degrees of pitch: "
        + ", ".join(f"{k} {v:.3f}" for k, v in slide.items())
    )


def mesh_rotations(mesh: np.ndarray) -> np.ndarray:
    """(frames, 3, 3) rotation of each frame's points (frames, P, 3) onto their median (Umeyama, no scale)."""
    reference = np.median(mesh, axis=0)
    a = reference - reference.mean(axis=0)
    b = mesh - mesh.mean(axis=1, keepdims=True)
    u, _, vt = np.linalg.svd(np.einsum("fpi,pj->fij", b, a))
    d = np.ones((len(mesh), 3))
    d[:, -1] = np.sign(np.linalg.det(u @ vt))
    return u @ (d[..., None] * vt)


def small_angles(rotations: np.ndarray) -> np.ndarray:
    """(frames, 3) degrees about x, y, z of each rotation relative to the take's mean rotation."""
    u, _, vt = np.linalg.svd(rotations.mean(axis=0))
    relative = np.einsum("ji,fjk->fik", u @ vt, rotations)
    skew = relative - relative.transpose(0, 2, 1)
    return np.degrees(np.stack([skew[:, 2, 1], skew[:, 0, 2], skew[:, 1, 0]], axis=1) / 2)


def against_the_mesh(track) -> list[tuple[str, float, float]]:
    """Per take of a tracking artifact: (label, tracked pitch over the mesh's, tracked yaw over the mesh's)."""
    from stages.eval.retarget import take_cameras
    from stages.geometry.rotations import quat_to_matrix
    from stages.retarget.shapes3d import undo_perspective

    sequence = np.asarray(track["sequence"])
    cameras = take_cameras(track.meta, sequence)
    out = []
    for take, label in enumerate(track.meta["labels"]):
        rows = np.flatnonzero(sequence == take)
        mesh = undo_perspective(np.asarray(track["mesh"][rows[0] : rows[-1] + 1], np.float64), cameras[take])
        own = small_angles(mesh_rotations(mesh))
        tracked = small_angles(quat_to_matrix(np.asarray(track["rotation"])[rows]))
        pitch, yaw = (abs(np.polyfit(own[:, i], tracked[:, i], 1)[0]) for i in (0, 1))
        out.append((Path(label).stem, pitch, yaw))
    return out


def real(folders: list[str]) -> None:
    """The tracked pose over the FaceMesh's own rotation on real clips, with the defaults and the former ones."""
    import msflow

    pipeline = ROOT / "eval" / "retarget.yaml"
    for folder in folders:
        relative = os.path.relpath(Path(folder).resolve(), pipeline.parent)
        rows = {}
        former = [f"capture_track.{k}={'null' if v is None else v}" for k, v in FORMER.items()]
        for name, extra in (("defaults", []), ("former defaults", former)):
            result = msflow.run(pipeline, [f"vars.takes={relative}", *extra], until="capture_track")
            rows[name] = against_the_mesh(result.artifact("capture_track"))
        print(f"\n{Path(folder).name}: tracked pitch / yaw over the FaceMesh's own\n")
        print("| take | defaults | former defaults |\n|---|---|---|")
        for new, old in zip(rows["defaults"], rows["former defaults"]):
            print(f"| {new[0]} | {new[1]:.2f} / {new[2]:.2f} | {old[1]:.2f} / {old[2]:.2f} |")
        medians = {k: np.median([r[1:] for r in v], axis=0) for k, v in rows.items()}
        d, f = medians["defaults"], medians["former defaults"]
        print(f"| median | {d[0]:.2f} / {d[1]:.2f} | {f[0]:.2f} / {f[1]:.2f} |")


def rigid_face_probes(size: int = 512, frames: int = 240, fps: int = 30) -> None:
    """The movement probes (stages.retarget.movements) on the rendered head, which moves no muscle: every probe that
    "moved" is the tracker's (or the probes') reading of the pose alone. Runs ``eval/retarget.yaml``'s capture
    branch on the video (in the project's store)."""
    from pose_media import known_turns, turned_head_video

    import msflow

    with tempfile.TemporaryDirectory() as work:
        turned_head_video(Path(work) / "turned.mp4", size, known_turns(frames, fps), fps, supersample=2)
        overrides = [f"vars.takes={work}", "capture_track.audio=optional"]
        result = msflow.run(ROOT / "eval" / "retarget.yaml", overrides, until="capture_eval")
        take = next(iter(result.artifact("capture_eval").meta["takes"].values()))
    moved = sorted(((p / level, c) for c, (p, level) in take["movements"].items() if p > level), reverse=True)
    print(f"\nprobes on the rigid rendered head: {len(moved)} of {len(take['movements'])} columns 'moved': ")
    print(", ".join(f"{c} {r:.2f}x" for r, c in moved))


if __name__ == "__main__":
    os.chdir(ROOT)
    args = sys.argv[1:]
    rendered()
    if "--probes" in args:
        rigid_face_probes()
    real([a for a in args if a != "--probes"])
