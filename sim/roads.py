"""highway-env roads with exact, pruned searches.

highway-env answers "which lane is this vehicle on?" (`RoadNetwork.get_closest_lane_index`), "who
drives ahead and behind me?" (`Road.neighbour_vehicles`), "who touches whom?" (the collision pass
of `Road.step`) and "who must yield at the junction?" (`RegulatedRoad.enforce_road_rules`) by
trying every lane, every vehicle or every pair. The subclasses here give the same answers, bit
for bit, but skip the candidates that provably cannot matter, with a cheap geometric lower bound:

* Every lane of a known type (StraightLane, SineLane, CircularLane) has an axis-aligned box around
  its centre line (`lane_box`). highway-env's lane distance |lateral| + (how far the point lies
  before the start or past the end) is at least the Euclidean distance from the point to the
  centre line, which is at least the distance to that box. A lane whose box is farther than the
  best distance found so far cannot be the closest lane, and a vehicle farther from the box than
  half the lane width + 1 m + 5 m cannot be `on_lane(margin=1)`.
* Two vehicles farther apart than highway-env's own "fast spherical pre-check" radius cannot
  collide, and two predicted trajectories that never come within a vehicle length cannot conflict.

The remaining candidates go through highway-env's own methods, in highway-env's order, so ties
resolve identically. Bounds are widened by `SLACK` to absorb float rounding (tests/sim/test_roads.py
compares every fast path with highway-env's method).
"""

from __future__ import annotations

import math

import numpy as np
from highway_env import utils
from highway_env.road.lane import CircularLane, SineLane, StraightLane
from highway_env.road.regulation import RegulatedRoad
from highway_env.road.road import Road, RoadNetwork
from highway_env.vehicle.controller import ControlledVehicle, MDPVehicle
from highway_env.vehicle.objects import Landmark

SLACK = 1e-6
"""[m] added to every lower bound's threshold: far above float rounding of these coordinates
(< 1e-9 m for roads within 10 km of the origin), far below any distance that matters."""

NEIGHBOUR_MARGIN = 1.0
"""[m] the `margin` of `lane.on_lane` in highway-env's `Road.neighbour_vehicles`."""


def lane_box(lane) -> tuple[np.ndarray, np.ndarray] | None:
    """(lo, hi) corners of an axis-aligned box within which highway-env's lane distance bound
    holds: for any point p, |lateral| + longitudinal overshoot >= distance(p, box). None for lane
    types without a known bound (they are always evaluated).

    StraightLane: the box of the segment start-end. SineLane: the same box grown by the
    amplitude (its lateral coordinate is the straight one minus A sin(.)). CircularLane: the box of
    the arc (end points and the axis extremes the arc passes), since the radial offset is |lateral|
    and an arc overshoot is at least the chord to the arc's end.
    """
    kind = type(lane)
    if kind in (StraightLane, SineLane):
        pts = np.array([lane.start, lane.end], float)
        grow = abs(float(lane.amplitude)) if kind is SineLane else 0.0
        return pts.min(axis=0) - grow, pts.max(axis=0) + grow
    if kind is CircularLane and lane.length >= 0:
        a0, a1 = sorted((float(lane.start_phase), float(lane.end_phase)))
        quarter = math.pi / 2
        angles = [a0, a1] + [k * quarter for k in range(math.ceil(a0 / quarter), math.floor(a1 / quarter) + 1)]
        angles = np.array(angles)
        pts = np.asarray(lane.center, float) + float(lane.radius) * np.column_stack([np.cos(angles), np.sin(angles)])
        return pts.min(axis=0), pts.max(axis=0)
    return None


