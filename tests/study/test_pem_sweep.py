"""`hydrabench pem sweep` (issue 49 item 3): per strength, every comparison of the verdict with its
interval and verdict; the per-context constant and the physical gate chosen on the gate set alone (a
test set of other frames leaves the choice as it was, and the choice is the gate set's best); the
a-posteriori oracle reads each frame's own ground truth; the figure is written. No network runs: the
PEM is fitted on boxes drawn from the ground truth (`tests.study.test_pem_study._seed_pem`)."""

import json

import pytest

from study.cli import main
from tests.study.test_known_answer import GATE
from tests.study.test_known_answer import TEST as TEST_A
from tests.study.test_pem_study import FIT, _seed_pem
from tests.study.test_pem_study import TEST as TEST_B

NEW = ("context_constant_minus_all_branches", "physical_gate_minus_all_branches", "room_for_context",
       "a_posteriori_oracle_minus_all_branches", "utility_oracle_minus_all_branches")
OLD = ("all_branches_minus_late", "knowledge_minus_all_branches", "knowledge_minus_late")


@pytest.fixture(scope="module")
def world(shared_dataset, tmp_path_factory):
    from study.engine.reference_model import resolve_run

    tmp = tmp_path_factory.mktemp("sweep")
    run = resolve_run("cpu-frontier")
    _seed_pem(run, shared_dataset(FIT), tmp / "pem.json")
    return run, tmp, shared_dataset(GATE), shared_dataset(TEST_A), shared_dataset(TEST_B)


def _check_difference(d):
    lo, hi = d["ci95"]
    assert lo <= hi and d["verdict"] == ("above" if lo > 0 else "below" if hi < 0 else "not resolved"), d


