"""fusion.temporal: gates with memory on synthetic sequences whose best choice changes at a known
frame, hysteresis on constant input, switching lags, clock gating's wake-ups."""

import numpy as np
import pytest

from fusion.temporal import (
    clock_schedule,
    ema_choice,
    ema_lag_bound,
    hysteresis_choice,
    per_frame_choice,
    sequence_scores,
    switches,
    switching_lags,
    transition_mask,
    wake_frames_of,
)


def _step(T=40, at=20, before=(0.0, 1.0), after=(1.0, 0.0)):
    s = np.empty((T, 2))
    s[:at], s[at:] = before, after
    return s


def test_hysteresis_never_switches_on_a_constant_input():
    rng = np.random.default_rng(0)
    for _ in range(50):
        row = rng.normal(size=int(rng.integers(2, 7)))
        s = np.tile(row, (30, 1))
        for margin in (0.0, 0.1, 1.0):
            c = hysteresis_choice(s, margin, min_dwell=int(rng.integers(0, 4)))
            assert switches(c) == 0 and c[0] == np.argmin(row)


def test_hysteresis_damps_flicker_between_near_equal_choices():
    rng = np.random.default_rng(1)
    s = np.stack([np.zeros(200), 0.01 + rng.normal(0, 0.05, 200)], axis=1)
    assert switches(per_frame_choice(s)) > 40
    assert switches(hysteresis_choice(s, margin=0.2)) < 5


def test_gates_switch_within_their_stated_lag_on_a_step():
    """The best choice changes at frame 20 (gaps of 1 before and after): the per-frame gate and a
    small-margin hysteresis follow at once; the EMA gate within ema_lag_bound frames, exactly."""
    s = _step()
    best = np.argmin(s, axis=1)
    assert switching_lags(best, per_frame_choice(s)) == [0]
    assert switching_lags(best, hysteresis_choice(s, margin=0.5)) == [0]
    assert switching_lags(best, hysteresis_choice(s, margin=2.5)) == [None]  # the gap never beats the margin
    for alpha in (0.9, 0.5, 0.3, 0.1):
        bound = ema_lag_bound(alpha, 1.0, 1.0)
        assert switching_lags(best, ema_choice(s, alpha)) == [bound], alpha
    assert ema_lag_bound(0.3, 1.0, 1.0) == 1  # ln(1/2) / ln(0.7) = 1.94
    assert ema_lag_bound(0.1, 3.0, 1.0) == 13  # ln(1/4) / ln(0.9) = 13.2
    s2 = _step(T=60, before=(0.0, 3.0), after=(1.0, 0.0))
    assert switching_lags(np.argmin(s2, axis=1), ema_choice(s2, 0.1)) == [13]


def test_sequence_scores_on_a_known_sequence():
    costs = _step(T=10, at=5)
    late_gate = [0] * 7 + [1] * 3  # switches two frames late
    r = sequence_scores(costs, late_gate, radius=1, frame_rate_hz=2.0)
    assert r["regret"] == pytest.approx(2 / 10)
    assert r["transition_frames"] == 3 and r["regret_transitions"] == pytest.approx(2 / 3)  # frames 4, 5, 6: late on 5 and 6
    assert r["lags"] == [2] and r["switches"] == 1 and r["best_switches"] == 1
    assert r["switches_per_minute"] == pytest.approx(1 / (10 / 2.0 / 60.0))
    assert list(transition_mask([0, 0, 1, 1, 1, 0], 0)) == [False, False, True, False, False, True]
    with pytest.raises(ValueError):
        sequence_scores(costs, [0, 1])


def test_clock_gating_wakes_a_sensor_before_its_data_counts():
    wanted = [("radar", "lidar")] * 5 + [("radar",)] * 5 + [("radar", "lidar")] * 5
    sched = clock_schedule(wanted, {"radar": 3, "lidar": 2})
    assert "lidar" not in sched.usable[10] and "lidar" not in sched.usable[11] and "lidar" in sched.usable[12]
    assert "lidar" in sched.powered[10] and "lidar" not in sched.powered[7]
    assert sched.wakes == {"lidar": 1} and sched.missing_frames() == 2
    # a sensor wanted only while waking is never usable and is gated again when dropped
    flick = [("radar",)] * 2 + [("radar", "lidar")] + [("radar",)] * 3
    s2 = clock_schedule(flick, {"radar": 3, "lidar": 2})
    assert all("lidar" not in u for u in s2.usable) and "lidar" not in s2.powered[3]
    with pytest.raises(ValueError, match="wake-up"):
        clock_schedule([("camera",)], {"radar": 1})


def test_wake_frames_of_the_rig_rates():
    # RADIATE's rig: radar 4 Hz, lidar 10 Hz, camera 15 Hz; at a 10 Hz study one radar sweep is 2.5 frames
    assert wake_frames_of({"radar": 4.0, "lidar": 10.0, "camera": 15.0}, 10.0) == {"radar": 3, "lidar": 1, "camera": 1}
