"""NEES / NIS and their chi-square bounds (Bar-Shalom, Li, Kirubarajan ch. 5)."""

import numpy as np
import pytest
from scipy import stats

from fusion.estimation import (
    chi2_interval,
    consistency_report,
    is_consistent,
    mean_chi2_interval,
    nees,
    nis,
    sequential_fusion,
    wls,
)

from .helpers import random_spd


def test_nees_is_e_P_inverse_e():
    assert nees([1.0, 2.0], np.diag([1.0, 4.0])) == pytest.approx(2.0)
    P = np.array([[2.0, 1.0], [1.0, 2.0]])
    e = np.array([1.0, -3.0])
    assert nees(e, P) == pytest.approx(e @ np.linalg.solve(P, e), rel=1e-12)
    assert nis([3.0], [[9.0]]) == pytest.approx(1.0)


def test_nees_broadcasts_over_runs_and_steps():
    rng = np.random.default_rng(0)
    Ps = np.stack([random_spd(rng, 3) for _ in range(6)]).reshape(2, 3, 3, 3)
    E = rng.standard_normal((2, 3, 3))
    out = nees(E, Ps)
    assert out.shape == (2, 3)
    for i in range(2):
        for k in range(3):
            assert out[i, k] == pytest.approx(E[i, k] @ np.linalg.solve(Ps[i, k], E[i, k]), rel=1e-12)
    # one covariance shared by many errors
    shared = nees(E.reshape(6, 3), Ps[0, 0])
    assert shared.shape == (6,)


@pytest.mark.parametrize(
    ("e", "P", "message"),
    [
        (np.zeros(3), np.eye(2), r"P must have shape \(\.\.\., 3, 3\)"),
        (np.zeros((4, 2)), np.stack([np.eye(2)] * 3), r"does not broadcast"),
        (np.zeros(2), np.diag([1.0, -1.0]), "P must be positive definite"),
    ],
)
def test_nees_rejects_bad_shapes(e, P, message):
    with pytest.raises(ValueError, match=message):
        nees(e, P)


def test_bounds_are_chi_square_quantiles():
    lo, hi = chi2_interval(2, 0.95)
    assert lo == pytest.approx(stats.chi2.ppf(0.025, 2)) and hi == pytest.approx(stats.chi2.ppf(0.975, 2))
    assert (lo, hi) == mean_chi2_interval(2, 1, 0.95)
    # Bar-Shalom's example: n = 2, M = 50 runs -> [1.5, 2.6]
    lo50, hi50 = mean_chi2_interval(2, 50)
    assert lo50 == pytest.approx(1.48, abs=0.01) and hi50 == pytest.approx(2.59, abs=0.01)
    # the M-run average concentrates around n: width ~ 2 * 1.96 * sqrt(2 n / M)
    lo_big, hi_big = mean_chi2_interval(4, 2000)
    assert lo_big < 4 < hi_big
    assert hi_big - lo_big == pytest.approx(2 * 1.96 * np.sqrt(8 / 2000), rel=0.02)
    with pytest.raises(ValueError, match="prob must be strictly between 0 and 1"):
        chi2_interval(2, 1.0)
    with pytest.raises(ValueError, match="n_runs must be a positive integer"):
        mean_chi2_interval(2, 0)


def test_single_run_bounds_hold_95_percent_of_honest_nees():
    rng = np.random.default_rng(1)
    P = random_spd(rng, 3, 2.0)
    n = 20_000
    e = rng.standard_normal((n, 3)) @ np.linalg.cholesky(P).T
    v = nees(e, P)
    lo, hi = chi2_interval(3)
    inside = np.mean((v >= lo) & (v <= hi))
    assert abs(inside - 0.95) < 4 * np.sqrt(0.95 * 0.05 / n)
    assert abs(v.mean() - 3.0) < 4 * np.sqrt(6.0 / n)  # E[NEES] = n_x, Var = 2 n_x


def _fusion_runs(rng, R_assumed_scale, n_runs=100):
    """NEES of the WLS fusion of three 2-D sensors, R assumed = scale x true R."""
    H_list = [np.eye(2), np.array([[1.0, 0.5], [0.0, 1.0]]), np.array([[0.3, 1.0]])]
    R_true = [np.diag([0.2, 0.5]), np.array([[0.3, 0.1], [0.1, 0.4]]), np.array([[0.1]])]
    R_assumed = [R_assumed_scale * R for R in R_true]
    x = np.array([12.0, -3.0])
    values = []
    for _ in range(n_runs):
        z_list = [
            H @ x + np.linalg.cholesky(R) @ rng.standard_normal(H.shape[0]) for H, R in zip(H_list, R_true)
        ]
        x_hat, P = wls(H_list, R_assumed, z_list)
        values.append(nees(x_hat - x, P))
    return np.array(values)


def test_honest_fusion_passes_and_overconfident_fails():
    rng = np.random.default_rng(2)
    honest = consistency_report(_fusion_runs(rng, 1.0), dof=2)
    assert honest.consistent and honest.verdict == "consistent"
    assert honest.lower < honest.mean[0] < honest.upper
    over = consistency_report(_fusion_runs(rng, 0.25), dof=2)  # R assumed 4x too small
    assert not over.consistent and over.verdict == "overconfident"
    assert over.mean[0] > over.upper
    under = consistency_report(_fusion_runs(rng, 4.0), dof=2)  # R assumed 4x too large
    assert not under.consistent and under.verdict == "underconfident"
    assert under.mean[0] < under.lower
    assert is_consistent(_fusion_runs(rng, 1.0), 2) and not is_consistent(_fusion_runs(rng, 0.25), 2)


def test_nis_of_sequential_updates_is_consistent():
    """NIS needs no ground truth: each sensor's innovation against the fusion of the others."""
    rng = np.random.default_rng(4)
    H_list = [np.eye(2), np.eye(2), np.array([[1.0, 1.0]])]
    R_list = [np.diag([0.5, 0.2]), np.diag([0.1, 0.3]), np.array([[0.05]])]
    x = np.array([3.0, 4.0])
    values = []
    for _ in range(200):
        z_list = [
            H @ x + np.linalg.cholesky(R) @ rng.standard_normal(H.shape[0]) for H, R in zip(H_list, R_list)
        ]
        x_prior, P_prior = sequential_fusion(H_list[:2], R_list[:2], z_list[:2])
        H, R = H_list[2], R_list[2]
        y = z_list[2] - H @ x_prior  # y = z - H x
        S = H @ P_prior @ H.T + R  # S = H P H' + R
        values.append(nis(y, S))
    report = consistency_report(values, dof=1)
    assert report.consistent, report


def test_report_over_runs_and_time_steps():
    rng = np.random.default_rng(6)
    M, T, n = 50, 40, 4
    honest = stats.chi2.rvs(n, size=(M, T), random_state=rng)
    rep = consistency_report(honest, dof=n)
    assert rep.mean.shape == (T,) and rep.n_runs == M
    assert rep.min_fraction == pytest.approx(0.95 - 3 * np.sqrt(0.95 * 0.05 / T))
    assert rep.consistent and rep.fraction_inside >= rep.min_fraction
    over = consistency_report(1.5 * honest, dof=n)
    assert over.verdict == "overconfident" and over.fraction_inside < 0.5
    with pytest.raises(ValueError, match="values must have shape"):
        consistency_report(np.zeros((2, 2, 2)), dof=2)
    with pytest.raises(ValueError, match="non-negative"):
        consistency_report([-1.0, 2.0], dof=2)
