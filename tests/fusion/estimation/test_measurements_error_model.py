"""True-versus-nominal error models and the fusion strategies, on synthetic measurements.

Three sensors measure points 10-50 m away with nominal covariances shaped like the real ones
(a camera poor in depth, a lidar sharp in both axes, a radar in between); their true errors are
drawn with a chosen scale and bias, so the answer of every statistic is known.
"""

import numpy as np
import pytest

from fusion.estimation import error_model as E
from fusion.estimation.consistency import mean_chi2_interval
from fusion.estimation.measurements import SENSORS, MeasurementSet, polar_covariance
from fusion.estimation.wls import wls

NOMINAL_SIGMA = {"camera": (3.0, 0.1), "lidar": (0.1, 0.15), "radar": (0.5, 0.6)}  # (radial, lateral) [m]


def synthetic(n, scale=None, bias_sigma=None, seed=0, sequences=4, missing=0.0):
    """n objects, each measured by every sensor with true errors scale[s] x its nominal sigma, plus a
    bias of bias_sigma[s] nominal sigmas along (radial, lateral)."""
    scale = {s: 1.0 for s in SENSORS} | (scale or {})
    bias_sigma = {s: (0.0, 0.0) for s in SENSORS} | (bias_sigma or {})
    rng = np.random.default_rng(seed)
    r = rng.uniform(10, 50, n)
    b = rng.uniform(-0.4, 0.4, n)
    truth = np.column_stack([r * np.cos(b), r * np.sin(b)])
    k = len(SENSORS)
    z = np.empty((n, k, 2))
    R = np.empty((n, k, 2, 2))
    for j, s in enumerate(SENSORS):
        sr, sl = NOMINAL_SIGMA[s]
        for i in range(n):
            R[i, j] = polar_covariance(b[i], sr, sl)
            c, si = np.cos(b[i]), np.sin(b[i])
            e_los = (rng.standard_normal(2) * scale[s] + bias_sigma[s]) * (sr, sl)
            z[i, j] = truth[i] + np.array([[c, -si], [si, c]]) @ e_los
    if missing:
        z[rng.uniform(size=(n, k)) < missing] = np.nan
    return MeasurementSet(np.arange(n) % sequences, np.zeros(n, np.int64), np.arange(n), np.ones(n, np.int64),
                          truth, z, R, np.zeros((n, k)))


def test_honest_sensor_statistics_match_their_expectation():
    ms = synthetic(4000, seed=1)
    for s in SENSORS:
        e = E.sensor_errors(ms, s)
        assert e.n == 4000 and e.availability == 1.0
        # 4 standard errors of a mean of squares of N(0, 1): 4 sqrt(2 / n)
        np.testing.assert_allclose(e.variance_ratio, 1.0, atol=4 * np.sqrt(2 / 4000))
        np.testing.assert_allclose(e.bias_sigma, 0.0, atol=4 / np.sqrt(4000))
        assert e.nees_bounds[0] <= e.nees_mean <= e.nees_bounds[1]
        assert e.nees_median == pytest.approx(2 * np.log(2), rel=0.06)  # chi2(2) median
        assert e.coverage95 == pytest.approx(0.95, abs=4 * np.sqrt(0.95 * 0.05 / 4000))
        np.testing.assert_allclose(e.rms_m, NOMINAL_SIGMA[s], rtol=0.05)


def test_an_overconfident_sensor_shows_in_its_variance_ratio_and_nees():
    ms = synthetic(2000, scale={"camera": 3.0}, bias_sigma={"radar": (2.0, 0.0)}, seed=2)
    cam, rad = E.sensor_errors(ms, "camera"), E.sensor_errors(ms, "radar")
    np.testing.assert_allclose(cam.variance_ratio, 9.0, rtol=0.1)
    assert cam.nees_mean > cam.nees_bounds[1] and cam.coverage95 < 0.5
    np.testing.assert_allclose(rad.bias_sigma, [2.0, 0.0], atol=0.1)
    assert rad.variance_ratio[0] == pytest.approx(1.0 + 4.0, rel=0.1)  # E[w^2] = 1 + bias^2


