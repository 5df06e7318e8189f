"""Road layouts: highway-env road networks with traffic, sidewalks, crossings and structures.

`LAYOUTS` is the registry of layouts. An entry is a `Layout` subclass; the simulator calls its
template hooks in this order (HighwayEnv style):

    road, ego = layout.make_road(rng)                       # highway-env network + vehicles
    crossings = layout.crossings()                          # world (2, 2) segments
    rows = layout.structures(rng, geometry, window)          # static structures
    parked = layout.parking_slots(rng, geometry, lanes_union) # parked cars (x, y, yaw)
    layout.spawn(rng, road, ego, dt, new_id)                 # every step: keep traffic flowing

| layout   | highway-env network                        | traffic                | people  |
|----------|--------------------------------------------|------------------------|---------|
| motorway | highway-fast-v0, 3-4 lanes one way         | cars, vans, HGVs, buses, motorbikes | none    |
| junction | intersection-v2, 4-way, 1 lane each way    | all vehicle classes    | sidewalks + 4 crossings |
| city     | roundabout-v1 (r = 20 m, 2 lanes) + 4 roads | all classes, parked cars | sidewalks + 4 crossings |
| rural    | two-way country road (straights and bends, highway-env StraightLane/CircularLane) | all classes | footpaths |
"""

from __future__ import annotations

import functools
import os

os.environ["SDL_VIDEODRIVER"] = "offscreen"

import gymnasium as gym  # noqa: E402
import highway_env  # noqa: E402, F401  (registers the envs)
import numpy as np  # noqa: E402
import shapely  # noqa: E402
from highway_env.road.lane import CircularLane, LineType, StraightLane  # noqa: E402
from highway_env.road.road import Road  # noqa: E402
from shapely.geometry import LineString, Polygon  # noqa: E402

from sim.actors import sample_size  # noqa: E402
from sim.registry import Registry  # noqa: E402
from sim.roads import HydraRoad, HydraRoadNetwork, hydra_road  # noqa: E402
from sim.traffic import HydraVehicle, adopt, new_vehicle, preserve_idm_defaults  # noqa: E402
from sim.world import (  # noqa: E402
    guardrail_segments,
    hw_to_world,
    outward_normals,
    place_along,
    place_buildings,
    resample,
    ring_lines,
)

LAYOUTS: Registry[type] = Registry(
    "layout",
    "Layout subclasses; the simulator instantiates one per sequence and calls make_road, "
    "crossings, structures, parking_slots and spawn (see sim/layouts.py).",
)

_BIG = 1e9
RETIRE_RADIUS_M = 250.0  # traffic farther than this from the ego leaves the simulation [m]


def _tree(rng):
    crown = rng.uniform(3.0, 7.0)
    return (crown, crown, rng.uniform(5.0, 12.0))


def _lamp(height: tuple[float, float]):
    def size(rng):
        return (rng.uniform(1.0, 2.0), 0.25, rng.uniform(*height))

    return size


@functools.cache
def _hydra_env_class(cls: type) -> type:
    """`cls` building its road as a `sim.roads` HydraRoad (same lanes, same traffic, faster)."""

    class HydraEnv(cls):
        def _make_road(self) -> None:  # intersection-v2, roundabout-v1
            super()._make_road()
            self.road = hydra_road(self.road)

        def _create_road(self) -> None:  # highway-v0 and its variants
            super()._create_road()
            self.road = hydra_road(self.road)

    HydraEnv.__name__ = HydraEnv.__qualname__ = f"Hydra{cls.__name__}"
    return HydraEnv


def _seeded_env(env_id: str, config: dict, seed: int):
    """highway-env's environment `env_id` (unwrapped), reset once with `seed`.

    `gym.make` would build it through its constructor, which resets it unseeded: a whole scene
    (intersection-v2's includes 3 s of traffic simulation) drawn from a fresh OS-seeded generator
    and thrown away by the seeded reset, which rebuilds everything from the seed. That first reset
    is skipped here; the seeded one is the same call as before, so the roads and vehicles are too.
    The env's road is a `sim.roads.HydraRoad` from the start (`_hydra_env_class`).
    """
    cls = _hydra_env_class(gym.envs.registration.load_env_creator(gym.spec(env_id).entry_point))
    env = cls.__new__(cls)
    env.reset = lambda *args, **kwargs: None  # shadows AbstractEnv.reset during the constructor
    cls.__init__(env, config=config)
    del env.reset
    env.reset(seed=seed)
    return env


