"""The model profile's cost options (issue 27): width, dilation of stride-1 stages, channels_last,
and `--model KEY=VALUE` overrides."""

import pytest
import torch

from fusion.nets import Stem, build_hydrafusion
from fusion.nets.profile import load_profile, parse_model_overrides
from sim.errors import UserError

BEV = [{"name": "bev", "sensors": ["radar"], "frame": "bev"}]
CAM = [{"name": "cam", "sensors": ["camera_right"], "frame": "camera_right"}]


def _params(model, prefix):
    return sum(p.numel() for n, p in model.named_parameters() if n.startswith(prefix))


def test_width_scales_layer2_to_4_channels_and_their_parameters_by_its_square():
    torch.manual_seed(0)
    full = build_hydrafusion(profile="cpu", branches=BEV)
    half = build_hydrafusion(profile="cpu", branches=BEV, width=0.5)
    assert load_profile("cpu", width=0.5).stage_channels() == (64, 128, 256)
    b = half.branches["bev"]
    assert [b.layer2[0].conv1.out_channels, b.layer3[0].conv1.out_channels, b.layer4[0].conv1.out_channels] == [64, 128, 256]
    assert b.neck.in_channels == 256 and b.neck.out_channels == 128  # roi_channels unchanged
    for stage in ("layer3", "layer4"):  # every 3x3 conv of these stages has 1/4 of the weights (input from a halved stage)
        ratio = _params(half, f"branches.bev.{stage}") / _params(full, f"branches.bev.{stage}")
        assert ratio == pytest.approx(0.25, rel=0.01), stage
    # layer2's first conv reads the 64-channel stem at both widths: its weights halve, the rest quarter
    assert _params(half, "branches.bev.layer2") / _params(full, "branches.bev.layer2") == pytest.approx(0.27, abs=0.02)
    with torch.no_grad():
        f = half.eval().extract_features({"radar": torch.rand(1, 1, 128, 256)})["radar"]
        assert b.features([f]).shape == (1, 128, 16, 32)  # same grid, same channels into the heads


def test_width_1_is_torchvisions_resnet18_bit_for_bit():
    import torchvision

    torch.manual_seed(3)
    model = build_hydrafusion(profile="cpu", branches=CAM)
    torch.manual_seed(3)
    Stem(3, norm="group")  # the stem's draws, first
    ref = torchvision.models.resnet18(weights=None, norm_layer=lambda c: torch.nn.GroupNorm(32, c))
    for name in ("layer2", "layer3", "layer4"):
        mine = dict(getattr(model.branches["cam"], name).named_parameters())
        theirs = dict(getattr(ref, name).named_parameters())
        assert mine.keys() == theirs.keys()
        assert all(torch.equal(mine[k], theirs[k]) for k in mine), name


def test_the_stem_is_torchvisions_conv1_to_layer1_initialised_as_torchvision_does():
    """The stem is built alone (not cut from a whole ResNet-18, whose other 11 M weights it threw away):
    the same modules and shapes as torchvision's conv1 .. layer1, Kaiming-normal (fan out) convolutions
    and unit-scale normalisation."""
    import torchvision

    torch.manual_seed(0)
    stem = Stem(3, norm="batch")
    ref = torchvision.models.resnet18(weights=None)
    theirs = {k: v for k, v in ref.state_dict().items() if k.split(".")[0] in ("conv1", "bn1", "layer1")}
    assert {k: v.shape for k, v in stem.state_dict().items()} == {k: v.shape for k, v in theirs.items()}
    for name, m in stem.named_modules():
        if isinstance(m, torch.nn.Conv2d):  # std sqrt(2 / fan_out): within 10 % on >= 36,864 draws
            fan_out = m.out_channels * m.kernel_size[0] * m.kernel_size[1]
            assert float(m.weight.std()) == pytest.approx((2.0 / fan_out) ** 0.5, rel=0.1), name
        elif isinstance(m, torch.nn.BatchNorm2d):
            assert torch.all(m.weight == 1) and torch.all(m.bias == 0), name
    assert Stem(4, norm="batch").conv1.weight.shape == (64, 4, 7, 7)


