"""A folder of takes that gains one: what tracking it again costs, with each take kept as a part (msflow.parts).

    python bench/bench_parts.py [--clips DIR] [--first a.mp4,b.mp4,...] [--added c.mp4] [--work DIR]

A project copy (msflow/, stages/, data/) gets a pipeline with one FaceMesh stage over ``clips/*.mp4``, whose files
are symbolic links to ``--clips``. Three CLI runs, each in a fresh process: the ``--first`` clips into an empty
store; the same with ``--added`` linked in (the first clips' parts are found); all of them into a second, empty
store (what a run costs without parts). Printed: wall seconds of each, the run's parts line, and whether the two
artifacts of the full folder have the same content hash (they must). Defaults: four of the shared talking-head
clips (100 s of video) and a 5 s one added.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PIPELINE = """version: 1
store: {store}
stages:
  track:
    uses: stages.tracking:FaceMesh
    inputs: {{videos: {{glob: "clips/*.mp4"}}}}
"""


def run(project: Path, pipeline: str) -> tuple[float, str]:
    """One ``msflow run`` in a fresh process: wall seconds and its line for the tracking stage."""
    env = {**os.environ, "PYTHONPATH": str(project)}
    env.pop("PYTHONDONTWRITEBYTECODE", None)  # users have bytecode caches
    started = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-m", "msflow.cli", "run", pipeline], cwd=project, env=env, capture_output=True, text=True
    )
    seconds = time.perf_counter() - started
    if done.returncode:
        sys.exit(f"msflow run {pipeline} failed:\n{done.stderr}")
    line = next((ln.strip() for ln in done.stderr.splitlines() if " track " in f" {ln} " and "done" in ln), "")
    return seconds, line


def content_hashes(project: Path, store: str) -> set[str]:
    """The content hashes of the tracking artifacts in one of the project's stores."""
    sys.path.insert(0, str(project))
    from msflow.stores import open_store

    opened = open_store(str(project / store))
    return {opened.manifest(k)["content_hash"] for k in opened.keys() if "parts" in opened.manifest(k)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--clips", type=Path, default=ROOT.parent / "shared" / "data" / "talking-heads")
    parser.add_argument("--first", default="address_fr.mp4,address_us.mp4,hdtf_aoc.mp4,hdtf_kh.mp4")
    parser.add_argument("--added", default="retalking_2.mp4")
    parser.add_argument("--work", type=Path, default=Path("/tmp/msflow-bench-parts"))
    args = parser.parse_args()
    shutil.rmtree(args.work, ignore_errors=True)
    project = args.work / "project"
    for name in ("msflow", "stages", "data", "pyproject.toml"):
        copy = shutil.copytree if (ROOT / name).is_dir() else shutil.copy2
        copy(ROOT / name, project / name)  # type: ignore[operator]
    (project / "clips").mkdir()
    (project / "grown.yaml").write_text(PIPELINE.format(store=".msflow"))
    (project / "fresh.yaml").write_text(PIPELINE.format(store=".msflow-fresh"))
    for name in args.first.split(","):
        (project / "clips" / name).symlink_to((args.clips / name).resolve())
    first = run(project, "grown.yaml")
    (project / "clips" / args.added).symlink_to((args.clips / args.added).resolve())
    grown = run(project, "grown.yaml")
    fresh = run(project, "fresh.yaml")
    for label, (seconds, line) in (("first clips", first), ("one clip added", grown), ("all, empty store", fresh)):
        print(f"{label:18} {seconds:7.2f} s   {line}")
    from_scratch = content_hashes(project, ".msflow-fresh")
    print(f"same artifact as from scratch: {from_scratch <= content_hashes(project, '.msflow')}")


if __name__ == "__main__":
    main()
