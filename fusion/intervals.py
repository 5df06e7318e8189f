"""Intervals that hold: draws of whole sequences within strata, how often an interval covers what
independent data estimate, and corrections for many comparisons at once.

A study's interval is only as good as its coverage. The check used here: split a large test set into
K disjoint test sets (or generate K of them), compute each set's 95 % interval of a difference
(gate minus late fusion, say) and ask whether it holds the estimate made from the other K-1 sets.
Even an exact interval does not hold that estimate 95 % of the time, since the rest's estimate is
noisy too: with set i's variance v_i and the rest's variance v_rest, the difference between set i's
estimate and the rest's has variance v_i + v_rest, so an exact normal 95 % interval of set i holds the
rest's estimate with probability ``2 Phi(1.96 sqrt(v_i / (v_i + v_rest))) - 1``; for 8 equal sets
(v_rest = v_i / 7) that is 0.933 (`expected_rest_coverage`). That, not 0.95, is what a correct
interval should reach; a coverage well below it means the interval is too narrow.

Multiple comparisons: a verdict that states an order in each of eight contexts makes eight tests; at
95 % each, about one in three verdicts of eight true nulls would claim some order by chance. `holm`
(family-wise error, Holm 1979) and `benjamini_hochberg` (false discovery rate, Benjamini and
Hochberg 1995) adjust the p-values of such a family; `bootstrap_p_value` turns a difference's
bootstrap draws into the p-value they imply.
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from fusion.metrics import DrawScorer, ImageMatches, sequence_draws

DESIGNS = ("sequence", "stratified", "rescaled")
"""How a test set's sequences are redrawn (`design_draws`): "sequence", whole sequences from all of
them (`fusion.metrics.sequence_draws`: the intervals the study and `compare` report); "stratified",
n_h of each context's n_h sequences; "rescaled", n_h - 1 of them (Rao and Wu 1988)."""


def stratified_sequence_draws(by_stratum: Mapping[Hashable, Mapping[Hashable, Sequence]], resamples: int,
                              seed: int, rescaled: bool = False):
    """Yield `resamples` draws of whole sequences with replacement, each stratum on its own: from
    each stratum {sequence: [items]} as many sequences as it holds (n_h), or n_h - 1 when `rescaled`,
    concatenated over the strata.

    A test set made of a fixed number of sequences per context is a stratified sample; drawing within
    each context reproduces that design (an unstratified draw also varies how many sequences of each
    context a draw holds, which the real test sets never do, and so widens the interval). Seeded: the
    same `seed` gives the same draws.

    Drawing n_h of n_h with replacement gives a mean the variance s_h^2 (n_h - 1) / n_h^2, (n_h - 1) /
    n_h of the design's s_h^2 / n_h: with 6 sequences of a context that is 0.83, and a 95 % interval
    that is 9 % too narrow. `rescaled` draws m_h = n_h - 1 (Rao and Wu 1988, "Resampling inference
    with complex survey data", JASA 83, with m_h = n_h - 1; McCarthy and Snowden 1985's BWR), whose
    mean has exactly the design's variance s_h^2 / n_h. Rao and Wu also rescale the weights of stratum
    h by n_h / (n_h - 1); when every stratum holds the same n_h (the study's test sets, and the sets a
    coverage check deals from them) that is one constant, which a pooled AP does not see, so the draw
    itself is the whole method. With unequal n_h a stratum's share of a draw moves from n_h / N to
    (n_h - 1) / (N - H) (7 against 6 sequences: 3 % relative), which is left as it is. A stratum of
    one sequence is drawn once (it has no variance to estimate either way).
    """
    if resamples < 1:
        raise ValueError(f"resamples must be >= 1, got {resamples!r}")
    strata = [sorted(by_stratum[s]) for s in sorted(by_stratum, key=str)]
    members = [[by_stratum[s][q] for q in seqs] for s, seqs in zip(sorted(by_stratum, key=str), strata)]
    if any(not seqs for seqs in strata):
        raise ValueError("stratified_sequence_draws: a stratum holds no sequence")
    rng = np.random.default_rng(seed)
    for _ in range(resamples):
        draw = []
        for items in members:
            m = len(items) - 1 if rescaled and len(items) > 1 else len(items)
            for j in rng.integers(0, len(items), m):
                draw.extend(items[j])
        yield draw


