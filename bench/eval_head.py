"""The head-motion goals table (issue 12) from the evaluation pipelines, one command:

    python bench/eval_head.py                       # CREMA-D, the shared talking-head clips, synthetic takes
    python bench/eval_head.py --data crema-d        # one of them
    python bench/eval_head.py --shared /path/to/shared -S motion_blend.timing=strokes
    python bench/eval_head.py --calibrate           # the jitter filter and the range fit, on real motion only

Each row is one run of an evaluation pipeline (stages.eval.head): CREMA-D ``eval/head.yaml`` (leave one take out;
one speaker), the talking-head clips ``eval/head_talking_heads.yaml`` (leave one speaker out; the same with the
amplitude read off the scored take, ``motion_blend.amplitude_target=auto``, the product's default for a performer
the database does not know, in-sample for the amplitude; leave one take out
with ``vars.holdout=take``; and every clip cut into 5-s pieces, leave one piece out, so that the speaker's other
pieces are in the database: ``vars.piece=5 vars.test=takes``),
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
    ("ba_synth_over_real", "synth / real (goal >= 80%)", "{:.0%}"),
    ("ba_rel", "(synth-random)/(real-random)", "{:.2f}"),
    ("win_synth_random", "synth > random (goal >= 75%)", "{:.0%}"),
    ("win_real_random", "real > random (real > shifted): calibration", "{:.0%}"),
    ("ba_accent_rel", "accents: rel.", "{:.2f}"),
    ("corr_synth", "corr. with real (path)", "{:.2f}"),
    ("amplitude_synth", "amplitude / real", "{:.2f}"),
    ("range_ok_synth", "p5..p95 inside the real p5..p95, as the goal reads (random real)", "{:.0%}"),
    ("range_fit_synth", "range fit: all speakers (real halves); speakers the database knows", "{:.0%}"),
    ("range_fit_angles", "range fit yaw / pitch / roll", "{}"),
    ("drift_synth", "drift deg (real)", "{:.1f}"),
    ("join_acc_max", "max join acc. deg/s2", "{:.0f}"),
    ("join_acc_over_p99", "worst take: max join / p99 (jitter-free p99)", "{:.2f}"),
    ("joins_over_p99_synth", "joins > real p99 (real)", "{:.0%}"),
]


def write_synthetic_takes(folder: Path, phrases: int, seed: int) -> Path:
    """Synthetic takes (tests/head_synthetic.py) whose head pitch is a known function of the voice (1.5 degrees
    per semitone above the speaker's base) as ``synth_<label>.csv`` (degrees) and ``.wav`` files: the synthesis
    of a held-out take must correlate with its real motion, random paths must not."""
    from head_synthetic import pitch_driven, synth_database

    from stages.head.praat_files import wav_bytes

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
        name = "talking heads, leave one speaker out, the performer's amplitude (read off the scored take)"
        out.append((name, "eval/head_talking_heads.yaml", "evaluate", [*clips, "motion_blend.amplitude_target=auto"]))
        take = [*clips, "vars.holdout=take"]
        out.append(("talking heads, leave one take out", "eval/head_talking_heads.yaml", "evaluate", take))
        pieces = [*take, "vars.piece=5", "vars.test=takes"]
        name = "talking heads cut into 5-s pieces, leave one piece out"
        out.append((name, "eval/head_talking_heads.yaml", "evaluate", pieces))
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
    if key == "win_real_random":
        value += f" ({metrics.get('win_real_shifted', float('nan')):.0%})"
    if key == "range_ok_synth":
        value += f" ({metrics.get('range_ok_random', float('nan')):.0%})"
    if key == "range_fit_synth":
        value += f" ({metrics.get('range_fit_halves', float('nan')):.0%})"
        known = int(metrics.get("speakers_known", 0))
        if known:
            value += f"; {known}: {metrics['range_fit_known_synth']:.0%} ({metrics['range_fit_known_halves']:.0%})"
        else:
            value += "; none"
    if key == "join_acc_over_p99":
        value += f" ({metrics.get('join_acc_over_p99_band', float('nan')):.2f})"
    if key == "join_acc_max":
        value += f" (p99 {metrics.get('real_acc_p99', float('nan')):.0f})"
    return value


def angle_metrics(evaluation) -> dict:
    """The synthesis's range fit per angle (yaw / pitch / roll), over the speakers (the stage keeps it as an array)."""
    fit = np.asarray(evaluation["range_fit"])[:, 0]  # (speakers, angles) of the synthesis
    return {"range_fit_angles": " / ".join(f"{v:.0%}" for v in fit.mean(axis=0))}


def lowpassed(angles: np.ndarray, fps: float, cutoff: float | None) -> np.ndarray:
    from stages.head.measures import lowpass_angles

    return angles if cutoff is None else lowpass_angles(angles, fps, cutoff)


def calibrate_jitter(clips: list, cutoffs: list, seed: int = 0) -> list[str]:
    """Rows of the jitter-filter calibration on real motion only: for each cutoff (Hz) of the database's low-pass
    applied to the real tracked motion, its beat alignment against the same motion shifted (the timing signal must
    survive), the share of its head beats within one frame of the unfiltered motion's, and the median and smallest
    99th percentile of angular acceleration over the clips."""
    from stages.eval.head import evaluation_windows, shifted_motion
    from stages.head.beats import beat_alignment, kinematic_beats, nearest_distance
    from stages.head.measures import angular_acceleration

    rng = np.random.default_rng(seed)
    rows = [
        "| cutoff (Hz) | BA real | shifted | real > shifted | z | head beats kept (+-1 frame) | acc. p99 median / min |"
    ]
    rows.append("|---|---|---|---|---|---|---|")
    for cutoff in cutoffs:
        ba, sh, kept, p99 = [], [], [], []
        for angles, fps, onsets in clips:
            motion = lowpassed(angles, fps, cutoff)
            raw_beats, beats = (kinematic_beats(m, fps, smoothing=0.1) for m in (angles, motion))
            kept.append(np.mean(nearest_distance(raw_beats, beats) <= 1.01 / fps) if len(beats) else 0.0)
            p99.append(np.percentile(angular_acceleration(motion, fps), 99))
            shifted = [shifted_motion(motion, fps, 1.0, rng) for _ in range(20)]
            for a, b in evaluation_windows(len(motion), fps, 10.0):
                beat = lambda m: beat_alignment(kinematic_beats(m[a:b], fps, smoothing=0.1), onsets - a / fps, 0.1)
                ba.append(beat(motion))
                sh.append(np.mean([beat(m) for m in shifted]))
        d = np.array(ba) - np.array(sh)
        z = d.mean() / (d.std(ddof=1) / np.sqrt(len(d)))
        rows.append(
            f"| {cutoff or 'none'} | {np.mean(ba):.3f} | {np.mean(sh):.3f} | {np.mean(d > 0):.0%} | {z:.1f} | "
            f"{np.mean(kept):.0%} | {np.median(p99):.0f} / {np.min(p99):.0f} |"
        )
    return rows


def calibrate_range(by_speaker: dict, span_tolerance: float, margin: float) -> list[str]:
    """Rows of the range-fit calibration: how often each kind of motion fits a speaker's real p5..p95 per angle
    (stages.eval.head.range_fit): the speaker's own real motion, one half (centred) against the other; the real
    motion scaled; other speakers' real motion as it is, and centred and scaled to the speaker's spread."""
    from stages.eval.head import range_fit
    from stages.head.measures import percentile_range

    def fit(motion, real):
        return range_fit(percentile_range(motion), percentile_range(real), span_tolerance, margin)

    results = {"own real motion, other half": [], "x 0.5": [], "x 0.7": [], "x 1.5": [], "still": []}
    results |= {"other speakers": [], "other speakers, centred and scaled to the speaker's spread": []}
    unknown = "own real motion, centred and scaled to the median other speaker's spread (a held-out speaker's guess)"
    results[unknown] = []
    spread = lambda m: np.ptp(percentile_range(m), axis=0)
    for speaker, motion in by_speaker.items():
        others = np.median([spread(m) for x, m in by_speaker.items() if x != speaker], axis=0)
        guess = np.exp(np.mean(np.log(others / np.maximum(spread(motion), 1e-12))))  # one gain for the angles
        results[unknown].append(fit((motion - motion.mean(axis=0)) * guess, motion))
        half = len(motion) // 2
        a, b = motion[:half] - motion[:half].mean(axis=0), motion[half:] - motion[half:].mean(axis=0)
        results["own real motion, other half"] += [fit(a, b), fit(b, a)]
        for gain in (0.5, 0.7, 1.5):
            results[f"x {gain}"].append(fit(gain * motion, motion))
        results["still"].append(fit(np.zeros_like(motion), motion))
        for other, theirs in by_speaker.items():
            if other == speaker:
                continue
            results["other speakers"].append(fit(theirs, motion))
            scaled = (theirs - theirs.mean(axis=0)) * spread(motion) / np.maximum(spread(theirs), 1e-12)
            results["other speakers, centred and scaled to the speaker's spread"].append(fit(scaled, motion))
    rows = ["| motion against a speaker's real p5..p95 | speaker-angles that fit |", "|---|---|"]
    rows += [f"| {name} | {np.mean(np.concatenate(v)):.0%} |" for name, v in results.items()]
    return rows


VOICE_FEATURES = ("pitch spread (st)", "loudness spread (dB)", "median f0 (log Hz)", "voiced fraction")


def voice_features(samples: np.ndarray, rate: int) -> np.ndarray:
    """One take's voice, summarised: pitch spread (standard deviation of the voiced semitones about the median),
    loudness spread (dB, voiced frames), log median f0, voiced fraction."""
    from stages.head.pitch import frame_energy, praat_pitch

    times, f0 = praat_pitch(samples, rate, floor=60.0)
    voiced = np.isfinite(f0)
    median = np.median(f0[voiced])
    loudness = frame_energy(samples, rate, times[voiced])
    return np.array([np.std(12 * np.log2(f0[voiced] / median)), np.std(loudness), np.log(median), voiced.mean()])


def calibrate_voice(spans: dict[str, np.ndarray], voices: dict[str, np.ndarray]) -> list[str]:
    """Does the voice predict how much a held-out speaker moves its head? Per voice feature: Pearson r across
    speakers with the log of the speaker's head span (geometric mean of the angles' p95 - p5), and leave one speaker
    out, a line fitted on the other speakers predicting the held-out one's span: how often the prediction is within
    the range fit's factor 1.5, against the median of the other speakers (the synthesis's guess)."""
    speakers = sorted(spans)
    log_span = np.array([np.mean(np.log(spans[s])) for s in speakers])
    features = np.array([voices[s] for s in speakers])
    rows = ["| predictor of a held-out speaker's head span | r with log span | within 1.5x |", "|---|---|---|"]
    held_out = np.arange(len(speakers))
    guess = np.array([np.median(np.delete(log_span, i)) for i in held_out])
    rows.append(f"| the median of the other speakers | | {np.mean(abs(guess - log_span) <= np.log(1.5)):.0%} |")
    for j, name in enumerate(VOICE_FEATURES):
        x = features[:, j]
        fitted = [np.polyfit(np.delete(x, i), np.delete(log_span, i), 1) for i in held_out]
        guess = np.array([np.polyval(line, x[i]) for i, line in zip(held_out, fitted)])
        within = np.mean(abs(guess - log_span) <= np.log(1.5))
        rows.append(
            f"| {name}, a line fitted on the other speakers | {np.corrcoef(x, log_span)[0, 1]:+.2f} | {within:.0%} |"
        )
    return rows


def calibrate(args) -> None:
    """Both calibrations on the shared clips' real motion (tracked by the leave-one-speaker-out pipeline)."""
    import msflow
    from stages.eval.head import take_audio
    from stages.head.beats import audio_onsets
    from stages.head.measures import percentile_range, reference_angles

    clips = f"vars.clips={Path(args.shared).resolve() / 'data' / 'talking-heads'}"
    run = msflow.run(ROOT / "eval/head_talking_heads.yaml", overrides=[clips, *args.set])
    track, trellis = run.artifact("track"), run.artifact("trellis")
    labels, rates = list(track.meta["labels"]), track.meta["fps"]
    takes, by_speaker, voices = [], {}, {}
    for k, (label, speaker) in enumerate(zip(labels, trellis.meta["speakers"])):
        angles = reference_angles(track, label, len(labels), rates[k])
        samples, rate, offset = take_audio(track, k)
        takes.append((angles, rates[k], audio_onsets(samples, rate, offset=offset, delta=0.15, min_gap=0.1)))
        by_speaker.setdefault(speaker, []).append(angles)
        voices.setdefault(speaker, []).append((voice_features(samples, rate), len(samples)))
    print("\n".join(calibrate_jitter(takes, [None, 8.0, 6.0, 5.0, 4.0, 3.0, 2.0])))
    print()
    print("\n".join(calibrate_range({s: np.concatenate(m) for s, m in by_speaker.items()}, 1.5, 0.25)))
    print()
    spans = {s: np.ptp(percentile_range(np.concatenate(m)), axis=0) for s, m in by_speaker.items()}
    voice = {s: np.average([f for f, _ in v], axis=0, weights=[n for _, n in v]) for s, v in voices.items()}
    print("\n".join(calibrate_voice(spans, voice)))


def main(argv=None):
    import msflow

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", nargs="+", default=["crema-d", "talking-heads", "synthetic"])
    parser.add_argument("--shared", default=str(ROOT.parent / "shared"), help="the shared folder beside the project")
    parser.add_argument("--work", default=None, help="folder for the synthetic takes (default: a temporary one)")
    parser.add_argument("--phrases", type=int, default=67)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("-S", "--set", action="append", default=[], help="stage.param=value for every pipeline")
    parser.add_argument("--rows", default="", help="only the rows whose name contains this text")
    parser.add_argument(
        "--calibrate", action="store_true", help="the jitter filter's and the range fit's calibration on real motion"
    )
    args = parser.parse_args(argv)
    if args.calibrate:
        return calibrate(args)
    with tempfile.TemporaryDirectory() as tmp:
        args.work = args.work or tmp
        rows = []
        for name, pipeline, stage, overrides in runs(args):
            if args.rows not in name:
                continue
            try:
                result = msflow.run(ROOT / pipeline, overrides=overrides + args.set)
            except msflow.UserError as exc:
                sys.exit(f"error: {exc} (for the shared clips elsewhere: --shared PATH)")
            evaluation = result.artifact(stage)
            rows.append((name, {**evaluation.metrics, **angle_metrics(evaluation)}))
            print(f"{name}: run {result.run_id}", file=sys.stderr)
    print("| data | " + " | ".join(title for _, title, _ in COLUMNS) + " |")
    print("|---" * (len(COLUMNS) + 1) + "|")
    for name, metrics in rows:
        print(f"| {name} | " + " | ".join(cell(metrics, key, fmt) for key, _, fmt in COLUMNS) + " |")


if __name__ == "__main__":
    main()
