"""The normalisation layers a model profile may name (`ModelProfile.norm`): one registry, imported by
the profile (to check the name) and by the layers (to build them), so neither imports the other."""

from __future__ import annotations

from functools import partial

from torch import nn

from sim.registry import Registry

NORM_LAYERS: Registry = Registry(
    "normalisation layer",
    doc="Entries are called with a channel count and return an nn.Module normalising (N, C, H, W).",
)
NORM_LAYERS.add("batch", nn.BatchNorm2d)  # torchvision's ResNet-18 when trained from scratch
# 32 groups (Wu & He 2018): batch-independent, so a sample's output never depends on its batch
NORM_LAYERS.add("group", partial(nn.GroupNorm, 32))
