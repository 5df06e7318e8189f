"""Scenario specs, contexts and the simulator that turns a spec into a sequence of Scenes.

Contexts: the eight names of RADIATE / HydraFusion Section 5.1 are four road layouts (city,
junction, motorway, rural) and four conditions (rain, fog, snow, night). A condition overlays a
layout; alone, it uses its default layout (`CONDITION_LAYOUT`). Combinations are written with
'+': ``city+night+rain`` (one layout, any conditions), each condition at the spec's severity.
"""

from __future__ import annotations

import hashlib
import math
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
from shapely.geometry import Point, box

from sim.actors import CLASS_ID, EGO_SIZE, Actors, box_corners_2d, boxes_overlap_2d, sample_size
from sim.errors import UserError
from sim.layouts import LAYOUTS, RETIRE_RADIUS_M, lanes_union_of
from sim.pedestrians import PedestrianModel
from sim.weather import (
    CONDITIONS,
    TRANSITIONS,
    Light,
    WeatherState,
    WeatherTrack,
    clear_like,
    light_for,
    sample_weather_and_twin,
)
from sim.world import RoadGeometry, Structures, extract_road, hw_to_world

LAYOUT_NAMES = ("city", "junction", "motorway", "rural")
CONTEXT_NAMES = LAYOUT_NAMES + CONDITIONS  # the eight contexts
# Default road layout under each condition (documented in the README).
CONDITION_LAYOUT = {"rain": "junction", "fog": "motorway", "snow": "rural", "night": "city"}
PROFILES = ("cpu", "paper")
WARMUP_DT = 0.2  # [s] integration step while traffic settles before the first frame
MAX_DT = 0.2  # [s] largest integration step during the recorded sequence (highway-fast-v0's 5 Hz)


def stream(seed: int, *keys: int | str) -> np.random.Generator:
    """A named, independent random stream derived from `seed` (numpy SeedSequence spawn keys).

    Each subsystem draws from its own stream (`stream(seed, "weather")`), so changing how many
    numbers one of them uses never changes what another one draws.
    """
    spawn_key = tuple(k if isinstance(k, int) else zlib.crc32(k.encode()) for k in keys)
    return np.random.default_rng(np.random.SeedSequence(entropy=seed, spawn_key=spawn_key))


@dataclass(frozen=True)
class Context:
    """A road layout plus zero or more conditions, e.g. Context("city", ("night", "rain"))."""

    layout: str
    conditions: tuple[str, ...] = ()

    @staticmethod
    def parse(text: str) -> Context:
        parts = [p.strip().lower() for p in str(text).split("+")]
        if not any(parts):
            raise UserError("empty context")
        if not all(parts):
            raise UserError(f"context {text!r} has a dangling '+' (combine names as in city+night+rain)")
        layouts = [p for p in parts if p in LAYOUT_NAMES]
        conds = [p for p in parts if p in CONDITIONS]
        unknown = [p for p in parts if p not in CONTEXT_NAMES]
        if unknown:
            raise UserError(
                f"unknown context {unknown[0]!r} (choose from: {', '.join(CONTEXT_NAMES)}, "
                "or combine one layout with conditions as in city+night+rain)"
            )
        if len(layouts) > 1:
            raise UserError(f"context {text!r} names two road layouts ({layouts[0]}, {layouts[1]})")
        if len(set(conds)) != len(conds):
            raise UserError(f"context {text!r} repeats a condition")
        layout = layouts[0] if layouts else CONDITION_LAYOUT[conds[0]]
        ordered = tuple(c for c in CONDITIONS if c in conds)
        return Context(layout, ordered)

    @property
    def name(self) -> str:
        """Canonical name: a single condition on its default layout is just the condition."""
        if len(self.conditions) == 1 and CONDITION_LAYOUT[self.conditions[0]] == self.layout:
            return self.conditions[0]
        return "+".join((self.layout,) + self.conditions)


MAX_FRAMES = 36_000
"""Most frames in one sequence (an hour at 10 Hz): the scenes of a sequence are held in memory."""
MAX_DURATION_S = 3600.0
"""Longest sequence [s] of simulated time: the road region grows with it, and each simulated second
costs about a second of CPU (measured: 200 s of city traffic took 165 s on one core)."""


