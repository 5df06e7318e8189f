"""Gross errors: robust figures, the cause of each gross error, and what the chi-square gate does.

Every input is built by hand so the answer is known: a sample with planted outliers, a radar peak
on the neighbouring car's cells, a lidar cluster of fog returns, a stereo match landing on another
object, three sensors of which one is planted far off, two sensors that disagree.
"""

import numpy as np
import pytest
from scipy import stats

from fusion.estimation import error_model as E
from fusion.estimation import gross as G
from fusion.estimation import measurements as M
from fusion.estimation.gating import gated_wls
from sensors.lidar import LidarObservation, beam_directions
from sensors.radar import RadarObservation
from sensors.rig import load_profile, make_calibration

CALIB = make_calibration(load_profile("cpu"))
H2 = np.eye(2)


# --- robust figures ------------------------------------------------------------------------------


def test_two_planted_outliers_decide_the_mean_but_not_the_median_or_trimmed_mean():
    rng = np.random.default_rng(0)
    clean = rng.chisquare(2, 200)  # squared errors of an honest 2-D sensor, mean 2
    planted = np.r_[clean, 5e3, 8e3]
    a, b = G.robust_summary(clean), G.robust_summary(planted)
    assert b["mean"] > 25 * a["mean"]  # (2 * 200 + 13e3) / 202 ~ 66 against ~2
    assert b["se"] == pytest.approx(np.std(planted, ddof=1) / np.sqrt(202))
    assert b["se"] > 0.5 * b["mean"]  # the standard error is as large as the mean: the signature
    assert b["median"] == pytest.approx(a["median"], rel=0.03)  # chi2(2) median 1.39
    # within 3 standard errors of the chi2(2) median: 1 / (2 f(m) sqrt(n)) = 0.14, f(m) = 1/4 the density
    assert b["median"] == pytest.approx(stats.chi2.median(2), abs=3 * 0.14)
    assert b["trimmed"] == pytest.approx(a["trimmed"], rel=0.05)
    assert b["trimmed"] < 2.5


def test_trimmed_mean_cuts_ten_percent_from_each_end_and_ignores_nan():
    v = np.r_[np.arange(1.0, 11.0), np.nan]  # 1..10: 10 % off each end leaves 2..9
    s = G.robust_summary(v)
    assert s["n"] == 10 and s["trimmed"] == pytest.approx(5.5) and s["median"] == pytest.approx(5.5)
    assert np.isnan(G.robust_summary([])["mean"]) and G.robust_summary([3.0])["n"] == 1


def test_the_gross_bound_is_the_chi2_999_quantile_and_flags_one_honest_error_in_a_thousand():
    assert G.GROSS_BOUND == pytest.approx(-2 * np.log(1e-3))  # chi2(2) tail exp(-x/2)
    w = np.random.default_rng(1).standard_normal((400_000, 2))
    share = G.is_gross(np.sum(w**2, axis=1)).mean()
    assert 0.0008 < share < 0.0012
    assert not G.is_gross([np.nan]).any()


# --- causes ------------------------------------------------------------------------------------


def cause(sensor="radar", source=7, purity=1.0, quality=50.0, occlusion=0.0, truncation=0.0, shared=False):
    return G.gross_cause(sensor, 7, source, purity, quality, occlusion, truncation, shared)


def test_each_cause_is_recognised_from_the_ground_truth_of_the_measurement():
    assert cause(source=9, purity=0.0) == "association"  # the peak is actor 9's echo
    assert cause(source=9, occlusion=0.4) == "association"  # another actor's data outranks occlusion
    assert cause(source=M.SOURCE_WEATHER) == "weather"
    assert cause("lidar", source=7, purity=0.3) == "weather"  # the cluster is mostly fog returns
    assert cause(source=M.SOURCE_WORLD) == "static_world"
    assert cause(source=M.SOURCE_NOISE) == "noise"
    assert cause(shared=True, occlusion=0.4) == "common_mode"
    assert cause(occlusion=0.4) == "occlusion"
    assert cause(truncation=0.1) == "out_of_field"
    assert cause("lidar", quality=5) == "few_returns"
    assert cause("radar", quality=5) == "own_object"  # a radar's quality is its SNR, not a count
    assert cause() == "own_object"
    with pytest.raises(ValueError):
        cause(source=M.SOURCE_NONE)


