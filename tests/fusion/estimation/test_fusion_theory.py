"""The covariance argument of HydraFusion Sec. 1.1: more sensors help only when their R is right.

The scenario used for the overconfident case: an object's ground-plane position (x forward,
y lateral, metres), seen by
- radar: range bins of 0.17 m, 0.9 deg azimuth at ~30 m: sigma = (0.25, 0.6) m;
- lidar: sigma = 0.15 m in both axes;
- stereo camera: the estimator assumes the clear-weather model, poor depth and sharp lateral
  position, sigma = (4, 0.1) m; behind raindrops the truth is sigma = (8, 0.5) m.
"""

import numpy as np
import pytest
from hypothesis import given

from fusion.estimation import (
    NotObservableError,
    best_subset,
    fused_error,
    scalar_fused_variance,
    subset_errors,
    wls,
    wls_gains,
)

from .helpers import PROPERTY, min_eig, rel_err, sensor_setups

H3 = [np.eye(2)] * 3
R_RADAR = np.diag([0.25, 0.6]) ** 2
R_LIDAR = np.diag([0.15, 0.15]) ** 2
R_CAMERA_ASSUMED = np.diag([4.0, 0.1]) ** 2
R_CAMERA_TRUE = np.diag([8.0, 0.5]) ** 2
X_TRUE = np.array([30.0, -2.0])  # [m]


def monte_carlo_errors(rng, H_list, R_assumed, R_true, x_true, n_draws, bias_list=None):
    """Errors of wls (built from R_assumed) on n_draws measurement sets drawn with R_true (+ bias)."""
    Z = []
    for i, (H, R) in enumerate(zip(H_list, R_true)):
        noise = rng.standard_normal((n_draws, H.shape[0])) @ np.linalg.cholesky(R).T
        if bias_list is not None:
            noise += bias_list[i]
        Z.append(x_true @ H.T + noise)
    y_hat, _ = wls(H_list, R_assumed, Z)
    return y_hat - x_true


def mse_tolerance(P_true, n_draws, sigmas=4.0):
    """sigmas x the standard error of a Monte-Carlo mean of |e|^2 for zero-mean Gaussian e."""
    return sigmas * np.sqrt(2.0 * np.trace(P_true @ P_true) / n_draws)


@PROPERTY
@given(sensor_setups(min_sensors=2))
def test_with_correct_R_fusing_more_never_hurts(setup):
    H_list, R_list, _ = setup
    errors = subset_errors(H_list, R_list, R_list)
    full = errors[tuple(range(len(H_list)))]
    scale = np.max(np.abs(full.P_assumed))
    for subset, err in errors.items():
        # the estimator's covariance is the true one when R is right
        assert rel_err(err.P_true, err.P_assumed) < 1e-9
        # Loewner order: P_subset - P_full is positive semi-definite, hence also in trace
        assert min_eig(err.P_true - full.P_true) >= -1e-9 * scale, subset
        assert np.trace(full.P_true) <= np.trace(err.P_true) * (1 + 1e-12), subset


def test_monte_carlo_mse_equals_trace_P_with_correct_R():
    rng = np.random.default_rng(11)
    R_list = [R_RADAR, R_LIDAR, np.diag([4.0, 0.1]) ** 2]
    _, P = wls(H3, R_list, [X_TRUE] * 3)
    n = 40_000
    e = monte_carlo_errors(rng, H3, R_list, R_list, X_TRUE, n)
    mse = np.mean(np.sum(e**2, axis=1))
    assert abs(mse - np.trace(P)) < mse_tolerance(P, n)
    # and the whole covariance, not just its trace: each entry within 4 standard errors
    C = np.cov(e.T)
    se = np.sqrt((P**2 + np.outer(np.diag(P), np.diag(P))) / n)
    assert np.all(np.abs(C - P) < 4 * se)
    assert np.all(np.abs(e.mean(axis=0)) < 4 * np.sqrt(np.diag(P) / n))  # unbiased


def test_gains_reproduce_wls_and_sum_to_identity():
    K_list, P = wls_gains(H3, [R_RADAR, R_LIDAR, R_CAMERA_ASSUMED])
    zs = [np.array([30.1, -2.3]), np.array([29.9, -1.9]), np.array([35.0, -2.05])]
    y_hat, P_wls = wls(H3, [R_RADAR, R_LIDAR, R_CAMERA_ASSUMED], zs)
    assert rel_err(sum(K @ z for K, z in zip(K_list, zs)), y_hat) < 1e-12
    assert rel_err(P, P_wls) < 1e-12
    assert np.allclose(sum(K @ H for K, H in zip(K_list, H3)), np.eye(2), atol=1e-12)