def test_every_comparison_has_its_interval_and_the_figure_is_written(world, capsys):
    run, tmp, gate, test, _ = world
    out, png = tmp / "sweep.json", tmp / "fig" / "sweep.png"
    assert main(["pem", "sweep", str(run), str(tmp / "pem.json"), str(test), "--strengths", "0.5,2",
                 "--gate-set", str(gate), "--work", str(tmp / "work"), "--bootstrap", "20", "--out", str(out),
                 "--plot", str(png), "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r == json.loads(out.read_text()) and r["plot"] == str(png)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000
    assert r["gate_set"] == str(gate) and r["gate_seed"] == 1 and "without_gate_set" not in r
    assert len(r["constants"]) == 15 and r["constants"]["all_branches"] == ["radar", "camera_right", "lidar", "radar_lidar"]
    assert [p["strength"] for p in r["points"]] == [0.5, 2.0]
    for p in r["points"]:
        for key in OLD + NEW:
            _check_difference(p[key])
        mp = p["maps"]
        for n in ("context_constant", "physical_gate", "a_posteriori_oracle", "utility_oracle"):
            # scored by composing the constants' matchings: all branches' mAP is compare's to the 4th decimal
            assert p[f"{n}_minus_all_branches"]["value"] == pytest.approx(mp[n] - mp["all_branches"], abs=1.5e-4), n
        assert p["a_posteriori_oracle_minus_all_branches"]["value"] >= 0  # it starts from all branches
        room = p["room_for_context"]
        assert room["null_upper"] >= room["null_mean"] and room["above_null"] == (room["value"] > room["null_upper"])
        assert room["naive"]["estimate"] >= 0  # chosen on what it scores, with all branches among the constants
        assert p["context_constant"]["chosen_on"] == {"frames": 4, "sequences": 4, "fitting_frames": 4}
        assert set(p["context_constant"]["choice"]) == {"city", "fog", "all"}
        assert set(p["per_context"]) == {"city", "fog"}
        assert p["seconds"] >= sum(p["seconds_parts"].values()) - 0.2
    # the work directory holds each strength's draws on both sets
    assert json.loads((tmp / "work" / "gate-strength-2" / "manifest.json").read_text())["identity"]["seed"] == 1
    assert json.loads((tmp / "work" / "strength-0.5" / "manifest.json").read_text())["identity"]["strength"] == 0.5


def test_the_choices_are_the_gate_sets_and_the_test_set_cannot_move_them(world):
    from sensors.dataset import DatasetReader
    from study.engine.predictions import load
    from study.engine.scoring import fuse_selection, score
    from study.experiments.pem_sweep import constants_of, split_by_sequence, sweep

    run, tmp, gate, test_a, test_b = world
    ra = sweep(run, test_a, tmp / "pem.json", [1.0], tmp / "a", gate_set=gate, resamples=0)["points"][0]
    rb = sweep(run, test_b, tmp / "pem.json", [1.0], tmp / "b", gate_set=gate, resamples=0)["points"][0]
    assert ra["maps"]["late"] != rb["maps"]["late"]  # other test frames
    assert ra["context_constant"] == rb["context_constant"]
    assert ra["physical_gate"]["rules"] == rb["physical_gate"]["rules"]
    assert ra["physical_gate"]["candidates"] == rb["physical_gate"]["candidates"]
    # the choice is the best constant of each context on the gate set's validation frames (the one scoring path)
    gp = load(tmp / "a" / "gate-strength-1")
    _, val = split_by_sequence(gp.per_frame)
    frames = [gp.per_frame[p] for p in val]
    constants = constants_of(gp.branches, gp.branch_sensors)
    per = {n: score(fuse_selection(frames, [tuple(b)] * len(frames), gp.branch_frames, "soft_nms"), DatasetReader(gate),
                    "camera_right", protocol=gp.manifest["identity"]["protocol"])["map_per_context"]
           for n, b in constants.items()}
    for ctx, chosen in ra["context_constant"]["choice"].items():
        if ctx != "all":
            best = max(v[ctx] for v in per.values() if v[ctx] is not None)
            assert per[chosen][ctx] == pytest.approx(best, abs=1e-4), (ctx, chosen, best)
    assert ra["room_for_context"] is None and ra["context_constant_minus_all_branches"]["ci95"] is None


def test_the_oracles_read_each_frames_own_ground_truth(world):
    from sensors.dataset import DatasetReader
    from study.engine.predictions import load
    from study.engine.scoring import frame_ground_truth
    from study.experiments.pem_sweep import (
        Constants,
        a_posteriori_choice,
        constants_of,
        frame_utility,
        utility_choice,
    )

    run, tmp, gate, test, _ = world
    p = load(tmp / "work" / "strength-0.5")
    reader = DatasetReader(test)
    c = Constants(p.per_frame, constants_of(p.branches, p.branch_sensors), p.branch_frames, "soft_nms", reader,
                  p.manifest["identity"]["protocol"])
    choice = utility_choice(c)
    for i, (meta, chosen) in enumerate(zip(c.metas, choice)):
        gt = frame_ground_truth(reader, meta, "camera_right", None, c.protocol)
        u = {n: frame_utility(f[i][1], gt) for n, f in c.fused.items()}
        assert u[chosen] == max(u.values()) and (chosen == "all_branches") == (u["all_branches"] == max(u.values()))
    assert set(choice) != {"all_branches"}  # (on these frames it chooses: the check above is not only the tie rule)
    # the mAP oracle: not below all branches, and no single frame's change raises the pooled mAP any more
    # (tests/fusion/test_bounds.py: it finds a known best choice)
    greedy = a_posteriori_choice(c)
    best = c.map_of(greedy)
    assert best >= c.map_of(["all_branches"] * len(greedy))
    for i in range(len(greedy)):
        for n in c.constants:
            assert c.map_of(greedy[:i] + [n] + greedy[i + 1:]) <= best + 1e-9, (i, n)


def test_without_a_gate_set_the_chosen_methods_are_absent_and_the_text_says_why(world, capsys):
    run, tmp, gate, test, _ = world
    base = ["pem", "sweep", str(run), str(tmp / "pem.json"), str(test), "--strengths", "1", "--work", str(tmp / "w0")]
    assert main([*base, "--bootstrap", "0", "--plot", str(tmp / "x.png")]) == 2
    err = capsys.readouterr().err
    assert "--plot" in err and len(err.strip().splitlines()) == 1 and not (tmp / "w0").exists()
    assert main([*base, "--bootstrap", "10"]) == 0
    text = capsys.readouterr().out
    assert "no --gate-set: the per-context constant and the physical gate" in text
    assert text.count("(no --gate-set)") == 2 and "a-posteriori oracle - all_branches" in text
    assert main([*base, "--gate-set", str(test), "--bootstrap", "0"]) == 2
    assert "the same frames as the test set" in capsys.readouterr().err



def _cell(d) -> str:
    iv = d["ci95"]
    return f"{d['value']:+.3f} [{iv[0]:+.3f}, {iv[1]:+.3f}]"


def _verdicts(points, key) -> dict:
    out: dict = {}
    for p in points:
        out[p[key]["verdict"]] = out.get(p[key]["verdict"], 0) + 1
    return out


def test_docs_sweep_numbers_are_the_record():
    """docs/pem.md's sweep section of 2026-12-08: every cell is the record's, and so is every count and
    range its text states (the networks' numbers are the cpu-verdict study's report)."""
    import re
    from pathlib import Path

    from study.engine.scoring import difference_interval

    root = Path(__file__).resolve().parents[2]
    flat = re.sub(r"\s+", " ", (root / "docs" / "pem.md").read_text())
    rec = json.loads((root / "results" / "pem_sweep_2026-12-08.json").read_text())
    assert rec["date"] == "2026-12-08" and "EPYC" in rec["cpu"] and "avx512f" in rec["cpu"]
    assert (root / "results" / "pem_sweep_2026-12-08.png").is_file()
    points = [p for run in rec["sweeps"].values() for p in run["points"]]
    assert len(points) == 12 and all(run["resamples"] == 500 and run["gate_set"] for run in rec["sweeps"].values())
    for seed, run in rec["sweeps"].items():
        for p in run["points"]:
            row = (f"| {p['strength']:g} | {seed} | " + " | ".join(_cell(p[k]) for k in (
                "all_branches_minus_late", "context_constant_minus_all_branches", "physical_gate_minus_all_branches",
                "room_for_context", "a_posteriori_oracle_minus_all_branches")) + f" | {p['seconds']} |")
            assert row in flat, row
            room, naive = p["room_for_context"], p["room_for_context"]["naive"]
            row = (f"| {p['strength']:g} | {seed} | {room['null_upper']:+.3f} | {naive['estimate']:+.3f} "
                   f"[{naive['interval'][0]:+.3f}, {naive['interval'][1]:+.3f}] | "
                   f"{_cell(p['utility_oracle_minus_all_branches'])} |")
            assert row in flat, row
    seconds = [p["seconds"] for p in points]
    assert f"{min(seconds)} to {max(seconds)}" in flat
    # the counts the answers state
    gates = {k: _verdicts(points, f"{k}_minus_all_branches") for k in ("knowledge", "context_constant", "physical_gate")}
    assert sum(v.get("above", 0) for v in gates.values()) == 0 and "0 of 36" in flat
    below = [gates[k].get("below", 0) for k in gates]
    assert (f"{sum(below)} of the 36 are resolved below (knowledge {below[0]}, per-context constant {below[1]}, "
            f"physical gate {below[2]})") in flat
    room = _verdicts(points, "room_for_context")
    assert room.get("above", 0) == 0 and not any(p["room_for_context"]["above_null"] for p in points)
    assert f"resolved below in {room['below']} of 12 points, never above its null" in flat
    assert not any(iv and iv[0] > 0 for p in points for k, per in p["per_context"].items()
                   for n, iv in per.items() if "oracle" not in n)
    fog = sum("camera_right" in p["context_constant"]["without"]["fog"] for p in points)
    snow = sum(p["context_constant"]["choice"]["snow"] == "single:camera_right" for p in points)
    rules = [r["text"] for p in points for r in p["physical_gate"]["rules"]]
    assert (f"the per-context constant in {fog} of 12 points; the physical gate's \"drop camera_right when "
            f"visibility_m <= 370.8\" in {rules.count('drop camera_right when visibility_m <= 370.8')} of 12") in flat
    assert f"keep only the camera in snow (the constant in {snow} of 12)" in flat
    assert f"(\"drop radar when snow_mm_h >= 0.213\" in {rules.count('drop radar when snow_mm_h >= 0.213')} of 12)" in flat
    oracle = [p["a_posteriori_oracle_minus_all_branches"] for p in points]
    assert all(d["verdict"] == "above" for d in oracle)
    assert f"{min(d['value'] for d in oracle):+.3f} to {max(d['value'] for d in oracle):+.3f}, flat over strength" in flat
    assert f"below all branches in {_verdicts(points, 'utility_oracle_minus_all_branches')['below']} of 12 points" in flat
    at1 = [p for p in points if p["strength"] == 1.0]

    def span(key, sub=None):
        v = sorted((p[key] if sub is None else p[key][sub])["value" if sub is None else "estimate"] for p in at1)
        return v[0], v[-1]

    lo, hi = span("all_branches_minus_late")
    assert all(p["all_branches_minus_late"]["verdict"] == "above" for p in at1) and f"({lo:+.3f} to {hi:+.3f};" in flat
    lo, hi = span("room_for_context", "naive")
    assert all(p["room_for_context"]["naive"]["interval"][0] > 0 for p in at1) and f"the naive room {lo:+.3f} to {hi:+.3f}" in flat
    lo, hi = span("room_for_context")
    assert f"The split-sample room at strength 1 ({lo:+.3f} to {hi:+.3f})" in flat
    pg = [p["physical_gate_minus_all_branches"] for p in at1]
    assert f"({pg[0]['value']:+.3f} to {min(d['value'] for d in pg):+.3f}, below on draws 1 and 2)" in flat
    assert [d["verdict"] for d in pg] == ["not resolved", "below", "below"]
    # the networks' verdict, from the cpu-verdict study's report
    r = json.loads((root / "results" / "study_cpu_verdict" / "report.json").read_text())["results"]
    ci, ms = r["intervals"]["per_context"]["all"], r["methods"]

    def net(a, b):
        lo, hi = difference_interval(ci, a, b)
        return f"{ms[a]['map'] - ms[b]['map']:+.3f} [{lo:+.3f}, {hi:+.3f}]"

    room_net = r["bounds"]["room_for_context"]["all"]
    assert f"all_branches - late {net('all_branches', 'late')}, no learned gate" in flat
    assert f"the physical gate minus all_branches {net('physical_gate', 'all_branches')}" in flat
    assert (f"room for context {room_net['estimate']:+.3f} [{room_net['interval'][0]:+.3f}, "
            f"{room_net['interval'][1]:+.3f}] (the naive room)") in flat
