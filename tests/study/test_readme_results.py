"""scripts/readme_results.py: the README's results block is a function of a study's report JSON,
replaced between its markers only, idempotently, and refused without them; and every number block the
README and docs/results.md quote from a file in results/ is that file's (the README's block is what the
script makes of results/study_cpu/report.json; each table of the reference run and of EcoFusion is
recomputed cell by cell from its JSON)."""

import importlib.util
import json
import re
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
    (tmp_path / "report.html").write_text("<html></html>")
    (tmp_path / "README.md").write_text(readme)
    args = [str(tmp_path / "report.json"), "--readme", str(tmp_path / "README.md")]
    assert rr.main([*args, "--check"]) == 1  # stale
    assert rr.main(args) == 0
    assert (tmp_path / "README.md").read_text() == rr.replace_block(readme, rr.results_block(REPORT, ("report.html",)))
    assert rr.main([*args, "--check"]) == 0
    assert rr.main([str(tmp_path / "missing.json"), "--readme", str(tmp_path / "README.md")]) == 2


def test_verdict_and_figure_print_and_draw_and_leave_the_readme_alone(tmp_path, capsys):
    from study.report.verdict import verdict_sentences

    report = ROOT / "results" / "study_cpu" / "report.json"
    readme = tmp_path / "README.md"
    readme.write_text("no markers\n")  # untouched, so the markers are not needed
    assert rr.main([str(report), "--readme", str(readme), "--verdict", "--figure", str(tmp_path / "v.png")]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert printed == verdict_sentences(json.loads(report.read_text())) and printed[0].startswith("Overall, ")
    assert (tmp_path / "v.png").read_bytes()[:4] == b"\x89PNG" and readme.read_text() == "no markers\n"
    # a report without intervals: the sentences say so, and there is no figure to draw
    (tmp_path / "bare.json").write_text(json.dumps(REPORT))
    assert rr.main([str(tmp_path / "bare.json"), "--verdict"]) == 0
    assert "resolves no order" in capsys.readouterr().out
    assert rr.main([str(tmp_path / "bare.json"), "--figure", str(tmp_path / "b.png")]) == 2
    assert not (tmp_path / "b.png").exists()


def test_the_repository_readme_has_one_block():
    text = (ROOT / "README.md").read_text()
    assert text.count(rr.BEGIN) == 1 and text.count(rr.END) == 1


# --- every number block the README and docs/ quote from a file in results/ is that file's ---------------

RESULTS = ROOT / "results"


def table(doc: Path, header: str) -> dict[str, list[str]]:
    """The Markdown table of `doc` whose header row starts with `header`: {first cell: other cells}, bold
    marks dropped; an AssertionError when the table is missing."""
    lines = doc.read_text().splitlines()
    starts = [i for i, line in enumerate(lines) if line.startswith(header)]
    assert len(starts) == 1, f"{doc.name}: one table headed {header!r}"
    rows = {}
    for line in lines[starts[0] + 2:]:
        if not line.startswith("|"):
            break
        cells = [c.strip().replace("**", "") for c in line.strip("|").split("|")]
        rows[cells[0]] = cells[1:]
    return rows


def _load(name: str) -> dict:
    return json.loads((RESULTS / name).read_text())


def _f(v, nd: int) -> str:
    return "-" if v is None else f"{v:.{nd}f}"


def test_the_readmes_block_is_what_the_script_makes_of_the_stored_cpu_study():
    report = RESULTS / "study_cpu_verdict" / "report.json"
    assert rr.main([str(report), "--readme", str(ROOT / "README.md"), "--check"]) == 0, \
        f"README.md's results block is stale: python scripts/readme_results.py {report.relative_to(ROOT)}"


def test_the_numbers_the_readme_and_docs_quote_from_the_cpu_study_are_its():
    readme = (ROOT / "README.md").read_text()
    block = readme.split(rr.BEGIN)[1].split(rr.END)[0]
    # the README's reading of the block: every decimal number in it is one of the block's, or one of
    # the replication's on an independent test set (results/study_cpu_verdict/replication_test2002.json)
    reading = readme.split(rr.END)[1].split("\n## ")[0]
    # the table of claims is checked on its own (tests/study/test_readme_claims.py)
    claims_begin, claims_end = "<!-- study-claims:begin", "<!-- study-claims:end -->"
    reading = reading.split(claims_begin)[0] + reading.split(claims_end)[1]
    numbers = re.findall(r"[-+]?\d+\.\d+", reading)
    rep = _load("study_cpu_verdict/replication_test2002.json")
    quoted = [f"{h['b']:+.3f}" for h in rep["headline"]] + [f"{x:+.3f}" for h in rep["headline"] for x in h["interval_b"]]
    quoted.append(f"{rep['summary']['agreement_rate']:.3f}")
    # ... or one of the second detector seed's (results/study_cpu_verdict/training_seeds.json)
    seeds = _load("study_cpu_verdict/training_seeds.json")
    for row in seeds["headline"]:
        for c in row["per"].values():
            quoted += [f"{c['estimate']:+.3f}", *(f"{x:+.3f}" for x in c["ci95"])]
    for name in ("training", "test_set"):
        quoted += [f"{seeds[name][k]:.2f}" for k in ("median_ratio", "max_ratio")]
    in_block = set(re.findall(r"[-+]?\d+\.\d+", block))  # whole numbers, not substrings ("0.43" of "0.430")
    assert len(numbers) >= 5 and not [n for n in numbers if n not in in_block and n not in quoted], numbers
    # docs/results.md's reading: every 3-decimal interval is one of the report's (any context, any pair)
    intervals = _load("study_cpu/report.json")["results"]["intervals"]["per_context"]
    stored = {f"[{lo:+.3f}, {hi:+.3f}]" for ctx in intervals.values() for kind in ("map", "difference")
              for lo, hi in ctx[kind].values()}
    stored |= {f"[{-hi:+.3f}, {-lo:+.3f}]" for ctx in intervals.values() for lo, hi in ctx["difference"].values()}
    text = (ROOT / "docs" / "results.md").read_text()
    reading = text.split("**What the `cpu` study resolves**")[1].split("\n## ")[0]
    quoted = re.findall(r"\[[-+]\d\.\d{3}, [-+]\d\.\d{3}\]", reading)
    assert len(quoted) >= 6 and not [q for q in quoted if q not in stored], quoted


REF3 = {"camera_right": "camera_right", "radar": "radar", "lidar": "lidar", "late fusion (Soft-NMS)": None}
CONTEXTS = ["city", "junction", "motorway", "rural", "rain", "fog", "snow", "night"]


def _branch(result: dict, name):
    return result if name is None else result["per_branch_reference"][name]


def test_the_reference_runs_table_1_analogue_and_range_bins_are_their_files():
    e4, e2 = _load("ref3_e4_reference.json"), _load("ref3_reference.json")
    doc = ROOT / "docs" / "results.md"
    rows = table(doc, "| branch | city | junction |")
    assert set(rows) == set(REF3)
    for row, name in REF3.items():
        b4, b2 = _branch(e4, name), _branch(e2, name)
        expected = [_f(b4["map_vehicles_per_context"][c], 3) for c in CONTEXTS]
        expected.append(f"{_f(b4['map_vehicles'], 3)} (was {_f(b2['map_vehicles'], 3)})")
        assert rows[row] == expected, row
    rows = table(doc, "| branch | 0-15 m | 15-30 m |")
    for row, name in {**REF3, "late fusion": None}.items():
        if row in rows:
            assert rows[row] == [_f(_branch(e4, name)["map_vehicles_per_range"][b], 3)
                                 for b in ("0-15", "15-30", "30-50", "50-100")], row
    assert len(rows) == 4


def test_the_reference_runs_intervals_are_their_file():
    ci = _load("ref3_e4_reference_ci.json")["ci95"]["per_context"]
    rows = table(ROOT / "docs" / "results.md", "| 95 % interval | city |")
    names = {"camera_right": "camera_right", "radar": "radar", "lidar": "lidar", "late fusion": "fused"}
    for row, name in names.items():
        assert rows[row] == [f"[{ci[c]['map_vehicles'][name][0]:.2f}, {ci[c]['map_vehicles'][name][1]:.2f}]"
                             for c in [*CONTEXTS, "all"]], row
    for row in ("radar - lidar", "late fusion - radar", "late fusion - lidar"):
        pair = row.replace("late fusion", "fused")
        assert rows[row] == [f"[{ci[c]['difference'][pair][0]:+.2f}, {ci[c]['difference'][pair][1]:+.2f}]"
                             for c in [*CONTEXTS, "all"]], row
    assert len(rows) == 7


TWINS = {"fog": "ref3_e4_fogtwins.json", "rain": "ref3_e4_raintwins.json", "snow": "ref3_e4_snowtwins.json",
         "night (city, lit)": "ref3_e4_nighttwins.json", "night (rural, unlit)": "ref3_e4_ruralnight_twins.json"}
TWIN_BRANCHES = {"radar (BEV)": "radar", "lidar (BEV)": "lidar", "camera_right": "camera_right",
                 "late fusion (camera frame)": None}


def test_the_twins_table_is_the_twin_files():
    doc = ROOT / "docs" / "results.md"
    lines = [line for line in doc.read_text().splitlines() if line.startswith(tuple(f"| {c} | " for c in TWINS))]
    assert len(lines) == len(TWINS) * len(TWIN_BRANCHES)
    for line in lines:
        cond, branch, *cells = [c.strip() for c in line.strip("|").split("|")]
        twins = _load(TWINS[cond])["twins"]
        t = twins["fused"] if TWIN_BRANCHES[branch] is None else twins["branches"][TWIN_BRANCHES[branch]]
        lo, hi = t["ci95"]["all"]["retained"]
        expected = [f"{t['degraded']:.3f} / {t['clear']:.3f}", f"{t['retained']:.2f} [{lo:.2f}, {hi:.2f}]"]
        expected += [_f((t["per_severity"].get(str(s)) or {}).get("retained"), 2) for s in range(1, 6)]
        assert cells == expected, (cond, branch)


def test_the_ecofusion_table_1_analogue_is_its_file():
    ev = _load("eco_ref3/evaluate_ci.json")
    assert ev["lambda_e"] == 0.01
    rows = table(ROOT / "docs" / "results.md", "| Table 1 analogue")
    late = ev["baselines"]["late"]
    names = {"radar alone": ("baselines", "none_radar"), "camera_right alone": ("baselines", "none_camera_right"),
             "lidar alone": ("baselines", "none_lidar"), "late (radar + camera_right + lidar)": ("baselines", "late"),
             "EcoFusion attention, lambda_E 0 / 0.01 / 0.05": ("gates", "attention"),
             "EcoFusion knowledge (any lambda_E)": ("gates", "knowledge"),
             "EcoFusion loss-based (oracle), lambda_E 0.01": ("gates", "loss_based")}
    assert set(rows) == set(names)
    for row, (kind, name) in names.items():
        m = ev[kind][name]
        ratio = "1" if name == "late" else _f(m["energy"] / late["energy"], 2)
        assert rows[row] == [_f(m["map"], 3), _f(m["energy"], 2), f"{m['latency_ms']:.0f}", ratio], row


def _close(quoted: str, value) -> bool:
    """`quoted` is `value` rounded to the digits it shows."""
    digits = len(quoted.split(".")[1]) if "." in quoted else 0
    return value is not None and abs(float(quoted) - value) <= 0.5 * 10 ** -digits + 1e-9


def test_the_fusion_theory_table_is_its_file():
    """docs/results.md's SMALL_CONFIG table (`hydrabench theory ... --json`, results/theory_small.json): each
    method's mean +- standard error (median) of the squared error, and the objects with a gross error."""
    theory = _load("theory_small.json")["details"]
    rows = table(ROOT / "docs" / "results.md", "| cell | camera | lidar | radar | full, nominal R |")
    cells = {"clear": ("fog", "0"), "fog, visibility 30-75 m": ("fog", "5"), "rain 25-50 mm/h": ("rain", "5"),
             "night": ("night", "5")}
    columns = ["camera", "lidar", "radar", "full_nominal", "full_true", "selective", "gated", "gated_true"]
    assert set(rows) == set(cells)
    for row, (cond, sev) in cells.items():
        d = theory[cond][sev]
        *quoted, gross = rows[row]
        for col, text in zip(columns, quoted, strict=True):
            r = d["robust"][col]
            m = re.fullmatch(r"([\d.]+) \+- ([\d.]+) \(([\d.]+)\)", text)
            if col == "selective":  # its mean, and the sensors it selects
                assert _close(text.split(" (")[0], r["mean"]), (row, col, text)
            else:
                assert m and _close(m[1], r["mean"]) and _close(m[2], r["se"]) and _close(m[3], r["median"]), \
                    (row, col, text)
        g = d["gross"]["objects_with_gross"]
        assert gross == f"{g['nominal']} / {g['measured']} of {d['compared']}", (row, gross)


def test_the_full_theory_sweeps_table_is_its_file():
    """docs/results.md's table of the cells where fusion with the measured R loses to the best sensor alone
    (`hydrabench theory --json`, results/theory_default.json)."""
    theory = _load("theory_default.json")["details"]
    rows = table(ROOT / "docs" / "results.md", "| cell | best alone |")
    assert len(rows) == 6
    for row, cells in rows.items():
        cond, sev = row.split()[:2]
        d = theory[cond][sev]
        best_alone, full, paired, gross, without, weather, gated = cells
        best = d["paired_vs_best_single"]["best_single"]
        name, value = best_alone.split()
        assert name == best and _close(value, d["robust"][best]["mean"]), (row, best_alone)
        r = d["robust"]["full_true"]
        m = re.fullmatch(r"([\d.]+) \+- ([\d.]+) \(([\d.]+)\)", full)
        assert m and _close(m[1], r["mean"]) and _close(m[2], r["se"]) and _close(m[3], r["median"]), (row, full)
        p = d["paired_vs_best_single"]["full_true"]
        m = re.fullmatch(r"([-+][\d.]+) \+- ([\d.]+)", paired)
        assert m and _close(m[1], p["mean"]) and _close(m[2], p["se"]), (row, paired)
        g = d["gross"]
        share = round(100 * g["sse_share"]["full_true"])
        assert gross == f"{g['objects_with_gross']['measured']} of {d['compared']}: {share} %", (row, gross)
        w = g["mse_without_gross"]["measured"]
        a, b = without.split(" / ")
        assert _close(a, w[best]) and _close(b, w["full_true"]), (row, without)
        assert int(weather.split()[0].rstrip(",")) == g["per_sensor"]["measured"]["lidar"]["causes"].get("weather", 0), \
            (row, weather)
        gate = {}
        for sensor in g["per_sensor"]["measured"].values():
            for what, n in sensor["gate"]["measured"].items():
                gate[what] = gate.get(what, 0) + n
        value, what = gated.split(" (")
        assert _close(value, d["robust"]["gated_true"]["mean"]), (row, gated)
        assert dict((k, int(n)) for k, n in (x.split() for x in what.rstrip(")").split(", "))) == gate, (row, gated, gate)


def test_the_other_protocols_figures_are_their_files():
    """The paragraph of docs/results.md on the `visible` and `bev` protocols (results/ref3_e4_{visible,bev}.json,
    and results/ref3_visible.json in brackets)."""
    text = (ROOT / "docs" / "results.md").read_text()
    para = " ".join(text.split("The same run after 4 epochs under the other protocols")[1].split("\n\n")[0].split())
    v4, v2, bev = _load("ref3_e4_visible.json"), _load("ref3_visible.json"), _load("ref3_e4_bev.json")
    m = re.search(r"late fusion ([\d.]+) \(([\d.]+)\), radar ([\d.]+) \(([\d.]+)\), lidar ([\d.]+) \(([\d.]+)\), "
                  r"camera ([\d.]+) \(([\d.]+)\)", para)
    assert m, para
    expected = [v4["map_vehicles"], v2["map_vehicles"]]
    for name in ("radar", "lidar", "camera_right"):
        expected += [v4["per_branch_reference"][name]["map_vehicles"], v2["per_branch_reference"][name]["map_vehicles"]]
    assert all(_close(q, e) for q, e in zip(m.groups(), expected, strict=True)), (m.groups(), expected)
    m = re.search(r"radar ([\d.]+), lidar ([\d.]+) vehicle mAP, per range bin radar ([\d.]+) / ([\d.]+) / ([\d.]+) / "
                  r"([\d.]+) and lidar ([\d.]+) / ([\d.]+) / ([\d.]+) / ([\d.]+)", para)
    assert m, para
    radar, lidar = bev["per_branch"]["radar"], bev["per_branch"]["lidar"]
    bins = ("0-15", "15-30", "30-50", "50-100")
    expected = [radar["map_vehicles"], lidar["map_vehicles"], *(radar["map_vehicles_per_range"][b] for b in bins),
                *(lidar["map_vehicles_per_range"][b] for b in bins)]
    assert all(_close(q, e) for q, e in zip(m.groups(), expected, strict=True)), (m.groups(), expected)


def test_the_cpu_studys_clear_daylight_camera_table_is_its_files():
    rows = table(ROOT / "docs" / "results.md", "| camera, clear daylight | 0-15 m |")
    assert len(rows) == 2
    for proto in ("visible", "reference"):
        r = _load(f"cpu_study_camera_clear_{proto}.json")
        assert r["branches"] == ["camera_right"] and r["contexts"] == ["city", "junction", "motorway", "rural"]
        bins = [_f(r["map_vehicles_per_range"][b], 3) for b in ("0-15", "15-30", "30-50", "50-100")]
        assert rows[f"camera_right, `{proto}`"] == [*bins, _f(r["map_vehicles"], 3)], proto


def test_the_gate_inputs_table_is_its_file_and_the_study_report():
    """docs/results.md's gate-input table: the grid column from the stored study, the others from
    results/cpu_study_gate_inputs.json (train-gate / eco-train-gate on the study's run)."""
    runs = _load("cpu_study_gate_inputs.json")["runs"]
    study = _load("study_cpu/report.json")["results"]["gate_training"]
    rows = table(ROOT / "docs" / "results.md", "| gate | grid (the study's) |")
    for label, fam, cmd, gate in (("HydraFusion deep", "hydrafusion", "train-gate", "deep"),
                                  ("HydraFusion attention", "hydrafusion", "train-gate", "attention"),
                                  ("EcoFusion deep", "ecofusion", "eco-train-gate", "deep"),
                                  ("EcoFusion attention", "ecofusion", "eco-train-gate", "attention")):
        cells = [c.split(" ")[0] for c in rows[label]]
        assert cells[0] == _f(study[f"{fam}:{gate}"]["choice"]["regret"], 4), label
        for cell, variant in zip(cells[1:], ("poolingglobal", "contextinputs", "poolingglobalcontextinputs")):
            run = runs.get(f"{cmd}-{gate}-{variant}")
            assert cell == ("-" if run is None else _f(run["test_regret"], 4)), (label, variant)


def test_the_amp_parity_figures_in_benchmarks_are_its_file():
    r = _load("bench_amp_parity_2026-12-03.json")
    text = (ROOT / "BENCHMARKS.md").read_text()
    fp32, bf16 = (r["runs"][p] for p in ("fp32", "bf16"))
    iv = r["ci95_vehicle_map"]["radar"]
    assert f"| {fp32['train_seconds']:.0f} s | {bf16['train_seconds']:.0f} s (**" \
           f"{fp32['train_seconds'] / bf16['train_seconds']:.2f}x** faster) |" in text
    assert (f"| {fp32['branches']['radar']['map_vehicles']:.3f} [{iv['fp32'][0]:.3f}, {iv['fp32'][1]:.3f}] | "
            f"{bf16['branches']['radar']['map_vehicles']:.3f} [{iv['bf16'][0]:.3f}, {iv['bf16'][1]:.3f}] |") in text
    assert f"**[{iv['bf16_minus_fp32'][0]:+.3f}, {iv['bf16_minus_fp32'][1]:+.3f}]**" in text


def test_the_arch_table_in_benchmarks_is_its_file():
    r = _load("bench_arch_2026-12-03.json")
    rows = table(ROOT / "BENCHMARKS.md", "| variant | parameters | float16 weights |")
    labels = {"base": "base (the `cpu` profile)", "dilation": "dilation (stride-1 stages dilated)",
              "bev stride 16": "BEV output stride 16 (layer3 back to stride 2)", "64 RoIs": "64 sampled RoIs (of 128)"}
    assert len(rows) == len(r["variants"])
    for name, v in r["variants"].items():
        cells = [c.replace("*", "") for c in rows[labels.get(name, name)]]
        assert cells[:2] == [f"{v['parameters_m']:.1f} M", f"{v['float16_mib']:.1f} MiB"], name
        assert cells[2:] == [f"{v['step_s']['fp32']:.2f} s", f"{v['speedup_vs_base']['fp32']:.2f}",
                             f"{v['step_s']['bf16']:.2f} s", f"{v['speedup_vs_base']['bf16']:.2f}",
                             f"{v['speedup_vs_base_fp32']['bf16']:.2f}"], name


def test_the_reference_model_table_is_its_manifest_and_the_width1_file():
    """docs/reference_model.md's table: models/cpu-ref's measured record and the full-width run's
    (results/cpu_study_width1_measured.json), the same `evaluate` on the same test frames."""
    rows = table(ROOT / "docs" / "reference_model.md", "| detectors | training |")
    man = json.loads((ROOT / "models" / "cpu-ref" / "manifest.json").read_text())["measured"]
    for label, m in (("width 1 (the `cpu` study's)", _load("cpu_study_width1_measured.json")),
                     ("width 0.5 (`cpu-ref`)", man)):
        per, iv = m["map_vehicles_per_branch_reference"], m["ci95_map_vehicles"]
        want = [f"{per[b]:.3f} [{iv[b][0]:.3f}, {iv[b][1]:.3f}]" for b in ("radar", "camera_right", "lidar", "radar_lidar")]
        want.append(f"{m['map_vehicles']:.3f} [{iv['fused'][0]:.3f}, {iv['fused'][1]:.3f}]")
        assert rows[label][1:] == want, label
        assert m["split"] == "test" and m["frames"] == 256 and m["bootstrap"]["sequences"] == 64


@pytest.mark.parametrize("name, header", [("lidar", "| candidate | training | core-hours |"),
                                          ("camera", "| candidate (camera_right) | training |")])
def test_the_recipe_tables_in_benchmarks_are_their_files(name, header):
    r = _load(f"bench_recipe_{name}_2026-12-03.json")
    rows = table(ROOT / "BENCHMARKS.md", header)
    assert set(rows) == set(r["candidates"]) and r["held_out"]["split"] == "gate"
    for cand, c in r["candidates"].items():
        last, iv = c["curve"][-1], c["ci95_map_vehicles_last_epoch"]
        assert rows[cand] == [f"{c['train_seconds']:.0f} s", f"{last['core_hours']:.4f}",
                              " / ".join(f"{p['map_vehicles']:.3f}" for p in c["curve"]),
                              f"{last['map_vehicles']:.3f} [{iv[0]:.3f}, {iv[1]:.3f}]",
                              f"{c['map_vehicles_at_budget']:.3f}"], cand
    text = (ROOT / "BENCHMARKS.md").read_text()
    assert f"at the budget ({r['budget_core_hours']:.4f} core-h)" in text
    assert r["branch"] == {"lidar": "lidar", "camera": "camera_right"}[name]
    if name == "lidar":
        assert f"- **Chosen: {r['chosen']}**" in text


def test_the_budget_frontier_tables_in_benchmarks_are_their_files():
    """BENCHMARKS.md's budget frontier: each schedule's end, best epoch and where the aim is reached
    (recomputed with `aim_reached` from the stored curves), and the 24-epoch detectors on the test split."""
    from study.bench.recipe import aim_reached

    rows = table(ROOT / "BENCHMARKS.md", "| branch and schedule | training |")
    seen = set()
    for name, branch, aim in (("lidar", "lidar", 0.35), ("camera", "camera_right", 0.20)):
        r = _load(f"bench_frontier_{name}_2026-12-03.json")
        assert r["branch"] == branch and r["held_out"]["split"] == "gate" and r["aim"]["map_vehicles"] == aim
        a = aim_reached(r["candidates"], aim)
        assert {k: v for k, v in a.items() if k != "per_candidate_stays_from_core_hours"} == r["aim"]
        for cand, c in r["candidates"].items():
            last, iv = c["curve"][-1], c["ci95_map_vehicles_last_epoch"]
            key = f"{branch}, {cand}"
            seen.add(key)
            assert rows[key] == [f"{c['train_seconds']:.0f} s", f"{last['core_hours']:.4f}",
                                 f"{last['map_vehicles']:.3f} [{iv[0]:.3f}, {iv[1]:.3f}]",
                                 f"{max(p['map_vehicles'] for p in c['curve']):.3f}",
                                 _f(a["per_candidate_core_hours"][cand], 4),
                                 _f(a["per_candidate_stays_from_core_hours"][cand], 4)], key
            assert c["fields"]["epochs"] == len(c["curve"])
    assert seen == set(rows)
    test_rows = table(ROOT / "BENCHMARKS.md", "| 24-epoch detector, test split |")
    for key, fname, branch in (("lidar, `reference`", "lidar_test_reference", "lidar"),
                               ("camera_right, `reference`", "camera_test_reference", "camera_right"),
                               ("camera_right, `visible`, clear contexts", "camera_test_visible", "camera_right")):
        m = _load(f"frontier_{fname}_2026-12-03.json")
        iv = m["ci95"]["per_context"]["all"]["map_vehicles"][branch]
        rng = m["map_vehicles_per_range"]
        assert test_rows[key][:6] == [str(m["frames"]), f"{m['map_vehicles']:.3f} [{iv[0]:.3f}, {iv[1]:.3f}]",
                                      *(f"{rng[b]:.3f}" for b in ("0-15", "15-30", "30-50", "50-100"))], key
        assert m["split"] == "test" and m["branches"] == [branch] and m["run"].endswith("/24_epochs")
        assert m["protocol"]["name"] == key.split("`")[1]
    clear = _load("frontier_camera_test_visible_2026-12-03.json")
    assert clear["contexts"] == ["city", "junction", "motorway", "rural"]


def test_the_cpu_frontier_detectors_table_is_its_files():
    """docs/results.md's aims table: the `cpu` study's detectors and the `cpu-frontier` study's, the same
    `evaluate` on the same 256 test frames, and the camera at 0-15 m in the clear contexts under `visible`."""
    rows = table(ROOT / "docs" / "results.md", "| detectors (test split, vehicle mAP, 95 % interval) |")
    for label, measured, clear in (("`cpu` (width 1, 9 epochs)", "cpu_study_width1_measured.json",
                                    "cpu_study_camera_clear_{}.json"),
                                   ("`cpu-frontier` (width 0.5, 64 RoIs, 24 epochs)",
                                    "cpu_frontier_measured_2026-12-03.json",
                                    "cpu_frontier_camera_clear_{}_2026-12-03.json")):
        m, c, ref = _load(measured), _load(clear.format("visible")), _load(clear.format("reference"))
        per, iv = m["map_vehicles_per_branch_reference"], m["ci95_map_vehicles"]
        want = [f"{m['train_seconds']:,.0f} s"]
        want += [f"{per[b]:.3f} [{iv[b][0]:.3f}, {iv[b][1]:.3f}]" for b in ("radar", "camera_right", "lidar", "radar_lidar")]
        want += [f"{m['map_vehicles']:.3f} [{iv['fused'][0]:.3f}, {iv['fused'][1]:.3f}]",
                 f"{c['map_vehicles_per_range']['0-15']:.3f}", f"{ref['map_vehicles_per_range']['0-15']:.3f}"]
        assert rows[label] == want, label
        assert ref["protocol"]["name"] == "reference" and ref["contexts"] == c["contexts"]
        assert m["split"] == "test" and m["frames"] == 256 and m["bootstrap"]["sequences"] == 64
        assert c["protocol"]["name"] == "visible" and c["contexts"] == ["city", "junction", "motorway", "rural"]
    frontier = _load("cpu_frontier_measured_2026-12-03.json")
    for b, aim in (("radar", 0.35), ("camera_right", 0.20), ("lidar", 0.35)):  # "every aim is met"
        assert frontier["map_vehicles_per_branch_reference"][b] >= aim, b
    assert _load("cpu_frontier_camera_clear_visible_2026-12-03.json")["map_vehicles_per_range"]["0-15"] >= 0.35
    per = frontier["map_vehicles_per_branch_reference"]
    near = _load("cpu_frontier_camera_clear_visible_2026-12-03.json")["map_vehicles_per_range"]["0-15"]
    said = (f"(radar {per['radar']:.3f}, camera_right {per['camera_right']:.3f}, lidar {per['lidar']:.3f}, the camera at"
            f" 0-15 m {near:.3f}) in {frontier['train_seconds']:,.0f} s")
    assert said in " ".join((ROOT / "BENCHMARKS.md").read_text().split())
    readme = " ".join((ROOT / "README.md").read_text().split())
    assert (f"vehicle mAP radar {per['radar']:.3f}, camera {per['camera_right']:.3f}, lidar {per['lidar']:.3f}"
            in readme)


def _cmp_cell(d) -> str:
    return "-" if not d else f"{d['value']:+.3f} [{d['ci95'][0]:+.3f}, {d['ci95'][1]:+.3f}] {d['verdict']}"


def test_the_compare_tables_of_the_reference_model_are_their_files():
    """docs/reference_model.md: the demo's comparison and the twins' comparison with mRA / mRR / mCE,
    from `hydrabench compare cpu-ref ... --json` (results/compare_cpu_ref_demo_2026-12-04.json, compare_cpu_ref_twins_2026-12-03.json)."""
    doc = ROOT / "docs" / "reference_model.md"
    demo = _load("compare_cpu_ref_demo_2026-12-04.json")
    rows = table(doc, "| method | mAP@0.5 (192 fresh frames) |")
    assert set(rows) == set(demo["methods"]) and demo["frames"] == 192 and demo["sequences"] == 64
    for name, m in demo["methods"].items():
        assert rows[name] == [f"{m['map']:.3f}", _cmp_cell(m.get("minus_late")), _cmp_cell(m.get("minus_all_branches"))]
    tw = _load("compare_cpu_ref_twins_2026-12-03.json")
    rows = table(doc, "| method | mAP@0.5 | minus late fusion | minus all_branches | mRA |")
    rob = tw["robustness"]["methods"]
    assert tw["frames"] == 480 and tw["best_gate"]["name"] == "attention"
    for name, m in tw["methods"].items():
        r = rob.get(name)
        tail = ([f"{r[k]:.3f}" if r[k] is not None else "-" for k in ("mRA", "mRR", "mCE_vs_late")] if r
                else ["-", "-", "-"])
        assert rows[name] == [f"{m['map']:.3f}", _cmp_cell(m.get("minus_late")),
                              _cmp_cell(m.get("minus_all_branches")), *tail], name
    seqs = [v["sequences"] for per in rob["late"]["per_condition"].values() for v in per.values()]
    assert f"{min(seqs)} to {max(seqs)} per condition and severity" in doc.read_text()


def test_make_demos_comparison_table_is_its_file():
    """docs/reference_model.md: make demo's `hydrabench compare cpu-frontier demo/test` (issue 36,
    item 8: 64 sequences, seed 1 fixed in advance), from results/compare_cpu_frontier_demo_2026-12-05.json;
    the Makefile runs that model."""
    doc = ROOT / "docs" / "reference_model.md"
    demo = _load("compare_cpu_frontier_demo_2026-12-05.json")
    rows = table(doc, "| method | mAP@0.5 (make demo's 192 frames, `cpu-frontier`) |")
    assert set(rows) == set(demo["methods"]) and demo["frames"] == 192 and demo["sequences"] == 64
    assert demo["run"].split("/")[-1].startswith("cpu-frontier-") and not demo["gates_not_trained"]
    for name, m in demo["methods"].items():
        assert rows[name] == [f"{m['map']:.3f}", _cmp_cell(m.get("minus_late")), _cmp_cell(m.get("minus_all_branches"))]
    assert "hydrabench compare cpu-frontier $(DEMO)/test" in (ROOT / "Makefile").read_text()
    assert "--seed 1 " in next(x for x in (ROOT / "Makefile").read_text().splitlines() if "$(DEMO)/test --" in x)


def test_the_readme_names_only_report_files_the_repository_has():
    import re

    line = next(x for x in (ROOT / "README.md").read_text().splitlines() if "The full tables:" in x)
    named = re.findall(r"`([^`]+)`", line.split("The full tables:")[1])
    assert named and all((ROOT / p).is_file() for p in named), named


def test_the_tables_named_are_those_beside_the_report(tmp_path):
    (tmp_path / "report.json").write_text("{}")
    with pytest.raises(ValueError):
        rr._tables_beside(tmp_path / "report.json", tmp_path)
    (tmp_path / "report.html").write_text("")
    assert rr._tables_beside(tmp_path / "report.json", tmp_path) == ("report.html",)
    (tmp_path / "report.md").write_text("")
    assert rr._tables_beside(tmp_path / "report.json", tmp_path / "elsewhere") == ("DIR/report.md", "DIR/report.html")


VERDICT_PAIRS = {
    "all_branches minus late fusion": ("all_branches", "late"),
    "HydraFusion deep gate (top 2 of 4) minus late fusion": ("hydrafusion:deep", "late"),
    "HydraFusion attention gate minus late fusion": ("hydrafusion:attention", "late"),
    "HydraFusion deep gate minus all_branches": ("hydrafusion:deep", "all_branches"),
    "EcoFusion attention gate minus all_branches": ("ecofusion:attention", "all_branches"),
    "room for context: context oracle minus all_branches": ("context_oracle", "all_branches"),
}
VERDICT_METHODS = {"physical knowledge gate": "physical_gate", "all_branches": "all_branches",
                   "HydraFusion knowledge gate (hand-written table)": "hydrafusion:knowledge",
                   "HydraFusion deep gate": "hydrafusion:deep", "HydraFusion attention gate": "hydrafusion:attention"}


def test_the_cpu_verdict_tables_in_the_results_page_are_its_report():
    """docs/results.md's two tables of the stored cpu-verdict study: every estimate and interval is the
    report's, rounded as the README block rounds (a 0.0155 bound is +0.015, never retyped as +0.016)."""
    from study.engine.scoring import difference_interval

    r = _load("study_cpu_verdict/report.json")["results"]
    ci, ms = r["intervals"]["per_context"]["all"], r["methods"]

    def cell(a, b):
        lo, hi = difference_interval(ci, a, b)
        return f"{ms[a]['map'] - ms[b]['map']:+.3f}", f"[{lo:+.3f}, {hi:+.3f}]"

    doc = ROOT / "docs" / "results.md"
    rows = table(doc, "| comparison (mAP@0.5, 500 draws of 384 sequences) |")
    assert set(rows) == set(VERDICT_PAIRS)
    for row, (a, b) in VERDICT_PAIRS.items():
        assert rows[row] == list(cell(a, b)), row
    rows = table(doc, "| method (test set, 384 sequences) | mAP | minus late [95 %] |")
    assert set(rows) == set(VERDICT_METHODS)
    for row, m in VERDICT_METHODS.items():
        assert rows[row][:2] == [f"{ms[m]['map']:.3f}", " ".join(cell(m, "late"))], row
