"""Model profiles: every size, threshold and count of the HydraFusion networks, loaded strictly.

A profile is a frozen dataclass loaded from `configs/model/<name>.yaml` by the strict loader
(`sim.config`), which rejects unknown keys and wrong types with the dotted path of the field.
`paper` is torchvision's Faster R-CNN defaults at RADIATE resolution; `cpu` keeps the architecture
and shrinks what dominates CPU time (output stride, proposals, RoIs, channels into RoIAlign,
box-head width). Field names that exist in `torchvision.models.detection.FasterRCNN.__init__`
(`rpn_*`, `box_*`) mean exactly what they mean there.

The inputs a network can consume are fixed by the sensor rig (`SENSORS`); the *branch set* is
configuration (`BranchSpec` entries in `ModelProfile.branches`).
"""

from __future__ import annotations

import copy
import dataclasses
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from sim.config import from_dict, load_yaml, to_dict
from sim.errors import UserError

PROFILE_DIR = Path(__file__).resolve().parents[2] / "configs" / "model"
"""Where `load_profile(name)` finds `<name>.yaml`."""


@dataclass(frozen=True)
class SensorInput:
    """One input tensor of the network, as the dataset delivers it.

    Attributes:
        stem: key of the stem that processes it (one shared stem per modality).
        channels: number of channels C of the (B, C, H, W) tensor.
        view: "camera" (perspective image of the right/left camera, size `ModelProfile.camera.size`)
            or "bev" (bird's-eye-view image, size `ModelProfile.bev.size`).
    """

    stem: str
    channels: int
    view: Literal["camera", "bev"]


SENSORS: dict[str, SensorInput] = {
    "camera_left": SensorInput(stem="camera", channels=3, view="camera"),  # RGB
    "camera_right": SensorInput(stem="camera", channels=3, view="camera"),  # RGB
    # lidar points projected into the RIGHT camera: depth, intensity, height; zeros where no point
    "fwd_lidar": SensorInput(stem="fwd_lidar", channels=3, view="camera"),
    "radar": SensorInput(stem="radar", channels=1, view="bev"),  # cartesian power image
    "lidar": SensorInput(stem="lidar", channels=3, view="bev"),  # height, density, intensity
}
"""Sensor name -> what the network expects for it. Input dict keys are these names."""

FRAMES: dict[str, Literal["camera", "bev"]] = {
    "camera_left": "camera",
    "camera_right": "camera",
    "bev": "bev",
}
"""Frame name -> view. A branch predicts boxes in pixels of its frame; targets are keyed by frame."""

_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


@dataclass(frozen=True)
class BranchSpec:
    """One branch: which sensors it fuses (early fusion when more than one) and its output frame.

    Attributes:
        name: key of the branch in `HydraFusion.branches` and in every output dict.
        sensors: names from `SENSORS`; their stem features are concatenated on channels and merged
            by a 3x3 conv back to 64 channels when there is more than one.
        frame: name from `FRAMES`; its boxes are in this frame's pixels and its targets are
            `targets[i][frame]`.
        fusion: "features" (HydraFusion's early-fusion branches: shared modality stems, stem
            features concatenated and merged) or "input" (the early-fusion baseline of Table 2 (ii):
            one network on the channel-stacked, normalised input images, with its own stem).
    """

    name: str
    sensors: tuple[str, ...]
    frame: Literal["camera_left", "camera_right", "bev"]
    fusion: Literal["features", "input"] = "features"

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not _NAME.match(self.name):
            raise ValueError(
                f"name: {self.name!r} is not a valid branch name (letters, digits and '_', "
                "not starting with a digit)"
            )
        if len(self.sensors) == 0:
            raise ValueError(f"sensors: branch {self.name!r} has no sensors")
        for s in self.sensors:
            if s not in SENSORS:
                raise ValueError(
                    f"sensors: branch {self.name!r} names unknown sensor {s!r} (known: {', '.join(SENSORS)})"
                )
        if len(set(self.sensors)) != len(self.sensors):
            raise ValueError(f"sensors: branch {self.name!r} lists a sensor twice: {list(self.sensors)}")
        if self.frame not in FRAMES:
            raise ValueError(f"frame: {self.frame!r} is not one of {list(FRAMES)}")
        if self.fusion not in ("features", "input"):
            raise ValueError(f"fusion: {self.fusion!r} is not 'features' or 'input'")
        view = FRAMES[self.frame]
        for s in self.sensors:
            if SENSORS[s].view != view:
                raise ValueError(
                    f"sensors: branch {self.name!r} mixes views: sensor {s!r} is a {SENSORS[s].view} "
                    f"image but frame {self.frame!r} is a {view} frame. Early fusion concatenates "
                    "feature maps cell by cell, so every sensor of a branch must be an image of the "
                    "frame's view (project the sensor into it first, as fwd_lidar does for lidar)"
                )


