"""`hydrabench study` end to end on the tiny preset (configs/study/tiny.yaml): every stage runs and
writes its report; a second run does no work; a changed downstream field reruns only the stages
below it; a run killed with SIGKILL mid-stage continues and gives what an uninterrupted run gives;
the report's numbers obey the equations they come from; bad configs are one-line errors.

The tiny study is kept in the session's shared cache (HYDRABENCH_CACHE layout of the notebook
tests), so tests/notebooks/test_notebooks.py reads the same study instead of running it again.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from sim.errors import UserError
from study.pipeline.config import load_study_config, study_config_from_dict
from study.pipeline.stages import STAGES, run_study

ROOT = Path(__file__).resolve().parents[2]


def tiny_study_dir(shared_cache) -> Path:
    """Where the session's tiny study lives (shared with the notebook test); HYDRABENCH_TINY_STUDY
    keeps one across sessions (its stages are keyed, so a stale one is never reused)."""
    if os.environ.get("HYDRABENCH_TINY_STUDY"):
        return Path(os.environ["HYDRABENCH_TINY_STUDY"])
    return shared_cache / "study-tiny"


@pytest.fixture(scope="module")
def tiny(shared_cache, cache_lock):
    cfg = load_study_config("tiny")
    out = tiny_study_dir(shared_cache)
    t0 = time.perf_counter()
    # held for the whole module: the notebook test on another xdist worker may be running the study,
    # and the tests below change it (a downstream field, then back) while the notebook would read it
    with cache_lock("study-tiny"):
        first = run_study(cfg, out, progress=True)
        yield {"cfg": cfg, "out": out, "first": first, "seconds": time.perf_counter() - t0}


def test_every_stage_runs_and_writes_the_report_with_its_tables(tiny):
    out, first = tiny["out"], tiny["first"]
    assert list(first["stages"]) == list(STAGES)
    for name, s in first["stages"].items():
        assert s["status"] in ("ran", "skipped"), name
        d = Path(s["dir"])
        assert d.name == f"{name}-{s['key']}" and (d / "manifest.json").is_file()
        assert not Path(str(d) + ".partial").exists()
    md = (out / "report.md").read_text()
    assert md.splitlines()[0].startswith("**These numbers mean nothing**")
    # every picture report.md links to is there (the report stage writes them in its .partial directory)
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md)
    assert len(links) >= 3 and all((out / link).is_file() for link in links), links
    for title in ("HydraFusion Table 2", "HydraFusion Table 3", "HydraFusion Table 4", "HydraFusion Table 5",
                  "HydraFusion Tables 6 and 7", "EcoFusion Table 1", "EcoFusion Table 2", "EcoFusion Table 3",
                  "mAP against severity per condition", "mAP per range bin per context",
                  "Gate regret against the oracle", "fusion regret", "What each gate picks"):
        assert title in md, title
    captions = [line for line in md.splitlines() if line.startswith("*") and line.endswith("*")
                and not line.startswith("**")]
    tables = sum(line.startswith("|---") for line in md.splitlines())
    assert tables >= 15 and len(captions) >= tables  # every table has its caption
    for c in captions:  # ... naming protocol, scale, dataset size and machine
        if "Figure" in c or "severity per condition (" in c:
            continue
        assert "protocol reference" in c and "scale tiny" in c and "6 frames (2 train, 2 gate split, 2 test)" in c, c
        assert "machine " in c and "thread(s)" in c, c
    html = (out / "report.html").read_text()
    assert html.count("data:image/png;base64,") >= 3  # figures 4, 5 and the severity sweep, embedded
    assert "src='http" not in html and 'src="http' not in html and "<img src='stages" not in html
    assert html.count("<table>") == tables
    rep = json.loads((out / "report.json").read_text())
    assert rep["scale"] == "tiny" and rep["meaningless"] and rep["protocol"] == "reference"
    assert rep["results"]["dataset"]["test_frames"] == 2
    # every choice from data was made on non-test frames and is in the report (issue 26)
    res = rep["results"]
    whats = [c["what"] for c in res["choices"]]
    assert any(w.startswith("late-fusion method") for w in whats)
    assert sum(w.startswith("HydraFusion Table 3") for w in whats) == len(res["hydra_table3"])
    assert all(c["on"] == "validation" and c["frames"] == res["validation"]["frames"] for c in res["choices"])
    assert res["fusion"] == res["choices"][0]["chosen"]
    assert all(v["chosen_on"] == "validation" for v in res["hydra_table3"].values())
    assert set(res["gate_training"]) == {f"{f}:{g}" for f in ("hydrafusion", "ecofusion") for g in tiny["cfg"].gates.gates}
    # HydraFusion's gates run their top evaluate.k and are chosen for it (issue 50 item 5); EcoFusion's choose one
    k = tiny["cfg"].evaluate.k
    for g in tiny["cfg"].gates.gates:
        assert res["gate_training"][f"hydrafusion:{g}"]["selected_on"] == f"validation regret of the top {k}"
        assert res["gate_training"][f"ecofusion:{g}"]["selected_on"] == "validation regret"
    assert "What was chosen where" in md and "Learned gates against the best constant" in md
    # the gate split (train.gate_holdout): the gates learn from it, the choices are made on it, and each gate
    # is also trained on the detectors' own frames for the comparison (issue 26)
    assert res["validation"]["holdout"] and res["dataset"]["gate_frames"] == 2
    for name, v in res["gate_training"].items():
        assert v["targets"] == "holdout" and v["train_frames"] == 2, name
        assert v["in_sample"]["targets"] == "train" and v["in_sample"]["train_frames"] == 2, name
    assert "Gate targets: held-out gate split against the detectors' training frames" in md
    # a learned gate pays for the stems it reads (Table 4 as EcoFusion Table 1)
    t4 = res["hydra_table4"]
    # ... and for its own network, timed on the latency frames (issue 36: the gate's own compute counted)
    gl = json.loads((Path(first["stages"]["gates"]["dir"]) / "run" / "eco" / "gate_latency.json").read_text())
    assert set(gl["gates"]) == {f"{f}:{g}" for f in ("hydrafusion", "ecofusion") for g in tiny["cfg"].gates.gates}
    assert all(v["median_ms"] > 0 for v in gl["gates"].values()) and len(gl["load_average_before"]) == 3
    for g in tiny["cfg"].gates.gates:
        assert t4[f"hydrafusion:{g}"]["gate_ms"] >= gl["gates"][f"hydrafusion:{g}"]["median_ms"] - 0.01
    assert t4["late"]["gate_ms"] == 0 and all(t4[f"ecofusion:{g}"]["gate_ms"] >= 0 for g in ("deep",))
    for g, v in res["lambda_front"]["gates"].items():
        assert v["span_pct"] is None or -100 <= v["span_pct"] <= 100, (g, v)


def test_report_numbers_follow_their_definitions(tiny):
    r = json.loads((tiny["out"] / "report.json").read_text())["results"]
    m = r["methods"]
    # Table 2 (i) is each single-sensor method's mAP; (iv) the configured gate's top-k
    for b, v in r["hydra_table2"]["single_sensors"].items():
        assert v == m[f"single:{b}"]["map"]
    assert set(r["hydra_table2"]["early_fusion"]) == {"early_radar_lidar"}
    assert list(r["hydra_table2"]["hydrafusion"].values()) == [m["hydrafusion:attention"]["map"]]
    # Table 2 (iii) shows Table 5's entry of the fusion method chosen on the validation frames (recorded
    # in "choices"), not the best one on test: on the quarter-width tiny network they differ
    chosen = {c["what"]: c for c in r["choices"]}
    for combo, row in r["hydra_table5"].items():
        pick = chosen[f"HydraFusion Table 2: fusion of late {combo}"]
        assert pick["on"] == "validation" and pick["chosen"] in row
        assert r["hydra_table2"]["late_fusion"][combo] == row[pick["chosen"]]
    # Eq. 6 with no energy counter here: E = P t, P = 45.4 W (the PX2), for every fixed configuration
    assert r["energy_unit"].endswith("modelled: 45.4 W (EcoFusion Table 1: Drive PX2 under load)") or \
        "45.4 W" in r["energy_unit"]
    for name in ("late", "single:radar", "all_branches"):
        row = r["hydra_table4"][name]
        assert row["energy_j"] == pytest.approx(45.4 * row["latency_ms"] / 1000, rel=2e-3, abs=2e-4)
    assert r["hydra_table4"]["late"]["branches"] == len(r["late"])
    assert r["hydra_table4"]["hydrafusion:attention"]["branches"] == r["k"] == 2
    # fusion regret = mAP without the sensor minus mAP with it; "with" is late fusion itself
    for b, v in r["fusion_regret"].items():
        assert b in r["late"]
        for ctx, row in v["per_context"].items():
            assert row["map_with"] == (m["late"]["map"] if ctx == "all" else m["late"]["map_per_context"][ctx])
            if row["map_with"] is not None and row["map_without"] is not None:
                assert row["regret_map"] == pytest.approx(row["map_without"] - row["map_with"], abs=1e-4)
        assert set(v["hurts_in"]) == {c for c, row in v["per_context"].items()
                                      if c != "all" and (row["regret_map"] or 0) > 0}
    # regret against the oracle: oracle minus gate, and the share of frames whose choice differs
    for fam, oracle in (("hydrafusion", "optimal"), ("ecofusion", "loss_based")):
        for rows in r["regret"][fam].values():
            for ctx, row in rows.items():
                key = f"{fam}:{oracle}"
                o = m[key]["map"] if ctx == "all" else m[key]["map_per_context"][ctx]
                assert row["map_oracle"] == o
                if row["map"] is not None and o is not None:
                    assert row["regret_map"] == pytest.approx(o - row["map"], abs=1e-4)
                assert 0 <= row["differs_pct"] <= 100
                assert row["differs_pct"] * row["frames"] / 100 == pytest.approx(round(row["differs_pct"] * row["frames"] / 100), abs=0.06)
    # severity sweep: fog frames at severity 4 only (the preset), with their clear twins scored
    fog = r["severity"]["fog"]
    assert set(fog["late"]) == {"4"} and fog["late"]["4"]["frames"] == 1
    assert "clear" in fog["single:radar"]["4"] and r["severity_clear_twins"]
    # intervals: with one test sequence per context every draw is that sequence, so a context's
    # interval is its point estimate; each difference is stored once, for every pair of methods
    ci = r["intervals"]
    assert ci["resamples"] == 20 and ci["unit"] == "sequence" and set(ci["per_context"]) == {"all", "city", "fog"}
    names = list(m)
    for ctx in ("city", "fog"):
        g = ci["per_context"][ctx]
        assert g["sequences"] == 1 and set(g["map"]) == set(names)
        for name in names:
            v = m[name]["map_per_context"][ctx]
            assert g["map"][name] == (None if v is None else [v, v]), (ctx, name)
        assert len(g["difference"]) == len(names) * (len(names) - 1) // 2
    assert ci["per_context"]["all"]["sequences"] == 2
    md = (tiny["out"] / "report.md").read_text()
    assert "95 % interval per context" in md and "minus late fusion's" in md
    # range bins per context come from the same scoring as the methods table
    assert r["range_per_context"]["late"] == m["late"]["map_vehicles_per_context_range"]


def test_the_front_record_places_every_gate_among_every_fixed_branch_set(tiny):
    """bounds.front (`study.experiments.bounds.front_record`): every EcoFusion configuration is a fixed one; a
    method's mAP is its own score, its energy Table 4's; a fixed configuration's energy interval is a
    point (the same branches on every frame); the report's front is drawn from it."""
    report = json.loads((tiny["out"] / "report.json").read_text())
    r = report["results"]
    f = r["bounds"]["front"]
    assert set(f["configurations"]) >= {"single:radar", "late", "all_branches"} and len(f["configurations"]) > 5
    assert "context_oracle" in f["placed"] and "hydrafusion:attention" in f["placed"]
    for n in f["placed"] + ["single:radar", "late", "all_branches"]:
        if n in r["methods"]:
            assert f["map_point"][n] == r["methods"][n]["map"], n
        if n in r["hydra_table4"]:
            assert f["energy_point"][n] == pytest.approx(r["hydra_table4"][n]["energy"], abs=1e-3), n
        assert len(f["map"][n]) == 2 and f["difference"], n
    for n in f["configurations"]:
        lo, hi = f["energy_ci95"][n]
        assert lo == hi == f["energy_point"][n], n
    front = report["energy_front"]
    assert set(front["fixed"]) == set(f["configurations"]) and set(front["placed"]) == set(f["placed"])