class HydraRoadNetwork(RoadNetwork):
    """RoadNetwork whose `get_closest_lane_index` skips lanes whose box is too far (same result)."""

    def add_lane(self, _from: str, _to: str, lane) -> None:
        super().add_lane(_from, _to, lane)
        self.__dict__.pop("_boxes", None)

    def boxes(self) -> LaneBoxes:
        """The lane boxes of the network (built once; `add_lane` drops them)."""
        boxes = self.__dict__.get("_boxes")
        if boxes is None:
            boxes = self._boxes = LaneBoxes(self)
        return boxes

    def get_closest_lane_index(self, position: np.ndarray, heading: float | None = None):
        """highway-env's closest lane: the first lane in graph order with the smallest
        `lane.distance_with_heading(position, heading)`, evaluating only lanes whose box is within
        the best distance found so far (boxes visited nearest first)."""
        x, y = float(position[0]), float(position[1])
        if not (math.isfinite(x) and math.isfinite(y) and (heading is None or math.isfinite(heading))):
            return super().get_closest_lane_index(position, heading)
        b = self.boxes()
        gap = np.maximum(b.lo - position, position - b.hi).max(axis=1)  # <= distance to each box
        gaps = gap.tolist()
        best, best_i = math.inf, -1
        for i in np.argsort(gap, kind="stable").tolist():
            if gaps[i] > best + SLACK:
                break
            d = b.lanes[i].distance_with_heading(position, heading)
            if d != d:  # NaN: highway-env's argmin picks the first NaN
                return super().get_closest_lane_index(position, heading)
            if d < best or (d == best and i < best_i):
                best, best_i = d, i
        return b.indexes[best_i]


class LaneBoxes:
    """The lanes of a network in graph order with what the pruned searches need: each lane's box
    (`lane_box`; lanes of unknown type get an infinite one) and, for the `on_lane(margin=1)` test
    of `Road.neighbour_vehicles`, its frame (StraightLane and SineLane: start, direction, lateral
    direction, length; CircularLane: centre and radius) and how far off the centre line a road
    user may be and still be on it."""

    def __init__(self, network: RoadNetwork) -> None:
        self.indexes, self.lanes, lo, hi = [], [], [], []
        for _from, to_dict in network.graph.items():
            for _to, lanes in to_dict.items():
                for _id, lane in enumerate(lanes):
                    box = lane_box(lane)
                    if box is None:
                        box = (np.full(2, -np.inf), np.full(2, np.inf))
                    self.indexes.append((_from, _to, _id))
                    self.lanes.append(lane)
                    lo.append(box[0])
                    hi.append(box[1])
        n = len(self.lanes)
        self.lo = np.array(lo, float).reshape(n, 2)
        self.hi = np.array(hi, float).reshape(n, 2)
        self.row = {index: k for k, index in enumerate(self.indexes)}

        # on_lane(margin=1): |lateral| <= width / 2 + 1 and -5 <= longitudinal < length + 5 (the
        # lane's VEHICLE_LENGTH), so the centre line is at most width / 2 + 1 + 5 away
        self.straight = np.array([type(lane) in (StraightLane, SineLane) for lane in self.lanes], bool)
        self.circular = np.array([type(lane) is CircularLane and lane.length >= 0 for lane in self.lanes], bool)
        known = self.straight | self.circular
        self.lateral_reach = np.array(
            [float(lane.width) / 2 + NEIGHBOUR_MARGIN + (abs(float(lane.amplitude)) if type(lane) is SineLane else 0.0)
             if k else np.inf for lane, k in zip(self.lanes, known)]
        )
        overshoot = np.array([float(lane.VEHICLE_LENGTH) if k else np.inf for lane, k in zip(self.lanes, known)])
        self.box_reach = self.lateral_reach + overshoot
        self.overshoot = overshoot
        zero = np.zeros(2)
        self.origin = np.array(
            [lane.start if s else lane.center if c else zero for lane, s, c in zip(self.lanes, self.straight, self.circular)],
            float,
        ).reshape(n, 2)
        self.direction = np.array([lane.direction if s else zero for lane, s in zip(self.lanes, self.straight)], float).reshape(n, 2)
        self.length = np.array([float(lane.length) for lane in self.lanes])
        self.radius = np.array([float(lane.radius) if c else 0.0 for lane, c in zip(self.lanes, self.circular)])

    def maybe_on_lane(self, positions: np.ndarray) -> np.ndarray:
        """(lanes, N) bool: False where `lane.on_lane(position, margin=1)` is certainly False."""
        gap = np.maximum(self.lo[:, None] - positions, positions - self.hi[:, None]).max(axis=2)
        maybe = ~(gap > self.box_reach[:, None] + SLACK)
        delta = positions - self.origin[:, None]  # (lanes, N, 2)
        u, v = self.direction[:, None, 0], self.direction[:, None, 1]
        longitudinal = delta[..., 0] * u + delta[..., 1] * v
        lateral = delta[..., 1] * u - delta[..., 0] * v  # along (-v, u), highway-env's direction_lateral
        straight_ok = ~(np.abs(lateral) > self.lateral_reach[:, None] + SLACK)
        straight_ok &= ~(longitudinal < -self.overshoot[:, None] - SLACK)
        straight_ok &= ~(longitudinal > (self.length + self.overshoot)[:, None] + SLACK)
        radial = np.sqrt((delta**2).sum(axis=2))
        circular_ok = ~(np.abs(self.radius[:, None] - radial) > self.lateral_reach[:, None] + SLACK)
        maybe &= np.where(self.straight[:, None], straight_ok, np.where(self.circular[:, None], circular_ok, True))
        return maybe


