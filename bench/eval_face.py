"""Out-of-sample evaluation of the face analysis (issue 4: aam, bilinear, edit) on CREMA-D actor 1001.

    OPENBLAS_NUM_THREADS=1 python bench/eval_face.py [--align audio|mouth] [--folds 5] [--content-dim J]
        [--init mean|nearest] [--shape-balance B] [--analysis-shape-weight A] [--smooth 0,0.1,1,10] [--json out.json]

Defaults are the stages' defaults; ``--analysis-shape-weight 1`` (with smooth 0) is exactly the paper's analysis.

Protocol (temporal k-fold): the training takes (neutral, happy, angry; same sentence) are tracked and time-aligned
to the neutral take's frames (the content axis) once. Each fold holds out one contiguous window of the content axis
in all takes (each take's frames aligned to the window, a contiguous run; the runs partition every take, so each
frame is scored exactly once), fits the appearance model and the bilinear model on the remaining frames only,
projects the held-out frames into that model (never refitting) and scores them:

1. style classification: held-out frames of each take analysed (Eq 5-6, the edit stage's analysis), nearest
   training style by cosine (the issue's rule); per take the mean over folds, the worst fold and the fraction of all
   its frames, split into the silent lead-in before the sentence starts (audio onset) and the rest. Two references
   beside it: the training style that explains each frame best with its content re-solved (maximum likelihood), and
   the take of the nearest training frame (no model). The unseen disgust, fear and sad takes are analysed with the
   model fitted on all frames.
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
from scipy.spatial.distance import cdist

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from msflow.testing import run_stage  # noqa: E402
from stages.face.aam import AamPca, fit_aam, generalised_procrustes, interocular_distance  # noqa: E402
from stages.face.alignment import align_takes  # noqa: E402
from stages.face.bilinear import content_features, fit_bilinear_model, reference_index  # noqa: E402
from stages.face.edit import ExpressionEdit, analyse_takes, classify_by_fit, classify_styles, component_weights, jitter  # noqa: E402

CLIPS = {"neutral": "NEU", "happy": "HAP", "angry": "ANG", "disgust": "DIS", "fear": "FEA", "sad": "SAD"}
TRAIN = ["neutral", "happy", "angry"]
UNSEEN = ["disgust", "fear", "sad"]


def track(labels: list[str]):
    from stages.tracking import FaceMesh

    videos = {label: ROOT / "data" / "crema-d" / f"1001_DFA_{CLIPS[label]}_XX.flv" for label in labels}
    return run_stage(FaceMesh, {}, {"videos": videos}).view()


class Fold:
    """One temporal fold: the window of the content axis it holds out, each take's held-out frames, the frames and
    content positions left for training.

    Each take's frames are partitioned at the frames aligned to the window boundaries, so over the k folds every
    frame is held out exactly once (taking min..max of the aligned frames instead can score a frame twice or never,
    where the warping path repeats or skips frames at a boundary).
    """

    def __init__(self, window, windows, aligned_local, takes, n_frames):
        self.window = window
        self.heldout_local = []
        for s, frames in enumerate(takes):
            starts = [0] + [int(aligned_local[s, w[0]]) for w in windows[1:]] + [len(frames)]
            f = next(i for i, w in enumerate(windows) if w[0] == window[0])
            self.heldout_local.append(np.arange(starts[f], max(starts[f + 1], starts[f])))
        self.heldout = np.concatenate([takes[s][h] for s, h in enumerate(self.heldout_local)])
        self.train_mask = np.ones(n_frames, dtype=bool)
        self.train_mask[self.heldout] = False
        outside = np.setdiff1d(np.arange(aligned_local.shape[1]), window)
        keep = np.ones(len(outside), dtype=bool)
        for s, held in enumerate(self.heldout_local):
            keep &= ~np.isin(aligned_local[s, outside], held)
        self.train_positions = outside[keep]


def fit_models(tracks, frames, aligned_global, positions, args):
    model, _ = fit_aam(
        tracks["landmarks"][frames],
        tracks["crops"][frames],
        tracks["crop_landmarks"][frames],
        texture_width=args.texture_width,
        shape_balance=args.shape_balance,
    )
    proj = model.project(tracks["landmarks"], tracks["crops"], tracks["crop_landmarks"])
    y = proj.y[aligned_global[:, positions]]  # (S, C_train, K)
    bilinear, fit = fit_bilinear_model(
        y, TRAIN, content_dim=args.content_dim, content_variance=args.content_variance, mean_weight=args.mean_weight
    )
    return model, proj, bilinear, fit


def analysis_weights(model, bilinear, args):
    """The edit stage's weights of the components in Eq 5-6 (None: all 1, the paper's analysis)."""
    if args.analysis_shape_weight == 1:
        return None
    return component_weights(model.n_shape, bilinear.w_full.shape[2], args.analysis_shape_weight)


def analyse(model, bilinear, y, args, smooth=0.0):
    """Eq 5-6 on configuration vectors y (F, K) of one take (the stage's analyse_takes with the run's params);
    residual |y - e' W c|^2 of the unweighted y components."""
    augmented = bilinear.augment(y)
    result = analyse_takes(
        bilinear,
        augmented,
        np.zeros(len(y), dtype=int),
        init=args.init,
        smooth=smooth,
        weights=analysis_weights(model, bilinear, args),
    )
    result.residual = np.sum((y - bilinear.synthesise(result.style, result.content)) ** 2, -1)
    return result