def design_draws(by_stratum: Mapping[Hashable, Mapping[Hashable, Sequence]], resamples: int, seed: int,
                 design: str = "sequence"):
    """Draws of whole sequences by one of `DESIGNS` from {stratum: {sequence: [items]}}: "sequence"
    pools every stratum's sequences and draws as many as there are (`fusion.metrics.sequence_draws`;
    sequence keys must then be unique across strata), "stratified" and "rescaled" draw within each
    stratum (`stratified_sequence_draws`)."""
    if design not in DESIGNS:
        raise ValueError(f"design must be one of {DESIGNS}, got {design!r}")
    if design != "sequence":
        return stratified_sequence_draws(by_stratum, resamples, seed, rescaled=design == "rescaled")
    if resamples < 1:
        raise ValueError(f"resamples must be >= 1, got {resamples!r}")
    pooled: dict = {}
    for s in sorted(by_stratum, key=str):
        for q, items in by_stratum[s].items():
            if q in pooled:
                raise ValueError(f"design_draws: sequence {q!r} is in more than one stratum")
            pooled[q] = items
    if not pooled:
        raise ValueError("design_draws: no sequence to draw")
    return sequence_draws(pooled, resamples, seed)


SCORINGS = ("weighted", "pooled")
"""How `map_draws` scores a draw: "weighted", the detections ranked once and each draw a weighting
of them (`fusion.metrics.DrawScorer`); "pooled", each draw's detections pooled and ranked again
(`fusion.metrics.ImageMatches.mean_ap`), the reference the weighted scoring is tested against."""


def map_draws(matches: Mapping[str, ImageMatches], by_stratum: Mapping[Hashable, Mapping[Hashable, Sequence]],
              resamples: int, seed: int, design: str = "sequence", scoring: str = "weighted",
              scorers: Mapping[str, DrawScorer] | None = None) -> np.ndarray:
    """(resamples, sources) each source's mAP on each draw of whole sequences (`design_draws` over
    {stratum: {sequence: [image rows]}}, seeded), every source on the same draws (paired).
    `scoring`: one of `SCORINGS`, equal to 1e-12; `scorers`: `DrawScorer`s already built for
    `matches` (one ranking serves every group of one set of images)."""
    if scoring not in SCORINGS:
        raise ValueError(f"scoring must be one of {SCORINGS}, got {scoring!r}")
    names = list(matches)
    draws = list(design_draws(by_stratum, resamples, seed, design))
    out = np.empty((len(draws), len(names)))
    for i, n in enumerate(names):
        if scoring == "pooled":
            out[:, i] = [matches[n].mean_ap(d) for d in draws]
        else:
            scorer = scorers[n] if scorers is not None else DrawScorer(matches[n])
            out[:, i] = scorer.mean_ap(draws)
    return out


def resolved_sign(interval) -> int:
    """+1 / -1 when an interval excludes 0 above / below, 0 when it holds 0 (or is missing): the order a
    difference's interval resolves."""
    if not interval or interval[0] is None or interval[1] is None:
        return 0
    return 1 if interval[0] > 0 else -1 if interval[1] < 0 else 0


def percentile_interval(values, level: float = 0.95) -> tuple[float, float] | None:
    """The central `level` percentile interval of the finite values (None when none is finite)."""
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level!r}")
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if not len(v):
        return None
    tail = 50.0 * (1.0 - level)
    return float(np.percentile(v, tail)), float(np.percentile(v, 100.0 - tail))


