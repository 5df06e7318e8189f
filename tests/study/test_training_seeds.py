"""study.experiments.training_seeds and its script: headline rows of two training seeds on one test set beside one
training on two test sets, on synthetic reports with known answers; the script refuses a seed pair
scored on different test sets."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from study.experiments.training_seeds import headline_rows, spread, training_variance

ROOT = Path(__file__).resolve().parents[2]


def report(maps: dict, diffs: dict, test_seed: int, cpu: str = "x") -> dict:
    return {"methods": {m: {"map": v} for m, v in maps.items()},
            "intervals": {"per_context": {"all": {"difference": diffs}}},
            "dataset": {"sets": {"test": {"seed": test_seed}}}, "machine": {"cpu": cpu}}


MAPS0 = {"late": 0.30, "all_branches": 0.33, "hydrafusion:deep": 0.32}
SEED0 = report(MAPS0, {"all_branches - late": [0.02, 0.04], "hydrafusion:deep - late": [0.01, 0.03]}, 2002)
SEED1 = report({"late": 0.29, "all_branches": 0.33, "hydrafusion:deep": 0.295},
               {"all_branches - late": [0.03, 0.05], "late - hydrafusion:deep": [-0.015, 0.005]}, 2002)
OTHER_TEST = report({"late": 0.31, "all_branches": 0.335, "hydrafusion:deep": 0.33},
                    {"all_branches - late": [0.015, 0.035], "hydrafusion:deep - late": [0.01, 0.03]}, 2001)


def test_the_rows_and_the_spreads_are_what_the_reports_say():
    reports = {"s0": SEED0, "s1": SEED1, "t": OTHER_TEST}
    rows = headline_rows(reports)
    assert [r["pair"] for r in rows] == ["all_branches - late", "hydrafusion:deep - late"]
    deep = rows[1]["per"]
    assert deep["s1"]["estimate"] == pytest.approx(0.005) and deep["s1"]["ci95"] == [-0.005, 0.015]
    assert deep["s0"]["verdict"] == "above" and deep["s1"]["verdict"] == "not resolved"
    s = spread(rows, "s0", "s1")
    # all_branches: 0.04 - 0.03 = +0.01 over h = (0.02 + 0.02) / 4 = 0.01 -> 1.0;
    # deep: 0.005 - 0.02 = -0.015 over h = (0.02 + 0.02) / 4 = 0.01 -> 1.5
    assert [p["difference"] for p in s["pairs"]] == [pytest.approx(0.01), pytest.approx(-0.015)]
    assert [p["ratio"] for p in s["pairs"]] == [1.0, 1.5]
    assert s["median_ratio"] == 1.25 and s["max_ratio"] == 1.5 and s["verdicts_changed"] == ["hydrafusion:deep - late"]
    r = training_variance(reports, ("s0", "s1"), ("s0", "t"))
    assert r["training"] == s and r["test_set"]["verdicts_changed"] == []
    assert r["methods"]["late"] == {"s0": 0.30, "s1": 0.29, "t": 0.31}
    assert r["reports"]["t"]["test_set"] == {"seed": 2001}


def test_seeds_must_share_the_test_set_and_test_sets_must_differ():
    with pytest.raises(ValueError, match="not scored on the same test set"):
        training_variance({"s0": SEED0, "t": OTHER_TEST}, ("s0", "t"))
    with pytest.raises(ValueError, match="scored on the same test set"):
        training_variance({"s0": SEED0, "s1": SEED1}, ("s0", "s1"), ("s0", "s1"))


def test_the_script_prints_writes_and_refuses(tmp_path):
    paths = {}
    for label, rep in (("s0", SEED0), ("s1", SEED1), ("t", OTHER_TEST)):
        paths[label] = tmp_path / f"{label}.json"
        paths[label].write_text(json.dumps({"results": rep}))
    cmd = [sys.executable, str(ROOT / "scripts" / "training_seeds.py"),
           *[x for k, v in paths.items() for x in ("--report", f"{k}={v}")], "--seeds", "s0,s1",
           "--test-sets", "s0,t", "--out", str(tmp_path / "out.json")]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, env={"PYTHONPATH": str(ROOT)})
    assert done.returncode == 0, done.stderr
    assert "training (s0 -> s1)" in done.stdout and "hydrafusion:deep - late" in done.stdout
    out = json.loads((tmp_path / "out.json").read_text())
    assert out["training"]["max_ratio"] == 1.5
    bad = subprocess.run([*cmd[:-2], "--seeds", "s0,t"], capture_output=True, text=True, cwd=ROOT,
                         env={"PYTHONPATH": str(ROOT)})
    assert bad.returncode == 2 and "not scored on the same test set" in bad.stderr


STORED = ROOT / "results" / "study_cpu_verdict"
LABELS = {"seed 0, test set 2001 (Intel)": "seed0_test2001", "seed 0, test set 2002": "seed0",
          "seed 1, test set 2002": "seed1"}


def test_the_stored_record_is_what_the_script_makes_of_the_stored_reports(tmp_path):
    """results/study_cpu_verdict/training_seeds.json, recomputed from the reports it was made of (the
    stored verdict, the replication's extract and the second seed's extract)."""
    cmd = [sys.executable, str(ROOT / "scripts" / "training_seeds.py"),
           "--report", f"seed0={STORED / 'report_test2002_extract.json'}",
           "--report", f"seed1={STORED / 'report_seed1_test2002_extract.json'}",
           "--report", f"seed0_test2001={STORED / 'report.json'}",
           "--seeds", "seed0,seed1", "--test-sets", "seed0,seed0_test2001", "--out", str(tmp_path / "again.json")]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, env={"PYTHONPATH": str(ROOT)})
    assert done.returncode == 0, done.stderr
    assert json.loads((tmp_path / "again.json").read_text()) == json.loads((STORED / "training_seeds.json").read_text())


def test_the_readme_shows_both_seeds_headline_rows_as_stored():
    rec = json.loads((STORED / "training_seeds.json").read_text())
    lines = (ROOT / "README.md").read_text().splitlines()
    head = [i for i, x in enumerate(lines) if x.startswith("| headline pair | seed 0, test set 2001 (Intel) |")]
    assert len(head) == 1
    header = [c.strip() for c in lines[head[0]].strip("|").split("|")][1:]
    assert set(header) == set(LABELS)
    rows = {}
    for line in lines[head[0] + 2:]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip("|").split("|")]
        rows[cells[0]] = dict(zip(header, cells[1:]))
    assert set(rows) == {r["pair"] for r in rec["headline"]}
    for r in rec["headline"]:
        for col, label in LABELS.items():
            c = r["per"][label]
            assert rows[r["pair"]][col] == f"{c['estimate']:+.3f} [{c['ci95'][0]:+.3f}, {c['ci95'][1]:+.3f}]", (r, col)
