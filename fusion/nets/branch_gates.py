"""Context-aware gates (HydraFusion Section 4.2 / 5.2.2, EcoFusion Section 4.2): rank the branches,
keep the top k.

Every gate is an `nn.Module` with one contract, so it can sit in `HydraFusion.gate`:

    predicted = gate.predict(features, meta)   # (B, n_branches) float32, lower = better
    selection = gate(features, meta)           # B tuples of branch names: the k lowest, branch order

    features: sensor name -> stem features (B, 64, H/4, W/4), as `HydraFusion.extract_features`
              returns them (the gate's input "brought to one grid" is made by `pool_features`).
    meta:     list of B per-frame dicts, as `fusion.data.FrameDataset` yields them ("layout",
              "conditions", "severity", "weather", ...), or None for gates that do not read it.

`gate.k` is the number of branches kept (None = all); ties keep the branch order. Wired into the
network (`model.gate = gate`), `model(inputs, meta=meta)` runs every stem once, the gate, and only
the branches it selected (HydraFusion Algorithm 1, lines 5-10).

The four entries of `GATES`:

- **knowledge**: the frame's external context (road layout, conditions and their severity, lens
  coverage from the weather record) -> a per-modality reliability from `KNOWLEDGE_TABLE` -> a
  branch quality -> predicted loss 1 - quality (relative, not in Faster R-CNN loss units).
- **deep**: three conv layers and an MLP on the pooled stem features of all modalities -> one
  predicted loss per branch (regression of the per-branch Faster R-CNN loss, trained with mean
  absolute error by `study.engine.gate_training`).
- **attention**: the same with a SAGAN self-attention layer (Zhang et al. 2019) after the convs,
  before the max-pool and the MLP.
- **optimal**: the a-posteriori loss of every branch on the frame (needs ground truth: the
  losses are handed in through `meta[i]["branch_losses"]`): the upper bound of any gate.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from fusion.nets.layers import STEM_CHANNELS, full_precision
from fusion.nets.profile import FRAMES, SENSORS
from sim.registry import Registry
from sim.weather import CONDITIONS

GATES: Registry = Registry(
    "gate",
    doc="Entries are Gate subclasses, built as `Entry(branch_sensors=..., branch_frames=..., k=..., **options)` "
    "(or `build_gate(name, model, k=...)`); an instance is called as `gate(features, meta)` -> one tuple of "
    "selected branch names per sample, and `gate.predict(features, meta)` -> (B, n_branches) predicted losses, "
    "lower is better.",
)



def trainable_gates(registry: Registry = GATES) -> list[str]:
    """The names of `registry`'s gates that learn (`trainable`), in registration order: the gates
    `train-gate` trains and a run must hold before they are used. `registry`: GATES, or
    `fusion.eco.config_gates.CONFIG_GATES` for EcoFusion's configuration gates."""
    return [name for name, gate in registry.items() if gate.trainable]


DEFAULT_GRID = (8, 16)
"""(rows, columns) every sensor's stem features are average-pooled to before the learned gates."""


# ----- top-k selection ------------------------------------------------------------------------


def check_k(k: Any, n_branches: int, field: str = "k") -> int:
    """Number of branches to keep: an int in 1..n_branches, or None / "all" for every branch."""
    if k is None or (isinstance(k, str) and k == "all"):
        return n_branches
    if isinstance(k, bool) or not isinstance(k, int):
        raise ValueError(f"{field}: expected an integer 1..{n_branches} or 'all', got {k!r}")
    if not 1 <= k <= n_branches:
        raise ValueError(f"{field}: must be in 1..{n_branches} (the number of branches) or 'all', got {k}")
    return k


def rank_branches(predicted: Tensor) -> Tensor:
    """(B, n) predicted losses -> (B, n) branch indices from best (lowest) to worst; ties keep the
    branch order (stable sort), so rankings are deterministic."""
    if not isinstance(predicted, Tensor) or predicted.dim() != 2:
        raise ValueError(f"predicted: expected a (B, n_branches) tensor, got {_describe(predicted)}")
    if not torch.isfinite(predicted).all():
        raise ValueError("predicted: predicted losses must be finite")
    return torch.sort(predicted.detach().float(), dim=1, stable=True).indices