INTERVALS = ("percentile", "basic", "bca", "studentized", "jackknife")
"""How `bootstrap_interval` turns draws of a statistic into an interval (Davison and Hinkley 1997,
Ch. 5; Efron and Tibshirani 1993, Ch. 12-14): "percentile", the draws' central quantiles;
"basic", those quantiles reflected about the estimate (2 theta_hat - q), which removes the bias the
draws show once; "bca", the percentile levels moved by the draws' median bias z0 and the jackknife's
acceleration a; "studentized", the estimate minus quantiles of the draws' t = (theta* - theta_hat) /
se*, scaled by the estimate's own standard error (each draw's se from a jackknife inside it);
"jackknife", no draws at all: the estimate plus or minus Student's t with n - 1 degrees of freedom
times the jackknife standard error over the n units (for a mean, exactly the t-interval)."""


def basic_interval(values, estimate: float, level: float = 0.95) -> tuple[float, float] | None:
    """The basic (reflected percentile) interval ``(2 theta_hat - q_hi, 2 theta_hat - q_lo)`` of the
    finite draws around `estimate` (None when none is finite or the estimate is not finite)."""
    q = percentile_interval(values, level)
    if q is None or not math.isfinite(estimate):
        return None
    return 2.0 * estimate - q[1], 2.0 * estimate - q[0]


def bca_interval(values, estimate: float, jackknife, level: float = 0.95) -> tuple[float, float] | None:
    """Efron's bias-corrected and accelerated interval (Efron 1987; Efron and Tibshirani 1993, Eq.
    14.9-14.15) of the finite draws `values` around `estimate`, with `jackknife` the statistic with
    each unit (sequence) left out once:

        z0 = Phi^-1( (#(theta* < theta_hat) + #(theta* = theta_hat) / 2) / B )
        a  = sum (m - theta_(i))^3 / (6 (sum (m - theta_(i))^2)^(3/2)),  m = mean theta_(i)
        level_k = Phi( z0 + (z0 + z_k) / (1 - a (z0 + z_k)) ),  z_k = Phi^-1(alpha/2), Phi^-1(1 - alpha/2)

    and the interval is the draws' quantiles at those two levels. Ties count half (so a statistic
    whose draws often equal the estimate is not pushed aside); a is 0 when the jackknife values are
    all equal (or fewer than 2 finite); None when no draw is finite, every draw lies on one side of
    the estimate (z0 infinite) or the estimate is not finite. scipy.stats.bootstrap(method="BCa")
    computes the same (tested)."""
    from scipy.stats import norm

    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level!r}")
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if not len(v) or not math.isfinite(estimate):
        return None
    share = (np.sum(v < estimate) + 0.5 * np.sum(v == estimate)) / len(v)
    if not 0.0 < share < 1.0:
        return None
    z0 = float(norm.ppf(share))
    jk = np.asarray(jackknife, dtype=float)
    jk = jk[np.isfinite(jk)]
    a = 0.0
    if len(jk) >= 2:
        dev = jk.mean() - jk
        ss = float(np.sum(dev ** 2))
        a = float(np.sum(dev ** 3)) / (6.0 * ss ** 1.5) if ss > 0 else 0.0
    z = norm.ppf([0.5 - level / 2.0, 0.5 + level / 2.0])
    levels = norm.cdf(z0 + (z0 + z) / (1.0 - a * (z0 + z)))
    lo, hi = np.percentile(v, 100.0 * levels)
    return float(lo), float(hi)


def studentized_interval(values, estimate: float, se: float, draw_se, level: float = 0.95) -> tuple[float, float] | None:
    """The bootstrap-t interval: t*_b = (theta*_b - theta_hat) / se*_b over the draws with a finite,
    positive se*_b, and ``(theta_hat - q_hi(t*) se, theta_hat - q_lo(t*) se)`` with `se` the
    estimate's standard error (Efron and Tibshirani 1993, Eq. 12.22). None when no draw has a t."""
    v, s = np.asarray(values, dtype=float), np.asarray(draw_se, dtype=float)
    if v.shape != s.shape:
        raise ValueError(f"studentized_interval: {v.shape} draws but {s.shape} standard errors")
    ok = np.isfinite(v) & np.isfinite(s) & (s > 0)
    if not ok.any() or not (math.isfinite(estimate) and math.isfinite(se)):
        return None
    q = percentile_interval((v[ok] - estimate) / s[ok], level)
    return estimate - q[1] * se, estimate - q[0] * se