class Layout:
    """Base layout. Subclasses set the class attributes and override the hooks they need.

    Attributes:
        env_id: highway-env id used by the default make_road (None for a custom network).
        env_config: highway-env config overrides.
        class_mix: probability of each vehicle class among moving traffic.
        pedestrians: (min, max) walkers spawned near the ego.
        group_share: share of walkers that are groups of pedestrians.
        parking_width: parking strip beside the outer lanes [m] (0 = none).
        sidewalk_offset: road edge -> sidewalk inner edge [m]; None = no sidewalk.
        sidewalk_width: [m].
        car_speed: (min, max) target speed of cars [m/s].
        spawn_rate_hz: new vehicles per second entering the network.
        max_speed: upper bound on any speed in this layout [m/s] (sizes the world region).
    """

    name = "base"
    env_id: str | None = None
    env_config: dict = {}
    class_mix: dict[str, float] = {"car": 1.0}
    pedestrians: tuple[int, int] = (0, 0)
    group_share = 0.2
    parking_width = 0.0
    sidewalk_offset: float | None = None
    sidewalk_width = 3.0
    car_speed: tuple[float, float] = (8.0, 12.0)
    spawn_rate_hz = 0.0
    max_speed = 20.0

    def __init__(self) -> None:
        self._next_id = 1

    # --- ids and classes ------------------------------------------------------------------------
    def new_id(self) -> int:
        i = self._next_id
        self._next_id += 1
        return i

    def draw_class(self, rng: np.random.Generator) -> str:
        names = list(self.class_mix)
        p = np.array([self.class_mix[n] for n in names])
        return names[int(rng.choice(len(names), p=p / p.sum()))]

    def target_speed(self, rng: np.random.Generator, cls: str) -> float:
        lo, hi = self.car_speed
        if cls == "bicycle":
            return float(rng.uniform(4.0, 7.0))
        if cls in ("truck", "bus"):
            return float(rng.uniform(lo, 0.5 * (lo + hi)))
        return float(rng.uniform(lo, hi))

    def classify(self, rng: np.random.Generator, vehicle, cls: str | None = None) -> HydraVehicle:
        cls = cls or self.draw_class(rng)
        return adopt(
            vehicle,
            actor_id=self.new_id(),
            cls_name=cls,
            size=sample_size(rng, cls),
            target_speed=self.target_speed(rng, cls),
        )

    # --- hooks --------------------------------------------------------------------------------
    def make_road(self, rng: np.random.Generator) -> tuple[Road, HydraVehicle]:
        """Build the highway-env road with classified traffic; returns (road, ego)."""
        with preserve_idm_defaults():
            env = _seeded_env(self.env_id, dict(self.env_config), int(rng.integers(2**31 - 1)))
        road = env.road
        ego_hw = env.vehicle
        vehicles = []
        ego = None
        for v in road.vehicles:
            if v is ego_hw:
                ego = adopt(v, actor_id=0, cls_name="car", size=np.array([4.9, 2.0, 1.9]))
                ego.target_speed = self.target_speed(rng, "car")
                vehicles.append(ego)
            else:
                vehicles.append(self.classify(rng, v))
        road.vehicles = vehicles
        env.close()
        return road, ego

    def crossings(self) -> list[np.ndarray]:
        return []

    def structures(self, rng: np.random.Generator, geometry, window: Polygon) -> list[tuple]:
        return []

    def parking_slots(self, rng, geometry, lanes_union) -> list[tuple[float, float, float]]:
        return []

    def entries(self) -> list[tuple[tuple[str, str, int], list[str]]]:
        """Entry lanes and the destinations a vehicle entering there may take."""
        return []

    def spawn(self, rng: np.random.Generator, road: Road, ego, dt: float) -> None:
        """Poisson arrivals at the entry lanes (bounded layouts)."""
        entries = self.entries()
        if not entries or rng.uniform() > self.spawn_rate_hz * dt:
            return
        lane_index, destinations = entries[int(rng.integers(len(entries)))]
        lane = road.network.get_lane(lane_index)
        start = lane.position(3.0, 0.0)
        for v in road.vehicles:
            if np.linalg.norm(v.position - start) < 18.0:
                return
        cls = self.draw_class(rng)
        v = new_vehicle(rng, road, lane_index, 3.0, self.target_speed(rng, cls), cls, self.new_id())
        v.target_speed = self.target_speed(rng, cls)
        v.plan_route_to(destinations[int(rng.integers(len(destinations)))])
        road.vehicles.append(v)

    def region_radius(self, duration_s: float) -> float:
        """Radius around the ego's start that the sequence can reach, plus sensor range [m]."""
        return self.max_speed * duration_s + RETIRE_RADIUS_M + 10.0