def top_k(predicted: Tensor, branches: Sequence[str], k: int | str | None) -> list[tuple[str, ...]]:
    """The k branches with the lowest predicted loss for each sample, as tuples in branch order.

    Args:
        predicted: (B, n_branches) predicted losses (lower = better), columns in `branches` order.
        branches: the branch names.
        k: 1..n_branches, or None / "all".
    """
    if predicted.dim() != 2 or predicted.shape[1] != len(branches):
        raise ValueError(
            f"predicted: expected shape (B, {len(branches)}) for branches {list(branches)}, got {tuple(predicted.shape)}"
        )
    k = check_k(k, len(branches))
    order = rank_branches(predicted)[:, :k]
    return [tuple(branches[j] for j in sorted(row)) for row in order.tolist()]


# ----- the gate base class --------------------------------------------------------------------


class Gate(nn.Module):
    """Base class: ranks `branches` per sample and keeps the top `k` (see the module docstring).

    Args:
        branch_sensors: branch name -> the sensors it consumes, in the network's branch order.
        branch_frames: branch name -> its output frame ("camera_left", "camera_right", "bev").
        k: branches to keep per sample, 1..n_branches, or None for all.

    Subclasses implement `predict(features, meta) -> (B, n_branches)`.
    """

    name = "gate"
    reads = "features"  # what predict() consumes: "features", "context" or "losses"
    trainable = False

    def __init__(
        self,
        *,
        branch_sensors: Mapping[str, Sequence[str]],
        branch_frames: Mapping[str, str],
        k: int | None = None,
    ) -> None:
        super().__init__()
        if not branch_sensors:
            raise ValueError("branch_sensors: a gate needs at least one branch")
        for b, sensors in branch_sensors.items():
            unknown = [s for s in sensors if s not in SENSORS]
            if not sensors or unknown:
                raise ValueError(f"branch_sensors[{b!r}]: expected sensor names from {list(SENSORS)}, got {list(sensors)}")
        if set(branch_frames) != set(branch_sensors):
            raise ValueError("branch_frames: must name the same branches as branch_sensors")
        for b, f in branch_frames.items():
            if f not in FRAMES:
                raise ValueError(f"branch_frames[{b!r}]: unknown frame {f!r} (frames: {', '.join(FRAMES)})")
        self.branches = tuple(branch_sensors)
        self.branch_sensors = {b: tuple(s) for b, s in branch_sensors.items()}
        self.branch_frames = {b: branch_frames[b] for b in self.branches}
        self.k = check_k(k, len(self.branches)) if k is not None else None

    def predict(self, features: Mapping[str, Tensor] | None, meta: Sequence[Any] | None) -> Tensor:
        """(B, n_branches) predicted loss per branch (lower ranks first): what each gate defines."""
        raise NotImplementedError(f"{type(self).__name__}: a gate subclass defines predict()")

    def forward(self, features: Mapping[str, Tensor] | None, meta: Sequence[Any] | None = None):
        return top_k(self.predict(features, meta), self.branches, self.k)

    def extra_repr(self) -> str:
        return f"branches={list(self.branches)}, k={self.k}"


def _batch(features: Mapping[str, Tensor] | None, meta: Sequence[Any] | None) -> int:
    if features:
        return int(next(iter(features.values())).shape[0])
    if meta is not None:
        return len(meta)
    raise ValueError("features: neither features nor meta given, so the batch size is unknown")


def _meta_list(meta: Any, batch: int, who: str) -> Sequence[Mapping[str, Any]]:
    if meta is None or isinstance(meta, str | Mapping) or not isinstance(meta, Sequence):
        raise ValueError(f"meta: the {who} gate needs a list of {batch} per-frame dicts, got {type(meta).__name__}")
    if len(meta) != batch:
        raise ValueError(f"meta: {len(meta)} entries for a batch of {batch}")
    for i, m in enumerate(meta):
        if not isinstance(m, Mapping):
            raise ValueError(f"meta[{i}]: expected a dict, got {type(m).__name__}")
    return meta


# ----- knowledge gate -------------------------------------------------------------------------

MODALITY = {"camera_left": "camera", "camera_right": "camera", "fwd_lidar": "lidar", "lidar": "lidar", "radar": "radar"}
"""Sensor -> the modality whose row of KNOWLEDGE_TABLE applies (fwd_lidar is lidar seen from the camera)."""


@dataclass(frozen=True)
class KnowledgeRow:
    """How one context factor sets each modality's detection reliability (1 = as good as it gets).

    For a road layout: the modality's reliability on that road in clear daylight. For a condition:
    the factor at severity 5; at severity s it is 1 - (1 - factor) * s / 5 (the severity table is
    log-spaced in physical units, so equal severity steps are roughly equal perceptual steps).
    """

    camera: float
    lidar: float
    radar: float
    reason: str