def classify(model, bilinear, y, result, args):
    """Both rules for the analysed frames: 'cosine' (the issue's: nearest training style to e(t) by cosine) and
    'fit' (the training style that, with its content re-solved, explains y best: maximum likelihood)."""
    by_fit, _ = classify_by_fit(bilinear, bilinear.augment(y), analysis_weights(model, bilinear, args))
    return {"cosine": classify_styles(result.style, bilinear.style)[0], "fit": by_fit}


def speech_onsets(tracks, labels, below_peak_db: float = 25.0) -> list[int]:
    """Per take, the first video frame whose audio level (one frame period around its time) is within
    ``below_peak_db`` of the take's loudest frame: where the sentence starts (CREMA-D takes open with silence)."""
    audio = np.asarray(tracks["audio"], dtype=np.float64)
    bounds = np.asarray(tracks["audio_bounds"])
    rate = float(np.ravel([tracks.meta["audio_rate"]])[0])
    offsets = np.broadcast_to(np.asarray(tracks.meta.get("audio_offset", 0.0), dtype=np.float64), (len(labels),))
    times = np.asarray(tracks["time"], dtype=np.float64)
    sequence = np.asarray(tracks["sequence"])
    fps = float(np.ravel([tracks.meta.get("fps", 30.0)])[0])
    onsets = []
    for s in range(len(labels)):
        samples = audio[bounds[s, 0] : bounds[s, 1]]
        centre = np.round((times[sequence == s] - offsets[s]) * rate).astype(int)
        half = int(rate / fps / 2)
        level = np.array([np.sqrt(np.mean(samples[max(c - half, 0) : max(c + half, 1)] ** 2) + 1e-20) for c in centre])
        db = 20 * np.log10(level)
        onsets.append(int(np.argmax(db > db.max() - below_peak_db)))
    return onsets


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
    onsets = speech_onsets(train, labels)

    folds = []
    times_held = [np.zeros(len(frames)) for frames in takes]
    for f, window in enumerate(windows):
        fold = Fold(window, windows, alignment.aligned_local, takes, len(sequence))
        for s, local in enumerate(fold.heldout_local):
            times_held[s][local] += 1
        model, proj, bilinear, fit = fit_models(train, fold.train_mask, aligned_global, fold.train_positions, args)
        iod = float(interocular_distance(model.mean_shape))
        row = {
            "fold": f,
            "window": [int(window[0]), int(window[-1])],
            "train_content": len(fold.train_positions),
            "heldout_frames": {
                labels[s]: [int(h[0]), int(h[-1])] if len(h) else [] for s, h in enumerate(fold.heldout_local)
            },
            "n_shape": model.n_shape,
            "n_texture": model.n_texture,
            "content_dim": int(fit.content.shape[1]),
            "shape_weight": model.shape_weight,
            "train_error": fit.error,
        }
        # 1. style classification of each take's held-out frames
        row["accuracy"], row["correct"], row["classes"] = {}, {}, {}
        train_frames = np.flatnonzero(fold.train_mask)
        weights = analysis_weights(model, bilinear, args)
        weights = np.ones(proj.y.shape[1]) if weights is None else weights[: proj.y.shape[1]]
        for s, label in enumerate(labels):
            local = fold.heldout_local[s]
            frames = takes[s][local]
            result = analyse(model, bilinear, proj.y[frames], args)
            rules = classify(model, bilinear, proj.y[frames], result, args)
            # no-model reference: the take of the nearest training frame (same weighted y)
            dist = cdist(proj.y[frames] * weights, proj.y[train_frames] * weights)
            rules["nearest_frame"] = sequence[train_frames][np.argmin(dist, axis=1)]
            row["classes"][label] = {rule: classes.tolist() for rule, classes in rules.items()}
            row["correct"][label] = {
                rule: {
                    "all": [int(np.sum(classes == s)), len(classes)],
                    "lead_in": [int(np.sum((classes == s) & (local < onsets[s]))), int(np.sum(local < onsets[s]))],
                    "speech_on": [int(np.sum((classes == s) & (local >= onsets[s]))), int(np.sum(local >= onsets[s]))],
                }
                for rule, classes in rules.items()
            }
            row["accuracy"][label] = float(np.mean(rules["cosine"] == s)) if len(frames) else 1.0
        # 2. edit fidelity: held-out neutral frames re-synthesised as each other expression
        neutral_frames = aligned_global[ref, window]
        neutral = analyse(model, bilinear, proj.y[neutral_frames], args)
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
                "model_floor": point_error(recon_real, real_shapes, iod),
            }
            row["texture"][target] = {
                "edited": float(np.mean(np.abs(edited_raw - raw[real]))),
                "neutral": float(np.mean(np.abs(raw[neutral_frames] - raw[real]))),
            }
        # 3. temporal prior on the held-out windows of every take
        row["smooth"] = {}
        for lam in smooths:
            jit, err, acc = [], [], []  # per take
            for s in range(len(labels)):
                frames = takes[s][fold.heldout_local[s]]
                y = proj.y[frames]
                result = analyse(model, bilinear, y, args, smooth=lam)
                jit.append(jitter(result.style))
                err.append(float(np.sum(result.residual) / np.sum(y**2)))
                acc.append(float(np.mean(classify_styles(result.style, bilinear.style)[0] == s)))
            row["smooth"][str(lam)] = {
                "jitter": float(np.mean(jit)),
                "recon_error": float(np.mean(err)),
                "accuracy": float(np.mean(acc)),
                "accuracy_per_take": dict(zip(labels, acc)),
            }
        folds.append(row)
    if not all(np.array_equal(times_held[s], np.ones(len(takes[s]))) for s in range(len(labels))):
        raise RuntimeError(f"folds do not hold out every frame exactly once: {times_held}")
    # unseen expressions, analysed with the model fitted on every training frame
    every = np.ones(len(sequence), dtype=bool)
    model, _, bilinear, fit = fit_models(train, every, aligned_global, np.arange(n_content), args)
    proj_u = model.project(unseen["landmarks"], unseen["crops"], unseen["crop_landmarks"])
    seq_u = np.asarray(unseen["sequence"])
    unseen_result = {}
    for s, label in enumerate(unseen.meta["labels"]):
        y = proj_u.y[seq_u == s]
        rules = classify(model, bilinear, y, analyse(model, bilinear, y, args), args)
        unseen_result[label] = {
            rule: {labels[c]: float(np.mean(classes == c)) for c in range(len(labels))}
            for rule, classes in rules.items()
        }
    settings = {
        name: getattr(args, name)
        for name in (
            "align",
            "init",
            "mean_weight",
            "shape_balance",
            "analysis_shape_weight",
            "content_dim",
            "content_variance",
            "texture_width",
            "dtw_band",
            "folds",
        )
    }
    return {
        **settings,
        "folds": folds,
        "unseen": unseen_result,
        "labels": labels,
        "speech_onset": onsets,
        "content_dim_full": int(fit.content.shape[1]),
        "tracking_seconds": t_track,
        "dtw_cost": alignment.costs.tolist(),
    }


