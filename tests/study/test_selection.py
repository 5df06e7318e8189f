"""The test-split guard: every choice the study makes from data goes through `SelectionLog`, which
refuses test frames; the study's validation frames are wired through it."""

from types import SimpleNamespace

import pytest

from study.experiments.selection import SelectionLog, TestSplitLeak


def test_a_choice_on_validation_frames_is_recorded_with_its_candidates():
    log = SelectionLog.of([10, 11, 12])
    pick = log.choose("late-fusion method", {"nms": 0.30, "soft_nms": 0.31, "wbf": None}, [1, 2, 3],
                      lower_is_better=False, measure="mAP", sequences=1)
    assert pick == "soft_nms"
    assert log.choose("epoch", {"a": 0.2, "b": 0.1}, [4], lower_is_better=True, measure="regret") == "b"
    assert log.choose("tie", {"x": 1.0, "y": 1.0}, [4], lower_is_better=True, measure="m") == "x"  # first wins
    c = log.choices[0]
    assert c["on"] == "validation" and c["frames"] == 3 and c["sequences"] == 1 and c["chosen"] == "soft_nms"
    assert c["candidates"] == {"nms": 0.3, "soft_nms": 0.31, "wbf": None}


@pytest.mark.parametrize("indices", [[10], [1, 2, 12], range(9, 13)])
def test_any_test_frame_among_the_choice_frames_is_refused(indices):
    log = SelectionLog.of([10, 11, 12])
    with pytest.raises(TestSplitLeak, match="test frames"):
        log.choose("late-fusion method", {"nms": 0.3}, indices, lower_is_better=False, measure="mAP")
    with pytest.raises(TestSplitLeak):
        log.record("objective", "mae", indices, "regret")
    assert log.choices == []


def test_no_frames_and_no_values_are_errors_not_silent_choices():
    log = SelectionLog.of([5])
    with pytest.raises(TestSplitLeak, match="no validation frames"):
        log.check([], "fusion")
    with pytest.raises(ValueError, match="no candidate"):
        log.choose("fusion", {"nms": None}, [1], lower_is_better=False, measure="mAP")


def test_the_study_validation_frames_pass_the_guard(monkeypatch):
    """bounds.ValidationFrames reads the validation split through the guard: a split that hands
    it a test frame (a bug in the carve) stops the evaluation before anything is scored."""
    import study.eco.data as eco_data
    from study.experiments.bounds import ValidationFrames
    from study.experiments.selection import GateFrames

    manifest = {"frames": [{"context": "fog", "shard": f"s{i // 2}"} for i in range(12)]}
    ev = SimpleNamespace(reader=SimpleNamespace(manifest=manifest), train=list(range(8)), test=[8, 9, 10, 11],
                         run_cfg={}, data="data")
    log = SelectionLog.of(ev.test)
    monkeypatch.setattr(eco_data, "eco_gate_frames",
                        lambda *a, **k: GateFrames("holdout", True, list(range(6)), [7, 8], ev.test))
    with pytest.raises(TestSplitLeak, match="validation frames"):
        ValidationFrames(ev, 0.15, 0, log)


@pytest.fixture(scope="module")
def split_data(shared_dataset):
    from sensors.generate import GenerateConfig

    # 10 one-frame sequences per context: 70:30 -> 7 train (4 of them the gate split at 0.5), 3 test
    return shared_dataset(GenerateConfig(contexts=("city", "fog"), frames_per_context=10, sequence_length=1,
                                         seed=3, twins=False))


def _run_cfg(data, holdout):
    from sensors.dataset import DatasetReader

    return {"data_config": DatasetReader(data).manifest["config"], "train_fraction": 0.7, "split_seed": 0,
            "gate_holdout": holdout, "data": str(data)}


