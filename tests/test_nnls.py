"""Batched NNLS (stages.geometry.nnls): agreement with scipy.optimize.nnls, the KKT conditions, options, bounded QP."""

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy.optimize import nnls as scipy_nnls

from stages.geometry.nnls import batched_nnls, kkt_violation, projected_gradient, solve_box_qp


def problem(seed, d=40, k=12, n=50, offset=0.0, sparsity=0.5, noise=0.3):
    """Targets made of sparse non-negative mixtures plus noise; ``offset`` > 0 makes the columns alike
    (like raw landmark shapes, which all resemble the mean face), i.e. the problem ill-conditioned."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(d, k)) + offset
    mix = np.abs(rng.normal(size=(k, n))) * (rng.random((k, n)) < sparsity)
    X = (A @ mix).T + noise * rng.normal(size=(n, d)) * np.linalg.norm(A) / np.sqrt(d * k)
    return A, X


def kkt_by_hand(A, x, w, tol):
    """The KKT conditions of min ||Aw - x||^2 s.t. w >= 0, written out."""
    g = A.T @ (A @ w - x)
    scale = np.linalg.norm(A, axis=0).max() * np.linalg.norm(x)
    assert np.all(w >= 0)
    assert np.all(g >= -tol * scale), "gradient negative on some coordinate: the objective could still decrease"
    assert np.all(np.abs(g[w > 0]) <= tol * scale), "non-zero gradient on a free coordinate"


@pytest.mark.parametrize("offset", [0.0, 5.0, 40.0])
@pytest.mark.parametrize("method", ["scipy", "active_set", "fista"])
def test_matches_scipy_nnls_and_satisfies_kkt(offset, method):
    A, X = problem(1, offset=offset)
    result = batched_nnls(
        A, X, method=method, rtol=1e-12 if method == "fista" else None, max_iter=200000 if method == "fista" else None
    )
    reference = np.array([scipy_nnls(A, x)[0] for x in X])
    ref_residual = np.linalg.norm(reference @ A.T - X, axis=1)
    # the optimum value is unique even where the minimiser is not: compare residuals first
    np.testing.assert_allclose(result.residual_norm, ref_residual, rtol=1e-7, atol=1e-9)
    if method != "fista":
        np.testing.assert_allclose(result.weights, reference, atol=1e-6 * max(1, np.abs(reference).max()))
    assert result.converged.all()
    for a_x, w in zip(X, result.weights):
        kkt_by_hand(A, a_x, w, tol=1e-6)
    assert result.kkt.max() < 1e-6
    # zero pattern: scipy and we agree on which keyshapes are used
    if method == "active_set" and offset == 0:
        assert np.array_equal(result.weights > 1e-9, reference > 1e-9)


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    k=st.integers(1, 15),
    n=st.integers(1, 30),
    d=st.integers(2, 60),
    offset=st.sampled_from([0.0, 3.0]),
)
@example(seed=0, k=5, n=12, d=2, offset=3.0)  # more keyshapes than dimensions: rank-deficient, no warm start
def test_random_shapes_agree_with_scipy(seed, k, n, d, offset):
    A, X = problem(seed, d=d, k=k, n=n, offset=offset)
    ref = np.array([np.linalg.norm(A @ scipy_nnls(A, x)[0] - x) for x in X])
    for method in ("scipy", "active_set"):  # the default, and the batched solver
        result = batched_nnls(A, X, method=method)
        assert np.all(result.weights >= 0)
        assert np.all(result.residual_norm <= ref * (1 + 1e-7) + 1e-9 * np.linalg.norm(X, axis=1).max())
        assert result.kkt.max() < 1e-7


def test_exact_recovery_of_nonnegative_mixtures():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(30, 8)) + 2.0
    true = np.abs(rng.normal(size=(100, 8))) * (rng.random((100, 8)) < 0.5)
    result = batched_nnls(A, true @ A.T)
    np.testing.assert_allclose(result.weights, true, atol=1e-8)
    assert result.residual_norm.max() < 1e-8


def test_degenerate_inputs():
    rng = np.random.default_rng(4)
    A = rng.normal(size=(20, 5))
    # zero target: zero weights; a target opposite to every column: zero weights, residual = ||x||
    x_opposite = -A.sum(axis=1) * 10
    X = np.vstack([np.zeros(20), x_opposite])
    A_pos = np.abs(A)
    result = batched_nnls(A_pos, np.vstack([np.zeros(20), -A_pos.sum(axis=1)]))
    np.testing.assert_array_equal(result.weights, 0)
    # duplicated column: a solution still exists, residual matches scipy
    A_dup = np.hstack([A, A[:, :1]])
    result = batched_nnls(A_dup, X)
    ref = np.array([np.linalg.norm(A_dup @ scipy_nnls(A_dup, x)[0] - x) for x in X])
    np.testing.assert_allclose(result.residual_norm, ref, rtol=1e-7, atol=1e-9)
    # a single column is a closed form: w = max(0, a.x / a.a)
    a = A[:, :1]
    result = batched_nnls(a, X)
    np.testing.assert_allclose(result.weights[:, 0], np.maximum(0, X @ a[:, 0] / (a[:, 0] @ a[:, 0])), atol=1e-12)


def test_sum_to_one_pulls_weight_sums_to_one():
    rng = np.random.default_rng(5)
    A = rng.normal(size=(30, 6))
    X = (A @ (2.5 * rng.dirichlet(np.ones(6), size=40).T)).T  # exact mixtures summing to 2.5
    plain = batched_nnls(A, X)
    soft = batched_nnls(A, X, sum_to_one=100.0)
    np.testing.assert_allclose(plain.weights.sum(axis=1), 2.5, rtol=1e-6)
    assert np.abs(soft.weights.sum(axis=1) - 1).max() < 0.05
    assert np.all(soft.weights >= 0)
    assert soft.residual_norm.mean() > plain.residual_norm.mean()
    assert soft.kkt.max() < 1e-7  # optimal for the augmented problem


def test_temporal_smoothing_reduces_jitter_and_is_optimal():
    rng = np.random.default_rng(6)
    A = rng.normal(size=(30, 5)) + 1.0
    t = np.linspace(0, 1, 120)
    smooth_w = np.c_[np.sin(3 * t) + 1, np.cos(2 * t) + 1, t, 1 - t, 0.5 + 0 * t]
    X = smooth_w @ A.T + 0.5 * rng.normal(size=(120, 30))
    plain = batched_nnls(A, X)
    smoothed = batched_nnls(A, X, smoothing=0.5)
    jitter = lambda w: np.abs(np.diff(w, axis=0)).mean()
    assert jitter(smoothed.weights) < 0.5 * jitter(plain.weights)
    assert np.all(smoothed.weights >= 0)
    assert np.abs(smoothed.weights - smooth_w).mean() < np.abs(plain.weights - smooth_w).mean()
    # optimality of the coupled problem: projected gradient of the full objective ~ 0
    energy = (A * A).sum() / A.shape[1]
    lam = 0.5 * energy
    W = smoothed.weights
    grad = (W @ A.T - X) @ A
    d = np.diff(W, axis=0)
    grad[:-1] -= lam * d
    grad[1:] += lam * d
    assert np.abs(projected_gradient(grad, W)).max() < 1e-5 * np.abs(X @ A).max()


def test_box_qp_respects_bounds_and_matches_reference():
    from scipy.optimize import lsq_linear

    rng = np.random.default_rng(7)
    J = rng.normal(size=(40, 10))
    targets = rng.normal(size=(15, 40)) * 3
    W, _, residual = solve_box_qp(J.T @ J, targets @ J, lower=0.0, upper=1.0, rtol=1e-10)
    assert W.min() >= 0 and W.max() <= 1
    assert residual.max() <= 1e-10
    for w, y in zip(W, targets):
        ref = lsq_linear(J, y, bounds=(0, 1), method="bvls", tol=1e-12).x
        np.testing.assert_allclose(w, ref, atol=1e-6)


def test_box_qp_with_one_matrix_per_row_solves_each_row_weighted():
    """Per-row matrices (n, k, k): each row is its own weighted least squares (the keymorph fit's robust
    reweighting), the same as scaling that row's data and solving it alone; a warm start changes nothing."""
    from scipy.optimize import lsq_linear

    rng = np.random.default_rng(11)
    J = rng.normal(size=(30, 8))
    targets = rng.normal(size=(5, 30)) * 2
    weights = rng.uniform(0.05, 1.0, size=(5, 30))
    H = np.einsum("dm,kd,dn->kmn", J, weights, J)
    W, _, residual = solve_box_qp(H, (targets * weights) @ J, lower=0.0, upper=1.0, rtol=1e-10)
    assert residual.max() <= 1e-10
    for w, y, d in zip(W, targets, weights):
        root = np.sqrt(d)
        ref = lsq_linear(J * root[:, None], y * root, bounds=(0, 1), method="bvls", tol=1e-12).x
        np.testing.assert_allclose(w, ref, atol=1e-6)
    warm, _, _ = solve_box_qp(H, (targets * weights) @ J, lower=0.0, upper=1.0, rtol=1e-10, W0=W * 0.5)
    np.testing.assert_allclose(warm, W, atol=1e-6)
    with pytest.raises(ValueError, match="smoothing"):
        solve_box_qp(H, targets @ J, smoothing=1.0)


