"""fusion.robustness: each metric against a hand-worked example written out from its formula
(MultiCorrupt RA / mRA, Robo3D CE / mCE and RR / mRR), the undefined cases, the paired-twin RA and
its sequence-bootstrap interval, and the severity's physical value read from sim.weather's table."""

import math

import numpy as np
import pytest

from fusion.robustness import (
    corruption_error,
    mean_corruption_error,
    mean_relative_accuracy,
    mean_resilience_rate,
    relative_accuracies,
    relative_accuracy,
    resilience_rate,
    severity_quantity,
    severity_value,
    twin_relative_accuracy,
    twin_relative_accuracy_by_severity,
)
from sim.errors import UserError
from sim.weather import SEVERITY_TABLE

CLEAN = 0.50
SCORES = {"fog": {1: 0.40, 2: 0.30, 3: 0.10}, "rain": {1: 0.45, 2: 0.35, 3: 0.25}}
BASE = {"fog": {1: 0.30, 2: 0.20, 3: 0.10}, "rain": {1: 0.50, 2: 0.40, 3: 0.30}}


def test_relative_accuracy_and_its_mean_by_hand():
    ra = relative_accuracies(SCORES, CLEAN)
    assert ra["fog"] == pytest.approx({1: 0.40 / 0.50, 2: 0.30 / 0.50, 3: 0.10 / 0.50})
    # RA_fog = (0.8 + 0.6 + 0.2) / 3 = 0.5333; RA_rain = (0.9 + 0.7 + 0.5) / 3 = 0.7; mRA = their mean
    assert mean_relative_accuracy(ra) == pytest.approx(((0.8 + 0.6 + 0.2) / 3 + (0.9 + 0.7 + 0.5) / 3) / 2)


def test_corruption_error_and_its_mean_by_hand():
    # CE_fog = (0.6 + 0.7 + 0.9) / (0.7 + 0.8 + 0.9) = 2.2 / 2.4; CE_rain = (0.55 + 0.65 + 0.75) / (0.5 + 0.6 + 0.7)
    assert corruption_error(SCORES["fog"], BASE["fog"]) == pytest.approx(2.2 / 2.4)
    assert corruption_error(SCORES["rain"], BASE["rain"]) == pytest.approx(1.95 / 1.8)
    assert mean_corruption_error(SCORES, BASE) == pytest.approx((2.2 / 2.4 + 1.95 / 1.8) / 2)
    # the baseline against itself: every CE_c = 1, so mCE = 1
    assert mean_corruption_error(BASE, BASE) == pytest.approx(1.0)


def test_resilience_rate_and_its_mean_by_hand():
    # RR_fog = (0.4 + 0.3 + 0.1) / (3 * 0.5); RR_rain = (0.45 + 0.35 + 0.25) / (3 * 0.5)
    assert resilience_rate(SCORES["fog"], CLEAN) == pytest.approx(0.8 / 1.5)
    assert mean_resilience_rate(SCORES, CLEAN) == pytest.approx((0.8 / 1.5 + 1.05 / 1.5) / 2)
    # paired twins: the denominator is the twins' sum over the same severities
    twins = {"fog": {1: 0.5, 2: 0.4, 3: 0.2}}
    assert resilience_rate(SCORES["fog"], twins["fog"]) == pytest.approx(0.8 / 1.1)
    assert relative_accuracies({"fog": SCORES["fog"]}, twins)["fog"] == pytest.approx({1: 0.8, 2: 0.75, 3: 0.5})


def test_perfect_robustness_gives_one_everywhere():
    same = {c: {s: CLEAN for s in per} for c, per in SCORES.items()}
    assert mean_relative_accuracy(relative_accuracies(same, CLEAN)) == 1.0
    assert mean_resilience_rate(same, CLEAN) == 1.0
    assert all(v == 1.0 for per in relative_accuracies(same, CLEAN).values() for v in per.values())


def test_clean_score_zero_or_missing_is_nan_and_left_out_of_the_means():
    assert math.isnan(relative_accuracy(0.3, 0.0)) and math.isnan(relative_accuracy(0.3, None))
    assert math.isnan(relative_accuracy(None, 0.5)) and math.isnan(relative_accuracy(0.3, float("nan")))
    assert math.isnan(resilience_rate(SCORES["fog"], 0.0))
    assert math.isnan(mean_relative_accuracy(relative_accuracies(SCORES, 0.0)))
    # twins of one severity that score 0: that RA is NaN, the condition's mean uses the others
    ra = relative_accuracies({"fog": SCORES["fog"]}, {"fog": {1: 0.5, 2: 0.0, 3: 0.2}})
    assert math.isnan(ra["fog"][2])
    assert mean_relative_accuracy(ra) == pytest.approx((0.8 + 0.5) / 2)
    # a baseline without errors: CE is undefined
    assert math.isnan(corruption_error({1: 0.5}, {1: 1.0}))
    assert math.isnan(mean_relative_accuracy({}))
    # numpy scalars count as scores; a NaN one is missing; twins of a condition not measured: NaN
    assert relative_accuracy(np.float32(0.25), np.float32(0.5)) == 0.5
    assert math.isnan(relative_accuracy(np.float32("nan"), 0.5))
    assert math.isnan(relative_accuracies({"snow": {1: 0.2}}, {"fog": {1: 0.4}})["snow"][1])
    assert math.isnan(mean_resilience_rate({"snow": {1: 0.2}}, {"fog": {1: 0.4}}))


