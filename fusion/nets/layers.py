"""Stems and branches: a ResNet-18 split after layer1, with torchvision's Faster R-CNN heads.

A `Stem` is ResNet-18 conv1 .. layer1 (64 channels, stride 4), one per modality and shared by the
sensors of that modality (HydraFusion 4.1). A `Branch` is ResNet-18 layer2 .. layer4 followed by
torchvision's RegionProposalNetwork and RoIHeads on the single feature map (HydraFusion 5.2.1);
a branch fed by several sensors first concatenates their stem features on channels and merges them
with a 3x3 conv back to 64 channels, as the official code's `merge_conv` does.

No pretrained weights are loaded: everything starts from torchvision's initialisation.
"""

from __future__ import annotations

from collections import OrderedDict

import torch
import torchvision
from torch import Tensor, nn
from torchvision.models.detection.faster_rcnn import FastRCNNPredictor, TwoMLPHead
from torchvision.models.detection.image_list import ImageList
from torchvision.models.detection.roi_heads import RoIHeads
from torchvision.models.detection.rpn import AnchorGenerator, RegionProposalNetwork, RPNHead
from torchvision.ops import MultiScaleRoIAlign

from fusion.nets.norms import NORM_LAYERS
from fusion.nets.profile import FRAMES, SENSORS, BranchSpec, ModelProfile

STEM_CHANNELS = 64
"""Channels of every stem output (ResNet-18 layer1)."""


def full_precision(like: Tensor):
    """Autocast off for the region (a no-op outside autocast): what runs inside computes in the
    dtype of its inputs, which the caller makes float32.

    Under bf16 autocast (8 mantissa bits) torchvision's anchors take the feature dtype and box
    decoding casts to it: on the 1152-px BEV grid a decoded 10 x 26 px car box moves by pixels
    (2.7 px on average, 10.4 px at most, emulated CUDA autocast), so anchors, box coding, the RPN
    and RoI heads and the gates run in fp32 while the backbones may run in bf16.
    """
    return torch.autocast(device_type=like.device.type, enabled=False)


def _resnet18(norm: str) -> torchvision.models.ResNet:
    return torchvision.models.resnet18(weights=None, norm_layer=NORM_LAYERS.get(norm))


def _init_as_resnet(module: nn.Module) -> None:
    """Initialise `module` as torchvision initialises ResNet: Kaiming-normal (fan out) convolutions,
    unit-scale normalisation, in the order of `module.modules()`."""
    for m in module.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
        elif isinstance(m, nn.BatchNorm2d | nn.GroupNorm):
            nn.init.constant_(m.weight, 1)
            nn.init.constant_(m.bias, 0)


class Stem(nn.Module):
    """ResNet-18 conv1 .. layer1 with `in_channels` input channels.

    Input (N, in_channels, H, W), normalised; output (N, 64, H/4, W/4) for H, W multiples of 4
    (conv1 stride 2, max-pool stride 2). Submodule names match torchvision's ResNet.
    """

    out_channels = STEM_CHANNELS

    def __init__(self, in_channels: int, *, norm: str, channels_last: bool = False) -> None:
        super().__init__()
        self.channels_last = bool(channels_last)
        from torchvision.models.resnet import BasicBlock

        # ResNet-18's conv1 .. layer1, built alone and initialised as torchvision initialises ResNet
        # (Kaiming-normal convolutions, unit-scale normalisation): building a whole ResNet-18 to keep
        # these drew 11.7 M weights per stem that were thrown away (0.1 s each on a 2-core CPU)
        norm_layer = NORM_LAYERS.get(norm)
        self.conv1 = nn.Conv2d(in_channels, 64, kernel_size=7, stride=2, padding=3, bias=False)
        self.bn1, self.relu = norm_layer(64), nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(kernel_size=3, stride=2, padding=1)
        self.layer1 = nn.Sequential(BasicBlock(64, 64, norm_layer=norm_layer), BasicBlock(64, 64, norm_layer=norm_layer))
        _init_as_resnet(self)
        self.in_channels = in_channels

    def forward(self, x: Tensor) -> Tensor:
        if self.channels_last:  # NHWC: oneDNN's native layout; the weights were converted at build
            x = x.contiguous(memory_format=torch.channels_last)
        return self.layer1(self.maxpool(self.relu(self.bn1(self.conv1(x)))))


