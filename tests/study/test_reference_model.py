"""Reference models (study.engine.reference_model) and `hydrabench compare`, end to end on a tiny dataset
and a one-step run of a narrow (width 0.25) network: float16 export, the manifest that loading
checks, gates that travel with the weights, names resolved to a cache copy, warm starts refused
across widths, and the selective-against-fixed comparison checked against `evaluate`."""

import json
import shutil

import numpy as np
import pytest
import torch

from sensors.generate import GenerateConfig
from study.cli import main
from study.engine import reference_model as rm
from study.engine.scoring import load_run
from study.engine.train import TrainConfig, train
from study.experiments.compare import verdict

BRANCHES = ("radar", "camera_right", "lidar", "radar_lidar")


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
    out = tmp_path_factory.mktemp("run") / "run"
    train(TrainConfig(data=str(data), branches=BRANCHES, epochs=1, batch_size=4, warmup_steps=1, lr=1e-3,
                      threads=2, eval_frames=1, model=("width=0.25",)), out, progress=False)
    return out


@pytest.fixture(scope="module")
def exported(run, data, tmp_path_factory):
    """The run exported in float16, a deep gate trained on the export, then packed as model 'mini'."""
    base = tmp_path_factory.mktemp("models")
    half = base / "half"
    rm.export_model(run, half, name="mini")
    assert main(["train-gate", str(half), str(data), "--gate", "deep", "--epochs", "1", "--val-fraction", "0",
                 "--threads", "1", "--json"]) == 0
    man = rm.export_model(half, base / "mini", name="mini", measured={"map": 0.0})
    return base / "mini", man, half


def _one_line_error(capsys, needle):
    out, err = capsys.readouterr()
    assert out == "" and len(err.strip().splitlines()) == 1 and needle in err, err
    assert "Traceback" not in err


def test_export_is_float16_weights_with_a_manifest_and_loads_close_to_the_float32_run(run, data, exported):
    model_dir, man, half = exported
    ckpt = torch.load(model_dir / "checkpoint.pt", weights_only=True)
    assert set(ckpt) == {"model"}  # weights only: no optimiser, no RNG states
    floats = [v for v in ckpt["model"].values() if v.is_floating_point()]
    assert floats and all(v.dtype == torch.float16 for v in floats)
    assert man["weights"]["parameters"] == sum(v.numel() for v in floats)
    assert man["weights"]["bytes"] == (model_dir / "checkpoint.pt").stat().st_size < rm.MAX_BYTES
    # the packed checkpoint is the one the gate was trained on, byte for byte, so the gate travels
    assert (model_dir / "checkpoint.pt").read_bytes() == (half / "checkpoint.pt").read_bytes()
    assert man["gates"] == ["deep"] and man["skipped_gates"] == []
    cfg = json.loads((run / "config.json").read_text())
    assert man["profile"] == "cpu" and man["model_overrides"] == ["width=0.25"] and man["branches"] == list(BRANCHES)
    assert cfg["profile_fields"]["width"] == 0.25
    gen = json.loads((data / "manifest.json").read_text())["config"]
    assert man["data"]["generation_config"] == gen
    assert man["measured"] == {"map": 0.0}
    assert man["training"]["command"] == (  # written from the run's config.json
        "hydrabench train DATA --out RUN --profile cpu --branch-set paper --branches radar,camera_right,lidar,radar_lidar"
        " --epochs 1 --batch-size 4 --lr 0.001 --warmup-steps 1 --lr-drop-epoch 0 --clip-grad 10 --seed 0"
        " --gate-holdout 0 --hflip 0 --protocol reference --sampling global --no-amp --model width=0.25")
    assert rm.verify(model_dir)["files"] == man["files"]
    # float16 weights give the float32 run's features to float16 precision
    m32, _ = load_run(run)
    m16, _ = load_run(model_dir)
    x = {"radar": torch.rand(1, 1, 128, 256)}
    with torch.no_grad():
        f32 = m32.branches["radar"].features([m32.extract_features(x)["radar"]])
        f16 = m16.branches["radar"].features([m16.extract_features(x)["radar"]])
    assert torch.allclose(f32, f16, rtol=0.02, atol=0.02 * float(f32.abs().max()))


