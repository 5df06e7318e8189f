"""Degradation framework: one registry, kornia-style two-part models.

Each entry of `DEGRADATIONS` is a `Degradation` subclass instance with
    sensor: "camera" | "lidar" | "radar"
    sample_params(rng, weather, ctx) -> dict | None   # what is random; None = inactive this frame
    apply(observation, params, ctx) -> observation    # pure: returns a new observation
Params are JSON-ready (numbers, short lists) and stored with the frame, so any frame can be
replayed and explained. Camera models are sampled per camera (ctx.camera names it).

`DegradeContext` carries the calibration, the camera name, the frame's Context, the selected lidar
fog model and a
sequence-level generator for faults that persist over a sequence (soiling, beam loss, blocked
radar sector): those are drawn once per sequence so they stay put from frame to frame.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

from sim.registry import Registry

DEGRADATIONS: Registry = Registry(
    "degradation",
    "Degradation instances: sample_params(rng, weather, ctx) -> dict | None and pure "
    "apply(observation, params, ctx) -> observation; applied in registration order per sensor.",
)


@dataclass
class DegradeContext:
    calib: object
    context: object  # sim.scenario.Context
    sequence: dict = field(default_factory=dict)  # persistent per-sequence draws, by model name
    camera: str = ""
    frame_index: int = 0
    lidar_fog: str = "ours"  # lidar fog model (sensors.degrade.lidar.LIDAR_FOG_MODELS)


class Degradation(ABC):
    name = "base"
    sensor = "camera"
    kind = "weather"  # "weather" (driven by the WeatherState) or "obstruction" (faults, per context)

    @abstractmethod
    def sample_params(self, rng: np.random.Generator, weather, ctx: DegradeContext) -> dict | None:
        """Draw this frame's parameters (JSON-ready) or return None when the model is inactive."""

    @abstractmethod
    def apply(self, obs, params: dict, ctx: DegradeContext):
        """Return a degraded copy of `obs` (never modify the input)."""


def register(cls):
    DEGRADATIONS.add(cls.name, cls())
    return cls


# Per-sequence probabilities of obstructions and failures, per context component (layout or
# condition); a combined context takes the largest of its components. Sources: robustness
# benchmarks (Dong et al. CVPR 2023, Robo3D, RoboBEV, WoodScape soiling) list the kinds; the
# rates are ours, higher where dirt, spray, snow and ice are likelier.
OBSTRUCTION_PROBABILITY: dict[str, dict[str, float]] = {
    "lens_soiling": {"city": 0.05, "junction": 0.05, "motorway": 0.08, "rural": 0.12,
                     "rain": 0.15, "fog": 0.05, "snow": 0.25, "night": 0.05},
    "camera_blackout": {"city": 0.02, "junction": 0.02, "motorway": 0.02, "rural": 0.02,
                        "rain": 0.03, "fog": 0.02, "snow": 0.04, "night": 0.02},
    "lidar_beam_loss": {"city": 0.03, "junction": 0.03, "motorway": 0.03, "rural": 0.04,
                        "rain": 0.04, "fog": 0.03, "snow": 0.08, "night": 0.03},
    "lidar_fov_loss": {"city": 0.02, "junction": 0.02, "motorway": 0.02, "rural": 0.03,
                       "rain": 0.03, "fog": 0.02, "snow": 0.06, "night": 0.02},
    "radar_blocked_sector": {"city": 0.03, "junction": 0.03, "motorway": 0.03, "rural": 0.04,
                             "rain": 0.04, "fog": 0.03, "snow": 0.10, "night": 0.03},
}


def obstruction_probability(kind: str, context) -> float:
    table = OBSTRUCTION_PROBABILITY[kind]
    return max(table.get(part, 0.0) for part in (context.layout, *context.conditions))


def persistent(ctx: DegradeContext, key: str, draw):
    """A per-sequence draw: computed on first use from the sequence generator, then reused."""
    if key not in ctx.sequence:
        ctx.sequence[key] = draw(ctx.sequence["_rng"])
    return ctx.sequence[key]
