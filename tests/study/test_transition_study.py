"""study.experiments.transitions: a parameter chosen on validation sequences is the one of least regret, and
the scoring of variants over test sequences (regret, its paired difference with the per-frame gate,
lags, switches, clock-gating wake-ups) on synthetic sequences whose best branch changes at a known
frame."""

import numpy as np
import pytest

from study.experiments.transitions import choose_parameter, score_variants, sequences, variant_choices


def _sequence(rng, T=40, change=20, noise=0.15):
    """Costs of 2 branches: branch 0 best before `change`, branch 1 after, by 0.3; the gate's scores are
    the costs plus noise of `noise` (so a per-frame gate flips near-ties)."""
    costs = np.zeros((T, 2))
    costs[:change, 1] = 0.3
    costs[change:, 0] = 0.3
    return costs, costs + rng.normal(0, noise, costs.shape)


def test_the_parameter_chosen_is_the_one_of_least_validation_regret_and_memory_cuts_switches():
    rng = np.random.default_rng(0)
    val = [_sequence(rng) for _ in range(6)]
    costs = {f"v{i}": c for i, (c, _) in enumerate(val)}
    scores = {f"v{i}": s for i, (_, s) in enumerate(val)}
    alpha, trace = choose_parameter(costs, scores, "ema", [1.0, 0.5, 0.3])
    assert trace[str(alpha)] == min(trace.values()) and alpha < 1.0  # memory averages the noise away
    test = [_sequence(rng) for _ in range(8)]
    tc = {f"t{i}": c for i, (c, _) in enumerate(test)}
    ts = {f"t{i}": s for i, (_, s) in enumerate(test)}
    choices = {"per-frame": {k: variant_choices(ts[k], "per-frame", None) for k in tc},
               "ema": {k: variant_choices(ts[k], "ema", alpha) for k in tc},
               "constant": {k: np.zeros(len(c), dtype=int) for k, c in tc.items()}}
    sensor = ["radar", "camera_right"]  # branch 0 reads the radar, branch 1 the camera
    wanted = {v: {k: [[sensor[int(b)]] for b in ch] for k, ch in per.items()} for v, per in choices.items()}
    out = score_variants(tc, choices, wanted, {"radar": 1, "camera_right": 1}, radius=2, frame_rate_hz=2.0,
                         resamples=200, seed=0)
    pf, ema, const = out["per-frame"], out["ema"], out["constant"]
    assert ema["switches_per_minute"] < pf["switches_per_minute"]
    assert ema["regret"] < pf["regret"] and ema["regret_minus_per-frame_interval"][1] < 0  # resolved below
    assert const["switches_per_minute"] == 0 and const["wakes_per_minute"] == 0
    assert const["regret"] == pytest.approx(0.3 * 20 / 40) and const["lag_censored_share"] == 1.0
    assert pf["changes_of_best"] == 8 and ema["lag_mean_frames"] is not None and ema["lag_mean_frames"] >= 0
    assert pf["wakes_per_minute"] > 0 and pf["frames_waiting_for_a_sensor"] > 0  # every switch wakes a sensor


def test_sequences_are_in_time_order():
    metas = [{"sequence_id": "b", "frame_index": 1}, {"sequence_id": "a", "frame_index": 0},
             {"sequence_id": "b", "frame_index": 0}]
    assert sequences(metas) == {"b": [2, 0], "a": [1]}
