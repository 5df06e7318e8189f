"""sim.roads: every pruned search gives highway-env's own answer (highway-env's methods are the
reference, called unbound on the same objects)."""

import copy

import numpy as np
import pytest
from highway_env.road.lane import CircularLane, SineLane, StraightLane
from highway_env.road.regulation import RegulatedRoad
from highway_env.road.road import Road, RoadNetwork
from highway_env.vehicle.objects import Obstacle

from sim.roads import SLACK, HydraRegulatedRoad, HydraRoad, HydraRoadNetwork, hydra_road, lane_box
from sim.scenario import LAYOUT_NAMES, ScenarioSpec, Simulator
from sim.traffic import new_vehicle


@pytest.fixture(scope="module")
def sims():
    """One short simulation per layout (roads with settled traffic, pedestrians on crossings)."""
    out = {}
    for name in LAYOUT_NAMES:
        sim = Simulator(ScenarioSpec(context=name, seed=11, frames=2, warmup_s=2.0))
        list(sim.scenes())
        out[name] = sim
    return out


def _probe_points(network, rng, n):
    """Points on, near and far from every lane (centre lines, lane ends, between lanes), plus
    lane-centre points exactly (ties between coincident lanes)."""
    lanes = network.lanes_list()
    pts = []
    for lane in lanes:
        length = float(lane.length)
        for s in (0.0, length, length / 2):
            pts.append(lane.position(s, 0.0))
        s = rng.uniform(-20, length + 20, n // len(lanes) + 1)
        r = rng.normal(0, 4, s.size)
        pts += [lane.position(si, ri) for si, ri in zip(s, r)]
    pts = np.array(pts)
    lo, hi = pts.min(axis=0) - 50, pts.max(axis=0) + 50
    return np.vstack([pts, rng.uniform(lo, hi, (n // 4, 2))])


def test_the_layouts_simulate_on_hydra_roads(sims):
    for name, sim in sims.items():
        assert isinstance(sim.road, HydraRoad), name
        assert isinstance(sim.road.network, HydraRoadNetwork), name
    assert isinstance(sims["junction"].road, RegulatedRoad)


@pytest.mark.parametrize("name", LAYOUT_NAMES)
def test_closest_lane_matches_highway_env(sims, name):
    network = sims[name].road.network
    rng = np.random.default_rng(1)
    pts = _probe_points(network, rng, 800)
    lanes = network.lanes_list()
    for k, p in enumerate(pts):
        lane = lanes[k % len(lanes)]
        s = float(lane.local_coordinates(p)[0])
        for heading in (None, float(lane.heading_at(s)), float(rng.uniform(-4, 4))):
            fast = network.get_closest_lane_index(p, heading)
            assert fast == RoadNetwork.get_closest_lane_index(network, p, heading), (p, heading)


def test_closest_lane_ties_resolve_to_the_first_lane_in_graph_order():
    net = HydraRoadNetwork()
    for nodes in (("a", "b"), ("c", "d"), ("e", "f")):  # the same centre line three times
        net.add_lane(*nodes, StraightLane([0.0, 0.0], [100.0, 0.0]))
    net.add_lane("g", "h", StraightLane([0.0, 8.0], [100.0, 8.0]))
    for p in ([50.0, 0.0], [50.0, 4.0], [-10.0, 0.0], [50.0, 6.0]):
        fast = net.get_closest_lane_index(np.array(p), 0.0)
        assert fast == RoadNetwork.get_closest_lane_index(net, np.array(p), 0.0)
    assert net.get_closest_lane_index(np.array([50.0, 1.0]), 0.0) == ("a", "b", 0)
    net.add_lane("i", "j", StraightLane([0.0, 1.0], [100.0, 1.0]))  # add_lane refreshes the boxes
    assert net.get_closest_lane_index(np.array([50.0, 1.0]), 0.0) == ("i", "j", 0)


@pytest.mark.filterwarnings("ignore:invalid value")
def test_closest_lane_of_a_non_finite_position_is_highway_envs():
    net = HydraRoadNetwork()
    net.add_lane("a", "b", StraightLane([0.0, 0.0], [100.0, 0.0]))
    net.add_lane("b", "c", StraightLane([100.0, 0.0], [200.0, 0.0]))
    for p, h in (([np.nan, 0.0], 0.0), ([1.0, 0.0], np.nan), ([np.inf, 0.0], None)):
        p = np.array(p)
        assert net.get_closest_lane_index(p, h) == RoadNetwork.get_closest_lane_index(net, p, h)


@pytest.mark.parametrize(
    "lane",
    [
        StraightLane([3.0, -2.0], [-40.0, 17.0]),
        SineLane([0.0, 0.0], [120.0, 30.0], amplitude=-2.5, pulsation=0.3, phase=0.7),
        CircularLane([5.0, 5.0], 20.0, np.radians(-30), np.radians(250), clockwise=True),
        CircularLane([0.0, 0.0], 9.0, np.radians(180), np.radians(90), clockwise=False),
        CircularLane([100.0, -50.0], 300.0, 0.1, 0.5),
    ],
)
def test_lane_box_bounds_highway_envs_lane_distance(lane):
    lo, hi = lane_box(lane)
    on_centre = np.array([lane.position(s, 0.0) for s in np.linspace(0, lane.length, 500)])
    assert (on_centre >= lo - SLACK).all() and (on_centre <= hi + SLACK).all()
    rng = np.random.default_rng(2)
    span = hi - lo
    pts = rng.uniform(lo - span - 10, hi + span + 10, (3000, 2))
    gap = np.maximum(lo - pts, pts - hi).max(axis=1)
    dist = np.array([lane.distance(p) for p in pts])
    assert (gap <= dist + 1e-9).all()
    assert (gap > dist - 5).any()  # the bound is not vacuous


def test_lane_box_of_an_unknown_lane_type_is_none():
    class Odd(StraightLane):
        pass

    assert lane_box(Odd([0.0, 0.0], [1.0, 0.0])) is None
    net = HydraRoadNetwork()
    net.add_lane("a", "b", StraightLane([0.0, 0.0], [100.0, 0.0]))
    net.add_lane("c", "d", Odd([0.0, 3.0], [100.0, 3.0]))
    for p in ([50.0, 2.0], [50.0, 1.0], [500.0, 500.0]):
        assert net.get_closest_lane_index(np.array(p), 0.0) == RoadNetwork.get_closest_lane_index(net, np.array(p), 0.0)


def _lane_queries(road, vehicle):
    net = road.network
    out = {None, vehicle.lane_index, getattr(vehicle, "target_lane_index", None)}
    if vehicle.lane_index:
        out |= set(net.side_lanes(vehicle.lane_index))
    out |= {net.get_closest_lane_index(vehicle.position + d) for d in ([12.0, 0], [0, 12.0], [-12.0, 0])}
    return out


@pytest.mark.parametrize("name", LAYOUT_NAMES)
def test_neighbour_vehicles_match_highway_env(sims, name):
    road = copy.deepcopy(sims[name].road)
    rng = np.random.default_rng(3)
    # obstacles anywhere near the traffic, some on lanes, some between them
    for v in list(road.vehicles)[:6]:
        for _ in range(3):
            ob = Obstacle(road, v.position + rng.normal(0, 6, 2))
            road.objects.append(ob)
    assert len(road.vehicles) >= 4
    for connected in (False, True):
        road.neighbour_vehicles_connected_lanes = connected
        for vehicle in road.vehicles + road.objects[:3]:
            for lane_index in _lane_queries(road, vehicle):
                want = Road.neighbour_vehicles(road, vehicle, lane_index)
                assert road.neighbour_vehicles(vehicle, lane_index) == want
                entities = road.vehicles + road.objects
                road._snapshot = (entities, road.network.boxes().maybe_on_lane(
                    np.array([e.position for e in entities])))
                try:
                    assert road.neighbour_vehicles(vehicle, lane_index) == want
                finally:
                    road._snapshot = None


def test_neighbour_vehicles_on_an_empty_road():
    road = hydra_road(Road(network=RoadNetwork.straight_road_network(2)))
    ob = Obstacle(road, [10.0, 0.0])
    assert road.neighbour_vehicles(ob, ("0", "1", 0)) == (None, None)
    road.objects.append(ob)
    assert road.neighbour_vehicles(ob, ("0", "1", 0)) == (None, None)
    assert road.neighbour_vehicles(Obstacle(road, [0.0, 0.0]), ("0", "1", 0)) == (ob, None)


def _state(road):
    return [(v.crashed, getattr(v, "hit", False), tuple(np.atleast_1d(v.impact)) if v.impact is not None else None,
             v.position.tobytes(), float(v.heading), float(v.speed)) for v in road.vehicles + road.objects]


@pytest.mark.parametrize("name", LAYOUT_NAMES)
def test_step_collisions_match_highway_env(sims, name):
    road = copy.deepcopy(sims[name].road)
    rng = np.random.default_rng(4)
    vehicles = road.vehicles
    # push some vehicles into each other and onto obstacles so that collisions happen
    for a, b in zip(vehicles[0:6:2], vehicles[1:6:2]):
        b.position = a.position + rng.normal(0, 2.0, 2)
    road.objects.append(Obstacle(road, vehicles[-1].position + [1.0, 0.5]))
    road.act()
    a, b = copy.deepcopy(road), copy.deepcopy(road)
    for _ in range(3):
        Road.step(a, 0.2)
        b.step(0.2)
        assert _state(a) == _state(b)
    assert any(v.crashed for v in a.vehicles)


def test_collisions_at_the_edge_of_the_spherical_pre_check_match_highway_env():
    """Vehicles whose corners just touch: the centres are nearly as far apart as the pre-check
    radius allows, the rectangles still intersect."""
    road = hydra_road(Road(network=RoadNetwork.straight_road_network(4)))
    for k, (dx, dy) in enumerate([(4.9, 1.9), (4.99, 1.99), (5.01, 2.01), (4.0, 0.0), (30.0, 30.0)]):
        a = new_vehicle(np.random.default_rng(k), road, ("0", "1", 0), 100.0 + 50 * k, 0.0, "car", 2 * k)
        b = new_vehicle(np.random.default_rng(k), road, ("0", "1", 0), 100.0 + 50 * k, 0.0, "car", 2 * k + 1)
        for v in (a, b):
            v.LENGTH, v.WIDTH = 5.0, 2.0
            v.diagonal = float(np.hypot(5.0, 2.0))
            v.heading = 0.0
        b.position = a.position + [dx, dy]
        road.vehicles += [a, b]
    road.objects.append(Obstacle(road, road.vehicles[0].position + [3.4, 1.9]))
    ref = copy.deepcopy(road)
    Road.step(ref, 0.1)
    road.step(0.1)
    assert _state(ref) == _state(road)
    assert [v.crashed for v in road.vehicles] == [True] * 4 + [False] * 2 + [True] * 2 + [False] * 2


def test_right_of_way_matches_highway_env(sims):
    road = sims["junction"].road
    assert isinstance(road, HydraRegulatedRoad)
    rng = np.random.default_rng(5)
    yielded = 0
    for _ in range(4):
        r = copy.deepcopy(road)
        for k in range(4):  # one vehicle close to the junction on every approach
            v = new_vehicle(rng, r, (f"o{k}", f"ir{k}", 0), float(rng.uniform(80, 98)), 8.0, "car", 90 + k)
            v.plan_route_to(f"o{(k + int(rng.integers(1, 4))) % 4}")
            r.vehicles.append(v)
        a, b = copy.deepcopy(r), copy.deepcopy(r)
        RegulatedRoad.enforce_road_rules(a)
        b.enforce_road_rules()
        want = [(v.target_speed, getattr(v, "is_yielding", None), getattr(v, "yield_timer", None)) for v in a.vehicles]
        assert want == [(v.target_speed, getattr(v, "is_yielding", None), getattr(v, "yield_timer", None)) for v in b.vehicles]
        yielded += sum(1 for w in want if w[1])
        RegulatedRoad.enforce_road_rules(a)
        b.enforce_road_rules()
        assert [v.target_speed for v in a.vehicles] == [v.target_speed for v in b.vehicles]
    assert yielded > 0


def test_hydra_road_keeps_the_road_type_and_options():
    net = RoadNetwork.straight_road_network(3)
    plain = hydra_road(Road(network=net, neighbour_vehicles_connected_lanes=True))
    assert type(plain) is HydraRoad and plain.neighbour_vehicles_connected_lanes
    assert plain.network.graph is net.graph
    regulated = hydra_road(RegulatedRoad(network=net))
    assert type(regulated) is HydraRegulatedRoad and regulated.steps == 0
    busy = Road(network=net)
    busy.objects.append(Obstacle(busy, [0.0, 0.0]))
    with pytest.raises(ValueError):
        hydra_road(busy)
