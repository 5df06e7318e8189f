"""`hydrabench pem known-answer` (issue 49, item 4): in a world where each context's best branch is
known by construction, the gates that learn from context recover it, the context-blind constant does
not (so the check can fail), and the construction itself is checked on the test frames."""

import json

import pytest

from fusion.pem import KNOWN_ANSWER_RULE, known_answer_world
from sensors.generate import GenerateConfig
from study.cli import main
from tests.study.test_pem_study import FIT, _seed_pem

# two contexts whose answers differ (camera in the clear city, radar in fog), sequences of one frame:
# the gate set alternates its four sequences per context into fitting and validation
GATE = GenerateConfig(contexts=("city", "fog"), frames_per_context=4, sequence_length=1, seed=31)
TEST = GenerateConfig(contexts=("city", "fog"), frames_per_context=4, sequence_length=1, seed=32)
SENSORS = {"radar": ("radar",), "camera_right": ("camera_right",), "lidar": ("lidar",), "radar_lidar": ("radar", "lidar")}


def test_the_world_makes_the_rules_branch_strong_and_every_other_weak():
    world, answer = known_answer_world(SENSORS, sorted(KNOWN_ANSWER_RULE))  # strong 8, weak 1/8
    assert answer == {"city": "camera_right", "junction": "camera_right", "motorway": "camera_right",
                      "rural": "camera_right", "night": "lidar", "fog": "radar", "rain": "radar", "snow": "radar"}
    for ctx, best in answer.items():
        assert world[best][ctx] == 8.0 and all(world[b][ctx] == 0.125 for b in SENSORS if b != best)
    with pytest.raises(ValueError, match="moon"):
        known_answer_world(SENSORS, ["moon"])
    with pytest.raises(ValueError, match="lidar"):
        known_answer_world({"radar": ("radar",), "camera_right": ("camera_right",)}, ["night"])
    with pytest.raises(ValueError, match="exceed"):
        known_answer_world(SENSORS, ["fog"], strong=1.0, weak=1.0)


@pytest.fixture(scope="module")
def world(shared_dataset, tmp_path_factory):
    from study.engine.reference_model import resolve_run

    tmp = tmp_path_factory.mktemp("known")
    _seed_pem(resolve_run("cpu-frontier"), shared_dataset(FIT), tmp / "pem.json")
    return tmp, shared_dataset(GATE), shared_dataset(TEST)


def test_learners_recover_the_rule_and_the_blind_constant_does_not(world, capsys):
    tmp, gate, test = world
    out = tmp / "result.json"
    assert main(["pem", "known-answer", str(tmp / "pem.json"), str(test), "--gate-set", str(gate), "--work", str(tmp / "work"),
                 "--bootstrap", "50", "--out", str(out), "--json"]) == 0  # the default world: strong 8, weak 1/8
    r = json.loads(capsys.readouterr().out)
    assert r == json.loads(out.read_text())
    assert r["world"]["answer"] == {"city": "camera_right", "fog": "radar"}
    assert r["construction_holds"], r["methods"]["context_oracle"]  # the test frames agree with the construction
    m = r["methods"]
    assert r["chosen_on_validation"]["context_constant"] == {"city": "camera_right", "fog": "radar"}
    assert m["context_constant"]["recovers_the_rule"] and m["context_constant"]["agreement_all"] == 1.0
    assert m["measured_gate"]["recovers_the_rule"], m["measured_gate"]["agreement"]
    # the physical gate: in the clear city no rule can fire (it runs every branch, the answer among
    # them); it is judged in fog alone, on the branch it runs alone there
    pg = m["physical_gate"]
    assert pg["expressible_contexts"] == ["fog"] and pg["agreement"]["city"] == 0.0 and pg["keeps_answer"]["city"] == 1.0
    assert pg["recovers_the_rule"] == (pg["agreement"]["fog"] >= 0.9) and "minus_answer_ci95" in pg
    assert set(r["physical_gate"]["candidates"]) == {f"{s} / fog" for s in ("radar", "camera_right", "lidar")}
    # one branch for both contexts: right in one of them at most
    assert not m["best_constant"]["recovers_the_rule"] and m["best_constant"]["agreement_all"] <= 0.5
    assert m["answer"]["agreement_all"] == 1.0 and "minus_answer_ci95" not in m["answer"]
    for name in ("best_constant", "knowledge"):
        lo, hi = m[name]["minus_answer_ci95"]
        assert lo <= hi
    # choosing the answer scores above the blind constant: the world is what it says it is
    assert m["answer"]["map"] > m["best_constant"]["map"]
    assert r["frames"] == {"fit": 4, "validation": 4, "test": 8}
    man = json.loads((tmp / "work" / "test" / "manifest.json").read_text())
    assert man["identity"]["world"]["radar"] == {"city": 0.125, "fog": 8.0} and man["identity"]["seed"] == 1


