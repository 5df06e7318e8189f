"""scripts/readme_results.py: the README's results block is a function of a study's report JSON,
replaced between its markers only, idempotently, and refused without them."""

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
spec = importlib.util.spec_from_file_location("readme_results", ROOT / "scripts" / "readme_results.py")
rr = importlib.util.module_from_spec(spec)
spec.loader.exec_module(rr)


def _method(m, city, fog):
    return {"map": m, "map_per_context": {"city": city, "fog": fog}}


REPORT = {
    "scale": "cpu", "meaningless": False,
    "results": {
        "protocol": "reference", "hydra_gate": "attention", "eco_gate": "attention", "lambda_e": 0.01, "gamma": 0.5,
        "dataset": {"frames": 2000, "train_frames": 1400, "test_frames": 600, "contexts": ["city", "fog"]},
        "machine": {"cpu": "AMD EPYC", "threads": 2},
        "methods": {"single:radar": _method(0.2, 0.1, 0.3), "late": _method(0.4, 0.5, 0.3),
                    "all_branches": _method(0.41, 0.5, 0.32), "hydrafusion:attention": _method(0.45, 0.5, 0.4),
                    "hydrafusion:optimal": _method(0.5, 0.55, 0.45), "ecofusion:attention": _method(0.43, 0.5, 0.36),
                    "ecofusion:loss_based": _method(0.47, 0.52, 0.42)},
        "hydra_table4": {"late": {"energy_j": 10.0, "latency_ms": 200.0},
                         "ecofusion:attention": {"energy_j": 4.0, "latency_ms": 90.0}},
        "energy_unit": "modelled: 45.4 W",
        "regret": {"hydrafusion": {"attention": {"all": {"regret_map": 0.05, "differs_pct": 40.0}}}},
        "fusion_regret": {"camera_right": {"hurts_in": {"fog": 0.031}}, "radar": {"hurts_in": {}}},
    },
}


def test_block_carries_the_reports_numbers_and_ratios():
    block = rr.results_block(REPORT)
    assert "protocol `reference`, scale `cpu`, 2000 frames (1400 train, 600 test), AMD EPYC with 2 thread(s)" in block
    assert "| late | 0.400 | 0.500 | 0.300 |" in block and "| hydrafusion:attention | 0.450 | 0.500 | 0.400 |" in block
    # EcoFusion against late: mAP difference and the energy and latency ratios, from the same numbers
    assert "mAP 0.0300 points, energy x0.40, latency x0.45" in block
    assert "regret against the oracle 0.0500 mAP, choice differs on 40.0 %" in block
    assert "fusing camera_right costs mAP in: fog (0.0310)" in block and "fusing radar costs mAP in: no context" in block
    assert "mean nothing" not in block
    assert rr.results_block({**REPORT, "meaningless": True}).startswith("**These numbers mean nothing**")


def test_block_carries_the_intervals_and_turns_stored_differences_round():
    ci = {"resamples": 500, "unit": "sequence", "seed": 0, "per_context": {"all": {
        "sequences": 20, "map": {"single:radar": [0.15, 0.25], "late": [0.35, 0.45], "hydrafusion:attention": [0.4, 0.5]},
        # pairs are stored one way round: late - single:radar, and hydrafusion:attention - late
        "difference": {"late - single:radar": [0.12, 0.28], "hydrafusion:attention - late": [-0.01, 0.11]}}}}
    report = {**REPORT, "results": {**REPORT["results"], "intervals": ci}}
    block = rr.results_block(report)
    assert "| method | mAP@0.5 | 95 % interval | minus late: 95 % interval | city | fog |" in block
    assert "| single:radar | 0.200 | [0.150, 0.250] | [-0.280, -0.120] | 0.100 | 0.300 |" in block
    assert "| hydrafusion:attention | 0.450 | [0.400, 0.500] | [-0.010, +0.110] | 0.500 | 0.400 |" in block
    assert "| late | 0.400 | [0.350, 0.450] | - | 0.500 | 0.300 |" in block
    assert "500 draws of the 20 test sequences" in block
    # a method the bootstrap did not score has no interval, not a wrong one
    assert "| all_branches | 0.410 | - | - | 0.500 | 0.320 |" in block


def test_replacing_keeps_the_rest_and_is_idempotent(tmp_path):
    readme = f"# title\n\nbefore\n{rr.BEGIN}\nold numbers\n{rr.END}\nafter\n"
    new = rr.replace_block(readme, rr.results_block(REPORT))
    assert new.startswith("# title\n\nbefore\n") and new.endswith(f"{rr.END}\nafter\n") and "old numbers" not in new
    assert rr.replace_block(new, rr.results_block(REPORT)) == new
    with pytest.raises(ValueError, match="exactly one"):
        rr.replace_block("no markers\n", "x")
    (tmp_path / "report.json").write_text(json.dumps(REPORT))
    (tmp_path / "README.md").write_text(readme)
    args = [str(tmp_path / "report.json"), "--readme", str(tmp_path / "README.md")]
    assert rr.main([*args, "--check"]) == 1  # stale
    assert rr.main(args) == 0 and (tmp_path / "README.md").read_text() == new
    assert rr.main([*args, "--check"]) == 0
    assert rr.main([str(tmp_path / "missing.json"), "--readme", str(tmp_path / "README.md")]) == 2


def test_the_repository_readme_has_one_block():
    text = (ROOT / "README.md").read_text()
    assert text.count(rr.BEGIN) == 1 and text.count(rr.END) == 1