KNOWLEDGE_TABLE: dict[str, KnowledgeRow] = {
    # road layouts (HydraFusion Table 1 "Urban" row and RADIATE's per-context radar results)
    "city": KnowledgeRow(1.0, 0.7, 0.45,
                         "Table 1 urban: camera good, radar and lidar poor. Buildings, parked cars and many close "
                         "objects give radar multipath and clutter, pedestrians return little radar power; lidar "
                         "suffers occlusion in a dense scene; daylight cameras see texture and class."),
    "junction": KnowledgeRow(1.0, 0.75, 0.5,
                             "Urban like city (RADIATE's junctions are in town) but more open: crossing traffic "
                             "at all angles and pedestrians, fewer walls beside the sensor."),
    "motorway": KnowledgeRow(0.9, 0.8, 0.95,
                             "Open road, large vehicles, no pedestrians: radar's strong vehicle returns and range "
                             "work best here; distant vehicles are only a few pixels tall in a 336x188 camera."),
    "rural": KnowledgeRow(0.95, 0.85, 0.75,
                          "Sparse scene: lidar sees the few objects cleanly; hedges and verges add radar clutter."),
    # conditions (physics of sensors/degrade and REFERENCE.md; HydraFusion Table 1 rows)
    "fog": KnowledgeRow(0.15, 0.45, 0.97,
                        "Camera: Koschmieder contrast exp(-3 d / MOR), at 50 m visibility an object 40 m away keeps "
                        "9 %; lidar: two-way exp(-2 alpha R) loses range and fog backscatter adds points near the "
                        "sensor (Hahner 2021); radar at 77 GHz: ~1.6 dB/km at 50 m visibility (ITU-R P.840), "
                        "nothing over 100 m. Table 1 foggy: camera poor, radar and lidar good (RADIATE's fog is "
                        "light; ours goes down to 30 m, where lidar loses most returns)."),
    "rain": KnowledgeRow(0.4, 0.6, 0.85,
                         "Camera: streaks, wet-road reflections, lower contrast (drops on the lens come from the "
                         "weather record, per camera); lidar: drop returns near the sensor and lost returns on dark "
                         "targets (LISA); radar: 18.8 dB/km at 50 mm/h (ITU-R P.838, under 2 dB two-way over the "
                         "50 m ahead) plus rain clutter. Table 1 rainy: camera poor, radar and lidar good."),
    "snow": KnowledgeRow(0.35, 0.35, 0.9,
                         "Lidar: flakes occlude beams and return clutter points close to the sensor (Hahner 2022); "
                         "camera: flakes in the air, snow on the lens, low contrast; radar: mild attenuation and "
                         "clutter. Table 1 snowy: camera and lidar poor, radar good."),
    "night": KnowledgeRow(0.3, 1.0, 1.0,
                          "Camera: down to 0.01 lx, gamma darkening, Poisson-Gaussian noise and headlight glare; "
                          "lidar and radar are active sensors, night changes nothing for them. Table 1 night: "
                          "camera poor, radar and lidar good."),
}
"""Context factor (road layout or condition) -> per-modality reliability, with the reason."""

EARLY_FUSION_GAIN = 0.25
"""An early-fusion branch's quality: its best sensor's reliability plus this gain times the mean of
(r - EARLY_FUSION_FLOOR) over its other sensors. Early fusion gains features when every input is
good and is hurt by noisy inputs (HydraFusion Sec. 2.2; Eq. 1-5: fusing a degraded sensor with an
overconfident weight makes the estimate worse), so a partner below the floor costs quality."""
EARLY_FUSION_FLOOR = 0.5

MAPPING_PENALTY = {"camera_right": 0.0, "camera_left": 0.02, "bev": 0.05}
"""Quality lost by mapping a branch's boxes into the fused reference frame (the right camera):
none for the right camera, a little for the left one (flat-ground stereo disparity), more for BEV
(Appendix A assumes a height per class). Also breaks the tie between the two cameras."""


CONTEXT_SEVERITY = 3
"""The severity the context-only knowledge gate assumes for every condition its label names: the
label ("city+rain") says which conditions hold, not how strong they are, so the gate takes the middle
of the 1..5 scale (the informed variant reads each frame's own severity)."""


