"""Training is resumable (kill -9 included) and reproducible; evaluate reports VOC mAP by class and context."""

import csv
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from sensors.generate import GenerateConfig, generate
from sim.errors import UserError
from study.cli import main
from study.engine.train import TrainConfig, train
from tests.conftest import NARROW_ARGS, NARROW_MODEL

BRANCHES = ("camera_right", "radar")


@pytest.fixture(scope="module")
def data(shared_dataset):  # the dataset of tests/study/test_distributed.py: generated once per session
    return shared_dataset(GenerateConfig(contexts=("junction", "fog"), frames_per_context=4, sequence_length=2, seed=9))


def _cfg(data, **kw):
    base = dict(data=str(data), branches=BRANCHES, epochs=2, batch_size=2, warmup_steps=2, checkpoint_steps=1,
                lr=2e-3, threads=2, model=NARROW_MODEL)
    base.update(kw)
    return TrainConfig(**base)


@pytest.fixture(scope="module")
def reference_run(data, tmp_path_factory):
    out = tmp_path_factory.mktemp("ref_run")
    # one test frame scored per epoch (metrics.csv's mAP columns; no test reads their values)
    result = train(_cfg(data, eval_frames=1), out, progress=False)
    return out, result


# The resume and checkpoint tests train several runs each (kill -9, time-based checkpoints, more
# epochs), and what they test (the state a checkpoint carries, where it is taken) does not depend on
# how many branches train: one branch (measured: 0.6 of the CPU time of two, camera or lidar) and
# one evaluation frame per epoch (free on resume: it changes no weight).
RESUME = dict(branches=("radar",), eval_frames=1)


@pytest.fixture(scope="module")
def resume_reference(data, tmp_path_factory):
    """The uninterrupted run the resume tests compare with: _cfg(data, **RESUME)."""
    out = tmp_path_factory.mktemp("resume_ref")
    train(_cfg(data, **RESUME), out, progress=False)
    return out


def test_a_run_writes_config_checkpoints_and_metrics(reference_run):
    out, result = reference_run
    assert result["train_frames"] == 4 and result["test_frames"] == 4  # 70:30 of 2 sequences per context
    rows = list(csv.DictReader(open(out / "metrics.csv")))
    assert [int(r["epoch"]) for r in rows] == [1, 2]
    for key in ("loss_camera_right", "loss_radar", "loss_total", "map_camera_right", "map_radar", "map_fused", "lr"):
        assert key in rows[0], key
    assert (out / "epoch-001.pt").exists() and (out / "epoch-002.pt").exists()
    import matplotlib.image

    curves = matplotlib.image.imread(out / "curves.png")  # the learning curves, drawn each epoch
    assert curves.shape[1] > curves.shape[0] > 200 and curves[..., :3].std() > 0.05
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["branches"] == list(BRANCHES) and cfg["data_config"]["seed"] == 9


def test_a_run_records_its_model_profile_and_is_loaded_with_it(reference_run, tmp_path):
    """Editing configs/model/cpu.yaml later (strides, anchors) must not change what a run's weights
    are loaded into: the resolved profile is in config.json and load_run builds from it."""
    import shutil

    from fusion.nets.profile import load_profile, parse_model_overrides
    from sim.config import to_dict
    from study.engine.scoring import load_run

    ref, _ = reference_run
    cfg = json.loads((ref / "config.json").read_text())
    resolved = load_profile("cpu", **parse_model_overrides(NARROW_MODEL))
    assert cfg["profile_fields"] == json.loads(json.dumps(to_dict(resolved)))
    copy = tmp_path / "other_profile"
    shutil.copytree(ref, copy)
    now = load_profile("cpu").camera.output_stride
    other = 8 if now != 8 else 16
    cfg["profile_fields"]["camera"]["output_stride"] = other
    (copy / "config.json").write_text(json.dumps(cfg))
    assert load_run(ref)[0].branches["camera_right"].output_stride == now
    assert load_run(copy)[0].branches["camera_right"].output_stride == other


