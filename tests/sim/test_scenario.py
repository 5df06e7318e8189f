import hashlib
from collections import Counter

import numpy as np
import pytest

from sim.actors import CLASS_ID, CLASS_SIZE, CLASSES, boxes_overlap_2d
from sim.errors import UserError
from sim.layouts import LAYOUTS
from sim.scenario import CONTEXT_NAMES, Context, ScenarioSpec, Simulator, simulate


def _digest(scenes):
    return hashlib.sha256("".join(s.digest() for s in scenes).encode()).hexdigest()


def test_same_seed_same_hash_different_seed_different_hash():
    spec = ScenarioSpec(context="city+night+rain", severity=2, seed=7, frames=6)
    a, b = _digest(simulate(spec)), _digest(simulate(spec))
    assert a == b
    c = _digest(simulate(ScenarioSpec(context="city+night+rain", severity=2, seed=8, frames=6)))
    assert c != a


def test_a_sequence_does_not_depend_on_what_the_process_simulated_before():
    """highway-env's intersection env mutates IDMVehicle class attributes; shards must not care."""
    spec = ScenarioSpec(context="motorway", seed=3, frames=5)
    before = _digest(simulate(spec))
    simulate(ScenarioSpec(context="junction", seed=3, frames=2))
    simulate(ScenarioSpec(context="city", seed=3, frames=2))
    assert _digest(simulate(spec)) == before


def test_the_eight_contexts_and_combinations_parse():
    assert [Context.parse(c).name for c in CONTEXT_NAMES] == list(CONTEXT_NAMES)
    ctx = Context.parse("rain+city+night")
    assert ctx.layout == "city" and ctx.conditions == ("rain", "night")
    assert ctx.name == "city+rain+night"
    assert Context.parse("fog").layout == "motorway"
    assert Context.parse("junction+fog").name == "junction+fog"


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(context="volcano"), "unknown context"),
        (dict(context="city+rural"), "two road layouts"),
        (dict(context="fog", severity=6), "severity"),
        (dict(context="fog", severity=-1), "severity"),
        (dict(context="city", severity=2), "no weather condition"),
        (dict(frames=0), "frames"),
        (dict(frames=-3), "frames"),
        (dict(seed=-1), "seed"),
        (dict(profile="gpu"), "profile"),
        (dict(context="fog", severity=2, transition="tornado"), "transition"),
        (dict(context="night", severity=2, transition="onset"), "transition"),
    ],
)
def test_bad_specs_are_clear_errors(kwargs, message):
    with pytest.raises(UserError, match=message):
        ScenarioSpec(**kwargs)


ALLOWED = {  # documented class mix per layout (sim/layouts.py)
    name: set(LAYOUTS.get(name).class_mix) | ({"pedestrian", "group_of_pedestrians"} if LAYOUTS.get(name).pedestrians[1] else set())
    | ({"car", "van"} if LAYOUTS.get(name).parking_width else set())
    for name in LAYOUTS.names()
}


@pytest.mark.parametrize("layout", LAYOUTS.names())
def test_every_layout_yields_valid_scenes(layout):
    seen = Counter()
    for seed in range(3):
        sim = Simulator(ScenarioSpec(context=layout, seed=seed, frames=8, warmup_s=3.0))
        scenes = list(sim.scenes())
        first = scenes[0]
        # no two actors (nor the ego) overlap at the first frame
        fps = list(first.actors.footprints())
        ego = first.ego
        from sim.actors import box_corners_2d

        fps.append(box_corners_2d(ego.position[None, :2], ego.size[None, :2], np.array([ego.yaw]))[0])
        centers = np.array([f.mean(axis=0) for f in fps])
        for i in range(len(fps)):
            close = np.where(np.linalg.norm(centers - centers[i], axis=1) < 20)[0]
            for j in close[close > i]:
                assert not boxes_overlap_2d(fps[i], fps[j]), (layout, seed, i, j)
        for s in scenes:
            names = s.actors.class_names()
            seen.update(names)
            assert set(names) <= ALLOWED[layout], (layout, set(names) - ALLOWED[layout])
            # pedestrians stay on sidewalks and crossings
            ped = np.isin(s.actors.classes, [CLASS_ID["pedestrian"], CLASS_ID["group_of_pedestrians"]])
            if ped.any():
                assert s.road.on_sidewalk_or_crossing(s.actors.centers[ped, :2]).all(), layout
            # moving vehicles are on the road surface
            veh = (~ped) & (~s.actors.parked)
            on = s.road.on_road(s.actors.centers[veh, :2])
            assert on.mean() > 0.9, (layout, on.mean())
            # sizes are the documented class sizes (within +-2 sigma)
            for cls, size in zip(names, s.actors.sizes):
                mean, rel = CLASS_SIZE[cls]
                assert np.all(np.abs(size - mean) <= 2.01 * rel * np.asarray(mean) + 0.5 * (cls == "group_of_pedestrians")), cls
            assert np.all(s.actors.centers[:, 2] > 0)
    assert seen, layout
    if LAYOUTS.get(layout).pedestrians[1]:
        assert seen["pedestrian"] + seen["group_of_pedestrians"] > 0
    else:
        assert seen["pedestrian"] == 0