def test_fitted_error_model_scales_the_nominal_covariance():
    ms = synthetic(3000, scale={"lidar": 4.0}, bias_sigma={"lidar": (1.0, -0.5)}, seed=3)
    model = E.fit_error_model(ms, "lidar")
    np.testing.assert_allclose(model.C, 16 * np.eye(2), atol=1.5)
    np.testing.assert_allclose(model.m, [1.0, -0.5], atol=0.25)  # the bias, in nominal sigmas
    bias, cov = model.apply(ms, "lidar")
    k = SENSORS.index("lidar")
    # R_true = Q' L C L' Q: for a diagonal C = c I this is c R_nominal
    np.testing.assert_allclose(cov[0], model.C[0, 0] * ms.R[0, k], rtol=0.15, atol=1e-4)
    few = E.fit_error_model(ms[:2], "lidar")  # too few to fit: the nominal model stands
    assert few.n == 0 and np.all(few.m == 0) and np.all(few.C == np.eye(2))


def test_with_honest_sensors_full_fusion_beats_every_single_sensor():
    """The MVUE statement of Eq. 5 on measured errors: nothing beats fusing all when R is right."""
    st = E.evaluate_strategies(synthetic(400, seed=4))
    assert st.n == 400 and st.folds == 2
    for s in SENSORS:
        assert st.mse["full_nominal"] < st.mse[s]
    # selection and true-R weighting cannot improve on the optimum beyond their own noise
    assert st.mse["full_nominal"] <= st.mse["selective"] + 2 * st.mse_se["full_nominal"]
    assert st.mse["full_true"] == pytest.approx(st.mse["full_nominal"], rel=0.1)
    assert st.nees_bounds[0] <= st.nees_mean <= st.nees_bounds[1]
    assert st.mse_full_nominal_predicted == pytest.approx(st.mse["full_nominal"], rel=0.15)


def test_an_overconfident_lidar_makes_full_fusion_lose_to_selective_fusion():
    """HydraFusion Sec. 1.1: a sensor 30x worse than it claims drags the full fusion; leaving it out
    (selective) or weighting it by its true error (full_true) wins, and the NEES shows it."""
    st = E.evaluate_strategies(synthetic(300, scale={"lidar": 30.0}, seed=5))
    assert all("lidar" not in s for s in st.subsets)
    assert st.mse["selective"] < 0.2 * st.mse["full_nominal"]
    assert st.mse["full_true"] < 0.2 * st.mse["full_nominal"]
    assert st.nees_mean > st.nees_bounds[1]
    # the predicted cost of the wrong R (fused_error with the fitted error models) is the measured one
    assert st.mse_full_nominal_predicted == pytest.approx(st.mse["full_nominal"], rel=0.2)


def test_strategies_compare_the_objects_the_active_sensors_saw_and_fuse_what_reported():
    ms = synthetic(40, seed=6)
    assert E.evaluate_strategies(ms[ms.sequence % 2 == 0]) is None  # one fold only
    holey = synthetic(120, seed=7, missing=0.3)
    st = E.evaluate_strategies(holey)
    active = holey.available[:, [1, 2]].all(axis=1)
    assert st is not None and st.n == int(active.sum()) < 120
    assert 0 < st.measured["camera"] < st.n == st.measured["lidar"] == st.measured["radar"]
    # every strategy gives an estimate for every compared object; a missing camera is left out
    for name in E.STRATEGIES:
        assert np.isfinite(st.errors[name]).all(), name
    assert np.isnan(st.errors["camera"]).any(axis=1).sum() == st.n - st.measured["camera"]
    # "full" on an object without a camera is exactly Eq. 5 over lidar and radar
    folds = holey.sequence % 2
    rows = np.flatnonzero(active & ~holey.available[:, 0] & (folds == 0))
    i = rows[0]
    x, _ = wls([np.eye(2)] * 2, [holey.R[i, 1], holey.R[i, 2]], [holey.z[i, 1], holey.z[i, 2]])
    k = int(np.sum(active & (folds == 0) & (np.arange(len(holey)) < i)))  # fold 0 is scored first
    np.testing.assert_allclose(st.errors["full_nominal"][k], x - holey.truth[i])


def test_nees_bounds_are_the_chi2_mean_interval():
    st = E.evaluate_strategies(synthetic(40, seed=8))
    assert st.nees_bounds == mean_chi2_interval(2, st.n)
