"""fusion.intervals: coverage on a synthetic problem with a known variance, the corrections against
their formulas and scipy, stratified draws against the design they mimic."""

import math

import numpy as np
import pytest
from scipy.stats import false_discovery_control

from fusion.intervals import (
    benjamini_hochberg,
    bootstrap_p_value,
    coverage,
    design_draws,
    expected_rest_coverage,
    holm,
    leave_one_out_means,
    percentile_interval,
    stratified_sequence_draws,
)
from fusion.metrics import sequence_draws


def test_holm_is_the_step_down_formula():
    p = [0.01, 0.04, 0.03, 0.005]
    # sorted 0.005, 0.01, 0.03, 0.04 times 4, 3, 2, 1 = 0.02, 0.03, 0.06, 0.04; running max 0.02, 0.03, 0.06, 0.06
    np.testing.assert_allclose(holm(p), [0.03, 0.06, 0.06, 0.02])
    assert np.isnan(holm([np.nan, 0.2])[0]) and holm([np.nan, 0.2])[1] == pytest.approx(0.2)  # m counts finite ones
    assert holm([0.9, 0.8]).max() <= 1.0


def test_benjamini_hochberg_matches_scipy():
    rng = np.random.default_rng(3)
    for _ in range(20):
        p = rng.uniform(0, 0.2, size=int(rng.integers(1, 12)))
        np.testing.assert_allclose(benjamini_hochberg(p), false_discovery_control(p, method="bh"), rtol=1e-12)
    # Holm controls the family-wise error, so it is never below BH's false-discovery adjustment
    assert np.all(holm(p) >= benjamini_hochberg(p) - 1e-12)


def test_bootstrap_p_value():
    assert bootstrap_p_value(np.full(999, 0.1)) == pytest.approx(2 / 1000)
    assert bootstrap_p_value(np.linspace(-1, 1, 1001)) == pytest.approx(1.0)
    assert math.isnan(bootstrap_p_value([np.nan]))


def test_expected_rest_coverage_of_eight_equal_sets():
    z = 1.959963984540054
    by_hand = math.erf(z * math.sqrt(1 / (1 + 1 / 7)) / math.sqrt(2))  # 2 Phi(x) - 1 = erf(x / sqrt 2)
    np.testing.assert_allclose(expected_rest_coverage([48] * 8), by_hand)
    assert by_hand == pytest.approx(0.933, abs=5e-4)
    # a set much smaller than the rest: the rest's estimate is nearly exact, so coverage nears 95 %
    assert expected_rest_coverage([10, 1000])[0] == pytest.approx(0.95, abs=2e-3)
    with pytest.raises(ValueError):
        expected_rest_coverage([5])


def _bootstrap_intervals(values: np.ndarray, rng, resamples: int = 400, shrink: float = 1.0) -> list:
    """Per set (rows of `values`: sets x sequences), the percentile interval of the mean over draws of
    sequences with replacement, its half-width scaled by `shrink` about the set's mean."""
    out = []
    for v in values:
        means = v[rng.integers(0, len(v), (resamples, len(v)))].mean(axis=1)
        lo, hi = percentile_interval(means)
        c = v.mean()
        out.append((c - shrink * (c - lo), c + shrink * (hi - c)))
    return out


def test_coverage_on_a_synthetic_problem_with_a_known_variance():
    """8 disjoint sets of 48 sequences, each sequence's difference ~ N(0.013, 0.1): the sequence
    bootstrap's interval holds the rest's estimate about as often as an exact interval would (0.933);
    an interval half as wide is caught (expected 2 Phi(0.98 / sqrt(8/7)) - 1 = 0.64)."""
    rng = np.random.default_rng(0)
    right, narrow = [], []
    for _ in range(150):
        values = rng.normal(0.013, 0.1, size=(8, 48))
        est = values.mean(axis=1)
        rest = leave_one_out_means(est, [48] * 8)
        right.append(coverage(_bootstrap_intervals(values, rng), rest, [48] * 8).coverage)
        narrow.append(coverage(_bootstrap_intervals(values, rng, shrink=0.5), rest, [48] * 8).coverage)
    expected = coverage([(0, 1)] * 8, [0.5] * 8, [48] * 8).expected
    assert expected == pytest.approx(0.933, abs=1e-3)
    # 1,200 set-checks: binomial sd of the share about 0.007; the percentile bootstrap at n = 48
    # under-covers by about a point (its variance is the plug-in one, (n-1)/n of the unbiased)
    assert 0.90 < np.mean(right) < 0.955
    assert np.mean(narrow) < 0.72


def test_coverage_counts_a_missing_interval_as_not_covering():
    c = coverage([(0.0, 1.0), None, (2.0, 3.0)], [0.5, 0.5, 0.5], [10, 10, 10])
    assert c.covered == (True, False, False) and c.coverage == pytest.approx(1 / 3)
    assert c.as_dict()["covered"] == 1
    with pytest.raises(ValueError):
        coverage([(0, 1)], [0.5], [3])


def test_leave_one_out_means():
    np.testing.assert_allclose(leave_one_out_means([1.0, 2.0, 4.0], [1, 1, 2]), [10 / 3, 9 / 3, 3 / 2])


