"""Streaming FaceMesh: the streaming gap filler agrees with the whole-take plan, blocks and worker counts do not
change results, pictures come from Y'CbCr planes with the right colours, and bad input (variable frame rate, a
face gone for longer than max_gap_frames, a file cut halfway) is kept, marked or refused, never half-written."""

import json
import subprocess
import sys
import time
from fractions import Fraction
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import cli_env, run_cli
from tracking_media import CLIPS, first_frames, write_untimed_video, write_video

from msflow import UserError
from msflow.testing import run_stage
from stages.tracking import FaceMesh
from stages.tracking.gaps import FILLED, HELD, TRACKED, apply_plan, fill_gaps, gap_plan
from stages.tracking.planes import RegionConverter, frame_planes
from stages.tracking.pose import PoseSolver, camera_matrix, solve_head_pose
from stages.tracking.stream import FrameRecord, GapFiller
from stages.tracking.video import FrameClock

# ------------------------------------------------------------------------------------- gaps


def stream_fill(valid, values, max_gap):
    filler, out = GapFiller(max_gap), []
    for i, ok in enumerate(valid):
        out += filler.push(FrameRecord(float(i), values[i] if ok else None, 1.0, crop=np.full(1, i) if ok else None))
    out += filler.finish()
    return out


@pytest.mark.parametrize("seed", range(6))
def test_streaming_gap_filler_is_the_whole_take_plan(seed):
    rng = np.random.default_rng(seed)
    n = 60
    valid = rng.random(n) > 0.3
    valid[rng.integers(0, 40) : rng.integers(40, 60)] = seed % 2 == 0  # sometimes one long gap
    valid[rng.integers(0, n)] = True
    values = rng.normal(size=(n, 4, 3))
    a, b, w, kind = gap_plan(valid, max_gap=5)
    out = stream_fill(valid, values, 5)
    assert [f.record.time for f in out] == list(range(n))  # every frame, in order
    np.testing.assert_array_equal([f.kind for f in out], kind)
    np.testing.assert_array_equal(np.stack([f.points for f in out]), apply_plan(values, a, b, w))
    for f, source in zip(out, a):  # held frames carry the crop of the frame they hold
        if f.kind == HELD:
            assert f.crop[0] == source


def test_gap_plan_known_cases():
    valid = np.array([0, 1, 1, 0, 0, 1, 0, 0, 0, 0, 1, 0], bool)
    a, b, w, kind = gap_plan(valid, max_gap=3)
    np.testing.assert_array_equal(kind, [FILLED, 0, 0, FILLED, FILLED, 0, HELD, HELD, HELD, HELD, 0, FILLED])
    np.testing.assert_array_equal(a, [1, 1, 2, 2, 2, 5, 5, 5, 5, 5, 10, 10])  # held across 6-9: frame 5
    np.testing.assert_allclose(w[3:5], [1 / 3, 2 / 3])
    values = np.arange(12.0)
    filled, sources, long = fill_gaps(values, valid, 3, "hold")
    np.testing.assert_allclose(filled, [1, 1, 2, 3, 4, 5, 5, 5, 5, 5, 10, 10])
    assert long == [(6, 10)] and list(sources[6:10]) == [5] * 4 and sources[3] == 3
    with pytest.raises(UserError, match=r"frames 6-9 \(4 frames"):
        fill_gaps(values, valid, 3, "error")
    lead = np.array([0] * 5 + [1, 1], bool)
    a, _, _, kind = gap_plan(lead, max_gap=2)
    assert list(a[:5]) == [5] * 5 and (kind[:5] == HELD).all()  # a long gap at the start holds the first face
    assert (kind[5:] == TRACKED).all()


# ------------------------------------------------------------------------------------- pose and planes


