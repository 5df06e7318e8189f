"""Model profiles: strict loading, the branch set as configuration, torchvision defaults."""

import inspect
from collections import OrderedDict

import numpy as np
import pytest
from torch import nn
from torchvision.models.detection import FasterRCNN
from torchvision.models.detection.faster_rcnn import _default_anchorgen

from fusion.nets import (
    PROFILE_DIR,
    BranchSpec,
    ModelProfile,
    available_profiles,
    build_branch,
    build_hydrafusion,
    load_profile,
)
from sim.config import load_yaml
from sim.errors import UserError

PAPER_BRANCHES = [
    ("radar", ("radar",), "bev"),
    ("camera_left", ("camera_left",), "camera_left"),
    ("camera_right", ("camera_right",), "camera_right"),
    ("lidar", ("lidar",), "bev"),
    ("camera_both", ("camera_left", "camera_right"), "camera_right"),
    ("camera_lidar", ("camera_left", "camera_right", "fwd_lidar"), "camera_right"),
    ("radar_lidar", ("radar", "lidar"), "bev"),
]


@pytest.mark.parametrize("name", ["cpu", "paper"])
def test_profiles_load_strictly_with_the_papers_seven_branches(name, tmp_path):
    assert {"cpu", "paper"} <= set(available_profiles())
    prof = load_yaml(ModelProfile, PROFILE_DIR / f"{name}.yaml")
    assert prof == load_profile(name)
    assert [(b.name, b.sensors, b.frame) for b in prof.branches] == PAPER_BRANCHES
    assert prof.num_classes == 9
    text = (PROFILE_DIR / f"{name}.yaml").read_text()
    bad = tmp_path / f"{name}.yaml"
    bad.write_text(text + "rpn_nms_treshold: 0.5\n")
    with pytest.raises(UserError, match=f"{name}.yaml: unknown key 'rpn_nms_treshold'"):
        load_yaml(ModelProfile, bad)
    bad.write_text(text.replace("  output_stride:", "  outptu_stride:", 1))
    with pytest.raises(UserError, match=rf"{name}.yaml.camera: unknown key 'outptu_stride'"):
        load_yaml(ModelProfile, bad)


def test_cpu_profile_shrinks_what_dominates_cpu_time():
    cpu, paper = load_profile("cpu"), load_profile("paper")
    assert cpu.camera.size == (188, 336) and cpu.bev.size == (128, 256)  # the forward half of the 256 x 256 BEV
    assert paper.camera.size == (376, 672) and paper.bev.size == (1152, 1152)
    assert cpu.camera.output_stride == 16 and paper.camera.output_stride == 32
    assert cpu.roi_channels == 128 and cpu.box_head_width == 256
    assert cpu.box_batch_size_per_image < paper.box_batch_size_per_image
    assert cpu.rpn_post_nms_top_n_test < paper.rpn_post_nms_top_n_test
    # anchors per view: BEV anchors cover a car (11 x 5 px at 0.4 m/px, sqrt(area) ~7.4 px) to a
    # truck; the cpu camera's smallest anchor is below the paper's (half the resolution)
    car_bev = np.sqrt(4.5 / 0.4 * 1.8 / 0.4)
    assert min(cpu.bev.anchor_sizes) <= 1.25 * car_bev and max(cpu.bev.anchor_sizes) >= 27
    assert min(cpu.camera.anchor_sizes) < min(paper.camera.anchor_sizes)


def test_overrides_merge_deeply_and_are_checked():
    prof = load_profile("cpu", camera={"size": (64, 96)}, roi_channels=64)
    assert (
        prof.camera.size == (64, 96) and prof.camera.anchor_sizes == load_profile("cpu").camera.anchor_sizes
    )
    assert prof.roi_channels == 64
    with pytest.raises(UserError, match="cpu: unknown key 'roi_chanels'"):
        load_profile("cpu", roi_chanels=64)
    with pytest.raises(UserError, match=r"cpu.camera.output_stride: 12 is not one of \[8, 16, 32\]"):
        load_profile("cpu", camera={"output_stride": 12})
    with pytest.raises(UserError, match=r"cpu.camera: size: expected \(H, W\)"):
        load_profile("cpu", camera={"size": (64, 96, 3)})
    with pytest.raises(UserError, match=r"cpu.bev: anchor_sizes: no anchor is at least 8 px"):
        load_profile("cpu", bev={"anchor_sizes": [4, 6]})  # the cpu BEV grid step is 8 px
    with pytest.raises(UserError, match="unknown normalisation layer 'instance'"):
        load_profile("cpu", norm="instance")
    with pytest.raises(UserError, match="normalization.radar: expected 1 mean and 1 std"):
        load_profile("cpu", normalization={"radar": {"mean": [0.0, 0.0], "std": [1.0, 1.0]}})
    with pytest.raises(UserError, match="rpn_nms_thresh: must be in"):
        load_profile("cpu", rpn_nms_thresh=1.5)
    with pytest.raises(UserError, match="unknown model profile 'gpu' .choose from: cpu, paper"):
        load_profile("gpu")