def test_kill_9_mid_training_then_rerun_gives_the_same_weights(data, resume_reference, tmp_path):
    ref = resume_reference
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "study.cli", "train", str(data), "--out", str(out), "--branches",
           ",".join(RESUME["branches"]), "--eval-frames", str(RESUME["eval_frames"]),
           "--epochs", "2", "--batch-size", "2", "--warmup-steps", "2", "--lr", "2e-3", "--threads", "2",
           "--checkpoint-steps", "1", *NARROW_ARGS]  # checkpoint after every step: the kill lands after a mid-epoch checkpoint
    env = dict(os.environ)
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    deadline = time.time() + 300
    while time.time() < deadline and not (out / "checkpoint.pt").exists():
        time.sleep(0.1)
    time.sleep(0.5)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert (out / "checkpoint.pt").exists(), "no checkpoint before the kill"
    done = subprocess.run(cmd + ["--json"], capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stderr[-2000:]
    a = torch.load(ref / "checkpoint.pt", weights_only=False)["model"]
    b = torch.load(out / "checkpoint.pt", weights_only=False)["model"]
    assert a.keys() == b.keys()
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=1e-5, atol=1e-6, msg=k)
    rows = list(csv.DictReader(open(out / "metrics.csv")))
    assert [int(r["epoch"]) for r in rows] == [1, 2]
    ref_rows = list(csv.DictReader(open(ref / "metrics.csv")))  # losses averaged over whole epochs
    assert [{k: v for k, v in r.items() if k.startswith("loss_")} for r in rows] == \
        [{k: v for k, v in r.items() if k.startswith("loss_")} for r in ref_rows]


def test_a_resumed_epoch_reports_the_mean_loss_of_the_whole_epoch(data, reference_run, tmp_path, monkeypatch):
    """Interrupted after the first step of epoch 2 and resumed: metrics.csv holds the same mean losses
    as the uninterrupted run (the running sums travel in the checkpoint), not the mean of the rest."""
    import study.engine.train as st

    ref, _ = reference_run  # two branches: each branch's running sum travels
    out = tmp_path / "run"
    real = st.torch_save_atomic

    def save_then_stop(obj, path):
        real(obj, path)
        if obj.get("epoch") == 1 and obj.get("step_in_epoch") == 1:
            raise KeyboardInterrupt

    monkeypatch.setattr(st, "torch_save_atomic", save_then_stop)
    with pytest.raises(KeyboardInterrupt):
        train(_cfg(data, eval_frames=1), out, progress=False)
    monkeypatch.setattr(st, "torch_save_atomic", real)
    assert [int(r["epoch"]) for r in csv.DictReader(open(out / "metrics.csv"))] == [1]
    train(_cfg(data, eval_frames=1), out, progress=False)
    rows = list(csv.DictReader(open(out / "metrics.csv")))
    ref_rows = list(csv.DictReader(open(ref / "metrics.csv")))
    losses = [k for k in ref_rows[0] if k.startswith("loss_")]
    assert len(losses) == 3  # two branches and the total
    for a, b in zip(ref_rows, rows, strict=True):
        assert {k: a[k] for k in losses} == {k: b[k] for k in losses}


@pytest.mark.parametrize("seconds, mid_epoch", [(1e-9, True), (0.0, False)])
def test_time_based_checkpoints_land_mid_epoch_and_do_not_change_the_weights(data, resume_reference, tmp_path,
                                                                            monkeypatch, seconds, mid_epoch):
    """On a loaded machine 100 steps can take hours: `checkpoint_seconds` also checkpoints when that
    much time passed since the last save (0 = off), and where a run checkpoints changes nothing."""
    import study.engine.train as st

    ref = resume_reference
    real, saves = st.torch_save_atomic, []

    def record(obj, path):
        if "step_in_epoch" in obj:
            saves.append((obj["epoch"], obj["step_in_epoch"]))
        real(obj, path)

    monkeypatch.setattr(st, "torch_save_atomic", record)
    train(_cfg(data, checkpoint_steps=1000, checkpoint_seconds=seconds, **RESUME), tmp_path / "run", progress=False)
    # 4 training frames in batches of 2: two steps per epoch, a mid-epoch save after the first
    assert saves == ([(0, 1), (1, 0), (1, 1), (2, 0)] if mid_epoch else [(1, 0), (2, 0)])
    a = torch.load(ref / "checkpoint.pt", weights_only=False)["model"]
    b = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)["model"]
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_checkpoint_seconds_must_be_finite_and_not_negative(data, tmp_path, capsys):
    with pytest.raises(UserError, match="checkpoint-seconds"):
        train(_cfg(data, checkpoint_seconds=float("nan")), tmp_path / "nan", progress=False)
    code = main(["train", str(data), "--out", str(tmp_path / "neg"), "--checkpoint-seconds", "-1"])
    assert code == 2 and "checkpoint-seconds" in capsys.readouterr().err