def test_structures_per_context():
    counts = {}
    for layout in ("motorway", "junction", "city", "rural"):
        s = simulate(ScenarioSpec(context=layout, seed=0, frames=1, warmup_s=0.0))[0]
        counts[layout] = {k: s.structures.count(k) for k in ("building", "tree", "guardrail", "street_lamp")}
    assert counts["motorway"]["guardrail"] > 20 and counts["motorway"]["building"] == 0
    assert counts["junction"]["building"] > 5 and counts["junction"]["street_lamp"] > 5
    assert counts["city"]["building"] > 10 and counts["city"]["tree"] > 5
    assert counts["rural"]["tree"] > 50 and counts["rural"]["street_lamp"] == 0


def test_city_has_parked_cars_that_never_move():
    scenes = simulate(ScenarioSpec(context="city", seed=1, frames=10))
    parked0 = scenes[0].actors[scenes[0].actors.parked]
    parked9 = scenes[-1].actors[scenes[-1].actors.parked]
    assert len(parked0) > 5
    np.testing.assert_array_equal(parked0.ids, parked9.ids)
    np.testing.assert_array_equal(parked0.centers, parked9.centers)
    assert set(parked0.class_names()) <= {"car", "van"}


def test_ids_are_stable_and_motion_is_consistent_with_velocity():
    scenes = simulate(ScenarioSpec(context="motorway", seed=2, frames=6, frame_rate_hz=10.0))
    a, b = scenes[2].actors, scenes[3].actors
    common, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
    assert len(common) > 3
    moved = b.centers[ib, :2] - a.centers[ia, :2]
    predicted = 0.5 * (a.velocities[ia, :2] + b.velocities[ib, :2]) * 0.1
    assert np.median(np.linalg.norm(moved - predicted, axis=1)) < 0.3


def test_classes_cover_radiate():
    assert CLASSES == ("car", "van", "truck", "bus", "motorbike", "bicycle", "pedestrian", "group_of_pedestrians")


def test_the_seeded_env_equals_gym_make_then_reset():
    """sim.layouts builds highway-env's envs without the constructor's unseeded reset: same scene."""
    import gymnasium as gym

    from sim.layouts import _seeded_env
    from sim.traffic import preserve_idm_defaults

    def state(env):
        return [(type(v).__name__, v.lane_index, v.position.tolist(), float(v.heading), float(v.speed))
                for v in env.road.vehicles]

    for env_id, config in (("intersection-v2", {"initial_vehicle_count": 10}), ("highway-fast-v0", {})):
        with preserve_idm_defaults():
            ours = _seeded_env(env_id, dict(config), 11)
            theirs = gym.make(env_id, config=dict(config))
            theirs.reset(seed=11)
        assert state(ours) == state(theirs.unwrapped) and len(state(ours)) > 3
        assert ours.vehicle.position.tolist() == theirs.unwrapped.vehicle.position.tolist()


def test_pyplot_is_imported_on_first_use_only():
    import subprocess
    import sys

    code = ("import sys, sim.scenario; assert 'matplotlib.font_manager' not in sys.modules; "
            "import matplotlib; matplotlib.use('Agg'); import matplotlib.pyplot as plt; "
            "fig, ax = plt.subplots(); ax.plot([0, 1]); assert 'matplotlib.font_manager' in sys.modules; print('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]


def test_walkers_near_a_crossing_end_prefilter_never_misses_one():
    from sim.pedestrians import NEAR_CROSSING_M

    sim = Simulator(ScenarioSpec(context="junction", seed=2, frames=1, warmup_s=0.0))
    people = sim.people
    ends = np.concatenate(people.crossings)
    rng = np.random.default_rng(0)
    angles = rng.uniform(0, 2 * np.pi, (len(ends), 200))
    radii = NEAR_CROSSING_M + rng.choice([-1e-12, 0.0, 1e-12, -0.3, 0.3, 5.0], angles.shape)
    pts = (ends[:, None] + radii[..., None] * np.stack([np.cos(angles), np.sin(angles)], -1)).reshape(-1, 2)
    pts = np.vstack([pts, rng.uniform(-100, 100, (2000, 2))])
    for p in pts:
        near = any(np.linalg.norm(p - e) < NEAR_CROSSING_M for e in ends)
        assert not near or people._near_a_crossing_end(p)
    assert not all(people._near_a_crossing_end(p) for p in pts)
