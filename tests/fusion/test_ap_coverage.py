"""fusion.ap_coverage and the bootstrap intervals of fusion.intervals: the synthetic problem's population AP
against closed forms and a huge sample, the coverage counter on a case with a known answer, the
interval formulas by hand and against scipy, and the exact mAP path they run on."""

import math

import numpy as np
import pytest
from scipy import integrate, stats

from fusion.ap_coverage import (
    ClassSpec,
    MethodSpec,
    SyntheticDetection,
    count_coverage,
    coverage_experiment,
    trial,
)
from fusion.intervals import (
    INTERVALS,
    basic_interval,
    bca_interval,
    bootstrap_interval,
    draw_jackknife_se,
    jackknife_p_value,
    jackknife_se,
    jackknife_t_interval,
    leave_one_out_rows,
    map_draws,
    map_intervals,
    percentile_interval,
    studentized_interval,
)
from fusion.metrics import DrawScorer

ONE = (ClassSpec("car", 1.0, 0.3, 0.8),)


def test_population_ap_without_false_positives_is_the_recall():
    """No false positives and no difficulty spread: precision is 1 everywhere, so AP = the largest
    recall Phi(margin + offset), in closed form."""
    m = SyntheticDetection(classes=(ClassSpec("car", 1.0, 0.3, 0.0),), methods=(MethodSpec("a", 0.5, 1.0),),
                           difficulty_sd=0.0)
    assert m.true_ap("a", 0) == pytest.approx(stats.norm.cdf(0.8), abs=1e-9)


def test_population_ap_is_the_binormal_integral():
    """With no difficulty spread the curve is binormal: R(t) = Phi(a) Phi(mu - t), false positives per
    frame fp Phi(-t); AP = integral of P(t) dR(t), by scipy's quad (precision falls with recall here,
    so no envelope)."""
    a, mu, rate, fp = 0.9, 1.5, 1.2, 0.7
    m = SyntheticDetection(classes=(ClassSpec("car", rate, 0.0, fp),), methods=(MethodSpec("a", a, mu),),
                           difficulty_sd=0.0)
    pa = stats.norm.cdf(a)

    def integrand(t):
        tp = rate * pa * stats.norm.cdf(mu - t)
        return tp / (tp + fp * stats.norm.cdf(-t)) * pa * stats.norm.pdf(mu - t)

    want, _ = integrate.quad(integrand, -15, 20, limit=200)
    assert m.true_ap("a", 0) == pytest.approx(want, abs=1e-6)


def test_population_ap_is_what_a_huge_sample_gives():
    """Difficulty shared by a sequence's frames, density, correlated methods: the pooled AP of 20 000
    sequences (60 000 frames) is within 0.01 of the population AP, while leaving the difficulty's
    effect on the false positives (exp(fp_slope^2 sd^2 / 2)) out of it moves it by more."""
    m = SyntheticDetection(classes=ONE, difficulty_sd=1.0, fp_slope=1.0)
    sample = m.sample(20_000, np.random.default_rng(5))
    for name, matches in sample.items():
        got = DrawScorer(matches).ap([list(range(len(matches.per_image)))])[1][0]
        assert got == pytest.approx(m.true_ap(name, 0), abs=0.01)
    wrong = SyntheticDetection(classes=(ClassSpec("car", 1.0, 0.3, 0.8 / math.exp(0.5)),), difficulty_sd=1.0,
                               fp_slope=1.0)  # the same, without the lognormal mean of exp(d)
    assert abs(wrong.true_ap("late", 0) - m.true_ap("late", 0)) > 0.03
    assert m.true_map("all_branches") > m.true_map("late")


def test_sample_shapes_and_errors():
    m = SyntheticDetection(classes=ONE, frames_per_sequence=2)
    s = m.sample(5, np.random.default_rng(0))
    assert set(s) == {"late", "all_branches"} and all(len(v.per_image) == 10 for v in s.values())
    n_pos = [[r[1][2] for r in v.per_image] for v in s.values()]
    assert n_pos[0] == n_pos[1]  # both methods see the same objects
    with pytest.raises(ValueError, match="n_sequences"):
        m.sample(0, np.random.default_rng(0))
    with pytest.raises(ValueError, match="shared"):
        SyntheticDetection(shared=1.5)
    with pytest.raises(ValueError, match="no method"):
        m.true_ap("gate", 0)


def test_count_coverage_by_hand():
    c = count_coverage([(0.0, 1.0), (2.0, 3.0), None, (-1.0, 0.2)], 0.5, estimates=[0.25, 2.5, 0.0, 0.0])
    assert (c["covered"], c["trials"], c["miss_low"], c["miss_high"], c["failed"]) == (1, 4, 1, 1, 1)
    assert c["coverage"] == 0.25 and c["se"] == pytest.approx(math.sqrt(0.25 * 0.75 / 4))
    assert c["mean_width"] == pytest.approx((1 + 1 + 1.2) / 3)
    assert c["median_position"] == pytest.approx(np.median([0.25, 0.5, 1 / 1.2]))


