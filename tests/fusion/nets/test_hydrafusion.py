"""HydraFusion: training losses and gradients, selective batched execution, eval outputs."""

import math

import pytest
import torch
from torch import nn

from fusion.nets import LOSS_NAMES, NORM_LAYERS, SENSORS, build_hydrafusion

from .conftest import TINY, make_inputs, make_targets

STEMS = {"camera", "radar", "lidar", "fwd_lidar"}


def _grads(module):
    """(every parameter has a gradient, some gradient is non-zero, any gradient exists)."""
    grads = [p.grad for p in module.parameters()]
    have = [g is not None for g in grads]
    nonzero = any(g is not None and g.abs().sum() > 0 for g in grads)
    return all(have), nonzero, any(have)


def test_train_all_seven_branches_losses_finite_and_gradients_reach_every_part(model):
    model.train()
    inputs, targets = make_inputs(model, 2), make_targets(model, 2)
    out = model(inputs, targets)
    assert set(out["branches"]) == set(model.branches) and len(model.branches) == 7
    for name, losses in out["branches"].items():
        assert tuple(sorted(losses)) == tuple(sorted(LOSS_NAMES)), name
        assert all(torch.isfinite(v) and v.dim() == 0 for v in losses.values()), name
    # one selection for every sample: the total is the plain sum, as in torchvision
    expected = sum(sum(d.values()) for d in out["branches"].values())
    assert torch.allclose(out["total"], expected)
    out["total"].backward()
    assert set(model.stems) == STEMS
    for name, part in [*model.stems.items(), *model.branches.items()]:
        all_have, nonzero, _ = _grads(part)
        assert all_have and nonzero, name
        assert all(torch.isfinite(p.grad).all() for p in part.parameters()), name


def test_per_sample_selection_weights_losses_and_gradients_skip_unselected_parts(model):
    model.train()
    inputs, targets = make_inputs(model, 2), make_targets(model, 2)
    selected = ["radar", "camera_both"]
    out = model(inputs, targets, selection=[["radar", "camera_both"], ["radar"]])
    # each branch weighs by the share of samples that selected it
    radar, both = (sum(out["branches"][n].values()) for n in selected)
    assert torch.allclose(out["total"], radar + 0.5 * both)
    out["total"].backward()
    for name, part in model.stems.items():
        all_have, nonzero, any_have = _grads(part)
        if name in ("radar", "camera"):
            assert all_have and nonzero, name
        else:
            assert not any_have, name
    for name, part in model.branches.items():
        all_have, nonzero, any_have = _grads(part)
        assert (all_have and nonzero) if name in selected else not any_have, name


class _Recorder:
    """Forward hooks counting calls and keeping the inputs of every stem and branch."""

    def __init__(self, model):
        self.calls = {}
        self.handles = []
        for kind, parts in (("stem", model.stems), ("branch", model.branches)):
            for name, part in parts.items():
                self.handles.append(part.register_forward_hook(self._hook((kind, name))))

    def _hook(self, key):
        def hook(module, args, output):
            self.calls.setdefault(key, []).append(args[0])

        return hook

    def remove(self):
        for h in self.handles:
            h.remove()


def test_only_needed_stems_and_selected_branches_run_once_per_group_in_order(model):
    inputs = make_inputs(model, 4)
    reference = model.extract_features(inputs)  # every stem on every sample
    selection = [["radar", "camera_both"], ["camera_left"], ["radar"], ["camera_left", "camera_both"]]
    assert model.stems_for(selection) == ("camera", "radar")
    assert model.sensors_for(selection) == ("camera_left", "camera_right", "radar")
    rec = _Recorder(model)
    try:
        with torch.no_grad():
            out = model(inputs, selection=selection)
    finally:
        rec.remove()
    assert set(rec.calls) == {
        ("stem", "camera"),
        ("stem", "radar"),
        ("branch", "radar"),
        ("branch", "camera_left"),
        ("branch", "camera_both"),
    }
    assert all(len(v) == 1 for v in rec.calls.values())
    # camera stem: left images of samples 0, 1, 3 (camera_left, camera_both) + right of 0, 3
    assert rec.calls[("stem", "camera")][0].shape[0] == 5
    assert rec.calls[("stem", "radar")][0].shape[0] == 2
    groups = {"radar": [0, 2], "camera_left": [1, 3], "camera_both": [0, 3]}
    for name, idx in groups.items():
        xs = rec.calls[("branch", name)][0]
        assert len(xs) == len(model.branches[name].sensors)
        for x, sensor in zip(xs, model.branches[name].sensors):
            assert torch.allclose(x, reference[sensor][idx], atol=1e-5), (name, sensor)
    # scattered back: each sample has exactly its branches, equal to running it alone
    assert [list(o) for o in out] == [
        ["radar", "camera_both"],
        ["camera_left"],
        ["radar"],
        ["camera_left", "camera_both"],
    ]
    for i in (0, 3):
        alone = model({s: x[i : i + 1] for s, x in inputs.items()}, selection=selection[i])[0]
        for name in selection[i]:
            for key in ("boxes", "labels", "scores"):
                assert torch.allclose(out[i][name][key].float(), alone[name][key].float(), atol=1e-4), (
                    i,
                    name,
                )


