"""HydraFusion / EcoFusion networks: stems, branches, batched selective execution.

See `configs/model/*.yaml` for the profiles.
"""

from fusion.nets.layers import NORM_LAYERS, STEM_CHANNELS, Branch, Stem, build_branch, build_stem
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
    "NORM_LAYERS",
    "PROFILE_DIR",
    "SENSORS",
    "STEM_CHANNELS",
    "Branch",
    "BranchSpec",
    "ModelProfile",
    "SensorInput",
    "SensorNorm",
    "Stem",
    "ViewSettings",
    "available_profiles",
    "build_branch",
    "build_stem",
    "load_profile",
]
