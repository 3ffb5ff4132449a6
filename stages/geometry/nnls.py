"""Batched non-negative least squares for the keyshape decomposition (paper Eq 8) and box-bounded QPs.

Every frame of an edited sequence is decomposed into the same dictionary of keyshapes, so the problems share
their matrix: ``min_w ||A w - x_t||^2, w >= 0`` for all frames t at once. Both solvers work in Gram form
(Q = A'A, c_t = A'x_t), which is k x k whatever the landmark count, and advance all frames together:

- ``nnls_active_set``: Lawson-Hanson active set, vectorised over frames (each frame keeps its own passive set;
  the restricted normal equations of all frames are solved as one batched masked ``np.linalg.solve``). Exact in
  a finite number of steps; the default.
- ``solve_box_qp``: accelerated projected gradient (FISTA with adaptive restart) for
  ``min 1/2 w'Hw - f'w`` with ``lower <= w <= upper``, optional temporal smoothing across frames; stops when
  the KKT conditions hold to a relative tolerance. Used for the smoothed decomposition and for the [0, 1]-bounded
  keymorph fit.

``batched_nnls`` is the entry point: optional (off by default) soft sum-to-one constraint and temporal smoothing.
Its default solver is the plain per-frame ``scipy.optimize.nnls`` loop: measured at the pipeline's sizes (136
landmark coordinates, k = 10-40, 60 to 6,000 frames; ``bench/bench_nnls.py``) it is faster than the batched
active set (e.g. 20 vs 80 ms for 600 frames, 179 vs 329 ms for 6,000, k = 20), which stays available as
``method="active_set"``.
``kkt_violation`` measures how far a solution is from optimal (0 at the optimum).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

EPS = np.finfo(np.float64).eps


@dataclass
class NnlsResult:
    weights: np.ndarray  # (frames, k) >= 0
    residual_norm: np.ndarray  # (frames,) ||A w - x||
    iterations: np.ndarray  # (frames,) solver iterations spent on each frame
    kkt: np.ndarray  # (frames,) relative KKT violation (see kkt_violation)
    converged: np.ndarray  # (frames,) bool


def projected_gradient(gradient: np.ndarray, weights: np.ndarray, lower=0.0, upper=np.inf) -> np.ndarray:
    """The part of the gradient that the bounds do not block: zero everywhere exactly at a KKT point (a variable
    whose bounds meet, lower = upper, is fixed: nothing of its gradient counts)."""
    at_lower = weights <= lower
    at_upper = weights >= upper
    blocked = np.where(at_lower, np.minimum(gradient, 0.0), np.where(at_upper, np.maximum(gradient, 0.0), gradient))
    return np.where(at_lower & at_upper, 0.0, blocked)


def kkt_violation(A: np.ndarray, X: np.ndarray, W: np.ndarray) -> np.ndarray:
    """Per frame, the KKT violation of ``min ||A w - x||^2, w >= 0``, relative to ``max_j ||a_j|| * ||x||``.

    KKT: w >= 0, gradient g = A'(A w - x) >= 0, and g_j = 0 wherever w_j > 0; the projected gradient is zero
    exactly when the last two hold, and a negative weight counts as infinite violation. 0 means optimal.
    """
    A = np.asarray(A, np.float64)
    X = np.atleast_2d(np.asarray(X, np.float64))
    W = np.atleast_2d(np.asarray(W, np.float64))
    gradient = (W @ A.T - X) @ A
    column_norm = np.sqrt(max(float((A * A).sum(axis=0).max(initial=0.0)), EPS))
    scale = column_norm * np.maximum(np.linalg.norm(X, axis=1), EPS)
    violation = np.abs(projected_gradient(gradient, W)).max(axis=1, initial=0.0) / scale
    return np.where((W < 0).any(axis=1), np.inf, violation)


def solve_restricted(Q: np.ndarray, C: np.ndarray, passive: np.ndarray, ridge: float) -> np.ndarray:
    """Per row, the least-squares solution on the passive variables (others 0): Q_PP s_P = c_P.

    Frames share passive sets far more often than not (every frame starts from one variable, and neighbouring
    frames of a take use the same keyshapes), so each distinct set is factorised once and applied to all of its
    frames; the restricted systems are padded to k x k (identity outside P) to batch them.
    """
    k = Q.shape[0]
    diag = np.arange(k)
    packed = np.packbits(passive, axis=1)
    patterns, first, inverse = np.unique(packed, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    mask = passive[first].astype(np.float64)
    M = mask[:, :, None] * Q * mask[:, None, :]
    M[:, diag, diag] += (1.0 - mask) + ridge
    if len(patterns) * 4 < len(C):
        # many frames per pattern: one inverse per pattern (Cholesky-based would need a loop), then a batched
        # product; the ridge keeps the inverses well defined
        inverses = np.linalg.inv(M)
        S = np.einsum("fij,fj->fi", inverses[inverse], C * passive)
    else:
        S = np.linalg.solve(M[inverse], (C * passive)[:, :, None])[:, :, 0]
    S[~passive] = 0.0
    return S


#: the phases of a frame in the batched active-set loop
_OUTER, _INNER, _DONE = 1, 2, 0


@dataclass
class _ActiveSetFrames:
    """Per-frame state of the batched active-set loop; the steps below update it in place."""

    W: np.ndarray  # (n, k) current feasible weights
    passive: np.ndarray  # (n, k) bool, the passive (free) set P
    iterations: np.ndarray  # (n,) inner iterations spent
    state: np.ndarray  # (n,) _OUTER, _INNER or _DONE
    added: np.ndarray  # (n,) variable added by the last outer step
    first_inner: np.ndarray  # (n,) bool: the next inner step is the first after an outer one


def _start_frames(n: int, k: int, initial_passive: np.ndarray | None) -> _ActiveSetFrames:
    """Every frame at w = 0 with an empty passive set, or (``initial_passive``) at a tiny feasible point on its
    guessed support, ready for the inner loop."""
    frames = _ActiveSetFrames(
        W=np.zeros((n, k)),
        passive=np.zeros((n, k), dtype=bool),
        iterations=np.zeros(n, dtype=np.int64),
        state=np.full(n, _OUTER, dtype=np.int8),
        added=np.full(n, -1, dtype=np.int64),
        first_inner=np.zeros(n, dtype=bool),
    )
    if initial_passive is not None:
        frames.passive = np.asarray(initial_passive, dtype=bool).copy()
        warm = frames.passive.any(axis=1)
        # any strictly positive point on the guessed support is feasible; the inner loop walks from it towards
        # the restricted least-squares solution and drops the guesses that block
        frames.W[frames.passive] = 1e-12
        frames.state[warm] = _INNER
    return frames


def _free_best_variable(frames: _ActiveSetFrames, Q: np.ndarray, C: np.ndarray, tol: np.ndarray, max_iter: int) -> None:
    """The outer step, for the frames waiting for it: free the active variable with the largest negative
    gradient, or finish the frame when none exceeds its tolerance (the KKT conditions hold) or its iterations
    ran out."""
    outer = np.flatnonzero(frames.state == _OUTER)
    if not outer.size:
        return
    neg_grad = C[outer] - frames.W[outer] @ Q
    candidates = np.where(frames.passive[outer], -np.inf, neg_grad)
    j = np.argmax(candidates, axis=1)
    best = candidates[np.arange(outer.size), j]
    finished = ~(best > tol[outer]) | (frames.iterations[outer] >= max_iter)
    frames.state[outer[finished]] = _DONE
    go = outer[~finished]
    frames.passive[go, j[~finished]] = True
    frames.added[go] = j[~finished]
    frames.first_inner[go] = True
    frames.state[go] = _INNER


def _inner_step(frames: _ActiveSetFrames, inner: np.ndarray, Q: np.ndarray, C: np.ndarray, ridge: float) -> None:
    """One pass of the inner loop for the frames in it: solve on the passive set; a feasible solution is taken
    (back to the outer loop), a stalled frame stops, the others step back towards feasibility."""
    frames.iterations[inner] += 1
    P = frames.passive[inner]
    S = solve_restricted(Q, C[inner], P, ridge)
    feasible = np.all((S > 0) | ~P, axis=1)
    # the variable just added got a non-positive value: its positive gradient was round-off, so stop there
    # rather than cycle (Lawson & Hanson's own safeguard)
    stalled = (
        ~feasible & frames.first_inner[inner] & (S[np.arange(inner.size), np.maximum(frames.added[inner], 0)] <= 0)
    )
    frames.first_inner[inner] = False

    ok = inner[feasible]
    frames.W[ok] = S[feasible]
    frames.state[ok] = _OUTER

    st = inner[stalled]
    frames.passive[st, frames.added[st]] = False
    frames.state[st] = _DONE

    step = ~feasible & ~stalled
    idx = inner[step]
    if idx.size:
        _step_back_to_feasibility(frames, idx, S[step], P[step])


def _step_back_to_feasibility(frames: _ActiveSetFrames, idx: np.ndarray, S: np.ndarray, P: np.ndarray) -> None:
    """Move the frames ``idx`` from their feasible weights towards their infeasible restricted solutions ``S``
    (passive sets ``P``) as far as feasibility allows, until the first passive variable reaches zero, and make
    the variables that reached zero active again."""
    W = frames.W[idx]
    blocking = P & (S <= 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(blocking, W / (W - S), np.inf)
    alpha = np.clip(ratio.min(axis=1), 0.0, 1.0)
    W = W + alpha[:, None] * (S - W)
    drop = P & (W <= 0)
    # the blocking variable leaves exactly, even when round-off leaves it a hair above zero
    drop[np.arange(idx.size), np.argmin(ratio, axis=1)] = True
    frames.passive[idx] = P & ~drop
    W[~frames.passive[idx]] = 0.0
    frames.W[idx] = W


def nnls_active_set(
    Q: np.ndarray,
    C: np.ndarray,
    x_norms: np.ndarray,
    *,
    rtol: float = 1e-10,
    max_iter: int | None = None,
    initial_passive: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lawson-Hanson NNLS in Gram form for many right-hand sides at once.

    Q (k, k) = A'A, C (n, k) rows A'x_t, x_norms (n,) = ||x_t|| (sets the per-frame gradient tolerance
    ``rtol * max_j ||a_j|| * ||x_t||``). Returns weights (n, k), iterations (n,), converged (n,).
    Each frame runs the textbook algorithm; the frames only share the loop, so a frame that finished is frozen.
    ``initial_passive`` (n, k) bool guesses each frame's support: the frames start from a tiny feasible point on
    it and the first inner loop removes wrong guesses, which saves most outer iterations when the guess is good.
    """
    Q = np.asarray(Q, np.float64)
    C = np.asarray(C, np.float64)
    n, k = C.shape
    max_iter = max_iter or 5 * k + 10
    col_scale = np.sqrt(max(np.diag(Q).max(initial=0.0), EPS))
    tol = rtol * col_scale * np.maximum(np.asarray(x_norms, np.float64), EPS)
    # a tiny ridge keeps the masked solves non-singular when two keyshapes are (nearly) collinear
    ridge = 1e-13 * max(np.trace(Q) / max(k, 1), EPS)

    frames = _start_frames(n, k, initial_passive)
    for _ in range(max_iter * 3):
        _free_best_variable(frames, Q, C, tol, max_iter)
        inner = np.flatnonzero(frames.state == _INNER)
        if not inner.size:
            if not (frames.state == _OUTER).any():
                break
            continue
        _inner_step(frames, inner, Q, C, ridge)
    converged = frames.state == _DONE
    converged &= frames.iterations < max_iter
    W, passive = frames.W, frames.passive
    W[~passive] = 0.0
    return W, frames.iterations, converged