def test_gate_frames_split_train_gate_and_test_and_validate_both_targets_on_the_same_frames(split_data):
    from sim.errors import UserError
    from study.engine.scoring import frames_for
    from study.experiments.selection import gate_frames

    cfg = _run_cfg(split_data, 0.5)
    train, gate, test = (frames_for(cfg, split_data, s)[0] for s in ("train", "gate", "test"))
    assert len(train) == 6 and len(gate) == 8 and len(test) == 6  # per context: 3 detector, 4 gate, 3 test
    assert not (set(train) & set(gate)) and not (set(gate) | set(train)) & set(test)
    held = gate_frames(cfg, split_data, "auto", 0.5, 0)
    assert held.targets == "holdout" and held.holdout and held.test == test
    assert set(held.fit) | set(held.val) == set(gate) and not set(held.fit) & set(held.val) and held.val
    insample = gate_frames(cfg, split_data, "train", 0.5, 0)
    assert insample.fit == train and insample.val == held.val  # the same validation frames: a fair comparison
    # without a gate split: the detectors' frames, validation carved from them; "holdout" is refused
    none = _run_cfg(split_data, 0.0)
    assert frames_for(none, split_data, "gate")[0] == []
    plain = gate_frames(none, split_data, "auto", 0.5, 0)
    assert plain.targets == "train" and not plain.holdout and sorted(plain.fit + plain.val) == sorted(train + gate)
    with pytest.raises(UserError, match="gate split"):
        gate_frames(none, split_data, "holdout", 0.5, 0)
    with pytest.raises(UserError, match="targets"):
        gate_frames(cfg, split_data, "test", 0.5, 0)


def test_training_with_a_gate_holdout_never_reads_the_gate_split(split_data, tmp_path, monkeypatch):
    """The detectors' dataset is the train split minus the gate split (checked where train() builds
    it, before any step), and the split is recorded in config.json, where frames_for reads it."""
    import json

    import study.engine.train as training
    from study.engine.scoring import frames_for

    seen = {}

    class Stop(Exception):
        pass

    def capture(data, indices, **kw):
        seen["indices"] = list(indices)
        raise Stop

    monkeypatch.setattr(training, "FrameDataset", capture)
    cfg = training.TrainConfig(data=str(split_data), branches=("radar",), branch_set="single", epochs=1,
                               gate_holdout=0.5, threads=1, device="cpu")
    with pytest.raises(Stop):
        training.train(cfg, tmp_path / "run", progress=False)
    run_cfg = json.loads((tmp_path / "run" / "config.json").read_text())
    assert run_cfg["gate_holdout"] == 0.5
    assert seen["indices"] == frames_for(run_cfg, split_data, "train")[0]
    assert not set(seen["indices"]) & set(frames_for(run_cfg, split_data, "gate")[0])
    bad = training.TrainConfig(data=str(split_data), branches=("radar",), branch_set="single", gate_holdout=1.0)
    with pytest.raises(training.UserError, match="gate-holdout"):
        training.train(bad, tmp_path / "bad", progress=False)


def test_fewer_frames_takes_whole_sequences_evenly_from_each_context():
    from study.experiments.selection import fewer_frames

    class Reader:  # 2 contexts x 6 sequences of 4 frames
        manifest = {"frames": [{"context": c, "shard": f"{c}-{s}"} for c in ("fog", "city") for s in range(6)
                               for _ in range(4)]}

    everything = list(range(48))
    some = fewer_frames(Reader, everything, 16, seed=0)
    frames = [Reader.manifest["frames"][i] for i in some]
    assert len(some) == 16 and {f["context"] for f in frames} == {"fog", "city"}
    assert all(sum(f["shard"] == s for f in frames) == 4 for s in {f["shard"] for f in frames})  # whole sequences
    assert sum(f["context"] == "fog" for f in frames) == 8
    assert fewer_frames(Reader, everything, 16, seed=0) == some and fewer_frames(Reader, everything, 16, seed=1) != some
    assert fewer_frames(Reader, everything, 100, seed=0) == everything