def _set_stride_one(layer: nn.Sequential, dilation: int = 1, previous: int = 1) -> None:
    """Turn a ResNet stage's downsampling into stride 1 (BasicBlock refuses dilation at construction).

    With `dilation` > 1 the stage's 3x3 convolutions after the first are dilated by it (the first
    keeps `previous`, the dilation of the stage before), as torchvision's
    `replace_stride_with_dilation` does for Bottleneck stages (DeepLab, Chen et al. 2017): the stage
    keeps the receptive field it had at stride 2 while its map stays at the input's resolution.
    """
    block = layer[0]
    block.conv1.stride = (1, 1)
    block.stride = 1
    if block.downsample is not None:
        block.downsample[0].stride = (1, 1)
    if dilation == 1 and previous == 1:
        return
    for k, b in enumerate(layer):
        for j, conv in enumerate((b.conv1, b.conv2)):
            d = previous if k == 0 and j == 0 else dilation
            conv.dilation, conv.padding = (d, d), (d, d)


def _stages(norm: str, width: float) -> tuple[nn.Module, nn.Module, nn.Module]:
    """ResNet-18's layer2, layer3, layer4 (two BasicBlocks each, stride 2 first), with 128, 256, 512
    output channels times `width`, initialised as torchvision initialises ResNet (Kaiming-normal
    convolutions, unit-scale normalisation). Width 1 is torchvision's own stages."""
    if width == 1:
        r = _resnet18(norm)
        return r.layer2, r.layer3, r.layer4
    from torchvision.models.resnet import BasicBlock, conv1x1

    norm_layer = NORM_LAYERS.get(norm)
    stages, inplanes = [], STEM_CHANNELS
    for planes in (int(round(c * width)) for c in (128, 256, 512)):
        down = nn.Sequential(conv1x1(inplanes, planes, 2), norm_layer(planes))
        stage = nn.Sequential(BasicBlock(inplanes, planes, 2, down, norm_layer=norm_layer),
                              BasicBlock(planes, planes, norm_layer=norm_layer))
        _init_as_resnet(stage)
        stages.append(stage)
        inplanes = planes
    return tuple(stages)