def solve_box_qp(
    H: np.ndarray,
    F: np.ndarray,
    *,
    lower: float = 0.0,
    upper: float = np.inf,
    smoothing: float = 0.0,
    W0: np.ndarray | None = None,
    rtol: float = 1e-7,
    max_iter: int = 20000,
) -> tuple[np.ndarray, int, np.ndarray]:
    """Minimise ``sum_t 1/2 w_t'H w_t - f_t'w_t + smoothing/2 sum_t ||w_t - w_(t-1)||^2`` over a box.

    FISTA (Beck & Teboulle 2009) with gradient-based adaptive restart (O'Donoghue & Candes 2015); rows (frames)
    are coupled only through ``smoothing``. Stops when the projected gradient, the KKT residual of the box
    constraints, is below ``rtol * (||f_t|| + ||H|| * ||w_t||)`` for every frame. ``H`` is one (k, k) matrix or
    one per row, (n, k, k) (no smoothing then), each row stepping by its own Lipschitz constant. ``W0`` starts
    the iteration (a warm start). Returns (W, iterations, per-frame KKT residual relative to that scale).
    """
    H = np.asarray(H, np.float64)
    F = np.atleast_2d(np.asarray(F, np.float64))
    n, k = F.shape
    per_row = H.ndim == 3
    if per_row and smoothing > 0:
        raise ValueError("smoothing couples the rows: it needs one H for all of them")
    # the gradient's Lipschitz constant; |eigenvalues| so that a slightly indefinite H (non-convex) still works
    if per_row:
        lipschitz = np.abs(np.linalg.eigvalsh(H)).max(axis=1, initial=0.0)[:, None]
    else:
        lipschitz = np.asarray(float(np.abs(np.linalg.eigvalsh(H)).max(initial=0.0)) + 4.0 * smoothing)
    lipschitz = np.maximum(lipschitz, EPS)
    h_norm = lipschitz.reshape(-1)

    def gradient(W):
        g = np.einsum("nj,njk->nk", W, H) - F if per_row else W @ H - F
        if smoothing > 0 and n > 1:
            d = np.diff(W, axis=0)
            g[:-1] -= smoothing * d
            g[1:] += smoothing * d
        return g

    W = np.clip(np.zeros((n, k)) if W0 is None else np.asarray(W0, np.float64), lower, upper)
    Y = W.copy()
    t = np.ones(n if smoothing == 0 else 1)
    residual = np.full(n, np.inf)
    it = 0
    for it in range(1, max_iter + 1):
        G = gradient(Y)
        W_new = np.clip(Y - G / lipschitz, lower, upper)
        # restart momentum where it points uphill
        uphill = np.einsum("ij,ij->i", G, W_new - W) > 0
        if smoothing > 0:
            uphill = np.array([uphill.any()])
        t_new = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * t * t))
        beta = np.where(uphill, 0.0, (t - 1.0) / t_new)
        t = np.where(uphill, 1.0, t_new)
        Y = W_new + (beta[:, None] if beta.size == n else beta[0]) * (W_new - W)
        W = W_new
        if it % 10 == 0 or it == max_iter:
            pg = projected_gradient(gradient(W), W, lower, upper)
            scale = np.linalg.norm(F, axis=1) + h_norm * np.linalg.norm(W, axis=1) + EPS
            residual = np.abs(pg).max(axis=1) / scale
            if residual.max() <= rtol:
                break
    return W, it, residual


