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
