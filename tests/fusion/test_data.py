import numpy as np
import pytest

from fusion.data import crop_bev_labels, hold_out_sequences, split_by_sequence


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


def test_the_gate_split_holds_out_whole_sequences_per_context():
    shards = [(f"s{i}", "fog" if i < 6 else "city", 4) for i in range(10)]  # 6 fog, 4 city sequences
    r = FakeReader(shards)
    frames = r.manifest["frames"]
    kept, held = hold_out_sequences(r, range(40), 0.3, seed=2)
    assert sorted(kept + held) == list(range(40)) and not set(kept) & set(held)
    shard = lambda idx: {frames[i]["shard"] for i in idx}  # noqa: E731
    assert not shard(kept) & shard(held)  # whole sequences
    per_ctx = lambda idx, c: len({frames[i]["shard"] for i in idx if frames[i]["context"] == c})  # noqa: E731
    assert per_ctx(held, "fog") == 2 and per_ctx(held, "city") == 1  # round(0.3 * 6), round(0.3 * 4)
    assert (kept, held) == hold_out_sequences(r, range(40), 0.3, seed=2)
    assert (kept, held) != hold_out_sequences(r, range(40), 0.3, seed=3)
    # a subset (the train split) is carved from its own sequences only; 0 holds out nothing
    sub = [i for i in range(40) if frames[i]["shard"] in ("s0", "s1", "s6")]
    k2, h2 = hold_out_sequences(r, sub, 0.5, seed=0)
    assert sorted(k2 + h2) == sub and per_ctx(h2, "fog") == 1 and per_ctx(h2, "city") == 0  # one left: kept
    assert hold_out_sequences(r, range(40), 0.0) == (list(range(40)), [])
    assert per_ctx(hold_out_sequences(r, range(40), 0.01)[1], "city") == 1  # any share holds out one sequence
    with pytest.raises(ValueError, match=r"\[0, 1\)"):
        hold_out_sequences(r, range(40), 1.0)
