"""HydraFusion Sec. 1.1 stated on measured data: rendered, degraded frames of the simulator.

The data is study.experiments.theory.SMALL_CONFIG (motorway fog, rain and night; severities 0, 3, 5; 24
frames per cell in two sequences, the same traffic in every cell) and the fog-bank sequence, measured
once per test session into a shared cache (the notebook test reads the same cache). Every number
below is a measurement of this fixed sample, not a draw that changes from run to run; the
thresholds leave margins of several times what the sample shows (see the comments), and each one
fails if an extractor, a nominal R or a sensor model changes the physics it relies on.

Errors are heavy-tailed (a stereo mismatch, a fog return in a lidar cluster), so clear-weather
consistency is stated robustly (coverage of the nominal 95 % ellipse, median NEES), while the
degradations are stated through the mean NEES, which the tails dominate: that is where they live.
"""

import numpy as np
import pytest
from scipy import stats

from fusion.estimation.error_model import evaluate_strategies, sensor_errors
from fusion.estimation.measurements import SENSORS
from study.experiments import theory

CHI2_MEDIAN = float(stats.chi2.median(2))  # 1.386


@pytest.fixture(scope="session")
def cells(cache_lock):
    with cache_lock("theory") as cache:  # measured once per session, by whichever test comes first
        data, _ = theory.collect(theory.SMALL_CONFIG, cache, workers=2, progress=False)
    return data


@pytest.fixture(scope="session")
def strategies(cells):
    return {cell: evaluate_strategies(ms) for cell, ms in cells.items()}


def test_in_clear_weather_each_sensor_is_consistent_with_its_nominal_R(cells):
    """Clear weather: the nominal 95 % ellipse covers >= 75 % of each sensor's errors (sample:
    camera 100 %, lidar 82 %, radar 86 %) and the typical error is not larger than R says: median
    NEES <= 2 x the chi2(2) median (sample: 0.6-0.8 against 2.77). The mean is reported, not
    bounded: rare mismatches make it 1.3-2.3 here (2 if R were exact)."""
    ms = cells[("fog", 0)]
    for s in SENSORS:
        e = sensor_errors(ms, s)
        assert e.n >= 20, s
        assert e.coverage95 >= 0.75, (s, e.coverage95)
        assert e.nees_median <= 2 * CHI2_MEDIAN, (s, e.nees_median)


def test_in_clear_weather_full_fusion_is_not_beaten_by_a_subset(strategies):
    """With (nearly) right R, Eq. 5 over all sensors is the best there is: the cross-fitted
    selective fusion does not beat it by more than two standard errors of the paired difference."""
    st = strategies[("fog", 0)]
    d = np.sum(st.errors["full_nominal"] ** 2, axis=1) - np.sum(st.errors["selective"] ** 2, axis=1)
    assert d.mean() <= 2 * d.std(ddof=1) / np.sqrt(len(d))
    assert st.mse["full_nominal"] < st.mse["radar"] and st.mse["full_nominal"] < st.mse["camera"]


def test_fog_makes_the_lidar_overconfident_and_leaves_the_radar_alone(cells):
    """Fog backscatter returns near the sensor land in the lidar's cluster: its errors become
    thousands of nominal sigmas (sample: mean NEES 3.5e4 against 2.3 in clear, none of its errors
    inside its ellipse). The radar barely notices fog (ITU-R P.840: < 0.3 dB over 100 m): its error
    statistics are those of clear weather."""
    clear, fog = cells[("fog", 0)], cells[("fog", 5)]
    lid0, lid5 = sensor_errors(clear, "lidar"), sensor_errors(fog, "lidar")
    assert lid5.nees_mean > 1000 * lid0.nees_mean
    assert lid5.coverage95 < 0.5 and lid5.nees_mean > lid5.nees_bounds[1]
    rad0, rad5 = sensor_errors(clear, "radar"), sensor_errors(fog, "radar")
    assert rad5.availability == rad0.availability
    assert rad5.nees_mean == pytest.approx(rad0.nees_mean, rel=0.25)
    assert rad5.coverage95 == pytest.approx(rad0.coverage95, abs=0.05)
    np.testing.assert_allclose(rad5.rms_m, rad0.rms_m, rtol=0.25)


def test_night_makes_the_camera_overconfident_while_the_active_sensors_do_not_change(cells):
    """On the motorway at night head- and tail-lamps give the stereo matcher bright, well-textured
    blobs: more objects pass the NCC test than by day (sample: 40 % against 29 %), but the lamps are
    not the surface the depth is meant for and low-light noise is 10x the day's, so the errors
    outgrow R: the share inside the nominal 95 % ellipse falls (sample: 80 % against 100 %) and the
    mean NEES doubles (2.7 against 1.3), as does the MSE, and the depth acquires a bias of metres.
    With 30 objects that mean is not yet outside the chi2 bounds of an honest sensor. The lidar and radar are active sensors:
    night leaves their errors exactly as they were."""
    clear, night = cells[("night", 0)], cells[("night", 5)]
    cam0, cam5 = sensor_errors(clear, "camera"), sensor_errors(night, "camera")
    assert cam5.n >= 20
    assert cam5.coverage95 < cam0.coverage95 - 0.1
    assert cam5.nees_mean > 1.5 * cam0.nees_mean
    assert abs(cam5.bias_m[0]) > 3 * abs(cam0.bias_m[0])  # in depth (sample: -3.8 m against -0.8 m)
    for s in ("lidar", "radar"):
        assert sensor_errors(night, s).nees_mean == sensor_errors(clear, s).nees_mean


