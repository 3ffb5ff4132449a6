"""Which expressions to train on: leave-expressions-out study of the face analysis, a thin wrapper over eval/face.yaml.

    OPENBLAS_NUM_THREADS=1 python bench/eval_face.py [--takes DIR] [--reference NEU] [--sizes 3,4,5] [-j 2]
        [--json out.json]

Runs ``msflow sweep eval/face.yaml`` with ``face.train`` set to every set of 3, 4 or 5 expressions that includes the
reference (neutral) one, so every other take is unseen by that model. Each variant is the evaluation stage's normal
run (tracking, aam and bilinear are shared and computed once); this script only tabulates its metrics:

- per training set: temporal k-fold balanced accuracy of the model and of the nearest-frame baseline, and the edit
  fidelity of held-out neutral frames (landmark error edited->real vs neutral->real, inter-ocular distances);
- per unseen take and training set: the fraction of its frames classified as each training expression (the analysis'
  reading of it), and the fidelity of its edit into the training expressions (edited->real vs unedited->real).

All figures come from the stage's metrics (``msflow show -f eval/face.yaml face`` shows one variant's).
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

EXPRESSIONS = ["NEU", "HAP", "ANG", "DIS", "FEA", "SAD"]


def training_sets(expressions: list[str], reference: str, sizes: list[int]) -> list[list[str]]:
    """Every set of ``sizes`` expressions that includes ``reference`` (listed first)."""
    others = [e for e in expressions if e != reference]
    return [[reference, *extra] for n in sizes for extra in itertools.combinations(others, n - 1)]


def run(args) -> list[dict]:
    from msflow.sweep import run_sweep

    variants = [{"face.train": train} for train in training_sets(args.expressions, args.reference, args.sizes)]
    base = [f"vars.takes={Path(args.takes).resolve()}"] if args.takes else []
    result = run_sweep(ROOT / "eval" / "face.yaml", variants, base_overrides=base, jobs=args.jobs)
    failed = [v for v in result.variants if not v.ok]
    if failed:
        raise SystemExit(f"{len(failed)} variants failed, first: {failed[0].error}")
    return [{"train": v.params["face.train"], "metrics": v.metrics["face"]} for v in result.variants]


def print_training_sets(rows: list[dict]) -> None:
    print(
        "| training expressions | k-fold accuracy | nearest-frame baseline | chance | edit landmarks (edited / neutral) |"
    )
    print("|---|---|---|---|---|")
    for row in rows:
        m = row["metrics"]
        print(
            f"| {' '.join(row['train'])} | {m['accuracy']:.2f} | {m['baseline_accuracy']:.2f} | {m['chance']:.2f} | "
            f"{m['edit_landmark_error']:.4f} / {m['unedited_landmark_error']:.4f} |"
        )


def print_unseen(rows: list[dict], expressions: list[str]) -> None:
    print(
        "\n| unseen take | training expressions | analysed as (fraction of frames) | edit landmarks (edited / unedited) "
        "| edit texture (edited / unedited) | residual |"
    )
    print("|---|---|---|---|---|---|")
    for unseen in expressions:
        for row in rows:
            m, train = row["metrics"], row["train"]
            if unseen in train or f"unseen_{unseen}_residual" not in m:
                continue
            reading = " ".join(f"{s} {m[f'unseen_{unseen}_as_{s}']:.0%}" for s in train)
            prefix = f"unseen_{unseen}_"
            print(
                f"| {unseen} | {' '.join(train)} | {reading} | {m[prefix + 'edit_landmark_error']:.4f} / "
                f"{m[prefix + 'unedited_landmark_error']:.4f} | {m[prefix + 'edit_texture_error']:.1f} / "
                f"{m[prefix + 'unedited_texture_error']:.1f} | {m[prefix + 'residual']:.3f} |"
            )


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--takes", default=None, help="folder of takes (default: the embedded CREMA-D clips)")
    parser.add_argument("--expressions", type=lambda s: s.split(","), default=EXPRESSIONS)
    parser.add_argument("--reference", default="NEU")
    parser.add_argument("--sizes", type=lambda s: [int(x) for x in s.split(",")], default=[3, 4, 5])
    parser.add_argument("-j", "--jobs", type=int, default=1)
    parser.add_argument("--json", default=None, help="write every variant's metrics to this file")
    args = parser.parse_args(argv)
    rows = run(args)
    print_training_sets(rows)
    print_unseen(rows, args.expressions)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
