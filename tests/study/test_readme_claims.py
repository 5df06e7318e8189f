"""scripts/readme_claims.py: the README's table of claims is what the script makes of the stored
cpu-verdict files; each cell's word follows its interval (holds, does not hold, not resolved, not
measured); the columns are the scorings they name (checked against training_seeds.json, written by
another script from the same reports)."""

import importlib.util
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
STORED = ROOT / "results" / "study_cpu_verdict"
spec = importlib.util.spec_from_file_location("readme_claims", ROOT / "scripts" / "readme_claims.py")
rc = importlib.util.module_from_spec(spec)
spec.loader.exec_module(rc)


def _report(maps: dict, diffs: dict, p_city: dict | None = None) -> dict:
    """A report with overall intervals `diffs` ("a - b": [lo, hi]) and, with `p_city`, one context whose
    intervals are the same and whose p-values are `p_city`."""
    per = {"all": {"sequences": 40, "map": {}, "difference": diffs}}
    if p_city is not None:
        per["city"] = {"sequences": 10, "map": {}, "difference": diffs, "p_value": p_city}
    return {"results": {"methods": {m: {"map": v, "map_per_context": {"city": v}} for m, v in maps.items()},
                        "dataset": {"contexts": ["city"]}, "intervals": {"resamples": 500, "per_context": per}}}


MAPS = {"single:radar": 0.2, "single:lidar": 0.25, "late": 0.3, "all_branches": 0.33, "hydrafusion:deep": 0.31}


def test_a_cell_says_what_its_interval_resolves():
    r = _report(MAPS, {"all_branches - late": [0.01, 0.05], "hydrafusion:deep - late": [-0.01, 0.03],
                       "late - single:radar": [0.05, 0.15], "late - single:lidar": [-0.09, -0.01],
                       "hydrafusion:deep - all_branches": [-0.06, -0.001]})["results"]
    assert rc._above(r, "all_branches", "late") == "holds: +0.030 [+0.010, +0.050]"
    assert rc._above(r, "hydrafusion:deep", "late") == "not resolved: +0.010 [-0.010, +0.030]"
    # stored one way round, asked the other: the interval turns round with the estimate
    assert rc._above(r, "late", "all_branches") == "does not hold: -0.030 [-0.050, -0.010]"
    assert rc._above(r, "physical_gate", "all_branches") == "not measured"
    # every single sensor: one resolved below is enough to fail, and it is the pair shown
    assert rc._all_above(r, "late", ["single:radar", "single:lidar"]) == \
        "does not hold; weakest: minus single:lidar +0.050 [-0.090, -0.010]"
    assert rc._all_above(r, "late", ["single:radar"]).startswith("holds; weakest: minus single:radar +0.100")
    # "no order": one resolved pair breaks it, either way round unless the claim names one way
    pairs = [("hydrafusion:deep", "all_branches"), ("hydrafusion:deep", "late")]
    assert rc._none_ordered(r, pairs).startswith("does not hold (1 of 2 ordered); nearest: hydrafusion:deep - all_branches")
    assert rc._none_ordered(r, pairs, ways=(1,)).startswith("holds (0 of 2 ordered)")
    assert rc._none_ordered(r, [("x", "late")]) == "not measured"


def test_per_context_orders_are_judged_over_the_whole_family():
    diffs = {"all_branches - late": [0.01, 0.05], "hydrafusion:deep - late": [0.01, 0.03],
             "late - single:radar": [0.05, 0.15], "late - single:lidar": [-0.09, 0.01],
             "single:radar - single:lidar": [-0.1, 0.02]}
    p = {k: 0.5 for k in diffs}
    # one p-value small enough to survive Holm over the family, one that would pass alone but not in it
    resolved = _report(MAPS, diffs, {**p, "all_branches - late": 0.001})
    assert rc._per_context(resolved) == "does not hold (1 of 6 orders resolved)"
    alone = _report(MAPS, diffs, {**p, "all_branches - late": 0.02})
    assert rc._per_context(alone) == "holds (0 of 6 orders resolved)"
    assert rc._per_context(_report(MAPS, diffs)) == "not measured"


def test_the_readmes_claims_are_what_the_script_makes_of_the_stored_files(tmp_path):
    assert rc.main([str(STORED), "--check"]) == 0, f"README.md's claims are stale: python scripts/readme_claims.py {STORED.relative_to(ROOT)}"
    readme = tmp_path / "README.md"
    readme.write_text(f"before\n{rc.BEGIN}\nold\n{rc.END}\nafter\n")
    assert rc.main([str(STORED), "--readme", str(readme), "--check"]) == 1
    assert rc.main([str(STORED), "--readme", str(readme)]) == 0
    text = readme.read_text()
    assert text.startswith(f"before\n{rc.BEGIN}\n") and text.endswith(f"{rc.END}\nafter\n") and "\nold\n" not in text
    assert rc.main([str(STORED), "--readme", str(readme), "--check"]) == 0
    readme.write_text("no markers\n")
    assert rc.main([str(STORED), "--readme", str(readme)]) == 2 and readme.read_text() == "no markers\n"
    assert rc.main([str(tmp_path / "missing"), "--readme", str(readme)]) == 2


def _rows(block: str, first: str) -> dict[str, list[str]]:
    lines = block.splitlines()
    i = next(i for i, x in enumerate(lines) if x.startswith(f"| {first} |"))
    out = {}
    for line in lines[i + 2:]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip("|").split("|")]
        out[cells[0]] = cells[1:]
    return out


def test_the_columns_are_the_scorings_training_seeds_json_names():
    """training_seeds.json (scripts/training_seeds.py, from the same three reports) holds each headline
    pair per scoring: the table's cells for those pairs carry its estimates and intervals, column by column."""
    rows = _rows(rc.claims_block(STORED), "claim (test sets)")
    seeds = json.loads((STORED / "training_seeds.json").read_text())
    columns = ("seed0_test2001", "seed0", "seed1")
    assert [seeds["reports"][c]["test_set"]["seed"] for c in columns] == [2001, 2002, 2002]
    checked = 0
    for h in seeds["headline"]:
        a, b = h["pair"].split(" - ")
        if b != "late" or a not in ("all_branches", *rc.GATES):
            continue
        for cell, c in zip(rows[f"{a} above late fusion"], columns):
            d = h["per"][c]
            word = {"above": "holds", "below": "does not hold", "not resolved": "not resolved"}[d["verdict"]]
            assert cell == f"{word}: {d['estimate']:+.3f} [{d['ci95'][0]:+.3f}, {d['ci95'][1]:+.3f}]", (a, c)
            checked += 1
    assert checked == 15


def test_the_radar_lidar_claim_compares_with_a_cheaper_branch_and_crossovers_come_from_both_sweeps():
    report = json.loads((STORED / "report.json").read_text())["results"]
    energy = report["bounds"]["front"]["energy_point"]
    assert all(energy["radar_lidar"] < energy[g] for g in rc.GATES)  # "(costs less)" in the claim
    rep = json.loads((STORED / "crossover_replication.json").read_text())
    own = _rows(rc.claims_block(STORED), "claim (sets of its own)")
    night = next(x for x in rep["crossings"] if (x["base"], x["condition"], x["sensor"]) == ("all_branches", "night", "camera_right"))
    cells = own["fusing camera_right costs mAP at night (all branches with minus without it)"]
    assert [f"from {night[s]['first_resolved_below']:.3g} lux" in c for s, c in zip("ab", cells)] == [True, True]
    assert all(c.startswith("holds") for c in cells)
