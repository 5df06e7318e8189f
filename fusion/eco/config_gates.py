"""Configuration gates (EcoFusion Section 4.2) and the selector that executes their choice.

A configuration gate predicts the fused loss L_f(phi) of every configuration of a
`ConfigurationSet` for each frame (Algorithm 1 line 4):

    predicted = gate.predict(features, meta)    # (B, n_configurations) float32, lower = better

- **knowledge** (4.2.1): external context only (road layout, conditions, severity, lens cover
  from the frame's metadata). HydraFusion's `KNOWLEDGE_TABLE` gives each branch a quality in the
  context (`fusion.nets.branch_gates.branch_quality`); the configuration for the context is every branch
  within `KNOWLEDGE_MARGIN` of the best one (the good sensors, late-fused). Its predicted loss is
  the number of branches by which a configuration differs from that set (0 for it), so with
  gamma < 1 the joint optimisation can only return it: static and not tunable by lambda_E, as
  in the paper (Sections 5.1, 5.3). It reads no stem features, so no stem runs before its decision.
- **deep** / **attention** (4.2.2-4.2.3): HydraFusion's gate architectures
  (`fusion.nets.branch_gates.DeepGate` / `AttentionGate`: three convs, [SAGAN self-attention], max-pool,
  MLP) with one output per configuration, regressing L_f (trained by `study.eco.config_gate_study`).
- **loss_based** (4.2.4): the a-posteriori L_f of every configuration on the frame (needs ground
  truth and every branch's output: `meta[i]["config_losses"]`): the oracle.

`EcoFusionSelector(gate, configurations, energy, lambda_e, gamma, rule)` is a module for
`HydraFusion.gate`: it runs the gate, the joint optimisation (Eq. 7-9, `fusion.eco.optimise`) and
returns each frame's chosen configuration as branch names, so the network then runs only those
branches and the stems they need (Algorithm 1 lines 9-11).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from fusion.eco.configurations import ConfigurationSet
from fusion.eco.optimise import DEFAULT_GAMMA, DEFAULT_RULE, select
from fusion.nets.branch_gates import AttentionGate, DeepGate, branch_quality, sensor_reliability
from sim.registry import Registry

CONFIG_GATES: Registry = Registry(
    "configuration gate",
    doc="Entries are ConfigurationGate subclasses built as `Entry(configurations=..., branch_sensors=..., "
        "branch_frames=..., **options)`; `gate.predict(features, meta)` -> (B, n_configurations) predicted L_f.",
)

KNOWLEDGE_MARGIN = 0.1
"""A branch joins the knowledge gate's configuration when its quality is within this of the best
branch's (qualities are 0..~1.1, `fusion.nets.branch_gates.branch_quality`): the branches the table
rates about as good as the best are late-fused, the clearly weaker ones are left out."""


class ConfigurationGate(nn.Module):
    """Base: predicts L_f for each configuration of `configurations`.

    Args:
        configurations: the ConfigurationSet Phi.
        branch_sensors: branch name -> sensors, in network order.
        branch_frames: branch name -> output frame.
    """

    name = "configuration_gate"
    reads = "features"  # "features", "context" or "losses"
    trainable = False

    def __init__(self, *, configurations: ConfigurationSet, branch_sensors: Mapping[str, Sequence[str]],
                 branch_frames: Mapping[str, str]) -> None:
        super().__init__()
        if tuple(branch_sensors) != configurations.branches:
            raise ValueError(f"branch_sensors: branches {list(branch_sensors)} differ from the configuration "
                             f"set's {list(configurations.branches)}")
        self.configurations = configurations
        self.branch_sensors = {b: tuple(s) for b, s in branch_sensors.items()}
        self.branch_frames = dict(branch_frames)

    def predict(self, features: Mapping[str, Tensor] | None, meta: Sequence[Any] | None) -> Tensor:
        """(B, n_configurations) predicted L_f, lower = better; each registered gate defines it."""
        raise NotImplementedError(f"{type(self).__name__}: a configuration gate subclass defines predict()")

    def extra_repr(self) -> str:
        return f"configurations={len(self.configurations)}"


def _meta(meta: Any, batch: int | None, who: str) -> Sequence[Mapping[str, Any]]:
    if meta is None or isinstance(meta, str | Mapping) or not isinstance(meta, Sequence):
        raise ValueError(f"meta: the {who} gate needs a list of per-frame dicts, got {type(meta).__name__}")
    if batch is not None and len(meta) != batch:
        raise ValueError(f"meta: {len(meta)} entries for a batch of {batch}")
    return meta


def _batch_of(features) -> int | None:
    return int(next(iter(features.values())).shape[0]) if features else None


@CONFIG_GATES.register("knowledge")
class KnowledgeConfigurationGate(ConfigurationGate):
    """Knowledge gating over configurations (module docstring). Reads `meta` only."""

    name = "knowledge"
    reads = "context"
    informed = False  # the context label only (fusion.nets.branch_gates.sensor_reliability)

    def __init__(self, *, margin: float = KNOWLEDGE_MARGIN, **kw) -> None:
        super().__init__(**kw)
        if margin < 0:
            raise ValueError(f"margin: must be >= 0, got {margin}")
        self.margin = float(margin)
        self._mask = np.array(self.configurations.mask(), bool)

    def chosen_branches(self, m: Mapping[str, Any], field: str = "meta") -> tuple[str, ...]:
        rel = sensor_reliability(m, field, self.informed)
        q = {b: branch_quality(rel, s, self.branch_frames[b]) for b, s in self.branch_sensors.items()}
        best = max(q.values())
        return tuple(b for b in self.configurations.branches if q[b] >= best - self.margin)

    def predict(self, features, meta) -> Tensor:
        meta = _meta(meta, _batch_of(features), self.name)
        rows = []
        for i, m in enumerate(meta):
            chosen = self.chosen_branches(m, f"meta[{i}]")
            want = np.array([b in chosen for b in self.configurations.branches])
            rows.append((self._mask != want[None, :]).sum(axis=1))  # branches that differ from the chosen set
        return torch.tensor(np.array(rows), dtype=torch.float32)


@CONFIG_GATES.register("knowledge_informed")
class InformedKnowledgeConfigurationGate(KnowledgeConfigurationGate):
    """Knowledge gating told each frame's severity and lens coverage: an oracle (simulator knowledge)."""

    name = "knowledge_informed"
    informed = True


