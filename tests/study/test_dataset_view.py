"""A study's dataset view (sensors.combine) read through the run's splits: the detectors' train split
is the one their own dataset gives, the gate and test sets are whole parts (study.engine.scoring.frames_for)."""

import shutil

import pytest

from sensors.combine import combine
from sensors.dataset import DatasetReader
from sensors.generate import GenerateConfig
from sim.errors import UserError
from study.engine.scoring import frames_for


@pytest.fixture(scope="module")
def view(shared_dataset, tmp_path_factory):
    # configs other test files use, so the session generates nothing new
    det = shared_dataset(GenerateConfig(contexts=("junction", "fog"), frames_per_context=4, sequence_length=2, seed=9))
    gate = shared_dataset(GenerateConfig(contexts=("city", "fog"), frames_per_context=4, sequence_length=2, seed=4))
    test = shared_dataset(GenerateConfig(contexts=("fog", "motorway"), frames_per_context=3, sequence_length=1, seed=4,
                                         twins=False))
    root = tmp_path_factory.mktemp("view")
    for name, src in (("detectors", det), ("gate", gate), ("test", test)):
        shutil.copytree(src, root / name)
    combine({n: root / n for n in ("detectors", "gate", "test")}, root / "view")
    return root


def test_the_view_splits_are_the_detectors_split_and_the_whole_sets(view):
    det = DatasetReader(view / "detectors")
    run_cfg = {"data_config": det.manifest["config"], "train_fraction": 0.5, "split_seed": 0, "gate_holdout": 0.0}
    own_train, _ = frames_for(run_cfg, view / "detectors", "train")
    train, _ = frames_for(run_cfg, view / "view", "train")
    assert train == own_train and train  # the detectors part comes first: same indices
    n_det, n_gate = len(det), len(DatasetReader(view / "gate"))
    assert frames_for(run_cfg, view / "view", "gate")[0] == list(range(n_det, n_det + n_gate))
    test, split = frames_for(run_cfg, view / "view", "auto")
    assert split == "auto" and test == frames_for(run_cfg, view / "view", "test")[0]
    assert test == list(range(n_det + n_gate, len(DatasetReader(view / "view"))))
    assert frames_for(run_cfg, view / "view", "all")[0] == list(range(len(DatasetReader(view / "view"))))
    # a run trained on another dataset cannot read the view's train split as its own
    other = {**run_cfg, "data_config": DatasetReader(view / "gate").manifest["config"]}
    with pytest.raises(UserError, match="not the run's training dataset"):
        frames_for(other, view / "view", "train")
