"""Speed of the face analysis: texture warp, Eq 5-6 analysis, fitting the default training takes, and the edit stage
on long takes (CPU time and memory, streaming).

    OPENBLAS_NUM_THREADS=1 python bench/bench_face.py [--repeats 5] [--long 60,600]

Targets: texture warp >= 500 frames/s; analysis >= 10,000 frames/s; aam + alignment + bilinear fit of the three
training takes < 2 s (tracking excluded: it is the tracking stage's cost). Prints the median of the repeats.

Long takes (``--long`` seconds): the sad take's tracking repeated to that length (read block by block, as a lazy
input is), edited by the default edit stage with its crops streaming through output sinks (chunks compressed and
dropped, as a store run writes them); CPU time (process time) and the peak memory the stage allocates (tracemalloc,
numpy's arrays included), beside the size of the take's crops.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from msflow.testing import run_stage  # noqa: E402
from stages.face.aam import AamModel, AamPca  # noqa: E402
from stages.face.analysis import analyse_style_content, analyse_takes, component_weights, initial_content  # noqa: E402
from stages.face.bilinear import BilinearFit, BilinearModel  # noqa: E402
from stages.face.edit import ExpressionEdit, edited_crops  # noqa: E402

CLIPS = {"neutral": "NEU", "happy": "HAP", "disgust": "DIS", "sad": "SAD"}


def track(labels):
    from stages.tracking import FaceMesh

    videos = {label: ROOT / "data" / "crema-d" / f"1001_DFA_{CLIPS[label]}_XX.flv" for label in labels}
    return run_stage(FaceMesh, {}, {"videos": videos}).view()


def timed(fn, repeats):
    times = []
    result = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), result


def main(argv=None):
    args = _parse_args(argv)
    train = track(["neutral", "happy", "disgust"])
    sad = track(["sad"])
    aam, bilinear = _bench_fit(train, args.repeats)
    model = AamModel.from_view(aam.view())
    _bench_warp(model, train, args.repeats)
    bil = BilinearModel.from_view(bilinear.view())
    proj = model.project(sad["landmarks"], sad["crops"], sad["crop_landmarks"])
    _bench_analysis(model, bil, proj, args.analysis_frames, max(1, args.repeats // 2))
    _bench_edited_images(model, proj, sad, args.repeats)
    for seconds in [float(x) for x in args.long.split(",") if x]:
        bench_long_edit(aam.view(), bilinear.view(), sad, seconds)


def _parse_args(argv):
    """The command line: repeats, analysis frames and the long takes' lengths."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--analysis-frames", type=int, default=20000)
    parser.add_argument("--long", default="60", help="comma-separated take lengths in seconds for the edit (or '')")
    return parser.parse_args(argv)


def _bench_fit(train, repeats):
    """Time the aam + alignment + bilinear fit of the training takes (and the aam alone); returns both results."""
    n_train = len(train["landmarks"])

    def fit_all():
        aam = run_stage(AamPca, {}, {"tracks": train})
        bilinear = run_stage(BilinearFit, {}, {"aam": aam, "tracks": train})
        return aam, bilinear

    fit_time, (aam, bilinear) = timed(fit_all, repeats)
    aam_time, _ = timed(lambda: run_stage(AamPca, {}, {"tracks": train}), repeats)
    print(
        f"fit: aam + DTW alignment + bilinear on the 3 training takes ({n_train} frames): {fit_time:.3f} s "
        f"(aam alone {aam_time:.3f} s)  [target < 2 s]"
    )
    return aam, bilinear


def _bench_warp(model, train, repeats):
    """Time the texture warp on the training crops repeated four times."""
    crops = np.concatenate([train["crops"]] * 4)
    crop_landmarks = np.concatenate([train["crop_landmarks"]] * 4)
    warp_time, _ = timed(lambda: model.warp.warp(crops, crop_landmarks), repeats)
    print(
        f"texture warp: {len(crops) / warp_time:,.0f} frames/s ({len(crops)} crops "
        f"{crops.shape[2]}x{crops.shape[1]} -> {model.texture_size[0]}x{model.texture_size[1]}, "
        f"{model.warp.n_pixels} pixels)  [target >= 500]"
    )


def _analysis_frames(proj, n_frames):
    """The sad take's parameters repeated to ``n_frames`` with a little noise (seeded): the analysis input."""
    rng = np.random.default_rng(0)
    reps = int(np.ceil(n_frames / len(proj.y)))
    y = np.concatenate([proj.y] * reps)[:n_frames]
    return y + rng.normal(0, 0.05, y.shape) * proj.y.std(0)