def context_of(m: Mapping[str, Any], field: str = "meta",
               severity_required: bool = True) -> tuple[str, tuple[str, ...], int]:
    """(layout, conditions, severity) of a frame's meta: keys "layout", "conditions", "severity"
    (as FrameDataset gives them), or a "context" name such as "city+night+rain" plus "severity".
    Without `severity_required` a missing severity reads as CONTEXT_SEVERITY (0 without conditions)."""
    from sim.scenario import LAYOUT_NAMES, Context

    if "layout" in m and "conditions" in m:
        layout, conditions = m["layout"], tuple(m["conditions"])
    elif "context" in m:
        ctx = Context.parse(m["context"])
        layout, conditions = ctx.layout, ctx.conditions
    else:
        raise ValueError(
            f"{field}: the knowledge gate needs the frame's context ('layout' and 'conditions', or 'context')"
        )
    if layout not in LAYOUT_NAMES:
        raise ValueError(f"{field}['layout']: unknown road layout {layout!r} (known: {', '.join(LAYOUT_NAMES)})")
    for c in conditions:
        if c not in CONDITIONS:
            raise ValueError(f"{field}['conditions']: unknown condition {c!r} (known: {', '.join(CONDITIONS)})")
    default = None if severity_required else CONTEXT_SEVERITY
    severity = m.get("severity", 0 if not conditions else default)
    if isinstance(severity, bool) or not isinstance(severity, int | float) or not 0 <= severity <= 5:
        raise ValueError(f"{field}['severity']: expected a number 0..5, got {severity!r}")
    return layout, conditions, int(severity)


def gate_context(m: Mapping[str, Any], field: str = "meta", informed: bool = False) -> tuple[str, tuple[str, ...], int]:
    """(layout, conditions, severity) as a knowledge gate reads them: the frame's own severity when
    `informed`, else CONTEXT_SEVERITY for a label with conditions (0 without)."""
    layout, conditions, severity = context_of(m, field, severity_required=informed)
    return layout, conditions, severity if informed else (CONTEXT_SEVERITY if conditions else 0)


def sensor_reliability(m: Mapping[str, Any], field: str = "meta", informed: bool = False) -> dict[str, float]:
    """Reliability 0..1 of every sensor in the frame's context (KNOWLEDGE_TABLE).

    From the context label alone (layout and conditions, each condition at CONTEXT_SEVERITY): what a
    car can know (a map, a rain sensor, a clock), and what HydraFusion's knowledge gate reads. With
    `informed`, the frame's own severity and each camera's lens coverage
    (meta["weather"]["lens_coverage_pct"]) too: what only the simulator knows, an oracle."""
    layout, conditions, severity = gate_context(m, field, informed)
    factor = {mod: getattr(KNOWLEDGE_TABLE[layout], mod) for mod in ("camera", "lidar", "radar")}
    for c in conditions:
        row = KNOWLEDGE_TABLE[c]
        for mod in factor:
            factor[mod] *= 1.0 - (1.0 - getattr(row, mod)) * severity / 5.0
    out = {s: factor[mod] for s, mod in MODALITY.items()}
    weather = m.get("weather")
    lens = weather.get("lens_coverage_pct") if informed and isinstance(weather, Mapping) else None
    if lens is not None:
        for cam, pct in zip(("camera_left", "camera_right"), lens):
            out[cam] *= 1.0 - min(max(float(pct), 0.0), 100.0) / 100.0  # that share of the image is covered
    return out


def branch_quality(reliability: Mapping[str, float], sensors: Sequence[str], frame: str) -> float:
    """Quality of one branch from its sensors' reliabilities (see EARLY_FUSION_GAIN, MAPPING_PENALTY)."""
    r = sorted((reliability[s] for s in sensors), reverse=True)
    q = r[0]
    if len(r) > 1:
        q += EARLY_FUSION_GAIN * sum(x - EARLY_FUSION_FLOOR for x in r[1:]) / (len(r) - 1)
    return q - MAPPING_PENALTY[frame]


@GATES.register("knowledge")
class KnowledgeGate(Gate):
    """Knowledge gating (HydraFusion 4.2, "Rigid Knowledge-Based Gating"): ranks branches from the
    frame's context label with `KNOWLEDGE_TABLE`; predicted loss = 1 - branch quality.

    Handles any combination of one layout and several conditions: condition factors multiply, each
    at CONTEXT_SEVERITY (the label names conditions, not their strength). `features` is not read
    (only its batch size); `meta` is required. `knowledge_informed` is the same table reading each
    frame's severity and lens coverage, which only the simulator knows: an oracle.
    """

    name = "knowledge"
    reads = "context"
    informed = False

    def predict(self, features, meta) -> Tensor:
        batch = _batch(features, meta)
        meta = _meta_list(meta, batch, self.name)
        rows = []
        for i, m in enumerate(meta):
            rel = sensor_reliability(m, f"meta[{i}]", self.informed)
            rows.append([1.0 - branch_quality(rel, self.branch_sensors[b], self.branch_frames[b]) for b in self.branches])
        return torch.tensor(rows, dtype=torch.float32)

    def explain(self, m: Mapping[str, Any]) -> dict[str, Any]:
        """Why a frame gets its ranking: the table rows used, sensor reliabilities, branch qualities."""
        layout, conditions, severity = gate_context(m, informed=self.informed)
        rel = sensor_reliability(m, informed=self.informed)
        quality = {b: round(branch_quality(rel, self.branch_sensors[b], self.branch_frames[b]), 4) for b in self.branches}
        return {
            "rows": {c: KNOWLEDGE_TABLE[c].reason for c in (layout, *conditions)},
            "severity": severity,
            "sensor_reliability": {s: round(v, 4) for s, v in rel.items()},
            "branch_quality": quality,
            "ranking": sorted(self.branches, key=lambda b: -quality[b]),
        }