def test_room_for_context_has_its_achievable_method_and_its_bias_corrected_bound(tiny):
    """Issue 50 item 1: the per-context constant chosen on the validation frames (recorded among the
    choices, never on test) is a method scored like every other, with the test selection its choice
    gives; the context oracle's room is reported naive and split-sample, each beside its null."""
    report = json.loads((tiny["out"] / "report.json").read_text())
    r = report["results"]
    cc = r["context_constant"]
    assert cc["chosen_on"] == "validation" and "all" in cc["choice"]
    chosen = [c for c in r["choices"] if c["what"].startswith("per-context constant")]
    assert chosen and all(c["on"] == "validation" for c in chosen)
    assert {c["chosen"] for c in chosen} == {v["candidate"] for v in cc["choice"].values()}
    candidates = r["bounds"]["context_oracle"]["candidates"]
    assert all(v["branches"] == candidates[v["candidate"]] for v in cc["choice"].values())
    assert "context_constant" in r["methods"] and r["methods"]["context_constant"]["map"] is not None
    # a method that reads the context cannot beat the oracle that chooses per context on the scored frames
    assert r["methods"]["context_constant"]["map"] <= r["methods"]["context_oracle"]["map"] + 1e-9
    rc = r["bounds"]["room_corrected"]
    assert rc["candidates"] == list(candidates) and rc["sequences"] >= 2
    # chosen on the scored sequences among constants that hold all_branches: >= 0 by construction, noise included
    assert rc["naive"]["estimate"] >= 0 and rc["naive"]["null_mean"] >= 0
    one = min(rc["sequences_per_context"].values()) < 2  # then no context can be halved
    assert ("skipped" in rc["split"]) == one
    for k in ("naive",) if one else ("naive", "split"):
        lo, hi = rc[k]["interval"]
        assert lo <= hi and rc[k]["null_upper"] >= rc[k]["null_mean"] - 1e-9
    html = (tiny["out"] / "report.html").read_text()
    assert "Room for context, achievable and bounded" in html and "split-sample" in html