def _positions(objects: list) -> np.ndarray:
    return np.array([o.position for o in objects], float).reshape(len(objects), 2)


class HydraRoad(Road):
    """Road with exact pruned `neighbour_vehicles` and collision pass (network: HydraRoadNetwork)."""

    _snapshot: tuple[list, np.ndarray] | None = None  # during act(): road users, maybe_on_lane

    def act(self) -> None:
        """Decide every vehicle's action. Positions do not move while vehicles decide, so the
        neighbour searches of this pass share one `maybe_on_lane` table of all road users."""
        entities = self.vehicles + self.objects
        self._snapshot = (entities, self.network.boxes().maybe_on_lane(_positions(entities)))
        try:
            super().act()
        finally:
            self._snapshot = None

    def neighbour_vehicles(self, vehicle, lane_index=None):
        """highway-env's `Road.neighbour_vehicles` (preceding and following vehicle on a lane),
        looking only at road users near enough to a searched lane to be on it."""
        lane_index = lane_index or vehicle.lane_index
        if not lane_index:
            return None, None
        lane = self.network.get_lane(lane_index)
        s = lane.local_coordinates(vehicle.position)[0]
        s_front = s_rear = None
        v_front = v_rear = None

        _from, _to, _id = lane_index
        lanes_offsets = [(lane, 0)]
        keys = [(_from, _to, 0 if _id is None else _id)]  # the lanes' (from, to, id), for their rows
        if self.neighbour_vehicles_connected_lanes:
            for next_to, next_lanes in self.network.graph.get(_to, {}).items():
                if _id < len(next_lanes):
                    lanes_offsets.append((next_lanes[_id], lane.length))
                    keys.append((_to, next_to, _id))
                elif next_lanes:
                    lanes_offsets.append((next_lanes[0], lane.length))
                    keys.append((_to, next_to, 0))
            for prev_from, to_dict in self.network.graph.items():
                if _from in to_dict:
                    prev_lanes = to_dict[_from]
                    if _id < len(prev_lanes):
                        prev_id = _id
                    elif prev_lanes:
                        prev_id = 0
                    else:
                        continue
                    prev_lane = prev_lanes[prev_id]
                    lanes_offsets.append((prev_lane, -prev_lane.length))
                    keys.append((prev_from, _from, prev_id))

        boxes = self.network.boxes()
        if self._snapshot is None:
            entities = self.vehicles + self.objects
            maybe = boxes.maybe_on_lane(_positions(entities))
        else:
            entities, maybe = self._snapshot
        rows = [boxes.row[key] for key in keys]
        near = maybe[rows[0]] if len(rows) == 1 else maybe[rows].any(axis=0)

        for j in np.flatnonzero(near).tolist():
            v = entities[j]
            if v is vehicle or isinstance(v, Landmark):
                continue
            for search_lane, offset in lanes_offsets:
                s_v, lat_v = search_lane.local_coordinates(v.position)
                if not search_lane.on_lane(v.position, s_v, lat_v, margin=NEIGHBOUR_MARGIN):
                    continue
                s_v += offset
                if s <= s_v and (s_front is None or s_v <= s_front):
                    s_front = s_v
                    v_front = v
                if s_v < s and (s_rear is None or s_v > s_rear):
                    s_rear = s_v
                    v_rear = v
                break
        return v_front, v_rear

    def step(self, dt: float) -> None:
        """highway-env's `Road.step`: move every vehicle, then check collisions pair by pair in
        highway-env's order, only for the pairs that pass its spherical pre-check (the others are
        no-ops in `RoadObject.handle_collisions`)."""
        for vehicle in self.vehicles:
            vehicle.step(dt)
        movers, objects = self.vehicles, self.objects
        n = len(movers)
        if n == 0:
            return
        everyone = movers + objects
        pos = _positions(everyone)
        diagonal = np.array([o.diagonal for o in everyone], float)
        speed = np.array([v.speed for v in movers], float)
        dist = np.sqrt(((pos[:n, None, :] - pos[None, :, :]) ** 2).sum(axis=2))
        reach = (diagonal[:n, None] + diagonal[None, :]) / 2 + speed[:, None] * dt
        maybe = ~(dist > reach + SLACK)
        for i, vehicle in enumerate(movers):
            for j in np.flatnonzero(maybe[i, i + 1:]).tolist():
                vehicle.handle_collisions(everyone[i + 1 + j], dt)
            for j in np.flatnonzero(maybe[i, n:]).tolist():
                vehicle.handle_collisions(everyone[n + j], dt)


