"""`hydrabench bench profile` on a tiny network: the parts add up to the step, the backward split is
a split, the feature maps are the strides the profile asks for."""

import pytest

from sim.errors import UserError
from study.bench.step_profile import PARTS, bench_profile
from tests.study.test_bench_amp import TINY


def test_the_parts_of_a_step_add_up_to_the_step():
    r = bench_profile("cpu", ("radar", "camera_right"), batch=2, steps=2, warmup=1, threads=1, overrides=TINY)
    parts = r["parts_ms"]
    assert set(PARTS) <= set(parts) and {"backward", "optimiser", "forward_other"} <= set(parts)
    # every part ran and took time; forward parts + backward + optimiser = the step (medians: a few % slack)
    for p in ("stems", "layer2", "layer3", "layer4", "rpn", "roi_align", "box_head", "backward", "optimiser"):
        assert parts[p] > 0, p
    assert sum(parts.values()) == pytest.approx(r["step_ms"], rel=0.1)
    assert sum(r["parts_pct"].values()) == pytest.approx(100, abs=10)
    assert r["backward_by_kind_pct"]["convolution"] > 0
    assert sum(r["backward_by_kind_pct"].values()) == pytest.approx(100, abs=0.5)
    # camera branches: output stride 16 (layer4 at stride 1); BEV: 8 (layer3 and layer4 at stride 1)
    cam, bev = r["feature_map_hw"]["camera_right"], r["feature_map_hw"]["radar"]
    assert cam["layer3"] == cam["layer4"] == [64 // 16, 96 // 16] and cam["layer2"] == [64 // 8, 96 // 8]
    assert bev["layer2"] == bev["layer3"] == bev["layer4"] == [64 // 8, 64 // 8]


def test_bad_arguments_are_user_errors():
    with pytest.raises(UserError, match="unknown branch"):
        bench_profile("cpu", ("sonar",), overrides=TINY)
    with pytest.raises(UserError, match="precision"):
        bench_profile("cpu", ("radar",), precision="fp8", overrides=TINY)