def _axis_crossings(layout: Layout, distance: float, road_half_width: float = 4.0) -> list[np.ndarray]:
    """Zebra crossings across the four approach roads of a junction centred at the origin, at
    `distance` from the centre, reaching the middle of the sidewalks on both sides."""
    half = road_half_width + layout.parking_width + layout.sidewalk_offset + layout.sidewalk_width / 2
    segs = []
    for u in (np.array([1.0, 0]), np.array([0, 1.0]), np.array([-1.0, 0]), np.array([0, -1.0])):
        v = np.array([-u[1], u[0]])
        c = u * distance
        segs.append(np.array([c - v * half, c + v * half]))
    return segs


def _remove_near(road: Road, ego, radius: float) -> None:
    road.vehicles = [
        v for v in road.vehicles if v is ego or np.linalg.norm(v.position - ego.position) > radius
    ]


def _parallel_parking(
    rng, geometry, lanes_union, offset: float, keep_out: list[tuple[np.ndarray, float]], window
) -> list[tuple[float, float, float]]:
    """Parallel-parked car positions along the straight kerbs, facing the adjacent traffic."""
    slots = []
    lane_pts = np.concatenate(geometry.lanes)
    lane_dir = np.concatenate([np.gradient(lane, axis=0) for lane in geometry.lanes])
    for line in ring_lines(lanes_union, offset, window):
        if LineString(line).length < 15:
            continue
        pts = resample(line, 0.5)
        t = np.gradient(pts, axis=0)
        ang = np.unwrap(np.arctan2(t[:, 1], t[:, 0]))
        s = rng.uniform(0, 10)
        while s < len(pts) * 0.5 - 6:
            i = int(s / 0.5)
            j0, j1 = max(0, i - 10), min(len(pts) - 1, i + 10)
            straight = abs(ang[j1] - ang[j0]) < np.radians(3)
            p = pts[i]
            far = all(np.linalg.norm(p - c) > r for c, r in keep_out)
            if straight and far and rng.uniform() < 0.7:
                k = int(np.argmin(np.linalg.norm(lane_pts - p, axis=1)))
                d = lane_dir[k]
                yaw = float(np.arctan2(d[1], d[0]))
                slots.append((float(p[0]), float(p[1]), yaw))
                s += rng.uniform(6.0, 8.0)
            else:
                s += rng.uniform(2.0, 10.0)
    return slots


@LAYOUTS.register("motorway")
class Motorway(Layout):
    """highway-fast-v0: a straight multi-lane carriageway, guardrails, lamps, tree lines."""

    name = "motorway"
    env_id = "highway-fast-v0"
    class_mix = {"car": 0.66, "van": 0.14, "truck": 0.14, "bus": 0.03, "motorbike": 0.03}
    car_speed = (24.0, 33.0)
    max_speed = 36.0

    def make_road(self, rng):
        self.env_config = {
            "lanes_count": int(rng.integers(3, 5)),
            "vehicles_count": 40,
            "vehicles_density": float(rng.uniform(1.2, 2.0)),
        }
        return super().make_road(rng)

    def spawn(self, rng, road, ego, dt):
        """Keep traffic around the ego: add a vehicle 180-220 m ahead or behind when sparse."""
        near = sum(1 for v in road.vehicles if abs(v.position[0] - ego.position[0]) < 220)
        if near >= 24 or rng.uniform() > 2.0 * dt:
            return
        lanes = road.network.graph["0"]["1"]
        lane_id = int(rng.integers(len(lanes)))
        ahead = rng.uniform() < 0.5
        x = ego.position[0] + (rng.uniform(180, 220) if ahead else -rng.uniform(180, 220))
        if any(np.linalg.norm(v.position - lanes[lane_id].position(x, 0)) < 25 for v in road.vehicles):
            return
        cls = self.draw_class(rng)
        speed = self.target_speed(rng, cls)
        # slower vehicles appear ahead, faster ones behind, so both can reach the ego
        speed = speed * (0.85 if ahead else 1.1)
        v = new_vehicle(rng, road, ("0", "1", lane_id), x, speed, cls, self.new_id())
        v.target_speed = speed
        road.vehicles.append(v)

    def structures(self, rng, geometry, window):
        road = geometry.road
        rows = guardrail_segments(ring_lines(road, 1.2, window))
        rows += place_along(
            rng, ring_lines(road, 2.5, window), "street_lamp", (40.0, 60.0), _lamp((10.0, 12.0)),
            normals_from=road,
        )
        rows += place_along(
            rng, ring_lines(road, rng.uniform(9.0, 14.0), window), "tree", (4.0, 14.0), _tree, jitter=1.5
        )
        return rows