def test_refusals_are_one_line(world, shared_dataset, tmp_path, capsys):
    tmp, gate, test = world
    base = ["pem", "known-answer", str(tmp / "pem.json")]
    assert main([*base, str(test), "--gate-set", str(gate), "--work", str(tmp_path / "w"), "--strong", "1", "--weak", "2"]) == 2
    err = capsys.readouterr().err
    assert "--strong" in err and len(err.strip().splitlines()) == 1
    one_sequence = shared_dataset(FIT)  # three frames of one sequence per context
    assert main([*base, str(test), "--gate-set", str(one_sequence), "--work", str(tmp_path / "w2"), "--bootstrap", "0"]) == 2
    err = capsys.readouterr().err
    assert "one sequence of" in err and len(err.strip().splitlines()) == 1


def test_the_docs_table_is_the_results_file():
    """docs/pem.md's known-answer table, row by row, against results/pem_known_answer_*.json."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    r = json.loads(sorted((root / "results").glob("pem_known_answer_*.json"))[-1].read_text())
    text = (root / "docs" / "pem.md").read_text()
    section = text.split("## A known-answer world for the gates", 1)[1].split("\n## ", 1)[0]
    assert r["construction_holds"] and "The construction holds" in section
    rows = {m.group(1): m.group(2).split(" | ") for m in re.finditer(r"^\| (\w+) \| [^|]+ \| (.+) \|$", section, re.M)
            if m.group(1) != "method"}  # (the header)
    assert set(rows) == set(r["methods"]) - {"answer"}
    for name, (agree, least, mean_ap, minus) in rows.items():
        m = r["methods"][name]
        assert agree == f"{100 * m['agreement_all']:.1f} %".replace("100.0 %", "100 %"), name
        worst = min(m.get("expressible_contexts") or m["agreement"], key=m["agreement"].get)
        want_least = "100 %" if m["agreement"][worst] == 1 else f"{worst} {100 * m['agreement'][worst]:.0f} %"
        assert least == want_least, name
        assert mean_ap == f"{m['map']:.3f}", name
        lo, hi = m["minus_answer_ci95"]
        assert minus == ("0" if lo == hi == 0 else f"[{lo:+.3f}, {hi:+.3f}]"), name
        if name in ("context_constant", "measured_gate", "best_constant"):
            assert m["recovers_the_rule"] == (min(m["agreement"].values()) >= r["recover"]), name
    pg = r["methods"]["physical_gate"]
    assert pg["recovers_the_rule"] == all(pg["agreement"][c] >= r["recover"] for c in pg["expressible_contexts"])
    assert ("does not recover the rule" if not pg["recovers_the_rule"] else "recovers the rule") in section


def test_the_physical_gate_recovers_the_rule_when_it_runs_the_answer_alone_where_a_condition_holds():
    """`physical_row` on chosen selections: running the answer alone in every frame with a condition
    recovers the rule, whatever it runs in clear weather; keeping a weak branch beside it does not."""
    from types import SimpleNamespace

    from study.experiments.known_answer import physical_row

    metas = [{"context": "city", "conditions": []}] * 2 + [{"context": "fog", "conditions": ["fog"]}] * 2
    tp = SimpleNamespace(per_frame=[(m, None) for m in metas])
    answer = {"city": "camera_right", "fog": "radar"}
    scored = {"physical_gate": {"map": 0.5, "map_per_context": {}}}
    every = ("radar", "camera_right", "lidar")
    good = physical_row([every, every, ("radar",), ("radar",)], tp, answer, scored, None)
    assert good["recovers_the_rule"] and good["agreement"] == {"city": 0.0, "fog": 1.0} and good["expressible_contexts"] == ["fog"]
    assert good["agreement_all"] == 0.5 and good["keeps_answer"] == {"city": 1.0, "fog": 1.0}
    bad = physical_row([every, every, ("radar", "lidar"), ("radar",)], tp, answer, scored, None)
    assert not bad["recovers_the_rule"] and bad["agreement"]["fog"] == 0.5 and bad["keeps_answer"]["fog"] == 1.0
