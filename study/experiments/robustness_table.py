"""A study's robustness in the field's metrics, from the per-severity scores its report already holds.

`results["severity"]` (written by the study's evaluate stage) is {condition: {method: {severity:
{"degraded", "clear", "frames"}}}}: the vehicle mAP@0.5 of the test frames of that condition at that
severity, and of their clear twins (the same frames, only the weather differs; None where the
method was not scored on the twins). `robustness_table` turns it into MultiCorrupt's RA / mRA and
Robo3D's RR / mRR (paired: each severity against its own twins) and CE / mCE against a named
baseline (`fusion.robustness`), with each severity's physical value (`fusion.robustness.severity_value`).
Point estimates only: the intervals need the frames (`fusion.robustness.twin_relative_accuracy`).
"""

from __future__ import annotations

import math

from fusion.robustness import (
    corruption_error,
    mean_corruption_error,
    mean_relative_accuracy,
    mean_resilience_rate,
    relative_accuracies,
    resilience_rate,
    severity_value,
)


def _none(v: float):
    return None if v is None or math.isnan(v) else round(float(v), 4)


def robustness_table(results: dict, baseline: str = "late") -> dict:
    """Per method: {"conditions": {c: {"severities": {s: {"value", "unit", "degraded", "clear",
    "frames", "ra"}}, "ra": RA_c, "rr": RR_c, "ce": CE_c}}, "mra", "mrr", "mce"}, plus "baseline".

    RA_{c,s} = degraded / clear of the same frames; RA_c their mean over s; RR_c = sum_s degraded /
    sum_s clear; CE_c = sum_s (1 - A) / sum_s (1 - A_baseline) over the severities both have (no
    twins needed, so a gate scored only on the degraded frames has CE but no RA or RR). NaN becomes
    None (JSON). An empty dict when the report has no severity sweep.
    """
    sev = results.get("severity") or {}
    methods = list(dict.fromkeys(m for per in sev.values() for m in per))
    out: dict = {"baseline": baseline, "methods": {}}
    base = {c: {int(s): v["degraded"] for s, v in per[baseline].items()} for c, per in sev.items() if baseline in per}
    for m in methods:
        deg = {c: {int(s): v["degraded"] for s, v in per[m].items()} for c, per in sev.items() if m in per}
        clr = {c: {int(s): v["clear"] for s, v in per[m].items()} for c, per in sev.items() if m in per}
        ra = relative_accuracies(deg, clr)
        conds = {}
        for c in deg:
            conds[c] = {
                "severities": {s: {"value": round(severity_value(c, s)[0], 3), "unit": severity_value(c, s)[1],
                                   "degraded": deg[c][s], "clear": clr[c][s],
                                   "frames": sev[c][m][str(s)]["frames"], "ra": _none(ra[c].get(s))}
                               for s in sorted(deg[c])},
                "ra": _none(mean_relative_accuracy({c: ra[c]})),
                "rr": _none(resilience_rate(deg[c], clr[c])),
                "ce": _none(corruption_error(deg[c], base[c])) if c in base else None,
            }
        out["methods"][m] = {"conditions": conds, "mra": _none(mean_relative_accuracy(ra)),
                             "mrr": _none(mean_resilience_rate(deg, clr)),
                             "mce": _none(mean_corruption_error(deg, base))}
    return out if methods else {}
