"""The constant-velocity tracker: its model, its consistency on its own model's data, its gate."""

import numpy as np
import pytest
from filterpy.common import Q_continuous_white_noise

from fusion.estimation import (
    CVTracker,
    Measurement,
    consistency_report,
    cv_model,
    cv_predict,
    nees,
    position_update,
    run_cv_tracker,
    run_cv_trackers,
    simulate_cv_truth,
)

Q_PSD = 0.5  # [m^2/s^3]
X0_HAT = np.array([10.0, 2.0, 15.0, 0.5])  # [m, m, m/s, m/s]
P0 = np.diag([1.0, 1.0, 4.0, 4.0])
# name: (rate [Hz], first time [s], R the tracker assumes [m^2])
SENSORS = {
    "radar": (4.0, 0.0, np.diag([0.3, 0.8]) ** 2),
    "lidar": (10.0, 0.03, np.diag([0.15, 0.15]) ** 2),
    "camera": (15.0, 0.01, np.diag([2.0, 0.2]) ** 2),
}


def schedule(duration: float):
    """(time, sensor) pairs of all sensors, time-ordered."""
    rows = []
    for name, (rate, t0, _) in SENSORS.items():
        rows += [(t, name) for t in np.arange(t0, duration, 1.0 / rate)]
    return sorted(rows)


def simulate_run(rng, duration=4.0, true_R_factor=None, object_id=0):
    """Truth from the tracker's own model and measurements with the sensors' noise (x true_R_factor)."""
    sched = schedule(duration)
    times = np.array([t for t, _ in sched])
    x0 = X0_HAT + np.linalg.cholesky(P0) @ rng.standard_normal(4)
    truth = simulate_cv_truth(rng, x0, times, Q_PSD)
    ms = []
    for (t, name), x in zip(sched, truth):
        R = SENSORS[name][2]
        R_true = R * (true_R_factor or {}).get(name, 1.0)
        z = x[:2] + np.linalg.cholesky(R_true) @ rng.standard_normal(2)
        ms.append(Measurement(t=t, sensor=name, z=z, R=R, object_id=object_id))
    return ms, truth


def test_cv_model_is_the_continuous_white_noise_acceleration_model():
    dt = 0.07
    F, Q = cv_model(dt, Q_PSD)
    assert np.array_equal(F, [[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]])
    ref = Q_continuous_white_noise(dim=2, dt=dt, spectral_density=Q_PSD, block_size=2, order_by_dim=False)
    assert np.allclose(Q, ref, rtol=1e-14, atol=0)


def test_prediction_composes_over_split_intervals():
    """Continuous-time noise: predicting 0.1 s then 0.15 s equals predicting 0.25 s."""
    x, P = X0_HAT, P0
    x1, P1 = cv_predict(*cv_predict(x, P, 0.1, Q_PSD), 0.15, Q_PSD)
    x2, P2 = cv_predict(x, P, 0.25, Q_PSD)
    assert np.allclose(x1, x2, atol=1e-12) and np.allclose(P1, P2, atol=1e-12)


def test_tracker_class_equals_its_stateless_twin():
    rng = np.random.default_rng(0)
    ms, _ = simulate_run(rng, duration=1.0)
    tracker = CVTracker(X0_HAT, P0, t0=0.0, q=Q_PSD, gate_prob=0.99)
    x, P, t = X0_HAT, P0, 0.0
    for m in ms:
        ok_c, nis_c = tracker.step(m)
        x, P = cv_predict(x, P, m.t - t, Q_PSD)
        t = m.t
        x, P, ok_f, nis_f = position_update(x, P, m.z, m.R, gate_prob=0.99)
        assert ok_c == ok_f and nis_c == pytest.approx(nis_f, rel=1e-10)
        assert np.allclose(tracker.x, x, atol=1e-10) and np.allclose(tracker.P, P, atol=1e-12)
    hist = run_cv_tracker(ms, q=Q_PSD, gate_prob=0.99, x0=X0_HAT, P0=P0, t0=0.0)
    assert np.allclose(hist.x[-1], tracker.x, atol=1e-12)
    assert hist.x.shape == (len(ms), 4) and hist.P.shape == (len(ms), 4, 4)
    assert hist.sensor == tuple(m.sensor for m in ms)


def _nees_nis(rng, n_runs, true_R_factor=None):
    nees_runs, nis_runs = [], []
    for _ in range(n_runs):
        ms, truth = simulate_run(rng, true_R_factor=true_R_factor)
        hist = run_cv_tracker(ms, q=Q_PSD, x0=X0_HAT, P0=P0, t0=0.0)
        nees_runs.append(nees(hist.x - truth, hist.P))
        nis_runs.append(hist.nis)
    return np.array(nees_runs), np.array(nis_runs)