def test_a_second_run_does_no_work_and_json_is_one_object(tiny, capsys):
    from study.cli import main

    cfg_file = tiny["out"].parent / "tiny_copy.yaml"
    cfg_file.write_text((ROOT / "configs" / "study" / "tiny.yaml").read_text())
    t0 = time.perf_counter()
    assert main(["study", str(cfg_file), "--out", str(tiny["out"]), "--json"]) == 0
    seconds = time.perf_counter() - t0
    out, err = capsys.readouterr()
    assert out.count("\n") == 1
    r = json.loads(out)
    assert {s["status"] for s in r["stages"].values()} == {"skipped"}
    assert r["seconds"] < 5 and seconds < 60, (r["seconds"], seconds)
    assert err.count("skipped (done") == len(STAGES)
    assert r["report_json"]["results"]["methods"]["late"]["map"] == \
        json.loads((tiny["out"] / "report.json").read_text())["results"]["methods"]["late"]["map"]


def test_changing_a_downstream_field_reruns_only_the_stages_below_it(tiny):
    cfg, out = tiny["cfg"], tiny["out"]
    before = json.loads((out / "report.json").read_text())
    changed = dataclasses.replace(cfg, evaluate=dataclasses.replace(cfg.evaluate, lambda_e=0.05))
    r = run_study(changed, out)
    status = {n: s["status"] for n, s in r["stages"].items()}
    assert status == {"generate": "skipped", "train": "skipped", "gatedata": "skipped", "gates": "skipped",
                      "crossover": "skipped", "evaluate": "ran", "pem": "skipped", "transitions": "skipped",
                      "report": "ran"}
    assert r["report_json"]["results"]["lambda_e"] == 0.05
    for n in ("generate", "train", "gatedata", "gates", "crossover", "pem", "transitions"):
        assert r["stages"][n]["key"] == tiny["first"]["stages"][n]["key"]
    # back to the original config: every stage is cached again, and the report is the original's
    again = run_study(cfg, out, progress=False)
    assert {s["status"] for s in again["stages"].values()} == {"skipped"}
    assert json.loads((out / "report.json").read_text()) == before