@dataclass(frozen=True)
class ViewSettings:
    """Input geometry and anchors of one view (all camera images, or all BEV images).

    Attributes:
        size: (H, W) in pixels of every input of this view; inputs must arrive at exactly this size
            (the network never resizes).
        output_stride: input pixels per cell of the branch feature map: 32 is ResNet-18 as is,
            16 runs layer4's first block at stride 1, 8 also layer3's. Inputs are zero-padded
            (after normalisation) at the bottom/right to a multiple of it.
        anchor_sizes: sqrt(anchor area) in input pixels, all anchors on the one feature map.
        aspect_ratios: anchor height / width (torchvision's convention).
    """

    # tuple[int, ...] + a length check: sim.config's fixed-length tuple branch returns the types
    size: tuple[int, ...]
    output_stride: Literal[8, 16, 32]
    anchor_sizes: tuple[float, ...]
    aspect_ratios: tuple[float, ...]

    def __post_init__(self) -> None:
        if len(self.size) != 2 or min(self.size) < 1:
            raise ValueError(f"size: expected (H, W) with positive pixels, got {self.size}")
        if not self.anchor_sizes or min(self.anchor_sizes) <= 0:
            raise ValueError(f"anchor_sizes: expected positive sizes, got {self.anchor_sizes}")
        if not self.aspect_ratios or min(self.aspect_ratios) <= 0:
            raise ValueError(f"aspect_ratios: expected positive ratios, got {self.aspect_ratios}")
        # A box lying between anchors has IoU 0 with all of them, and torchvision's low-quality
        # matching then makes every anchor with IoU 0 (almost all) a positive for the first box.
        if not any(
            min(a / r**0.5, a * r**0.5) >= self.output_stride
            for a in self.anchor_sizes
            for r in self.aspect_ratios
        ):
            raise ValueError(
                f"anchor_sizes: no anchor is at least {self.output_stride} px (output_stride) in both width and "
                "height, so anchors leave gaps between grid cells and a box in a gap would match no anchor"
            )

    @property
    def padded_size(self) -> tuple[int, int]:
        """(H, W) after zero-padding to a multiple of `output_stride`."""
        s = self.output_stride
        return (-(-self.size[0] // s) * s, -(-self.size[1] // s) * s)


@dataclass(frozen=True)
class SensorNorm:
    """Per-channel normalisation applied inside the model: x' = (x - mean) / std."""

    mean: tuple[float, ...]
    std: tuple[float, ...]


@dataclass(frozen=True)
class ModelProfile:
    """Everything that sizes a HydraFusion network. Units and meaning in `configs/model/*.yaml`."""

    num_classes: int  # classes including background 0 (RADIATE: 8 + 1)
    norm: str  # normalisation layer of stems and branches, a NORM_LAYERS name ("batch", "group")
    camera: ViewSettings  # camera_left, camera_right and fwd_lidar inputs
    bev: ViewSettings  # radar and lidar BEV inputs
    normalization: dict[str, SensorNorm]  # sensor name -> mean/std, one value per channel
    # RPN (torchvision names; "train" values in training mode and for per-sample losses)
    rpn_pre_nms_top_n_train: int  # [proposals/image] kept before NMS
    rpn_pre_nms_top_n_test: int
    rpn_post_nms_top_n_train: int  # [proposals/image] kept after NMS
    rpn_post_nms_top_n_test: int
    rpn_nms_thresh: float  # [IoU]
    rpn_fg_iou_thresh: float  # [IoU] anchor is foreground at or above
    rpn_bg_iou_thresh: float  # [IoU] anchor is background below
    rpn_batch_size_per_image: int  # [anchors/image] sampled for the RPN loss
    rpn_positive_fraction: float  # [1] of those, at most this fraction foreground
    rpn_score_thresh: float  # [probability] proposals below are dropped
    # RoI heads
    roi_channels: int  # channels into RPN head and RoIAlign; < 512 adds a 1x1 conv after layer4
    roi_output_size: int  # [cells] RoIAlign output is roi_output_size x roi_output_size
    roi_sampling_ratio: int  # [samples/bin] RoIAlign sampling points per bin side
    box_head_width: int  # width of both fully connected layers of TwoMLPHead
    box_score_thresh: float  # [probability] detections below are dropped
    box_nms_thresh: float  # [IoU] per-class NMS of detections
    box_detections_per_img: int  # [detections/image/branch]
    box_fg_iou_thresh: float  # [IoU] RoI is foreground at or above
    box_bg_iou_thresh: float  # [IoU] RoI is background below
    box_batch_size_per_image: int  # [RoIs/image] sampled for the box-head loss
    box_positive_fraction: float  # [1] of those, at most this fraction foreground
    branches: tuple[BranchSpec, ...]  # the branch set (HydraFusion 5.2.1 has seven)
    # Cost options of the branch backbones (issue 27); the defaults are ResNet-18 as the paper has it
    width: float = 1.0  # [1] channels of layer2..layer4 are 128, 256, 512 times this (stems keep 64)
    dilation: bool = False  # a stage run at stride 1 dilates its 3x3 convs (DeepLab) to keep its receptive field
    channels_last: bool = False  # NHWC memory format for stems and branch backbones (oneDNN's native layout)

    def stage_channels(self) -> tuple[int, int, int]:
        """Output channels of layer2, layer3, layer4 at this `width`."""
        return tuple(int(round(c * self.width)) for c in (128, 256, 512))

    def __post_init__(self) -> None:
        from fusion.nets.norms import NORM_LAYERS  # here, not at the top: importing profiles needs no torch

        if self.num_classes < 2:
            raise ValueError(f"num_classes: need background + at least one class, got {self.num_classes}")
        NORM_LAYERS.get(self.norm)
        missing = [s for s in SENSORS if s not in self.normalization]
        unknown = [s for s in self.normalization if s not in SENSORS]
        if unknown:
            raise ValueError(f"normalization: unknown sensor {unknown[0]!r} (known: {', '.join(SENSORS)})")
        if missing:
            raise ValueError(f"normalization: no mean/std for sensor {missing[0]!r}")
        for s, n in self.normalization.items():
            c = SENSORS[s].channels
            if len(n.mean) != c or len(n.std) != c:
                raise ValueError(f"normalization.{s}: expected {c} mean and {c} std values for {c} channels")
            if min(n.std) <= 0:
                raise ValueError(f"normalization.{s}.std: must be positive, got {n.std}")
        for name in (
            "rpn_nms_thresh",
            "rpn_fg_iou_thresh",
            "rpn_bg_iou_thresh",
            "rpn_positive_fraction",
            "rpn_score_thresh",
            "box_score_thresh",
            "box_nms_thresh",
            "box_fg_iou_thresh",
            "box_bg_iou_thresh",
            "box_positive_fraction",
        ):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"{name}: must be in [0, 1], got {v}")
        for name in (
            "rpn_pre_nms_top_n_train",
            "rpn_pre_nms_top_n_test",
            "rpn_post_nms_top_n_train",
            "rpn_post_nms_top_n_test",
            "rpn_batch_size_per_image",
            "roi_channels",
            "roi_output_size",
            "roi_sampling_ratio",
            "box_head_width",
            "box_detections_per_img",
            "box_batch_size_per_image",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: must be at least 1, got {getattr(self, name)}")
        if self.rpn_bg_iou_thresh > self.rpn_fg_iou_thresh:
            raise ValueError("rpn_bg_iou_thresh: must not exceed rpn_fg_iou_thresh")
        if self.box_bg_iou_thresh > self.box_fg_iou_thresh:
            raise ValueError("box_bg_iou_thresh: must not exceed box_fg_iou_thresh")
        if not (isinstance(self.width, int | float) and 0.0 < self.width <= 1.0):
            raise ValueError(f"width: a channel multiplier in (0, 1], got {self.width!r}")
        groups = 32 if self.norm == "group" else 1
        odd = [c for c in self.stage_channels() if c < groups or c % groups]
        if odd:
            raise ValueError(f"width: {self.width:g} gives {odd[0]} channels, which {self.norm} normalisation cannot "
                             f"split into {groups} groups (0.25, 0.5, 0.75 and 1 can)")
        top = self.stage_channels()[2]
        if self.roi_channels > top:
            raise ValueError(f"roi_channels: at most layer4's {top} channels (width {self.width:g}), got {self.roi_channels}")
        if not self.branches:
            raise ValueError("branches: the branch set is empty")
        seen: set[str] = set()
        for b in self.branches:
            if b.name in seen:
                raise ValueError(f"branches: duplicate branch name {b.name!r}")
            seen.add(b.name)

    def view(self, name: str) -> ViewSettings:
        """`camera` or `bev` settings by view name."""
        return {"camera": self.camera, "bev": self.bev}[name]


def available_profiles() -> list[str]:
    """Names of the YAML profiles in `PROFILE_DIR`."""
    return sorted(p.stem for p in PROFILE_DIR.glob("*.yaml"))


def deep_merge(base: dict[str, Any], overrides: Mapping[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(base)
    for key, value in overrides.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def load_profile(profile: str | ModelProfile = "cpu", **overrides: Any) -> ModelProfile:
    """Load a profile and apply overrides (deep-merged; nested fields may be given partially).

    Args:
        profile: a name in `available_profiles()` (`configs/model/<name>.yaml`) or a ModelProfile.
        **overrides: ModelProfile fields. Mappings merge into nested dataclasses
            (`camera={"size": (64, 96)}` keeps the camera anchors); dataclass values are accepted.

    Raises:
        UserError (a ValueError): unknown profile, unknown key, wrong type or invalid value, with
            the dotted path of the field (`cpu.camera.size: ...`).
    """
    if isinstance(profile, ModelProfile):
        where = "profile"
        base = to_dict(profile)
    else:
        path = PROFILE_DIR / f"{profile}.yaml"
        if not isinstance(profile, str) or not path.is_file():
            raise UserError(
                f"unknown model profile {profile!r} (choose from: {', '.join(available_profiles())})"
            )
        where = str(profile)
        base = to_dict(load_yaml(ModelProfile, path))
    if not overrides:
        return profile if isinstance(profile, ModelProfile) else from_dict(ModelProfile, base, where=where)
    plain = {k: _plain(v) for k, v in overrides.items()}
    return from_dict(ModelProfile, deep_merge(base, plain), where=where)


def _plain(value: Any) -> Any:
    """Dataclasses anywhere inside lists/dicts -> plain dicts (e.g. a list of BranchSpec)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return to_dict(value)
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    return value


FIXED_BY_DATA = ("num_classes", "camera.size", "bev.size", "normalization", "branches")
"""Profile fields a run cannot override: the dataset's renders fix the sizes and classes, the branch
set comes from its own option."""


def parse_model_overrides(items: Any) -> dict[str, Any]:
    """`KEY=VALUE` strings (dotted keys into nested fields, YAML values) -> `load_profile` overrides.

    `["width=0.5", "bev.output_stride=16", "dilation=true"]` ->
    `{"width": 0.5, "bev": {"output_stride": 16}, "dilation": True}`. Keys in `FIXED_BY_DATA`, an
    item without "=", a key given twice or a value YAML cannot read are refused (UserError); whether
    the key exists and the value fits is `load_profile`'s check.
    """
    import yaml

    out: dict[str, Any] = {}
    seen: set[str] = set()
    for item in items or ():
        key, eq, raw = str(item).partition("=")
        key = key.strip()
        if not eq or not key:
            raise UserError(f"--model {item!r}: expected KEY=VALUE, e.g. width=0.5 or bev.output_stride=16")
        if key in seen:
            raise UserError(f"--model {key}: given twice")
        seen.add(key)
        if any(key == f or key.startswith(f + ".") for f in FIXED_BY_DATA):
            raise UserError(f"--model {key}: fixed by the dataset or the branch options, not overridable")
        try:
            value = yaml.safe_load(raw)
        except yaml.YAMLError as err:
            raise UserError(f"--model {key}: cannot read value {raw!r} ({err.__class__.__name__})") from None
        node = out
        *parents, leaf = key.split(".")
        for p in parents:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise UserError(f"--model {key}: {p} is given both as a value and as a group")
        if isinstance(node.get(leaf), dict):
            raise UserError(f"--model {key}: given both as a value and as a group")
        node[leaf] = value
    return out
