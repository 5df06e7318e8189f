"""Shared, module-cached sensor fixtures (rendering costs ~0.3 s per frame on 2 cores)."""

import pytest

from sensors.frame import SequenceRenderer
from sensors.rig import load_profile
from sim.scenario import ScenarioSpec, Simulator


def render(context: str, severity: int = 0, seed: int = 0, frames: int = 1, warmup_s: float = 3.0):
    scenes = list(Simulator(ScenarioSpec(context=context, severity=severity, seed=seed, frames=frames,
                                         warmup_s=warmup_s)).scenes())
    renderer = SequenceRenderer(scenes[0], load_profile("cpu"), seed=seed)
    return scenes, renderer


@pytest.fixture(scope="session")
def city():
    scenes, renderer = render("city", seed=1)
    return scenes[0], renderer, renderer.observe(scenes[0])


@pytest.fixture(scope="session")
def junction():
    scenes, renderer = render("junction", seed=2)
    return scenes[0], renderer, renderer.observe(scenes[0])
