"""Target checks without device syncs: `forward` reads target values only where they are on the CPU;
`check_targets` checks them all, before a training loop moves them to a GPU."""

import pytest
import torch

from .conftest import make_targets


def test_check_targets_reads_values_and_forward_reads_none_off_the_cpu(model):
    targets = make_targets(model, 2)
    model.check_targets(targets)  # good targets pass
    bad = [{f: dict(t) for f, t in per.items()} for per in targets]
    bad[1]["bev"]["labels"] = torch.full_like(bad[1]["bev"]["labels"], 99)
    with pytest.raises(ValueError, match=r"targets\[1\]\['bev'\]\['labels'\]: labels must be in"):
        model.check_targets(bad)
    per_sample = model.expand_selection(None, 2)
    with pytest.raises(ValueError, match="labels must be in"):
        model._check_targets(bad, per_sample)  # CPU tensors: forward checks the values itself
    # tensors on the meta device stand in for a GPU's: reading any value of them raises, so passing
    # means no value was read (no sync); shapes and dtypes are still checked
    meta = [{f: {k: v.to("meta") for k, v in t.items()} for f, t in per.items()} for per in bad]
    model._check_targets(meta, per_sample)
    meta[0]["bev"]["boxes"] = meta[0]["bev"]["boxes"].double()
    with pytest.raises(ValueError, match="expected a float32 tensor"):
        model._check_targets(meta, per_sample)