@CONFIG_GATES.register("loss_based")
class LossBasedGate(ConfigurationGate):
    """Loss-based gating (4.2.4): each frame's a-posteriori L_f per configuration, from
    `meta[i]["config_losses"]` (n_configurations,). Not deployable: the oracle."""

    name = "loss_based"
    reads = "losses"

    def predict(self, features, meta) -> Tensor:
        meta = _meta(meta, _batch_of(features), self.name)
        rows = []
        for i, m in enumerate(meta):
            losses = m.get("config_losses") if isinstance(m, Mapping) else None
            if losses is None or len(losses) != len(self.configurations):
                raise ValueError(f"meta[{i}]['config_losses']: the loss-based gate needs the frame's a-posteriori "
                                 f"L_f of all {len(self.configurations)} configurations")
            rows.append(np.asarray(losses, np.float32))
        return torch.tensor(np.array(rows), dtype=torch.float32)


class LearnedConfigurationGate(ConfigurationGate):
    """Deep / attention gating over configurations: `net` is HydraFusion's DeepGate / AttentionGate
    with one output per configuration (pooled stem features in, predicted L_f out)."""

    trainable = True
    net_class: type = DeepGate

    def __init__(self, *, sensors: Sequence[str] | None = None, **kw) -> None:
        options = {k: kw.pop(k) for k in ("grid", "channels", "hidden", "dropout", "context", "pooling") if k in kw}
        super().__init__(**kw)
        self.net = self.net_class(branch_sensors=self.branch_sensors, branch_frames=self.branch_frames,
                                  sensors=sensors, outputs=len(self.configurations), **options)
        self.net.name = self.name
        self.sensors = self.net.sensors
        self.grid = self.net.grid

    def prepare(self, features) -> Tensor:
        return self.net.prepare(features)

    def predict_prepared(self, x: Tensor) -> Tensor:
        return self.net.predict_prepared(x)

    def predict(self, features, meta=None) -> Tensor:
        return self.net.predict(features, meta)


@CONFIG_GATES.register("deep")
class DeepConfigurationGate(LearnedConfigurationGate):
    name = "deep"
    net_class = DeepGate


@CONFIG_GATES.register("attention")
class AttentionConfigurationGate(LearnedConfigurationGate):
    name = "attention"
    net_class = AttentionGate


def build_config_gate(name: str, model, configurations: ConfigurationSet, **options) -> ConfigurationGate:
    """A configuration gate for `model`'s branches (eval mode). Learned gates read every shared stem."""
    from fusion.nets.branch_gates import gate_sensors

    cls = CONFIG_GATES.get(name)
    if issubclass(cls, LearnedConfigurationGate):
        options.setdefault("sensors", list(gate_sensors(model)))
    return cls(configurations=configurations, branch_sensors=model.branch_sensors,
               branch_frames=model.branch_frames, **options).eval()


class EcoFusionSelector(nn.Module):
    """EcoFusion's decision (Algorithm 1 lines 4-8) as a `HydraFusion.gate`.

    Args:
        gate: a ConfigurationGate.
        energy: (n_configurations,) E(phi) on the scale lambda_E weighs (`normalise_energy`).
        lambda_e: Eq. 8 weight in [0, 1].
        gamma: Eq. 7 tolerance.
        rule: "prose" or "equation" (`fusion.eco.optimise.candidates`).
        loss_unit: the predicted losses are divided by it before Eq. 7-9
            (`fusion.eco.optimise.normalise_loss`; 1: as predicted).

    `forward(features, meta)` -> B tuples of branch names (the chosen configurations);
    `last_choice` holds their indices into the configuration set.
    """

    def __init__(self, gate: ConfigurationGate, energy, lambda_e: float, gamma: float = DEFAULT_GAMMA,
                 rule: str = DEFAULT_RULE, loss_unit: float = 1.0) -> None:
        super().__init__()
        if not loss_unit > 0:
            raise ValueError(f"loss_unit: must be > 0, got {loss_unit}")
        self.loss_unit = float(loss_unit)
        energy = np.asarray(energy, np.float64)
        if energy.shape != (len(gate.configurations),):
            raise ValueError(f"energy: expected ({len(gate.configurations)},) energies, got {energy.shape}")
        self.gate, self.energy = gate, energy
        self.lambda_e, self.gamma, self.rule = float(lambda_e), float(gamma), rule
        self.reads = gate.reads
        self.last_choice: np.ndarray | None = None

    def forward(self, features, meta=None) -> list[tuple[str, ...]]:
        pred = self.gate.predict(features if self.reads == "features" else None, meta)
        idx = select(pred.detach().cpu().numpy() / self.loss_unit, self.energy, self.lambda_e, self.gamma, self.rule)
        self.last_choice = idx
        return [self.gate.configurations.members[i] for i in idx]