@GATES.register("knowledge_informed")
class InformedKnowledgeGate(KnowledgeGate):
    """The knowledge gate told each frame's severity and lens coverage (simulator knowledge a car does
    not have): an oracle, shown beside the context-only gate to say what that knowledge is worth."""

    name = "knowledge_informed"
    informed = True


# ----- optimal gate ---------------------------------------------------------------------------


@GATES.register("optimal")
class OptimalGate(Gate):
    """Optimal gating (HydraFusion 4.2): ranks branches by their a-posteriori aggregated loss on the
    frame (the sum of the four Faster R-CNN losses against the ground truth). Not deployable: the
    losses need ground truth and every branch's output. The upper bound for the other gates.

    Reads `meta[i]["branch_losses"]` (branch name -> loss, e.g. from `HydraFusion.per_sample_losses`
    summed over the four losses, or the gate dataset of `study.engine.gate_training`).
    """

    name = "optimal"
    reads = "losses"

    def predict(self, features, meta) -> Tensor:
        batch = _batch(features, meta)
        meta = _meta_list(meta, batch, self.name)
        rows = []
        for i, m in enumerate(meta):
            losses = m.get("branch_losses")
            if not isinstance(losses, Mapping):
                raise ValueError(
                    f"meta[{i}]['branch_losses']: the optimal gate ranks by each branch's a-posteriori loss on the "
                    "frame, which needs ground truth; give branch name -> loss (summed per_sample_losses)"
                )
            missing = [b for b in self.branches if b not in losses]
            if missing:
                raise ValueError(f"meta[{i}]['branch_losses']: no loss for branch {missing[0]!r}")
            rows.append([float(losses[b]) for b in self.branches])
        return torch.tensor(rows, dtype=torch.float32)


# ----- learned gates --------------------------------------------------------------------------


def pool_features(features: Mapping[str, Tensor], sensors: Sequence[str], grid: tuple[int, int] = DEFAULT_GRID) -> Tensor:
    """Bring the stem features of `sensors` to one grid: adaptive average pooling of each to `grid`
    (rows, columns), concatenated on channels in `sensors` order -> (B, 64 * len(sensors), *grid).

    Camera stems (H/4 x W/4 of a camera image) and BEV stems (of the BEV crop) have different sizes;
    pooling keeps each map's layout (top rows far / forward, columns left to right).
    """
    if not isinstance(features, Mapping):
        raise ValueError(f"features: expected a dict sensor name -> stem features, got {type(features).__name__}")
    maps = []
    batch = None
    for s in sensors:
        if s not in features:
            raise ValueError(f"features: no stem features for sensor {s!r} (the gate reads {', '.join(sensors)})")
        f = features[s]
        if not isinstance(f, Tensor) or f.dim() != 4 or f.shape[1] != STEM_CHANNELS:
            raise ValueError(f"features[{s!r}]: expected a (B, {STEM_CHANNELS}, h, w) tensor, got {_describe(f)}")
        if batch is not None and f.shape[0] != batch:
            raise ValueError(f"features[{s!r}]: batch size {f.shape[0]} differs from the other sensors' {batch}")
        batch = f.shape[0]
        maps.append(F.adaptive_avg_pool2d(f.float(), grid))
    return torch.cat(maps, dim=1)


def context_features() -> tuple[str, ...]:
    """The context a learned gate may read besides the stem features (`ConvGate` option `context`):
    the road layout (one-hot: what a map and a position give) and the conditions (multi-hot: what a
    rain sensor, a light sensor and a clock give), as the knowledge gate reads them from the frame's
    context label; never the severity or the lens cover, which only the simulator knows."""
    from sim.scenario import LAYOUT_NAMES

    return (*LAYOUT_NAMES, *CONDITIONS)