@dataclass(frozen=True)
class ScenarioSpec:
    """What to simulate. Every field has a unit or a closed set of values.

    Fields:
        context: a context name or combination ("junction", "fog", "city+night+rain").
        severity: 0-5; applies to every condition of the context (0 = clear).
        seed: root seed; the same spec and seed give the same sequence.
        frames: number of recorded frames (>= 1).
        frame_rate_hz: recording rate [Hz] (default 10, the lidar's rate).
        profile: sensor profile name ("cpu" default, "paper" at RADIATE resolution).
        transition: weather along the sequence: none | onset | clearing | bank.
        warmup_s: traffic settling time before the first frame [s]; < 0 draws 1-6 s.
    """

    context: str = "city"
    severity: int = 0
    seed: int = 0
    frames: int = 20
    frame_rate_hz: float = 10.0
    profile: str = "cpu"
    transition: str = "none"
    warmup_s: float = -1.0

    def __post_init__(self) -> None:
        ctx = Context.parse(self.context)
        if isinstance(self.severity, bool) or not isinstance(self.severity, int | np.integer):
            raise UserError(f"severity must be an integer 0..5, got {self.severity!r}")
        if not 0 <= self.severity <= 5:
            raise UserError(f"severity must be 0..5, got {self.severity}")
        if self.severity > 0 and not ctx.conditions:
            raise UserError(
                f"context {self.context!r} is a road layout with no weather condition, so severity "
                f"{self.severity} means nothing; use severity 0 or add a condition "
                f"(e.g. {ctx.layout}+rain)"
            )
        if isinstance(self.frames, bool) or int(self.frames) != self.frames or self.frames < 1:
            raise UserError(f"frames must be a positive integer, got {self.frames!r}")
        if self.frames > MAX_FRAMES:
            raise UserError(f"frames must be <= {MAX_FRAMES} per sequence, got {self.frames}")
        if not (isinstance(self.seed, int | np.integer) and 0 <= self.seed < 2**63):
            raise UserError(f"seed must be a non-negative integer, got {self.seed!r}")
        if not (self.frame_rate_hz > 0 and math.isfinite(self.frame_rate_hz)):
            raise UserError(f"frame_rate_hz must be > 0, got {self.frame_rate_hz}")
        if self.frames / self.frame_rate_hz > MAX_DURATION_S:
            raise UserError(f"a sequence of {self.frames} frames at {self.frame_rate_hz:g} Hz lasts "
                            f"{self.frames / self.frame_rate_hz:g} s; the limit is {MAX_DURATION_S} s "
                            "(simulation costs about 1 s of CPU per simulated second)")
        if self.profile not in PROFILES:
            raise UserError(f"unknown profile {self.profile!r} (choose from: {', '.join(PROFILES)})")
        if self.transition not in TRANSITIONS:
            raise UserError(
                f"unknown weather transition {self.transition!r} (choose from: {', '.join(TRANSITIONS)})"
            )
        if self.transition != "none" and (self.severity == 0 or not set(ctx.conditions) - {"night"}):
            raise UserError("a weather transition needs rain, fog or snow at severity >= 1")

    @property
    def parsed_context(self) -> Context:
        return Context.parse(self.context)

    @property
    def duration_s(self) -> float:
        return self.frames / self.frame_rate_hz


@dataclass(frozen=True)
class EgoState:
    """The ego vehicle. The ego frame has its origin on the ground below the box centre,
    x forward, y left, z up.

    Fields:
        pose: (4, 4) world_from_ego transform.
        velocity: (3,) world-frame velocity [m/s].
        size: (3,) (length, width, height) [m].
    """

    pose: np.ndarray
    velocity: np.ndarray
    size: np.ndarray

    @property
    def position(self) -> np.ndarray:
        return self.pose[:3, 3]

    @property
    def yaw(self) -> float:
        return float(np.arctan2(self.pose[1, 0], self.pose[0, 0]))


def pose_from(x: float, y: float, yaw: float, z: float = 0.0) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    pose = np.eye(4)
    pose[:2, :2] = [[c, -s], [s, c]]
    pose[:3, 3] = (x, y, z)
    return pose


@dataclass(frozen=True)
class Scene:
    """Everything in the world at one time step.

    Fields:
        sequence_id: identifies the sequence (spec + seed hash).
        frame_index: 0-based index within the sequence.
        timestamp_s: time since the first frame [s].
        context: the Context (layout + conditions); severity: 0-5.
        ego: EgoState. actors: Actors (everyone else, parked cars included).
        road: RoadGeometry and structures: Structures (shared by the frames of a sequence).
        weather: WeatherState of this frame. light: Light of this frame.
    """

    sequence_id: str
    frame_index: int
    timestamp_s: float
    context: Context
    severity: int
    ego: EgoState
    actors: Actors
    road: RoadGeometry
    structures: Structures
    weather: WeatherState
    light: Light
    extra: dict = field(default_factory=dict, compare=False)

    def digest(self) -> str:
        """sha256 over everything that defines the scene (for determinism tests)."""
        h = hashlib.sha256()
        h.update(f"{self.sequence_id}|{self.frame_index}|{self.timestamp_s:.9f}|{self.context.name}|{self.severity}".encode())
        h.update(np.round(self.ego.pose, 9).tobytes())
        for name in Actors.__dataclass_fields__:
            arr = getattr(self.actors, name)
            h.update(np.round(arr, 9).tobytes() if arr.dtype.kind == "f" else arr.tobytes())
        h.update(self.road.fingerprint())
        h.update(self.structures.fingerprint())
        h.update(repr(self.weather).encode())
        h.update(repr(self.light).encode())
        return h.hexdigest()