class HydraRegulatedRoad(RegulatedRoad, HydraRoad):
    """RegulatedRoad (junction right of way) on a HydraRoad, with `enforce_road_rules` predicting
    each vehicle's trajectory once per call instead of once per pair."""

    CONFLICT_TIMES = np.arange(0.25, 3, 0.25)
    """[s] `RegulatedRoad.is_conflict_possible`'s prediction times (horizon 3 s, step 0.25 s)."""

    def enforce_road_rules(self) -> None:
        """highway-env's `RegulatedRoad.enforce_road_rules`, same pairs in the same order."""
        for v in self.vehicles:
            if getattr(v, "is_yielding", False):
                if v.yield_timer >= self.YIELD_DURATION * self.REGULATION_FREQUENCY:
                    v.target_speed = v.lane.speed_limit
                    delattr(v, "color")
                    v.is_yielding = False
                else:
                    v.yield_timer += 1

        vehicles = self.vehicles
        n = len(vehicles)
        if n < 2:
            return
        predictions = [v.predict_trajectory_constant_speed(self.CONFLICT_TIMES) for v in vehicles]
        paths = np.array([p[0] for p in predictions], float).reshape(n, -1, 2)
        # closest approach of every pair over the horizon, against the first vehicle's length
        closest = np.sqrt(((paths[:, None] - paths[None, :]) ** 2).sum(axis=3)).min(axis=2)
        length = np.array([v.LENGTH for v in vehicles], float)
        maybe = ~(closest > length[:, None] + SLACK)
        for i in range(n - 1):
            for j in (np.flatnonzero(maybe[i, i + 1:]) + i + 1).tolist():
                if self._conflict(vehicles[i], vehicles[j], predictions[i], predictions[j]):
                    yielding_vehicle = self.respect_priorities(vehicles[i], vehicles[j])
                    if (
                        yielding_vehicle is not None
                        and isinstance(yielding_vehicle, ControlledVehicle)
                        and not isinstance(yielding_vehicle, MDPVehicle)
                    ):
                        yielding_vehicle.color = self.YIELDING_COLOR
                        yielding_vehicle.target_speed = 0
                        yielding_vehicle.is_yielding = True
                        yielding_vehicle.yield_timer = 0

    @staticmethod
    def _conflict(v1, v2, prediction_1, prediction_2) -> bool:
        """`RegulatedRoad.is_conflict_possible` on already predicted (positions, headings)."""
        positions_1, headings_1 = prediction_1
        positions_2, headings_2 = prediction_2
        for position_1, heading_1, position_2, heading_2 in zip(
            positions_1, headings_1, positions_2, headings_2, strict=False
        ):
            if np.linalg.norm(position_2 - position_1) > v1.LENGTH:
                continue
            if utils.rotated_rectangles_intersect(
                (position_1, 1.5 * v1.LENGTH, 0.9 * v1.WIDTH, heading_1),
                (position_2, 1.5 * v2.LENGTH, 0.9 * v2.WIDTH, heading_2),
            ):
                return True
        return False


_HYDRA_ROAD = {Road: HydraRoad, RegulatedRoad: HydraRegulatedRoad}


def hydra_road(road: Road) -> HydraRoad:
    """The Hydra counterpart of a freshly built highway-env road (no vehicles or objects yet): same
    network graph, random generator and options."""
    if road.vehicles or road.objects:
        raise ValueError("hydra_road: convert a road before vehicles are placed on it")
    network = HydraRoadNetwork()
    network.graph = road.network.graph
    return _HYDRA_ROAD[type(road)](
        network=network,
        np_random=road.np_random,
        record_history=road.record_history,
        neighbour_vehicles_connected_lanes=road.neighbour_vehicles_connected_lanes,
    )
