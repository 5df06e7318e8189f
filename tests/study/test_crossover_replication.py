"""study.experiments.crossover_replication: two crossover records compared level by level, crossings against
each other's intervals; on synthetic records with a known truth, and on the committed verdict's two
sweep sets (results/study_cpu_verdict)."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from study.experiments.crossover_replication import inside, replicate

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "results" / "study_cpu_verdict"


def _record(estimates, half=0.02, kind="crossed", crossing=100.0, cross_iv=(150.0, 60.0), worse="lower"):
    """One condition (fog-like), one base, one sensor per entry of `estimates` {sensor: [d per level]}."""
    curves = {s: {"steps": [800.0, 400.0, 200.0, 100.0, 50.0][:len(e)], "estimate": list(e),
                  "interval": [[v - half, v + half] for v in e], "crossing": crossing if kind != "none" else None,
                  "crossing_kind": kind, "crossing_interval": list(cross_iv) if kind != "none" else [None, None],
                  "first_resolved_below": None} for s, e in estimates.items()}
    return {"conditions": {"fog": {"unit": "m", "worse": worse, "curves": {"late": curves}}},
            "level_seeds": {"1": 1}, "frames_per_step": 96}


def test_inside_reads_the_milder_end_first_on_both_kinds_of_axis():
    assert inside(100.0, [150.0, 60.0], "lower") and not inside(40.0, [150.0, 60.0], "lower")
    assert inside(1e6, [None, 60.0], "lower") and not inside(10.0, [None, 60.0], "lower")  # open toward clear
    assert inside(3.0, [1.0, 5.0], "higher") and inside(99.0, [1.0, None], "higher") and not inside(0.5, [1.0, None], "higher")
    assert inside(None, [1.0, 2.0], "higher") is None


def test_identical_records_agree_everywhere_and_opposite_resolutions_are_contradictions():
    a = _record({"lidar": [0.1, 0.05, 0.0, -0.05, -0.1]})
    r = replicate(a, a)
    assert r["summary"]["agreement_rate"] == 1.0 and r["summary"]["contradictions"] == 0
    assert r["summary"]["resolved_in_both_same_way"] == 4 and r["crossings"][0]["b_in_a"] is True
    flipped = _record({"lidar": [-0.1, 0.05, 0.0, -0.05, 0.1]}, crossing=300.0, cross_iv=(500.0, 250.0))
    r = replicate(a, flipped)
    assert r["summary"]["contradictions"] == 2 and r["summary"]["agreement_rate"] == 0.6
    assert r["crossings"][0]["b_in_a"] is False and r["crossings"][0]["a_in_b"] is False
    with pytest.raises(ValueError, match="levels"):
        replicate(a, _record({"lidar": [0.1, 0.05]}))


def test_calibrated_intervals_agree_about_95_percent_of_the_time():
    """Two sets drawn around one truth with standard error 0.02 and intervals of +-1.96 x 0.02: the
    difference stays within sqrt(2) x 1.96 x 0.02 in 95 % of levels."""
    rng = np.random.default_rng(0)
    truth = rng.normal(0, 0.05, size=(400, 5))
    recs = [_record({f"s{i}": list(t + rng.normal(0, 0.02, 5)) for i, t in enumerate(truth)}, half=1.96 * 0.02)
            for _ in range(2)]
    rate = replicate(*recs)["summary"]["agreement_rate"]
    assert 0.93 < rate < 0.97
    narrow = [_record({f"s{i}": list(t + rng.normal(0, 0.02, 5)) for i, t in enumerate(truth)}, half=0.02)
              for _ in range(2)]
    assert replicate(*narrow)["summary"]["agreement_rate"] < 0.8  # intervals half as wide as they should be


def test_the_committed_replication_is_what_the_two_committed_sweep_sets_give():
    report = json.loads((RESULTS / "report.json").read_text())
    b = json.loads((RESULTS / "crossover_seed3100.json").read_text())
    a = report["results"]["crossover"]
    assert set(a["level_seeds"].values()).isdisjoint(b["level_seeds"].values())  # independent sweep sets
    committed = json.loads((RESULTS / "crossover_replication.json").read_text())
    assert json.loads(json.dumps(replicate(a, b))) == committed
    s = committed["summary"]
    assert s["levels"] == 120 and s["contradictions"] == 0


def test_the_script_reads_a_report_and_a_record(tmp_path):
    out = tmp_path / "r.json"
    run = subprocess.run([sys.executable, "scripts/crossover_replication.py", str(RESULTS / "report.json"),
                          str(RESULTS / "crossover_seed3100.json"), "--out", str(out)],
                         capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert run.returncode == 0, run.stderr
    assert "estimates agreeing within their intervals" in run.stdout
    assert json.loads(out.read_text()) == json.loads((RESULTS / "crossover_replication.json").read_text())
    bad = subprocess.run([sys.executable, "scripts/crossover_replication.py", str(out), str(out)],
                         capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert bad.returncode != 0 and "not a crossover record" in bad.stderr


def test_the_crossover_is_the_same_on_another_cpu():
    """results/study_cpu_verdict/crossover_amd.json: the verdict's crossover stage run again with the
    same sweep seeds on an AMD EPYC (the verdict's ran on an Intel Xeon with AMX); every level's
    estimate and interval within 1e-3 of the verdict's, the same crossings, and the stored comparison
    is what the script computes."""
    verdict = json.loads((RESULTS / "report.json").read_text())["results"]["crossover"]
    amd = json.loads((RESULTS / "crossover_amd.json").read_text())
    assert verdict["level_seeds"] == amd["level_seeds"] and verdict["machine"]["cpu"] != amd["machine"]["cpu"]
    r = replicate(verdict, amd)
    assert r["summary"]["levels"] == 120 and r["summary"]["contradictions"] == 0
    assert max(abs(x["difference"]) for x in r["levels"]) < 1e-3
    assert r["summary"]["resolved_in_a"] == r["summary"]["resolved_in_b"] == r["summary"]["resolved_in_both_same_way"]
    for c in r["crossings"]:
        assert c["same_kind"], c
        if c["a"]["crossing"] is not None:
            assert c["b"]["crossing"] == pytest.approx(c["a"]["crossing"], rel=1e-3), c
    stored = json.loads((RESULTS / "crossover_cross_cpu.json").read_text())
    assert json.loads(json.dumps(r)) == stored