def test_an_error_another_sensor_shares_is_common_mode():
    R = np.diag([0.04, 0.04])
    assert G.shares_error(np.array([-3.0, 0.0]), R, [np.array([-2.8, -0.2])], [np.diag([0.5, 1.0])])
    # the other sensor is right: the errors disagree
    assert not G.shares_error(np.array([-3.0, 0.0]), R, [np.array([0.0, 0.0])], [np.diag([0.5, 1.0])])
    # a vague sensor "agrees" with anything, but is not wrong the same way
    assert not G.shares_error(np.array([-3.0, 0.0]), R, [np.array([0.1, 0.0])], [np.diag([100.0, 100.0])])
    assert not G.shares_error(np.array([-3.0, 0.0]), R, [np.full(2, np.nan)], [R])


def test_a_radar_peak_on_the_neighbouring_car_is_recorded_as_that_car():
    A, B = CALIB.radar_azimuths, CALIB.radar_range_bins
    signal = np.zeros((A, B), np.float32)
    inst = np.zeros((A, B), np.int64)
    inst[20, 80] = 7  # the object: a weak echo
    signal[20, 80] = 50.0
    inst[21, 81] = 9  # its neighbour, one azimuth row and one range bin away (inside the window)
    signal[21, 81] = 5000.0
    obs = RadarObservation(signal, np.ones((A, B), np.float32), inst, np.zeros((A, B), np.float32))
    assert M.radar_source(obs.instance, obs, 7) == (9, 0.0)
    assert M.radar_source(obs.instance, obs, 9) == (9, pytest.approx(5000 / 5001))
    # the beam smears the neighbour's echo into a cell no actor hit: still the neighbour
    smeared = RadarObservation(signal.copy(), obs.noise, inst.copy(), obs.clutter)
    smeared.signal[22, 81] = 8000.0
    assert M.radar_source(smeared.instance, smeared, 7)[0] == 9
    # rain clutter stronger than any echo
    wet = RadarObservation(signal, obs.noise, inst, np.zeros((A, B), np.float32))
    wet.clutter[19, 79] = 1e5
    assert M.radar_source(wet.instance, wet, 7)[0] == M.SOURCE_WEATHER
    src, purity = M.radar_source(obs.instance, obs, 3)  # an actor without cells
    assert src == M.SOURCE_NONE and np.isnan(purity)


def test_a_lidar_cluster_of_fog_returns_is_recorded_as_weather():
    A = CALIB.lidar_azimuth_steps
    el = np.radians(CALIB.lidar_elevations_deg)
    rng = np.full((32, A), np.inf, np.float32)
    inst = np.zeros((32, A), np.int64)
    az = np.arange(10, 31)
    for r in range(12, 20):
        rng[r, az] = 25.0 / np.cos(el[r])
        inst[r, az] = 7
    ret = np.isfinite(rng)
    clean = LidarObservation(rng, ret.astype(np.float32), inst, np.zeros((32, A), np.uint8),
                             np.ones((32, A), np.float32), ret, np.zeros((0, 5), np.float32))
    dirs = beam_directions(CALIB)
    assert M.lidar_source(clean.instance, clean, CALIB, 7, dirs) == (7, 1.0)
    fog = clean.copy()  # fog backscatter at 4 m replaces the surface return on every ray
    fog.range[12:20][:, az] = 4.0
    fog.instance[12:20][:, az] = 0  # sensors.degrade.lidar marks a weather return with instance 0
    src, purity = M.lidar_source(clean.instance, fog, CALIB, 7, dirs)
    assert src == M.SOURCE_WEATHER and purity == 0.0
    # rain drops on 3 of the 7 central columns (|offset| <= span / 6): a minority of the returns, but
    # the nearest quarter, so the 25 % range quantile is set by drops while most returns are the car's
    rain = clean.copy()
    rain.range[12:20][:, az[9:12]] = 5.0  # 3 of the 7 central columns (central: |offset| <= span / 6)
    rain.instance[12:20][:, az[9:12]] = 0
    z, _, _ = M.lidar_measurement(clean.instance, rain, CALIB, 7, 1, dirs)
    src, purity = M.lidar_source(clean.instance, rain, CALIB, 7, dirs)
    assert np.linalg.norm(z - CALIB.ego_from_lidar[:2, 3]) < 20.0  # pulled short of 25 m
    assert src == M.SOURCE_WEATHER and 0.5 < purity < 1.0