def test_box_qp_with_fixed_variables_stops_at_the_optimum():
    """A variable whose bounds meet (upper 0: a corrective held at 0) is fixed; its gradient must not count as a
    KKT violation, or the solver never sees that it converged and runs to max_iter (the keymorph fit did, 20,000
    iterations for every mouth region)."""
    rng = np.random.default_rng(3)
    J = rng.normal(size=(40, 10))
    targets = rng.normal(size=(6, 40)) * 3 + J.sum(axis=1)  # every variable wants to be positive
    upper = np.ones((6, 10))
    upper[:, 4] = 0.0
    W, iterations, residual = solve_box_qp(J.T @ J, targets @ J, lower=0.0, upper=upper, rtol=1e-9)
    assert iterations < 2000 and residual.max() <= 1e-9 and not W[:, 4].any()
    free = [i for i in range(10) if i != 4]
    for w, y in zip(W, targets):
        from scipy.optimize import lsq_linear

        np.testing.assert_allclose(w[free], lsq_linear(J[:, free], y, bounds=(0, 1), tol=1e-12).x, atol=1e-6)
    pg = projected_gradient(np.full((1, 2), -1.0), np.zeros((1, 2)), 0.0, np.array([[0.0, 1.0]]))
    assert pg.tolist() == [[0.0, -1.0]]


def test_kkt_violation_detects_suboptimal_and_infeasible():
    A, X = problem(8, n=5)
    good = batched_nnls(A, X).weights
    assert kkt_violation(A, X, good).max() < 1e-8
    assert np.all(kkt_violation(A, X, good * 0.5 + 0.1) > 1e-3)
    bad = good.copy()
    bad[0, 0] = -0.1
    assert np.isinf(kkt_violation(A, X, bad)[0])


def test_rejects_mismatched_shapes_and_unknown_method():
    with pytest.raises(ValueError, match="do not match"):
        batched_nnls(np.ones((5, 2)), np.ones((3, 4)))
    with pytest.raises(ValueError, match="unknown method"):
        batched_nnls(np.ones((5, 2)), np.ones((3, 5)), method="magic")