def test_more_epochs_extend_a_finished_run_and_other_configs_are_refused(data, resume_reference, tmp_path, capsys):
    ref = resume_reference
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(ref, copy)
    result = train(_cfg(data, epochs=3, **RESUME), copy, progress=False)
    assert result["last"]["epoch"] == 3
    code = main(["train", str(data), "--out", str(copy), "--branches", "camera_right", "--epochs", "3"])
    assert code == 2 and "different config" in capsys.readouterr().err


def test_evaluate_reports_map_per_class_and_context(data, reference_run, capsys):
    ref, _ = reference_run
    assert main(["evaluate", str(ref), str(data), "--branches", "camera_right,radar", "--fusion", "wbf", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    for key in ("map", "ap_per_class", "map_per_context", "map_per_branch_native", "frames", "split"):
        assert key in r, key
    assert r["split"] == "test" and r["frames"] == 4 and set(r["map_per_context"]) <= {"junction", "fog"}
    assert r["fusion"] == "wbf"
    vehicle_aps = [r["ap_per_class"][c] for c in ("car", "van", "truck", "bus") if r["ap_per_class"][c] is not None]
    assert vehicle_aps, "the fixture has vehicles"
    assert r["map_vehicles"] == pytest.approx(np.mean(vehicle_aps), abs=1e-4)
    assert set(r["map_vehicles_per_context"]) == set(r["map_per_context"])
    assert main(["evaluate", str(ref), str(data), "--branches", "camera_right", "--contexts", "fog", "--json"]) == 0
    fog = json.loads(capsys.readouterr().out)
    assert fog["contexts"] == ["fog"] and set(fog["map_per_context"]) == {"fog"} and 0 < fog["frames"] < r["frames"]
    # --bootstrap: intervals per context from draws of whole sequences, every source on the same draws
    assert main(["evaluate", str(ref), str(data), "--branches", "camera_right,radar", "--bootstrap", "40", "--json"]) == 0
    b = json.loads(capsys.readouterr().out)
    ci = b["ci95"]["per_context"]
    assert set(ci) == {"all", *b["map_vehicles_per_context"]} and b["ci95"]["unit"] == "sequence"
    assert set(ci["all"]["difference"]) == {"fused - camera_right", "fused - radar", "camera_right - radar"}
    single = [c for c in ci if c != "all" and ci[c]["sequences"] == 1]
    assert single, "the fixture's test split has one sequence per context"
    for c in single:  # one sequence: every draw is the same frames, so the interval is the figure itself
        point = {"fused": b["map_vehicles_per_context"][c],
                 **{br: b["per_branch_reference"][br]["map_vehicles_per_context"][c] for br in BRANCHES}}
        for name, value in point.items():
            assert ci[c]["map_vehicles"][name] == ([value, value] if value is not None else None), (c, name)
        for pair, v in ci[c]["difference"].items():
            first, second = pair.split(" - ")
            if point[first] is not None and point[second] is not None:
                assert v[0] == v[1] == pytest.approx(point[first] - point[second], abs=2e-4), (c, pair)
    assert main(["evaluate", str(ref), str(data), "--branches", "camera_right,radar", "--bootstrap", "10"]) == 0
    assert "95% intervals of the vehicle mAP (10 draws of whole sequences)" in capsys.readouterr().out
    for bad, needle in ((["--branches", "sonar"], "unknown branch 'sonar'"), (["--fusion", "max"], "unknown fusion"),
                        (["--contexts", "moon"], "'moon' is not in the test split"),
                        (["--weights", "radar=x"], "not name=number"),
                        (["--bootstrap", "-1"], "--bootstrap: must be >= 0"), (["--bootstrap", "100001"], "must be <= 100000"),
                        (["--protocol", "bev", "--bootstrap", "5"], "--protocol bev has no right-camera result")):
        assert main(["evaluate", str(ref), str(data), *bad]) == 2
        assert needle in capsys.readouterr().err


def test_warm_start_copies_matching_modules_and_maps_branches(reference_run):
    from fusion.nets import build_hydrafusion
    from study.engine.train import branch_set
    from study.engine.warm_start import warm_start

    ref, _ = reference_run
    from fusion.nets.profile import load_profile, parse_model_overrides

    source = torch.load(ref / "checkpoint.pt", weights_only=False)["model"]
    torch.manual_seed(1)
    narrow = load_profile("cpu", **parse_model_overrides(NARROW_MODEL))  # the profile the run trained
    model = build_hydrafusion(profile=narrow, branches=branch_set("paper", "cpu"))
    report = warm_start(model, source)
    state = model.state_dict()
    # same-named and mapped branches carry the trained weights
    for dst, src in (("camera_right", "camera_right"), ("camera_both", "camera_right"), ("lidar", "radar")):
        k = f"branches.{dst}.layer4.0.conv1.weight"
        torch.testing.assert_close(state[k], source[f"branches.{src}.layer4.0.conv1.weight"])
    assert report["from"]["branches.camera_lidar."] == "branches.camera_right."
    # tensors of other shapes stay fresh: the lidar stem's 3-channel conv1 (radar's has 1 channel);
    # the fused branches' merge convs pass their origin's sensor through instead
    assert report["kept"] == ["stems.lidar.conv1.weight"]
    assert report["merge_pass_through"] == {"camera_both": "camera_right", "camera_lidar": "camera_right",
                                            "radar_lidar": "radar"}
    assert report["copied"] > 100


def test_warm_start_from_several_runs_takes_each_module_from_the_first_that_has_it():
    """--init-from CAMERA_RUN,ALL_RUN: camera-view branches from the camera run's camera_right
    (even though the second run has same-named ones), radar and lidar ones from the second run;
    the merge conv of a fused camera branch then passes the right camera's features through."""
    from fusion.nets import build_hydrafusion
    from study.engine.train import branch_set
    from study.engine.warm_start import warm_start

    paper = branch_set("paper", "cpu")
    torch.manual_seed(1)
    cam = build_hydrafusion(profile="cpu", branches=[b for b in paper if b.name == "camera_right"]).state_dict()
    torch.manual_seed(2)
    full = build_hydrafusion(profile="cpu", branches=paper).state_dict()
    torch.manual_seed(3)
    model = build_hydrafusion(profile="cpu", branches=paper)
    report = warm_start(model, [cam, full])
    state = model.state_dict()
    leaf = "layer4.0.conv1.weight"
    for dst, src, which in (("camera_left", "camera_right", cam), ("camera_both", "camera_right", cam),
                            ("radar", "radar", full), ("lidar", "lidar", full), ("radar_lidar", "radar_lidar", full)):
        torch.testing.assert_close(state[f"branches.{dst}.{leaf}"], which[f"branches.{src}.{leaf}"])
    assert report["source"]["branches.camera_left."] == 0 and report["source"]["branches.lidar."] == 1
    torch.testing.assert_close(state["stems.camera.conv1.weight"], cam["stems.camera.conv1.weight"])
    torch.testing.assert_close(state["stems.radar.conv1.weight"], full["stems.radar.conv1.weight"])
    assert report["merge_pass_through"] == {"camera_both": "camera_right", "camera_lidar": "camera_right"}
    assert report["kept"] == []
    model.eval()
    right, other = torch.randn(1, 64, 12, 20), torch.randn(1, 64, 12, 20)
    with torch.no_grad():
        alone = model.branches["camera_right"].features([right])
        both = model.branches["camera_both"].features([other, right])
        with_lidar = model.branches["camera_lidar"].features([other, right, other])
    torch.testing.assert_close(both, alone)
    torch.testing.assert_close(with_lidar, alone)
    # the BEV fused branch came from a same-named module with a merge: no pass-through, copied as is
    torch.testing.assert_close(state["branches.radar_lidar.merge.weight"], full["branches.radar_lidar.merge.weight"])


def test_evaluate_twins_scores_the_same_frames_in_clear_weather(reference_run, data, tmp_path, capsys, monkeypatch):
    """--twins: each branch on the degraded frames and on their clear twins, and the ratio."""
    from sensors.dataset import DatasetReader
    from study.engine.run_eval import evaluate
    from study.engine.scoring import bev_crop_of, load_run, native, run_branches, score

    ref, _ = reference_run
    twins = tmp_path / "twins"
    generate(GenerateConfig(contexts=("fog",), frames_per_context=4, sequence_length=2, seed=5, twins=True),
             twins, workers=1, progress=False)
    r = evaluate(ref, twins, twins=True)
    t = r["twins"]
    assert set(t["branches"]) == set(BRANCHES) and r["frames"] == 4
    reader = DatasetReader(twins)
    sev = sorted({str(reader.meta(i)["severity"]) for i in range(4)}, key=int)
    model, _ = load_run(ref)
    clear = run_branches(model, twins, range(4), ["radar"], clear=True)
    expected = score(native(clear, "radar"), DatasetReader(twins, clear=True), "bev", bev_crop_of(model, reader))
    for v in t["branches"].values():
        assert list(v["per_severity"]) == sev
        if v["clear"]:
            assert v["retained"] == round(v["degraded"] / v["clear"], 3)
    assert t["branches"]["radar"]["clear"] == expected["map_vehicles"]
    op = t["fused"]["at_score_0.5"]
    assert set(op) == {"degraded", "clear", "by_distance_over_visibility"} and set(op["clear"]) == {"recall", "precision"}
    # the twin is binned by its fog frame's visibility, so both sides count the same objects
    from study.engine.scoring import operating_point, recall_by_visibility

    bins = t["branches"]["radar"]["at_score_0.5"]["by_distance_over_visibility"]
    deg = run_branches(model, twins, range(4), ["radar"])
    pos = operating_point(native(deg, "radar"), reader, "bev", bev_crop_of(model, reader))["positives"]
    assert sum(v["objects"] for v in bins.values()) == pos
    mine = recall_by_visibility(native(clear, "radar"), DatasetReader(twins, clear=True), "bev",
                                bev_crop_of(model, reader), visibility={i: reader.meta(i)["weather"]["visibility_m"]
                                                                        for i in range(4)})
    assert [v["clear"] for v in bins.values()] == [v["recall"] for v in mine.values()]
    assert r["map_vehicles_per_severity"].keys() == set(sev)
    # --bootstrap: sequences drawn with replacement, each draw scored degraded and clear
    from study.engine.scoring import paired_bootstrap

    crop, clear_reader = bev_crop_of(model, reader), DatasetReader(twins, clear=True)
    args = (native(deg, "radar"), native(clear, "radar"), reader, clear_reader, "bev", crop)
    ci = paired_bootstrap(*args, resamples=30, severities=sev)
    assert ci == paired_bootstrap(*args, resamples=30, severities=sev)  # seeded
    assert ci["all"]["sequences"] == 2 and ci["unit"] == "sequence"
    radar = t["branches"]["radar"]
    for s_, v in ci["per_severity"].items():
        assert v["sequences"] == 1  # severities 1 and 2, one sequence each (seed 5)
        # one sequence: every draw is the same frames, so the interval is the figure itself
        assert v["degraded"] == [radar["per_severity"][s_]["degraded"]] * 2
        assert v["clear"] == [radar["per_severity"][s_]["clear"]] * 2
    same = paired_bootstrap(native(deg, "radar"), native(deg, "radar"), reader, reader, "bev", crop, resamples=30)
    assert same["all"]["retained"] in ([1.0, 1.0], None)  # the same detections on both sides
    assert list(ci["per_severity"]) == sev and sum(v["sequences"] for v in ci["per_severity"].values()) == 2
    monkeypatch.setenv("HYDRABENCH_PROGRESS_S", "0")  # a progress line per batch: stderr is not a terminal here
    capsys.readouterr()  # the calls above print progress too when a batch outlasts 5 s (a loaded machine)
    assert main(["evaluate", str(ref), str(twins), "--twins"]) == 0
    out = capsys.readouterr()
    assert "same frames in clear weather" in out.out and "warning" not in out.err and "warning" not in t
    for what in ("detect", "clear twins"):  # one line each (one batch), not silent, not repeated
        assert out.err.count(f"{what}: 4/4 frame (100%)") == 1, out.err
    # twins made before the overcast sky was kept (no `overcast` record) are named, not scored silently
    import shutil

    from study.engine.run_eval import stale_twins

    old = tmp_path / "old_twins"
    shutil.copytree(twins, old)
    for f in old.glob("shard-*/clear/frames.json"):
        doc = json.loads(f.read_text())
        for fr in doc["frames"]:
            del fr["meta"]["weather"]["overcast"]
        f.write_text(json.dumps(doc))
    assert stale_twins(DatasetReader(old), DatasetReader(old, clear=True), range(4)) == 4
    assert stale_twins(reader, DatasetReader(twins, clear=True), range(4)) == 0
    assert main(["evaluate", str(ref), str(old), "--twins"]) == 0
    assert "4 of 4 twins were made by sensor model version 2 or older" in capsys.readouterr().err
    # a dataset without twins is refused with a clear message
    assert main(["evaluate", str(ref), str(data), "--twins"]) == 2
    assert "has no clear-weather twins" in capsys.readouterr().err


def test_hflip_mirrors_inputs_and_boxes_together(data):
    """A mirrored frame is the frame seen in a mirror: every input flipped left-right and each box
    covering exactly the mirrored pixels (an off-by-one in x -> W - x would show here)."""
    from fusion.data import FrameDataset

    ds = FrameDataset(data, bev_size=(128, 192))
    checked = 0
    for k in range(len(ds)):
        x, t, meta = ds.item(k)
        xf, tf, mf = ds.item(k, flip=True)
        assert not meta["flipped"] and mf["flipped"]
        for s in x:
            torch.testing.assert_close(xf[s], torch.flip(x[s], dims=(-1,)), rtol=0, atol=0)
        for frame, sensor in (("camera_right", "camera_right"), ("camera_left", "camera_left"), ("bev", "lidar")):
            assert torch.equal(t[frame]["labels"], tf[frame]["labels"])
            W = x[sensor].shape[-1]
            for b, bf in zip(t[frame]["boxes"].round().int().tolist(), tf[frame]["boxes"].round().int().tolist()):
                assert bf[1] == b[1] and bf[3] == b[3] and 0 <= bf[0] < bf[2] <= W
                crop = x[sensor][:, b[1]:b[3], b[0]:b[2]]
                crop_f = xf[sensor][:, bf[1]:bf[3], bf[0]:bf[2]]
                torch.testing.assert_close(crop_f, torch.flip(crop, dims=(-1,)), rtol=0, atol=0)
                checked += 1
    assert checked > 10


def test_training_with_hflip_records_it_resumes_old_runs_and_refuses_stereo_branches(data, resume_reference, tmp_path,
                                                                                    capsys):
    import shutil

    run = tmp_path / "flip"
    result = train(_cfg(data, epochs=1, hflip=0.5, eval_frames=1), run, progress=False)
    assert result["last"]["epoch"] == 1 and json.loads((run / "config.json").read_text())["hflip"] == 0.5
    # a run made before --hflip existed has no such key: it resumes as hflip 0
    ref = resume_reference
    old = tmp_path / "old"
    shutil.copytree(ref, old)
    cfg = json.loads((old / "config.json").read_text())
    del cfg["hflip"]
    (old / "config.json").write_text(json.dumps(cfg))
    assert train(_cfg(data, epochs=3, **RESUME), old, progress=False)["last"]["epoch"] == 3
    code = main(["train", str(data), "--out", str(tmp_path / "stereo"), "--branches", "camera_both", "--hflip", "0.5"])
    assert code == 2 and "camera_both" in capsys.readouterr().err
    code = main(["train", str(data), "--out", str(tmp_path / "p"), "--branches", "radar", "--hflip", "1.5"])
    assert code == 2 and "--hflip: must be <= 1" in capsys.readouterr().err


def test_bev_label_ranges_match_the_camera_labels_distances(data):
    """The BEV boxes' ranges (used to bin recall by distance / visibility) agree with the camera
    labels' distances of the same objects to within the radar-camera offset."""
    from sensors.dataset import DatasetReader
    from study.engine.scoring import bev_distances

    reader = DatasetReader(data)
    diffs = []
    for i in range(len(reader)):
        lab, meta = reader.labels(i), reader.meta(i)
        rng = dict(zip(lab["bev"]["ids"], bev_distances(lab["bev"], meta["calibration"])))
        diffs += [rng[j] - d for j, d in zip(lab["camera_right"]["ids"], lab["camera_right"]["distance_m"]) if j in rng]
    assert len(diffs) > 10 and np.max(np.abs(diffs)) < 1.5


def test_split_data_test_is_the_datasets_own_test_split(reference_run, data):
    """--split data-test: on the run's own dataset the same frames and mAP as its test split; it
    also works on another dataset, where --split test is refused."""
    from study.engine.run_eval import evaluate
    from study.engine.scoring import frames_for

    ref, _ = reference_run
    a, b = evaluate(ref, data, split="test"), evaluate(ref, data, split="data-test")
    assert b["split"] == "data-test" and (a["frames"], a["map"]) == (b["frames"], b["map"])
    cfg = json.loads((ref / "config.json").read_text())
    other = {**cfg, "data_config": {**cfg["data_config"], "seed": -1}}  # as if trained on another dataset
    assert frames_for(other, data, "data-test")[0] == frames_for(cfg, data, "test")[0]
    with pytest.raises(Exception, match="needs the run's training dataset"):
        frames_for(other, data, "test")


def test_only_the_main_rank_judges_the_run_directory(tmp_path):
    """Rank 0 creates --out and writes config.json through a temporary file; a rank that looked at that
    moment used to see "not empty, no config.json" and exit 2, failing a good DDP launch under load."""
    from sim.errors import UserError
    from study.engine.train import check_run_dir

    out = tmp_path / "run"
    out.mkdir()
    (out / ".config.json.tmp").write_text("{}")  # rank 0, mid-write
    with pytest.raises(UserError, match="holds no training run"):
        check_run_dir(out, main_rank=True)
    check_run_dir(out, main_rank=False)  # the other ranks leave the judgement to rank 0
    (out / "config.json").write_text("{}")
    check_run_dir(out, main_rank=True)
    check_run_dir(tmp_path / "new", main_rank=True)  # a new directory is fine


def test_a_checkpoint_holds_the_rng_states_and_config_json_the_device_and_precision(reference_run):
    ref, result = reference_run
    state = torch.load(ref / "checkpoint.pt", weights_only=False)
    assert torch.equal(state["torch_rng"], state["torch_rng"]) and state["torch_rng"].dtype == torch.uint8
    assert "cuda_rng" in state and state["cuda_rng"] is None  # a CPU run: the GPUs' generators play no part
    cfg = json.loads((ref / "config.json").read_text())
    assert cfg["compute"] == {"device": "cpu", "precision": "fp32"}
    assert (result["device"]["device_type"], result["device"]["precision"]) == ("cpu", "fp32")


def test_frames_as_uint8_become_the_same_float_inputs_where_they_are_used(data):
    from fusion.data import FrameDataset, collate
    from study.engine.device import to_device

    f32 = FrameDataset(data, [0, 3], bev_size=(128, 256))
    u8 = FrameDataset(data, [0, 3], bev_size=(128, 256), uint8=True)
    for flip in (False, True):
        a, ta, _ = collate([f32.item(k, flip=flip) for k in range(2)])
        b, tb, _ = collate([u8.item(k, flip=flip) for k in range(2)])
        assert all(v.dtype == torch.uint8 for v in b.values())
        assert sum(v.nbytes for v in b.values()) * 4 == sum(v.nbytes for v in a.values())
        b, _ = to_device(b, tb, "cpu")
        assert a.keys() == b.keys() and all(torch.equal(a[s], b[s]) for s in a)