def test_eval_detections_per_sample_per_branch_inside_the_frame(model):
    inputs = make_inputs(model, 2)
    with torch.no_grad():
        out = model(inputs)
    assert len(out) == 2
    for per_branch in out:
        assert list(per_branch) == list(model.branches)
        for name, det in per_branch.items():
            h, w = model.transform.sizes["bev" if model.branch_frames[name] == "bev" else "camera"]
            boxes, labels, scores = det["boxes"], det["labels"], det["scores"]
            assert boxes.shape[1] == 4 and boxes.shape[0] == labels.shape[0] == scores.shape[0] > 0
            assert boxes.shape[0] <= model.profile.box_detections_per_img
            assert (boxes[:, 0] >= 0).all() and (boxes[:, 1] >= 0).all()
            assert (boxes[:, 2] <= w).all() and (boxes[:, 3] <= h).all(), name
            assert (boxes[:, 2] >= boxes[:, 0]).all() and (boxes[:, 3] >= boxes[:, 1]).all()
            assert labels.dtype == torch.int64 and labels.min() >= 1 and labels.max() <= 8
            assert (scores >= model.profile.box_score_thresh).all() and (scores <= 1).all()


def _set_norm_eval(model):
    for m in model.modules():
        if isinstance(m, nn.modules.batchnorm._BatchNorm):
            m.eval()


def test_per_sample_losses_equal_batch1_training_losses_under_the_same_seed(model):
    inputs, targets = make_inputs(model, 2), make_targets(model, 2)
    stats = {k: v.clone() for k, v in model.state_dict().items()}
    rng = torch.get_rng_state()
    per = model.per_sample_losses(inputs, targets, seed=7)
    assert torch.equal(torch.get_rng_state(), rng)  # the caller's random stream is untouched
    assert all(torch.equal(v, stats[k]) for k, v in model.state_dict().items())  # nothing updated
    assert [list(p) for p in per] == [list(model.branches)] * 2
    # batch norm uses its running statistics in eval mode, so compare with a training step that does too
    model.train()
    _set_norm_eval(model)
    alone = {s: x[1:2] for s, x in inputs.items()}  # the second sample, so not "first in batch" luck
    for name in model.branches:
        torch.manual_seed(7)
        with torch.no_grad():
            ref = model(alone, [targets[1]], selection=[name])["branches"][name]
        for k in LOSS_NAMES:
            assert math.isclose(per[1][name][k].item(), ref[k].item(), rel_tol=1e-4, abs_tol=1e-6), (name, k)
    model.eval()
    # independent of batch order and composition
    flipped = model.per_sample_losses({s: x.flip(0) for s, x in inputs.items()}, targets[::-1], seed=7)
    for name in model.branches:
        for k in LOSS_NAMES:
            assert torch.allclose(flipped[1][name][k], per[0][name][k], rtol=1e-4, atol=1e-6)
    # the seed matters: sampling is random
    other = model.per_sample_losses(inputs, targets, selection=["camera_right"], seed=8)
    assert any(other[0]["camera_right"][k] != per[0]["camera_right"][k] for k in LOSS_NAMES)
    model.train()
    with pytest.raises(RuntimeError, match="eval mode"):
        model.per_sample_losses(inputs, targets)