def test_a_stereo_match_landing_on_another_object_is_recorded_as_that_object():
    left = np.zeros((40, 120), np.int64)
    left[10:30, 60:80] = 7
    right = np.zeros((40, 120), np.int64)
    right[10:30, 50:70] = 7  # the object at disparity 10
    right[10:30, 30:50] = 9  # another object further left
    assert M.camera_source(left, right, 7, 10.0) == (7, 1.0)
    src, purity = M.camera_source(left, right, 7, 28.0)  # a mismatch 18 px too far
    assert src == 9 and purity < 0.2
    assert M.camera_source(left, right, 7, np.nan)[0] == M.SOURCE_NONE


# --- the gate ------------------------------------------------------------------------------------


def test_the_gate_removes_a_planted_outlier_whose_nis_exceeds_the_bound():
    R = [np.diag([0.04, 0.04]), np.diag([0.09, 0.25]), np.diag([0.25, 1.0])]
    z = [np.array([20.0, 1.0]), np.array([20.1, 1.2]), np.array([28.0, 1.0])]  # the third is 8 m off
    g = gated_wls([H2] * 3, R, z)
    assert g.nis[2] > G.GROSS_BOUND
    assert [G.gate_outcome(k, g) for k in range(3)] == ["other_removed", "other_removed", "removed"]
    np.testing.assert_allclose(g.x, [20.0, 1.0], atol=0.15)


def test_two_sensors_that_disagree_leave_the_gate_ambiguous():
    R = [np.diag([0.04, 0.04]), np.diag([0.25, 1.0])]
    g = gated_wls([H2] * 2, R, [np.array([4.0, 0.0]), np.array([40.0, 0.0])])  # a fog return and a car
    assert g.kept.all()
    assert [G.gate_outcome(k, g) for k in range(2)] == ["ambiguous", "ambiguous"]


def test_a_wrong_association_within_the_covariances_passes_the_gate():
    # the radar's lateral R spans a car's width: its peak on the car in the next lane (2.8 m over)
    # is within the gate of the lidar's and camera's agreeing measurements
    R = [np.diag([0.04, 0.04]), np.diag([0.3, 0.05]), np.diag([0.1, 2.7])]
    z = [np.array([40.0, 0.0]), np.array([40.2, 0.1]), np.array([40.0, -2.8])]
    g = gated_wls([H2] * 3, R, z)
    assert G.gate_outcome(2, g) == "inside_gate" and g.kept.all()


# --- on a measurement set ----------------------------------------------------------------------


def test_gross_errors_of_a_set_count_classify_and_carry_the_fused_error():
    rng = np.random.default_rng(3)
    n, k = 80, len(M.SENSORS)
    truth = np.column_stack([rng.uniform(10, 50, n), rng.uniform(-5, 5, n)])
    R = np.broadcast_to(np.diag([0.05, 0.05]), (n, k, 2, 2)).copy()
    # honest errors clipped at 2.5 sigma per axis: NEES <= 12.5, below the bound, so only the planted cross it
    z = truth[:, None, :] + np.clip(rng.standard_normal((n, k, 2)), -2.5, 2.5) * np.sqrt(0.05)
    source = np.broadcast_to(np.arange(1, n + 1)[:, None], (n, k)).copy()
    z[5, 2] += [0.0, 6.0]  # radar on the neighbour: actor 99
    source[5, 2] = 99
    z[40, 1] -= [15.0, 0.0]  # lidar on fog
    source[40, 1] = M.SOURCE_WEATHER
    ms = M.MeasurementSet(np.arange(n) % 2, np.zeros(n, np.int64), np.arange(1, n + 1), np.ones(n, np.int64),
                          truth, z, R, np.full((n, k), 50.0), source, np.ones((n, k)), np.zeros(n), np.zeros(n))
    st = E.evaluate_strategies(ms)
    g = E.gross_errors(ms, st)
    nominal = g["per_sensor"]["nominal"]
    assert nominal["radar"]["gross"] == 1 and nominal["radar"]["causes"] == {"association": 1}
    assert nominal["lidar"]["gross"] == 1 and nominal["lidar"]["causes"] == {"weather": 1}
    assert nominal["camera"]["gross"] == 0
    # three sensors: the gate sees both and removes them
    assert nominal["radar"]["gate"]["nominal"] == {"removed": 1}
    assert nominal["lidar"]["gate"]["nominal"] == {"removed": 1}
    assert g["sse_share"]["full_nominal"] > 0.5  # two objects of 80 carry most of the fused error
    recs = {(r["sensor"], r["cause"]) for r in g["records"]}
    assert {("radar", "association"), ("lidar", "weather")} <= recs
    robust_gated = G.robust_summary(np.sum(st.errors["gated"] ** 2, axis=1))
    assert robust_gated["mean"] < 0.2 * st.mse["full_nominal"]
