"""A second observation of the same moment (the clear twin) reuses the weather-independent passes
(camera codes, lidar sweep, radar scan) and equals an observation made from scratch; every
observation owns its arrays."""

import dataclasses

import numpy as np

from sim.scenario import ScenarioSpec, Simulator
from tests.sensors.conftest import render


def _arrays(obs):
    out = {}
    for name in ("camera_left", "camera_right"):
        cam = getattr(obs, name)
        for f in ("radiance", "depth", "instance", "material"):
            out[f"{name}.{f}"] = getattr(cam, f)
    for f in dataclasses.fields(obs.lidar):
        out[f"lidar.{f.name}"] = getattr(obs.lidar, f.name)
    for f in dataclasses.fields(obs.radar):
        out[f"radar.{f.name}"] = getattr(obs.radar, f.name)
    return out


def _equal(a, b):
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape and a[k].tobytes() == b[k].tobytes(), k


def test_the_twin_reuses_the_geometry_and_equals_a_fresh_observation():
    scenes, renderer = render("fog", severity=4, seed=11, frames=2)
    scene = scenes[0]
    clear = Simulator(ScenarioSpec(context="fog", severity=4, seed=11, frames=2, warmup_s=3.0)).twin_weather
    assert clear.visibility_m > scene.weather.visibility_m  # the twin's weather differs

    calls = {"codes": 0}
    codes = renderer.stereo.codes

    def counting(*args, **kwargs):
        calls["codes"] += 1
        return codes(*args, **kwargs)

    renderer.stereo.codes = counting
    degraded = renderer.observe(scene)
    twin = renderer.observe(scene, clear)
    assert calls["codes"] == 2  # two cameras, once for both observations
    # written into: the next observation of the moment must not see it
    for arr in _arrays(twin).values():
        arr[...] = 0 if arr.dtype != bool else False
    for arr in _arrays(degraded).values():
        arr[...] = 0 if arr.dtype != bool else False
    again = renderer.observe(scene, clear)
    assert calls["codes"] == 2
    renderer._geometry_key = None  # from scratch
    fresh = renderer.observe(scene, clear)
    assert calls["codes"] == 4
    _equal(_arrays(again), _arrays(fresh))
    assert np.isfinite(fresh.camera_right.depth).mean() > 0.3 and fresh.lidar.returned.any()
    # the next moment is observed anew
    renderer.observe(scenes[1])
    assert calls["codes"] == 6