@pytest.mark.parametrize(
    ("branches", "message"),
    [
        (
            [{"name": "r", "sensors": ["radr"], "frame": "bev"}],
            r"branches\[0\]: sensors: branch 'r' names unknown sensor 'radr'",
        ),
        (
            [{"name": "r", "sensors": [], "frame": "bev"}],
            r"branches\[0\]: sensors: branch 'r' has no sensors",
        ),
        (
            [
                {"name": "r", "sensors": ["radar"], "frame": "bev"},
                {"name": "r", "sensors": ["lidar"], "frame": "bev"},
            ],
            "branches: duplicate branch name 'r'",
        ),
        ([{"name": "r", "sensors": ["radar", "radar"], "frame": "bev"}], "lists a sensor twice"),
        ([{"name": "r.x", "sensors": ["radar"], "frame": "bev"}], "not a valid branch name"),
        ([{"name": "r", "sensors": ["radar"], "frame": "fwd"}], r"branches\[0\].frame: 'fwd' is not one of"),
        ([{"name": "r", "sensors": ["radar"]}], r"branches\[0\]: missing key 'frame'"),
        ([], "branches: the branch set is empty"),
        # radar is a BEV image: concatenating it cell by cell with a camera image is meaningless
        (
            [{"name": "radar_cam", "sensors": ["radar", "camera_right"], "frame": "camera_right"}],
            "branch 'radar_cam' mixes views: sensor 'radar' is a bev image but frame 'camera_right'",
        ),
    ],
)
def test_bad_branch_configs_fail_naming_the_field(branches, message):
    with pytest.raises(UserError, match=message):
        load_profile("cpu", branches=branches)
    with pytest.raises(ValueError, match=message):  # UserError is a ValueError
        build_hydrafusion(profile="cpu", branches=branches)


class _Backbone(nn.Module):
    out_channels = 512

    def forward(self, x):
        return OrderedDict([("0", x)])


def test_paper_profile_is_torchvision_faster_rcnn_defaults():
    paper = load_profile("paper")
    defaults = {
        k: p.default
        for k, p in inspect.signature(FasterRCNN.__init__).parameters.items()
        if p.default is not inspect.Parameter.empty and p.default is not None
    }
    shared = [k for k in defaults if hasattr(paper, k)]
    assert len(shared) >= 17  # every rpn_* and box_* number
    for k in shared:
        assert getattr(paper, k) == defaults[k], k

    anchorgen = _default_anchorgen()  # FPN layout: one size per level; ours puts all on one map
    sizes = tuple(float(s) for level in anchorgen.sizes for s in level)
    for view in (paper.camera, paper.bev):
        assert view.anchor_sizes == sizes
        assert view.aspect_ratios == tuple(anchorgen.aspect_ratios[0])
        assert view.output_stride == 32

    # Built modules, attribute by attribute, against a torchvision FasterRCNN on a 512-channel map.
    ref = FasterRCNN(_Backbone(), num_classes=9, rpn_anchor_generator=None)
    ours = build_branch(BranchSpec("camera_right", ("camera_right",), "camera_right"), paper)
    assert ours.neck is None  # 512 channels straight into the RPN head and RoIAlign
    for attr in ("_pre_nms_top_n", "_post_nms_top_n", "nms_thresh", "score_thresh", "min_size"):
        assert getattr(ours.rpn, attr) == getattr(ref.rpn, attr), attr
    for a, b in ((ours.rpn, ref.rpn), (ours.roi_heads, ref.roi_heads)):
        assert a.proposal_matcher.high_threshold == b.proposal_matcher.high_threshold
        assert a.proposal_matcher.low_threshold == b.proposal_matcher.low_threshold
        assert a.proposal_matcher.allow_low_quality_matches == b.proposal_matcher.allow_low_quality_matches
        assert a.fg_bg_sampler.batch_size_per_image == b.fg_bg_sampler.batch_size_per_image
        assert a.fg_bg_sampler.positive_fraction == b.fg_bg_sampler.positive_fraction
        assert a.box_coder.weights == b.box_coder.weights
    assert ours.rpn.head.conv[0][0].in_channels == ref.rpn.head.conv[0][0].in_channels == 512
    for attr in ("score_thresh", "nms_thresh", "detections_per_img"):
        assert getattr(ours.roi_heads, attr) == getattr(ref.roi_heads, attr), attr
    pool, ref_pool = ours.roi_heads.box_roi_pool, ref.roi_heads.box_roi_pool
    assert (pool.output_size, pool.sampling_ratio) == (ref_pool.output_size, ref_pool.sampling_ratio)
    for layer in ("fc6", "fc7"):
        a, b = getattr(ours.roi_heads.box_head, layer), getattr(ref.roi_heads.box_head, layer)
        assert (a.in_features, a.out_features) == (b.in_features, b.out_features) == (b.in_features, 1024)
    assert ours.roi_heads.box_predictor.cls_score.out_features == 9
    assert ours.roi_heads.box_predictor.bbox_pred.out_features == 36


def test_branch_spec_is_usable_directly():
    spec = BranchSpec("cam_fwd", ("camera_right", "fwd_lidar"), "camera_right")
    prof = load_profile("cpu", branches=[spec])
    assert prof.branches == (spec,)
    with pytest.raises(ValueError, match="has no sensors"):
        BranchSpec("x", (), "bev")
