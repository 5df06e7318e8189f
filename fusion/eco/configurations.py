"""Configurations: the set Phi of branch subsets EcoFusion chooses from (Section 4, Algorithm 1).

A configuration phi is a non-empty set of branches; executing it runs each of its branches (and
the stems they need) and late-fuses their detections (Eq. 4-5). The default set is every
non-empty subset of the network's branches (2^7 - 1 = 127 for HydraFusion's seven). The paper's
named baselines (Section 5.2, Table 1) are marked:

- "none_<branch>": one single-sensor branch, no fusion (C_L, C_R, R, L);
- "early": C_L + C_R + L as one early-fusion model: the branch fusing camera_left, camera_right
  and fwd_lidar (the lidar projected into the camera) at the stem features (`camera_lidar`);
- "late": C_L + C_R + L + R, the four single-sensor branches late-fused.

`ConfigurationsConfig` is the YAML form (strict: unknown keys are errors):

    subsets: all            # all | listed
    max_branches: 0         # [branches] 0 = no limit; with subsets: all, keep subsets up to this size
    configurations: []      # with subsets: listed, each a list of branch names
    baselines: {}           # extra named configurations, name -> list of branch names

Names: a configuration is named by its branches in network order joined by "+"
("radar+camera_right"); baselines are also reachable by their baseline name.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from sim.config import from_dict, load_yaml
from sim.errors import UserError

SINGLE_SENSORS = ("camera_left", "camera_right", "radar", "lidar")
"""The sensors of the paper's no-fusion rows and of its late-fusion baseline (C_L, C_R, R, L)."""
EARLY_SENSORS = frozenset({"camera_left", "camera_right", "fwd_lidar"})
"""The paper's early fusion: both cameras and the lidar into one model (Section 5.2)."""