def jackknife_se(values) -> float:
    """The jackknife standard error ``sqrt((n - 1) / n sum (theta_(i) - mean)^2)`` of leave-one-out
    values (NaN with fewer than 2 finite)."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if len(v) < 2:
        return float("nan")
    return float(math.sqrt((len(v) - 1) / len(v) * np.sum((v - v.mean()) ** 2)))


def jackknife_t_interval(estimate: float, jackknife, level: float = 0.95) -> tuple[float, float] | None:
    """``theta_hat -+ t_{n-1, (1 + level) / 2} se_jack`` over the n finite leave-one-out values
    (Efron and Tibshirani 1993, Ch. 11; for a mean it is Student's t-interval); None with fewer than
    2 or a non-finite estimate."""
    from scipy.stats import t

    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level!r}")
    jk = np.asarray(jackknife, dtype=float)
    n = int(np.isfinite(jk).sum())
    se = jackknife_se(jk)
    if n < 2 or not (math.isfinite(estimate) and math.isfinite(se)):
        return None
    half = float(t.ppf(0.5 + level / 2.0, n - 1)) * se
    return estimate - half, estimate + half


def jackknife_p_value(estimate: float, jackknife) -> float:
    """Two-sided p-value of "the statistic is 0" that matches `jackknife_t_interval`: ``2 (1 -
    F_{t, n-1}(|theta_hat| / se_jack))``, so p < 1 - level exactly when that interval excludes 0 (NaN
    with fewer than 2 finite values; 0 when se is 0 and the estimate is not)."""
    from scipy.stats import t

    jk = np.asarray(jackknife, dtype=float)
    n = int(np.isfinite(jk).sum())
    se = jackknife_se(jk)
    if n < 2 or not (math.isfinite(estimate) and math.isfinite(se)):
        return float("nan")
    if se == 0:
        return 1.0 if estimate == 0 else 0.0
    return float(2.0 * t.sf(abs(estimate) / se, n - 1))


def leave_one_out_rows(rows_by_sequence: Mapping[Hashable, Sequence[int]]) -> list[list[int]]:
    """For each sequence of {sequence: [rows]} in sorted order, the rows of all the others (in the
    same order): the jackknife's "draws", to pass where a bootstrap takes draws of rows
    (`fusion.bounds.bootstrap_table(..., draws=...)`), so derived statistics are recomputed too."""
    seqs = sorted(rows_by_sequence)
    if len(seqs) < 2:
        raise ValueError("leave_one_out_rows: needs at least 2 sequences")
    return [[r for q in seqs if q != left for r in rows_by_sequence[q]] for left in seqs]


def bootstrap_interval(method: str, values, estimate: float | None = None, jackknife=None, se: float | None = None,
                       draw_se=None, level: float = 0.95) -> tuple[float, float] | None:
    """The `level` interval of draws `values` by one of `INTERVALS`; "basic" needs the `estimate`,
    "bca" the estimate and the `jackknife` values, "studentized" the estimate, its `se` and each
    draw's `draw_se`."""
    if method not in INTERVALS:
        raise ValueError(f"interval must be one of {INTERVALS}, got {method!r}")
    if method != "percentile" and estimate is None:
        raise ValueError(f"a {method!r} interval needs the estimate")
    if method == "percentile":
        return percentile_interval(values, level)
    if method == "basic":
        return basic_interval(values, estimate, level)
    if method in ("bca", "jackknife"):
        if jackknife is None:
            raise ValueError(f"a {method!r} interval needs the jackknife values")
        return (bca_interval(values, estimate, jackknife, level) if method == "bca"
                else jackknife_t_interval(estimate, jackknife, level))
    if se is None or draw_se is None:
        raise ValueError("a 'studentized' interval needs the estimate's se and each draw's se")
    return studentized_interval(values, estimate, se, draw_se, level)


def _nanmean_rows(table: np.ndarray) -> np.ndarray:
    """Mean of each row's finite entries (NaN when none): a draw's mAP over the classes it holds."""
    fin = np.isfinite(table)
    k = fin.sum(axis=1)
    return np.divide(np.where(fin, table, 0.0).sum(axis=1), k, out=np.full(len(table), np.nan), where=k > 0)


class SequenceStatistic:
    """Each source's mAP (`DrawScorer`, exact) on weightings of whole sequences: rows of `counts`
    (draws, sequences) say how often each of `sequences` (a list of image-row lists) is taken."""

    def __init__(self, matches: Mapping[str, ImageMatches], sequences: Sequence[Sequence[int]],
                 scorers: Mapping[str, DrawScorer] | None = None) -> None:
        self.names = list(matches)
        self.scorers = {n: scorers[n] if scorers is not None else DrawScorer(matches[n]) for n in self.names}
        n_images = len(matches[self.names[0]].per_image)
        self.incidence = np.zeros((len(sequences), n_images), np.int64)  # sequence x image
        for j, rows in enumerate(sequences):
            np.add.at(self.incidence[j], np.asarray(rows, np.int64), 1)

    def class_ap(self, name: str, counts: np.ndarray) -> np.ndarray:
        """(rows, classes) AP of each class of `name` (NaN where a row holds none of its ground truth)."""
        per = self.scorers[name].ap_of_multiplicities(np.asarray(counts, np.int64) @ self.incidence)
        return np.stack([per[c] for c in self.scorers[name].classes], axis=1)

    def __call__(self, counts: np.ndarray) -> np.ndarray:
        """(rows, sources) mAP over the classes each row holds, as `DrawScorer.mean_ap`."""
        with np.errstate(invalid="ignore"):
            return np.stack([_nanmean_rows(self.class_ap(n, counts)) for n in self.names], axis=1)


def draw_jackknife_se(statistic, counts: np.ndarray) -> np.ndarray:
    """(draws, columns) each draw's jackknife standard error inside it: one copy of each of its
    members left out in turn, ``sqrt((N - 1) / N sum_j k_j (theta_(j) - mean_k)^2)`` over its N members
    (k_j copies of sequence j, mean_k the k-weighted mean). `statistic(counts) -> (rows, columns)`.
    NaN where fewer than 2 distinct members have a finite value."""
    counts = np.asarray(counts, np.int64)
    owner, member = np.nonzero(counts)
    rows = counts[owner].copy()
    rows[np.arange(len(owner)), member] -= 1
    values = np.asarray(statistic(rows), float).reshape(len(owner), -1)
    weight = counts[owner, member].astype(float)
    out = np.full((len(counts), values.shape[1]), np.nan)
    for col in range(values.shape[1]):
        x = values[:, col]
        ok = np.isfinite(x)
        w, xs = np.where(ok, weight, 0.0), np.where(ok, x, 0.0)
        n = np.bincount(owner, w, len(counts))  # members with a finite value
        distinct = np.bincount(owner, ok.astype(float), len(counts))
        m = np.divide(np.bincount(owner, w * xs, len(counts)), n, out=np.zeros(len(counts)), where=n > 0)
        ss = np.bincount(owner, w * (xs - m[owner]) ** 2, len(counts))
        good = distinct >= 2
        out[good, col] = np.sqrt((n[good] - 1) / n[good] * ss[good])
    return out


def map_intervals(matches: Mapping[str, ImageMatches], by_stratum: Mapping[Hashable, Mapping[Hashable, Sequence]],
                  resamples: int, seed: int, methods: Sequence[str] = ("percentile",), design: str = "sequence",
                  pairs: Sequence[tuple[str, str]] = (), scorers: Mapping[str, DrawScorer] | None = None,
                  level: float = 0.95, keep_draws: bool = False) -> dict:
    """Each source's mAP and each pair's paired difference (a minus b) on the images of `by_stratum`
    {stratum: {sequence: [image rows]}}, with a `level` interval by each of `methods` (`INTERVALS`)
    from the same `resamples` draws of whole sequences (`design_draws`, seeded). BCa's jackknife and
    the studentized interval's standard errors leave one sequence out (of the estimate, and of every
    draw: about 0.63 x sequences extra scorings per draw, "studentized" only).

    Returns {"estimate": {name or "a - b": value}, "intervals": {method: {name or "a - b": (lo, hi)
    or None}}, "sequences": n}; with `keep_draws` also "columns", "draws" (resamples, columns), "counts"
    (resamples, sequences) and the `SequenceStatistic` under "statistic"."""
    bad = [m for m in methods if m not in INTERVALS]
    if bad:
        raise ValueError(f"interval must be one of {INTERVALS}, got {bad[0]!r}")
    keys = [(s, q) for s in sorted(by_stratum, key=str) for q in sorted(by_stratum[s])]  # design_draws' order
    if not keys:
        raise ValueError("map_intervals: no sequence")
    index = {k: j for j, k in enumerate(keys)}
    stat = SequenceStatistic(matches, [by_stratum[s][q] for s, q in keys], scorers)
    strata = {s: {index[(s, q)]: [index[(s, q)]] for q in by_stratum[s]} for s in by_stratum}  # indices: unique
    n = len(keys)
    counts = np.stack([np.bincount(np.asarray(d, np.int64), minlength=n)
                       for d in design_draws(strata, resamples, seed, design)])
    names = stat.names
    cols = list(names) + [f"{a} - {b}" for a, b in pairs]

    def columns(c):
        v = stat(c)
        return np.concatenate([v, np.stack([v[:, names.index(a)] - v[:, names.index(b)] for a, b in pairs], axis=1)],
                              axis=1) if pairs else v

    est = columns(np.ones((1, n), np.int64))[0]
    draws = columns(counts)
    jack = columns(np.ones((n, n), np.int64) - np.eye(n, dtype=np.int64)) if n > 1 else None
    tse = draw_jackknife_se(columns, counts) if "studentized" in methods and n > 2 else None
    out = {"estimate": {k: float(e) for k, e in zip(cols, est)}, "intervals": {}, "sequences": n}
    for m in methods:
        rec = out["intervals"][m] = {}
        for i, k in enumerate(cols):
            if m in ("bca", "studentized", "jackknife") and jack is None or m == "studentized" and tse is None:
                rec[k] = None
                continue
            rec[k] = bootstrap_interval(m, draws[:, i], float(est[i]), None if jack is None else jack[:, i],
                                        jackknife_se(jack[:, i]) if jack is not None else None,
                                        None if tse is None else tse[:, i], level)
    if keep_draws:
        out.update(columns=cols, draws=draws, counts=counts, statistic=stat)
    return out


def bootstrap_p_value(draws) -> float:
    """Two-sided p-value of "the difference is 0" from bootstrap draws of a difference:
    ``min(1, 2 min(#(d <= 0) + 1, #(d >= 0) + 1) / (B + 1))`` over the B finite draws (the +1 keeps
    a p-value of 0 from a finite number of draws; Davison and Hinkley 1997, Eq. 4.11). A difference
    whose 95 % percentile interval excludes 0 has p < 0.05 up to that +1."""
    d = np.asarray(draws, dtype=float)
    d = d[np.isfinite(d)]
    if not len(d):
        return float("nan")
    below, above = int(np.sum(d <= 0)), int(np.sum(d >= 0))
    return min(1.0, 2.0 * min(below + 1, above + 1) / (len(d) + 1))


def holm(pvalues: Sequence[float]) -> np.ndarray:
    """Holm's step-down adjusted p-values (family-wise error): sort ascending, p_(j) x (m - j + 1)
    (j from 1), running maximum, capped at 1; returned in the input's order. NaN stays NaN and does
    not count towards m."""
    return _adjust(pvalues, lambda sorted_p, m: np.maximum.accumulate(sorted_p * (m - np.arange(m))))


def benjamini_hochberg(pvalues: Sequence[float]) -> np.ndarray:
    """Benjamini-Hochberg adjusted p-values (false discovery rate): sort ascending,
    p_(j) x m / j, running minimum from the largest down, capped at 1; in the input's order. NaN
    stays NaN and does not count towards m (scipy's `false_discovery_control` on the finite ones)."""
    return _adjust(pvalues, lambda sorted_p, m: np.minimum.accumulate((sorted_p * m / np.arange(1, m + 1))[::-1])[::-1])


def _adjust(pvalues: Sequence[float], step) -> np.ndarray:
    """Apply `step(sorted finite p-values, m)` to the finite p-values in ascending order, cap at 1,
    and return them in the input's order (NaN where the input is not finite)."""
    p = np.asarray(pvalues, dtype=float)
    out = np.full_like(p, np.nan)
    ok = np.flatnonzero(np.isfinite(p))
    if len(ok):
        order = ok[np.argsort(p[ok], kind="stable")]
        out[order] = np.minimum(1.0, step(p[order], len(ok)))
    return out


CORRECTIONS = {"holm": holm, "bh": benjamini_hochberg, "none": lambda p: np.asarray(p, dtype=float)}


def expected_rest_coverage(sizes: Sequence[float], level: float = 0.95) -> np.ndarray:
    """Per set, the probability that an exact normal `level` interval of set i holds the estimate of
    the other sets pooled, when a set's variance is proportional to 1 / its size (sequences):
    ``2 Phi(z sqrt(v_i / (v_i + v_rest))) - 1`` with v_i = 1 / n_i, v_rest = 1 / sum_{j != i} n_j."""
    from scipy.stats import norm

    n = np.asarray(sizes, dtype=float)
    if len(n) < 2 or np.any(n <= 0):
        raise ValueError("expected_rest_coverage: needs at least 2 sets of positive size")
    z = norm.ppf(0.5 + level / 2.0)
    v_i, v_rest = 1.0 / n, 1.0 / (n.sum() - n)
    return 2.0 * norm.cdf(z * np.sqrt(v_i / (v_i + v_rest))) - 1.0


@dataclass(frozen=True)
class Coverage:
    """How often each disjoint test set's interval held the estimate of the rest of the data.

    covered[i]: set i's interval holds rest[i]; coverage: their share; expected: the share an exact
    interval would reach (`expected_rest_coverage`, mean over the sets); level: the intervals' nominal
    level.
    """

    intervals: tuple
    rest: tuple
    covered: tuple
    coverage: float
    expected: float
    level: float

    def as_dict(self) -> dict:
        return {"sets": len(self.covered), "covered": int(sum(self.covered)), "coverage": self.coverage,
                "expected_if_exact": self.expected, "level": self.level,
                "per_set": [{"interval": list(iv) if iv is not None else None, "rest": r, "covered": c}
                            for iv, r, c in zip(self.intervals, self.rest, self.covered)]}


def leave_one_out_means(estimates: Sequence[float], weights: Sequence[float]) -> np.ndarray:
    """For each set, the weighted mean of the other sets' estimates (weights: their sizes). Where a
    statistic is not a mean of its sets (a pooled AP), pass the rest's own estimate to `coverage`
    instead."""
    e, w = np.asarray(estimates, dtype=float), np.asarray(weights, dtype=float)
    if e.shape != w.shape or len(e) < 2:
        raise ValueError("leave_one_out_means: needs as many weights as estimates, at least 2")
    return ((e * w).sum() - e * w) / (w.sum() - w)


def coverage(intervals: Sequence, rest: Sequence[float], sizes: Sequence[float], level: float = 0.95) -> Coverage:
    """`Coverage` of per-set `intervals` [(lo, hi) or None] against the rest's estimates `rest`
    (`sizes`: each set's number of sequences, for the expected share). A set without an interval
    counts as not covering."""
    if not (len(intervals) == len(rest) == len(sizes)) or len(intervals) < 2:
        raise ValueError("coverage: needs one interval, rest estimate and size per set, at least 2 sets")
    covered = tuple(bool(iv is not None and math.isfinite(r) and iv[0] <= r <= iv[1])
                    for iv, r in zip(intervals, rest))
    return Coverage(intervals=tuple(None if iv is None else (float(iv[0]), float(iv[1])) for iv in intervals),
                    rest=tuple(float(r) for r in rest), covered=covered,
                    coverage=float(np.mean(covered)), expected=float(np.mean(expected_rest_coverage(sizes, level))),
                    level=float(level))