def test_heavy_rain_takes_the_camera_away(cells):
    """Rain on the lens and streaks in the air break the stereo match; the matcher's confidence test
    rejects what it cannot match (sample: 29 % of objects measured in clear weather, 8 % at 25-50 mm/h)."""
    cam0 = sensor_errors(cells[("rain", 0)], "camera")
    cam5 = sensor_errors(cells[("rain", 5)], "camera")
    assert cam5.availability < cam0.availability / 3


def test_an_overconfident_lidar_in_fog_makes_full_fusion_lose_to_selective_fusion(strategies):
    """HydraFusion's claim, measured: at 30-75 m visibility the nominal full fusion follows the
    lidar's fog returns (sample: MSE 718 m^2) while the radar (and the camera where it still
    matches), selected on the other fold, stays within a few m^2 (sample: 1.7); the difference is
    > 3 standard errors of the paired difference. The full fusion's NEES is far outside its bounds
    (sample: 3.3e4 against 2.5): it does not know it is wrong."""
    st = strategies[("fog", 5)]
    assert all("lidar" not in subset for subset in st.subsets)
    d = np.sum(st.errors["full_nominal"] ** 2, axis=1) - np.sum(st.errors["selective"] ** 2, axis=1)
    assert d.mean() > 3 * d.std(ddof=1) / np.sqrt(len(d))
    assert st.mse["selective"] < st.mse["full_nominal"] / 10
    assert st.nees_mean > 100 * st.nees_bounds[1]
    # weighting each sensor by its measured error (the true R) repairs most of the damage too
    assert st.mse["full_true"] < st.mse["full_nominal"] / 10


def test_chi2_gating_keeps_a_tracker_on_target_through_a_fog_bank(cache_lock):
    """A constant-velocity tracker fed every sensor at its nominal R follows the lidar's fog returns
    while the bank passes (sample: 19 m error); the same tracker with a 99 % chi-square gate rejects
    them and stays within a couple of metres (sample: <= 1.2 m); the lidar is rejected only in fog."""
    with cache_lock("theory") as cache:
        bank = theory.fog_bank_tracks(cache)
    foggy = bank.visibility_m < 100.0
    clear = bank.visibility_m > 5000.0
    assert foggy.sum() >= 5 and clear.sum() >= 10
    err = {name: np.hypot(*e.T) for name, e in bank.errors.items()}
    assert np.nanmax(err["all sensors"][foggy]) > 10.0
    assert np.nanmax(err["all sensors, gated"][foggy]) < 3.0
    assert np.nanmax(err["camera + radar"][foggy]) < 3.0
    lidar_in_fog = bank.available["lidar"] & foggy
    assert bank.rejected["lidar"][lidar_in_fog].mean() >= 0.8
    assert not bank.rejected["lidar"][clear].any()


def test_in_dense_fog_the_lidar_gross_errors_are_fog_returns_and_the_static_gate_cannot_remove_them(cells,
                                                                                                 strategies):
    """Every lidar error at 30-75 m visibility lies beyond the 99.9 % bound of its nominal R, and
    the ground truth recorded with each measurement says why: the return that set the range came
    from the air (sample: 73 of 73). The chi-square gate sees the conflict but, with only lidar and
    radar left, cannot say which of the two is wrong ("ambiguous"): it removes a fog return only on
    objects the camera still measured, a third opinion (sample: 2, on the 2 such objects), so the
    gated MSE stays that of full fusion."""
    from fusion.estimation.error_model import gross_errors

    ms, st = cells[("fog", 5)], strategies[("fog", 5)]
    lidar = gross_errors(ms, st)["per_sensor"]["nominal"]["lidar"]
    assert lidar["gross"] >= 0.9 * lidar["n"]
    assert lidar["causes"].get("weather", 0) >= 0.9 * lidar["gross"]
    gate = lidar["gate"]["nominal"]
    assert gate.get("ambiguous", 0) >= 0.9 * lidar["gross"]
    assert gate.get("removed", 0) <= st.measured["camera"]
    assert st.mse["gated"] == pytest.approx(st.mse["full_nominal"], rel=0.05)


def test_in_clear_weather_a_few_objects_decide_the_fused_mean_and_the_sensors_share_their_error(cells, strategies):
    """Clear weather, nearly right R: still the mean squared error of fusion is several times its
    median (sample: 1.25 m^2 against 0.13), because a handful of objects carry it. Against each
    sensor's measured covariance (fitted on the other sequences) those objects are gross errors
    and carry most of the summed squared error of fusion with the measured R (sample: 89 % on 14 of
    59 objects). Most of the lidar's are common-mode (sample: 9 of 12): a truck seen obliquely
    that lidar and radar both put ~3 m short of its reference point, which no comparison of the
    sensors, and so no gate, can detect."""
    from fusion.estimation.error_model import gross_errors
    from fusion.estimation.gross import robust_summary

    ms, st = cells[("fog", 0)], strategies[("fog", 0)]
    fused = robust_summary(np.sum(st.errors["full_true"] ** 2, axis=1))
    assert fused["mean"] > 4 * fused["median"]
    g = gross_errors(ms, st)
    assert g["sse_share"]["full_true"] > 0.5
    assert g["objects_with_gross"]["measured"] < 0.4 * st.n
    lidar = g["per_sensor"]["measured"]["lidar"]
    assert lidar["causes"].get("common_mode", 0) >= 0.5 * lidar["gross"] > 0
    assert lidar["gate"]["measured"].get("removed", 0) == 0