@LAYOUTS.register("junction")
class Junction(Layout):
    """intersection-v2: a four-way junction, sidewalks, zebra crossings, buildings, lamps."""

    name = "junction"
    env_id = "intersection-v2"
    env_config = {"initial_vehicle_count": 10}
    class_mix = {"car": 0.62, "van": 0.14, "truck": 0.06, "bus": 0.06, "motorbike": 0.05, "bicycle": 0.07}
    pedestrians = (8, 16)
    sidewalk_offset = 0.3
    sidewalk_width = 3.0
    car_speed = (7.0, 10.0)
    spawn_rate_hz = 0.7
    max_speed = 12.0
    CROSS_AT = 16.0  # crossing centre distance from the junction centre [m]

    def make_road(self, rng):
        road, _ = super().make_road(rng)
        # our own ego: random approach and destination, anywhere along the approach
        k = int(rng.integers(4))
        dest = int((k + rng.integers(1, 4)) % 4)
        road.vehicles = [v for v in road.vehicles if v.actor_id != 0]
        lane_index = (f"o{k}", f"ir{k}", 0)
        ego = new_vehicle(rng, road, lane_index, float(rng.uniform(20, 85)), 8.0, "car", 0)
        ego.LENGTH, ego.WIDTH, ego.HEIGHT = 4.9, 2.0, 1.9
        ego.target_speed = self.target_speed(rng, "car")
        ego.plan_route_to(f"o{dest}")
        _remove_near(road, ego, 15.0)
        road.vehicles.append(ego)
        return road, ego

    def classify(self, rng, vehicle, cls=None):
        v = super().classify(rng, vehicle, cls)
        v.COMFORT_ACC_MAX, v.COMFORT_ACC_MIN = 6.0, -3.0  # as highway-env's intersection-v2 drivers
        return v

    def spawn(self, rng, road, ego, dt):
        n = len(road.vehicles)
        super().spawn(rng, road, ego, dt)
        for v in road.vehicles[n:]:
            v.COMFORT_ACC_MAX, v.COMFORT_ACC_MIN = 6.0, -3.0

    def entries(self):
        return [((f"o{k}", f"ir{k}", 0), [f"o{j}" for j in range(4) if j != k]) for k in range(4)]

    def crossings(self):
        return _axis_crossings(self, self.CROSS_AT)

    def structures(self, rng, geometry, window):
        road = geometry.road
        clearance = self.sidewalk_offset + self.sidewalk_width + 0.5
        rows = place_buildings(rng, road, window, clearance=clearance)
        rows += place_along(
            rng, ring_lines(road, self.sidewalk_offset + 0.4, window), "street_lamp", (25.0, 35.0),
            _lamp((6.0, 8.0)), normals_from=road,
        )
        return rows