def test_a_missing_severity_is_skipped_not_counted_as_zero():
    holed = {"fog": {1: 0.40, 2: None, 3: 0.10}}
    assert relative_accuracies(holed, CLEAN) == {"fog": pytest.approx({1: 0.8, 3: 0.2})}
    assert mean_relative_accuracy(relative_accuracies(holed, CLEAN)) == pytest.approx(0.5)
    # RR over the S = 2 severities measured; CE over the severities both models have
    assert resilience_rate(holed["fog"], CLEAN) == pytest.approx(0.5 / (2 * 0.5))
    assert corruption_error(holed["fog"], BASE["fog"]) == pytest.approx((0.6 + 0.9) / (0.7 + 0.9))
    assert corruption_error({1: 0.4}, {2: 0.3}) != corruption_error({1: 0.4}, {2: 0.3})  # no common severity: NaN


def _mean_scorer(values):
    values = np.asarray(values, float)
    return lambda items: float(values[list(items)].mean())


def test_twin_ra_is_the_ratio_of_exactly_the_paired_frames():
    deg, clr = [0.2, 0.4, 0.6, 0.8], [0.5, 0.5, 1.0, 1.0]
    seq = ["a", "a", "b", "b"]
    r = twin_relative_accuracy(_mean_scorer(deg), _mean_scorer(clr), seq, resamples=50)
    assert r.ra == pytest.approx(0.5 / 0.75) and (r.degraded, r.clear) == pytest.approx((0.5, 0.75))
    assert (r.sequences, r.frames) == (2, 4)
    by = twin_relative_accuracy_by_severity(_mean_scorer(deg), _mean_scorer(clr), seq, [1, 3, 1, 3], resamples=50)
    assert sorted(by) == [1, 3]
    assert by[1].ra == pytest.approx((0.2 + 0.6) / (0.5 + 1.0)) and by[3].ra == pytest.approx((0.4 + 0.8) / (0.5 + 1.0))
    # identical degraded and clear frames: RA = 1 on every draw, so the interval is [1, 1]
    same = twin_relative_accuracy(_mean_scorer(deg), _mean_scorer(deg), seq, resamples=50)
    assert same.ra == 1.0 and same.interval == (1.0, 1.0)
    assert twin_relative_accuracy(_mean_scorer(deg), _mean_scorer(clr), seq, resamples=0).interval is None
    with pytest.raises(ValueError, match="severity_of"):
        twin_relative_accuracy_by_severity(_mean_scorer(deg), _mean_scorer(clr), seq, [1, 3])


def test_twin_draws_pair_the_scores_and_report_each_draw():
    # two sequences: every draw is (a, a), (a, b), (b, a) or (b, b), each scored on the same items
    deg, clr, seq = [0.3, 0.3, 0.6, 0.6], [0.4, 0.4, 0.8, 0.8], ["a", "a", "b", "b"]
    calls = []
    r = twin_relative_accuracy(_mean_scorer(deg), _mean_scorer(clr), seq, resamples=40, on_draw=lambda: calls.append(1))
    assert len(calls) == 40
    assert 0.3 <= r.degraded_interval[0] < r.degraded_interval[1] <= 0.6
    assert 0.4 <= r.clear_interval[0] < r.clear_interval[1] <= 0.8
    # each sequence keeps 3/4 of its twins' score, so every paired draw's ratio is exactly 0.75
    assert r.interval == pytest.approx((0.75, 0.75))
    by = twin_relative_accuracy_by_severity(_mean_scorer(deg), _mean_scorer(clr), seq, [1, 1, 2, 2], resamples=5,
                                            on_draw=lambda: calls.append(1))
    assert len(calls) == 50 and by[2].sequences == 1 and by[2].degraded_interval == pytest.approx((0.6, 0.6))


def _synthetic(n_seq, rng):
    """Sequences of 5 frames; a sequence's clear score varies, the condition keeps about 60 % of it."""
    clr = np.repeat(rng.uniform(0.3, 0.9, n_seq), 5) + rng.normal(0, 0.05, 5 * n_seq)
    deg = clr * rng.normal(0.6, 0.15, 5 * n_seq)
    return deg, clr, np.repeat(np.arange(n_seq), 5)


def test_twin_interval_holds_the_estimate_and_shrinks_with_more_sequences():
    rng = np.random.default_rng(1)
    widths = []
    for n_seq in (6, 24, 96):
        deg, clr, seq = _synthetic(n_seq, rng)
        r = twin_relative_accuracy(_mean_scorer(deg), _mean_scorer(clr), seq, resamples=400, seed=0)
        lo, hi = r.interval
        assert lo <= r.ra <= hi
        widths.append(hi - lo)
    assert widths[0] > widths[1] > widths[2]
    assert widths[2] < widths[0] / 1.5  # 16x the sequences; the bootstrap of 6 is itself too narrow, so not 4x


def test_severity_value_reads_the_weather_table():
    for cond, spec in SEVERITY_TABLE.items():
        for s in range(1, 6):
            value, unit = severity_value(cond, s)
            lo, hi = spec["levels"][s - 1]
            assert lo <= value <= hi and unit == spec["unit"]
            centre = math.sqrt(lo * hi) if spec["scale"] == "log" else (lo + hi) / 2
            assert value == pytest.approx(centre)
        assert severity_quantity(cond) == spec["quantity"]
    assert severity_value("fog", 3) == (pytest.approx(math.sqrt(150.0 * 300.0)), "m")
    assert severity_value("rain", 0) == (0.0, "mm/h")
    assert severity_value("fog", 0)[0] >= 10_000.0  # clear air
    with pytest.raises(UserError, match="unknown condition"):
        severity_value("hail", 2)
    with pytest.raises(UserError, match="unknown condition"):
        severity_value("hail", 0)
    with pytest.raises(UserError, match="severity must be"):
        severity_value("fog", 6)
