"""FaceMesh keeps each take's tracking as a part (Stage.part): a folder of clips that gains one tracks only the
new clip, and the artifact equals the one tracked from scratch."""

import shutil

from conftest import copy_project
from tracking_media import CLIPS

import msflow

PIPELINE = """version: 1
stages:
  track:
    uses: stages.tracking:FaceMesh
    inputs: {videos: {glob: "clips/*.flv"}}
"""


def project_with_clips(dest, names):
    proj = copy_project(dest, names=("data", "stages", "pyproject.toml"))
    (proj / "pipeline.yaml").write_text(PIPELINE)
    (proj / "clips").mkdir()
    for name in names:
        shutil.copy2(CLIPS[name], proj / "clips" / CLIPS[name].name)
    return proj


def test_a_clip_added_to_the_folder_is_the_only_one_tracked(tmp_path):
    proj = project_with_clips(tmp_path / "grown", ["NEU", "HAP"])
    msflow.run(proj / "pipeline.yaml")
    shutil.copy2(CLIPS["SAD"], proj / "clips" / CLIPS["SAD"].name)
    grown = msflow.run(proj / "pipeline.yaml").states["track"]
    assert grown.state == "ran" and grown.detail == "2 of 3 parts reused"
    assert grown.manifest["parts"]["reused"] == [CLIPS["HAP"].name, CLIPS["NEU"].name]
    fresh = msflow.run(project_with_clips(tmp_path / "fresh", ["NEU", "HAP", "SAD"]) / "pipeline.yaml")
    tracked = fresh.states["track"].manifest
    assert tracked["parts"]["reused"] == []
    assert grown.manifest["content_hash"] == tracked["content_hash"]
    assert grown.manifest["meta"]["sources"] == [CLIPS[n].name for n in ("HAP", "NEU", "SAD")]
