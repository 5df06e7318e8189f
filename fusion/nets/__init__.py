"""HydraFusion / EcoFusion networks: stems, branches, batched selective execution.

    from fusion.nets import build_hydrafusion
    model = build_hydrafusion(profile="cpu")           # the paper's seven branches
    losses = model(inputs, targets)                      # training mode
    model.eval(); detections = model(inputs, selection=[["radar"], ["camera_right", "lidar"]])

See `HydraFusion` for the input/output contract and `configs/model/*.yaml` for the profiles.
"""

from fusion.nets.hydrafusion import LOSS_NAMES, HydraFusion, SensorTransform, build_hydrafusion
from fusion.nets.layers import STEM_CHANNELS, Branch, Stem, build_branch, build_stem
from fusion.nets.norms import NORM_LAYERS
from fusion.nets.profile import (
    FRAMES,
    PROFILE_DIR,
    SENSORS,
    BranchSpec,
    ModelProfile,
    SensorInput,
    SensorNorm,
    ViewSettings,
    available_profiles,
    load_profile,
)

__all__ = [
    "FRAMES",
    "LOSS_NAMES",
    "NORM_LAYERS",
    "PROFILE_DIR",
    "SENSORS",
    "STEM_CHANNELS",
    "Branch",
    "BranchSpec",
    "HydraFusion",
    "ModelProfile",
    "SensorInput",
    "SensorNorm",
    "SensorTransform",
    "Stem",
    "ViewSettings",
    "available_profiles",
    "build_branch",
    "build_hydrafusion",
    "build_stem",
    "load_profile",
]
