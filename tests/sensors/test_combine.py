"""sensors.combine: a view of several datasets reads every frame of every part, unchanged, and checks
and verifies like a generated dataset."""

import shutil

import numpy as np
import pytest

from sensors.combine import combine, part_indices
from sensors.dataset import DatasetReader, check, verify
from sensors.generate import GenerateConfig
from sim.errors import UserError


@pytest.fixture(scope="module")
def parts(shared_dataset, tmp_path_factory):
    # the same configs other test files use, so the session generates nothing new
    a = shared_dataset(GenerateConfig(contexts=("junction", "fog"), frames_per_context=4, sequence_length=2, seed=9))
    b = shared_dataset(GenerateConfig(contexts=("city", "fog"), frames_per_context=4, sequence_length=2, seed=4))
    root = tmp_path_factory.mktemp("parts")
    shutil.copytree(a, root / "gate")
    shutil.copytree(b, root / "test")
    return root


def test_a_view_reads_every_frame_of_its_parts(parts, tmp_path):
    root = tmp_path / "study"
    shutil.copytree(parts, root)
    view = combine({"gate": root / "gate", "test": root / "test"}, root / "view")
    ra, rb, rv = DatasetReader(root / "gate"), DatasetReader(root / "test"), DatasetReader(root / "view")
    assert len(rv) == len(ra) + len(rb)
    assert part_indices(view, "gate") == list(range(len(ra)))
    assert part_indices(view, "test") == list(range(len(ra), len(ra) + len(rb)))
    for i in (0, len(ra) - 1):
        assert rv.meta(i) == ra.meta(i) and rv.labels(i) == ra.labels(i)
    for j in (0, len(rb) - 1):
        fv, fb = rv[len(ra) + j], rb[j]
        assert fv["meta"] == fb["meta"]
        for name in ("camera_right", "radar_bev", "lidar_points"):
            np.testing.assert_array_equal(fv[name], fb[name])
    cfg = rv.manifest["config"]
    assert cfg["combined"] == {"gate": ra.manifest["config"], "test": rb.manifest["config"]}
    assert "seed" not in cfg and cfg["sequence_length"] == 2  # only the fields both parts share
    assert check(root / "view")["frames"] == rv.manifest["frames"] and verify(root / "view") == []
    # a second call with the same parts leaves it as it is; the links are relative: the folder moves
    assert combine({"gate": root / "gate", "test": root / "test"}, root / "view") == view
    moved = tmp_path / "moved"
    root.rename(moved)
    assert DatasetReader(moved / "view").meta(len(ra))["sequence_id"] == rb.meta(0)["sequence_id"]


def test_combine_refuses_what_would_mislead(parts, tmp_path):
    with pytest.raises(UserError, match="same seed"):
        combine({"a": parts / "gate", "b": parts / "gate"}, tmp_path / "v")
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "x").write_text("")
    with pytest.raises(UserError, match="not empty"):
        combine({"gate": parts / "gate"}, tmp_path / "busy")
    combine({"gate": parts / "gate"}, tmp_path / "one")
    with pytest.raises(UserError, match="another dataset"):
        combine({"test": parts / "test"}, tmp_path / "one")
    with pytest.raises(UserError, match="not a part"):
        part_indices(DatasetReader(tmp_path / "one").manifest, "test")
    assert not list(tmp_path.glob(".*tmp-*"))