def test_tracker_is_consistent_on_constant_velocity_data():
    rng = np.random.default_rng(1)
    nees_mt, nis_mt = _nees_nis(rng, n_runs=40)
    assert nees_mt.shape == (40, len(schedule(4.0)))
    rep = consistency_report(nees_mt, dof=4)
    assert rep.consistent, (rep.fraction_inside, rep.min_fraction)
    assert rep.lower < nees_mt.mean() < 4 * 1.1  # the grand mean sits at n_x = 4
    assert consistency_report(nis_mt, dof=2).consistent


def test_tracker_trusting_a_fogged_camera_is_overconfident():
    rng = np.random.default_rng(2)
    nees_mt, nis_mt = _nees_nis(rng, n_runs=40, true_R_factor={"camera": 25.0})
    rep = consistency_report(nees_mt, dof=4)
    assert not rep.consistent and rep.verdict == "overconfident"
    assert consistency_report(nis_mt, dof=2).verdict == "overconfident"  # visible without ground truth


def test_gate_rejects_an_outlier_and_protects_the_track():
    rng = np.random.default_rng(3)
    ms, truth = simulate_run(rng)
    k = next(i for i, m in enumerate(ms) if m.sensor == "camera" and m.t > 2.0)
    bad = ms[k]
    ms[k] = Measurement(
        t=bad.t, sensor=bad.sensor, z=bad.z + np.array([0.0, 8.0]), R=bad.R
    )  # 40 sigma laterally
    gated = run_cv_tracker(ms, q=Q_PSD, gate_prob=0.99, x0=X0_HAT, P0=P0, t0=0.0)
    plain = run_cv_tracker(ms, q=Q_PSD, x0=X0_HAT, P0=P0, t0=0.0)
    assert not gated.accepted[k] and plain.accepted.all()
    assert gated.accepted.mean() > 0.95  # honest measurements pass the 99 % gate
    err_gated = np.linalg.norm(gated.x[k, :2] - truth[k, :2])
    err_plain = np.linalg.norm(plain.x[k, :2] - truth[k, :2])
    assert err_gated < 0.3 < 1.0 < err_plain


def test_track_can_start_at_its_first_measurement():
    rng = np.random.default_rng(4)
    ms, truth = simulate_run(rng, duration=3.0)
    hist = run_cv_tracker(ms, q=Q_PSD, velocity_std=20.0)
    first = ms[0]
    assert np.array_equal(hist.x[0], np.concatenate([first.z, [0.0, 0.0]]))
    assert np.allclose(hist.P[0], np.diag([*np.diag(first.R), 400.0, 400.0]))
    assert np.isnan(hist.nis[0]) and hist.accepted[0]
    assert np.linalg.norm(hist.x[-1, 2:] - truth[-1, 2:]) < 1.5  # the velocity is learnt [m/s]


def test_several_objects_get_their_own_tracks():
    rng = np.random.default_rng(5)
    ms_a, _ = simulate_run(rng, duration=1.0, object_id=7)
    ms_b, _ = simulate_run(rng, duration=1.0, object_id=3)
    tracks = run_cv_trackers(ms_a + ms_b, q=Q_PSD)
    assert list(tracks) == [3, 7]
    assert tracks[7].object_id == 7 and len(tracks[7].t) == len(ms_a)
    assert np.array_equal(tracks[3].x, run_cv_tracker(ms_b, q=Q_PSD).x)
    with pytest.raises(ValueError, match=r"measurements mix objects \[3, 7\]"):
        run_cv_tracker(ms_a + ms_b)


def test_bad_input_is_named():
    with pytest.raises(ValueError, match=r"R of the radar measurement at t=1.0 must have shape \(2, 2\)"):
        Measurement(t=1.0, sensor="radar", z=np.zeros(2), R=np.eye(3))
    with pytest.raises(ValueError, match="z of the lidar measurement"):
        Measurement(t=1.0, sensor="lidar", z=np.zeros(3), R=np.eye(2))
    tracker = CVTracker(X0_HAT, P0, t0=2.0)
    with pytest.raises(ValueError, match="out-of-sequence"):
        tracker.predict(1.0)
    with pytest.raises(ValueError, match="q must be a finite spectral density"):
        cv_model(0.1, -1.0)
    with pytest.raises(ValueError, match="x0 and P0 must be given together"):
        run_cv_tracker([Measurement(0.0, "radar", np.zeros(2), np.eye(2))], x0=X0_HAT)
    with pytest.raises(ValueError, match=r"P0 must have shape \(4, 4\)"):
        CVTracker(X0_HAT, np.eye(2))