@LAYOUTS.register("city")
class City(Layout):
    """roundabout-v1 with four access streets: kerbside parking, sidewalks, crossings, dense
    buildings, lamps and street trees."""

    name = "city"
    env_id = "roundabout-v1"
    env_config = {"vehicles_count": 10, "roundabout_radius": 20, "roundabout_lanes": 2}
    class_mix = {"car": 0.58, "van": 0.14, "truck": 0.04, "bus": 0.08, "motorbike": 0.06, "bicycle": 0.10}
    pedestrians = (12, 24)
    parking_width = 2.2
    sidewalk_offset = 0.3
    sidewalk_width = 3.5
    car_speed = (8.0, 13.0)
    spawn_rate_hz = 0.6
    max_speed = 15.0
    CROSS_AT = 58.0

    def make_road(self, rng):
        road, _ = super().make_road(rng)
        for v in road.vehicles:
            v.target_speed = min(v.target_speed, self.car_speed[1])
        names = ["s", "e", "n", "w"]
        k = int(rng.integers(4))
        dest = names[int((k + rng.integers(1, 4)) % 4)]
        road.vehicles = [v for v in road.vehicles if v.actor_id != 0]
        lane_index = (f"{names[k]}er", f"{names[k]}es", 0)
        ego = new_vehicle(rng, road, lane_index, float(rng.uniform(10, 110)), 9.0, "car", 0)
        ego.LENGTH, ego.WIDTH, ego.HEIGHT = 4.9, 2.0, 1.9
        ego.target_speed = self.target_speed(rng, "car")
        ego.plan_route_to(f"{dest}xr")
        _remove_near(road, ego, 15.0)
        road.vehicles.append(ego)
        return road, ego

    def entries(self):
        names = ["s", "e", "n", "w"]
        return [((f"{n}er", f"{n}es", 0), [f"{m}xr" for m in names if m != n]) for n in names]

    def crossings(self):
        return _axis_crossings(self, self.CROSS_AT)

    def structures(self, rng, geometry, window):
        road = geometry.road
        clearance = self.sidewalk_offset + self.sidewalk_width + 0.3
        rows = place_buildings(rng, road, window, clearance=clearance, gap=(0.5, 4.0), height=(8.0, 30.0))
        rows += place_along(
            rng, ring_lines(road, self.sidewalk_offset + 0.4, window), "street_lamp", (22.0, 32.0),
            _lamp((6.0, 8.0)), normals_from=road,
        )
        rows += place_along(
            rng, ring_lines(road, self.sidewalk_offset + self.sidewalk_width - 0.6, window), "tree",
            (12.0, 30.0), lambda r: (r.uniform(2.5, 4.5),) * 2 + (r.uniform(5.0, 9.0),),
        )
        rows += [("tree", float(x), float(y), 5.0, 5.0, 8.0, 0.0) for x, y in rng.uniform(-6, 6, (2, 2))]
        return rows

    def parking_slots(self, rng, geometry, lanes_union):
        keep_out = [(np.zeros(2), 52.0)] + [(seg.mean(axis=0), 9.0) for seg in self.crossings()]
        window = Polygon.from_bounds(*geometry.region)
        return _parallel_parking(rng, geometry, lanes_union, self.parking_width / 2, keep_out, window)