def test_dilation_keeps_the_grid_and_widens_the_receptive_field():
    torch.manual_seed(0)
    plain = build_hydrafusion(profile="cpu", branches=BEV).eval()
    torch.manual_seed(0)
    dil = build_hydrafusion(profile="cpu", branches=BEV, dilation=True).eval()
    b = dil.branches["bev"]  # BEV at output stride 8: layer3 and layer4 run at stride 1
    assert b.layer3[0].conv1.dilation == (1, 1) and b.layer3[0].conv2.dilation == (2, 2)
    assert b.layer3[1].conv1.dilation == (2, 2) and b.layer4[0].conv1.dilation == (2, 2)
    assert b.layer4[1].conv2.dilation == (4, 4) and b.layer4[1].conv2.padding == (4, 4)
    assert b.layer2[0].conv2.dilation == (1, 1)  # layer2 keeps its stride 2: nothing to dilate
    # same weights, only the dilation differs; a single impulse in the stem map reaches further
    dil.load_state_dict(plain.state_dict())
    x = torch.zeros(1, 64, 32, 256)  # wide enough that neither field covers the whole row
    x[..., 16, 128] = 1.0

    def reach(model):
        # GroupNorm's statistics span the whole map, so measure the convolutions' field without them
        for mod in model.modules():
            for name, child in mod.named_children():
                if isinstance(child, torch.nn.GroupNorm):
                    setattr(mod, name, torch.nn.Identity())
        with torch.no_grad():
            y = model.branches["bev"].layer4(model.branches["bev"].layer3(model.branches["bev"].layer2(x)))
            y0 = model.branches["bev"].layer4(model.branches["bev"].layer3(model.branches["bev"].layer2(x * 0)))
        changed = (y - y0).abs().sum(dim=(0, 1)) > 1e-6
        return changed.nonzero()[:, 1].max() - changed.nonzero()[:, 1].min()

    assert reach(dil) > reach(plain)
    assert reach(dil) >= reach(plain) + 8  # layer3 + layer4: (1 + 3 + 3 x 3) extra cells each way at least
    with torch.no_grad():
        assert dil.branches["bev"].features([x]).shape == plain.branches["bev"].features([x]).shape


def test_channels_last_computes_what_the_contiguous_model_computes():
    torch.manual_seed(0)
    a = build_hydrafusion(profile="cpu", branches=BEV, width=0.25).eval()
    torch.manual_seed(0)
    b = build_hydrafusion(profile="cpu", branches=BEV, width=0.25, channels_last=True).eval()
    assert b.branches["bev"].layer2[0].conv1.weight.is_contiguous(memory_format=torch.channels_last)
    x = {"radar": torch.rand(2, 1, 128, 256)}
    with torch.no_grad():
        fa, fb = a.extract_features(x)["radar"], b.extract_features(x)["radar"]
        assert fb.is_contiguous(memory_format=torch.channels_last)
        ya, yb = a.branches["bev"].features([fa]), b.branches["bev"].features([fb])
    assert torch.allclose(fa, fb, atol=1e-4) and torch.allclose(ya, yb, atol=1e-3)


def test_model_overrides_parse_and_refuse_one_line():
    assert parse_model_overrides(["width=0.5", "bev.output_stride=16", "dilation=true", "channels_last=false"]) == {
        "width": 0.5, "bev": {"output_stride": 16}, "dilation": True, "channels_last": False}
    assert load_profile("cpu", **parse_model_overrides(["box_batch_size_per_image=64"])).box_batch_size_per_image == 64
    for items, needle in [(["width"], "expected KEY=VALUE"), (["camera.size=[1, 2]"], "fixed by the dataset"),
                          (["branches=[]"], "fixed by the dataset"), (["width=0.5", "width=1"], "given twice"),
                          (["bev=1", "bev.output_stride=16"], "both as a value and as a group")]:
        with pytest.raises(UserError, match=needle):
            parse_model_overrides(items)
    for items, needle in [(["width=0.3"], "cannot split into 32 groups"), (["width=2"], r"in \(0, 1\]"),
                          (["widht=0.5"], "unknown key 'widht'"), (["roi_channels=300", "width=0.5"], "at most layer4's 256")]:
        with pytest.raises(UserError, match=needle):
            load_profile("cpu", **parse_model_overrides(items))
