"""The mAP-energy front (`study.experiments.energy_front`, issue 36): the Pareto set of the fixed
configurations, each gate compared with the best fixed configuration at no more energy by the
study's paired intervals, the chord of time-sharing, and the figure."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from study.experiments.energy_front import chord, energy_front, front_figure, front_sentence, is_fixed, pareto

ROOT = Path(__file__).resolve().parents[2]


def _report(gate_minus_radar=(0.01, 0.05), gate_energy=2.0):
    """Radar (1.0, 0.20), camera (1.1, 0.15: off the front), late (3.0, 0.30), all_branches (4.0, 0.35);
    a gate at `gate_energy` with mAP 0.25 and a cheap oracle."""
    methods = {"single:radar": 0.20, "single:camera_right": 0.15, "late": 0.30, "all_branches": 0.35,
               "hydrafusion:deep": 0.25, "ecofusion:loss_based": 0.40}
    energy = {"single:radar": 1.0, "single:camera_right": 1.1, "late": 3.0, "all_branches": 4.0,
              "hydrafusion:deep": gate_energy, "ecofusion:loss_based": 0.5}
    return {"methods": {n: {"map": v} for n, v in methods.items()},
            "hydra_table4": {n: {"energy": e} for n, e in energy.items()},
            "energy_unit": "PX2-equivalent J: ...",
            "intervals": {"per_context": {"all": {
                "sequences": 64, "map": {n: [v - 0.05, v + 0.05] for n, v in methods.items()},
                "difference": {"single:radar - hydrafusion:deep": [-gate_minus_radar[1], -gate_minus_radar[0]],
                               "hydrafusion:deep - late": [-0.1, -0.02]}}}}}


def test_the_front_is_the_pareto_set_cheapest_first():
    pts = {"a": (1.0, 0.2), "b": (1.1, 0.15), "c": (3.0, 0.3), "d": (3.0, 0.1), "e": (4.0, 0.29)}
    assert pareto(pts) == ["a", "c"]
    assert pareto({"x": (1.0, 0.2), "y": (1.0, 0.2)}) == ["x"]  # a tie: one of them


def test_the_chord_interpolates_between_front_neighbours():
    fixed = {"a": {"energy": 1.0, "map": 0.2}, "c": {"energy": 3.0, "map": 0.3}}
    assert chord(fixed, ["a", "c"], 2.0) == pytest.approx(0.25)
    assert chord(fixed, ["a", "c"], 0.5) == 0.2 and chord(fixed, ["a", "c"], 9.0) == 0.3


def test_a_gate_is_placed_against_the_best_fixed_configuration_it_can_afford():
    f = energy_front(_report())
    assert f["front"] == ["single:radar", "late", "all_branches"]
    assert not f["fixed"]["single:camera_right"]["on_front"]
    g = f["placed"]["hydrafusion:deep"]
    assert g["against"] == "single:radar" and g["minus_front"] == [0.01, 0.05]  # negated from "radar - deep"
    assert g["verdict"] == "above the front" and g["point"] == pytest.approx(0.05)
    assert g["minus_chord"] == pytest.approx(0.25 - (0.20 + 0.10 * 0.5))
    assert not g["bound"]
    oracle = f["placed"]["ecofusion:loss_based"]
    assert oracle["bound"] and oracle["verdict"] == "cheaper than every fixed configuration"
    assert "not achievable" in oracle["what"]


@pytest.mark.parametrize(("interval", "verdict"), [((-0.03, 0.02), "not resolved"), ((-0.06, -0.01), "below the front")])
def test_the_verdict_follows_the_paired_interval(interval, verdict):
    assert energy_front(_report(interval))["placed"]["hydrafusion:deep"]["verdict"] == verdict


def test_a_dearer_gate_is_held_to_the_dearer_configuration():
    g = energy_front(_report(gate_energy=3.5))["placed"]["hydrafusion:deep"]
    assert g["against"] == "late" and g["minus_front"] == [-0.1, -0.02] and g["verdict"] == "below the front"
    assert "below the front" in front_sentence(energy_front(_report(gate_energy=3.5)))


def test_what_is_fixed():
    assert all(map(is_fixed, ["single:lidar", "late", "all_branches", "early:early_radar_lidar"]))
    assert not any(map(is_fixed, ["hydrafusion:deep", "ecofusion:attention", "context_oracle"]))


def test_no_costs_or_no_intervals_no_front():
    r = _report()
    assert energy_front({**r, "hydra_table4": {}}) is None
    assert energy_front({**r, "intervals": None}) is None


def test_the_stored_cpu_frontier_study_has_a_front_and_a_figure(tmp_path):
    report = json.loads((ROOT / "results" / "study_cpu_frontier" / "report.json").read_text())
    f = energy_front(report)
    assert f["front"][0].startswith("single:") and f["front"][-1] == "all_branches"
    for p in f["placed"].values():  # each compared with a front configuration no dearer than itself
        assert p["against"] is None or f["fixed"][p["against"]]["energy"] <= p["energy"]
    png = front_figure(f, tmp_path / "front.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
