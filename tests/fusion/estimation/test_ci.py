"""Covariance intersection: consistent whatever the cross-correlation; naive fusion is not."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from fusion.estimation import (
    ci_combine,
    covariance_intersection,
    covariance_intersection_n,
    mean_chi2_interval,
    naive_fusion,
    nees,
    wls,
)

from .helpers import PROPERTY, min_eig, random_spd, sqrtm_psd

P_A = np.array([[1.0, 0.3], [0.3, 0.25]])
P_B = np.array([[0.3, -0.1], [-0.1, 1.2]])


def random_joint_covariance(rng, P_list):
    """A valid joint covariance of stacked errors whose diagonal blocks are P_list (unknown correlation).

    Whitened errors u_i = T_i xi share one random source xi of k dimensions (n <= k <= N n): k = n
    makes them fully correlated (the case where CI is tight), k = N n can make them nearly
    independent. Block-normalising makes each u_i ~ N(0, I); e_i = P_i^1/2 u_i.
    """
    n = P_list[0].shape[0]
    N = len(P_list)
    k = int(rng.integers(n, N * n + 1))
    T = rng.standard_normal((N * n, k))
    blocks = []
    for i, P in enumerate(P_list):
        T_i = T[i * n : (i + 1) * n]
        G_ii = T_i @ T_i.T
        blocks.append(sqrtm_psd(P) @ np.linalg.inv(sqrtm_psd(G_ii)) @ T_i)  # e_i = P^1/2 G_ii^-1/2 T_i xi
    A = np.vstack(blocks)
    return A @ A.T


def fused_error_covariance(weights_info, joint):
    """Covariance of sum_i A_i e_i for the stacked error covariance `joint` (A_i = P w_i P_i^-1)."""
    A = np.hstack(weights_info)
    return A @ joint @ A.T


def test_omega_minimises_the_trace_and_the_determinant():
    grid = np.linspace(0.0, 1.0, 401)
    for criterion, cost in (("trace", np.trace), ("det", np.linalg.det)):
        _, P, w = covariance_intersection(np.zeros(2), P_A, np.ones(2), P_B, criterion=criterion)
        assert 0.0 <= w <= 1.0
        costs = [cost(ci_combine([np.zeros(2), np.ones(2)], [P_A, P_B], [g, 1 - g])[1]) for g in grid]
        assert cost(P) <= min(costs) + 1e-9
        assert cost(P) <= min(cost(P_A), cost(P_B)) + 1e-12


def test_a_dominant_estimate_takes_all_the_weight():
    x, P, w = covariance_intersection(np.array([1.0, 2.0]), 0.1 * P_B, np.zeros(2), P_B)
    assert w == 1.0
    assert np.allclose(x, [1.0, 2.0]) and np.allclose(P, 0.1 * P_B)


def test_ci_equations_written_out():
    x_a, x_b, w = np.array([1.0, -1.0]), np.array([0.5, 0.5]), 0.3
    x, P = ci_combine([x_a, x_b], [P_A, P_B], [w, 1 - w])
    Ia, Ib = np.linalg.inv(P_A), np.linalg.inv(P_B)
    assert np.allclose(P, np.linalg.inv(w * Ia + (1 - w) * Ib), atol=1e-14)
    assert np.allclose(x, P @ (w * Ia @ x_a + (1 - w) * Ib @ x_b), atol=1e-14)


@PROPERTY
@given(st.integers(0, 2**32 - 1), st.integers(1, 4), st.sampled_from(["trace", "det"]))
def test_ci_bounds_the_true_error_covariance_for_any_correlation(seed, n, criterion):
    rng = np.random.default_rng(seed)
    P_a, P_b = random_spd(rng, n, 1.0, 20.0), random_spd(rng, n, rng.uniform(0.1, 10), 20.0)
    joint = random_joint_covariance(rng, [P_a, P_b])
    _, P, w = covariance_intersection(np.zeros(n), P_a, np.zeros(n), P_b, criterion=criterion)
    true = fused_error_covariance([w * P @ np.linalg.inv(P_a), (1 - w) * P @ np.linalg.inv(P_b)], joint)
    assert min_eig(P - true) >= -1e-8 * np.max(np.abs(P))


def test_monte_carlo_ci_is_consistent_and_naive_fusion_is_not():
    """Two trackers that share part of their error (the same radar fed both): e_a = s + d_a, e_b = s + d_b."""
    rng = np.random.default_rng(9)
    P_s = np.array([[0.2, 0.05], [0.05, 0.2]])  # shared error, unknown to the fusion
    P_a, P_b = P_s + np.diag([0.05, 0.3]), P_s + np.diag([0.3, 0.05])
    x_true = np.array([40.0, 3.0])
    n = 20_000
    s = rng.standard_normal((n, 2)) @ np.linalg.cholesky(P_s).T
    x_a = x_true + s + rng.standard_normal((n, 2)) @ np.diag(np.sqrt([0.05, 0.3]))
    x_b = x_true + s + rng.standard_normal((n, 2)) @ np.diag(np.sqrt([0.3, 0.05]))
    _, P_ci, w = covariance_intersection(x_a[0], P_a, x_b[0], P_b)  # w depends on P only, not on x
    Ia, Ib = np.linalg.inv(P_a), np.linalg.inv(P_b)
    e_ci = (x_a @ (w * Ia).T + x_b @ ((1 - w) * Ib).T) @ P_ci.T - x_true  # x = P (w Ia x_a + (1-w) Ib x_b)
    _, P_naive = naive_fusion([x_a[0], x_b[0]], [P_a, P_b])
    e_naive = (x_a @ Ia.T + x_b @ Ib.T) @ P_naive.T - x_true
    C_ci, C_naive = np.cov(e_ci.T), np.cov(e_naive.T)
    sampling = 4 * np.sqrt(2.0 / n) * np.max(np.abs(C_ci))  # 4 standard errors of a sample covariance
    assert min_eig(P_ci - C_ci) >= -sampling
    assert min_eig(P_naive - C_naive) < -10 * sampling  # naive fusion claims more than it has
    lo, hi = mean_chi2_interval(2, n)
    assert nees(e_ci, P_ci).mean() <= hi
    assert nees(e_naive, P_naive).mean() > hi
    # on independent estimates naive fusion is right: it is Eq. 5 with H = I
    x_w, P_w = wls([np.eye(2)] * 2, [P_a, P_b], [x_a[0], x_b[0]])
    x_n, P_n = naive_fusion([x_a[0], x_b[0]], [P_a, P_b])
    assert np.allclose(x_n, x_w, atol=1e-12) and np.allclose(P_n, P_w, atol=1e-14)


def test_n_way_reduces_to_the_two_way_optimum():
    x_list = [np.array([1.0, 0.0]), np.array([0.0, 1.0])]
    for criterion in ("trace", "det"):
        x2, P2, w2 = covariance_intersection(x_list[0], P_A, x_list[1], P_B, criterion=criterion)
        xn, Pn, wn = covariance_intersection_n(x_list, [P_A, P_B], criterion=criterion)
        assert wn.sum() == pytest.approx(1.0) and np.all(wn >= 0)
        assert abs(wn[0] - w2) < 1e-4
        assert np.allclose(Pn, P2, atol=1e-6) and np.allclose(xn, x2, atol=1e-5)


@PROPERTY
@given(st.integers(0, 2**32 - 1), st.integers(3, 5), st.sampled_from(["trace", "det"]))
def test_n_way_is_optimal_on_the_simplex_and_consistent(seed, N, criterion):
    rng = np.random.default_rng(seed)
    n = 3
    P_list = [random_spd(rng, n, 10.0 ** rng.uniform(-1, 1), 20.0) for _ in range(N)]
    x_list = [rng.standard_normal(n) for _ in range(N)]
    _, P, w = covariance_intersection_n(x_list, P_list, criterion=criterion)
    # random points of the simplex, and the vertices (one estimate alone), never do better
    V = np.vstack([rng.dirichlet(np.ones(N), size=500), np.eye(N)])
    P_v = np.linalg.inv(np.einsum("sk,kij->sij", V, np.linalg.inv(np.stack(P_list))))  # P^-1 = sum w_i P_i^-1
    if criterion == "trace":
        assert np.trace(P) <= np.trace(P_v, axis1=1, axis2=2).min() * (1 + 1e-6)
    else:
        assert np.linalg.det(P) <= np.linalg.det(P_v).min() * (1 + 1e-6)
    assert np.allclose(P, ci_combine(x_list, P_list, w)[1], atol=1e-12)
    joint = random_joint_covariance(rng, P_list)
    true = fused_error_covariance([wi * P @ np.linalg.inv(Pi) for wi, Pi in zip(w, P_list)], joint)
    assert min_eig(P - true) >= -1e-8 * np.max(np.abs(P))


def test_bad_input_is_named():
    with pytest.raises(ValueError, match=r"P_b must have shape \(2, 2\)"):
        covariance_intersection(np.zeros(2), P_A, np.zeros(2), np.eye(3))
    with pytest.raises(ValueError, match="criterion must be 'trace' or 'det'"):
        covariance_intersection(np.zeros(2), P_A, np.zeros(2), P_B, criterion="volume")
    with pytest.raises(ValueError, match="weights must be 2 non-negative numbers summing to 1"):
        ci_combine([np.zeros(2)] * 2, [P_A, P_B], [0.7, 0.7])
    with pytest.raises(ValueError, match=r"P_list\[1\] must be positive definite"):
        covariance_intersection_n([np.zeros(2)] * 2, [P_A, -P_B])
