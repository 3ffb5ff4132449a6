"""FaceMesh keeps each take's tracking as a part (Stage.part): a folder of clips that gains one tracks only the
new clip, and the artifact equals the one tracked from scratch."""

import shutil

from conftest import copy_project
from tracking_media import CLIPS, first_frames, write_video

import msflow

PIPELINE = """version: 1
stages:
  track:
    uses: stages.tracking:FaceMesh
    inputs: {videos: {glob: "clips/*.mp4"}}
    params: {audio: none}
"""


def short_clip(name, folder):
    """The first 12 frames of a CREMA-D clip, with no sound: enough to track, quick to track."""
    path = folder / f"{name}.mp4"
    if not path.exists():
        write_video(path, first_frames(CLIPS[name], 12), fps=30)
    return path


def project_with_clips(dest, clips):
    proj = copy_project(dest, names=("data", "stages", "pyproject.toml"))
    (proj / "pipeline.yaml").write_text(PIPELINE)
    (proj / "clips").mkdir()
    for clip in clips:
        shutil.copy2(clip, proj / "clips" / clip.name)
    return proj


def test_a_clip_added_to_the_folder_is_the_only_one_tracked(tmp_path):
    neutral, happy, sad = (short_clip(name, tmp_path) for name in ("NEU", "HAP", "SAD"))
    proj = project_with_clips(tmp_path / "grown", [neutral, happy])
    msflow.run(proj / "pipeline.yaml")
    shutil.copy2(sad, proj / "clips" / sad.name)
    grown = msflow.run(proj / "pipeline.yaml").states["track"]
    assert grown.state == "ran" and grown.detail == "2 of 3 parts reused"
    assert grown.manifest["parts"]["reused"] == ["HAP.mp4", "NEU.mp4"]
    fresh = msflow.run(project_with_clips(tmp_path / "fresh", [neutral, happy, sad]) / "pipeline.yaml")
    tracked = fresh.states["track"].manifest
    assert tracked["parts"]["reused"] == []
    assert grown.manifest["content_hash"] == tracked["content_hash"]
    assert grown.manifest["meta"]["sources"] == ["HAP.mp4", "NEU.mp4", "SAD.mp4"]
    assert grown.manifest["meta"]["frames"] == [12, 12, 12]
    heard = msflow.run(proj / "pipeline.yaml", overrides=("track.audio=optional",)).states["track"]
    assert heard.state == "ran" and heard.detail == "3 of 3 parts reused"  # the audio params reach no part
