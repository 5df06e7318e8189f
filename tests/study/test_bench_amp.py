"""`hydrabench bench amp` on a tiny network: both precisions train from the same weights on the same
frames, the report says what --amp auto picks on this CPU and why."""

import pytest

from sim.errors import UserError
from study.bench.amp import bench_amp
from study.device import native_bf16

TINY = {"camera": {"size": (64, 96)}, "bev": {"size": (64, 64)}, "roi_channels": 32, "box_head_width": 64,
        "box_batch_size_per_image": 32, "rpn_pre_nms_top_n_train": 200, "rpn_post_nms_top_n_train": 100}


def test_bench_amp_measures_both_precisions_from_the_same_start():
    r = bench_amp("cpu", ("radar",), batch=2, steps=2, warmup=1, threads=1, overrides=TINY)
    assert r["branches"] == ["radar"] and r["threads"] == 1
    assert all(len(r["step_s_all"][p]) == 2 and min(r["step_s_all"][p]) > 0 for p in ("fp32", "bf16"))
    assert r["speedup_bf16"] == pytest.approx(r["step_s"]["fp32"] / r["step_s"]["bf16"], rel=0.05)
    fp32, bf16 = r["loss_per_step"]["fp32"], r["loss_per_step"]["bf16"]
    assert len(fp32) == len(bf16) == 3
    # the same weights, frames and sampling: the first losses differ by bf16 rounding of the backbone only
    assert fp32[0] != bf16[0] and abs(fp32[0] - bf16[0]) < 0.05 * fp32[0]
    assert (r["native_bf16"], r["native_bf16_reason"]) == native_bf16("cpu")
    assert r["amp_auto_picks"] == ("bf16" if r["native_bf16"] else "fp32")


def test_bench_amp_refuses_unknown_branches():
    with pytest.raises(UserError, match="unknown branch 'sonar'"):
        bench_amp("cpu", ("sonar",), overrides=TINY)