class Branch(nn.Module):
    """One HydraFusion branch: [merge conv] -> layer2..layer4 -> [1x1 conv] -> RPN -> RoI heads.

    Args:
        spec: name, sensors (in input order) and output frame.
        image_size: (H, W) of the inputs of the frame's view, in pixels.
        output_stride: 8, 16 or 32 input pixels per feature-map cell.
        merge: conv mapping the concatenated stem features (N, 64*len(sensors), h, w) to 64
            channels, or None for a single-sensor branch.
        layer2, layer3, layer4: ResNet-18 stages (strides already set).
        neck: 1x1 conv to the channels seen by the RPN and RoIAlign, or None (layer4's channels).
        rpn, roi_heads: torchvision modules, on feature map "0".

    Precision: `features` (merge, layer2..4, neck) follows autocast; the heads always run in fp32
    (`full_precision`).

    `forward(xs, targets=None)`:
        xs: list with one (N, 64, h, w) stem-feature tensor per sensor, in `sensors` order, where
            (h, w) = padded input size / 4.
        targets: training only, list of N dicts {"boxes": (M, 4) float x1, y1, x2, y2 pixels of the
            frame, "labels": (M,) int64 in 1..num_classes-1}.
        Returns (training) torchvision's four losses averaged over the N samples:
        {"loss_classifier", "loss_box_reg", "loss_objectness", "loss_rpn_box_reg"};
        (eval) a list of N dicts {"boxes": (D, 4) float, "labels": (D,) int64, "scores": (D,) float},
        boxes clipped to `image_size`.
    """

    def __init__(
        self,
        *,
        spec: BranchSpec,
        image_size: tuple[int, int],
        output_stride: int,
        merge: nn.Module | None,
        layer2: nn.Module,
        layer3: nn.Module,
        layer4: nn.Module,
        neck: nn.Module | None,
        rpn: RegionProposalNetwork,
        roi_heads: RoIHeads,
        input_stem: nn.Module | None = None,
    ) -> None:
        super().__init__()
        self.name = spec.name
        self.sensors = tuple(spec.sensors)
        self.fusion = spec.fusion
        self.input_stem = input_stem
        self.frame = spec.frame
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.output_stride = int(output_stride)
        s = self.output_stride
        self.padded_size = (-(-self.image_size[0] // s) * s, -(-self.image_size[1] // s) * s)
        self.merge = merge
        self.layer2, self.layer3, self.layer4 = layer2, layer3, layer4
        self.neck = neck
        self.rpn = rpn
        self.roi_heads = roi_heads

    def features(self, xs: list[Tensor]) -> Tensor:
        """Stem features (fusion "features") or normalised, padded input images (fusion "input"),
        one per sensor -> the (N, C, H_pad/stride, W_pad/stride) map seen by RPN and RoIAlign."""
        if isinstance(xs, Tensor) or len(xs) != len(self.sensors):
            raise ValueError(
                f"branch {self.name!r}: expected a list of {len(self.sensors)} "
                + ("input images" if self.fusion == "input" else "stem feature maps")
            )
        if self.input_stem is not None:  # early fusion of the raw inputs (Table 2 (ii))
            x = self.input_stem(torch.cat(xs, dim=1))
        else:
            x = xs[0] if self.merge is None else self.merge(torch.cat(xs, dim=1))
        x = self.layer4(self.layer3(self.layer2(x)))
        return x if self.neck is None else self.neck(x)

    def _images(self, n: int, like: Tensor) -> ImageList:
        # The RPN reads only the padded size (anchor strides) and the real sizes (clipping) from
        # the ImageList, so a broadcast zero stands in for the images.
        dummy = torch.zeros((), dtype=like.dtype, device=like.device).expand(n, 1, *self.padded_size)
        return ImageList(dummy, [self.image_size] * n)

    def _heads(self, feats: Tensor, targets: list[dict[str, Tensor]] | None):
        # fp32 from here on whatever the backbone ran in (`full_precision`): anchors, box coding,
        # RPN, RoIAlign and the box head; a float32 map passes through unchanged
        with full_precision(feats):
            feats = feats.float()
            fmap = OrderedDict([("0", feats)])
            images = self._images(feats.shape[0], feats)
            proposals, rpn_losses = self.rpn(images, fmap, targets)
            detections, roi_losses = self.roi_heads(fmap, proposals, images.image_sizes, targets)
        return detections, {**roi_losses, **rpn_losses}

    def forward(self, xs: list[Tensor], targets: list[dict[str, Tensor]] | None = None):
        if self.training and targets is None:
            raise ValueError(f"branch {self.name!r}: targets are required in training mode")
        detections, losses = self._heads(self.features(xs), targets if self.training else None)
        return losses if self.training else detections

    @torch.no_grad()
    def detect_and_losses(
        self, xs: list[Tensor], targets: list[dict[str, Tensor]], *, seed: int
    ) -> tuple[list[dict[str, Tensor]], list[dict[str, Tensor]]]:
        """(eval-mode detections, `per_sample_losses`) of a batch from one run of the backbone: the
        same results as calling `forward` and `per_sample_losses` apart, at the cost of the heads
        alone for the losses."""
        if self.training:
            raise RuntimeError(f"branch {self.name!r}: detect_and_losses needs eval mode (call .eval())")
        feats = self.features(xs)
        detections, _ = self._heads(feats, None)
        return detections, self._sample_losses(feats, targets, seed)

    @torch.no_grad()
    def per_sample_losses(
        self, xs: list[Tensor], targets: list[dict[str, Tensor]], *, seed: int
    ) -> list[dict[str, Tensor]]:
        """The four training losses of each sample alone, without touching any weight or statistic.

        The backbone runs once on the batch in its current (eval) behaviour; then the RPN and RoI
        heads run in training behaviour (training proposal counts, anchor and RoI sampling) on each
        sample alone, with the global torch RNG forked and seeded with `seed` for every sample, so
        a sample's losses equal those of a batch-1 training step taken right after
        `torch.manual_seed(seed)` with the same normalisation behaviour, and do not depend on the
        other samples or their order. The caller's RNG state is restored.
        """
        if self.training:
            raise RuntimeError(f"branch {self.name!r}: per_sample_losses needs eval mode (call .eval())")
        return self._sample_losses(self.features(xs), targets, seed)

    def _sample_losses(self, feats: Tensor, targets: list[dict[str, Tensor]], seed: int) -> list[dict[str, Tensor]]:
        devices = [feats.device.index or 0] if feats.is_cuda else []
        modes = (self.rpn.training, self.roi_heads.training)
        self.rpn.train()
        self.roi_heads.train()
        out = []
        try:
            for j in range(feats.shape[0]):
                with torch.random.fork_rng(devices=devices):
                    torch.manual_seed(seed)
                    _, losses = self._heads(feats[j : j + 1], [targets[j]])
                out.append(losses)
        finally:
            self.rpn.train(modes[0])
            self.roi_heads.train(modes[1])
        return out


def build_stem(stem: str, profile: ModelProfile) -> Stem:
    """The stem `stem` ("camera", "radar", "lidar", "fwd_lidar") for `profile`."""
    channels = {s.stem: s.channels for s in SENSORS.values()}
    if stem not in channels:
        raise ValueError(f"stem: unknown stem {stem!r} (known: {', '.join(channels)})")
    return _memory_format(Stem(channels[stem], norm=profile.norm, channels_last=profile.channels_last), profile)


def _memory_format(module: nn.Module, profile: ModelProfile) -> nn.Module:
    """`module` with its 4-D weights in NHWC when the profile asks for channels_last."""
    return module.to(memory_format=torch.channels_last) if profile.channels_last else module


def build_branch(spec: BranchSpec, profile: ModelProfile) -> Branch:
    """A branch for `spec` sized by `profile` (its view's size, stride and anchors)."""
    view = profile.view(FRAMES[spec.frame])
    layer2, layer3, layer4 = _stages(profile.norm, profile.width)
    dilate = 2 if profile.dilation else 1
    if view.output_stride <= 8:
        _set_stride_one(layer3, dilate)
    if view.output_stride <= 16:
        _set_stride_one(layer4, dilate * (dilate if view.output_stride <= 8 else 1),
                        previous=dilate if view.output_stride <= 8 else 1)
    k = len(spec.sensors)
    merge = (nn.Conv2d(STEM_CHANNELS * k, STEM_CHANNELS, kernel_size=3, padding=1)
             if k > 1 and spec.fusion == "features" else None)
    input_stem = (Stem(sum(SENSORS[s].channels for s in spec.sensors), norm=profile.norm,
                       channels_last=profile.channels_last)
                  if spec.fusion == "input" else None)
    channels = profile.roi_channels
    top = profile.stage_channels()[2]
    neck = nn.Conv2d(top, channels, kernel_size=1) if channels != top else None
    anchors = AnchorGenerator(sizes=(tuple(view.anchor_sizes),), aspect_ratios=(tuple(view.aspect_ratios),))
    rpn = RegionProposalNetwork(
        anchors,
        RPNHead(channels, anchors.num_anchors_per_location()[0]),
        fg_iou_thresh=profile.rpn_fg_iou_thresh,
        bg_iou_thresh=profile.rpn_bg_iou_thresh,
        batch_size_per_image=profile.rpn_batch_size_per_image,
        positive_fraction=profile.rpn_positive_fraction,
        pre_nms_top_n={
            "training": profile.rpn_pre_nms_top_n_train,
            "testing": profile.rpn_pre_nms_top_n_test,
        },
        post_nms_top_n={
            "training": profile.rpn_post_nms_top_n_train,
            "testing": profile.rpn_post_nms_top_n_test,
        },
        nms_thresh=profile.rpn_nms_thresh,
        score_thresh=profile.rpn_score_thresh,
    )
    res = profile.roi_output_size
    roi_heads = RoIHeads(
        MultiScaleRoIAlign(featmap_names=["0"], output_size=res, sampling_ratio=profile.roi_sampling_ratio),
        TwoMLPHead(channels * res * res, profile.box_head_width),
        FastRCNNPredictor(profile.box_head_width, profile.num_classes),
        fg_iou_thresh=profile.box_fg_iou_thresh,
        bg_iou_thresh=profile.box_bg_iou_thresh,
        batch_size_per_image=profile.box_batch_size_per_image,
        positive_fraction=profile.box_positive_fraction,
        bbox_reg_weights=None,
        score_thresh=profile.box_score_thresh,
        nms_thresh=profile.box_nms_thresh,
        detections_per_img=profile.box_detections_per_img,
    )
    return _memory_format(Branch(
        spec=spec,
        image_size=view.size,
        output_stride=view.output_stride,
        merge=merge,
        layer2=layer2,
        layer3=layer3,
        layer4=layer4,
        neck=neck,
        rpn=rpn,
        roi_heads=roi_heads,
        input_stem=input_stem,
    ), profile)
