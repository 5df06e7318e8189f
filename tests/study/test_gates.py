"""train-gate and evaluate with gates, end to end on a tiny generated dataset and a one-step run:
the gate dataset cache, resumable gate training, Tables 6 and 7, only the selected branches running,
and bad input (exit 2, one line)."""

import json
import os

import numpy as np
import pytest
import torch

from sensors.generate import GenerateConfig
from study.cli import main
from study.engine.gate_data import GateData
from study.engine.scoring import load_run
from study.engine.train import TrainConfig, train
from tests.conftest import NARROW_MODEL

BRANCHES = ("radar", "camera_right", "lidar", "radar_lidar")  # k = 1, 3 and all exist for 4 branches


@pytest.fixture(autouse=True, scope="module")
def _restore_threads():
    before = torch.get_num_threads()  # the commands set torch's thread count
    yield
    torch.set_num_threads(before)


def _linked_copy(run, dst):
    """The run's files (checkpoints, config) as symlinks in `dst`: no trained gates, no gate dataset."""
    dst.mkdir()
    for f in run.iterdir():
        if f.is_file():
            os.symlink(f, dst / f.name)
    return dst


@pytest.fixture(scope="module")
def data(shared_dataset):  # the dataset of tests/study/test_ecofusion.py: generated once per session
    return shared_dataset(GenerateConfig(contexts=("city", "fog"), frames_per_context=4, sequence_length=2, seed=4))