def point_error(a, b, iod):
    """Mean Euclidean distance between corresponding landmarks, in inter-ocular distances."""
    return float(np.mean(np.linalg.norm(np.asarray(a) - np.asarray(b), axis=-1)) / iod)


def report(res):
    folds = res["folds"]
    labels = res["labels"]

    def stat(values):
        values = np.asarray(values, dtype=float)
        return values.mean(), values

    print(
        f"align={res['align']} init={res['init']} mean_weight={res['mean_weight']} "
        f"shape_balance={res['shape_balance']} analysis_shape_weight={res['analysis_shape_weight']} "
        f"folds={len(folds)} content_dim per fold={[f['content_dim'] for f in folds]} "
        f"n_shape={[f['n_shape'] for f in folds]} n_texture={[f['n_texture'] for f in folds]}"
    )
    print(
        f"\n1. style classification of held-out frames, per take: mean over folds, worst fold, all frames pooled "
        f"[lead-in = frames before the speech onset {res['speech_onset']}, speech = from the onset on]"
    )
    rules = (
        ("cosine", "nearest training style to e(t) by cosine (the issue's rule)"),
        ("fit", "training style explaining y best, content re-solved (maximum likelihood)"),
        ("nearest_frame", "no model: take of the nearest training frame in y (reference)"),
    )
    for rule, title in rules:
        print(f"   {title}")
        for label in labels:
            counts = np.array([f["correct"][label][rule]["all"] for f in folds], dtype=float)
            per_fold = counts[:, 0] / np.maximum(counts[:, 1], 1)
            parts = {
                part: np.sum([f["correct"][label][rule][part] for f in folds], axis=0)
                for part in ("lead_in", "speech_on")
            }
            right, total = int(counts[:, 0].sum()), int(counts[:, 1].sum())
            print(
                f"   {label:8s} mean {per_fold.mean():6.1%}  worst fold {per_fold.min():6.1%}  frames "
                f"{right / total:6.1%} ({right}/{total})"
                f"   lead-in {parts['lead_in'][0]}/{parts['lead_in'][1]}  speech {parts['speech_on'][0]}/"
                f"{parts['speech_on'][1]}   per fold " + " ".join(f"{v:.0%}" for v in per_fold)
            )
    print("   unseen takes (model fitted on all training frames), fraction of frames classified as:")
    for label, by_rule in res["unseen"].items():
        print(
            f"   {label:8s} "
            + "   ".join(
                f"{rule}: " + " ".join(f"{k} {v:5.1%}" for k, v in fr.items())
                for rule, fr in by_rule.items()
                if rule != "nearest_frame"
            )
        )
    print(
        "\n2. edit fidelity on held-out windows (landmarks: mean point error / inter-ocular distance; "
        "texture: mean |grey level| error)"
    )
    for target in folds[0]["landmarks"]:
        e_mean, e = stat([f["landmarks"][target]["edited"] for f in folds])
        n_mean, n = stat([f["landmarks"][target]["neutral"] for f in folds])
        m_mean, _ = stat([f["landmarks"][target]["model_floor"] for f in folds])
        wins = int(np.sum(e < n))
        print(
            f"   {target:8s} landmarks edited->real {e_mean:.4f} (worst {e.max():.4f})  neutral->real "
            f"{n_mean:.4f} (worst {n.max():.4f})  [edited lower in {wins}/{len(folds)} folds; "
            f"model floor {m_mean:.4f}]"
        )
        e_mean, e = stat([f["texture"][target]["edited"] for f in folds])
        n_mean, n = stat([f["texture"][target]["neutral"] for f in folds])
        wins = int(np.sum(e < n))
        print(
            f"   {target:8s} texture   edited->real {e_mean:7.2f} (worst {e.max():7.2f})  neutral->real "
            f"{n_mean:7.2f} (worst {n.max():7.2f})  [edited lower in {wins}/{len(folds)} folds]"
        )
    print(
        "\n3. temporal prior (held-out windows of all takes): smooth, jitter of e(t), relative "
        "reconstruction error, classification accuracy"
    )
    for lam in folds[0]["smooth"]:
        j_mean, j = stat([f["smooth"][lam]["jitter"] for f in folds])
        r_mean, r = stat([f["smooth"][lam]["recon_error"] for f in folds])
        a_mean, a = stat([f["smooth"][lam]["accuracy"] for f in folds])
        per_take = "  ".join(
            f"{label} {np.mean([f['smooth'][lam]['accuracy_per_take'][label] for f in folds]):.0%}" for label in labels
        )
        print(
            f"   smooth {float(lam):6g}: jitter {j_mean:.3e} (worst {j.max():.3e})  recon error {r_mean:.4f} "
            f"(worst {r.max():.4f})  accuracy {a_mean:.1%} (worst fold {a.min():.1%}; {per_take})"
        )


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
    parser.add_argument(
        "--shape-balance",
        type=float,
        default=AamPca.Params().shape_balance,
        help="aam shape_balance: r in Eq 3 as a multiple of Cootes' balance",
    )
    parser.add_argument(
        "--analysis-shape-weight",
        type=float,
        default=ExpressionEdit.Params().analysis_shape_weight,
        help="edit analysis_shape_weight: weight of the shape rows when solving the style "
        "(1 with --smooth 0: the paper's analysis)",
    )
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
