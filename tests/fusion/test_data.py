import numpy as np
import pytest

from fusion.data import crop_bev_labels, split_by_sequence


def test_bev_crop_keeps_pixel_coordinates_and_drops_mostly_hidden_boxes():
    lab = {"boxes": [[10, 20, 20, 40], [10, 120, 20, 140], [10, 124, 20, 130], [50, 10, 60, 12]],
           "labels": [1, 2, 3, 4], "difficult": [False, False, True, False]}
    out = crop_bev_labels(lab, (128, 256), 256)
    assert out["labels"] == [1, 3, 4]  # box 2 is 60 % behind the crop edge: dropped
    assert out["boxes"][0] == [10, 20, 20, 40] and out["boxes"][1] == [10, 124, 20, 128]
    assert out["difficult"] == [False, True, False]
    lab2 = {"boxes": lab["boxes"] + [[100, 5, 110, 15]], "labels": [1, 2, 3, 4, 5], "difficult": [False] * 5}
    centred = crop_bev_labels(lab2, (128, 128), 256)  # columns 64..192 kept, shifted by 64
    assert centred["labels"] == [5] and centred["boxes"] == [[36, 5, 46, 15]]
    assert crop_bev_labels(lab, (256, 256), 256) is lab


class FakeReader:
    def __init__(self, shards):
        self.manifest = {"frames": [{"shard": s, "context": c, "index": k}
                                    for s, c, n in shards for k in range(n)]}


def test_split_is_by_sequence_and_stratified():
    shards = [(f"s{i}", "fog" if i < 5 else "city", 3) for i in range(10)]
    r = FakeReader(shards)
    train, test = split_by_sequence(r, 0.7, seed=1)
    shard_of = [f["shard"] for f in r.manifest["frames"]]
    assert not {shard_of[i] for i in train} & {shard_of[i] for i in test}
    assert sorted(train + test) == list(range(30))
    for ctx in ("fog", "city"):
        assert any(r.manifest["frames"][i]["context"] == ctx for i in test)
    assert (train, test) == split_by_sequence(r, 0.7, seed=1)
    with pytest.raises(ValueError):
        split_by_sequence(r, 1.0)
    assert np.isclose(len(train) / 30, 0.7, atol=0.1)