@dataclass(frozen=True)
class ConfigurationsConfig:
    """Which configurations Phi holds (see the module docstring for the YAML form).

    Fields:
        subsets: "all" (every non-empty subset of the branches, up to `max_branches`) or "listed"
            (exactly `configurations`).
        max_branches: [branches] largest subset kept with subsets "all"; 0 = no limit.
        configurations: with subsets "listed": the configurations, each a list of branch names.
        baselines: extra named configurations (name -> branch names), added to Phi when missing.
    """

    subsets: Literal["all", "listed"] = "all"
    max_branches: int = 0
    configurations: list[list[str]] = field(default_factory=list)
    baselines: dict[str, list[str]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.max_branches < 0:
            raise ValueError(f"max_branches: must be >= 0, got {self.max_branches}")
        if self.subsets == "listed" and not self.configurations:
            raise ValueError("configurations: subsets 'listed' needs at least one configuration")
        if self.subsets == "all" and self.configurations:
            raise ValueError("configurations: only used with subsets 'listed'")


def load_configurations_config(path: str | Path | None) -> ConfigurationsConfig:
    """The YAML file at `path` (strict), or the default (every subset) for None."""
    return ConfigurationsConfig() if path is None else load_yaml(ConfigurationsConfig, path)


@dataclass(frozen=True)
class ConfigurationSet:
    """An ordered set of configurations over a network's branches.

    Attributes:
        branches: the network's branch names, in network order.
        members: the configurations, each a tuple of branch names in network order, no duplicates.
        baselines: baseline name -> index into `members`.
    """

    branches: tuple[str, ...]
    members: tuple[tuple[str, ...], ...]
    baselines: Mapping[str, int]

    def __len__(self) -> int:
        return len(self.members)

    @property
    def names(self) -> list[str]:
        return [config_name(m) for m in self.members]

    def index(self, name_or_branches: str | Sequence[str]) -> int:
        """Index of a configuration by baseline name, "+"-joined name, or branch list."""
        if isinstance(name_or_branches, str):
            if name_or_branches in self.baselines:
                return self.baselines[name_or_branches]
            chosen = name_or_branches.split("+")
        else:
            chosen = list(name_or_branches)
        key = tuple(b for b in self.branches if b in chosen)
        if len(key) != len(set(chosen)) or key not in self.members:
            raise UserError(f"configuration {name_or_branches!r} is not in this configuration set "
                            f"(baselines: {', '.join(self.baselines)}; or branches joined by '+')")
        return self.members.index(key)

    def mask(self) -> list[list[bool]]:
        """(n_configurations, n_branches) membership: mask[c][j] is True when branch j is in configuration c."""
        return [[b in m for b in self.branches] for m in self.members]

    def sensors(self, branch_sensors: Mapping[str, Sequence[str]]) -> list[tuple[str, ...]]:
        """Per configuration: the sensors its branches consume (sorted by name)."""
        return [tuple(sorted({s for b in m for s in branch_sensors[b]})) for m in self.members]


def config_name(members: Sequence[str]) -> str:
    return "+".join(members)


def named_baselines(branch_sensors: Mapping[str, Sequence[str]]) -> dict[str, tuple[str, ...]]:
    """The paper's baselines that exist among these branches (Section 5.2): "none_<branch>" for
    each single-sensor branch of C_L, C_R, R, L; "early" for the branch fusing exactly C_L, C_R
    and the forward lidar; "late" for the four single-sensor branches when all exist.

    A network with only some of the four single-sensor branches (e.g. camera_right, radar, lidar)
    gets "late" = every single-sensor branch it has, late-fused, when it has two or more: the same
    rule (fuse every single-sensor detector) on the sensors it has, so that EcoFusion can still be
    compared with late fusion (and lambda_E's energy scale, E / E(late), still exists). Results name
    the configuration, so the departure from C_L + C_R + L + R is visible."""
    out: dict[str, tuple[str, ...]] = {}
    singles = {}
    for b, sensors in branch_sensors.items():
        if len(sensors) == 1 and sensors[0] in SINGLE_SENSORS:
            out[f"none_{b}"] = (b,)
            singles[sensors[0]] = b
        if frozenset(sensors) == EARLY_SENSORS:
            out.setdefault("early", (b,))
    if len(singles) >= 2:
        out["late"] = tuple(b for b in branch_sensors if b in singles.values())
    return out


def build_configurations(branch_sensors: Mapping[str, Sequence[str]],
                         cfg: ConfigurationsConfig | None = None) -> ConfigurationSet:
    """Phi for a network (branch name -> sensors, in network order) under `cfg` (default: every
    non-empty subset). Order: by size, then lexicographic in branch order (itertools.combinations),
    so the single branches come first. Raises UserError naming an unknown branch."""
    cfg = cfg or ConfigurationsConfig()
    branches = tuple(branch_sensors)
    if not branches:
        raise UserError("a configuration set needs at least one branch")

    def canonical(names: Sequence[str], where: str) -> tuple[str, ...]:
        bad = [n for n in names if n not in branches]
        if bad:
            raise UserError(f"{where}: unknown branch {bad[0]!r} (branches: {', '.join(branches)})")
        if not names or len(set(names)) != len(names):
            raise UserError(f"{where}: a configuration needs one or more distinct branches, got {list(names)}")
        return tuple(b for b in branches if b in names)

    if cfg.subsets == "all":
        top = cfg.max_branches or len(branches)
        members = [c for r in range(1, min(top, len(branches)) + 1) for c in itertools.combinations(branches, r)]
    else:
        members = []
        for i, c in enumerate(cfg.configurations):
            m = canonical(c, f"configurations[{i}]")
            if m not in members:
                members.append(m)
    named = named_baselines(branch_sensors)
    named.update({k: canonical(v, f"baselines.{k}") for k, v in cfg.baselines.items()})
    for m in named.values():
        if m not in members:
            members.append(m)
    return ConfigurationSet(branches, tuple(members), {k: members.index(m) for k, m in named.items()})


def configurations_from_dict(data: dict) -> ConfigurationsConfig:
    return from_dict(ConfigurationsConfig, data, where="configurations")
