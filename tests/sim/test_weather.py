import math

import numpy as np
import pytest

from sim.errors import UserError
from sim.scenario import ScenarioSpec, simulate
from sim.weather import (
    CONDITIONS,
    SEVERITY_TABLE,
    WeatherState,
    WeatherTrack,
    clear_like,
    sample_weather,
    sun_elevation_from_lux,
)

WORSE = {"fog": "fog_visibility_m", "rain": "rain_mm_h", "snow": "snow_mm_h", "night": "illuminance_lux"}


@pytest.mark.parametrize("condition", CONDITIONS)
def test_weather_is_monotone_in_severity(condition):
    quantity = WORSE[condition]
    lower_is_worse = SEVERITY_TABLE[condition]["worse"] == "lower"
    for seed in range(20):
        values = []
        for sev in range(6):
            w = sample_weather(np.random.default_rng(seed), (condition,), sev)
            values.append(getattr(w, quantity))
        diffs = np.diff(values)
        assert np.all(diffs < 0) if lower_is_worse else np.all(diffs > 0), (condition, values)
        # visibility never improves with severity
        vis = [sample_weather(np.random.default_rng(seed), (condition,), s).visibility_m for s in range(6)]
        assert np.all(np.diff(vis) <= 1e-9)


@pytest.mark.parametrize("condition", CONDITIONS)
def test_draws_stay_inside_the_documented_interval(condition):
    for sev in range(1, 6):
        lo, hi = SEVERITY_TABLE[condition]["levels"][sev - 1]
        for seed in range(10):
            v = getattr(sample_weather(np.random.default_rng(seed), (condition,), sev), WORSE[condition])
            assert lo <= v <= hi or (condition == "night" and v <= hi)


def test_physical_relations():
    w = WeatherState(fog_visibility_m=300.0)
    assert math.isclose(w.fog_alpha_per_m, math.log(20) / 300.0)
    # ITU-R P.840 reference points: 0.05 g/m3 at ~300 m, 0.5 g/m3 at ~50 m
    assert math.isclose(w.fog_liquid_water_g_m3, 0.05, rel_tol=1e-9)
    assert math.isclose(WeatherState(fog_visibility_m=50.0).fog_liquid_water_g_m3, 0.5, rel_tol=1e-9)
    # extinction coefficients add: rain lowers visibility, and more rain lowers it more
    v = [WeatherState(rain_mm_h=r).visibility_m for r in (0.0, 1.0, 10.0, 50.0)]
    assert v[0] > v[1] > v[2] > v[3]
    # 25 mm/h rain leaves about 1.2 mm of water on the road
    assert math.isclose(sample_weather(np.random.default_rng(0), ("rain",), 5).water_film_mm,
                        1.2 * (sample_weather(np.random.default_rng(0), ("rain",), 5).rain_mm_h / 25) ** 0.59)


def test_sun_elevation_is_monotone_in_illuminance():
    lux = np.logspace(-3, 5, 200)
    elev = [sun_elevation_from_lux(x) for x in lux]
    assert np.all(np.diff(elev) >= 0)
    assert sun_elevation_from_lux(3.0) == pytest.approx(-6.0)


def test_invalid_states_are_rejected():
    with pytest.raises(UserError):
        WeatherState(fog_visibility_m=-5)
    with pytest.raises(UserError):
        WeatherState(lens_coverage_pct=(120.0, 0.0))


def test_transitions_ramp_between_clear_and_target():
    target = sample_weather(np.random.default_rng(1), ("fog",), 5)
    clear = clear_like(target)
    onset = WeatherTrack(clear, target, "onset", start_s=1.0, ramp_s=2.0)
    assert onset.state_at(0.0) == clear and onset.state_at(10.0) == target
    vis = [onset.state_at(t).fog_visibility_m for t in np.linspace(0, 4, 41)]
    assert np.all(np.diff(vis) <= 0)
    bank = WeatherTrack(clear, target, "bank", start_s=1.0, ramp_s=1.0, hold_s=1.0)
    f = [bank.fraction(t) for t in (0.0, 2.5, 10.0)]
    assert f[0] == 0.0 and f[1] == 1.0 and f[2] == 0.0


def test_fog_bank_in_a_sequence():
    scenes = simulate(ScenarioSpec(context="fog", severity=5, seed=0, frames=30, transition="bank"))
    vis = np.array([s.weather.fog_visibility_m for s in scenes])
    assert vis[0] > 5000 and vis.min() < 75 and vis[-1] > 5000


def test_night_lights():
    s = simulate(ScenarioSpec(context="night", severity=4, seed=0, frames=1))[0]
    assert s.light.street_lamps_on and s.light.headlights_on and s.light.sun_elevation_deg < -5
    d = simulate(ScenarioSpec(context="city", seed=0, frames=1))[0]
    assert not d.light.street_lamps_on and d.light.sun_elevation_deg > 10