def test_pose_solver_by_blocks_is_the_whole_sequence():
    from stages.tracking.face3d import load_face3d
    from stages.tracking.pose import project_face

    face = load_face3d().neutral
    cam = camera_matrix(640, 480)
    yaw = np.radians(np.linspace(-20, 170, 40))  # past 90 degrees: the quaternion sign must stay continuous
    from stages.geometry.rotations import euler_to_quat

    q = euler_to_quat(yaw * 0.1, yaw * 0.05, 0 * yaw)
    lm = project_face(face, q, np.tile([0.0, 0.0, -60.0], (40, 1)), cam)
    whole = solve_head_pose(lm, face, cam)
    solver = PoseSolver(face, cam)
    parts = [solver.solve(lm[s]) for s in (slice(0, 7), slice(7, 8), slice(8, 40))]
    for k in range(3):
        np.testing.assert_array_equal(np.concatenate([p[k] for p in parts]), whole[k])


@pytest.mark.parametrize("fmt", ["yuv420p", "yuvj420p", "yuv422p", "yuv444p", "nv12"])
@pytest.mark.parametrize("height", [180, 181])
def test_warps_read_exactly_the_whole_frame_conversion(fmt, height):
    """Regions converted on demand are FFmpeg's whole-frame BGR, byte for byte, so every warp (the model's patch,
    the gray crop) is what it was when each whole frame was converted."""
    import av
    import cv2

    rng = np.random.default_rng(1)
    y, x = np.mgrid[0:height, 0:244]
    rgb = np.stack([x, y * 1.4, 255 - x + y], axis=-1) + rng.normal(scale=20, size=(height, 244, 3))
    frame = av.VideoFrame.from_ndarray(rgb.clip(0, 255).astype(np.uint8), format="rgb24").reformat(format=fmt)
    whole = frame.to_ndarray(format="bgr24")
    gray = cv2.cvtColor(whole, cv2.COLOR_BGR2GRAY)
    converter = RegionConverter()
    for angle, scale, centre, size in ((0.3, 0.7, (120, 90), 64), (-0.2, 1.6, (20, 170), 96), (1.0, 0.4, (240, 5), 48)):
        planes = frame_planes(frame, converter)  # a fresh frame object: no region cached yet
        c, s = np.cos(angle) * scale, np.sin(angle) * scale
        affine = np.array(
            [[c, s, size / 2 - c * centre[0] - s * centre[1]], [-s, c, size / 2 + s * centre[0] - c * centre[1]]]
        )
        expect = cv2.warpAffine(whole, affine, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        np.testing.assert_array_equal(planes.warp_bgr(affine, size), expect)
        expect = cv2.warpAffine(gray, affine, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        np.testing.assert_array_equal(planes.warp_gray(affine, size), expect)
    np.testing.assert_array_equal(frame_planes(frame, converter).gray(), gray)


# ------------------------------------------------------------------------------------- the stage


def run_with_jobs(params, videos, jobs):
    return run_stage(FaceMesh, params, {"videos": videos}, jobs=jobs).arrays, None


def test_results_do_not_depend_on_workers_or_blocks(monkeypatch):
    import stages.tracking.stream as stream

    videos = {"sad": CLIPS["SAD"], "hap": CLIPS["HAP"]}
    params = {"audio": "none"}
    serial, _ = run_with_jobs(params, videos, 1)
    parallel, _ = run_with_jobs(params, videos, 2)
    monkeypatch.setattr(stream, "BLOCK_FRAMES", 7)
    small_blocks, _ = run_with_jobs(params, videos, 1)
    assert set(serial) == set(parallel) == set(small_blocks)
    for name in serial:
        np.testing.assert_array_equal(parallel[name], serial[name], err_msg=name)
        np.testing.assert_array_equal(small_blocks[name], serial[name], err_msg=name)


def test_variable_frame_rate_keeps_the_timestamps(tmp_path):
    frames = first_frames(CLIPS["NEU"], 20)
    times = np.cumsum(np.r_[0.0, np.where(np.arange(19) % 3 == 0, 0.05, 0.025)])
    vfr = write_video(tmp_path / "vfr.mp4", frames, times=times)
    out = run_stage(FaceMesh, {"audio": "none"}, {"videos": {"v": vfr}})
    np.testing.assert_allclose(out.arrays["time"], times, atol=1e-3)
    assert out.arrays["valid"].all()


def test_frames_without_usable_timestamps_are_timed_by_the_rate_with_a_warning(tmp_path):
    """Every frame at timestamp 0: the frames are timed at the declared 25 fps (not FFmpeg's average, 8 frames over
    one frame's duration: 200 fps), the take's rate is 25 fps and a warning names the file. Before: all times 0,
    which the export divided by."""
    untimed = write_untimed_video(tmp_path / "untimed.mp4", first_frames(CLIPS["NEU"], 8), fps=25)
    with pytest.warns(UserWarning, match="untimed.mp4: 7 of 8 frames .* timed at the stream's 25 fps"):
        out = run_stage(FaceMesh, {"audio": "none"}, {"videos": {"u": untimed}})
    np.testing.assert_allclose(out.arrays["time"], np.arange(8) / 25.0, atol=1e-9)
    assert out.meta["fps"] == [25.0] and any("untimed.mp4" in w for w in out.warnings)


def test_unusable_timestamps_and_no_frame_rate_are_a_user_error():
    """Nothing to time a frame by: a UserError naming the file and field, not times that stand still."""
    clock = FrameClock(Path("still.mp4"), "inputs.videos.s", fps=0.0)
    frame = SimpleNamespace(pts=0, time_base=Fraction(1, 12800))
    assert clock.time(frame) == 0.0
    with pytest.raises(UserError, match="no frame rate") as err:
        clock.time(frame)
    assert err.value.file == "still.mp4" and err.value.field == "inputs.videos.s"


def test_increasing_timestamps_are_kept_without_a_warning():
    """Uneven but increasing timestamps (dropped frames) are the frames' times; only a repeated or missing one
    is re-timed, one frame after the previous frame."""
    clock = FrameClock(Path("vfr.mp4"), None, fps=30.0)
    stamps = [3000, 3033, 3100, 3100, None, 3200]  # ms: a dropped frame, a repeated and a missing timestamp
    times = [clock.time(SimpleNamespace(pts=s, time_base=Fraction(1, 1000))) for s in stamps]
    np.testing.assert_allclose(times, [0.0, 0.033, 0.1, 0.1 + 1 / 30, 0.1 + 2 / 30, 0.2])
    with pytest.warns(UserWarning, match="vfr.mp4: 2 of 6 frames"):
        clock.warn(6)


@pytest.fixture(scope="module")
def gap_video(tmp_path_factory):
    """The neutral clip with frames 20-29 replaced by a blank grey picture."""
    frames = first_frames(CLIPS["NEU"], 61)
    for i in range(20, 30):
        frames[i][:] = 128
    return write_video(tmp_path_factory.mktemp("gap") / "gap.mp4", frames)


def test_a_long_gap_is_held_and_marked(gap_video):
    out = run_stage(FaceMesh, {"max_gap_frames": 5, "audio": "none"}, {"videos": {"g": gap_video}})
    a = out.arrays
    assert not a["valid"][20:30].any() and a["valid"][:20].all() and a["valid"][30:].all()
    for name in ("landmarks", "mesh", "crops", "crop_transforms", "eye_aperture", "gaze"):
        np.testing.assert_array_equal(a[name][20:30], np.repeat(a[name][19:20], 10, axis=0), err_msg=name)
    # the pose is solved again from the held landmarks (each solve starts from the last): the same to 1e-6
    np.testing.assert_allclose(a["rotation"][20:30], np.repeat(a["rotation"][19:20], 10, axis=0), atol=1e-6)
    assert (a["confidence"][20:30] == 0).all()
    assert out.meta["gaps"] == [[[20, 30]]] and out.meta["long_gaps"] == "hold"
    with pytest.raises(UserError, match=r"no face in frames 20-29 \(10 frames"):
        run_stage(FaceMesh, {"max_gap_frames": 5, "long_gaps": "error", "audio": "none"}, {"videos": {"g": gap_video}})


def test_a_held_gap_is_a_warning_and_a_cut_file_leaves_no_artifact(gap_video, tmp_path):
    data = CLIPS["ANG"].read_bytes()
    cut = tmp_path / "cut.flv"
    cut.write_bytes(data[: len(data) // 2])
    (tmp_path / "pipeline.yaml").write_text(
        "version: 1\nstages:\n"
        f"  held:\n    uses: stages.tracking:FaceMesh\n    inputs: {{videos: {{g: {gap_video}}}}}\n"
        "    params: {max_gap_frames: 5, audio: none, output_mesh: false}\n"
        f"  cut:\n    uses: stages.tracking:FaceMesh\n    inputs: {{videos: {{c: {cut}}}}}\n"
    )
    proc = run_cli(tmp_path, "run", "--until", "held")
    assert proc.returncode == 0, proc.stderr
    assert "take 'g': no face in frames 20-29" in proc.stdout + proc.stderr
    proc = run_cli(tmp_path, "run")
    assert proc.returncode == 2 and "truncated" in proc.stderr and "cut.flv" in proc.stderr
    assert "Traceback" not in proc.stderr
    shown = run_cli(tmp_path, "show", "cut")
    assert shown.returncode != 0  # nothing was stored for the stage that failed halfway


# A run of the real tracking stage stopped between two blocks of frames: the driver patches the stage so that after
# its first block went to the output sinks it marks a file and waits (forever) to be killed, then runs the CLI
# in-process (-j 1), so the stage is killed mid-stream at a known point, not after a guessed delay.
KILL_DRIVER = """
import sys, threading
from pathlib import Path
import stages.tracking.stream as stream

stream.BLOCK_FRAMES = 8
original = stream.BlockWriter._flush

def flush_then_wait(self, frames):
    original(self, frames)
    Path(sys.argv[1]).touch()
    threading.Event().wait()

stream.BlockWriter._flush = flush_then_wait
from msflow.cli import main
sys.exit(main(sys.argv[2:]))
"""


def test_a_tracking_run_killed_mid_stream_leaves_nothing_and_the_rerun_is_whole(tmp_path):
    from msflow.artifact import read_artifact

    clip = write_video(tmp_path / "short.mp4", first_frames(CLIPS["NEU"], 30))
    (tmp_path / "pipeline.yaml").write_text(
        f"version: 1\nstages:\n  track:\n    uses: stages.tracking:FaceMesh\n    inputs: {{videos: {{v: {clip}}}}}\n"
        "    params: {audio: none}\n"
    )
    (tmp_path / "driver.py").write_text(KILL_DRIVER)
    ready = tmp_path / "ready"
    cmd = [sys.executable, str(tmp_path / "driver.py"), str(ready), "run", "-j", "1", "-q"]
    proc = subprocess.Popen(cmd, cwd=tmp_path, env=cli_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120
        while not ready.exists():  # polls for the mark the stage writes after its first block
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
            time.sleep(0.01)
    finally:
        proc.kill()
        proc.wait()
    artifacts = tmp_path / ".msflow" / "artifacts"
    assert not artifacts.exists() or not any(artifacts.glob("*/*")), "a killed run left an artifact"
    result = run_cli(tmp_path, "run", "-q")
    assert result.returncode == 0, result.stderr
    assert run_cli(tmp_path, "verify").returncode == 0
    key = json.loads(sorted((tmp_path / ".msflow" / "runs").glob("*.json"))[-1].read_text())["stages"]["track"]["key"]
    stored = read_artifact(artifacts / key[:2] / key)
    whole = run_stage(FaceMesh, {"audio": "none"}, {"videos": {"v": clip}}).arrays
    assert stored["landmarks"].shape[0] == 30
    for name in ("landmarks", "mesh", "crops", "rotation", "valid"):
        np.testing.assert_array_equal(stored[name], whole[name], err_msg=name)