def context_vector(meta: Sequence[Mapping[str, Any]]) -> Tensor:
    """(B, len(context_features())) float32: each frame's layout one-hot and conditions multi-hot,
    from its meta ("layout" and "conditions", or a "context" name such as "city+night")."""
    names = context_features()
    rows = []
    for i, m in enumerate(meta):
        layout, conditions, _ = context_of(m, f"meta[{i}]", severity_required=False)
        rows.append([1.0 if n == layout or n in conditions else 0.0 for n in names])
    return torch.tensor(rows, dtype=torch.float32).reshape(len(rows), len(names))


def with_context(x, meta: Sequence[Mapping[str, Any]]):
    """Pooled features x (B, C, rows, cols), a tensor or an array, with the frames' context vectors
    appended as constant planes (B, C + n_context, rows, cols): the input of a gate that reads the
    context (`ConvGate(context=True).predict_prepared`)."""
    import numpy as np

    ctx = context_vector(meta)
    if len(ctx) != len(x):
        raise ValueError(f"meta: {len(ctx)} entries for {len(x)} frames of features")
    if isinstance(x, np.ndarray):
        planes = np.broadcast_to(ctx.numpy()[:, :, None, None], (len(x), ctx.shape[1], *x.shape[2:]))
        return np.concatenate([x, planes.astype(x.dtype)], axis=1)
    planes = ctx.to(x.device, x.dtype)[:, :, None, None].expand(-1, -1, *x.shape[2:])
    return torch.cat([x, planes], dim=1)