def test_overconfident_camera_makes_full_fusion_worse_analytically():
    R_assumed = [R_RADAR, R_LIDAR, R_CAMERA_ASSUMED]
    R_true = [R_RADAR, R_LIDAR, R_CAMERA_TRUE]
    errors = subset_errors(H3, R_assumed, R_true)
    full = errors[(0, 1, 2)]
    best_single = min(errors[(i,)].mse for i in range(3))
    subset, best = best_subset(H3, R_assumed, R_true)
    assert subset == (0, 1)  # radar + lidar: leave the camera out
    assert full.mse > best_single  # worse than the lidar alone
    assert full.mse > 3.0 * best.mse
    # the estimator does not know: it claims less than the best subset's true error
    assert np.trace(full.P_assumed) < best.mse < full.mse
    # the harm is all in the lateral axis, where the camera was trusted most
    assert full.P_true[1, 1] > 5.0 * best.P_true[1, 1]


def test_overconfident_camera_makes_full_fusion_worse_in_monte_carlo():
    rng = np.random.default_rng(5)
    R_assumed = [R_RADAR, R_LIDAR, R_CAMERA_ASSUMED]
    R_true = [R_RADAR, R_LIDAR, R_CAMERA_TRUE]
    n = 40_000
    e_full = monte_carlo_errors(rng, H3, R_assumed, R_true, X_TRUE, n)
    e_best = monte_carlo_errors(rng, H3[:2], R_assumed[:2], R_true[:2], X_TRUE, n)
    e_lidar = monte_carlo_errors(rng, H3[1:2], R_assumed[1:2], R_true[1:2], X_TRUE, n)
    full = fused_error(H3, R_assumed, R_true)
    best = fused_error(H3[:2], R_assumed[:2], R_true[:2])
    mse_full = np.mean(np.sum(e_full**2, axis=1))
    mse_best = np.mean(np.sum(e_best**2, axis=1))
    mse_lidar = np.mean(np.sum(e_lidar**2, axis=1))
    # Monte Carlo agrees with P_true = sum K_i R_i K_i' ...
    assert abs(mse_full - full.mse) < mse_tolerance(full.P_true, n)
    assert abs(mse_best - best.mse) < mse_tolerance(best.P_true, n)
    # ... and confirms the ordering with margins far beyond the sampling error
    assert mse_full > mse_lidar + mse_tolerance(full.P_true, n)
    assert mse_full > 3.0 * mse_best


@pytest.mark.parametrize(
    ("r1_hat", "r2_hat", "r1", "r2"),
    [(1.0, 1.0, 1.0, 1.0), (0.1, 1.0, 4.0, 1.0), (2.0, 0.5, 2.0, 0.5), (0.01, 1.0, 1.0, 1.0)],
)
def test_one_dimensional_formula(r1_hat, r2_hat, r1, r2):
    w = r2_hat / (r1_hat + r2_hat)
    var = scalar_fused_variance(r1_hat, r2_hat, r1, r2)
    assert var == pytest.approx(w**2 * r1 + (1 - w) ** 2 * r2, rel=1e-14)
    err = fused_error([[[1.0]], [[1.0]]], [r1_hat, r2_hat], [r1, r2])
    assert err.P_true[0, 0] == pytest.approx(var, rel=1e-12)
    rng = np.random.default_rng(int(1000 * r1_hat + r2))
    n = 40_000
    e = monte_carlo_errors(
        rng, [np.eye(1)] * 2, [r1_hat, r2_hat], [np.array([[r1]]), np.array([[r2]])], np.zeros(1), n
    )
    assert abs(np.mean(e**2) - var) < 4 * np.sqrt(2 * var**2 / n)


def test_one_dimensional_overconfidence_threshold():
    """With correct variances fusion beats the better sensor; trusting sensor 1 too much loses."""
    r1, r2 = 4.0, 1.0
    assert scalar_fused_variance(r1, r2, r1, r2) < min(r1, r2)
    # sensor 1 claims 0.1 instead of 4: w = 1/1.1, var = (1/1.1)^2 4 + (0.1/1.1)^2 1 = 3.31 > r2
    assert scalar_fused_variance(0.1, r2, r1, r2) == pytest.approx(
        (1 / 1.1) ** 2 * 4 + (0.1 / 1.1) ** 2, rel=1e-12
    )
    assert scalar_fused_variance(0.1, r2, r1, r2) > r2


