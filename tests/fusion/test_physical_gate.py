"""fusion.physical_gate: rules fire on the right side of their threshold, the gate reads nothing but
what a car measures (never ground truth, the context label or the severity), candidates come from a
crossover record, and the threshold search finds a known optimum and keeps a sensor on ties."""

from collections.abc import Mapping

import pytest

from fusion.physical_gate import (
    NEVER,
    choose_thresholds,
    dropped,
    observed_candidates,
    physical_selection,
    rule,
    threshold_candidates,
    weather_of,
)

BRANCHES = ("radar", "camera_right", "lidar", "radar_lidar")
SENSORS = {"radar": ("radar",), "camera_right": ("camera_right",), "lidar": ("lidar",), "radar_lidar": ("radar", "lidar")}
CLEAR = {"visibility_m": 20000.0, "rain_mm_h": 0.0, "snow_mm_h": 0.0, "illuminance_lux": 30000.0}


def test_a_rule_fires_at_and_beyond_its_threshold_in_the_direction_that_is_worse():
    fog = rule("camera_right", "fog", 150.0)
    assert fog.fires({**CLEAR, "visibility_m": 150.0}) and fog.fires({**CLEAR, "visibility_m": 40.0})
    assert not fog.fires({**CLEAR, "visibility_m": 151.0}) and not fog.fires(CLEAR)
    snow = rule("lidar", "snow", 1.0)
    assert snow.fires({**CLEAR, "snow_mm_h": 1.0}) and not snow.fires({**CLEAR, "snow_mm_h": 0.99})
    with pytest.raises(ValueError, match="unknown condition"):
        rule("lidar", "hail", 1.0)


def test_dropping_a_sensor_drops_every_branch_that_reads_it():
    night = [rule("camera_right", "night", 2.0)]
    dark = {**CLEAR, "illuminance_lux": 0.5}
    assert physical_selection(dark, BRANCHES, SENSORS, night) == ("radar", "lidar", "radar_lidar")
    assert physical_selection(CLEAR, BRANCHES, SENSORS, night) == BRANCHES
    lidar = [rule("lidar", "snow", 1.0)]
    assert physical_selection({**CLEAR, "snow_mm_h": 2.0}, BRANCHES, SENSORS, lidar) == ("radar", "camera_right")
    # every sensor dropped: all branches are kept (a car never runs nothing)
    every = [rule(s, "snow", 0.1) for s in ("radar", "camera_right", "lidar")]
    assert physical_selection({**CLEAR, "snow_mm_h": 2.0}, BRANCHES, SENSORS, every) == BRANCHES
    assert dropped({**CLEAR, "snow_mm_h": 2.0}, every) == {"radar", "camera", "lidar"}


class Recording(Mapping):
    """A frame meta that records every key read from it."""

    def __init__(self, data):
        self.data, self.read = data, set()

    def __getitem__(self, k):
        self.read.add(k)
        return self.data[k]

    def __iter__(self):
        return iter(self.data)

    def __len__(self):
        return len(self.data)

    def get(self, k, default=None):
        self.read.add(k)
        return self.data.get(k, default)


def test_the_gate_reads_only_the_weather_a_car_measures_never_labels_context_or_severity():
    weather = Recording({**CLEAR, "fog_visibility_m": 90.0, "lens_coverage_pct": [40.0, 40.0], "overcast": True})
    meta = Recording({"weather": weather, "context": "fog", "severity": 5, "labels": {"boxes": []},
                      "difficult": [], "branch_losses": {}})
    seen = weather_of(meta)
    assert meta.read == {"weather"}
    assert weather.read == {"visibility_m", "rain_mm_h", "snow_mm_h", "illuminance_lux"}
    assert set(seen) == weather.read
    # the gate decides from that dict alone: a frame's ground truth cannot reach it
    assert physical_selection(seen, BRANCHES, SENSORS, [rule("camera_right", "fog", 150.0)]) == BRANCHES
    with pytest.raises(ValueError, match="no weather record"):
        weather_of({"context": "fog", "severity": 5})


def test_candidates_come_from_the_crossover_and_a_curve_that_never_crosses_gives_none():
    crossed = {"steps": [800.0, 400.0, 200.0], "crossing": 300.0, "crossing_kind": "crossed",
               "first_resolved_below": 200.0, "crossing_interval": [500.0, None]}
    assert threshold_candidates(crossed) == [NEVER, 300.0, 200.0, 500.0]
    mildest = {"steps": [800.0, 400.0], "crossing": 800.0, "crossing_kind": "at_mildest",
               "first_resolved_below": None, "crossing_interval": [None, 600.0]}
    assert threshold_candidates(mildest, bounds=(1000.0, 40.0)) == [NEVER, 1000.0, 600.0]
    never = {"steps": [1.0, 2.0], "crossing": None, "crossing_kind": "none", "first_resolved_below": None,
             "crossing_interval": [None, None]}
    assert threshold_candidates(never) == [NEVER]


def test_observed_candidates_are_seen_values_from_the_worst_end_and_each_fires_on_fewer_frames_first():
    fog = [900.0, 120.0, 60.0, 300.0, 45.0]  # visibility (m): lower is worse
    assert observed_candidates(fog, "fog") == [NEVER, 45.0, 60.0, 120.0, 300.0, 900.0]
    rain = [2.0, 30.0, 7.0, 7.0, 12.0]  # mm/h: higher is worse; the repeated value once
    assert observed_candidates(rain, "rain") == [NEVER, 30.0, 12.0, 7.0, 2.0]
    frames = [{**CLEAR, "rain_mm_h": v} for v in rain]
    fired = [sum(rule("camera_right", "rain", t).fires(w) for w in frames) for t in observed_candidates(rain, "rain")[1:]]
    assert fired == sorted(fired) and fired[0] == 1 and fired[-1] == len(rain)  # the worst frame only, ..., every frame
    assert observed_candidates([], "night") == [NEVER] and observed_candidates([float("nan")], "snow") == [NEVER]
    assert observed_candidates(list(range(1, 101)), "snow", quantiles=(0.0, 0.5)) == [NEVER, 100, 50]
    with pytest.raises(ValueError, match="unknown condition"):
        observed_candidates([1.0], "hail")


def test_the_threshold_search_finds_the_best_rules_and_keeps_a_sensor_on_a_tie():
    best = {("camera_right", "fog"): 200.0, ("lidar", "snow"): 1.5}

    def score(rules):  # 1 at the best assignment, less the further from it; radar's rule changes nothing
        got = {(r.sensor, r.condition): r.threshold for r in rules}
        return -sum(abs((got.get(k) or 0.0) - v) for k, v in best.items())

    cands = {("camera_right", "fog"): [NEVER, 300.0, 200.0], ("lidar", "snow"): [NEVER, 1.5, 2.0],
             ("radar", "rain"): [NEVER, 5.0]}
    rules, trace = choose_thresholds(cands, score)
    assert {(r.sensor, r.condition): r.threshold for r in rules} == best
    assert trace[0] == {"rules": [], "score": score([])}
    flat, _ = choose_thresholds({("radar", "rain"): [NEVER, 5.0]}, lambda rules: 0.3)
    assert flat == []  # no strict gain: the sensor stays