def _bench_analysis(model, bil, proj, n_frames, repeats):
    """Time the Eq 5-6 analysis in the paper's setting, the stage default and two variants."""
    y = _analysis_frames(proj, n_frames)
    y_model = bil.augment(y)
    default_weight = ExpressionEdit.Params().analysis_shape_weight
    rows = component_weights(model.n_shape, y_model.shape[1], default_weight)
    frames = np.zeros(len(y_model), dtype=int)
    for label, init, smooth, weights in (
        ("paper (mean init, smooth 0, all rows)", "mean", 0.0, None),
        (f"stage default (analysis_shape_weight {default_weight:g})", "mean", 0.0, rows),
        ("nearest init, smooth 0, all rows", "nearest", 0.0, None),
        ("mean init, smooth 1, all rows", "mean", 1.0, None),
    ):

        def run():
            if weights is None:
                return analyse_style_content(
                    bil.w_full, bil.style, initial_content(y_model, bil, init), y_model, smooth=smooth
                )
            return analyse_takes(bil, y_model, frames, init=init, smooth=smooth, weights=weights)

        t, result = timed(run, repeats)
        target = "[target >= 10,000]" if smooth == 0 else "[beyond the paper; no target]"
        print(
            f"analysis {label}: {len(y) / t:,.0f} frames/s ({len(y)} frames, I={bil.w.shape[0]} "
            f"J={bil.w.shape[1]} K={bil.w_full.shape[2]}, {result.iterations} iterations, converged "
            f"{result.converged})  {target}"
        )


def _bench_edited_images(model, proj, sad, repeats):
    """Time the edited images (inverse warp + paste) of the sad take's first 60 frames."""
    y_edit = proj.y[:60]
    images_time, _ = timed(
        lambda: edited_crops(
            model,
            y_edit,
            sad["crops"][:60],
            proj.crop_similarity[:60],
            proj.texture_offset[:60],
            proj.texture_scale[:60],
        ),
        repeats,
    )
    print(f"edited images (inverse warp + paste): {60 / images_time:,.0f} frames/s")


class Tiled:
    """A frames-first array repeated to ``frames`` rows, read by slices without building it (like a lazy input)."""

    def __init__(self, array, frames: int):
        self.array, self.shape = np.asarray(array), (frames, *np.shape(array)[1:])

    def __len__(self):
        return self.shape[0]

    def __getitem__(self, index):
        rows = np.arange(self.shape[0])[index]
        return self.array[rows % len(self.array)]


class DiscardChunks:
    """Where output sinks put their chunks: compressed and dropped (a store run writes them to disk instead)."""

    def put(self, rel: str, data: bytes) -> None:
        pass


def long_take(sad, seconds: float):
    """The sad take's tracking artifact repeated to ``seconds`` (time continues; crops read by slices)."""
    from msflow.testing import artifact

    fps = float(np.ravel([sad.meta["fps"]])[0])
    frames = int(round(seconds * fps))
    arrays = {name: Tiled(sad[name], frames)[:] for name in ("landmarks", "crop_landmarks")}
    # the stage reads crops through view.lazy only; the stored array is a one-frame stand-in for the input check
    arrays.update(sequence=np.zeros(frames, dtype=np.int32), time=np.arange(frames) / fps, crops=sad["crops"][:1])
    view = artifact(arrays, dict(sad.meta))
    crops = Tiled(sad["crops"], frames)
    stored = view.lazy  # the view's own reader: view[name] reads through view.lazy, so it must not call back
    view.lazy = lambda name: crops if name == "crops" else stored(name)
    return view, crops


def bench_long_edit(aam, bilinear, sad, seconds: float) -> None:
    import tracemalloc

    from msflow.testing import prepare_inputs

    tracks, crops = long_take(sad, seconds)
    inputs = prepare_inputs(ExpressionEdit, {"model": bilinear, "aam": aam, "tracks": tracks})
    stage = ExpressionEdit("edit", chunk_target=DiscardChunks())
    tracemalloc.start()
    t0 = time.process_time()
    result = stage.run(ExpressionEdit.Params(), inputs)
    for sink in stage.sinks.values():
        sink.finish()
    cpu = time.process_time() - t0
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    frames, crop_bytes = crops.shape[0], int(np.prod(crops.shape))
    print(
        f"edit of a {seconds:g} s take ({frames} frames, 3 targets, video on): {cpu:.1f} s CPU "
        f"({frames / cpu:,.0f} frames/s), peak allocated {peak / 1e6:,.0f} MB (the take's crops: "
        f"{crop_bytes / 1e6:,.0f} MB; its edited crops: {3 * crop_bytes / 1e6:,.0f} MB); video "
        f"{len(result.arrays['video']) / 1e6:.1f} MB"
    )


if __name__ == "__main__":
    main()
