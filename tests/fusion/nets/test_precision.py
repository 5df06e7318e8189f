"""Precision under autocast: the backbone may run in bf16, box decoding may not.

bf16 keeps 8 mantissa bits: between 512 and 1024 px consecutive values are 4 px apart. torchvision's
anchors take the feature dtype and its BoxCoder decodes in the dtype of the regression codes, so
under autocast a decoded BEV car box (about 10 x 26 px) on the 1152-px grid moves by pixels. The
branch's heads therefore run in fp32 (`fusion.nets.layers.full_precision`); these tests emulate
autocast on the CPU (`torch.autocast("cpu", dtype=torch.bfloat16)`, the same casts as on CUDA) and
show both the parity and how far a naive bf16 decode lands.
"""

from contextlib import nullcontext

import pytest
import torch
from torchvision.ops import box_iou

import fusion.nets.layers as layers
from fusion.nets import build_hydrafusion
from fusion.nets.profile import BranchSpec

from .conftest import TINY

GRID = 1152  # [px] the paper profile's BEV grid side


@pytest.fixture(scope="module")
def bev_branch():
    """A radar branch of the cpu architecture (narrow heads) on the 1152 x 1152 BEV grid, in eval mode."""
    torch.manual_seed(0)
    small = {k: v for k, v in TINY.items() if k not in ("camera", "bev")}
    model = build_hydrafusion(profile="cpu", branches=[BranchSpec("radar", ("radar",), "bev")],
                              bev={"size": (GRID, GRID)}, **small)
    return model.branches["radar"].eval()


def _car_boxes(n: int, seed: int = 0) -> torch.Tensor:
    """n boxes of 10 x 26 px (either orientation) anywhere on the grid: (n, 4) x1, y1, x2, y2."""
    g = torch.Generator().manual_seed(seed)
    wh = torch.tensor([10.0, 26.0]).repeat(n, 1)
    turn = torch.rand(n, generator=g) < 0.5
    wh[turn] = wh[turn].flip(1)
    xy = torch.rand(n, 2, generator=g) * (GRID - wh)
    return torch.cat([xy, xy + wh], 1)


def _features(branch, seed: int = 1) -> torch.Tensor:
    """A backbone output as bf16 autocast leaves it: (1, C, GRID/8, GRID/8) in bfloat16."""
    g = torch.Generator().manual_seed(seed)
    c = branch.rpn.head.conv[0][0].in_channels
    s = GRID // branch.output_stride
    return torch.randn(1, c, s, s, generator=g).to(torch.bfloat16)


def _decode_of_proposals(branch, feats, proposals, autocast: bool, monkeypatch, guard: bool = True):
    """What the RoI heads' box coder decodes for `proposals` (the RPN's output replaced by them)
    when `branch._heads` runs on `feats`, with or without CPU bf16 autocast; `guard` False runs
    the heads as torchvision would (no `full_precision`)."""
    seen = []
    coder = branch.roi_heads.box_coder
    real_decode = type(coder).decode

    def recording_decode(self, rel_codes, boxes):
        out = real_decode(self, rel_codes, boxes)
        seen.append(out.detach().clone())
        return out

    with monkeypatch.context() as m:
        m.setattr(type(coder), "decode", recording_decode)
        m.setattr(branch.rpn, "forward", lambda images, fmap, targets=None: ([proposals.to(fmap["0"].dtype)], {}))
        if not guard:
            m.setattr(layers, "full_precision", lambda like: nullcontext())
        ctx = torch.autocast("cpu", dtype=torch.bfloat16) if autocast else nullcontext()
        with torch.no_grad(), ctx:
            dets, _ = branch._heads(feats, None)
    return seen[-1], dets


def _corner_error(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per box, the largest corner-coordinate difference [px]."""
    return (a.float() - b.float()).abs().flatten(1).max(dim=1).values


def test_bev_boxes_decode_in_fp32_under_bf16_autocast(bev_branch, monkeypatch):
    feats = _features(bev_branch)
    proposals = _car_boxes(200)
    ref, ref_dets = _decode_of_proposals(bev_branch, feats.float(), proposals, False, monkeypatch)
    amp, amp_dets = _decode_of_proposals(bev_branch, feats, proposals, True, monkeypatch)
    assert ref.dtype == amp.dtype == torch.float32
    torch.testing.assert_close(amp, ref, rtol=0, atol=0)  # the same fp32 operations on the same numbers
    for a, r in zip(amp_dets, ref_dets):
        for k in ("boxes", "scores", "labels"):
            assert torch.equal(a[k], r[k]), k


def test_a_naive_bf16_decode_is_pixels_off_so_the_parity_test_can_fail(bev_branch, monkeypatch):
    """Without `full_precision` (torchvision under autocast) the same proposals decode in bf16:
    the parity assertion above would fail by pixels, as the GPU issue measured (2.7 px mean,
    10.4 px max on 10 x 26 px cars, emulated CUDA autocast)."""
    feats = _features(bev_branch)
    proposals = _car_boxes(200)
    ref, _ = _decode_of_proposals(bev_branch, feats.float(), proposals, False, monkeypatch)
    naive, _ = _decode_of_proposals(bev_branch, feats, proposals, True, monkeypatch, guard=False)
    assert naive.dtype == torch.bfloat16
    err = _corner_error(naive, ref)
    print(f"naive bf16 decode: {float(err.mean()):.2f} px mean, {float(err.max()):.2f} px max corner error")
    assert err.mean() > 1.0 and err.max() >= 4.0, (float(err.mean()), float(err.max()))
    iou = box_iou(naive.float().view(-1, 4), ref.view(-1, 4)).diagonal()
    assert (iou < 0.7).float().mean() > 0.05  # a car box is small next to bf16's 4-8 px steps
    with pytest.raises(AssertionError):
        torch.testing.assert_close(naive.float(), ref, rtol=0, atol=0.5)


def test_anchors_and_proposals_stay_fp32_under_autocast(bev_branch):
    """The real RPN (anchors, decode, NMS) under autocast: float32 anchors and proposals."""
    feats = _features(bev_branch)
    seen = {}
    gen = bev_branch.rpn.anchor_generator
    def record(module, args, out):
        seen["anchors"] = out[0].dtype

    hook = gen.register_forward_hook(record)
    try:
        with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
            dets, _ = bev_branch._heads(feats, None)
    finally:
        hook.remove()
    assert seen["anchors"] == torch.float32
    assert all(d["boxes"].dtype == torch.float32 and d["scores"].dtype == torch.float32 for d in dets)


def test_gates_rank_in_fp32_under_autocast():
    from fusion.nets.branch_gates import DeepGate

    torch.manual_seed(0)
    gate = DeepGate(branch_sensors={"radar": ("radar",), "lidar": ("lidar",)},
                    branch_frames={"radar": "bev", "lidar": "bev"}).eval()
    torch.nn.init.normal_(gate.mlp[-1].weight)  # an untrained gate predicts a constant
    x = torch.randn(3, 128, *gate.grid)
    with torch.no_grad():
        ref = gate.predict_prepared(x)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            amp = gate.predict_prepared(x.to(torch.bfloat16))
    assert amp.dtype == torch.float32
    torch.testing.assert_close(amp, gate.predict_prepared(x.to(torch.bfloat16).float()), rtol=0, atol=0)
    assert ref.shape == amp.shape