def test_detect_and_losses_are_forward_and_per_sample_losses_from_one_backbone_run(model):
    """One run of stems and backbones gives the detections of `forward` over every branch and the
    losses of `per_sample_losses`, bit for bit (the prediction pass relies on it)."""
    was = model.training
    model.eval()
    inputs, targets = make_inputs(model, 2, seed=3), make_targets(model, 2, seed=3)
    dets, losses = model.detect_and_losses(inputs, targets, seed=5)
    with torch.no_grad():
        ref = model(inputs, selection=list(model.branches))
    per = model.per_sample_losses(inputs, targets, seed=5)
    assert [list(d) for d in dets] == [list(model.branches)] * 2 and [list(p) for p in losses] == [list(model.branches)] * 2
    for i in range(2):
        for name in model.branches:
            for key in ("boxes", "scores", "labels"):
                assert torch.equal(dets[i][name][key], ref[i][name][key]), (i, name, key)
            for k in LOSS_NAMES:
                assert torch.equal(losses[i][name][k], per[i][name][k]), (i, name, k)
    model.train()
    with pytest.raises(RuntimeError, match="eval mode"):
        model.detect_and_losses(inputs, targets)
    model.train(was)


def test_detect_and_losses_on_given_stem_features_are_the_same_bit_for_bit(model):
    """The prediction pass hands the stems' features the gates read to detect_and_losses instead of
    running the stems twice: on features of exactly `stem_sensors` the numbers are identical, and
    features missing a sensor the branches need are refused."""
    was = model.training
    model.eval()
    inputs, targets = make_inputs(model, 2, seed=4), make_targets(model, 2, seed=4)
    need = model.stem_sensors(inputs)
    assert need and set(need) <= set(model.sensors)
    dets, losses = model.detect_and_losses(inputs, targets, seed=5)
    with torch.no_grad():
        feats = model.extract_features(inputs, need)
    dets2, losses2 = model.detect_and_losses(inputs, targets, seed=5, features=feats)
    for i in range(2):
        for name in model.branches:
            for key in ("boxes", "scores", "labels"):
                assert torch.equal(dets[i][name][key], dets2[i][name][key]), (i, name, key)
            for k in LOSS_NAMES:
                assert torch.equal(losses[i][name][k], losses2[i][name][k]), (i, name, k)
    with pytest.raises(ValueError, match="no stem features for sensor"):
        model.detect_and_losses(inputs, targets, seed=5, features={s: f for s, f in feats.items() if s != need[0]})
    model.train(was)


@pytest.mark.parametrize("norm", NORM_LAYERS.names())
def test_every_norm_layer_trains_and_group_norm_matches_plain_training(norm):
    torch.manual_seed(0)
    branches = [{"name": "radar_lidar", "sensors": ["radar", "lidar"], "frame": "bev"}]
    model = build_hydrafusion(profile="cpu", branches=branches, norm=norm, **TINY)
    inputs, targets = make_inputs(model, 2), make_targets(model, 2)
    model.train()
    torch.manual_seed(3)
    out = model(inputs, targets)
    out["total"].backward()
    assert torch.isfinite(out["total"])
    if norm == "group":  # batch-independent: per-sample eval losses = plain batch-1 training losses
        model.eval()
        per = model.per_sample_losses(inputs, targets, seed=3)
        model.train()
        torch.manual_seed(3)
        with torch.no_grad():
            ref = model({s: x[1:] for s, x in inputs.items()}, targets[1:])["branches"]["radar_lidar"]
        for k in LOSS_NAMES:
            assert math.isclose(per[1]["radar_lidar"][k].item(), ref[k].item(), rel_tol=1e-4, abs_tol=1e-6)