def test_loading_checks_the_manifest(exported, tmp_path, capsys):
    model_dir, man, _ = exported
    bad = tmp_path / "bad"
    shutil.copytree(model_dir, bad)
    raw = bytearray((bad / "checkpoint.pt").read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    (bad / "checkpoint.pt").write_bytes(bytes(raw))
    with pytest.raises(rm.UserError, match="checkpoint.pt does not match its manifest"):
        rm.verify(bad)
    assert main(["compare", str(bad), "/nonexistent"]) == 2  # refused while parsing RUN, before DATA
    _one_line_error(capsys, "does not match its manifest")
    (bad / "checkpoint.pt").write_text("version https://git-lfs.github.com/spec/v1\n")
    with pytest.raises(rm.UserError, match="Git LFS pointer"):
        rm.verify(bad)
    shutil.copyfile(model_dir / "checkpoint.pt", bad / "checkpoint.pt")
    cfg = json.loads((bad / "config.json").read_text())
    cfg["profile_fields"]["width"] = 0.5
    (bad / "config.json").write_text(json.dumps(cfg))
    mf = json.loads((bad / "manifest.json").read_text())
    mf["files"]["config.json"] = {"sha256": rm.sha256(bad / "config.json"), "bytes": (bad / "config.json").stat().st_size}
    (bad / "manifest.json").write_text(json.dumps(mf))
    with pytest.raises(rm.UserError, match="config.json's model profile is not the manifest's"):
        rm.verify(bad)


def test_a_name_in_models_resolves_to_a_verified_cache_copy(exported, tmp_path, monkeypatch):
    model_dir, man, _ = exported
    repo_models = tmp_path / "models"
    shutil.copytree(model_dir, repo_models / "mini")
    monkeypatch.setattr(rm, "MODEL_DIR", repo_models)
    monkeypatch.setenv("HYDRABENCH_CACHE", str(tmp_path / "cache"))
    assert rm.available_models() == ["mini"]
    got = rm.resolve_run("mini")
    assert got == tmp_path / "cache" / "models" / f"mini-{man['files']['checkpoint.pt']['sha256'][:12]}"
    assert (got / "gates" / "deep" / "gate.pt").read_bytes() == (model_dir / "gates" / "deep" / "gate.pt").read_bytes()
    stamp = (got / "checkpoint.pt").stat().st_mtime_ns
    assert rm.resolve_run(str(repo_models / "mini")) == got and (got / "checkpoint.pt").stat().st_mtime_ns == stamp
    assert rm.resolve_run(str(model_dir)) == model_dir  # outside models/: used in place
    assert rm.resolve_run("no-such-model") == rm.Path("no-such-model")  # not a model: left to the run checks


def test_export_refusals(run, exported, tmp_path):
    with pytest.raises(rm.UserError, match="over the 1 MiB budget"):
        rm.export_model(run, tmp_path / "big", name="big", max_bytes=2**20)
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "notes.txt").write_text("mine")
    with pytest.raises(rm.UserError, match="is not a reference model"):
        rm.export_model(run, busy, name="x")
    for bad in ("no/slash", "__bogus__", "Upper", ""):
        with pytest.raises(rm.UserError, match="lower-case letters, digits"):
            rm.export_model(run, tmp_path / "n", name=bad)
    with pytest.raises(rm.UserError, match="hexadecimal digits"):
        rm.export_model(run, tmp_path / "n", name="n", training_commit="__bogus__")
    # a checkpoint of another network: refused by loading it into the config's network, nothing left behind
    other = tmp_path / "other"
    shutil.copytree(run, other)
    torch.save({"model": {"w": torch.zeros(3)}}, other / "checkpoint.pt")
    with pytest.raises(rm.UserError):
        rm.export_model(other, tmp_path / "o" / "m", name="m")
    assert not (tmp_path / "o").exists()
    with pytest.raises(rm.UserError, match="is not a training run"):
        rm.export_model(tmp_path, tmp_path / "m", name="m")
    # the float16 conversion is byte-for-byte repeatable: the float32 run exported again gives the
    # checkpoint the gate was trained on, so the gate is kept ...
    shutil.copytree(run, tmp_path / "with_gate")
    shutil.copytree(exported[2] / "gates", tmp_path / "with_gate" / "gates")
    man = rm.export_model(tmp_path / "with_gate", tmp_path / "out", name="g")
    assert man["gates"] == ["deep"] and man["files"]["checkpoint.pt"] == exported[1]["files"]["checkpoint.pt"]
    # ... and a gate trained on another checkpoint is left out, and says so
    gate = tmp_path / "with_gate" / "gates" / "deep" / "gate.pt"
    saved = torch.load(gate, weights_only=False)
    saved["checkpoint_sha256"] = "0" * 64
    torch.save(saved, gate)
    man = rm.export_model(tmp_path / "with_gate", tmp_path / "out", name="g")
    assert man["gates"] == [] and man["skipped_gates"] == ["deep"]


