"""Pedestrians and groups of pedestrians walking on sidewalks and crossing at crosswalks.

Walkers follow sidewalk centre lines (`RoadGeometry.walk_paths`). Near a crosswalk a walker may
decide to cross; it waits until no vehicle is approaching within a gap-acceptance distance, then
walks across. While on the road it is a highway-env `Obstacle`, so IDM drivers brake for it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import shapely
from highway_env.vehicle.objects import Obstacle
from shapely.geometry import LineString, Point

from sim.actors import CLASS_ID, sample_size
from sim.world import Polyline, RoadGeometry, hw_to_world

WALK_SPEED = (1.0, 1.6)  # [m/s], adult walking speeds
GROUP_SPEED_FACTOR = 0.8
CROSS_PROBABILITY = 0.5  # chance to take a crosswalk when passing one
GAP_ACCEPT_M = 30.0  # no approaching vehicle closer than this to the crossing [m]
NEAR_CROSSING_M = 1.5


@dataclass
class Walker:
    actor_id: int
    cls_name: str
    size: np.ndarray
    members: int
    speed: float
    path: int  # index into walk_paths, or -1 while crossing
    s: float  # arc length on the current path [m]
    direction: int  # +1 / -1 along the path
    crossing: int = -1  # crosswalk index while waiting or crossing
    cross_s: float = 0.0
    cross_dir: int = 1
    waiting: bool = False
    cooldown: float = 0.0  # seconds before considering another crossing
    obstacle: object = None
    xy: np.ndarray = field(default_factory=lambda: np.zeros(2))
    heading: float = 0.0


class PedestrianModel:
    """All walkers of a sequence; `step(dt, road)` advances them, `actors_rows()` reports them."""

    def __init__(
        self,
        rng: np.random.Generator,
        geometry: RoadGeometry,
        count: int,
        group_share: float,
        first_id: int,
        near: np.ndarray,
        radius: float,
        keep_right_m: float = 0.5,
    ) -> None:
        self.rng = rng
        self.keep_right_m = keep_right_m  # walkers keep right of the path centre [m]
        self.geom = geometry
        self.paths = [LineString(p) for p in geometry.walk_paths]
        self.lines = [Polyline(shapely.get_coordinates(p)) for p in self.paths]  # point at a distance
        self.lengths = [p.length for p in self.paths]
        self.crossings = [np.asarray(c, float) for c in geometry.crossing_paths]
        self.crossing_ends = np.concatenate(self.crossings) if self.crossings else None  # (2C, 2)
        self.walkers: list[Walker] = []
        if not self.paths or count <= 0:
            return
        lengths = np.array([p.length for p in self.paths])
        # Spawn near the ego (within `radius`) so walkers are where the sensors look.
        candidates = []
        for i, p in enumerate(self.paths):
            s_all = np.arange(0.0, p.length, 2.0)
            q = shapely.get_coordinates(shapely.line_interpolate_point(p, s_all))
            close = np.linalg.norm(q - near, axis=1) < radius
            candidates += [(i, float(s)) for s in s_all[close]]
        if not candidates:
            candidates = [(int(np.argmax(lengths)), 0.0)]
        taken: list[tuple[np.ndarray, float]] = []  # (position, radius) of placed walkers
        next_id = first_id
        for _ in range(count):
            cls = "group_of_pedestrians" if rng.uniform() < group_share else "pedestrian"
            size = sample_size(rng, cls)
            members = int(rng.integers(2, 6)) if cls == "group_of_pedestrians" else 1
            speed = rng.uniform(*WALK_SPEED) * (GROUP_SPEED_FACTOR if members > 1 else 1.0)
            radius_w = float(np.hypot(size[0], size[1]) / 2)
            for _try in range(20):
                i, s = candidates[rng.integers(len(candidates))]
                s = float(np.clip(s + rng.uniform(-1, 1), 0, lengths[i]))
                w = Walker(next_id, cls, size, members, speed, i, s, int(rng.choice([-1, 1])))
                self._update_pose(w, 0.0)
                if all(np.linalg.norm(w.xy - q) > radius_w + r + 0.2 for q, r in taken):
                    break
            else:
                continue
            self.walkers.append(w)
            taken.append((w.xy, radius_w))
            next_id += 1
        self.next_id = next_id

    # --- motion ---------------------------------------------------------------------------
    def _update_pose(self, w: Walker, ds: float) -> None:
        if w.crossing >= 0 and not w.waiting:
            seg = self.crossings[w.crossing]
            a, b = (seg[0], seg[1]) if w.cross_dir > 0 else (seg[1], seg[0])
            d = b - a
            w.xy = a + d * (w.cross_s / np.linalg.norm(d))
            w.heading = float(np.arctan2(d[1], d[0]))
            return
        if w.crossing >= 0 and w.waiting:
            return
        line = self.lines[w.path]
        p0 = line.point(w.s)
        p1 = line.point(min(max(w.s + w.direction * 0.5, 0), self.lengths[w.path]))
        d = p1 - p0
        if np.linalg.norm(d) > 1e-6:
            w.heading = float(np.arctan2(d[1], d[0]))
        right = np.array([np.sin(w.heading), -np.cos(w.heading)])
        w.xy = p0 + right * self.keep_right_m

    def _vehicle_near(self, road, point: np.ndarray) -> bool:
        for v in road.vehicles:
            pos = hw_to_world(v.position)
            rel = point - pos
            dist = np.linalg.norm(rel)
            if dist < 6.0:
                return True
            if dist < GAP_ACCEPT_M:
                vel = hw_to_world(v.velocity)
                if np.dot(vel, rel) > 0:  # driving towards the crossing
                    return True
        return False

    def step(self, dt: float, road) -> None:
        for w in self.walkers:
            w.cooldown = max(0.0, w.cooldown - dt)
            if w.crossing >= 0:
                seg = self.crossings[w.crossing]
                if w.waiting:
                    mid = seg.mean(axis=0)
                    if not self._vehicle_near(road, mid):
                        w.waiting = False
                        w.cross_s = 0.0
                        self._add_obstacle(w, road)
                    continue
                w.cross_s += w.speed * dt
                length = float(np.linalg.norm(seg[1] - seg[0]))
                if w.cross_s >= length:
                    end = seg[1] if w.cross_dir > 0 else seg[0]
                    self._remove_obstacle(w, road)
                    w.crossing = -1
                    w.cooldown = 20.0
                    w.path, w.s = self._nearest_path(end)
                    w.direction = int(self.rng.choice([-1, 1]))
                self._update_pose(w, 0.0)
                self._sync_obstacle(w)
                continue
            length = self.lengths[w.path]
            w.s += w.direction * w.speed * dt
            if w.s <= 0.0 or w.s >= length:
                w.s = float(np.clip(w.s, 0.0, length))
                w.direction *= -1
            self._update_pose(w, 0.0)
            if w.cooldown <= 0.0 and self._near_a_crossing_end(w.xy):
                for k, seg in enumerate(self.crossings):
                    for end_idx in (0, 1):
                        if np.linalg.norm(w.xy - seg[end_idx]) < NEAR_CROSSING_M:
                            if self.rng.uniform() < CROSS_PROBABILITY:
                                w.crossing = k
                                w.cross_dir = 1 if end_idx == 0 else -1
                                w.waiting = True
                            w.cooldown = 10.0
                            break
                    if w.crossing >= 0:
                        break

    def _near_a_crossing_end(self, xy: np.ndarray) -> bool:
        """False when no crosswalk end can be within NEAR_CROSSING_M of `xy` (each coordinate
        differs by more; the 1e-9 m absorbs the rounding of the Euclidean distance)."""
        if self.crossing_ends is None:
            return False
        return bool((np.abs(self.crossing_ends - xy).max(axis=1) <= NEAR_CROSSING_M + 1e-9).any())

    def _nearest_path(self, xy: np.ndarray) -> tuple[int, float]:
        pt = Point(xy)
        dists = [p.distance(pt) for p in self.paths]
        i = int(np.argmin(dists))
        return i, float(self.paths[i].project(pt))

    # --- highway-env obstacles while on the road --------------------------------------------
    def _add_obstacle(self, w: Walker, road) -> None:
        hw = w.xy * np.array([1.0, -1.0])
        ob = Obstacle(road, hw, heading=-w.heading)
        ob.LENGTH, ob.WIDTH = float(w.size[0]), float(w.size[1])
        ob.diagonal = float(np.hypot(ob.LENGTH, ob.WIDTH))
        w.obstacle = ob
        road.objects.append(ob)

    def _sync_obstacle(self, w: Walker) -> None:
        if w.obstacle is not None:
            w.obstacle.position = w.xy * np.array([1.0, -1.0])
            w.obstacle.heading = -w.heading

    def _remove_obstacle(self, w: Walker, road) -> None:
        if w.obstacle is not None and w.obstacle in road.objects:
            road.objects.remove(w.obstacle)
        w.obstacle = None

    # --- reporting ----------------------------------------------------------------------------
    def rows(self) -> dict[str, np.ndarray]:
        n = len(self.walkers)
        out = {
            "ids": np.array([w.actor_id for w in self.walkers], np.int64),
            "classes": np.array([CLASS_ID[w.cls_name] for w in self.walkers], np.int64),
            "centers": np.zeros((n, 3)),
            "sizes": np.array([w.size for w in self.walkers]).reshape(n, 3),
            "yaws": np.array([w.heading for w in self.walkers], float),
            "velocities": np.zeros((n, 3)),
            "parked": np.zeros(n, bool),
            "members": np.array([w.members for w in self.walkers], np.int64),
        }
        for i, w in enumerate(self.walkers):
            out["centers"][i] = (w.xy[0], w.xy[1], w.size[2] / 2)
            moving = not (w.crossing >= 0 and w.waiting)
            if moving:
                sign = 1.0
                out["velocities"][i, :2] = sign * w.speed * np.array([np.cos(w.heading), np.sin(w.heading)])
        return out