def support_guess(Q: np.ndarray, C: np.ndarray) -> np.ndarray | None:
    """Where the unconstrained least-squares weights are positive: a guess of the NNLS support that saves
    most active-set iterations. None when A lacks full column rank (a guessed set could then be dependent and
    its restricted system singular)."""
    eigenvalues = np.linalg.eigvalsh(Q)
    if eigenvalues.size == 0 or eigenvalues[0] <= 1e-10 * eigenvalues[-1]:
        return None
    return C @ np.linalg.inv(Q) > 0


def scipy_nnls_rows(A: np.ndarray, X: np.ndarray, max_iter: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``scipy.optimize.nnls`` (Lawson-Hanson) for every row of X: weights (n, k), and 0 iterations (scipy does
    not report them)."""
    from scipy.optimize import nnls

    W = np.zeros((len(X), A.shape[1]))
    options = {"maxiter": max_iter} if max_iter else {}
    for t, x in enumerate(X):
        W[t] = nnls(A, x, **options)[0]
    return W, np.zeros(len(X), dtype=np.int64)


def _fit_problem(A: np.ndarray, X: np.ndarray, sum_to_one: float, energy: float) -> tuple[np.ndarray, np.ndarray]:
    """The least-squares problem actually solved: (A, X), with the soft sum-to-one row when ``sum_to_one`` > 0."""
    if sum_to_one <= 0:
        return A, X
    n, k = X.shape[0], A.shape[1]
    # the soft constraint is one more least-squares row: sqrt(mu) * (1'w - 1)
    root_mu = np.sqrt(sum_to_one * energy)
    A_fit = np.vstack([A, np.full((1, k), root_mu)])
    X_fit = np.hstack([X, np.full((n, 1), root_mu)])
    return A_fit, X_fit


def _active_set_with_retry(
    Q: np.ndarray,
    C: np.ndarray,
    x_norms: np.ndarray,
    A_fit: np.ndarray,
    X_fit: np.ndarray,
    guess: np.ndarray | None,
    rtol: float | None,
    max_iter: int | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The batched active set, warm-started from ``guess``; frames the warm start left short of optimal are
    solved again from scratch."""
    W, iterations, converged = nnls_active_set(
        Q, C, x_norms, rtol=rtol or 1e-10, max_iter=max_iter, initial_passive=guess
    )
    if guess is not None:
        # a warm start is only a shortcut: frames it left short of optimal start again from scratch
        retry = ~converged | (kkt_violation(A_fit, X_fit, W) > 1e-6)
        if retry.any():
            W[retry], iterations[retry], converged[retry] = nnls_active_set(
                Q, C[retry], x_norms[retry], rtol=rtol or 1e-10, max_iter=max_iter
            )
    return W, iterations, converged


def _box_qp_solution(
    Q: np.ndarray,
    C: np.ndarray,
    x_norms: np.ndarray,
    guess: np.ndarray | None,
    *,
    method: str,
    smoothing: float,
    energy: float,
    rtol: float | None,
    max_iter: int | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """FISTA on the Gram form, with temporal smoothing if asked; warm-started from the per-frame active-set
    solution unless the method is plain "fista" without smoothing."""
    W0 = None
    if smoothing > 0 or method != "fista":
        W0, _, _ = nnls_active_set(Q, C, x_norms, rtol=1e-10, initial_passive=guess)
    W, it, res = solve_box_qp(
        Q,
        C,
        lower=0.0,
        upper=np.inf,
        smoothing=smoothing * energy,
        W0=W0,
        rtol=rtol or 1e-8,
        max_iter=max_iter or 50000,
    )
    iterations = np.full(len(C), it, dtype=np.int64)
    converged = res <= (rtol or 1e-8)
    return W, iterations, converged


def batched_nnls(
    A: np.ndarray,
    X: np.ndarray,
    *,
    method: str = "scipy",
    sum_to_one: float = 0.0,
    smoothing: float = 0.0,
    rtol: float | None = None,
    max_iter: int | None = None,
) -> NnlsResult:
    """Non-negative weights w_t minimising ``||A w_t - x_t||^2`` for every row x_t of X (paper Eq 8).

    A (d, k): one dictionary column per keyshape; X (n, d): one frame per row.
    Options (off by default):
    - ``sum_to_one`` = mu > 0 adds ``mu * mean_j ||a_j||^2 * (sum_j w_j - 1)^2``, a soft convexity prior;
    - ``smoothing`` = lam > 0 adds ``lam * mean_j ||a_j||^2 * sum_t ||w_t - w_(t-1)||^2`` (frames in time order);
      it couples frames, so it is solved by FISTA warm-started from the per-frame solution.
    ``method``: "scipy" (Lawson-Hanson per frame, ``scipy.optimize.nnls``: exact, the default, because it is the
    fastest at the pipeline's sizes, ``bench/bench_nnls.py``), "active_set" (the same algorithm batched over frames
    in Gram form) or "fista" (projected gradient, KKT stopping rule). With ``smoothing`` the frames are coupled and
    FISTA refines the per-frame solution whatever the method.
    """
    A = np.asarray(A, np.float64)
    X = np.atleast_2d(np.asarray(X, np.float64))
    if A.ndim != 2 or X.shape[1] != A.shape[0]:
        raise ValueError(f"batched_nnls: A {A.shape} and X {X.shape} do not match (X rows must have A.shape[0])")
    if method not in ("scipy", "active_set", "fista"):
        raise ValueError(f"batched_nnls: unknown method {method!r} (scipy, active_set, fista)")
    n, k = X.shape[0], A.shape[1]
    energy = float((A * A).sum()) / max(k, 1)
    A_fit, X_fit = _fit_problem(A, X, sum_to_one, energy)
    if method == "scipy" and smoothing <= 0:
        W, iterations = scipy_nnls_rows(A_fit, X_fit, max_iter)
        converged = np.ones(n, dtype=bool)
    else:
        Q = A_fit.T @ A_fit
        C = X_fit @ A_fit
        x_norms = np.linalg.norm(X_fit, axis=1)
        guess = support_guess(Q, C)
        if method == "active_set" and smoothing <= 0:
            W, iterations, converged = _active_set_with_retry(Q, C, x_norms, A_fit, X_fit, guess, rtol, max_iter)
        else:
            W, iterations, converged = _box_qp_solution(
                Q, C, x_norms, guess, method=method, smoothing=smoothing, energy=energy, rtol=rtol, max_iter=max_iter
            )
    return NnlsResult(
        weights=W,
        residual_norm=np.linalg.norm(W @ A.T - X, axis=1),
        iterations=iterations,
        kkt=kkt_violation(A_fit, X_fit, W),
        converged=converged,
    )