def test_stratified_draws_keep_the_design_and_its_variance():
    """Two contexts with very different values, 30 sequences each (as a test set is built: a fixed
    number per context). Drawing within each context keeps 30 per context and gives the design's
    standard error (plug-in: sqrt(sum_h s_h^2 (n-1)/n / n) / 2 for two strata of n); drawing from all
    sequences mixes the contexts and inflates it."""
    rng = np.random.default_rng(1)
    n = 30
    by = {"fog": {f"f{i}": [i] for i in range(n)}, "city": {f"c{i}": [n + i] for i in range(n)}}
    values = np.concatenate([rng.normal(0.0, 0.05, n), rng.normal(1.0, 0.05, n)])
    draws = list(stratified_sequence_draws(by, 3000, seed=7))
    assert all(sum(k < n for k in d) == n and len(d) == 2 * n for d in draws)
    assert draws[:5] == list(stratified_sequence_draws(by, 5, seed=7))  # seeded
    strat_se = np.std([values[d].mean() for d in draws])
    plug_in = [np.var(values[:n]) / n, np.var(values[n:]) / n]
    assert strat_se == pytest.approx(math.sqrt(sum(plug_in)) / 2, rel=0.08)
    flat = rng.integers(0, 2 * n, (3000, 2 * n))
    flat_se = np.std(values[flat].mean(axis=1))
    assert flat_se > 5 * strat_se
    with pytest.raises(ValueError):
        next(stratified_sequence_draws({"a": {}}, 1, 0))


def test_rescaled_draws_give_the_designs_variance_at_few_sequences_per_stratum():
    """Rao and Wu's bootstrap with m_h = n_h - 1: with 6 sequences per context (a coverage check's
    sets), drawing 6 of 6 gives the mean a standard error sqrt(5 / 6) of the design's (s_h^2 / n_h,
    s_h^2 with n_h - 1 in its denominator), drawing 5 of 6 gives the design's own."""
    rng = np.random.default_rng(3)
    n, h = 6, 4
    by = {f"c{s}": {f"c{s}q{i}": [s * n + i] for i in range(n)} for s in range(h)}
    values = rng.normal(0.0, 1.0, n * h) + np.repeat(np.arange(h) * 5.0, n)
    design_se = math.sqrt(sum(np.var(values[s * n:(s + 1) * n], ddof=1) / n for s in range(h))) / h
    plain = np.std([values[d].mean() for d in stratified_sequence_draws(by, 6000, seed=2)])
    draws = list(stratified_sequence_draws(by, 6000, seed=2, rescaled=True))
    assert all(len(d) == (n - 1) * h and all(sum(k // n == s for k in d) == n - 1 for s in range(h)) for d in draws[:50])
    rescaled = np.std([values[d].mean() for d in draws])
    assert plain == pytest.approx(design_se * math.sqrt((n - 1) / n), rel=0.04)
    assert rescaled == pytest.approx(design_se, rel=0.04)
    # a stratum of one sequence is drawn once (there is nothing to rescale)
    one = next(stratified_sequence_draws({"a": {"q": [0, 1]}, "b": {"r": [2], "s": [3]}}, 1, 0, rescaled=True))
    assert sorted(one)[:2] == [0, 1] and len(one) == 3


def test_design_draws_dispatch_and_pool():
    by = {"fog": {"f0": [0, 1], "f1": [2, 3]}, "city": {"c0": [4, 5]}}
    assert list(design_draws(by, 4, seed=5, design="sequence")) == list(sequence_draws(
        {"c0": [4, 5], "f0": [0, 1], "f1": [2, 3]}, 4, 5))
    assert list(design_draws(by, 4, seed=5, design="stratified")) == list(stratified_sequence_draws(by, 4, 5))
    assert list(design_draws(by, 4, seed=5, design="rescaled")) == list(stratified_sequence_draws(by, 4, 5, True))
    with pytest.raises(ValueError, match="design"):
        design_draws(by, 4, 5, design="flat")
    with pytest.raises(ValueError, match="more than one stratum"):
        design_draws({"a": {"q": [0]}, "b": {"q": [1]}}, 4, 5, design="sequence")


def test_resolved_sign_reads_the_order_an_interval_resolves():
    from fusion.intervals import resolved_sign

    assert resolved_sign([0.01, 0.02]) == 1 and resolved_sign([-0.02, -0.01]) == -1
    assert resolved_sign([-0.01, 0.02]) == 0 and resolved_sign([0.0, 0.02]) == 0
    assert resolved_sign(None) == 0 and resolved_sign([None, 0.1]) == 0 and resolved_sign([]) == 0


@pytest.mark.parametrize("design", ["sequence", "stratified", "rescaled"])
def test_map_draws_weighted_is_the_pooled_bootstrap_for_every_design(design):
    """`map_draws` ranked once gives every source's mAP on every draw of the design as pooling each
    draw does, paired (the same draws for every source), overall and on one stratum."""
    from fusion.intervals import map_draws
    from fusion.metrics import ImageMatches
    from tests.fusion.test_metrics import random_scenes

    rng = np.random.default_rng(8)
    gts, _ = random_scenes(rng, n_images=36)
    matches = {}
    for name in ("a", "b"):
        _, dets = random_scenes(np.random.default_rng(len(name) + ord(name)), n_images=36)
        matches[name] = ImageMatches.of(dets, gts, classes=[1, 2, 3])
    by = {s: {f"{s}{q}": [12 * s + 3 * q + f for f in range(3)] for q in range(4)} for s in range(3)}
    new = map_draws(matches, by, 60, 4, design)
    old = map_draws(matches, by, 60, 4, design, scoring="pooled")
    assert new.shape == (60, 2) and np.array_equal(np.isnan(new), np.isnan(old))
    np.testing.assert_allclose(new, old, atol=1e-12)
    assert np.std(new[:, 0] - new[:, 1]) > 0
    one = map_draws(matches, {0: by[0]}, 30, 4, design)
    np.testing.assert_allclose(one, map_draws(matches, {0: by[0]}, 30, 4, design, scoring="pooled"), atol=1e-12)
    with pytest.raises(ValueError, match="scoring"):
        map_draws(matches, by, 5, 0, design, scoring="fast")