def test_count_coverage_of_a_t_interval_is_95_percent():
    """A normal mean's t-interval is exact: over 4000 samples of 8 its coverage is 0.95 within 3
    standard errors, and the estimate sits at the middle; a z-interval at n = 8 undercovers."""
    rng = np.random.default_rng(1)
    x = rng.normal(2.0, 3.0, (4000, 8))
    mean, se = x.mean(axis=1), x.std(axis=1, ddof=1) / math.sqrt(8)
    t = stats.t.ppf(0.975, 7)
    c = count_coverage(list(zip(mean - t * se, mean + t * se)), 2.0, mean)
    assert abs(c["coverage"] - 0.95) < 3 * c["se"] and c["median_position"] == pytest.approx(0.5)
    z = count_coverage(list(zip(mean - 1.96 * se, mean + 1.96 * se)), 2.0)
    assert z["coverage"] < 0.95 - 2 * z["se"]


def test_basic_and_studentized_intervals_by_hand():
    v = np.arange(1.0, 102.0)  # percentiles 2.5 %, 97.5 %: 3.5, 98.5
    assert percentile_interval(v) == pytest.approx((3.5, 98.5))
    assert basic_interval(v, 40.0) == pytest.approx((80.0 - 98.5, 80.0 - 3.5))
    # constant se* = 2: t* = (v - 40) / 2, quantiles (3.5 - 40) / 2, (98.5 - 40) / 2; se = 3
    assert studentized_interval(v, 40.0, 3.0, np.full(101, 2.0)) == pytest.approx((40 - 29.25 * 3, 40 + 18.25 * 3))
    assert basic_interval([np.nan], 1.0) is None and studentized_interval(v, 40.0, 3.0, np.zeros(101)) is None


def test_bca_by_hand():
    """z0 from the share of draws below the estimate, a from the jackknife's skew, then the draws'
    quantiles at the moved levels; with z0 = a = 0 it is the percentile interval."""
    v = np.arange(1.0, 102.0)
    assert bca_interval(v, 51.0, [1.0, 2.0, 3.0]) == pytest.approx(percentile_interval(v))
    jk = np.array([1.0, 2.0, 3.0, 10.0])
    dev = jk.mean() - jk
    a = np.sum(dev ** 3) / (6 * np.sum(dev ** 2) ** 1.5)
    z0 = stats.norm.ppf((40 + 0.5) / 101)  # 40 draws below 41, one equal
    lv = stats.norm.cdf(z0 + (z0 + stats.norm.ppf([0.025, 0.975])) / (1 - a * (z0 + stats.norm.ppf([0.025, 0.975]))))
    assert bca_interval(v, 41.0, jk) == pytest.approx(tuple(np.percentile(v, 100 * lv)))
    assert bca_interval(v, 0.5, jk) is None  # every draw above the estimate: z0 infinite


def test_bca_matches_scipy_on_a_skewed_mean():
    """scipy.stats.bootstrap(method="BCa") on the mean of 25 exponential values against ours on our
    own 20 000 draws of the same statistic: the same interval within Monte Carlo error."""
    rng = np.random.default_rng(2)
    x = rng.exponential(1.0, 25)
    want = stats.bootstrap((x,), np.mean, n_resamples=20_000, method="BCa", random_state=3).confidence_interval
    draws = x[rng.integers(0, 25, (20_000, 25))].mean(axis=1)
    jack = (x.sum() - x) / 24
    lo, hi = bca_interval(draws, x.mean(), jack)
    width = want.high - want.low
    assert abs(lo - want.low) < 0.03 * width and abs(hi - want.high) < 0.03 * width
    # BCa moves a right-skewed mean's interval right of the percentile one
    p = percentile_interval(draws)
    assert lo > p[0] and hi > p[1]


def test_bootstrap_interval_dispatch():
    v = np.linspace(0, 1, 50)
    assert bootstrap_interval("percentile", v) == percentile_interval(v)
    assert bootstrap_interval("basic", v, 0.5) == basic_interval(v, 0.5)
    with pytest.raises(ValueError, match="interval must be one of"):
        bootstrap_interval("normal", v, 0.5)
    with pytest.raises(ValueError, match="jackknife"):
        bootstrap_interval("bca", v, 0.5)
    with pytest.raises(ValueError, match="se"):
        bootstrap_interval("studentized", v, 0.5)
    assert set(INTERVALS) == {"percentile", "basic", "bca", "studentized", "jackknife"}


def test_jackknife_interval_of_a_mean_is_the_t_interval():
    x = np.array([0.3, 1.2, -0.4, 2.5, 0.9, 1.1])
    half = stats.t.ppf(0.975, 5) * x.std(ddof=1) / math.sqrt(6)
    got = bootstrap_interval("jackknife", [], x.mean(), (x.sum() - x) / 5)
    assert got == pytest.approx((x.mean() - half, x.mean() + half))
    assert jackknife_t_interval(1.0, [0.5]) is None


