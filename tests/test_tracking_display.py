"""Videos stored turned or mirrored with a display matrix (a phone's portrait video, a front camera's mirror image):
tracked as a player shows them (stages/tracking/display.py)."""

import shutil
import subprocess

import numpy as np
import pytest
from conftest import missing_tool
from tracking_media import CLIPS, first_frames, write_video

from msflow import UserError
from msflow.testing import run_stage
from stages.geometry.rotations import quat_to_euler
from stages.tracking import FaceMesh
from stages.tracking.display import display_matrix, stored_picture
from stages.tracking.video import iter_frames, probe_video

#: every quarter turn, with and without each mirror
TURNS = [(angle, h, v) for angle in (0, 90, 180, 270) for h in (0, 1) for v in (0, 1)]


def picture() -> np.ndarray:
    """48 x 64 BGR with three flat marks, no two alike under any turn or mirror."""
    image = np.full((48, 64, 3), 40, np.uint8)
    image[4:16, 4:20] = (255, 0, 0)
    image[4:12, 44:60] = (0, 255, 0)
    image[32:44, 8:16] = (0, 0, 255)
    return image


@pytest.mark.parametrize("angle,hflip,vflip", TURNS)
def test_a_turned_or_mirrored_video_is_read_as_shown(tmp_path, angle, hflip, vflip):
    """Known answer: the stored frames are the picture turned back, so reading them as shown gives the picture."""
    matrix = display_matrix(angle, hflip, vflip)
    upright = picture()
    path = write_video(tmp_path / "turned.mp4", [stored_picture(upright, matrix)] * 3, display=matrix)
    info = probe_video(path)
    assert (info.width, info.height) == (64, 48)
    for _, frame in iter_frames(path):
        assert frame.shape == upright.shape
        assert np.abs(frame.astype(int) - upright).mean() < 4  # the codec's error only


@pytest.mark.parametrize("angle,hflip,vflip", [(90, 0, 0), (270, 0, 0), (90, 1, 0), (180, 0, 1)])
def test_the_display_convention_is_ffmpegs(tmp_path, angle, hflip, vflip):
    """FFmpeg's command-line tool turns a video by its display matrix when it decodes it; ours must show the same."""
    if shutil.which("ffmpeg") is None:
        missing_tool("FFmpeg's command-line tool is not installed: apt-get install -y ffmpeg")
    matrix = display_matrix(angle, hflip, vflip)
    path = write_video(tmp_path / "turned.mp4", [stored_picture(picture(), matrix)] * 3, display=matrix)
    raw = subprocess.run(
        ["ffmpeg", "-v", "error", "-i", str(path), "-frames:v", "1", "-pix_fmt", "bgr24", "-f", "rawvideo", "-"],
        capture_output=True,
        check=True,
    ).stdout
    ours = next(iter_frames(path))[1]
    theirs = np.frombuffer(raw, np.uint8).reshape(ours.shape)
    assert np.abs(theirs.astype(int) - ours).mean() < 2


def test_a_display_matrix_of_another_angle_is_a_user_error(tmp_path):
    path = write_video(tmp_path / "tilted.mp4", [picture()] * 2, display=display_matrix(30))
    with pytest.raises(UserError, match="30 degrees"):
        list(iter_frames(path))


def test_a_portrait_phone_video_is_tracked_upright(tmp_path):
    """A CREMA-D take stored on its side (turned a quarter, and another turned three quarters and mirrored) tracks
    as the upright copy does: the same landmarks and head pose, the frame size as shown. Read as stored, the
    landmarks would lie on their side and the head would roll by 90 degrees."""
    frames = first_frames(CLIPS["SAD"], 20)
    videos = {"upright": write_video(tmp_path / "upright.mp4", frames)}
    for name, matrix in {"turned": display_matrix(90), "mirrored": display_matrix(270, 1, 0)}.items():
        videos[name] = write_video(
            tmp_path / f"{name}.mp4", [stored_picture(f, matrix) for f in frames], display=matrix
        )
    run = run_stage(FaceMesh, {"audio": "none"}, {"videos": videos}, store=tmp_path / "store")
    labels, sequence = run.meta["labels"], run.arrays["sequence"]
    rows = {name: sequence == labels.index(name) for name in videos}
    landmarks = run.arrays["landmarks"]
    roll = np.degrees(quat_to_euler(run.arrays["rotation"]))
    height, width = frames[0].shape[:2]
    assert run.meta["frame_size"] == [[width, height]] * 3
    for name in ("turned", "mirrored"):
        error = np.linalg.norm(landmarks[rows[name]] - landmarks[rows["upright"]], axis=-1)
        assert np.median(error) < 1.0, (name, np.median(error))
        assert np.abs(roll[rows[name]] - roll[rows["upright"]]).max() < 2.0, name
