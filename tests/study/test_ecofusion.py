"""EcoFusion end to end on a tiny generated dataset and a one-step five-branch run: the
configuration dataset (cached, resumable, subsets fused afterwards equal to running them), measured
latency with its additive check, configuration gates, evaluation at lambda_E / gamma with the
choice executed in the network, the sweep's tables and figures, and bad input."""

import json
import os

import numpy as np
import pytest
import torch

from sensors.generate import GenerateConfig
from study.cli import main
from study.engine.train import TrainConfig, train
from tests.conftest import NARROW_MODEL

BRANCHES = ("radar", "camera_left", "camera_right", "lidar", "camera_lidar")  # none, early and late exist


@pytest.fixture(autouse=True, scope="module")
def _restore_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def data(shared_dataset):  # the dataset of tests/study/test_gates.py: generated once per session
    return shared_dataset(GenerateConfig(contexts=("city", "fog"), frames_per_context=4, sequence_length=2, seed=4))


@pytest.fixture(scope="module")
def run(data, tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    train(TrainConfig(data=str(data), branches=BRANCHES, epochs=1, batch_size=4, warmup_steps=1, lr=1e-3,
                      threads=2, eval_frames=1, model=NARROW_MODEL), out, progress=False)
    return out


def _json(capsys):
    out = capsys.readouterr().out
    assert out.count("\n") == 1
    return json.loads(out)


@pytest.fixture(scope="module")
def eco(run, data):
    """The run with its configuration dataset, a latency table (1 frame, 1 repeat) and both gates."""
    assert main(["eco-data", str(run), str(data), "--json"]) == 0
    assert main(["eco-energy", str(run), str(data), "--frames", "1", "--repeats", "1", "--threads", "2",
                 "--check", "2", "--json"]) == 0
    for gate in ("deep", "attention"):
        assert main(["eco-train-gate", str(run), str(data), "--gate", gate, "--epochs", "2", "--val-fraction", "0",
                     "--threads", "1", "--json"]) == 0
    return run


def test_eco_data_reports_loss_ap_rank_correlation_and_subsets_fused_afterwards_equal_running_them(eco, data, capsys,
                                                                                                  tmp_path):
    from fusion.data import FrameDataset, collate
    from fusion.eco.configurations import build_configurations
    from fusion.eco.loss import loss_terms
    from fusion.late import fuse
    from sensors.dataset import DatasetReader
    from sensors.rig import Calibration
    from study.eco.data import EcoData
    from study.engine.scoring import ground_truth, load_run, to_detections

    assert main(["eco-data", str(eco), str(data), "--json"]) == 0
    r = _json(capsys)
    assert r["configurations"] == 31 and r["computed_frames"] == 0  # cached by the fixture
    assert r["baselines"]["late"] == "radar+camera_left+camera_right+lidar" and r["baselines"]["early"] == "camera_lidar"
    assert set(r["loss_vs_ap_validation"]) >= {"default", "no_false_positive_term", "no_miss_term"}
    model, _ = load_run(eco)
    configs = build_configurations(model.branch_sensors)
    ed = EcoData(eco, data, model, configs, "wbf")
    assert ed.dir.parent == eco / "eco_data" and ed.missing(range(8)) == []
    arr = ed.arrays([1, 6], ["features", "detections", "terms", "ap"])
    from fusion.nets.branch_gates import gate_sensors

    assert set(gate_sensors(model)) == {"radar", "camera_left", "camera_right", "lidar", "fwd_lidar"}  # every stem
    assert arr["features"].shape == (2, 5 * 64, 8, 16) and arr["terms"].shape == (2, 31, 7)
    assert arr["detections"].shape[:2] == (2, 5) and arr["ap"].shape == (2, 31)
    # a configuration run alone in the network, then fused, gives the cached loss terms
    reader = DatasetReader(data)
    ds = FrameDataset(data, [6], sensors=model.sensors, bev_size=model.transform.image_size("radar"))
    inputs, _t, metas = collate([ds[0]])
    gt = ground_truth(reader.labels(6), "camera_right", None, metas[0], ed.protocol)  # the run's protocol
    for name in ("late", "none_radar", "camera_right+camera_lidar"):
        members = configs.members[configs.index(name)]
        with torch.no_grad():
            dets = model(inputs, selection=list(members))[0]
        f = fuse({b: to_detections(d) for b, d in dets.items()}, model.branch_frames,
                 Calibration.from_dict(metas[0]["calibration"]), method="wbf")
        direct = loss_terms(f.boxes, f.scores, f.labels, gt["boxes"], gt["labels"], gt["difficult"])
        assert np.allclose(direct, arr["terms"][1, configs.index(name)], rtol=1e-4, atol=1e-4), name
    # resumable: a run directory without the cache rebuilds it, with the same numbers
    copy = tmp_path / "copy"
    copy.mkdir()
    for f in eco.iterdir():
        if f.is_file():
            os.symlink(f, copy / f.name)
    ed2 = EcoData(copy, data, model, configs, "wbf")
    assert ed2.key == ed.key and ed2.ensure([1, 6], progress=False) == 2
    assert np.allclose(ed2.arrays([1, 6], ["terms"])["terms"], arr["terms"], rtol=1e-4, atol=1e-4)


def test_eco_energy_is_cached_additive_and_labelled(eco, data, capsys):
    assert main(["eco-energy", str(eco), str(data), "--frames", "1", "--repeats", "1", "--threads", "2",
                 "--check", "2", "--json"]) == 0  # the fixture's table: read from RUN/eco/latency.json
    r = _json(capsys)
    lm = r["latency_model"]
    assert set(lm["stems_ms"]) == {"camera_left", "camera_right", "fwd_lidar", "radar", "lidar"}
    assert set(lm["branches_ms"]) == set(BRANCHES) and set(lm["fusion_ms"]) == {"1", "2", "3", "4", "5"}
    check = r["additive_check"]["configurations"]
    assert set(check) == {"radar+camera_left+camera_right+lidar", "radar+camera_left+camera_right+lidar+camera_lidar"}
    assert all(v["measured_ms"] > 0 and v["additive_ms"] > 0 for v in check.values())
    assert r["energy_source"].startswith("modelled: 45.4 W")  # this machine: no RAPL, no NVML
    late = r["baselines"]["late"]
    assert late["energy_j"] == pytest.approx(45.4 * late["latency_ms"] / 1000, rel=1e-3)
    # the additive model: late = its four stems + four branches + the fusion of four
    expected = sum(lm["stems_ms"][s] for s in ("camera_left", "camera_right", "radar", "lidar")) + sum(
        lm["branches_ms"][b] for b in ("radar", "camera_left", "camera_right", "lidar")) + lm["fusion_ms"]["4"]
    assert late["latency_ms"] == pytest.approx(expected, abs=0.05)
    assert (eco / "eco" / "latency.json").exists()


def test_eco_evaluate_executes_the_choice_with_only_its_branches_and_stems(eco, data, capsys):
    assert main(["eco-evaluate", str(eco), str(data), "--lambda-e", "0.01", "--gamma", "0.5", "--execute", "knowledge",
                 "--json"]) == 0
    r = _json(capsys)
    assert set(r["gates"]) == {"knowledge", "deep", "attention", "loss_based"}
    assert set(r["baselines"]) == {"none_radar", "none_camera_left", "none_camera_right", "none_lidar", "early", "late"}
    lb = r["gates"]["loss_based"]
    assert lb["regret_joint_loss"] == 0.0
    for row in r["gates"].values():
        assert row["avg_joint_loss"] >= lb["avg_joint_loss"] - 1e-9 or row is lb  # the oracle minimises it
    # a feature-reading gate pays for every stem it reads before deciding: the stems its choice does
    # not need are on top of the configuration's latency; knowledge and the oracle pay nothing
    assert r["gates"]["knowledge"]["gate_ms"] == 0.0 and lb["gate_ms"] == 0.0
    for g in ("deep", "attention"):
        assert r["gates"][g]["gate_ms"] > 0.0
        assert r["gates"][g]["latency_ms"] > r["gates"][g]["gate_ms"]
    x = r["executed"]
    assert x["choice_equals_offline"] == 1.0 and x["detections_equal_offline"] == 1.0
    assert x["branch_runs_per_frame"] == x["mean_branches_chosen"]
    # knowledge: the cameras in the city (no radar or lidar stem), the radar in fog: never every stem
    assert x["stem_runs_per_frame"].get("camera", 0) >= 0.5 and sum(x["stem_runs_per_frame"].values()) < 4
    # lambda_E = 0, gamma = 0: the oracle's mean loss is the mean of each frame's lowest loss
    assert main(["eco-evaluate", str(eco), str(data), "--lambda-e", "0", "--gamma", "0", "--gates", "loss_based",
                 "--bootstrap", "30", "--json"]) == 0
    r0 = _json(capsys)
    assert r0["gates"]["loss_based"]["avg_loss"] <= min(b["avg_loss"] for b in r0["baselines"].values())
    # --bootstrap: every configuration on the same sequence draws; the oracle's margin over late fusion
    ci = r0["ci95"]["per_context"]
    band = r0["against_late"]["loss_based"]["map_minus_late_ci95"]
    assert band == ci["all"]["difference"]["loss_based - late"] and band[0] <= band[1]
    one = [c for c in ci if c != "all" and ci[c]["sequences"] == 1]
    assert one, "one test sequence per context in this fixture"
    for c in one:  # one sequence: the interval is the context's own mAP
        for name, row in [*r0["baselines"].items(), ("loss_based", r0["gates"]["loss_based"])]:
            value = row["per_scene"][c]["map"]
            assert ci[c]["map"][name] == ([value, value] if value is not None else None), (c, name)


def test_eco_sweep_writes_tables_and_figures(eco, data, tmp_path, capsys):
    out = tmp_path / "sweep"
    assert main(["eco-sweep", str(eco), str(data), "--out", str(out), "--lambdas", "0,0.01,0.5,1", "--json"]) == 0
    r = _json(capsys)
    assert {"none_radar", "early", "late", "ecofusion_attention_lambda_0.01"} <= set(r["table1"])
    assert set(r["table2"]) == {"0", "0.01", "0.1"} and set(r["table2"]["0"]) == {"knowledge", "deep", "attention",
                                                                                 "loss_based"}
    t3 = r["table3"]
    assert set(t3["late_fusion"]) == {"city", "fog", "overall"} and "ecofusion_knowledge_savings_pct" in t3
    for f in r["figures"]:
        assert os.path.getsize(f) > 10_000
    # Eq. 9 on the same predicted losses: a larger lambda_E never chooses configurations of more energy
    # ((1 - l) L + l E has the argmin of L + m E, m = l / (1 - l) rising with l; if c1 is chosen at m1 and c2
    # at m2 > m1, adding the two optimality conditions gives (m2 - m1)(E(c2) - E(c1)) <= 0; at l = 1 the
    # least energy among the candidates). The gates' own measured decision time is not part of the trade, so
    # the theorem holds for the configurations' energy; with the gate's cost added it holds where the gate
    # costs nothing to decide (the a-posteriori loss_based oracle)
    for g in ("deep", "attention", "loss_based"):
        for lo, hi in (("0", "0.01"), ("0.01", "0.5"), ("0.5", "1")):
            assert r["figure4"][g][hi]["energy_configuration"] <= r["figure4"][g][lo]["energy_configuration"], (g, lo, hi)
    assert r["figure4"]["loss_based"]["1"]["energy"] <= r["figure4"]["loss_based"]["0"]["energy"]


def test_fp_weight_reweights_cached_terms_and_keeps_its_gates_apart(eco, data, capsys):
    """--fp-weight changes only how the cached L_f terms combine: eco-data computes nothing new and its
    mean losses follow L_f = (tp + box + w fp + miss n_miss) / n_pos; gates trained at w live in
    RUN/eco/gates/<gate>-fp<w>/ beside the default ones, and a command at w refuses to use untrained or
    differently trained gates."""
    from fusion.eco.configurations import build_configurations
    from fusion.eco.loss import FusedLossSpec
    from study.eco.data import EcoData, EcoSettings, eco_splits
    from study.engine.scoring import load_run

    assert main(["eco-data", str(eco), str(data), "--fp-weight", "0.25", "--json"]) == 0
    r = _json(capsys)
    assert r["computed_frames"] == 0 and r["loss_definition"]["fp_weight"] == 0.25
    assert "fp_weight_0.25" in r["loss_vs_ap_validation"]
    model, cfg = load_run(eco)
    configs = build_configurations(model.branch_sensors)
    ed = EcoData(eco, data, model, configs, "wbf")
    _, test = eco_splits(cfg, data)
    t = ed.arrays(test, ["terms"])["terms"]
    law = (t[..., 0] + t[..., 1] + 0.25 * t[..., 2] + FusedLossSpec().miss_cost * t[..., 3]) / np.maximum(t[..., 4], 1)
    for name, v in r["mean_loss_test"].items():
        assert v == pytest.approx(law[:, configs.names.index(name)].mean(), abs=1e-4), name
    assert r["lowest_mean_loss_test"] == configs.names[int(np.argmin(law.mean(axis=0)))]
    assert len(r["mean_loss_test"]) == len(configs)

    # no deep gate at 0.25 yet: refused before any work, naming the command that trains it
    assert main(["eco-evaluate", str(eco), str(data), "--fp-weight", "0.25", "--gates", "deep", "--json"]) == 2
    err = capsys.readouterr().err
    assert "--fp-weight 0.25" in err and "eco-train-gate" in err
    before = (eco / "eco" / "gates" / "deep" / "gate.pt").read_bytes()
    assert main(["eco-train-gate", str(eco), str(data), "--gate", "deep", "--epochs", "2", "--val-fraction", "0",
                 "--threads", "1", "--fp-weight", "0.25", "--json"]) == 0
    g = _json(capsys)
    assert g["loss_definition"]["fp_weight"] == 0.25 and g["gate_path"].endswith("deep-fp0.25/gate.pt")
    assert (eco / "eco" / "gates" / "deep" / "gate.pt").read_bytes() == before  # the default gate untouched
    assert EcoSettings(fp_weight=0.25).gate_dir(eco, "deep") == eco / "eco" / "gates" / "deep-fp0.25"
    assert main(["eco-evaluate", str(eco), str(data), "--fp-weight", "0.25", "--gates", "deep,loss_based",
                 "--lambda-e", "0", "--gamma", "0", "--json"]) == 0
    e = _json(capsys)
    assert e["fp_weight"] == 0.25
    # the oracle minimises L_f at this weight: its mean loss is the mean of each frame's lowest
    assert e["gates"]["loss_based"]["avg_loss"] == pytest.approx(law.min(axis=1).mean(), abs=1e-4)
    # a gate file whose L_f differs from the one asked for is refused (here: copied by hand)
    import shutil

    bad = eco / "eco" / "gates" / "deep-fp0.5"
    bad.mkdir()
    shutil.copy(eco / "eco" / "gates" / "deep-fp0.25" / "gate.pt", bad / "gate.pt")
    assert main(["eco-evaluate", str(eco), str(data), "--fp-weight", "0.5", "--gates", "deep", "--json"]) == 2
    assert "another L_f" in capsys.readouterr().err
    shutil.rmtree(bad)


@pytest.mark.parametrize("argv, needle", [
    (["eco-evaluate", "--lambda-e", "2"], "lambda_E must be in [0, 1]"),
    (["eco-evaluate", "--gamma", "-1"], "--gamma: must be >= 0"),
    (["eco-evaluate", "--gates", "magic"], "unknown gate 'magic'"),
    (["eco-evaluate", "--fusion", "max"], "--fusion: unknown fusion method 'max' (choose from: nms, soft-nms, wbf)"),
    (["eco-train-gate", "--gate", "knowledge"], "nothing to train"),
    (["eco-train-gate", "--gate", "deep", "--targets", "holdout"], "need a gate split, and this run has none"),
    (["eco-sweep", "--out", "/proc/no/such", "--gates", "knowledge"], "/proc is not writable"),
    (["eco-energy", "--power", "-4"], "--power"),
    (["eco-train-gate", "--gate", "deep", "--fp-weight", "-1"], "--fp-weight: must be >= 0"),
    (["eco-sweep", "--out", "/tmp/x", "--fp-weight", "nan"], "--fp-weight: expected a finite number"),
])
def test_bad_input_exits_2_with_one_line(run, data, argv, needle, capsys):
    cmd, *rest = argv
    assert main([cmd, str(run), str(data), *rest]) == 2
    out, err = capsys.readouterr()
    assert out == "" and len(err.strip().splitlines()) == 1 and needle in err, err