def test_custom_branch_set_builds_only_the_stems_it_needs():
    torch.manual_seed(0)
    branches = [
        {"name": "cam_fwd_lidar", "sensors": ["camera_right", "fwd_lidar"], "frame": "camera_right"},
        {"name": "lidar_radar", "sensors": ["lidar", "radar"], "frame": "bev"},
    ]
    model = build_hydrafusion(profile="cpu", branches=branches, **TINY)
    assert list(model.branches) == ["cam_fwd_lidar", "lidar_radar"]
    assert set(model.stems) == STEMS
    assert model.branch_sensors == {
        "cam_fwd_lidar": ("camera_right", "fwd_lidar"),
        "lidar_radar": ("lidar", "radar"),
    }
    assert model.branch_frames == {"cam_fwd_lidar": "camera_right", "lidar_radar": "bev"}
    assert model.branches["cam_fwd_lidar"].merge.in_channels == 128
    assert model.stems_for(["cam_fwd_lidar"]) == ("camera", "fwd_lidar")
    assert model.stems["radar"].conv1.in_channels == 1
    inputs = make_inputs(model, 2, sensors=["camera_right", "fwd_lidar", "lidar", "radar"])
    model.train()
    out = model(inputs, make_targets(model, 2))
    assert set(out["branches"]) == {"cam_fwd_lidar", "lidar_radar"} and torch.isfinite(out["total"])
    single = build_hydrafusion(
        profile="cpu", branches=[{"name": "r", "sensors": ["camera_right"], "frame": "camera_right"}], **TINY
    )
    assert list(single.stems) == ["camera"] and single.branches["r"].merge is None


def test_output_stride_is_real_at_profile_sizes():
    torch.manual_seed(0)
    cpu = build_hydrafusion(
        profile="cpu",
        branches=[
            {"name": "cam", "sensors": ["camera_right"], "frame": "camera_right"},
            {"name": "bev", "sensors": ["radar"], "frame": "bev"},
        ],
    ).eval()
    inputs = {"camera_right": torch.rand(1, 3, 188, 336), "radar": torch.rand(1, 1, 128, 256)}  # forward BEV half
    with torch.no_grad():
        feats = cpu.extract_features(inputs)
        assert feats["camera_right"].shape == (1, 64, 48, 84)  # 188 padded to 192, stride 4
        assert feats["radar"].shape == (1, 64, 32, 64)
        cam = cpu.branches["cam"].features([feats["camera_right"]])
        bev = cpu.branches["bev"].features([feats["radar"]])
    assert cam.shape == (1, 128, 12, 21)  # 192 / 16, 336 / 16 (camera output stride 16 in the cpu profile)
    assert bev.shape == (1, 128, 16, 32)  # BEV at output stride 8 (configs/model/cpu.yaml)
    images = cpu.branches["cam"]._images(1, cam)
    anchors = cpu.branches["cam"].rpn.anchor_generator(images, [cam])[0]
    centres = ((anchors[:, 0] + anchors[:, 2]) / 2).unique()
    assert torch.allclose(centres.diff(), torch.tensor(16.0)) and len(centres) == 21

    paper = build_hydrafusion(
        profile="paper",
        branches=[{"name": "cam", "sensors": ["camera_right"], "frame": "camera_right"}],
        camera={"size": (96, 160)},
    )
    with torch.no_grad():
        stem = paper.eval().extract_features({"camera_right": torch.rand(1, 3, 96, 160)})["camera_right"]
        f = paper.branches["cam"].features([stem])
    assert f.shape == (1, 512, 3, 5)  # stride 32, no channel reduction


class _EvenOddGate(nn.Module):
    """Radar for even samples, the right camera for odd ones; records what it was given."""

    def forward(self, features, meta):
        self.seen = {s: tuple(f.shape) for s, f in features.items()}
        self.meta = meta
        return [["radar"] if i % 2 == 0 else ["camera_right"] for i in range(len(meta))]


class _Concat(nn.Module):
    """Keeps every branch's boxes, tagged with the branch frame."""

    def forward(self, detections, frames, meta):
        self.called = True
        return [
            {"frames": [frames[n] for n in d], "count": sum(len(v["boxes"]) for v in d.values())}
            for d in detections
        ]