def test_the_pem_stage_fits_on_gate_frames_and_sweeps_every_comparison_over_strength(tiny):
    """Issue 49 item 3 as a study section: the PEM fitted on the detectors' predictions on the gate split's
    fitting frames only, drawn on the test frames and the gate frames, every comparison of the sweep with
    its interval at each strength, the figure, and the report's section with the strength-1 sentence
    computed from the evaluation's own all_branches minus late."""
    from study.engine.predictions import load
    from study.engine.scoring import frames_for
    from study.experiments.pem_sweep import COMPARISONS
    from study.experiments.selection import gate_frames

    cfg, first, out = tiny["cfg"], tiny["first"], tiny["out"]
    work = Path(first["stages"]["pem"]["dir"])
    rec = json.loads((work / "pem.json").read_text())
    assert [p["strength"] for p in rec["points"]] == list(cfg.pem.strengths)
    assert rec["seed"] == cfg.pem.seed and rec["gate_seed"] == cfg.pem.seed + 1 and rec["resamples"] == cfg.pem.bootstrap
    for p in rec["points"]:
        for key in COMPARISONS:
            d = p[key]
            if key == "room_for_context" and d.get("skipped"):  # one test sequence per context: no split
                assert d["value"] is None and d["ci95"] is None and "test sequence" in d["skipped"]
                continue
            lo, hi = d["ci95"]
            assert lo <= hi and d["verdict"] == ("above" if lo > 0 else "below" if hi < 0 else "not resolved"), key
        assert p["seconds"] > 0 and rec["seconds_per_point"][f"{p['strength']:g}"] == p["seconds"]
    # fitted on the gate split's fitting frames, and on nothing else; no draw the choices read is a test frame
    data = Path(first["stages"]["generate"]["dir"]) / "data"
    run_cfg = json.loads((Path(first["stages"]["train"]["dir"]) / "paper" / "config.json").read_text())
    frames = gate_frames(run_cfg, data, "auto", cfg.gates.val_fraction, cfg.gates.seed)
    test, _ = frames_for(run_cfg, data, "test")
    assert rec["fit"]["indices"] == sorted(frames.fit) and rec["fit"]["frames"] == len(frames.fit) > 0
    assert not set(rec["fit"]["indices"]) & set(test)
    assert json.loads((work / "pem_model.json").read_text())["fit_indices"] == sorted(frames.fit)
    net = load(work / "network_gate_fit")
    assert sorted(int(m["dataset_index"]) for m, _ in net.per_frame) == sorted(frames.fit)
    for s in cfg.pem.strengths:
        drawn = {int(m["dataset_index"]) for m, _ in load(work / "draws" / f"strength-{s:g}").per_frame}
        chosen_on = {int(m["dataset_index"]) for m, _ in load(work / "draws" / f"gate-strength-{s:g}").per_frame}
        assert drawn == set(test) and not chosen_on & set(test) and chosen_on <= set(frames.fit) | set(frames.val)
    assert rec["gate_frames"]["fit"] == len(frames.fit) and "fitted on" in rec["gate_frames"]["on"]  # no validation
    assert (work / "pem_sweep.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the report: the curves' table, the figure beside report.md, and the sentence as computed
    md = (out / "report.md").read_text()
    links = [x for x in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md) if x.endswith("/pem_sweep.png")]
    assert "The verdict over detector strength" in md and len(links) == 1 and (out / links[0]).is_file()
    one = json.loads((out / "report.json").read_text())["pem"]["strength_one"]
    net_d, pem_d = one["networks"], one["pem"]
    assert pem_d == rec["points"][0]["all_branches_minus_late"]
    assert one["agree"] == (net_d["verdict"] == pem_d["verdict"]) and one["sentence"] in md
    assert ("their verdicts agree" if one["agree"] else "their verdicts differ") in one["sentence"]


