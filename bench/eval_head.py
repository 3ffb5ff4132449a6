"""Leave-one-utterance-out evaluation of the head-motion synthesis (paper Sec. 5) against two baselines.

For every database recording, its own takes (and mirror images) are left out of the database (Trellis
exclude_source), its audio drives the synthesis, and the result is compared with its real motion:
  (1) Wasserstein-1 distance between angular-speed distributions (deg/s), synthesis vs real;
  (2) the largest angular acceleration within the crossfade window of each join (deg/s^2), against the real
      motion's 99th percentile and maximum;
  (3) correlation between voice pitch (semitones) and head-pitch velocity, synthesised and real.
Baselines: random database segments stitched the same way (same test segments, same blending), and smooth noise
with the database's power spectrum per angle.

    python bench/eval_head.py --data synthetic [--phrases 67] [--out /tmp/eval_head]
    python bench/eval_head.py --data crema-d [--out /tmp/eval_head_crema]

Writes summary.json and the figures (paper Fig. 6 pitch segments, Fig. 7 trellis, head angles synthesised vs
real) to --out. Stage figures are the stages' own ``figures`` functions.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from msflow.testing import artifact, run_stage  # noqa: E402
from stages.headdb import TrackedHeadDb  # noqa: E402
from stages.motion_blend import (MotionBlend, _reference_angles, angular_acceleration, database_motion,  # noqa: E402
                                 join_acceleration, pitch_velocity_correlation, synthesise, wasserstein_speed)
from stages.pitch import Pitch, semitones  # noqa: E402
from stages.trellis import Trellis  # noqa: E402


def synthetic_inputs(n_phrases: int, seed: int):
    from head_synthetic import synth_database, tracking_artifact

    phrases = synth_database(n_phrases, seed=seed)
    return tracking_artifact(phrases, fps=30.0)


def crema_inputs():
    from stages.tracking import FaceMesh

    files = {p.name.split("_")[2]: p for p in sorted((ROOT / "data" / "crema-d").glob("*.flv"))}
    return run_stage(FaceMesh, {}, {"videos": files}).view()


def noise_like(db_angles: np.ndarray, db_sequence: np.ndarray, n_frames: int, rng) -> np.ndarray:
    """Gaussian noise with the database's average power spectrum per angle (random phases), n_frames long."""
    from scipy.signal import welch

    nper = int(min(128, np.bincount(db_sequence).min()))
    spectra = []
    for s in np.unique(db_sequence):
        x = db_angles[db_sequence == s]
        f, p = welch(x - x.mean(0), nperseg=nper, axis=0)
        spectra.append(p)
    psd = np.mean(spectra, axis=0)                      # (freqs, 3), per frame^-1 units
    n_fft = max(n_frames, 2 * (len(f) - 1))
    freqs = np.fft.rfftfreq(n_fft)
    amplitude = np.stack([np.interp(freqs, f, np.sqrt(psd[:, c])) for c in range(3)], axis=1)
    phase = rng.uniform(0, 2 * np.pi, amplitude.shape)
    noise = np.fft.irfft(amplitude * np.exp(1j * phase), n=n_fft, axis=0)[:n_frames]
    target_sd = np.sqrt(np.trapezoid(psd, f, axis=0))
    return (noise - noise.mean(0)) / np.maximum(noise.std(0), 1e-12) * target_sd


def random_trellis(tr_view, db_view, rng):
    """The trellis artifact with each chosen segment replaced by a random database segment from the phrases
    the search was allowed to use (the held-out recording stays excluded)."""
    arrays = {k: np.asarray(tr_view[k]) for k in tr_view.names}
    seg_seq = arrays["db_segment_sequence"]
    excluded = tr_view.meta["excluded"]
    labels = list(db_view.meta["labels"])
    chosen = arrays["chosen"].copy()
    for u in range(len(tr_view.meta["labels"])):
        rows = np.flatnonzero(arrays["segment_utterance"] == u)
        banned = np.array([labels[s] in excluded[u] for s in seg_seq])
        pool = np.flatnonzero(~banned)
        chosen[rows] = rng.choice(pool, size=len(rows))
    arrays["chosen"] = chosen
    return artifact(arrays, tr_view.meta)