def test_gate_and_fusion_block_extension_points(_tiny_model):
    gate, fusion = _EvenOddGate(), _Concat()
    model = type(_tiny_model)(
        _tiny_model.stems, _tiny_model.branches, gate, fusion, transform=_tiny_model.transform
    ).eval()
    inputs = make_inputs(model, 3)
    with torch.no_grad():
        fused = model(inputs, meta=["a", "b", "c"])
    assert set(gate.seen) == set(SENSORS) and gate.meta == ["a", "b", "c"]
    assert [f["frames"] for f in fused] == [["bev"], ["camera_right"], ["bev"]]
    with torch.no_grad():  # an explicit selection bypasses the gate
        fused = model(inputs, selection=["lidar"], meta=[1, 2, 3])
    assert [f["frames"] for f in fused] == [["bev"]] * 3
    model.train()
    out = model(inputs, make_targets(model, 3), meta=["a", "b", "c"])
    assert set(out["branches"]) == {"radar", "camera_right"}
    _tiny_model.zero_grad(set_to_none=True)


def _box(x1, y1, x2, y2):
    return torch.tensor([[x1, y1, x2, y2]], dtype=torch.float32)


def test_bad_inputs_selections_and_targets_raise_value_errors_naming_the_field(model):
    inputs = make_inputs(model, 2)
    good = make_targets(model, 2)

    def fails(message, inputs=inputs, targets=None, selection=None, train=False):
        model.train(train)
        with pytest.raises(ValueError, match=message):
            model(inputs, targets, selection=selection)
        model.eval()

    no_lidar = {k: v for k, v in inputs.items() if k != "lidar"}
    fails(r"inputs: sensor 'lidar' is missing; branch 'lidar' needs it", inputs=no_lidar)
    with torch.no_grad():  # sensors of unselected branches may be missing
        assert list(model(no_lidar, selection=["radar"])[0]) == ["radar"]
    fails(
        r"inputs\['radar'\]: expected shape \(B, 1, 64, 64\)",
        inputs={**inputs, "radar": torch.rand(2, 3, 64, 64)},
    )
    fails(
        r"inputs\['camera_left'\]: expected shape \(B, 3, 64, 96\)",
        inputs={**inputs, "camera_left": torch.rand(2, 3, 64, 64)},
    )
    fails(r"inputs\['lidar'\]: expected shape", inputs={**inputs, "lidar": torch.rand(3, 64, 64)})
    fails(
        r"inputs\['lidar'\]: expected a float32 tensor",
        inputs={**inputs, "lidar": torch.zeros(2, 3, 64, 64, dtype=torch.uint8)},
    )
    fails(r"inputs\['lidar'\]: batch size 1 differs", inputs={**inputs, "lidar": torch.rand(1, 3, 64, 64)})
    fails(r"inputs: unknown sensor 'camera_lft'", inputs={**inputs, "camera_lft": inputs["camera_left"]})
    fails(r"selection: unknown branch 'radr'", selection=["radr"])
    fails(r"selection\[1\]: no branch selected", selection=[["radar"], []])
    fails(r"selection: 3 per-sample lists for a batch of 2", selection=[["radar"]] * 3)
    fails(r"selection: expected a non-empty list", selection="radar")
    fails(r"selection: expected a non-empty list", selection=[])
    fails(r"selection: mixes branch names and per-sample lists", selection=["radar", ["lidar"]])
    fails(r"selection\[0\]: a branch is named twice", selection=[["radar", "radar"], ["lidar"]])
    fails(r"targets: only used in training mode", targets=good)
    fails(r"targets: required in training mode", train=True)

    def bad_target(message, i, frame, **entry):
        targets = [{f: dict(v) for f, v in t.items()} for t in good]
        if entry:
            targets[i][frame].update(entry)
        else:
            del targets[i][frame]
        fails(message, targets=targets, train=True)

    bad_target(r"targets\[1\]: no 'bev' entry, needed by branch 'radar'", 1, "bev")
    bad_target(
        r"targets\[0\]\['bev'\]\['labels'\]: labels must be in 1..8", 0, "bev", labels=torch.tensor([9, 1, 2])
    )
    bad_target(
        r"labels must be in 1..8 \(0 is background\), got \[0, 1\]", 0, "bev", labels=torch.tensor([0, 1, 1])
    )
    bad_target(
        r"targets\[0\]\['camera_left'\]\['labels'\]: expected an int64",
        0,
        "camera_left",
        labels=torch.tensor([1.0, 2.0, 3.0]),
    )
    bad_target(
        r"targets\[1\]\['camera_right'\]: 1 boxes but 3 labels", 1, "camera_right", boxes=_box(1, 1, 9, 9)
    )
    bad_target(r"\['boxes'\]: boxes need x2 > x1", 1, "bev", boxes=_box(9, 1, 1, 9), labels=torch.tensor([1]))
    bad_target(
        r"inside the 64x64 \(W x H\) image of frame 'bev'",
        1,
        "bev",
        boxes=_box(1, 1, 9, 70),
        labels=torch.tensor([1]),
    )
    bad_target(r"\['boxes'\]: expected a float32 tensor \(N, 4\)", 1, "bev", boxes=torch.zeros(3, 5))
    bad_target(
        r"\['boxes'\]: expected a float32 tensor", 1, "bev", boxes=torch.zeros(3, 4, dtype=torch.float64)
    )
    typo = [dict(t, BEV=t["bev"]) for t in good]
    fails(r"targets\[0\]: unknown frame 'BEV'", targets=typo, train=True)
    fails(r"targets: 1 entries for a batch of 2", targets=good[:1], train=True)
    # empty targets are background images, allowed
    empty = {"boxes": torch.zeros(0, 4), "labels": torch.zeros(0, dtype=torch.int64)}
    model.train()
    out = model(inputs, [{"bev": empty}, {"bev": empty}], selection=["radar"])
    assert torch.isfinite(out["total"])
    model.eval()