@pytest.fixture(scope="module")
def run(data, tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    train(TrainConfig(data=str(data), branches=BRANCHES, epochs=1, batch_size=4, warmup_steps=1, lr=1e-3,
                      threads=2, eval_frames=1, model=NARROW_MODEL), out, progress=False)  # (no test reads the epoch's mAPs)
    return out


@pytest.fixture(scope="module")
def trained(run, data):
    """The run with a deep and an attention gate (two epochs each, no validation share)."""
    for gate in ("deep", "attention"):
        assert main(["train-gate", str(run), str(data), "--gate", gate, "--epochs", "2", "--val-fraction", "0",
                     "--threads", "1", "--json"]) == 0
    return run


def _json(capsys):
    out = capsys.readouterr().out
    assert out.count("\n") == 1
    return json.loads(out)


def test_train_gate_reports_held_out_mae_against_a_constant_and_resumes(run, data, trained, capsys):
    r = json.loads((trained / "gates" / "deep" / "result.json").read_text())
    for key in ("test_mae", "constant_mean_mae", "constant_median_mae", "test_mae_per_branch", "optimizer", "lr",
                "top1_agreement_with_optimal", "beats_constant"):
        assert key in r, key
    assert r["optimizer"] == "Adam" and r["lr"] == 5e-5 and r["loss"] == "mean absolute error"
    assert r["train_frames"] == 4 and r["test_frames"] == 4 and set(r["test_mae_per_branch"]) == set(BRANCHES)
    assert np.isfinite(r["test_mae"]) and r["constant_mean_mae"] > 0
    assert (trained / "gates" / "attention" / "gate.pt").exists()
    rows = (trained / "gates" / "deep" / "metrics.csv").read_text().splitlines()
    assert rows[0].startswith("epoch,train_mae") and len(rows) == 3
    # more epochs continue the run; other settings are refused until --fresh
    assert main(["train-gate", str(run), str(data), "--gate", "deep", "--epochs", "3", "--val-fraction", "0",
                 "--threads", "1", "--json"]) == 0
    res = capsys.readouterr()
    assert json.loads(res.out)["epochs"] == 3 and "resuming" in res.err
    assert len((trained / "gates" / "deep" / "metrics.csv").read_text().splitlines()) == 4
    code = main(["train-gate", str(run), str(data), "--gate", "deep", "--epochs", "3", "--val-fraction", "0",
                 "--grid", "4x8"])
    err = capsys.readouterr().err
    assert code == 2 and "--fresh" in err and "grid" in err


def test_gate_dataset_is_cached_keyed_and_resumable(run, data, trained, tmp_path):
    model, _ = load_run(run)
    gd = GateData(run, data, model)
    assert gd.dir.parent == run / "gate_data" and (gd.dir / "info.json").exists()
    indices = list(range(8))
    assert gd.missing(indices) == [] and gd.ensure(indices, progress=False) == 0
    feats, losses = gd.load(indices)
    assert gd.sensors == ("camera_right", "radar", "lidar")
    assert feats.dtype == np.float16 and feats.shape == (8, 3 * 64, 8, 16)
    assert losses.shape == (8, len(BRANCHES)) and (losses > 0).all()
    # losses are the sum of per_sample_losses' four terms
    from fusion.data import FrameDataset, collate

    assert gd.protocol == "reference"  # the run's protocol (TrainConfig's default)
    inputs, targets, _ = collate([FrameDataset(data, [5], sensors=model.sensors, protocol=gd.protocol,
                                               bev_size=model.transform.image_size("radar"))[0]])
    per = model.per_sample_losses(inputs, targets, seed=0)[0]
    assert np.allclose(losses[5], [float(sum(per[b].values())) for b in BRANCHES], rtol=1e-4)
    # a lost chunk is rebuilt, with the same numbers (seeded sampling)
    copy = _linked_copy(run, tmp_path / "copy")
    gd2 = GateData(copy, data, model)
    assert gd2.key == gd.key and gd2.missing(indices) == indices
    # the device type and precision the network ran in are part of the key and of info.json
    assert gd.identity["device"] == "cpu" and gd.identity["precision"] == "fp32"
    assert json.loads((gd.dir / "info.json").read_text())["device"] == "cpu"
    import study.engine.gate_data as gate_data

    real_device = gate_data.model_device
    gate_data.model_device = lambda m: "cuda:1"  # as if the network were on a GPU
    try:
        on_gpu = GateData(copy, data, model)
    finally:
        gate_data.model_device = real_device
    assert on_gpu.identity["device"] == "cuda" and on_gpu.key != gd2.key
    assert gd2.ensure(indices[:3], progress=False) == 3 and gd2.missing(indices) == list(range(3, 8))
    f2, l2 = gd2.load(indices[:3])
    assert np.allclose(f2.astype(np.float32), feats[:3].astype(np.float32), rtol=2e-3, atol=1e-3)
    # float sums depend on thread count and batching (3 frames a batch here, 4 before): measured up to
    # 1.6e-4 relative on the quarter-width test network; unseeded sampling would move a loss by percents
    assert np.allclose(l2, losses[:3], rtol=1e-3)
    # another checkpoint is another key
    (copy / "checkpoint.pt").unlink()
    (copy / "checkpoint.pt").write_bytes(b"another checkpoint")
    assert GateData(copy, data, model).key != gd2.key


def test_evaluate_all_gates_gives_tables_6_and_7_equal_to_the_wired_gates(trained, data, capsys):
    assert main(["evaluate", str(trained), str(data), "--all-gates", "--json"]) == 0
    r = _json(capsys)
    gates = {"knowledge", "knowledge_informed", "deep", "attention", "optimal"}
    assert set(r["map_table"]) == gates and set(r["selection_rate"]) == gates
    for g in gates:
        assert set(r["map_table"][g]) == {"nms", "soft-nms", "wbf"}
        for f in r["map_table"][g].values():
            assert set(f) == {"1", "3", "all"}
        for k, n in (("1", 1), ("3", 3), ("all", 4)):
            rates = r["selection_rate"][g][k]
            assert set(rates) == set(BRANCHES) and sum(rates.values()) == pytest.approx(100.0 * n)
    for f in ("nms", "soft-nms", "wbf"):  # every gate keeps every branch at k = all
        assert len({r["map_table"][g][f]["all"] for g in gates}) == 1
    assert r["frames"] == 4 and r["split"] == "test" and set(r["loss_mae"]) == {"deep", "attention"}
    # the wired single-gate path (only the chosen branches run) gives the same numbers
    for gate, k, fusion in (("optimal", "1", "nms"), ("deep", "3", "soft-nms"), ("knowledge", "1", "wbf")):
        assert main(["evaluate", str(trained), str(data), "--gate", gate, "--k", k, "--fusion", fusion, "--json"]) == 0
        s = _json(capsys)
        assert s["map_table"][gate][fusion][k] == r["map_table"][gate][fusion][k] == s["map"], (gate, k, fusion)
        assert s["selection_rate"][gate][k] == r["selection_rate"][gate][k]
        assert s["branch_runs_per_frame"] == int(k)  # k branches ran per frame, no more
    # the knowledge gate's k = 1 choice: radar in fog, the right camera in clear city daylight
    per_ctx = r["selection_rate_per_context"]["knowledge"]["1"]
    assert per_ctx["fog"]["radar"] + per_ctx["fog"]["radar_lidar"] == 100.0
    assert per_ctx["city"]["camera_right"] == 100.0


@pytest.mark.parametrize("argv, needle", [
    (["--gate", "magic"], "unknown gate 'magic'"),
    (["--gate", "knowledge", "--k", "5"], "--k: must be in 1..4"),
    (["--gate", "knowledge", "--k", "0"], "--k: must be in 1..4"),
    (["--gate", "knowledge", "--k", "three"], "--k: expected an integer 1..4 or 'all'"),
    (["--gate", "knowledge", "--fusion", "max"], "unknown fusion method"),
    (["--gate", "knowledge", "--branches", "radar"], "--branches cannot be combined with a gate"),
    (["--gate", "knowledge", "--all-gates"], "exclude each other"),
    (["--all-gates", "--k", "3"], "--k is for --gate"),
    (["--k", "3"], "--k needs --gate"),
    (["--gate", "deep"], "no trained deep gate"),
])
def test_evaluate_bad_gate_input_exits_2_with_one_line(run, data, argv, needle, capsys, tmp_path):
    bare = _linked_copy(run, tmp_path / "bare")  # the run without trained gates
    assert main(["evaluate", str(bare), str(data), *argv]) == 2
    out, err = capsys.readouterr()
    assert out == "" and len(err.strip().splitlines()) == 1 and needle in err, err
    assert "Traceback" not in err


@pytest.mark.parametrize("argv, needle", [
    (["--gate", "optimal"], "nothing to train, the optimal gate ranks by the a-posteriori losses, which need ground truth"),
    (["--gate", "knowledge"], "nothing to train"),
    (["--gate", "magic"], "unknown gate 'magic'"),
    (["--gate", "deep", "--grid", "2x2"], "grid must be at least 4x4"),
    (["--gate", "deep", "--val-fraction", "1.5"], "must be in [0, 1)"),
    (["--gate", "deep", "--targets", "holdout"], "targets 'holdout' need a gate split, and this run has none"),
    (["--gate", "deep", "--targets", "test"], "--targets: invalid choice: 'test'"),
])
def test_train_gate_bad_input_exits_2_with_one_line(run, data, argv, needle, capsys):
    assert main(["train-gate", str(run), str(data), *argv]) == 2
    out, err = capsys.readouterr()
    assert out == "" and len(err.strip().splitlines()) == 1 and needle in err, err


def test_train_gate_needs_the_runs_own_dataset(run, data, tmp_path, capsys):
    other = tmp_path / "other"  # the same frames under another generation config
    other.mkdir()
    for f in data.iterdir():
        if f.name != "manifest.json":
            os.symlink(f, other / f.name)
    manifest = json.loads((data / "manifest.json").read_text())
    manifest["config"]["seed"] += 1
    (other / "manifest.json").write_text(json.dumps(manifest))
    assert main(["train-gate", str(run), str(other), "--gate", "deep"]) == 2
    assert "needs the run's training dataset" in capsys.readouterr().err