def test_changing_the_pem_strengths_reruns_only_pem_and_report(tiny):
    cfg, out = tiny["cfg"], tiny["out"]
    changed = dataclasses.replace(cfg, pem=dataclasses.replace(cfg.pem, strengths=(1.0, 4.0)))
    r = run_study(changed, out, progress=False)
    assert {n for n, s in r["stages"].items() if s["status"] == "ran"} == {"pem", "report"}
    assert [p["strength"] for p in json.loads((Path(r["stages"]["pem"]["dir"]) / "pem.json").read_text())["points"]] \
        == [1.0, 4.0]
    again = run_study(cfg, out, progress=False)
    assert {s["status"] for s in again["stages"].values()} == {"skipped"}


def test_killed_with_sigkill_mid_run_it_continues_and_equals_an_uninterrupted_run(tiny, tmp_path):
    out = tmp_path / "killed"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
    proc = subprocess.Popen([sys.executable, "-m", "study.cli", "study", "tiny", "--out", str(out), "--until", "train"],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    try:
        # once the train stage has begun (on the idle 2-core machine the tiny train stage takes 1.7 s, less
        # than a fixed wait after generate's end: the test once killed the process after it)
        while time.time() < deadline and not list((out / "stages").glob("train-*.partial")):
            assert proc.poll() is None, "the study ended before it could be killed"
            time.sleep(0.05)
        time.sleep(0.5)  # into the train stage
        assert proc.poll() is None, "the train stage finished before it could be killed"
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL
    assert list((out / "stages").glob("train-*.partial")) and not list((out / "stages").glob("train-*/manifest.json"))
    r = run_study(tiny["cfg"], out, until="train")
    assert r["stages"]["generate"]["status"] == "skipped" and r["stages"]["train"]["status"] == "ran"
    assert not list((out / "stages").glob("*.partial"))
    # the same inputs give the same keys, and the resumed training the same checkpoints (its digest
    # is the SHA-256 of each run's checkpoint.pt)
    ref = {n: json.loads((Path(tiny["first"]["stages"][n]["dir"]) / "manifest.json").read_text())
           for n in ("generate", "train")}
    for n in ("generate", "train"):
        got = json.loads((Path(r["stages"][n]["dir"]) / "manifest.json").read_text())
        assert got["key"] == ref[n]["key"] and got["digest"] == ref[n]["digest"], n
    assert got["checkpoints_sha256"] == ref["train"]["checkpoints_sha256"]


def test_bad_configs_are_one_line_errors(tmp_path, capsys):
    from study.cli import main

    for text, needle in (("scale: x\nbogus: 1\n", "unknown key 'bogus'"),
                         ("train:\n  epochs: 0\n", "train.epochs must be >= 1"),
                         ("train:\n  branches: [sonar]\n", "unknown branch 'sonar'"),
                         ("evaluate:\n  lambda_e: 2\n", "evaluate.lambda_e"),
                         ("evaluate:\n  bootstrap: -1\n", "evaluate.bootstrap"),
                         ("evaluate:\n  bootstrap: 1000000\n", "evaluate.bootstrap"),
                         ("data:\n  contexts: [mars]\n", "mars"),
                         ("gates:\n  gates: [optimal]\n", "not a learned gate"),
                         ("train:\n  gate_holdout: 1.0\n", "train.gate_holdout must be in [0, 1)"),
                         ("gates:\n  targets: test\n", "gates: targets: expected one of auto, holdout, train"),
                         ("gates:\n  epochs: 0\n", "gates.epochs must be >= 1"),
                         ("data:\n  frames_per_context: 0\n", "data: frames_per_context must be >= 1"),
                         ("gates:\n  pooling: global\n", "the attention gate attends over the pooled grid"),
                         ("data: [1, 2]\n", "data"),
                         ("pem:\n  strengths: [1, 0]\n", "pem.strengths must be distinct finite numbers > 0"),
                         ("pem:\n  bootstrap: 0\n", "pem.bootstrap must be an integer in [1, "),
                         ("pem: {}\n", "pem: the PEM is fitted on gate frames the detectors never trained on"),
                         ("train:\n  gate_holdout: 0.5\nevaluate:\n  fusion: nms\npem: {}\n",
                          "pem.fusion 'soft-nms' differs from evaluate.fusion 'nms'")):
        path = tmp_path / "bad.yaml"
        path.write_text(text)
        assert main(["study", str(path), "--out", str(tmp_path / "out")]) == 2
        out, err = capsys.readouterr()
        assert out == "" and len(err.strip().splitlines()) == 1 and needle in err, (text, err)
        assert not (tmp_path / "out").exists()
    with pytest.raises(UserError, match="unknown key"):
        study_config_from_dict({"train": {"epoch": 3}})
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    assert main(["study", "tiny", "--out", str(foreign)]) == 2
    assert "holds no study" in capsys.readouterr().err and os.listdir(foreign) == ["notes.txt"]


def test_every_preset_loads_and_the_help_names_it(capsys):
    from study.cli import main
    from study.pipeline.config import PRESETS_DIR

    names = sorted(p.stem for p in PRESETS_DIR.glob("*.yaml"))
    assert {"tiny", "smoke", "cpu", "cpu-long", "paper"} <= set(names)
    for n in names:
        cfg = load_study_config(n)
        assert cfg.scale == n, n  # every table carries the preset's name
    with pytest.raises(SystemExit):
        main(["study", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    for n in names:
        assert n in help_text.split("presets:")[1], n
    # the README's study is sized for 2 cores and reports intervals; cpu-long is it at full size
    cpu, long_ = load_study_config("cpu"), load_study_config("cpu-long")
    assert cpu.evaluate.bootstrap > 0 and long_.evaluate.bootstrap > 0
    assert cpu.data.frames_per_context < long_.data.frames_per_context and cpu.train.epochs < long_.train.epochs


def test_the_twin_columns_are_scored_on_the_clear_twins(tiny, tmp_path, monkeypatch):
    """The severity sweep's "clear" column runs the branches on the clear-weather arrays (a study once
    ran them on the degraded frames again, so every twin equalled its frame, lidar in dense fog too)."""
    import study.engine.scoring as detect
    from study.pipeline.cache import link_farm
    from study.pipeline.evaluation import evaluate_study
    from study.pipeline.stages import _device_setup, eco_settings

    stages = {n: Path(s["dir"]) for n, s in tiny["first"]["stages"].items()}
    real, calls = detect.run_branches, []

    def spy(*args, **kw):
        calls.append((kw.get("progress"), kw.get("clear", False)))
        return real(*args, **kw)

    monkeypatch.setattr(detect, "run_branches", spy)
    run = tmp_path / "run"
    link_farm(stages["gates"] / "run", run)
    cfg = tiny["cfg"]
    evaluate_study(run, stages["train"] / "early", stages["generate"] / "data", cfg, eco_settings(cfg), tmp_path,
                   setup=_device_setup(cfg), progress=False)
    twins = [c for c in calls if c[0] and "clear twins" in c[0]]
    assert len(twins) == 2 and all(clear for _, clear in twins), calls  # the paper run and the early model
    assert all(not clear for p, clear in calls if not (p and "clear twins" in p)), calls


def test_a_gate_set_and_a_test_set_run_end_to_end_on_the_tiny_detectors(tiny, tmp_path):
    """data.gate and data.test (issue 36): the tiny study's detectors (its generate and train stages,
    linked: same keys, so skipped) with a gate set and a test set of their own seeds; the gates fit on
    the gate set, every choice is made on its validation sequences, every method is scored on the
    test set, and no detector trains."""
    from study.pipeline.config import SetSection

    cfg = tiny["cfg"]
    cfg = dataclasses.replace(
        cfg, data=dataclasses.replace(cfg.data, gate=SetSection(4, 1, 5), test=SetSection(3, 1, 6)),
        gates=dataclasses.replace(cfg.gates, gates=("attention",), epochs=1, val_fraction=0.5, compare_targets=False,
                                  curve=(2,)),
        evaluate=dataclasses.replace(cfg.evaluate, twins=False, bootstrap=0))
    from study.pipeline.cache import Study

    out = tmp_path / "sets"
    Study(cfg, out, progress=False).prepare()
    for name in ("generate", "train", "crossover"):
        src = Path(tiny["first"]["stages"][name]["dir"])
        shutil.copytree(src, out / "stages" / src.name, symlinks=True, copy_function=os.link)
    r = run_study(cfg, out, until="pem", progress=False)
    status = {n: s["status"] for n, s in r["stages"].items()}
    assert status == {"generate": "skipped", "gateset": "ran", "testset": "ran", "train": "skipped",
                      "gatedata": "ran", "gates": "ran", "crossover": "skipped", "evaluate": "ran", "pem": "ran"}
    res = json.loads((Path(r["stages"]["evaluate"]["dir"]) / "results.json").read_text())
    ds = res["dataset"]
    assert ds["sets"] == {"gate": {"frames": 8, "seed": 5, "frames_per_context": 4, "sequence_length": 1},
                          "test": {"frames": 6, "seed": 6, "frames_per_context": 3, "sequence_length": 1}}
    assert ds["test_frames"] == 6 and ds["gate_frames"] == 8 and ds["train_frames"] == 2
    assert res["validation"]["carved"] and res["validation"]["frames"] == 4  # half the gate set's sequences
    assert all(c["on"] == "validation" and c["frames"] == 4 for c in res["choices"])
    for v in res["gate_training"].values():
        assert v["targets"] == "holdout" and v["train_frames"] == 4
    # the learning curve: the gate again on 2 of its 4 fitting frames (one sequence per context), same test frames
    curve = res["learning_curve"]["hydrafusion:attention"]
    assert [c["fit_frames"] for c in curve] == [2, 4] and len({c["test_frames"] for c in curve}) == 1
    assert all(len(c["minus_constant"]["interval"]) == 2 for c in curve)
    view = Path(r["stages"]["evaluate"]["dir"]) / "data"
    manifest = json.loads((view / "manifest.json").read_text())
    assert list(manifest["parts"]) == ["detectors", "gate", "test"]
    # the pem section with a gate set: fitted on the gate set's fitting sequences, chosen on its validation ones
    pem = json.loads((Path(r["stages"]["pem"]["dir"]) / "pem.json").read_text())
    gate_part, test_part = (range(manifest["parts"][p]["start"], manifest["parts"][p]["stop"]) for p in ("gate", "test"))
    assert pem["fit"]["split"] == "gate" and len(pem["fit"]["indices"]) == 4 and set(pem["fit"]["indices"]) <= set(gate_part)
    assert pem["gate_frames"] == {"fit": 4, "val": 4, "on": "the gate frames' validation sequences"}
    for p in pem["points"]:  # every comparison at every strength, with its interval; the room estimable here
        for key in ("context_constant_minus_all_branches", "physical_gate_minus_all_branches",
                    "a_posteriori_oracle_minus_all_branches", "room_for_context"):
            lo, hi = p[key]["ci95"]
            assert lo <= p[key]["value"] <= hi and p[key]["verdict"] in ("above", "below", "not resolved"), key
        assert p["context_constant"]["chosen_on"]["on"] == "the gate frames' validation sequences"
    assert len(test_part) == 6 and [p["strength"] for p in pem["points"]] == list(tiny["cfg"].pem.strengths)
    assert all((view / s["name"]).resolve().is_dir() for s in manifest["shards"])  # links hold after the rename


def test_the_crossover_stage_sweeps_its_own_set_and_the_physical_gate_is_scored_like_every_method(tiny):
    """Issue 37 at its smallest: the sweep set (one dataset per level, its own seeds, clear twins), every
    curve of every condition, the figures, and the physical knowledge gate in the evaluation: its
    thresholds chosen on validation frames, its mAP in the methods, its comparison and report sections."""
    first = tiny["first"]
    cx = Path(first["stages"]["crossover"]["dir"])
    rec = json.loads((cx / "crossover.json").read_text())
    sec = tiny["cfg"].crossover
    assert rec["level_seeds"] == {"1": 41, "5": 45} and rec["frames"] == len(sec.conditions) * len(sec.severities)
    for s in sec.severities:
        m = json.loads((cx / "levels" / f"severity-{s}" / "manifest.json").read_text())
        assert m["config"]["seed"] == 40 + s and m["config"]["twins"] and m["config"]["severities"] == [s]
    assert set(rec["conditions"]) == set(sec.conditions)
    for cond, c in rec["conditions"].items():
        assert [st["severity"] for st in c["steps"]] == [1, 5], cond
        xs = [st["x"] for st in c["steps"]]
        assert (xs[0] > xs[1]) if c["worse"] == "lower" else (xs[0] < xs[1]), (cond, xs)  # mild to strong
        for base in ("late", "all_branches"):
            assert set(c["curves"][base]) == {"camera_right", "lidar", "radar"}, (cond, base)
            for cur in c["curves"][base].values():
                assert len(cur["estimate"]) == 2 and cur["crossing_kind"] in ("crossed", "at_mildest", "none")
    assert all((cx / f).stat().st_size > 10_000 for f in rec["figures"])
    res = json.loads((tiny["out"] / "report.json").read_text())["results"]
    assert "physical_gate" in res["methods"] and res["crossover"]["level_seeds"] == rec["level_seeds"]
    pg = res["physical_gate"]
    assert pg["reads"] == ["illuminance_lux", "rain_mm_h", "snow_mm_h", "visibility_m"]
    choice = [c for c in res["choices"] if c["what"].startswith("physical knowledge gate")]
    assert len(choice) == 1 and choice[0]["on"] == "validation"
    comp = pg["comparison"]
    assert comp["physical_gate"]["map"] == res["methods"]["physical_gate"]["map"]
    assert comp["physical_gate"]["energy"] == res["hydra_table4"]["physical_gate"]["energy"]
    md = (tiny["out"] / "report.md").read_text()
    assert "When fusing a sensor stops paying" in md and "A knowledge gate from the measured crossovers" in md


def test_the_transitions_stage_scores_each_learned_gate_with_memory_on_ramping_weather(tiny):
    """Issue 37 item 3 at its smallest: the transition set (one dataset per part and kind, their own
    seeds), each learned gate's variants with their parameters chosen on the validation part, the
    per-sequence scores and the report's section."""
    first = tiny["first"]
    tx_dir = Path(first["stages"]["transitions"]["dir"])
    tx = json.loads((tx_dir / "transitions.json").read_text())
    sec = tiny["cfg"].transitions
    assert tx["seeds"] == {"validation-onset": 65, "validation-bank": 85, "test-onset": 60, "test-bank": 80}
    for name, seed in tx["seeds"].items():
        m = json.loads((tx_dir / "sets" / name / "manifest.json").read_text())
        assert m["config"]["seed"] == seed and m["config"]["transitions"] == [name.split("-")[1]]
        assert m["config"]["sequence_length"] == round(sec.duration_s * sec.frame_rate_hz)
    assert tx["sequences"] == {"validation": 2, "test": 2}
    assert set(tx["gates"]) == {f"hydrafusion:{g}" for g in tiny["cfg"].gates.gates} | {"recurrent"}
    rec = tx["gates"]["recurrent"]  # item 3 (c): trained on the gate set's sequences, its window on validation
    assert rec["window"] in sec.windows and set(rec["window_trace"]) == {str(w) for w in sec.windows}
    assert rec["training"]["fit_sequences"] > 0 and rec["training"]["sequence_frames"] == [tiny["cfg"].data.sequence_length]
    assert rec["training"]["kept_by"].startswith("last epoch")  # tiny's gates have no validation frames
    assert [r["epoch"] for r in rec["history"]] == list(range(sec.recurrent_epochs + 1))
    assert 0 <= rec["training"]["best_epoch"] <= sec.recurrent_epochs and rec["step_ms"] > 0
    v = rec["variants"]
    chosen = next(k for k in v if k.startswith("recurrent ("))
    assert {"per-frame", "hydrafusion:deep per-frame", "a-posteriori oracle"} <= set(v)
    assert v[chosen]["regret_minus_deep_interval"] is not None
    assert tx["energy"]["scale"] == tiny["cfg"].evaluate.energy_scale
    for x in (y for r in tx["gates"].values() for y in r["variants"].values()):  # energy per variant
        assert x["energy_compute"] > 0 and x["energy_sensors_j"] >= x["energy_sensors_clock_gated_by_choice_j"] > 0
    for g in tiny["cfg"].gates.gates:  # a gate that reads every stem keeps every sensor measuring
        v = tx["gates"][f"hydrafusion:{g}"]["variants"]
        assert len({x["energy_sensors_j"] for k, x in v.items() if not k.startswith(("best", "a-post"))}) == 1
        const = next(k for k in v if k.startswith("best constant"))
        assert v[const]["energy_sensors_j"] == v[const]["energy_sensors_clock_gated_by_choice_j"]
    for g, rec in tx["gates"].items():
        if g == "recurrent":
            continue
        assert rec["margin"] in sec.margins and rec["alpha"] in sec.alphas
        assert set(rec["margin_trace"]) == {str(m) for m in sec.margins}
        v = rec["variants"]
        assert list(v)[0] == "per-frame" and "a-posteriori oracle" in v
        assert v["a-posteriori oracle"]["regret"] == 0.0
        assert all(x["regret"] >= 0 for x in v.values())
    assert all((tx_dir / f).stat().st_size > 5_000 for f in tx["figures"])
    md = (tiny["out"] / "report.md").read_text()
    assert "Weather that changes: gates with memory" in md
