"""Do the study's intervals hold? Split a large test set into disjoint test sets and count how often
each set's 95 % interval of a difference (gate minus late fusion, all_branches minus late) holds the
estimate from the rest of the data (`fusion.intervals.coverage`; an exact interval reaches about
0.933 with 8 equal sets, not 0.95: see there).

The sets are dealt by sequence within each context (seeded), so every set is a smaller test set of
the same design (the same share of each context); a set's interval is a sequence bootstrap run on
that set alone, by one of `fusion.intervals.DESIGNS`: "sequence" (the default), whole sequences from
all of the set's, the bootstrap whose intervals the study and `compare` report, so the check checks
the interval a reader is shown; "stratified", n_h of each context's n_h; "rescaled", n_h - 1 of them
(Rao and Wu). The rest's estimate is the difference scored on the pooled frames of the other sets (AP
is not a mean of its sets' APs).
Besides the coverage, the spread of the sets' estimates against the bootstrap's standard error says
the same thing in one number (about 1 when the bootstrap's width is right).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from fusion.intervals import DESIGNS, coverage, design_draws, percentile_interval
from fusion.metrics import ImageMatches


def deal_sets(contexts: Sequence[str], sequences: Sequence[str], n_sets: int, seed: int = 0) -> list[list[int]]:
    """Rows (frames) of each of `n_sets` disjoint sets: each context's sequences shuffled (seeded) and
    dealt in turn, so the sets hold the same number of sequences of a context, give or take one."""
    if n_sets < 2:
        raise ValueError(f"n_sets must be >= 2, got {n_sets!r}")
    if len(contexts) != len(sequences):
        raise ValueError("deal_sets: one context and one sequence per row")
    rows_of: dict[tuple[str, str], list[int]] = {}
    for r, (c, s) in enumerate(zip(contexts, sequences)):
        rows_of.setdefault((str(c), str(s)), []).append(r)
    rng = np.random.default_rng(seed)
    sets: list[list[int]] = [[] for _ in range(n_sets)]
    turn = 0  # carries over contexts, so a context with fewer sequences than sets does not always fill set 0
    for ctx in sorted({c for c, _ in rows_of}):
        seqs = sorted(s for c, s in rows_of if c == ctx)
        for j in rng.permutation(len(seqs)):
            sets[turn % n_sets].extend(rows_of[(ctx, seqs[j])])
            turn += 1
    if any(not s for s in sets):
        raise ValueError(f"deal_sets: {len({s for _, s in rows_of})} sequences cannot fill {n_sets} sets")
    return [sorted(s) for s in sets]


def _strata(rows: Sequence[int], contexts, sequences) -> dict:
    by: dict = {}
    for r in rows:
        by.setdefault(str(contexts[r]), {}).setdefault(str(sequences[r]), []).append(r)
    return by


def _difference(matches: Mapping[str, ImageMatches], a: str, b: str, rows) -> float:
    return matches[a].mean_ap(rows) - matches[b].mean_ap(rows)


def set_draws(matches: Mapping[str, ImageMatches], a: str, b: str, rows, contexts, sequences,
              resamples: int, seed: int, design: str = "sequence") -> np.ndarray:
    """`resamples` bootstrap draws of mAP(a) - mAP(b) over the sequences of `rows`, by `design`
    (`fusion.intervals.design_draws`)."""
    draws = design_draws(_strata(rows, contexts, sequences), resamples, seed, design)
    return np.array([_difference(matches, a, b, d) for d in draws])


def coverage_over_sets(matches: Mapping[str, ImageMatches], contexts: Sequence[str], sequences: Sequence[str],
                       pairs: Sequence[tuple[str, str]], n_sets: int = 8, resamples: int = 200, seed: int = 0,
                       design: str = "sequence", level: float = 0.95) -> dict:
    """Per pair (a, b): each disjoint set's estimate and interval of mAP(a) - mAP(b), the rest's
    estimate, the coverage (`fusion.intervals.Coverage.as_dict`) and the spread ratio (standard
    deviation of the sets' estimates over the mean bootstrap standard error)."""
    sets = deal_sets(contexts, sequences, n_sets, seed)
    sizes = [len({sequences[r] for r in s}) for s in sets]
    everything = sorted(r for s in sets for r in s)
    if design not in DESIGNS:
        raise ValueError(f"design must be one of {DESIGNS}, got {design!r}")
    out = {"sets": n_sets, "sequences_per_set": sizes, "design": design, "resamples": resamples,
           "pairs": {}}
    for a, b in pairs:
        estimates, intervals, rest, ses = [], [], [], []
        for i, rows in enumerate(sets):
            d = set_draws(matches, a, b, rows, contexts, sequences, resamples, seed + 1 + i, design)
            estimates.append(_difference(matches, a, b, rows))
            intervals.append(percentile_interval(d, level))
            ses.append(float(np.nanstd(d)))
            others = sorted(set(everything) - set(rows))
            rest.append(_difference(matches, a, b, others))
        cov = coverage(intervals, rest, sizes, level)
        spread = float(np.std(estimates, ddof=1))
        out["pairs"][f"{a} - {b}"] = {**cov.as_dict(), "estimates": [float(e) for e in estimates],
                                      "all": _difference(matches, a, b, everything),
                                      "spread_over_se": spread / float(np.mean(ses)) if np.mean(ses) > 0 else None}
    return out


def coverage_over_deals(matches: Mapping[str, ImageMatches], contexts: Sequence[str], sequences: Sequence[str],
                        pairs: Sequence[tuple[str, str]], n_sets: int = 8, deals: int = 10, resamples: int = 200,
                        seed: int = 0, designs: Sequence[str] = ("sequence",), level: float = 0.95,
                        progress: bool = False) -> dict:
    """`coverage_over_sets` over `deals` independent deals of the test set into `n_sets` sets (deal
    seeds seed .. seed + deals - 1), once per bootstrap design in `designs` (the same deals and draw
    seeds for each), pooled per design and pair: sets covered of all sets dealt, the rate, the rate an
    exact interval reaches (as one deal's), the mean spread ratio and the mean width of a set's
    interval. One deal of 8 sets says little (6 of 8 happens one time in 9 with exact intervals); many
    deals of the same test set are not independent either (they reuse its sequences), but they tell a
    deal's bad luck from an interval that is too narrow on this test set."""
    from sim.progress import progress as progress_bar

    designs = list(dict.fromkeys(designs))
    if not designs or any(d not in DESIGNS for d in designs):
        raise ValueError(f"designs must be some of {DESIGNS}, got {designs!r}")
    per: dict = {d: {} for d in designs}
    first = None
    bar = progress_bar(total=deals * len(designs), desc="coverage over deals", unit="deal", enabled=progress)
    for d in range(deals):
        for design in designs:
            one = coverage_over_sets(matches, contexts, sequences, pairs, n_sets, resamples, seed + d, design, level)
            first = first or one
            for name, v in one["pairs"].items():
                per[design].setdefault(name, []).append(v)
            bar.update(1)
    bar.close()
    out = {"deals": deals, "sets": n_sets, "sequences_per_set": first["sequences_per_set"] if first else [],
           "resamples": resamples, "level": level, "designs": {}}
    for design, by_pair in per.items():
        rec = out["designs"][design] = {"pairs": {}}
        for name, vs in by_pair.items():
            covered, sets = sum(v["covered"] for v in vs), sum(v["sets"] for v in vs)
            ratios = [v["spread_over_se"] for v in vs if v["spread_over_se"] is not None]
            widths = [p["interval"][1] - p["interval"][0] for v in vs for p in v["per_set"] if p["interval"]]
            rec["pairs"][name] = {"covered": covered, "sets": sets, "coverage": covered / sets if sets else None,
                                  "expected_if_exact": vs[0]["expected_if_exact"],
                                  "covered_per_deal": [v["covered"] for v in vs],
                                  "spread_over_se_mean": float(np.mean(ratios)) if ratios else None,
                                  "mean_width": float(np.mean(widths)) if widths else None,
                                  "all": vs[0]["all"]}
    return out