class Simulator:
    """Builds one sequence from a ScenarioSpec; iterate `scenes()` for the frames.

    The road layout's highway-env traffic is advanced by `Road.act()` / `Road.step(dt)` directly
    (no gym observation or rendering), pedestrians by `PedestrianModel.step`.
    """

    def __init__(self, spec: ScenarioSpec) -> None:
        self.spec = spec
        self.context = spec.parsed_context
        seed = int(spec.seed)
        self.sequence_id = hashlib.sha256(
            f"{self.context.name}|{spec.severity}|{seed}|{spec.frames}|{spec.frame_rate_hz}|{spec.transition}".encode()
        ).hexdigest()[:16]
        self.rng_traffic = stream(seed, "traffic")
        self.rng_world = stream(seed, "world")
        self.rng_people = stream(seed, "pedestrians")
        rng_weather = stream(seed, "weather")

        target, twin = sample_weather_and_twin(rng_weather, self.context.conditions, spec.severity)
        # the clear-weather twin of every frame (generate --twins): only the condition differs
        self.twin_weather: WeatherState = twin
        self.sun_azimuth_deg = float(rng_weather.uniform(0, 360))
        kind = spec.transition
        duration = spec.duration_s
        start = float(rng_weather.uniform(0.15, 0.35)) * duration
        ramp = float(rng_weather.uniform(0.15, 0.3)) * duration
        self.weather = WeatherTrack(
            clear=clear_like(target), target=target, kind=kind, start_s=start, ramp_s=ramp,
            hold_s=max(0.0, duration - 2 * ramp - 2 * start),
        )

        self.layout = LAYOUTS.get(self.context.layout)()
        self.road, self.ego = self.layout.make_road(self.rng_traffic)
        self.warmup_s = spec.warmup_s if spec.warmup_s >= 0 else float(self.rng_traffic.uniform(1.0, 6.0))

        ego_xy = hw_to_world(self.ego.position)
        radius = self.layout.region_radius(self.warmup_s + duration)
        region = (ego_xy[0] - radius, ego_xy[1] - radius, ego_xy[0] + radius, ego_xy[1] + radius)
        L = self.layout
        self.geometry = extract_road(
            self.road.network,
            region,
            parking_width=L.parking_width,
            sidewalk_offset=L.sidewalk_offset,
            sidewalk_width=L.sidewalk_width,
            crossings=L.crossings(),
        )
        window = box(*region)
        self.structures = Structures.from_rows(L.structures(self.rng_world, self.geometry, window))
        self.parked = self._parked_cars()
        self._drop_overlapping_traffic()
        n_ped = int(self.rng_people.integers(L.pedestrians[0], L.pedestrians[1] + 1)) if L.pedestrians[1] else 0
        self.people = PedestrianModel(
            self.rng_people, self.geometry, n_ped, L.group_share, first_id=100_000,
            near=ego_xy, radius=70.0, keep_right_m=max(0.0, L.sidewalk_width / 2 - 0.7),
        )
        self.time = -self.warmup_s
        self._warm_up()

    # --- construction helpers ----------------------------------------------------------------
    def _parked_cars(self) -> Actors:
        slots = self.layout.parking_slots(self.rng_world, self.geometry, lanes_union_of(self.geometry))
        rows = []
        taken: list[np.ndarray] = []
        for x, y, yaw in slots:
            cls = "van" if self.rng_world.uniform() < 0.15 else "car"
            size = sample_size(self.rng_world, cls)
            corners = box_corners_2d(np.array([[x, y]]), size[None, :2], np.array([yaw]))[0]
            near = [t for t in taken if abs(t[0, 0] - x) < 10 and abs(t[0, 1] - y) < 10]
            if any(boxes_overlap_2d(corners, t) for t in near):
                continue
            taken.append(corners)
            rows.append((cls, x, y, yaw, size))
        n = len(rows)
        if n == 0:
            return Actors.empty()
        return Actors(
            ids=np.arange(200_000, 200_000 + n, dtype=np.int64),
            classes=np.array([CLASS_ID[r[0]] for r in rows], np.int64),
            centers=np.array([(r[1], r[2], r[4][2] / 2) for r in rows]),
            sizes=np.array([r[4] for r in rows]),
            yaws=np.array([r[3] for r in rows]),
            velocities=np.zeros((n, 3)),
            parked=np.ones(n, bool),
            members=np.ones(n, np.int64),
        )

    def _footprint(self, v) -> np.ndarray:
        xy = hw_to_world(v.position)
        return box_corners_2d(xy[None], np.array([[v.LENGTH, v.WIDTH]]), np.array([-v.heading]))[0]

    def _drop_overlapping_traffic(self) -> None:
        """Remove spawned vehicles whose 3D footprint overlaps another vehicle or a parked car."""
        kept, shapes = [], []
        parked = [c for c in self.parked.footprints()] if len(self.parked) else []
        order = [self.ego] + [v for v in self.road.vehicles if v is not self.ego]
        for v in order:
            fp = self._footprint(v)
            if v is not self.ego and any(boxes_overlap_2d(fp, s) for s in shapes + parked):
                continue
            kept.append(v)
            shapes.append(fp)
        self.road.vehicles = kept

    def _advance(self, dt: float) -> None:
        self.layout.spawn(self.rng_traffic, self.road, self.ego, dt)
        self.road.act()
        self.road.step(dt)
        self.people.step(dt, self.road)
        self._retire()
        self.time += dt

    def _retire(self) -> None:
        """Drop vehicles far from the ego or past the end of the network; stop the ego there."""
        net = self.road.network
        ego_pos = self.ego.position
        keep = []
        for v in self.road.vehicles:
            lane = v.lane
            s = lane.local_coordinates(v.position)[0] if lane is not None else 0.0
            at_end = lane is not None and not net.graph.get(v.lane_index[1]) and s > lane.length - 8.0
            if v is self.ego:
                if at_end:
                    v.target_speed = 0.0  # the map ends: the ego pulls up
                keep.append(v)
            elif np.linalg.norm(v.position - ego_pos) < RETIRE_RADIUS_M and not (at_end and s > lane.length - 2.0):
                keep.append(v)
        self.road.vehicles = keep

    def _warm_up(self) -> None:
        n = int(round(self.warmup_s / WARMUP_DT))
        for _ in range(n):
            self._advance(WARMUP_DT)
        self.time = 0.0

    # --- recording -----------------------------------------------------------------------------
    def _actors(self) -> Actors:
        vehicles = [v for v in self.road.vehicles if v is not self.ego]
        n = len(vehicles)
        moving = Actors(
            ids=np.array([v.actor_id for v in vehicles], np.int64),
            classes=np.array([CLASS_ID[v.cls_name] for v in vehicles], np.int64),
            centers=np.array(
                [(*hw_to_world(v.position), v.HEIGHT / 2) for v in vehicles], float
            ).reshape(n, 3),
            sizes=np.array([(v.LENGTH, v.WIDTH, v.HEIGHT) for v in vehicles], float).reshape(n, 3),
            yaws=np.array([-v.heading for v in vehicles], float),
            velocities=np.array(
                [(*hw_to_world(v.velocity), 0.0) for v in vehicles], float
            ).reshape(n, 3),
            parked=np.zeros(n, bool),
            members=np.ones(n, np.int64),
        )
        people = Actors(**self.people.rows())
        actors = Actors.concat([moving, people, self.parked])
        order = np.argsort(actors.ids, kind="stable")
        return actors[order]

    def _scene(self, index: int) -> Scene:
        xy = hw_to_world(self.ego.position)
        yaw = -self.ego.heading
        ego = EgoState(
            pose=pose_from(float(xy[0]), float(xy[1]), yaw),
            velocity=np.array([*hw_to_world(self.ego.velocity), 0.0]),
            size=np.array(EGO_SIZE, float),
        )
        t = index / self.spec.frame_rate_hz
        weather = self.weather.state_at(t)
        return Scene(
            sequence_id=self.sequence_id,
            frame_index=index,
            timestamp_s=t,
            context=self.context,
            severity=self.spec.severity,
            ego=ego,
            actors=self._actors(),
            road=self.geometry,
            structures=self.structures,
            weather=weather,
            light=light_for(weather, self.sun_azimuth_deg),
            extra={"weather_fraction": self.weather.fraction(t)},
        )

    def scenes(self) -> Iterator[Scene]:
        period = 1.0 / self.spec.frame_rate_hz
        sub = max(1, math.ceil(period / MAX_DT - 1e-9))
        for i in range(self.spec.frames):
            if i > 0:
                for _ in range(sub):
                    self._advance(period / sub)
            yield self._scene(i)


def simulate(spec: ScenarioSpec) -> list[Scene]:
    """All frames of a spec (see `Simulator` for streaming)."""
    return list(Simulator(spec).scenes())


def point_in_region(scene: Scene, xy: np.ndarray) -> bool:
    return box(*scene.road.region).contains(Point(xy))
