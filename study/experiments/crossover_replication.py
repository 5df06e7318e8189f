"""Does a crossover replicate? Two crossover records (`study.experiments.crossover`) of the same design on
independent sweep sets (other seeds), compared level by level and crossing by crossing.

Per (base, condition, sensor, level) the two with-minus-without estimates are independent, each with
its 95 % sequence-bootstrap interval; their difference has a 95 % interval of half-width about
sqrt(h_a^2 + h_b^2) (the two half-widths, each side's own: normal approximation). If the intervals
are as wide as they should be, |d_a - d_b| stays inside that about 95 % of the time: the *agreement
rate* is the coverage check of the per-level intervals on an independent set. Besides it: of the
levels one set resolves (its interval excludes 0), how many the other resolves the same way, and
how many the other resolves the *opposite* way (a contradiction: with calibrated intervals about
none). Per crossing: both sets' crossings and, where both have one (crossed, or at the mildest step),
whether each lies in the other's crossing interval.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

from fusion.intervals import resolved_sign

SIDES = ("late", "all_branches")


def inside(x: float | None, interval, worse: str) -> bool | None:
    """Is the crossing `x` within a crossing interval [mild bound, strong bound] (None: open on that
    side) of a condition whose severity grows toward `worse` ("lower" or "higher" values)? None when
    there is no x."""
    if x is None or interval is None:
        return None
    mild, strong = interval
    big = math.inf
    if worse == "lower":  # mild bound is the larger value
        hi = big if mild is None else mild
        lo = -big if strong is None else strong
    else:
        lo = -big if mild is None else mild
        hi = big if strong is None else strong
    return min(lo, hi) <= x <= max(lo, hi)


def replicate(a: Mapping, b: Mapping) -> dict:
    """Compare crossover records `a` and `b` (the same conditions, bases, sensors and levels; other
    sweep sets). Returns the per-level rows, the per-crossing rows and the summary (module doc)."""
    if set(a["conditions"]) != set(b["conditions"]):
        raise ValueError(f"the records hold other conditions: {sorted(a['conditions'])} vs {sorted(b['conditions'])}")
    levels, crossings = [], []
    for cond, ca in a["conditions"].items():
        cb = b["conditions"][cond]
        for base, per in ca["curves"].items():
            for sensor, cur_a in per.items():
                cur_b = cb["curves"][base][sensor]
                if len(cur_a["estimate"]) != len(cur_b["estimate"]):
                    raise ValueError(f"{cond}/{base}/{sensor}: the records have other numbers of levels")
                for i, (ea, eb) in enumerate(zip(cur_a["estimate"], cur_b["estimate"])):
                    ia, ib = cur_a["interval"][i], cur_b["interval"][i]
                    if ea is None or eb is None or not ia or not ib or None in ia or None in ib:
                        continue
                    half = math.hypot((ia[1] - ia[0]) / 2, (ib[1] - ib[0]) / 2)
                    levels.append({"condition": cond, "base": base, "sensor": sensor, "level": i + 1,
                                   "x_a": cur_a["steps"][i], "x_b": cur_b["steps"][i], "a": ea, "b": eb,
                                   "difference": round(ea - eb, 6), "half_width": round(half, 6),
                                   "agree": abs(ea - eb) <= half, "resolved_a": resolved_sign(ia), "resolved_b": resolved_sign(ib)})
                crossings.append({"condition": cond, "base": base, "sensor": sensor, "unit": ca["unit"],
                                  "a": {k: cur_a[k] for k in ("crossing", "crossing_kind", "crossing_interval",
                                                              "first_resolved_below")},
                                  "b": {k: cur_b[k] for k in ("crossing", "crossing_kind", "crossing_interval",
                                                              "first_resolved_below")},
                                  "b_in_a": inside(cur_b["crossing"], cur_a["crossing_interval"], ca["worse"])
                                  if "none" not in (cur_a["crossing_kind"], cur_b["crossing_kind"])
                                  else None,
                                  "a_in_b": inside(cur_a["crossing"], cur_b["crossing_interval"], ca["worse"])
                                  if "none" not in (cur_a["crossing_kind"], cur_b["crossing_kind"])
                                  else None,
                                  "same_kind": cur_a["crossing_kind"] == cur_b["crossing_kind"]})
    resolved = [r for r in levels if r["resolved_a"] or r["resolved_b"]]
    one_way = [r for r in levels if r["resolved_a"]]
    summary = {
        "levels": len(levels),
        "agreement_rate": round(sum(r["agree"] for r in levels) / len(levels), 4) if levels else None,
        "agreement_expected": 0.95,
        "resolved_in_a": len(one_way),
        "resolved_in_b": sum(1 for r in levels if r["resolved_b"]),
        "resolved_in_both_same_way": sum(1 for r in levels if r["resolved_a"] and r["resolved_a"] == r["resolved_b"]),
        "contradictions": sum(1 for r in resolved if r["resolved_a"] * r["resolved_b"] == -1),
        "crossings_same_kind": sum(c["same_kind"] for c in crossings), "crossings": len(crossings),
        "seeds": {"a": a.get("level_seeds"), "b": b.get("level_seeds")},
        "frames_per_step": [a.get("frames_per_step"), b.get("frames_per_step")]}
    return {"what": "a crossover measured again on an independent sweep set", "summary": summary,
            "levels": levels, "crossings": crossings}