class SelfAttention2d(nn.Module):
    """SAGAN self-attention (Zhang et al., ICML 2019) on a (B, C, H, W) map.

    f = W_f x, g = W_g x (C/8 channels), h = W_h x (C channels), all 1x1 convs;
    beta[j, i] = softmax_i(f_i' g_j): how much position j attends to position i;
    o_j = sum_i beta[j, i] h_i; y = gamma o + x with gamma a learned scalar starting at 0, so the
    layer starts as the identity and learns how much non-local evidence to add.
    """

    def __init__(self, channels: int) -> None:
        super().__init__()
        inner = max(1, channels // 8)
        self.f = nn.Conv2d(channels, inner, 1, bias=False)
        self.g = nn.Conv2d(channels, inner, 1, bias=False)
        self.h = nn.Conv2d(channels, channels, 1, bias=False)
        self.gamma = nn.Parameter(torch.zeros(1))
        self.last_attention: Tensor | None = None

    def forward(self, x: Tensor) -> Tensor:
        b, c, hh, ww = x.shape
        f = self.f(x).flatten(2)  # (B, C', N)
        g = self.g(x).flatten(2)  # (B, C', N)
        h = self.h(x).flatten(2)  # (B, C, N)
        beta = torch.softmax(torch.bmm(g.transpose(1, 2), f), dim=-1)  # beta[b, j, i] = softmax_i(f_i' g_j)
        o = torch.bmm(h, beta.transpose(1, 2))  # o[:, :, j] = sum_i beta[j, i] h[:, :, i]
        self.last_attention = beta.detach()
        return self.gamma * o.view(b, c, hh, ww) + x


class ConvGate(Gate):
    """Deep gating (HydraFusion 4.2 / 5.2.2, Figure 3): three conv layers, [self-attention], max-pool,
    MLP -> one predicted loss per branch.

    Args:
        branch_sensors, branch_frames, k: see Gate.
        sensors: the stem outputs it reads, in concatenation order (default: every sensor some
            branch uses, in SENSORS order).
        grid: (rows, columns) each sensor's stem features are pooled to (`pool_features`).
        channels: output channels of the three convs (3x3; the second has stride 2).
        hidden: width of the MLP's hidden layer.
        dropout: before the MLP.
        outputs: number of predicted losses (default: one per branch; EcoFusion's configuration
            gates predict one per configuration, `fusion.eco.config_gates`).
        attention: add SelfAttention2d after the convs (the Attention gate).
        context: also read the frame's context label (`context_features`: road layout and
            conditions, what a car can know), added to the MLP's hidden layer through its own
            linear map (issue 26).
        pooling: "grid" (the convs on the pooled `grid`) or "global" (each stem channel averaged
            over the grid, the MLP alone on those compact features; not with attention, which
            attends over the grid).

    Input of the convs: `pool_features(features)` standardised per channel with `input_mean` /
    `input_std` (buffers set by `fit_normalization` from the training set); with `context`, the
    context vector follows as constant planes (`with_context`), read from the first cell. Output:
    `target_center + target_scale * MLP(...)` per branch, with the MLP's last layer starting at
    zero, so an untrained gate predicts the per-branch training median (a constant predictor) and
    training can only move it by what the features explain.
    """

    trainable = True
    reads = "features"
    attention = False

    def __init__(
        self,
        *,
        branch_sensors: Mapping[str, Sequence[str]],
        branch_frames: Mapping[str, str],
        k: int | None = None,
        sensors: Sequence[str] | None = None,
        grid: Sequence[int] = DEFAULT_GRID,
        channels: Sequence[int] = (64, 32, 16),
        hidden: int = 64,
        dropout: float = 0.2,
        outputs: int | None = None,
        context: bool = False,
        pooling: str = "grid",
    ) -> None:
        super().__init__(branch_sensors=branch_sensors, branch_frames=branch_frames, k=k)
        if pooling not in ("grid", "global"):
            raise ValueError(f"pooling: expected grid or global, got {pooling!r}")
        if pooling == "global" and self.attention:
            raise ValueError("pooling: the attention gate attends over the pooled grid; 'global' leaves it none")
        n_out = len(self.branches) if outputs is None else int(outputs)
        if n_out < 1:
            raise ValueError(f"outputs: must be at least 1, got {outputs}")
        if sensors is None:
            used = {s for ss in self.branch_sensors.values() for s in ss}
            sensors = [s for s in SENSORS if s in used]
        unknown = [s for s in sensors if s not in SENSORS]
        if not sensors or unknown:
            raise ValueError(f"sensors: expected sensor names from {list(SENSORS)}, got {list(sensors)}")
        grid = tuple(int(g) for g in grid)
        if len(grid) != 2 or min(grid) < 4:
            raise ValueError(f"grid: expected (rows, columns) of at least 4 each, got {grid}")
        channels = tuple(int(c) for c in channels)
        if len(channels) != 3 or min(channels) < 1:
            raise ValueError(f"channels: expected three positive conv widths, got {channels}")
        if not 0.0 <= dropout < 1.0:
            raise ValueError(f"dropout: must be in [0, 1), got {dropout}")
        if hidden < 1:
            raise ValueError(f"hidden: must be at least 1, got {hidden}")
        self.sensors = tuple(sensors)
        self.grid = grid
        self.options = {"sensors": list(self.sensors), "grid": list(grid), "channels": list(channels),
                        "hidden": int(hidden), "dropout": float(dropout)}
        if context or pooling != "grid":  # recorded only when set: gates saved before these load unchanged
            self.options.update(context=bool(context), pooling=pooling)
        self.context, self.pooling = bool(context), pooling
        self.n_context = len(context_features()) if self.context else 0
        c_in = STEM_CHANNELS * len(self.sensors)
        c1, c2, c3 = channels

        def block(a, b, stride):
            return nn.Sequential(nn.Conv2d(a, b, 3, stride=stride, padding=1),
                                 nn.GroupNorm(_groups(b), b), nn.ReLU(inplace=True))

        if pooling == "grid":
            self.convs = nn.Sequential(block(c_in, c1, 1), block(c1, c2, 2), block(c2, c3, 1))
            self.attn = SelfAttention2d(c3) if self.attention else None
            self.pool = nn.MaxPool2d(2)
            flat = c3 * ((grid[0] + 1) // 2 // 2) * ((grid[1] + 1) // 2 // 2)
        else:
            self.convs, self.attn, self.pool, flat = None, None, None, c_in
        self.mlp = nn.Sequential(nn.Flatten(), nn.Dropout(dropout), nn.Linear(flat, hidden),
                                 nn.ReLU(inplace=True), nn.Linear(hidden, n_out))
        # the context enters the hidden layer through its own weights (initialised for its 8 inputs,
        # not drowned among the convs' hundreds)
        self.context_in = nn.Linear(self.n_context, hidden) if self.context else None
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)
        self.register_buffer("input_mean", torch.zeros(c_in))
        self.register_buffer("input_std", torch.ones(c_in))
        self.register_buffer("target_center", torch.zeros(n_out))
        self.register_buffer("target_scale", torch.ones(n_out))

    def prepare(self, features: Mapping[str, Tensor]) -> Tensor:
        """What the gate consumes and the gate dataset stores: `pool_features(features, sensors, grid)`."""
        return pool_features(features, self.sensors, self.grid)

    def predict_prepared(self, x: Tensor) -> Tensor:
        """(B, 64 * n_sensors [+ n_context], *grid) pooled features (float16 or float32; with the
        context planes of `with_context` when the gate reads the context) -> (B, outputs)."""
        c = self.input_mean.numel() + self.n_context
        if not isinstance(x, Tensor) or x.dim() != 4 or x.shape[1] != c or tuple(x.shape[2:]) != self.grid:
            what = " with the context planes (`with_context`)" if self.context else ""
            raise ValueError(f"x: expected pooled features{what} (B, {c}, {self.grid[0]}, {self.grid[1]}), "
                             f"got {_describe(x)}")
        with full_precision(x):  # a gate's ranking in fp32 even under autocast (its losses differ by little)
            c_feat = self.input_mean.numel()
            ctx = x[:, c_feat:, 0, 0].float()
            x = (x[:, :c_feat].float() - self.input_mean.view(1, -1, 1, 1)) / self.input_std.view(1, -1, 1, 1)
            if self.convs is None:  # pooling "global": each channel's mean over the grid
                flat = x.mean(dim=(2, 3))
            else:
                x = self.convs(x)
                if self.attn is not None:
                    x = self.attn(x)
                flat = self.pool(x).flatten(1)
            z = self.mlp[2](self.mlp[1](self.mlp[0](flat)))
            if self.context_in is not None:
                z = z + self.context_in(ctx)
            return self.target_center + self.target_scale * self.mlp[4](self.mlp[3](z))

    def predict(self, features, meta=None) -> Tensor:
        x = self.prepare(features)
        if self.context:
            x = with_context(x, _meta_list(meta, x.shape[0], self.name))
        return self.predict_prepared(x)

    @torch.no_grad()
    def fit_normalization(self, x: Tensor, losses: Tensor) -> None:
        """Set input standardisation from pooled training features x (N, C, *grid) and the output
        centre / scale from training losses (N, n_branches): median and mean absolute deviation.
        Context planes (after the C feature channels) are read as they are."""
        x = x[:, :self.input_mean.numel()].float()
        self.input_mean.copy_(x.mean(dim=(0, 2, 3)))
        self.input_std.copy_(x.std(dim=(0, 2, 3), unbiased=False).clamp_min(1e-3))
        losses = losses.float()
        center = torch.quantile(losses, 0.5, dim=0)  # the median (midpoint of the two middle values)
        self.target_center.copy_(center)
        self.target_scale.copy_((losses - center).abs().mean(dim=0).clamp_min(1e-3))


@GATES.register("deep")
class DeepGate(ConvGate):
    """Deep gating: ConvGate without attention."""

    name = "deep"
    attention = False


@GATES.register("attention")
class AttentionGate(ConvGate):
    """Attention gating: ConvGate with SAGAN self-attention after the convs."""

    name = "attention"
    attention = True


def _groups(channels: int) -> int:
    return math.gcd(channels, 8)


def _describe(x: Any) -> str:
    if isinstance(x, Tensor):
        return f"{x.dtype} tensor of shape {tuple(x.shape)}"
    return type(x).__name__


def gate_sensors(model) -> tuple[str, ...]:
    """Sensors a feature-reading gate can read in `model`: those with a shared stem."""
    return tuple(s for s in model.sensors if SENSORS[s].stem in model.stems)


def build_gate(name: str, model, k: int | str | None = None, **options: Any) -> Gate:
    """A gate for `model`'s branches (`GATES.get(name)`), reading every stem the model has, in eval
    mode (call `.train()` to train a learned gate).

    Raises UserError (a ValueError) for an unknown name, ValueError for a bad k or option, and for
    a feature-reading gate on a network without shared stems.
    """
    cls = GATES.get(name)
    kw: dict[str, Any] = dict(options)
    if issubclass(cls, ConvGate):
        sensors = kw.setdefault("sensors", list(gate_sensors(model)))
        if not sensors:
            raise ValueError(f"model: the {name} gate reads stem features, and this network has no shared stems")
    k = None if k is None or k == "all" else check_k(k, len(model.branches))
    return cls(branch_sensors=model.branch_sensors, branch_frames=model.branch_frames, k=k, **kw).eval()


__all__ = [
    "CONTEXT_SEVERITY",
    "DEFAULT_GRID",
    "EARLY_FUSION_FLOOR",
    "EARLY_FUSION_GAIN",
    "GATES",
    "InformedKnowledgeGate",
    "KNOWLEDGE_TABLE",
    "MAPPING_PENALTY",
    "AttentionGate",
    "ConvGate",
    "DeepGate",
    "Gate",
    "KnowledgeGate",
    "KnowledgeRow",
    "OptimalGate",
    "SelfAttention2d",
    "branch_quality",
    "build_gate",
    "check_k",
    "context_features",
    "context_of",
    "context_vector",
    "gate_sensors",
    "pool_features",
    "rank_branches",
    "sensor_reliability",
    "top_k",
    "with_context",
]