def test_bias_adds_sum_K_b_and_its_square_to_the_mse():
    rng = np.random.default_rng(8)
    R_assumed = [R_RADAR, R_LIDAR, R_CAMERA_ASSUMED]
    R_true = [R_RADAR, R_LIDAR, R_CAMERA_TRUE]
    biases = [np.zeros(2), np.array([0.05, 0.0]), np.array([2.0, 0.4])]  # a camera seeing a lens drop's ghost
    err = fused_error(H3, R_assumed, R_true, biases)
    K_list, _ = wls_gains(H3, R_assumed)
    assert np.allclose(err.bias, sum(K @ b for K, b in zip(K_list, biases)), atol=1e-15)
    assert err.mse == pytest.approx(np.trace(err.P_true) + err.bias @ err.bias, rel=1e-14)
    n = 40_000
    e = monte_carlo_errors(rng, H3, R_assumed, R_true, X_TRUE, n, bias_list=biases)
    assert np.all(np.abs(e.mean(axis=0) - err.bias) < 4 * np.sqrt(np.diag(err.P_true) / n))
    assert abs(np.mean(np.sum(e**2, axis=1)) - err.mse) < 0.03 * err.mse


def test_subsets_that_do_not_observe_the_state_are_left_out():
    H_list = [np.array([[1.0, 0.0]]), np.array([[0.0, 1.0]]), np.eye(2)]
    R = [1.0, 1.0, np.eye(2)]
    errors = subset_errors(H_list, R, R)
    assert set(errors) == {(2,), (0, 1), (0, 2), (1, 2), (0, 1, 2)}
    with pytest.raises(NotObservableError):
        subset_errors(H_list[:1], R[:1], R[:1])


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"R_true_list": [np.eye(2), np.eye(2)]}, r"R_true_list has 2 entries but H_list has 3"),
        (
            {"R_true_list": [np.eye(2), np.eye(2), np.diag([1.0, -1.0])]},
            r"R_true_list\[2\] must be positive semi-definite",
        ),
        ({"bias_list": [np.zeros(2), np.zeros(3), np.zeros(2)]}, r"bias_list\[1\] must have shape \(2,\)"),
    ],
)
def test_bad_true_model_names_the_entry(kwargs, message):
    args = {
        "H_list": H3,
        "R_assumed_list": [R_RADAR, R_LIDAR, R_CAMERA_ASSUMED],
        "R_true_list": [R_RADAR, R_LIDAR, R_CAMERA_TRUE],
    }
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        fused_error(**args)


def test_a_perfect_true_sensor_may_have_singular_true_R():
    err = fused_error([[[1.0]], [[1.0]]], [1.0, 1.0], [0.0, 2.0])
    assert err.P_true[0, 0] == pytest.approx(0.25 * 0.0 + 0.25 * 2.0)
    with pytest.raises(ValueError, match="r1_assumed must be > 0"):
        scalar_fused_variance(0.0, 1.0, 1.0, 1.0)


def test_scalar_crossover_is_where_fusing_stops_paying():
    """Below r2*, fusing sensor 2 (weighted by its nominal variance) beats sensor 1 alone; above, it
    is worse; at r2* equal. With r1 known, r2* = r1 + 2 r2_hat."""
    from fusion.estimation.mismatch import scalar_crossover, scalar_fused_variance

    r1, r2_hat = 1.0, 0.25
    r2_star = scalar_crossover(r1, r1, r2_hat)
    assert r2_star == pytest.approx(r1 + 2 * r2_hat)
    assert scalar_fused_variance(r1, r2_hat, r1, r2_star) == pytest.approx(r1)
    assert scalar_fused_variance(r1, r2_hat, r1, 0.99 * r2_star) < r1 < scalar_fused_variance(r1, r2_hat, r1, 1.01 * r2_star)
    # sensor 1 mis-assumed too: the general (1 + w) / (1 - w) form, checked against the variance
    s = scalar_crossover(2.0, 1.5, 0.7)
    assert scalar_fused_variance(1.5, 0.7, 2.0, s) == pytest.approx(2.0)
    with pytest.raises(ValueError):
        scalar_crossover(1.0, 0.0, 1.0)
