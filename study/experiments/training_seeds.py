"""Training variance beside test-set variance (issue 36 item 6): a study's headline rows for detectors
trained with two seeds and scored on the same test set, beside the same detectors scored on two
independent test sets.

The two kinds of difference are read differently:

- *Seeds, one test set.* Both estimates are made on the same test frames, so the test set's own luck
  largely cancels in their difference (as in a paired comparison): what is left is what training
  moves (the detectors and, downstream, the gates trained on their outputs). It is set against the
  test interval's mean half-width h: |difference| / h near 1 means a retrained model moves a pair as
  far as a new test set's sampling error does.
- *Test sets, one training.* The two estimates are independent; their difference carries both test
  sets' sampling error (about sqrt(2) h when the intervals are right), plus whatever differs in the
  gates trained again.

Per headline pair (`study.experiments.verdict_replication.HEADLINE`) and report: the estimate, its 95 % interval
and the verdict it reads ("above", "below", "not resolved"); per comparison: the difference, its
ratio to h and whether the verdict changes. A pair missing from a report is left out.
"""

from __future__ import annotations

import statistics
from collections.abc import Mapping, Sequence

from fusion.intervals import resolved_sign
from study.experiments.verdict_replication import HEADLINE, pair_difference


def _verdict(interval) -> str:
    return {1: "above", -1: "below", 0: "not resolved"}[resolved_sign(interval)]


def headline_rows(reports: Mapping[str, Mapping], pairs: Sequence[tuple[str, str]] = HEADLINE) -> list[dict]:
    """Per pair that every report holds: {"pair", "per": {label: {"estimate", "ci95", "verdict"}}}."""
    rows = []
    for a, b in pairs:
        per = {}
        for label, res in reports.items():
            d = pair_difference(res, a, b)
            if d is None:
                break
            per[label] = {"estimate": d[0], "ci95": d[1], "verdict": _verdict(d[1])}
        else:
            rows.append({"pair": f"{a} - {b}", "per": per})
    return rows


def spread(rows: Sequence[dict], first: str, second: str) -> dict:
    """How far `second`'s estimates lie from `first`'s over `rows` (`headline_rows`): per pair the
    difference, the mean half-width h of the two intervals and |difference| / h; the median and
    largest ratio; the pairs whose verdict differs."""
    per, ratios, changed = [], [], []
    for r in rows:
        x, y = r["per"][first], r["per"][second]
        h = ((x["ci95"][1] - x["ci95"][0]) + (y["ci95"][1] - y["ci95"][0])) / 4
        d = y["estimate"] - x["estimate"]
        ratio = abs(d) / h if h > 0 else None
        per.append({"pair": r["pair"], "difference": round(d, 6), "half_width": round(h, 6),
                    "ratio": None if ratio is None else round(ratio, 3), "verdicts": [x["verdict"], y["verdict"]]})
        if ratio is not None:
            ratios.append(ratio)
        if x["verdict"] != y["verdict"]:
            changed.append(r["pair"])
    return {"between": [first, second], "pairs": per,
            "median_ratio": round(statistics.median(ratios), 3) if ratios else None,
            "max_ratio": round(max(ratios), 3) if ratios else None,
            "mean_abs_difference": round(statistics.fmean(abs(p["difference"]) for p in per), 6) if per else None,
            "verdicts_changed": changed}


def _test_set(res: Mapping):
    return ((res.get("dataset") or {}).get("sets") or {}).get("test")


def training_variance(reports: Mapping[str, Mapping], seeds: tuple[str, str], test_sets: tuple[str, str] | None = None,
                      pairs: Sequence[tuple[str, str]] = HEADLINE) -> dict:
    """The side-by-side record: `reports` {label: a study report's results}; `seeds`: the two labels
    trained with different seeds on the same test set (checked: their test sets must be equal);
    `test_sets`: optionally two labels of one training on independent test sets (checked: different).
    Each method's mAP in every report, the headline rows, and the two spreads (module doc)."""
    a, b = seeds
    if _test_set(reports[a]) != _test_set(reports[b]):
        raise ValueError(f"{a!r} and {b!r} are not scored on the same test set: {_test_set(reports[a])} vs "
                         f"{_test_set(reports[b])}")
    if test_sets is not None and _test_set(reports[test_sets[0]]) == _test_set(reports[test_sets[1]]):
        raise ValueError(f"{test_sets[0]!r} and {test_sets[1]!r} are scored on the same test set")
    rows = headline_rows(reports, pairs)
    if not rows:
        raise ValueError("the reports share no headline pair")
    methods = sorted(set.intersection(*(set(r.get("methods") or {}) for r in reports.values())))
    return {"what": "headline rows of detectors trained with two seeds (same test set) beside one training scored "
                    "on two test sets",
            "reports": {k: {"test_set": _test_set(v), "machine": (v.get("machine") or {}).get("cpu")}
                        for k, v in reports.items()},
            "methods": {m: {k: (v["methods"][m] or {}).get("map") for k, v in reports.items()} for m in methods},
            "headline": rows,
            "training": spread(rows, a, b),
            "test_set": spread(rows, *test_sets) if test_sets is not None else None}
