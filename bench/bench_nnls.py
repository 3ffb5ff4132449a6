"""Speed and accuracy of the batched NNLS solvers (stages.geometry.nnls) against a per-frame scipy.optimize.nnls loop.

Problems shaped like the keyshape decomposition (Eq 8): d = 136 (68 landmarks x 2), k keyshapes that all look
alike (raw landmark shapes near the mean face, so the dictionary is ill-conditioned), frames = rows that move
smoothly in time.

    OPENBLAS_NUM_THREADS=1 python bench/bench_nnls.py [--frames 60 600 6000] [--k 10 20 40]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.optimize import nnls as scipy_nnls

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stages.geometry.nnls import batched_nnls, kkt_violation


def keyshape_like_problem(frames: int, k: int, seed: int = 0):
    """Keyshapes = mean face + a few strong and many weak modes (full rank, like tracked landmarks with noise);
    frames = temporally smooth non-negative mixtures (a talking face moves continuously) plus noise."""
    rng = np.random.default_rng(seed)
    mean_face = rng.normal(size=136)
    modes = rng.normal(size=(136, 60)) * np.geomspace(1, 0.01, 60)
    keyshapes = mean_face[:, None] + 0.15 * modes @ rng.normal(size=(60, k))
    walk = np.cumsum(rng.normal(size=(frames, k)) * 0.3, axis=0)
    mixtures = np.maximum(np.sin(walk) - 0.3, 0) + 1e-3
    mixtures /= mixtures.sum(axis=1, keepdims=True)
    X = mixtures @ keyshapes.T + 0.003 * rng.normal(size=(frames, 136))
    return keyshapes, X


def best_of(fn, repeats: int) -> tuple[float, object]:
    best, out = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, nargs="+", default=[60, 600, 6000])
    parser.add_argument("--k", type=int, nargs="+", default=[10, 20, 40])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    print(
        f"{'frames':>7} {'k':>4} {'cond(A)':>9} | {'scipy loop':>10} {'active set':>10} {'fista':>10} | "
        f"{'act. KKT':>9} {'fista KKT':>9} {'scipy KKT':>9} | {'max |res-res_scipy|/|x|':>22}"
    )
    for frames in args.frames:
        for k in args.k:
            A, X = keyshape_like_problem(frames, k)
            t_scipy, ref = best_of(lambda: np.array([scipy_nnls(A, x)[0] for x in X]), args.repeats)
            t_active, act = best_of(lambda: batched_nnls(A, X, method="active_set"), args.repeats)
            t_fista, fis = best_of(lambda: batched_nnls(A, X, method="fista"), 1)
            ref_res = np.linalg.norm(ref @ A.T - X, axis=1)
            gap = max(np.abs(act.residual_norm - ref_res).max(), np.abs(fis.residual_norm - ref_res).max())
            print(
                f"{frames:7d} {k:4d} {np.linalg.cond(A):9.2e} | {1e3 * t_scipy:8.1f}ms {1e3 * t_active:8.1f}ms "
                f"{1e3 * t_fista:8.1f}ms | {act.kkt.max():9.1e} {fis.kkt.max():9.1e} "
                f"{kkt_violation(A, X, ref).max():9.1e} | {gap / np.linalg.norm(X, axis=1).min():22.1e}"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
