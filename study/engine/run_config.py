"""What a training run's `config.json` says about the network it trained: read by the trainer (to
resume) and by everything that loads the run (`study.engine.scoring.load_run`)."""

from __future__ import annotations

from fusion.nets.profile import ModelProfile, load_profile
from sim.config import from_dict


def run_profile(run_cfg: dict, where) -> ModelProfile:
    """The model profile a run was trained with: its recorded fields, or (runs from before they were
    recorded) the named profile as it is now.

    run_cfg: the run's config.json as a dict; where: the run directory, named in errors."""
    if "profile_fields" in run_cfg:
        return from_dict(ModelProfile, run_cfg["profile_fields"], where=f"{where}/config.json profile_fields")
    return load_profile(run_cfg["model_profile"])
