"""The retargeting evaluation as a table: ``eval/retarget.yaml`` on the embedded CREMA-D takes (the capture branch
and the default run's paper branch) and, given folders, the capture branch on each; with ``--capture``, the
performance-capture pipeline ``pipelines/capture.yaml`` run on each clip given (GLB, CSV, preview in out/) and
scored the same way.

    python bench/eval_retarget.py [FOLDER ...]          # from the project root
    python bench/eval_retarget.py ../shared/data/talking-heads
    python bench/eval_retarget.py --capture ../shared/data/talking-heads/{hdtf_kh,retalking_2,vlog_31}.mp4

Prints one markdown row per run (pooled over the takes) and one per take of each folder. Every number is a stage
metric of ``stages.eval.retarget:RetargetEval``; ``msflow show -f eval/retarget.yaml capture_eval`` shows the same.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's msflow and stages, whichever one pip installed
PIPELINE = ROOT / "eval" / "retarget.yaml"
COLUMNS = [
    ("mouth err", "mouth_motion_error_iod", "{:.1%}"),
    ("mouth err shifted", "mouth_motion_error_iod_shifted", "{:.1%}"),
    ("eyes err", "eyes_motion_error_iod", "{:.1%}"),
    ("brows err", "brows_motion_error_iod", "{:.1%}"),
    ("mouth abs", "mouth_error_iod", "{:.1%}"),
    ("keyshape residual", "keyshape_residual_rms_iod", "{:.1%}"),
    ("closures", None, None),
    ("blink recall", "blink_recall", "{:.0%}"),
    ("false blinks", "false_blink_rate", "{:.0%}"),
    ("jaw > funnel", "jaw_over_funnel_fraction", "{:.0%}"),
    ("env r char/perf/shift", None, None),
    ("dead ARKit", "dead_arkit_columns", "{:.0f}"),
]


def row(name: str, m: dict) -> str:
    cells = [name]
    for _, key, fmt in COLUMNS:
        if key is not None:
            cells.append(fmt.format(m[key]) if key in m else "-")
        elif _ == "closures":
            cells.append(f"{m['closures_reproduced']:.0f}/{m['closures']:.0f}")
        else:
            keys = ("envelope_r_character", "envelope_r_performer", "envelope_r_shifted")
            cells.append("/".join(f"{m[k]:.2f}" for k in keys) if keys[0] in m else "-")
    return "| " + " | ".join(cells) + " |"


def per_take(view, tracks, keyshapes) -> list[tuple[str, dict]]:
    """Per take, from the per-frame outputs of the evaluation and the keyshapes: landmark errors, closures and
    the decomposition residual."""
    from stages.eval.retarget import closure_agreement

    sequence = np.asarray(tracks["sequence"])
    error = view["region_error"]
    regions = view.meta["regions"]
    gaps = view["lip_gap"]
    out = []
    for take, label in enumerate(view.meta["labels"]):
        rows = sequence == take
        m = {f"{r}_motion_error_iod": float(np.sqrt(np.mean(error[rows, i] ** 2))) for i, r in enumerate(regions)}
        closures = closure_agreement(gaps[rows, 0], gaps[rows, 1], sequence[rows], gap=0.03, frames=2, ratio=1.2)
        m["closures"], m["closures_reproduced"] = len(closures), sum(c["reproduced"] for c in closures)
        m["keyshape_residual_rms_iod"] = float(np.sqrt(np.mean(keyshapes["residual"][0, rows] ** 2)))
        out.append((Path(label).name, m))
    return out


def capture(clips: list[str]) -> None:
    """pipelines/capture.yaml on each clip, scored against the clip's tracking (RetargetEval on its artifacts)."""
    import resource

    import msflow
    from msflow.testing import run_stage
    from stages.eval.retarget import RetargetEval

    pipeline = ROOT / "pipelines" / "capture.yaml"
    clips = [Path(c).resolve() for c in clips]
    os.chdir(ROOT)
    print("| clip | frames | CPU s | " + " | ".join(c for c, _, _ in COLUMNS) + " | export warnings |")
    print("|" + "---|" * (len(COLUMNS) + 4))
    for clip in clips:
        before = resource.getrusage(resource.RUSAGE_SELF)
        take = os.path.relpath(clip, pipeline.parent)
        result = msflow.run(pipeline, [f"vars.take={take}", f"vars.name={clip.stem}_captured"])
        after = resource.getrusage(resource.RUSAGE_SELF)
        cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
        inputs = {
            n: result.artifact(s) for n, s in (("tracks", "track"), ("blend", "blend"), ("character", "character"))
        }
        metrics = run_stage(RetargetEval, {}, dict(inputs, keyshapes=result.artifact("keyshapes"))).metrics
        export = result.artifact("export")
        frames = len(result.artifact("blend")["weights"])
        cells = row(clip.name, metrics).rstrip(" |").split(" | ")
        print(" | ".join([cells[0], str(frames), f"{cpu:.1f}"] + cells[1:]) + f" | {len(export.warnings)} |")


def main(folders: list[str]) -> None:
    import msflow

    folders = [Path(f).resolve() for f in folders]
    os.chdir(ROOT)
    header = "| run | " + " | ".join(c for c, _, _ in COLUMNS) + " |"
    print(header)
    print("|" + "---|" * (len(COLUMNS) + 1))
    default = msflow.run(PIPELINE)
    print(row("CREMA-D 1001, default run's path (edit of the unseen sad take)", default.artifact("paper_eval").metrics))
    print(row("CREMA-D 1001, capture of the 6 takes", default.artifact("capture_eval").metrics))
    for folder in folders:
        relative = os.path.relpath(folder, PIPELINE.parent)
        result = msflow.run(PIPELINE, [f"vars.takes={relative}"], until="capture_eval")
        view = result.artifact("capture_eval")
        print(row(f"{Path(folder).name}, capture of {len(view.meta['labels'])} takes", view.metrics))
        for label, m in per_take(view, result.artifact("capture_track"), result.artifact("capture_keyshapes")):
            print(row(f"  {label}", m))


if __name__ == "__main__":
    if sys.argv[1:2] == ["--capture"]:
        capture(sys.argv[2:])
    else:
        main(sys.argv[1:])
