"""Warm starts (`hydrabench train --init-from RUN`): a new run's stems and branches initialised from
trained runs' weights, module by module, refused when the source's model profile changes a weight's
shape, and reported in RUN/warm_start.json."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import torch

from sim.errors import UserError

# Which trained module initialises which new one when warm-starting (`--init-from`): the paper's
# branches share one architecture (ResNet-18 layer2..4 + RPN + RoI heads), so a trained camera
# branch is a good start for the other camera-view branches, a trained radar branch for the BEV ones.
WARM_START_BRANCH = {
    "camera_left": "camera_right", "camera_both": "camera_right", "camera_lidar": "camera_right",
    "early_cameras": "camera_right", "early_camera_lidar": "camera_right",
    "lidar": "radar", "radar_lidar": "radar", "early_radar_lidar": "radar",
}
WARM_START_STEM = {"fwd_lidar": "camera", "lidar": "radar"}


def warm_start(model, source_states) -> dict:
    """Copy matching parameters from trained models' state dicts into `model`.

    `source_states`: one state dict, or several in priority order. Each module of `model` (a branch
    or a stem) comes from the first source that has it, either under its own name or under its
    warm-start origin (WARM_START_BRANCH / WARM_START_STEM); so with sources (a camera-only run, a
    seven-branch run) the camera-view branches start from the first run's trained camera branch and
    the radar / lidar ones from the second. Tensors whose shapes differ (the first conv of a stem
    with other input channels) keep their fresh initialisation; the merge conv of a fused branch
    started from a single-sensor branch passes that sensor's features through. Returns {"copied": n,
    "from": {target prefix: source prefix}, "source": {target prefix: index of the source},
    "merge_pass_through": {branch: sensor}, "kept": [...]}.
    """
    sources = [source_states] if isinstance(source_states, dict) else list(source_states)
    own = model.state_dict()
    mapping, origin_of = {}, {}
    for kind, names, table in (("branches", model.branches, WARM_START_BRANCH), ("stems", model.stems, WARM_START_STEM)):
        present_in = [{k.split(".")[1] for k in state if k.startswith(kind + ".")} for state in sources]
        for name in names:
            for s, present in enumerate(present_in):
                origin = name if name in present else table.get(name)
                if origin in present:
                    mapping[f"{kind}.{name}."] = f"{kind}.{origin}."
                    origin_of[f"{kind}.{name}."] = s
                    break
    new, kept = {}, []
    for key, value in own.items():
        dst = next((d for d in mapping if key.startswith(d)), None)
        state = sources[origin_of[dst]] if dst is not None else sources[0]
        src_key = mapping[dst] + key[len(dst):] if dst is not None else key
        if src_key in state and state[src_key].shape == value.shape:
            new[key] = state[src_key]
        else:
            kept.append(key)
    # A fused branch started from a single-sensor one: its fresh merge conv would scramble the
    # features the copied layer2.. expect, so it starts as a pass-through of that sensor's stem
    # channels (the other sensors' weights at zero; they still get gradients and learn).
    passed = {}
    for name, branch in model.branches.items():
        dst = f"branches.{name}."
        key = dst + "merge.weight"
        origin = mapping.get(dst, "")[len("branches."):-1]
        if key in kept and origin in branch.sensors and branch.merge is not None:
            w = torch.zeros_like(own[key])
            c = w.shape[0]
            at = branch.sensors.index(origin) * c
            w[torch.arange(c), at + torch.arange(c), w.shape[2] // 2, w.shape[3] // 2] = 1.0
            new[key], new[dst + "merge.bias"] = w, torch.zeros_like(own[dst + "merge.bias"])
            kept = [k for k in kept if k not in (key, dst + "merge.bias")]
            passed[name] = origin
    model.load_state_dict({**own, **new})
    return {"copied": len(new), "from": mapping, "source": origin_of, "merge_pass_through": passed, "kept": kept}


SHAPE_FIELDS = ("num_classes", "width", "roi_channels", "roi_output_size", "box_head_width")
"""Profile fields that change the shapes of branch weights: a warm start across them would skip
every such tensor silently (`warm_start` copies only tensors of equal shape)."""


def check_warm_start_profile(src: Path, run_cfg: dict) -> None:
    """Refuse (one line) a --init-from run whose recorded profile differs from this run's in a field
    of `SHAPE_FIELDS`."""
    try:
        src_fields = json.loads((src / "config.json").read_text()).get("profile_fields")
    except (OSError, ValueError):
        return  # runs from before profiles were recorded: warm_start reports what it copied
    if not src_fields:
        return
    from fusion.nets.profile import ModelProfile

    defaults = {f.name: f.default for f in dataclasses.fields(ModelProfile)}
    mine = run_cfg["profile_fields"]
    diff = [f"{k} {src_fields.get(k, defaults.get(k))} there, {mine.get(k, defaults.get(k))} here"
            for k in SHAPE_FIELDS if src_fields.get(k, defaults.get(k)) != mine.get(k, defaults.get(k))]
    if diff:
        raise UserError(f"--init-from {src}: trained with another model profile ({'; '.join(diff)}); "
                        "give this run the same --model overrides")


def apply_warm_start(model, sources: list, srcs: list[Path], out: Path, main_rank: bool, progress: bool) -> None:
    """`warm_start` from the --init-from runs' weights, reported in RUN/warm_start.json."""
    report = warm_start(model, sources)
    if main_rank:
        (out / "warm_start.json").write_text(json.dumps({"sources": [str(s) for s in srcs], **report}, indent=1))
    if progress:
        sys.stderr.write(f"warm start from {', '.join(map(str, srcs))}: {report['copied']} tensors copied, "
                         f"{len(report['kept'])} fresh\n")