def test_input_level_early_fusion_branch_has_its_own_stem_and_trains():
    """Table 2 (ii): one network on channel-stacked inputs (fusion "input"), no shared stems."""
    from fusion.nets import build_hydrafusion
    from fusion.nets.profile import BranchSpec
    from tests.fusion.nets.conftest import TINY, make_inputs, make_targets

    torch.manual_seed(0)
    spec = BranchSpec("early_cams", ("camera_left", "camera_right"), "camera_right", fusion="input")
    model = build_hydrafusion(profile="cpu", branches=[spec], **TINY)
    branch = model.branches["early_cams"]
    assert branch.input_stem is not None and branch.input_stem.in_channels == 6 and branch.merge is None
    assert model.stems_for(["early_cams"]) == () and len(model.stems) == 0
    calls = []
    hooks = [stem.register_forward_hook(lambda *a: calls.append(1)) for stem in model.stems.values()]
    model.train()
    inputs = make_inputs(model, 2, sensors=("camera_left", "camera_right"))
    out = model(inputs, make_targets(model, 2))
    out["total"].backward()
    assert calls == [] and torch.isfinite(out["total"])
    assert branch.input_stem.conv1.weight.grad is not None
    # the stacked input really carries both cameras: changing the left image changes the output
    model.eval()
    with torch.no_grad():
        f1 = branch.features([model.transform(s, inputs[s]) for s in ("camera_left", "camera_right")])
        inputs2 = dict(inputs, camera_left=torch.zeros_like(inputs["camera_left"]))
        f2 = branch.features([model.transform(s, inputs2[s]) for s in ("camera_left", "camera_right")])
    assert not torch.allclose(f1, f2)
    for h in hooks:
        h.remove()


def test_a_context_gate_decides_before_any_stem_runs(model):
    """EcoFusion 4.2.1: a knowledge gate reads external context, so wired into the network it
    decides first and only the stems of the branches it chose run (the informed one, told the fog's
    severity 5, picks radar alone: the radar stem once, no camera or lidar stem); a feature-reading
    gate still runs every stem."""
    from fusion.nets.branch_gates import build_gate

    inputs = make_inputs(model, 2)
    meta = [{"layout": "motorway", "conditions": ["fog"], "severity": 5}] * 2
    calls = {}
    hooks = [m.register_forward_hook(lambda mod, a, o, n=n: calls.__setitem__(n, calls.get(n, 0) + 1))
             for n, m in model.stems.items()]
    try:
        model.gate = build_gate("knowledge_informed", model, k=1)
        with torch.no_grad():
            out = model(inputs, meta=meta)
        assert [list(o) for o in out] == [["radar"], ["radar"]]
        assert calls == {"radar": 1}
        calls.clear()
        model.gate = build_gate("deep", model, k=1)  # untrained: reads every stem, keeps the first branch
        with torch.no_grad():
            model(inputs, meta=meta)
        assert set(calls) == STEMS
    finally:
        model.gate = None
        for h in hooks:
            h.remove()
