"""Out-of-sample evaluation of the face analysis (issue 4: aam, bilinear, edit) on CREMA-D actor 1001.

    python bench/eval_face.py [--align audio|mouth] [--folds 5] [--content-dim J] [--init mean|nearest] [--json out.json]

Protocol (temporal k-fold): the training takes (neutral, happy, angry; same sentence) are tracked and time-aligned
to the neutral take's frames (the content axis) once. Each fold holds out one contiguous window of the content axis
in all takes (each take's frames aligned to the window, a contiguous run), fits the appearance model and the
bilinear model on the remaining frames only, projects the held-out frames into that model (never refitting) and
scores them:

1. style classification: held-out frames of each take analysed (Eq 5-6), nearest training style by cosine;
   accuracy per take. The unseen disgust, fear and sad takes are analysed with the model fitted on all frames.
2. edit fidelity: the held-out neutral frames are re-synthesised as happy and angry (Eq 7) and compared with the
   real happy and angry frames aligned to them: mean landmark error over the 68 points in inter-ocular distances
   (both shapes in the model's Procrustes frame), edited->real versus neutral->real; the same for the shape-free
   texture (mean absolute grey level, 0-255; the edited texture carries the neutral frame's brightness and contrast).
3. temporal prior: jitter (mean squared second difference of e(t)) and reconstruction error of the held-out frames
   for several ``smooth`` values against smooth = 0 (the paper).

Prints tables with the mean over folds and the worst fold; --json writes every number.
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

from msflow.testing import run_stage  # noqa: E402
from stages.aam import fit_aam, generalised_procrustes, interocular_distance  # noqa: E402
from stages.alignment import align_takes  # noqa: E402
from stages.bilinear import content_features, fit_bilinear_model, reference_index  # noqa: E402
from stages.edit import analyse_style_content, classify_styles, initial_content, jitter  # noqa: E402

CLIPS = {"neutral": "NEU", "happy": "HAP", "angry": "ANG", "disgust": "DIS", "fear": "FEA", "sad": "SAD"}
TRAIN = ["neutral", "happy", "angry"]
UNSEEN = ["disgust", "fear", "sad"]


def track(labels: list[str]):
    from stages.tracking import FaceMesh

    videos = {label: ROOT / "data" / "crema-d" / f"1001_DFA_{CLIPS[label]}_XX.flv" for label in labels}
    return run_stage(FaceMesh, {}, {"videos": videos}).view()


class Fold:
    """One temporal fold: which frames train, which are held out, and the models fitted without them."""

    def __init__(self, window, aligned_local, takes, n_frames):
        self.window = window
        self.heldout_local = [np.arange(aligned_local[s, window].min(), aligned_local[s, window].max() + 1)
                              for s in range(len(takes))]
        self.heldout = np.concatenate([takes[s][h] for s, h in enumerate(self.heldout_local)])
        self.train_mask = np.ones(n_frames, dtype=bool)
        self.train_mask[self.heldout] = False
        outside = np.setdiff1d(np.arange(aligned_local.shape[1]), window)
        keep = np.ones(len(outside), dtype=bool)
        for s, held in enumerate(self.heldout_local):
            keep &= ~np.isin(aligned_local[s, outside], held)
        self.train_positions = outside[keep]


def fit_models(tracks, frames, aligned_global, positions, args):
    model, _ = fit_aam(tracks["landmarks"][frames], tracks["crops"][frames], tracks["crop_landmarks"][frames],
                       texture_width=args.texture_width)
    proj = model.project(tracks["landmarks"], tracks["crops"], tracks["crop_landmarks"])
    y = proj.y[aligned_global[:, positions]]                        # (S, C_train, K)
    bilinear, fit = fit_bilinear_model(y, TRAIN, content_dim=args.content_dim,
                                       content_variance=args.content_variance, mean_weight=args.mean_weight)
    return model, proj, bilinear, fit


def analyse(bilinear, y, args, smooth=0.0):
    """Eq 5-6 on configuration vectors y (F, K); residual relative to |y|^2 of the y components."""
    augmented = bilinear.augment(y)
    result = analyse_style_content(bilinear.w_full, bilinear.style, initial_content(augmented, bilinear, args.init),
                                   augmented, smooth=smooth)
    result.residual = np.sum((y - bilinear.synthesise(result.style, result.content)) ** 2, -1)
    return result


def raw_textures(proj):
    return proj.textures * proj.texture_scale[:, None] + proj.texture_offset[:, None]


def evaluate(args):
    t0 = time.perf_counter()
    train = track(TRAIN)
    unseen = track(UNSEEN)
    t_track = time.perf_counter() - t0
    labels = list(train.meta["labels"])
    sequence = np.asarray(train["sequence"])
    takes = [np.flatnonzero(sequence == s) for s in range(len(labels))]
    ref = reference_index(None, labels)
    aligned_all, _, _ = generalised_procrustes(train["landmarks"])
    features = content_features(args.align, labels, sequence, aligned_shapes=aligned_all, tracks=train)
    alignment = align_takes(features, ref, args.dtw_band)
    aligned_global = np.stack([takes[s][alignment.aligned_local[s]] for s in range(len(labels))])
    n_content = alignment.aligned_local.shape[1]
    windows = np.array_split(np.arange(n_content), args.folds)
    smooths = [float(v) for v in args.smooth.split(",")]
    targets = [t for t in labels if t != labels[ref]]

    folds = []
    for f, window in enumerate(windows):
        fold = Fold(window, alignment.aligned_local, takes, len(sequence))
        model, proj, bilinear, fit = fit_models(train, fold.train_mask, aligned_global, fold.train_positions, args)
        iod = float(interocular_distance(model.mean_shape))
        row = {"fold": f, "window": [int(window[0]), int(window[-1])], "train_content": len(fold.train_positions),
               "heldout_frames": {labels[s]: len(h) for s, h in enumerate(fold.heldout_local)},
               "n_shape": model.n_shape, "n_texture": model.n_texture, "content_dim": int(fit.content.shape[1]),
               "train_error": fit.error}
        # 1. style classification of each take's held-out frames
        row["accuracy"] = {}
        for s, label in enumerate(labels):
            frames = takes[s][fold.heldout_local[s]]
            result = analyse(bilinear, proj.y[frames], args)
            row["accuracy"][label] = float(np.mean(classify_styles(result.style, bilinear.style)[0] == s))
        # 2. edit fidelity: held-out neutral frames re-synthesised as each other expression
        neutral_frames = aligned_global[ref, window]
        neutral = analyse(bilinear, proj.y[neutral_frames], args)
        row["landmarks"], row["texture"] = {}, {}
        raw = raw_textures(proj)
        for target in targets:
            s = labels.index(target)
            real = aligned_global[s, window]
            y_edit = bilinear.synthesise(np.broadcast_to(bilinear.style[s], neutral.style.shape), neutral.content)
            shapes, textures = model.reconstruct(y_edit)
            edited_raw = textures * proj.texture_scale[neutral_frames, None] + proj.texture_offset[neutral_frames, None]
            real_shapes = proj.aligned_shapes[real]
            recon_real, _ = model.reconstruct(proj.y[real])
            row["landmarks"][target] = {
                "edited": point_error(shapes, real_shapes, iod),
                "neutral": point_error(proj.aligned_shapes[neutral_frames], real_shapes, iod),
                "model_floor": point_error(recon_real, real_shapes, iod)}
            row["texture"][target] = {
                "edited": float(np.mean(np.abs(edited_raw - raw[real]))),
                "neutral": float(np.mean(np.abs(raw[neutral_frames] - raw[real])))}
        # 3. temporal prior on the held-out windows of every take
        row["smooth"] = {}
        for lam in smooths:
            jit, err, acc = [], [], []  # per take
            for s in range(len(labels)):
                frames = takes[s][fold.heldout_local[s]]
                y = proj.y[frames]
                result = analyse(bilinear, y, args, smooth=lam)
                jit.append(jitter(result.style))
                err.append(float(np.sum(result.residual) / np.sum(y ** 2)))
                acc.append(float(np.mean(classify_styles(result.style, bilinear.style)[0] == s)))
            row["smooth"][str(lam)] = {"jitter": float(np.mean(jit)), "recon_error": float(np.mean(err)),
                                       "accuracy": float(np.mean(acc)),
                                       "accuracy_per_take": dict(zip(labels, acc))}
        folds.append(row)

    # unseen expressions, analysed with the model fitted on every training frame
    every = np.ones(len(sequence), dtype=bool)
    model, _, bilinear, fit = fit_models(train, every, aligned_global, np.arange(n_content), args)
    proj_u = model.project(unseen["landmarks"], unseen["crops"], unseen["crop_landmarks"])
    seq_u = np.asarray(unseen["sequence"])
    unseen_result = {}
    for s, label in enumerate(unseen.meta["labels"]):
        result = analyse(bilinear, proj_u.y[seq_u == s], args)
        classes = classify_styles(result.style, bilinear.style)[0]
        unseen_result[label] = {labels[c]: float(np.mean(classes == c)) for c in range(len(labels))}
    return {"align": args.align, "init": args.init, "mean_weight": args.mean_weight, "folds": folds, "unseen": unseen_result, "labels": labels,
            "content_dim_full": int(fit.content.shape[1]), "tracking_seconds": t_track,
            "dtw_cost": alignment.costs.tolist()}


def point_error(a, b, iod):
    """Mean Euclidean distance between corresponding landmarks, in inter-ocular distances."""
    return float(np.mean(np.linalg.norm(np.asarray(a) - np.asarray(b), axis=-1)) / iod)


def report(res):
    folds = res["folds"]
    labels = res["labels"]

    def stat(values):
        values = np.asarray(values, dtype=float)
        return values.mean(), values

    print(f"align={res['align']} init={res['init']} mean_weight={res['mean_weight']} folds={len(folds)} "
          f"content_dim per fold={[f['content_dim'] for f in folds]} "
          f"n_shape={[f['n_shape'] for f in folds]} n_texture={[f['n_texture'] for f in folds]}")
    print("\n1. style classification of held-out frames (nearest training style by cosine)")
    for label in labels:
        mean, vals = stat([f["accuracy"][label] for f in folds])
        print(f"   {label:8s} accuracy mean {mean:6.1%}  worst fold {vals.min():6.1%}   per fold "
              + " ".join(f"{v:.0%}" for v in vals))
    print("   unseen takes (model fitted on all training frames), fraction of frames classified as:")
    for label, fractions in res["unseen"].items():
        print(f"   {label:8s} " + "  ".join(f"{k} {v:5.1%}" for k, v in fractions.items()))
    print("\n2. edit fidelity on held-out windows (landmarks: mean point error / inter-ocular distance; "
          "texture: mean |grey level| error)")
    for target in folds[0]["landmarks"]:
        e_mean, e = stat([f["landmarks"][target]["edited"] for f in folds])
        n_mean, n = stat([f["landmarks"][target]["neutral"] for f in folds])
        m_mean, _ = stat([f["landmarks"][target]["model_floor"] for f in folds])
        wins = int(np.sum(e < n))
        print(f"   {target:8s} landmarks edited->real {e_mean:.4f} (worst {e.max():.4f})  neutral->real "
              f"{n_mean:.4f} (worst {n.max():.4f})  [edited lower in {wins}/{len(folds)} folds; "
              f"model floor {m_mean:.4f}]")
        e_mean, e = stat([f["texture"][target]["edited"] for f in folds])
        n_mean, n = stat([f["texture"][target]["neutral"] for f in folds])
        wins = int(np.sum(e < n))
        print(f"   {target:8s} texture   edited->real {e_mean:7.2f} (worst {e.max():7.2f})  neutral->real "
              f"{n_mean:7.2f} (worst {n.max():7.2f})  [edited lower in {wins}/{len(folds)} folds]")
    print("\n3. temporal prior (held-out windows of all takes): smooth, jitter of e(t), relative "
          "reconstruction error, classification accuracy")
    for lam in folds[0]["smooth"]:
        j_mean, j = stat([f["smooth"][lam]["jitter"] for f in folds])
        r_mean, r = stat([f["smooth"][lam]["recon_error"] for f in folds])
        a_mean, a = stat([f["smooth"][lam]["accuracy"] for f in folds])
        per_take = "  ".join(f"{label} {np.mean([f['smooth'][lam]['accuracy_per_take'][label] for f in folds]):.0%}"
                             for label in labels)
        print(f"   smooth {float(lam):6g}: jitter {j_mean:.3e} (worst {j.max():.3e})  recon error {r_mean:.4f} "
              f"(worst {r.max():.4f})  accuracy {a_mean:.1%} (worst fold {a.min():.1%}; {per_take})")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--align", default="audio", choices=["audio", "mouth"])
    parser.add_argument("--folds", type=int, default=5)
    parser.add_argument("--content-dim", type=int, default=None, help="J (default: by --content-variance)")
    parser.add_argument("--content-variance", type=float, default=0.98)
    parser.add_argument("--mean-weight", type=float, default=1.0, help="0: centred bilinear fit")
    parser.add_argument("--texture-width", type=int, default=64)
    parser.add_argument("--dtw-band", type=float, default=0.3)
    parser.add_argument("--init", default="mean", choices=["mean", "nearest"])
    parser.add_argument("--smooth", default="0,0.1,1,10", help="comma-separated smooth values")
    parser.add_argument("--json", default=None, help="write all numbers to this file")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    res = evaluate(args)
    report(res)
    print(f"\n(tracking {res['tracking_seconds']:.1f} s, total {time.perf_counter() - t0:.1f} s)")
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
