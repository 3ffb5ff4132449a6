"""The head-motion goals table (issue 12) from the evaluation pipelines, one command:

    python bench/eval_head.py                       # CREMA-D, the shared talking-head clips, synthetic takes
    python bench/eval_head.py --data crema-d        # one of them
    python bench/eval_head.py --shared /path/to/shared -S motion_blend.timing=strokes

Each row is one run of an evaluation pipeline (stages.eval.head): CREMA-D ``eval/head.yaml`` (leave one take out;
one speaker), the talking-head clips ``eval/head_talking_heads.yaml`` (leave one speaker out, and leave one take out
with ``vars.holdout=take``),
synthetic takes ``eval/head_csv.yaml`` (67 phrases of tests/head_synthetic.py whose head pitch follows the voice's
pitch, written as CSV + WAV into --work; leave one take out). ``-S`` overrides go to every pipeline (stage params and vars). Results are cached in the
project's store like any run; ``msflow show -f eval/head.yaml evaluate`` prints every metric.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

COLUMNS = [
    ("utterances", "utt.", "{:.0f}"),
    ("ba_synth", "BA synth", "{:.3f}"),
    ("ba_real", "real", "{:.3f}"),
    ("ba_shifted", "shifted", "{:.3f}"),
    ("ba_random", "random", "{:.3f}"),
    ("ba_path", "path", "{:.3f}"),
    ("ba_rel", "(synth-random)/(real-random)", "{:.2f}"),
    ("win_synth_random", "synth > random", "{:.0%}"),
    ("win_real_random", "real > random", "{:.0%}"),
    ("ba_accent_rel", "accents: rel.", "{:.2f}"),
    ("corr_synth", "corr. with real (path)", "{:.2f}"),
    ("amplitude_synth", "amplitude / real", "{:.2f}"),
    ("range_ok_synth", "p5..p95 inside real", "{:.0%}"),
    ("drift_synth", "drift deg (real)", "{:.1f}"),
    ("join_acc_max", "max join acc. deg/s2", "{:.0f}"),
    ("joins_over_p99_synth", "joins > real p99 (real)", "{:.0%}"),
]


def write_synthetic_takes(folder: Path, phrases: int, seed: int) -> Path:
    """Synthetic takes (tests/head_synthetic.py) whose head pitch is a known function of the voice (1.5 degrees
    per semitone above the speaker's base) as ``synth_<label>.csv`` (degrees) and ``.wav`` files: the synthesis
    of a held-out take must correlate with its real motion, random paths must not."""
    from head_synthetic import pitch_driven, synth_database

    from stages.head.pitch import wav_bytes

    folder.mkdir(parents=True, exist_ok=True)
    for p in pitch_driven(synth_database(phrases, seed=seed)):
        t, angles, translation = p.motion_at(30.0)
        deg = np.degrees(angles)
        rows = np.column_stack([t, deg[:, 1], deg[:, 0], deg[:, 2], translation])  # rx = pitch, ry = yaw, rz = roll
        header = "time,rx,ry,rz,tx,ty,tz"
        np.savetxt(folder / f"synth_{p.label}.csv", rows, delimiter=",", header=header, comments="", fmt="%.8f")
        (folder / f"synth_{p.label}.wav").write_bytes(wav_bytes(p.audio, p.audio_rate))
    return folder


def runs(args) -> list[tuple[str, str, str, list[str]]]:
    """(row name, pipeline, evaluate stage, overrides) of every evaluation asked for."""
    out = []
    if "crema-d" in args.data:
        out.append(("CREMA-D 1001, leave one take out", "eval/head.yaml", "evaluate", []))
    if "talking-heads" in args.data:
        clips = [f"vars.clips={Path(args.shared).resolve() / 'data' / 'talking-heads'}"]
        out.append(("talking heads, leave one speaker out", "eval/head_talking_heads.yaml", "evaluate", clips))
        take = [*clips, "vars.holdout=take"]
        out.append(("talking heads, leave one take out", "eval/head_talking_heads.yaml", "evaluate", take))
    if "synthetic" in args.data:
        takes = write_synthetic_takes(Path(args.work) / "synthetic", args.phrases, args.seed)
        name = "synthetic (head pitch = f(voice pitch)), leave one take out"
        out.append((name, "eval/head_csv.yaml", "evaluate", [f"vars.takes={takes}"]))
    return out


def cell(metrics: dict, key: str, fmt: str) -> str:
    value = fmt.format(metrics.get(key, float("nan")))
    if key == "ba_rel":
        value += f" [{metrics.get('ba_rel_lo', float('nan')):.2f}, {metrics.get('ba_rel_hi', float('nan')):.2f}]"
    if key == "corr_synth":
        value += f" ({metrics.get('corr_path', float('nan')):.2f})"
    if key == "drift_synth":
        value += f" ({metrics.get('drift_real', float('nan')):.1f})"
    if key == "joins_over_p99_synth":
        value += f" ({metrics.get('joins_over_p99_real', float('nan')):.0%})"
    if key == "join_acc_max":
        value += f" (p99 {metrics.get('real_acc_p99', float('nan')):.0f})"
    return value


def main(argv=None):
    import msflow

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", nargs="+", default=["crema-d", "talking-heads", "synthetic"])
    parser.add_argument("--shared", default=str(ROOT.parent / "shared"), help="the shared folder beside the project")
    parser.add_argument("--work", default=None, help="folder for the synthetic takes (default: a temporary one)")
    parser.add_argument("--phrases", type=int, default=67)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("-S", "--set", action="append", default=[], help="stage.param=value for every pipeline")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        args.work = args.work or tmp
        rows = []
        for name, pipeline, stage, overrides in runs(args):
            try:
                result = msflow.run(ROOT / pipeline, overrides=overrides + args.set)
            except msflow.UserError as exc:
                sys.exit(f"error: {exc} (for the shared clips elsewhere: --shared PATH)")
            rows.append((name, result.artifact(stage).metrics))
            print(f"{name}: run {result.run_id}", file=sys.stderr)
    print("| data | " + " | ".join(title for _, title, _ in COLUMNS) + " |")
    print("|---" * (len(COLUMNS) + 1) + "|")
    for name, metrics in rows:
        print(f"| {name} | " + " | ".join(cell(metrics, key, fmt) for key, _, fmt in COLUMNS) + " |")


if __name__ == "__main__":
    main()