def test_draw_jackknife_se_is_the_jackknife_of_each_draws_multiset():
    """Each row of counts is a multiset of sequences; its se is the plain jackknife of the mean over
    that multiset written out member by member."""
    x = np.array([0.3, 1.2, -0.4, 2.5, 0.9])

    def mean(counts):
        c = np.asarray(counts, float)
        return (c @ x / c.sum(axis=1))[:, None]

    counts = np.array([[2, 0, 1, 1, 1], [1, 1, 1, 1, 1], [5, 0, 0, 0, 0]])
    got = draw_jackknife_se(mean, counts)
    for row, se in zip(counts, got[:, 0]):
        members = np.repeat(x, row)
        loo = [(members.sum() - members[i]) / (len(members) - 1) for i in range(len(members))]
        want = jackknife_se(loo) if len(set(np.repeat(np.arange(5), row))) > 1 else np.nan
        assert se == pytest.approx(want, nan_ok=True)
    # the jackknife se of a mean is the textbook s / sqrt(n)
    assert jackknife_se((x.sum() - x) / 4) == pytest.approx(x.std(ddof=1) / math.sqrt(5))


def _small_problem():
    m = SyntheticDetection(frames_per_sequence=2)
    matches = m.sample(7, np.random.default_rng(4))
    by = {"fog": {f"s{j}": [2 * j, 2 * j + 1] for j in range(7)}}
    return matches, by


def test_map_intervals_percentile_is_the_studys_per_context_interval():
    """On one context, map_intervals' percentile interval is `percentile_interval(map_draws(...))`, the
    study's, to the last bit (same draws, same exact mAP), and the paired difference is the draws'."""
    matches, by = _small_problem()
    r = map_intervals(matches, by, 80, 9, INTERVALS, pairs=[("all_branches", "late")], keep_draws=True)
    draws = map_draws(matches, by, 80, 9)
    names = list(matches)
    assert r["intervals"]["percentile"]["late"] == percentile_interval(draws[:, names.index("late")])
    d = draws[:, names.index("all_branches")] - draws[:, names.index("late")]
    assert r["intervals"]["percentile"]["all_branches - late"] == pytest.approx(percentile_interval(d), abs=1e-12)
    assert r["estimate"]["late"] == pytest.approx(matches["late"].mean_ap(range(14)), abs=1e-12)
    for m in INTERVALS:
        lo, hi = r["intervals"][m]["late"]
        assert lo < hi
    with pytest.raises(ValueError, match="interval must be one of"):
        map_intervals(matches, by, 10, 0, ("normal",))


def test_ap_of_multiplicities_is_ap_of_the_draws():
    matches, _ = _small_problem()
    sc = DrawScorer(matches["late"])
    draws = [[0, 0, 3, 5], [1, 2, 13], list(range(14))]
    want = sc.ap(draws)
    got = sc.ap_of_multiplicities(sc.multiplicities(draws))
    for c in want:
        np.testing.assert_allclose(got[c], want[c], atol=1e-12)
    with pytest.raises(ValueError, match="multiplicities"):
        sc.ap_of_multiplicities(np.ones((2, 3)))


def test_trial_and_experiment_report_every_interval():
    m = SyntheticDetection(frames_per_sequence=2)
    t = trial(m, 5, 40, 1)
    assert set(t["quantities"]) == {"map:late", "difference:all_branches - late"}
    r = coverage_experiment(m, (4,), 3, 30, 0, studentized=False)
    cov = r["by_sequences"]["4"]["quantities"]["map:late"]["coverage"]
    assert set(cov) == {"percentile", "basic", "bca", "jackknife", "percentile_rescaled", "bca_rescaled"}
    assert all(c["trials"] == 3 for c in cov.values())
    assert r["truth"]["map:late"] == pytest.approx(m.true_map("late"))
    with pytest.raises(ValueError, match="sequences per context"):
        coverage_experiment(m, (1,), 3, 30)


def test_jackknife_p_value_agrees_with_its_interval():
    """p < 0.05 exactly when the jackknife-t interval excludes 0; for a mean it is the one-sample
    t-test's p-value."""
    rng = np.random.default_rng(6)
    for shift in (0.0, 0.3, 0.8, 1.5):
        x = rng.normal(shift, 1.0, 7)
        jk = (x.sum() - x) / 6
        p = jackknife_p_value(x.mean(), jk)
        assert p == pytest.approx(stats.ttest_1samp(x, 0.0).pvalue)
        lo, hi = jackknife_t_interval(x.mean(), jk)
        assert (p < 0.05) == (lo > 0 or hi < 0)
    assert math.isnan(jackknife_p_value(1.0, [0.5]))


def test_leave_one_out_rows_feed_the_jackknife_through_any_scorer():
    """The rows without each sequence, scored by the pooled mAP, are the jackknife map_intervals uses."""
    matches, by = _small_problem()
    loo = leave_one_out_rows(by["fog"])
    assert len(loo) == 7 and loo[0] == list(range(2, 14)) and loo[6] == list(range(12))
    r = map_intervals(matches, by, 20, 0, ("jackknife",))
    jk = [matches["late"].mean_ap(rows) for rows in loo]
    assert r["intervals"]["jackknife"]["late"] == pytest.approx(jackknife_t_interval(r["estimate"]["late"], jk))
    with pytest.raises(ValueError, match="2 sequences"):
        leave_one_out_rows({"s": [0, 1]})