@LAYOUTS.register("rural")
class Rural(Layout):
    """A two-way country road of straights and bends (one lane each way, built from highway-env
    StraightLane / CircularLane), footpaths, trees, scattered houses."""

    name = "rural"
    class_mix = {"car": 0.66, "van": 0.12, "truck": 0.08, "bus": 0.03, "motorbike": 0.05, "bicycle": 0.06}
    pedestrians = (2, 6)
    group_share = 0.3
    sidewalk_offset = 1.5
    sidewalk_width = 1.8
    car_speed = (15.0, 24.0)
    spawn_rate_hz = 0.35
    max_speed = 26.0
    LANE_WIDTH = 3.5
    SEGMENTS = 14

    def make_road(self, rng):
        net = HydraRoadNetwork()
        w = self.LANE_WIDTH
        p = np.zeros(2)  # highway-env plane (y down)
        h = 0.0
        n_seg = self.SEGMENTS
        s, c, n = LineType.STRIPED, LineType.CONTINUOUS_LINE, LineType.NONE
        for k in range(n_seg):
            straight = k % 2 == 0
            right = np.array([-np.sin(h), np.cos(h)])  # driver's right in the y-down plane
            if straight:
                length = float(rng.uniform(80, 220))
                d = np.array([np.cos(h), np.sin(h)])
                end = p + d * length
                net.add_lane(f"f{k}", f"f{k + 1}", StraightLane(p + right * w / 2, end + right * w / 2, width=w, line_types=(s, c), speed_limit=25))
                net.add_lane(f"b{k + 1}", f"b{k}", StraightLane(end - right * w / 2, p - right * w / 2, width=w, line_types=(s, c), speed_limit=25))
                p = end
            else:
                radius = float(rng.uniform(120, 400))
                angle = float(rng.uniform(np.radians(15), np.radians(50)))
                turn_right = rng.uniform() < 0.5
                if turn_right:  # centre on the right, phase increases (clockwise on screen)
                    centre = p + right * radius
                    phi0 = h - np.pi / 2
                    phi1 = phi0 + angle
                    net.add_lane(f"f{k}", f"f{k + 1}", CircularLane(centre, radius - w / 2, phi0, phi1, clockwise=True, width=w, line_types=(s, c), speed_limit=25))
                    net.add_lane(f"b{k + 1}", f"b{k}", CircularLane(centre, radius + w / 2, phi1, phi0, clockwise=False, width=w, line_types=(s, c), speed_limit=25))
                    h = h + angle
                    p = centre + radius * np.array([np.cos(phi1), np.sin(phi1)])
                else:
                    centre = p - right * radius
                    phi0 = h + np.pi / 2
                    phi1 = phi0 - angle
                    net.add_lane(f"f{k}", f"f{k + 1}", CircularLane(centre, radius + w / 2, phi0, phi1, clockwise=False, width=w, line_types=(s, c), speed_limit=25))
                    net.add_lane(f"b{k + 1}", f"b{k}", CircularLane(centre, radius - w / 2, phi1, phi0, clockwise=True, width=w, line_types=(s, c), speed_limit=25))
                    h = h - angle
                    p = centre + radius * np.array([np.cos(phi1), np.sin(phi1)])
        del n
        self.n_seg = n_seg
        road = HydraRoad(network=net, np_random=np.random.default_rng(int(rng.integers(2**31 - 1))))
        # traffic in both directions, spaced by at least 30 m
        for direction in ("f", "b"):
            for k in range(n_seg):
                lane_index = (f"f{k}", f"f{k + 1}", 0) if direction == "f" else (f"b{k + 1}", f"b{k}", 0)
                lane = net.get_lane(lane_index)
                for x in np.arange(rng.uniform(5, 40), lane.length - 5, rng.uniform(45, 110)):
                    if rng.uniform() < 0.55:
                        cls = self.draw_class(rng)
                        v = new_vehicle(rng, road, lane_index, float(x), self.target_speed(rng, cls), cls, self.new_id())
                        v.target_speed = self.target_speed(rng, cls)
                        v.plan_route_to("f" + str(n_seg) if direction == "f" else "b0")
                        road.vehicles.append(v)
        # ego on a random segment of the first two thirds, either direction
        k = int(rng.integers(1, max(2, 2 * n_seg // 3)))
        fwd = rng.uniform() < 0.5
        lane_index = (f"f{k}", f"f{k + 1}", 0) if fwd else (f"b{n_seg - k}", f"b{n_seg - k - 1}", 0)
        lane = net.get_lane(lane_index)
        ego = new_vehicle(rng, road, lane_index, float(rng.uniform(0, lane.length)), 18.0, "car", 0)
        ego.LENGTH, ego.WIDTH, ego.HEIGHT = 4.9, 2.0, 1.9
        ego.target_speed = self.target_speed(rng, "car")
        ego.plan_route_to(f"f{n_seg}" if fwd else "b0")
        _remove_near(road, ego, 25.0)
        road.vehicles.append(ego)
        return road, ego

    def entries(self):
        n = self.n_seg
        return [(("f0", "f1", 0), [f"f{n}"]), ((f"b{n}", f"b{n - 1}", 0), ["b0"])]

    def structures(self, rng, geometry, window):
        road = geometry.road
        path_outer = self.sidewalk_offset + self.sidewalk_width
        rows = place_along(
            rng, ring_lines(road, path_outer + rng.uniform(3.0, 6.0), window), "tree", (5.0, 25.0),
            _tree, jitter=1.0,
        )
        rows += place_along(
            rng, ring_lines(road, path_outer + rng.uniform(12.0, 20.0), window), "tree", (3.0, 10.0),
            _tree, jitter=2.0,
        )
        houses = place_buildings(
            rng, road, window, clearance=path_outer + 6.0, frontage=(8.0, 14.0), depth=(7.0, 11.0),
            height=(5.0, 8.0), gap=(60.0, 250.0),
        )
        taken = [shapely.Point(r[1], r[2]).buffer(max(r[3], r[4])) for r in houses]
        return _outside(rows, taken) + houses


def _outside(rows: list[tuple], shapes: list) -> list[tuple]:
    """The structure rows whose position (x, y) = row[1:3] no shape contains (shapely's
    `contains`, all rows at once per shape)."""
    xy = np.array([r[1:3] for r in rows], float).reshape(len(rows), 2)
    covered = np.zeros(len(rows), bool)
    for shape in shapes:
        covered |= shapely.contains_xy(shape, xy[:, 0], xy[:, 1])
    return [r for r, c in zip(rows, covered) if not c]


def lanes_union_of(geometry) -> shapely.Geometry:
    """Drivable lanes only (no parking strip), rebuilt from the lane polylines and widths."""
    strips = [LineString(lane).buffer(w / 2, cap_style="flat") for lane, w in zip(geometry.lanes, geometry.lane_widths)]
    return shapely.unary_union(strips)


__all__ = ["LAYOUTS", "Layout", "hw_to_world", "outward_normals", "lanes_union_of", "_BIG"]
