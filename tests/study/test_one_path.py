"""One scoring path (issue 36): every table cell that shows a method holds the method's own mAP
(`study.experiments.one_path`), checked on the stored studies and on a results record with one cell changed."""

from __future__ import annotations

import copy
import dataclasses
import json
from pathlib import Path

import pytest

from sim.errors import UserError
from study.experiments.one_path import disagreements, one_path_record, shown_maps
from study.pipeline.config import load_study_config

RESULTS = Path(__file__).resolve().parents[2] / "results"


def _results(name: str) -> dict:
    return json.loads((RESULTS / name / "report.json").read_text())["results"]


def test_the_cpu_frontier_study_shows_every_method_with_its_own_map():
    r = _results("study_cpu_frontier")
    rec = one_path_record(r)
    assert rec["checked"] >= 15 and not rec["disagreements"]
    assert {"late", "all_branches", "single:radar", "ecofusion:attention", "hydrafusion:attention"} <= set(rec["methods"])


def test_the_older_cpu_study_is_caught_where_its_ecofusion_tables_fused_another_way():
    # the `cpu` study fused EcoFusion's configurations with WBF (gates.fusion) and its headline with Soft-NMS (the
    # late fusion chosen on validation), so even a single sensor shows another mAP there (WBF merges a model's own
    # overlapping boxes): what the check exists to catch
    bad = disagreements(_results("study_cpu"))
    assert {d["where"] for d in bad} >= {"EcoFusion Table 1, none_radar", "EcoFusion Table 1, late"}
    assert all(d["where"].startswith("EcoFusion") for d in bad)


def test_a_changed_cell_is_found_and_another_fusions_column_is_not_checked():
    r = _results("study_cpu_frontier")
    changed = copy.deepcopy(r)
    changed["hydra_table2"]["single_sensors"]["radar"] += 0.01
    assert [d["where"] for d in disagreements(changed)] == ["HydraFusion Table 2, single sensor radar"]
    other = copy.deepcopy(r)
    for cols in other["hydra_table6"].values():  # every column but the study's fusion is another method
        for f in cols:
            if f.replace("_", "-") != r["fusion"].replace("_", "-"):
                cols[f] = {kk: v + 0.05 for kk, v in cols[f].items()}
    assert not disagreements(other)
    places = shown_maps(r)
    assert all(r["fusion"].replace("_", "-") in w or "Table 6" not in w for v in places.values() for w, _ in v)


def test_a_declared_fusion_must_be_ecofusions_too():
    from study.pipeline.checks import check_study_config

    cfg = load_study_config("tiny")
    declared = dataclasses.replace(cfg, evaluate=dataclasses.replace(cfg.evaluate, fusion="soft-nms"))
    with pytest.raises(UserError, match="make them the same"):
        check_study_config(dataclasses.replace(declared, gates=dataclasses.replace(cfg.gates, fusion="wbf")))
    check_study_config(dataclasses.replace(declared, gates=dataclasses.replace(cfg.gates, fusion="soft-nms")))
    with pytest.raises(UserError, match="evaluate.fusion must be"):
        dataclasses.replace(cfg.evaluate, fusion="max")