def test_warm_start_from_a_model_of_another_width_is_one_line(exported, data, tmp_path, capsys):
    model_dir, _, _ = exported
    argv = ["train", str(data), "--out", str(tmp_path / "warm"), "--branches", "radar", "--epochs", "1",
            "--init-from", str(model_dir), "--threads", "1"]
    assert main([*argv, "--model", "width=0.5"]) == 2
    _one_line_error(capsys, "trained with another model profile (width 0.25 there, 0.5 here)")
    assert not (tmp_path / "warm").exists()


def test_compare_scores_fixed_and_gated_fusion_with_paired_intervals(exported, data, capsys):
    model_dir, _, _ = exported
    assert main(["compare", str(model_dir), str(data), "--bootstrap", "40", "--gates", "knowledge,deep,optimal",
                 "--threads", "1", "--coverage-deals", "2", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    # a coverage check needs at least 2 sets of 6 sequences of every context: refused by name on a tiny set
    assert "skipped" in r["coverage"] and "two disjoint sets need" in r["coverage"]["skipped"]
    assert main(["compare", str(model_dir), str(data), "--coverage-design", "sequence,flat"]) == 2
    _one_line_error(capsys, "--coverage-design: unknown design 'flat'")
    names = list(r["methods"])
    assert names == ["single:radar", "single:camera_right", "single:lidar", "late", "all_branches",
                     "hydrafusion:knowledge", "hydrafusion:deep", "hydrafusion:optimal"]
    assert r["k"] == 2 and r["gates_not_trained"] == [] and r["split"] == "test"
    for name, row in r["methods"].items():
        if name == "late":
            assert "minus_late" not in row
            continue
        d = row["minus_late"]
        lo, hi = d["ci95"]
        assert lo <= hi and d["verdict"] == verdict([lo, hi])
        assert d["value"] == pytest.approx(row["map"] - r["methods"]["late"]["map"], abs=2e-4)
        if name.startswith("hydrafusion:"):  # what choosing adds over fusing every branch
            a = row["minus_all_branches"]
            assert a["value"] == pytest.approx(row["map"] - r["methods"]["all_branches"]["map"], abs=2e-4)
            assert a["verdict"] == verdict(a["ci95"])
        else:
            assert "minus_all_branches" not in row
    for g, rates in r["selection_rate_pct"].items():  # each gate keeps k branches on every frame
        assert sum(rates.values()) == pytest.approx(100.0 * r["k"], abs=0.5), g
    # the late baseline is what `evaluate` gives for the single-sensor branches fused the same way
    assert main(["evaluate", str(model_dir), str(data), "--branches", "radar,camera_right,lidar",
                 "--fusion", "soft-nms", "--threads", "1", "--json"]) == 0
    ev = json.loads(capsys.readouterr().out)
    assert ev["map"] == pytest.approx(r["methods"]["late"]["map"], abs=1e-4)
    # --interval: the same scores, drawn by another design, and the record says which
    assert r["bootstrap"]["design"] == "sequence"
    assert main(["compare", str(model_dir), str(data), "--bootstrap", "40", "--gates", "knowledge,deep,optimal",
                 "--threads", "1", "--interval", "rescaled", "--json"]) == 0
    rescaled = json.loads(capsys.readouterr().out)
    assert rescaled["bootstrap"]["design"] == "rescaled"
    assert {n: v["map"] for n, v in rescaled["methods"].items()} == {n: v["map"] for n, v in r["methods"].items()}
    assert any(rescaled["methods"][n]["minus_late"]["ci95"] != r["methods"][n]["minus_late"]["ci95"]
               for n in r["methods"] if n != "late")


def test_verdict_reads_the_interval():
    assert verdict([0.01, 0.02]) == "above" and verdict([-0.02, -0.001]) == "below"
    assert verdict([-0.01, 0.01]) == "not resolved" and verdict([0.0, 0.01]) == "not resolved"
    assert verdict(None) == "not resolved"


def test_compare_bad_input_is_one_line(exported, data, capsys):
    model_dir, _, _ = exported
    assert main(["compare", str(model_dir), str(data), "--gates", "magic"]) == 2
    _one_line_error(capsys, "unknown gate 'magic'")
    assert main(["compare", str(model_dir), str(data), "--fusion", "max"]) == 2
    _one_line_error(capsys, "unknown fusion method")
    assert main(["compare", str(model_dir), str(data), "--k", "9"]) == 2
    _one_line_error(capsys, "must be in 1..4")


def test_compare_twins_gives_ra_per_physical_severity_and_the_benchmarks_means(exported, shared_dataset, capsys,
                                                                               tmp_path):
    from fusion import robustness as R

    model_dir, _, _ = exported
    twins = shared_dataset(GenerateConfig(contexts=("fog", "night"), frames_per_context=4, sequence_length=2, seed=5,
                                          twins=True))
    png = tmp_path / "cmp.png"
    assert main(["compare", str(model_dir), str(twins), "--twins", "--bootstrap", "20", "--gates", "knowledge,deep",
                 "--plot", str(png), "--threads", "1", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    rob = r["robustness"]
    assert png.is_file() and (tmp_path / "cmp_ra.png").is_file() and r["plot_ra"] == str(tmp_path / "cmp_ra.png")
    assert set(rob["physical"]) == {"fog", "night"} and rob["gates"] == ["knowledge", "deep"]
    from sensors.dataset import DatasetReader

    reader = DatasetReader(twins)
    for cond, phys in rob["physical"].items():  # the median of the frames' own weather, in its unit
        assert phys["quantity"] == R.severity_quantity(cond)
        for sev, value in phys["per_severity"].items():
            vals = sorted(reader.meta(i)["weather"][phys["quantity"]] for i in range(len(reader))
                          if reader.meta(i)["conditions"] == [cond] and str(reader.meta(i)["severity"]) == sev)
            assert value == pytest.approx(float(np.median(vals)), rel=1e-3)
    for row in rob["methods"].values():
        deg, clr = {}, {}
        for cond, per in row["per_condition"].items():
            for sev, v in per.items():
                assert v["frames"] >= 2 and v["sequences"] >= 1
                if v["ra"] is not None:
                    assert v["ra"] == pytest.approx(v["degraded"] / v["clear"], rel=1e-3, abs=1e-4)
                deg.setdefault(cond, {})[int(sev)] = v["degraded"]
                clr.setdefault(cond, {})[int(sev)] = v["clear"]
        assert _same(row["mRA"], R.mean_relative_accuracy(R.relative_accuracies(deg, clr)))
        assert _same(row["mRR"], R.mean_resilience_rate(deg, clr))
    assert rob["methods"]["late"]["mCE_vs_late"] in (1.0, None)  # the baseline against itself


def _same(a, b):
    return (a is None and not np.isfinite(b)) or a == pytest.approx(b, abs=2e-4)


def test_compare_twins_needs_a_dataset_with_twins(exported, data, capsys):
    assert main(["compare", str(exported[0]), str(data), "--twins", "--bootstrap", "5", "--threads", "1"]) == 2
    _one_line_error(capsys, "has no clear-weather twins")


def test_model_list_checks_every_model(exported, tmp_path, monkeypatch, capsys):
    model_dir, _, _ = exported
    repo_models = tmp_path / "models"
    shutil.copytree(model_dir, repo_models / "mini")
    shutil.copytree(model_dir, repo_models / "broken")
    (repo_models / "broken" / "gates" / "deep" / "gate.pt").write_bytes(b"x")
    monkeypatch.setattr(rm, "MODEL_DIR", repo_models)
    assert main(["model", "list", "--json"]) == 0
    rows = {x["name"]: x for x in json.loads(capsys.readouterr().out)["models"]}
    assert rows["mini"]["ok"] and rows["mini"]["gates"] == ["deep"] and rows["mini"]["branches"] == list(BRANCHES)
    assert not rows["broken"]["ok"] and "gates/deep/gate.pt does not match its manifest" in rows["broken"]["problem"]


def test_the_committed_reference_model_is_whole_and_runs_by_name(data, tmp_path, monkeypatch, capsys):
    """models/cpu-ref: every file matches its manifest, the weights fit issue 27's ~40 MB, and by name it
    compares on a dataset it never saw, its trained gates loading (they match its checkpoint)."""
    man = rm.verify(rm.MODEL_DIR / "cpu-ref")
    assert man["weights"]["bytes"] <= rm.MAX_BYTES and man["gates"] == ["attention", "deep"]
    cfg = json.loads((rm.MODEL_DIR / "cpu-ref" / "config.json").read_text())
    assert cfg["profile_fields"]["width"] == 0.5 and cfg["branches"] == list(BRANCHES)
    monkeypatch.setenv("HYDRABENCH_CACHE", str(tmp_path / "cache"))
    before = sorted(p.relative_to(rm.MODEL_DIR) for p in rm.MODEL_DIR.rglob("*"))
    assert main(["compare", "cpu-ref", str(data), "--bootstrap", "10", "--gates", "knowledge,deep,attention",
                 "--threads", "1", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["gates"] == ["knowledge", "deep", "attention"] and r["gates_not_trained"] == [] and r["split"] == "all"
    assert sorted(p.relative_to(rm.MODEL_DIR) for p in rm.MODEL_DIR.rglob("*")) == before  # nothing written there
    assert any((tmp_path / "cache" / "models").iterdir())  # the cache run took the writes


def test_the_bootstrap_ranked_once_gives_the_pooled_intervals_on_a_networks_detections(run, data):
    """`context_bootstrap` scoring each draw by weights on detections ranked once gives the intervals
    of pooling every draw (the old path), overall and per context, for each design."""
    from study.engine.scoring import context_bootstrap, fused, load_run, run_branches

    model, _ = load_run(run)
    from sensors.dataset import DatasetReader

    reader = DatasetReader(data)
    per_frame = run_branches(model, data, list(range(len(reader))), list(model.branches), progress="test")
    frames = model.branch_frames
    sources = {b: fused(per_frame, [b], frames, "soft_nms") for b in ("radar", "camera_right", "lidar")}
    sources["all"] = fused(per_frame, list(model.branches), frames, "soft_nms")
    assert sum(len(d.scores) for _, d in sources["all"]) > 50
    for design in ("sequence", "rescaled"):
        new = context_bootstrap(sources, reader, resamples=30, classes="all", design=design)
        old = context_bootstrap(sources, reader, resamples=30, classes="all", design=design, scoring="pooled")
        assert new.keys() == old.keys() and new["per_context"].keys() == old["per_context"].keys() == {"all", "city", "fog"}
        for g, row in old["per_context"].items():
            for part in ("map", "difference"):
                for name, iv in row[part].items():
                    assert (iv is None) == (new["per_context"][g][part][name] is None), (g, name)
                    if iv is not None:
                        assert new["per_context"][g][part][name] == pytest.approx(iv, abs=1e-9), (g, part, name)


def test_a_dataset_whose_files_differ_from_its_manifest_is_refused_not_served_from_the_cache(exported, data, tmp_path,
                                                                                              capsys):
    """Caches are keyed on a dataset's contents: after a label changes but manifest.json does not,
    `compare` neither reuses the gate data cached from the old labels nor caches from the new ones:
    one line naming the shard (issue 51 measured an optimal gate read from stale losses)."""
    model_dir, _, _ = exported
    copy = tmp_path / "data"
    shutil.copytree(data, copy)
    argv = ["compare", str(model_dir), str(copy), "--gates", "knowledge,optimal", "--bootstrap", "0", "--threads", "1",
            "--json"]
    assert main(argv) == 0
    capsys.readouterr()
    frames = sorted(copy.glob("shard-*/frames.json"))[0]
    doc = json.loads(frames.read_text())
    box = next(f["labels"]["camera_right"]["boxes"][0] for f in doc["frames"] if f["labels"]["camera_right"]["boxes"])
    box[2] = box[0] + (box[2] - box[0]) / 2  # a narrower box: still valid, another answer
    frames.write_text(json.dumps(doc))
    assert main(argv) == 2
    _one_line_error(capsys, f"{frames.parent.name} does not match the checksum its manifest records")


def test_predictions_of_cpu_frontier_are_what_the_two_passes_they_replace_gave_and_compare_scores_them_alone(
        data, tmp_path, monkeypatch, capsys):
    """`predict` (stems and backbones once per batch) gives bit for bit the detections and gate outputs
    of `gate_pass` and the losses and pooled features of `GateData` (the two passes `compare` ran
    before; checked on the first batch), so `compare`'s numbers do not move; `compare` reuses the set
    `predict` cached, and `compare --predictions` scores a copy of it with no network to the same JSON."""
    from study.engine.gate_data import GateData
    from study.engine.gate_tables import gate_pass, setup_run
    from study.engine.predictions import predict

    monkeypatch.setenv("HYDRABENCH_CACHE", str(tmp_path / "cache"))
    run = rm.resolve_run("cpu-frontier")
    gates = ["knowledge", "deep", "attention", "optimal"]
    pred = predict(run, data, gates=gates, progress=False)
    model, _, indices, _, _ = setup_run(run, data, "auto", None, "latest", None)
    first = indices[:4]  # one batch of the pass
    old = gate_pass(run, data, model, gates, first, progress=False)
    feats, losses = GateData(run, data, model).load(first)
    assert [m["dataset_index"] for m, _ in pred.per_frame] == indices
    assert sum(len(d.scores) for _, per in pred.per_frame for d in per.values()) > 0
    for (_, new), (_, was) in zip(pred.per_frame, old.per_frame, strict=False):
        assert new.keys() == was.keys()
        for b in new:
            for f in ("boxes", "scores", "labels"):
                assert np.array_equal(getattr(new[b], f), getattr(was[b], f)), (b, f)
    for g in gates:
        assert np.array_equal(pred.predicted[g][:4], np.asarray(old.predicted[g], np.float32)), g
    assert np.array_equal(pred.losses[:4].sum(axis=2), losses) and np.array_equal(pred.features[:4], feats)
    made = sorted((run / "predictions").iterdir())
    argv = ["compare", "cpu-frontier", str(data), "--bootstrap", "20", "--threads", "1", "--json"]
    assert main(argv) == 0
    fresh = json.loads(capsys.readouterr().out)
    assert sorted((run / "predictions").iterdir()) == made and fresh["predictions"] == str(pred.root)  # reused
    shutil.copytree(pred.root, tmp_path / "pred")
    assert main([*argv, "--predictions", str(tmp_path / "pred")]) == 0
    stored = json.loads(capsys.readouterr().out)
    assert {k: v for k, v in stored.items() if k != "predictions"} == {k: v for k, v in fresh.items() if k != "predictions"}
    assert main([*argv, "--predictions", str(tmp_path)]) == 2
    _one_line_error(capsys, "is not a predictions directory")
    few = tmp_path / "few"  # a set made with fewer gates than compare asks for
    shutil.copytree(pred.root, few)
    m = json.loads((few / "manifest.json").read_text())
    (few / "manifest.json").write_text(json.dumps({**m, "gates": ["knowledge", "optimal"]}))
    assert main([*argv, "--predictions", str(few)]) == 2
    _one_line_error(capsys, "holds no outputs of gate 'deep'")


def test_predict_writes_a_whole_set_numpy_reads_it_and_it_is_reused_replaced_when_stale_never_mixed(
        exported, data, tmp_path, capsys):
    """`hydrabench predict`: a manifest and .npz chunks that numpy and json read alone; run again on
    the same model, data and code, the set is reused; a set of another identity is replaced whole (no
    temporary folder left); a folder of other files is refused with one line and left as it was."""
    model_dir, _, _ = exported
    out = tmp_path / "pred"
    argv = ["predict", str(model_dir), str(data), "--out", str(out), "--gates", "knowledge,deep", "--threads", "1",
            "--json"]
    assert main(argv) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["gates"] == ["knowledge", "deep"] and r["mb_per_1000_frames"] > 0
    m = json.loads((out / "manifest.json").read_text())
    assert m["format"] == "hydrabench-predictions" and m["version"] == 1 and m["branches"] == list(BRANCHES)
    assert m["identity"]["split"] == "test" and m["chunks"] == ["chunk-00000.npz"]  # the run's own test frames
    with np.load(out / m["chunks"][0], allow_pickle=False) as z:
        n = len(z["indices"])
        assert n == r["frames"] == m["frames"] > 0
        assert z["gate.deep"].shape == (n, 4) and z["losses"].shape == (n, 4, 4) and z["features"].dtype == np.float16
        assert len(z["det.radar.boxes"]) == z["det.radar.count"].sum() and json.loads(z["meta"][0])["context"]
    stamp = (out / "manifest.json").stat().st_mtime_ns
    assert main(argv) == 0 and (out / "manifest.json").stat().st_mtime_ns == stamp  # reused
    capsys.readouterr()
    m["identity"]["code"] = "0" * 64  # as if the code had changed since
    (out / "manifest.json").write_text(json.dumps(m))
    assert main(argv) == 0
    capsys.readouterr()
    assert json.loads((out / "manifest.json").read_text())["identity"]["code"] != "0" * 64
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pred"]  # no pred.tmp-* or pred.old-* left
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    assert main([*argv[:4], str(foreign), *argv[5:]]) == 2
    _one_line_error(capsys, "exists and is not a predictions directory")
    assert [p.name for p in foreign.iterdir()] == ["notes.txt"]
