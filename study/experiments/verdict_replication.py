"""Does a verdict replicate? Two study reports of the same design scored on independent test sets (the
same detectors; the gates trained again on the same gate set, possibly on another CPU), compared
pair by pair and context by context.

Per (pair of methods, context) each report holds the mAP difference a - b and its 95 % sequence-
bootstrap interval. On independent test sets the two estimates are independent; their difference
has a 95 % interval of half-width about sqrt(h_a^2 + h_b^2) (normal approximation, as
`study.experiments.crossover_replication`). If the intervals are as wide as they should be, |d_a - d_b| stays
inside it about 95 % of the time: the *agreement rate* checks the intervals on an independent test
set (the pairs share methods, so they are not independent draws: a rate over many correlated pairs
is less sure than its count says). Beside it: of the pairs one report resolves (its interval excludes
0), how many the other resolves the same way, and how many the opposite way (a contradiction).

The headline pairs (`HEADLINE`, overall) are listed one by one, with each report's estimate and
interval and whether each estimate lies in the other's interval. A method missing from either report
(a study run without early fusion, say) is left out of every count.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

from fusion.intervals import resolved_sign

HEADLINE = (
    ("all_branches", "late"),
    ("hydrafusion:deep", "late"),
    ("hydrafusion:attention", "late"),
    ("ecofusion:deep", "late"),
    ("ecofusion:attention", "late"),
    ("physical_gate", "late"),
    ("hydrafusion:deep", "all_branches"),
    ("hydrafusion:attention", "all_branches"),
    ("ecofusion:attention", "all_branches"),
    ("physical_gate", "all_branches"),
    ("physical_gate", "hydrafusion:knowledge"),
    ("late", "single:lidar"),
    ("late", "single:radar"),
)
"""The pairs the README block and the closing notes quote, as (a, b) for a - b."""


def pair_difference(results: Mapping, a: str, b: str, context: str = "all") -> tuple[float, list[float]] | None:
    """(estimate, 95 % interval) of mAP(a) - mAP(b) in `context` ("all": overall) from a report's
    `results`, or None when either method or the interval is missing. The report keeps one order per
    pair; the other is its negative."""
    methods = results.get("methods") or {}
    per = ((results.get("intervals") or {}).get("per_context") or {}).get(context) or {}
    diff = per.get("difference") or {}
    if a not in methods or b not in methods:
        return None
    if f"{a} - {b}" in diff:
        iv = list(diff[f"{a} - {b}"])
    elif f"{b} - {a}" in diff:
        lo, hi = diff[f"{b} - {a}"]
        iv = [-hi, -lo]
    else:
        return None

    def score(m):
        return m.get("map") if context == "all" else (m.get("map_per_context") or {}).get(context)

    sa, sb = score(methods[a]), score(methods[b])
    if sa is None or sb is None:
        return None
    return round(sa - sb, 6), iv


def _inside(x: float, interval) -> bool:
    return interval[0] <= x <= interval[1]


def compare_pair(ra: Mapping, rb: Mapping, a: str, b: str, context: str = "all") -> dict | None:
    """One pair in one context in both reports: the estimates, intervals, their agreement (module doc),
    each estimate inside the other's interval, and how each resolves; None when either lacks it."""
    da, db = pair_difference(ra, a, b, context), pair_difference(rb, a, b, context)
    if da is None or db is None:
        return None
    (ea, ia), (eb, ib) = da, db
    half = math.hypot((ia[1] - ia[0]) / 2, (ib[1] - ib[0]) / 2)
    return {"pair": f"{a} - {b}", "context": context, "a": ea, "interval_a": ia, "b": eb, "interval_b": ib,
            "difference": round(ea - eb, 6), "half_width": round(half, 6), "agree": abs(ea - eb) <= half,
            "b_in_a": _inside(eb, ia), "a_in_b": _inside(ea, ib), "resolved_a": resolved_sign(ia), "resolved_b": resolved_sign(ib)}


def replicate(ra: Mapping, rb: Mapping) -> dict:
    """Compare two reports' `results` (module doc): every pair of methods both hold, in every context
    both hold; the headline pairs overall; the gates' kept objectives and the physical gate's rules."""
    pa = ((ra.get("intervals") or {}).get("per_context") or {})
    pb = ((rb.get("intervals") or {}).get("per_context") or {})
    contexts = [c for c in pa if c in pb]
    if "all" not in contexts:
        raise ValueError("both reports need the overall intervals (results.intervals.per_context.all)")
    rows = []
    for c in contexts:
        for key in (pa[c].get("difference") or {}):
            a, b = key.split(" - ", 1)
            row = compare_pair(ra, rb, a, b, c)
            if row is not None:
                rows.append(row)
    if not rows:
        raise ValueError("the reports share no pair of methods")
    headline = [r for r in (compare_pair(ra, rb, a, b) for a, b in HEADLINE) if r is not None]
    resolved_a = [r for r in rows if r["resolved_a"]]
    summary = {
        "pairs": len(rows), "contexts": contexts,
        "agreement_rate": round(sum(r["agree"] for r in rows) / len(rows), 4), "agreement_expected": 0.95,
        "headline_agreement": f"{sum(r['agree'] for r in headline)} of {len(headline)}",
        "resolved_in_a": len(resolved_a), "resolved_in_b": sum(1 for r in rows if r["resolved_b"]),
        "resolved_in_both_same_way": sum(1 for r in resolved_a if r["resolved_a"] == r["resolved_b"]),
        "contradictions": sum(1 for r in rows if r["resolved_a"] * r["resolved_b"] == -1),
        "test_sets": [(ra.get("dataset") or {}).get("sets", {}).get("test"),
                      (rb.get("dataset") or {}).get("sets", {}).get("test")],
        "machines": [(ra.get("machine") or {}).get("cpu"), (rb.get("machine") or {}).get("cpu")],
    }
    gates = {}
    for name in sorted(set(ra.get("gate_training") or {}) & set(rb.get("gate_training") or {})):
        ga, gb = ra["gate_training"][name], rb["gate_training"][name]
        gates[name] = {"objective": [ga.get("objective"), gb.get("objective")],
                       "val_regret": [ga.get("val_regret"), gb.get("val_regret")],
                       "objectives_b": {o: x.get("val_regret") for o, x in (gb.get("objectives") or {}).items()}}
    rules = [[r.get("text") for r in ((x.get("physical_gate") or {}).get("rules") or [])] for x in (ra, rb)]
    return {"what": "a verdict scored again on an independent test set", "summary": summary, "headline": headline,
            "gates": gates, "physical_gate_rules": rules, "pairs": rows}
