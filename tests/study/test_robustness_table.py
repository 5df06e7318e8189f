"""study.experiments.robustness_table: the report's per-severity scores in the field's metrics, checked by hand on
a small sweep and against the committed cpu study's numbers."""

import json
from pathlib import Path

import pytest

from fusion.robustness import severity_value
from study.experiments.robustness_table import robustness_table

ROOT = Path(__file__).resolve().parents[2]


def _cell(d, c, n=10):
    return {"degraded": d, "clear": c, "frames": n}


SWEEP = {"severity": {
    "fog": {"late": {"1": _cell(0.4, 0.5), "3": _cell(0.2, 0.4)},
            "single:lidar": {"1": _cell(0.3, 0.5), "3": _cell(0.1, 0.5)},
            "hydrafusion:attention": {"1": _cell(0.45, None), "3": _cell(0.25, None)}},
    "rain": {"late": {"2": _cell(0.5, 0.5)}, "single:lidar": {"2": _cell(0.25, 0.0)}}}}


def test_a_small_sweep_by_hand():
    t = robustness_table(SWEEP)
    assert t["baseline"] == "late" and list(t["methods"]) == ["late", "single:lidar", "hydrafusion:attention"]
    late, lidar, gate = (t["methods"][m] for m in t["methods"])
    fog = late["conditions"]["fog"]
    assert fog["severities"][3] == {"value": round(severity_value("fog", 3)[0], 3), "unit": "m", "degraded": 0.2,
                                    "clear": 0.4, "frames": 10, "ra": 0.5}
    assert fog["ra"] == pytest.approx((0.8 + 0.5) / 2) and fog["rr"] == pytest.approx(round(0.6 / 0.9, 4))
    assert late["mra"] == pytest.approx(((0.8 + 0.5) / 2 + 1.0) / 2) and late["mce"] == 1.0
    # lidar: CE_fog = (0.7 + 0.9) / (0.6 + 0.8); rain's twins score 0, so its RA and RR are undefined
    assert lidar["conditions"]["fog"]["ce"] == pytest.approx(round(1.6 / 1.4, 4))
    assert lidar["conditions"]["rain"]["ra"] is None and lidar["conditions"]["rain"]["rr"] is None
    assert lidar["conditions"]["rain"]["ce"] == pytest.approx(0.75 / 0.5)
    assert lidar["mra"] == pytest.approx((0.6 + 0.2) / 2)
    # a gate scored without twins: CE against late, no RA / RR
    assert gate["mra"] is None and gate["mrr"] is None
    assert gate["mce"] == pytest.approx(round((0.55 + 0.75) / (0.6 + 0.8), 4))
    assert robustness_table({}) == {} and robustness_table({"severity": {}}) == {}


def test_the_cpu_studys_table_is_its_severity_sweep():
    r = json.loads((ROOT / "results" / "study_cpu" / "report.json").read_text())["results"]
    t = robustness_table(r)
    assert t["methods"]["late"]["mce"] == 1.0
    for c, per in r["severity"].items():
        for m, cells in per.items():
            for s, v in cells.items():
                row = t["methods"][m]["conditions"][c]["severities"][int(s)]
                assert (row["degraded"], row["clear"], row["frames"]) == (v["degraded"], v["clear"], v["frames"])
                if v["clear"] and v["degraded"] is not None:
                    assert row["ra"] == round(v["degraded"] / v["clear"], 4)
                else:
                    assert row["ra"] is None