def evaluate(tracks, *, params_trellis: dict | None = None, params_blend: dict | None = None, seed: int = 0,
             out: Path | None = None) -> dict:
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    headdb = run_stage(TrackedHeadDb, {}, {"tracks": tracks}).view()
    db_pitch = run_stage(Pitch, {}, {"source": headdb}).view()
    test_pitch = run_stage(Pitch, {}, {"source": tracks}).view()
    t_ingest = time.perf_counter() - t0
    t0 = time.perf_counter()
    trellis = run_stage(Trellis, {"exclude_source": True, **(params_trellis or {})},
                        {"database": headdb, "database_pitch": db_pitch, "test_pitch": test_pitch}).view()
    blend = run_stage(MotionBlend, dict(params_blend or {}),
                      {"trellis": trellis, "database": headdb, "reference": tracks}).view()
    t_search = time.perf_counter() - t0
    fps = float(blend.meta["fps"])
    window = float((params_blend or {}).get("blend_window", 0.15))
    db = database_motion(headdb)
    random_synth = synthesise(random_trellis(trellis, headdb, rng), db, fps,
                              **{k: v for k, v in (params_blend or {}).items() if k in (
                                  "blend_window", "break_blend_window", "drift_correction")})
    labels = list(trellis.meta["labels"])
    medians = np.asarray(test_pitch["speaker_median"])
    rows = []
    for u, label in enumerate(labels):
        real = _reference_angles(tracks, label, len(labels), fps)
        synth = blend["angles"][blend["sequence"] == u]
        rand = random_synth[u][0][:, :3]
        noise = noise_like(headdb["angles"], headdb["sequence"], len(synth), rng)
        n = min(len(real), len(synth))
        real, synth, rand, noise = real[:n], synth[:n], rand[:n], noise[:n]
        joins = blend["joins"][blend["join_utterance"] == u]
        joins = joins[joins < (n - 2) / fps]
        mask = np.asarray(test_pitch["pitch_utterance"]) == u
        f0_st = semitones(np.asarray(test_pitch["f0"])[mask], medians[u])
        f0_t = np.asarray(test_pitch["pitch_time"])[mask]
        acc_real = angular_acceleration(real, fps)
        row = {"label": label, "joins": int(len(joins)),
               "w1_synth": wasserstein_speed(synth, real, fps), "w1_random": wasserstein_speed(rand, real, fps),
               "w1_noise": wasserstein_speed(noise, real, fps),
               "real_acc_p99": float(np.percentile(acc_real, 99)), "real_acc_max": float(acc_real.max())}
        for name, motion in (("synth", synth), ("random", rand), ("noise", noise), ("real", real)):
            ja = join_acceleration(motion, fps, joins, window)
            row[f"join_acc_max_{name}"] = float(ja.max()) if len(ja) else 0.0
            row[f"join_acc_over_p99_{name}"] = float((ja > row["real_acc_p99"]).mean()) if len(ja) else 0.0
            row[f"corr_{name}"] = pitch_velocity_correlation(motion, fps, f0_t, f0_st)
        rows.append(row)
    summary = summarise(rows)
    summary.update({"utterances": len(rows), "db_sequences": len(headdb.meta["labels"]),
                    "db_segments": int(len(trellis["db_segments"])), "seconds_ingest_and_pitch": t_ingest,
                    "seconds_trellis_and_blend": t_search, "trellis_metrics": trellis.metrics})
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "summary.json").write_text(json.dumps({"summary": summary, "per_utterance": rows}, indent=1))
        save_figures(out, test_pitch, trellis, blend, tracks, utterance=0)
    return summary


def summarise(rows: list[dict]) -> dict:
    def mean(key):
        values = np.array([r[key] for r in rows], dtype=float)
        values = values[np.isfinite(values)]
        return float(values.mean()) if len(values) else float("nan")

    def frac(cond):
        return float(np.mean([cond(r) for r in rows]))

    return {
        "w1_synth": mean("w1_synth"), "w1_random": mean("w1_random"), "w1_noise": mean("w1_noise"),
        "synth_beats_random_w1": frac(lambda r: r["w1_synth"] < r["w1_random"]),
        "synth_beats_noise_w1": frac(lambda r: r["w1_synth"] < r["w1_noise"]),
        "join_acc_max_synth": mean("join_acc_max_synth"), "join_acc_max_random": mean("join_acc_max_random"),
        "join_acc_max_noise": mean("join_acc_max_noise"), "join_acc_max_real": mean("join_acc_max_real"),
        "real_acc_p99": mean("real_acc_p99"), "real_acc_max": mean("real_acc_max"),
        "join_fraction_over_real_p99_synth": mean("join_acc_over_p99_synth"),
        "join_fraction_over_real_p99_random": mean("join_acc_over_p99_random"),
        "join_fraction_over_real_p99_real": mean("join_acc_over_p99_real"),
        "synth_join_max_within_real_max": frac(lambda r: r["join_acc_max_synth"] <= r["real_acc_max"]),
        "corr_real": mean("corr_real"), "corr_synth": mean("corr_synth"), "corr_random": mean("corr_random"),
        "corr_noise": mean("corr_noise"),
    }


def save_figures(out: Path, test_pitch, trellis, blend, tracks, utterance: int = 0):
    import matplotlib

    matplotlib.use("Agg")
    for name, func in Pitch.figures.items():
        func(test_pitch, {}).savefig(out / f"fig6_{name}.png", dpi=110)
    for name, func in Trellis.figures.items():
        func(trellis, {}).savefig(out / f"fig7_{name}.png", dpi=110)
    for name, func in MotionBlend.figures.items():
        func(blend, {"reference": tracks}).savefig(out / f"{name}.png", dpi=110)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", choices=["synthetic", "crema-d"], default="synthetic")
    parser.add_argument("--phrases", type=int, default=67)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--k", type=int, default=None)
    parser.add_argument("--w1", type=float, default=None)
    parser.add_argument("--blend-window", type=float, default=None)
    args = parser.parse_args(argv)
    tracks = synthetic_inputs(args.phrases, args.seed) if args.data == "synthetic" else crema_inputs()
    pt = {k: v for k, v in {"k": args.k, "w1": args.w1}.items() if v is not None}
    pb = {"blend_window": args.blend_window} if args.blend_window is not None else {}
    out = args.out or Path(f"/tmp/eval_head_{args.data}")
    summary = evaluate(tracks, params_trellis=pt, params_blend=pb, seed=args.seed, out=out)
    width = max(len(k) for k in summary)
    for key, value in summary.items():
        print(f"{key:<{width}}  {value if not isinstance(value, float) else round(value, 4)}")
    print(f"written: {out}/summary.json and figures")


if __name__ == "__main__":
    main()
