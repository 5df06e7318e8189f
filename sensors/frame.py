"""From a Scene to a Frame: every sensor, exact labels and the calibration.

`SequenceRenderer` holds what is built once per sequence (static mesh, Embree BVH, the pyrender
scene); `observe(scene, weather)` produces the raw observations of one moment (camera radiance with
depth and instance maps, the lidar sweep with per-ray power, the radar's polar power), which
weather degradations (sensors.degrade) act on; `finalize` turns them into the stored Frame.
The same scene can be observed under any WeatherState: clear and degraded twins of one moment.
"""

from __future__ import annotations

import time
from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np
import shapely

from sensors import camera as cam_mod
from sensors import lidar as lidar_mod
from sensors import radar as radar_mod
from sensors.labels import bev_labels, fwd_labels, object_labels
from sensors.raycast import WorldCaster
from sensors.rig import Calibration, SensorProfile, make_calibration
from sensors.world_mesh import MeshSoup, actors_mesh, lamp_heads, static_mesh
from sim.scenario import Scene, stream
from sim.weather import WeatherState, light_for

SENSOR_RANGE_M = 110.0


@dataclass
class Observations:
    """Raw observations of one moment (before the camera model and quantisation)."""

    camera_left: cam_mod.CameraObservation
    camera_right: cam_mod.CameraObservation
    lidar: lidar_mod.LidarObservation
    radar: radar_mod.RadarObservation
    weather: WeatherState
    actor_ids: np.ndarray


@dataclass
class Frame:
    """One stored frame. Arrays (profile sizes in DESIGN.md):

    camera_left, camera_right: (H, W, 3) uint8 sRGB.
    lidar_points: (N, 5) float32, lidar frame: x, y, z [m], intensity 0..1, ring 0..31.
    lidar_instance: (N,) int64 actor id each point hit (0 = static world / weather).
    lidar_bev: (S, S, 3) uint8 on the radar BEV grid: height, density, intensity.
    fwd_lidar: (H, W, 3) uint8 lidar projected into the right camera: closeness, intensity, height.
    radar_polar: (A, B) uint8, 0.5 dB per count (azimuth rows, range columns).
    radar_bev: (S, S) uint8 cartesian radar image, same scale.
    labels: {"camera_left": ..., "camera_right": ..., "bev": ..., "objects": ...} (sensors.labels:
        visible-pixel boxes per camera, BEV boxes, 3D boxes with their clean observability).
    meta: context, severity, timestamps, weather, light, degradation params, calibration.
    """

    camera_left: np.ndarray
    camera_right: np.ndarray
    lidar_points: np.ndarray
    lidar_instance: np.ndarray
    lidar_bev: np.ndarray
    fwd_lidar: np.ndarray
    radar_polar: np.ndarray
    radar_bev: np.ndarray
    labels: dict
    meta: dict
    observations: Observations | None = field(default=None, repr=False)


ARRAY_FIELDS = ("camera_left", "camera_right", "lidar_bev", "fwd_lidar", "radar_polar", "radar_bev")


class SequenceRenderer:
    """Sensors of one sequence. Build it from the sequence's first scene."""

    def __init__(self, scene: Scene, profile: SensorProfile, seed: int = 0,
                 ego_path: np.ndarray | None = None) -> None:
        """`ego_path` (N, 2): the ego's positions over the sequence; the static world is then built
        only within SENSOR_RANGE_M + 20 m of it (default: everything the simulator laid out)."""
        t0 = time.perf_counter()
        self.profile = profile
        self.calib: Calibration = make_calibration(profile)
        self.seed = int(seed)
        # instance indices are stable over the sequence: index k <-> self._ids[k] (0 = none)
        self._ids: list[int] = [0]
        self._index: dict[int, int] = {}
        focus = None
        if ego_path is not None:
            path = np.asarray(ego_path, float).reshape(-1, 2)
            geom = shapely.LineString(path) if len(path) > 1 and np.ptp(path, axis=0).max() > 0 else shapely.Point(path[0])
            focus = geom.buffer(SENSOR_RANGE_M + 20.0)
        world = static_mesh(scene, rng_seed=int(stream(self.seed, "static-mesh").integers(2**31)), focus=focus)
        # parked cars never move: they join the static meshes once, with their instance indices
        parked_soup, _ = actors_mesh(scene.actors[scene.actors.parked], index_of=self.index_of)
        self.static = MeshSoup.concat([world, parked_soup])
        self.caster = WorldCaster(self.static)
        self.stereo = cam_mod.StereoRenderer(self.static, profile.camera.width, profile.camera.height)
        self.lamps = lamp_heads(scene.structures)
        self.lidar_dirs = lidar_mod.beam_directions(self.calib)
        self.timings: dict[str, float] = defaultdict(float)
        self.frames_done = 0
        self.timings["setup"] += time.perf_counter() - t0
        self._actors_key, self.actors_soup = None, MeshSoup.empty()
        self._geometry_key, self._geometry = None, None

    def _tick(self, name: str, t0: float) -> float:
        t = time.perf_counter()
        self.timings[name] += t - t0
        return t

    def index_of(self, actor_id: int) -> int:
        """The sequence-stable instance index of an actor (assigned on first sight)."""
        if actor_id not in self._index:
            self._index[actor_id] = len(self._ids)
            self._ids.append(actor_id)
        return self._index[actor_id]

    def _set_actors(self, scene: Scene):
        """Mesh the moving actors of this frame; returns the index -> actor id table (without 0)."""
        key = (scene.sequence_id, scene.frame_index)
        if key != self._actors_key:
            moving = scene.actors[~scene.actors.parked]
            soup, _ = actors_mesh(moving, SENSOR_RANGE_M, scene.ego.position, index_of=self.index_of)
            self.caster.set_actors(soup)
            self.stereo.set_actors(soup)
            self.actors_soup = soup
            self._actors_key = key
        return np.array(self._ids[1:], np.int64)

    def observe(self, scene: Scene, weather: WeatherState | None = None, trace: dict | None = None) -> Observations:
        """Raw observations of `scene` under `weather` (default: the scene's own weather).

        `trace`: a dict that receives the intermediate products by stage (the actors' mesh, the
        cameras' code pass, the lidar and radar scans, the shaded cameras), for `sensors.stages`."""
        weather = scene.weather if weather is None else weather
        light = light_for(weather, scene.light.sun_azimuth_deg)
        t = time.perf_counter()
        ids = self._set_actors(scene)
        t = self._tick("actors_mesh", t)
        lighting = cam_mod.lighting_for(
            weather, light, self.lamps, cam_mod.headlights_of(scene.actors, scene.ego.pose, scene.ego.size)
        )
        key = (scene.sequence_id, scene.frame_index)
        if self._geometry_key != key:
            # what the weather does not touch: the cameras' code pass, the lidar sweep and the radar
            # scan (its speckle is drawn from the frame's own stream); another observation of the
            # same moment (the clear twin, the gallery's rows) reuses them, and every observation
            # gets its own copies (tests/sensors/test_observe.py)
            codes = {}
            for name in ("camera_left", "camera_right"):
                codes[name] = self.stereo.codes(self.calib.camera(name), scene.ego.pose)
                t = self._tick("camera_raster", t)
            lid = lidar_mod.scan(self.caster, self.calib, scene.ego.pose, ids, self.lidar_dirs)
            t = self._tick("lidar", t)
            rng = stream(self.seed, "radar", scene.frame_index)
            rad = radar_mod.scan(self.caster, self.calib, scene.ego.pose, ids, rng)
            t = self._tick("radar", t)
            self._geometry_key, self._geometry = key, (codes, lid, rad)
        codes, lid, rad = self._geometry
        if trace is not None:
            trace.update(actors_mesh=self.actors_soup, camera_raster=codes,
                         lidar_scan=lid, radar_scan=rad)
        cams = {}
        for name in ("camera_left", "camera_right"):
            index, material, depth = (a.copy() for a in codes[name])  # the observation owns its arrays
            cams[name] = cam_mod.shade(index, material, depth, self.calib.camera(name), scene.ego.pose, ids, lighting,
                                       self.caster)
            t = self._tick("camera_shading", t)
        if trace is not None:
            trace["camera_shading"] = cams
        return Observations(cams["camera_left"], cams["camera_right"], lid.copy(), rad.copy(), weather, ids)

    def finalize(self, scene: Scene, obs: Observations, degradation: dict | None = None,
                 keep_observations: bool = False, clean: Observations | None = None) -> Frame:
        """Camera model, lidar images, radar images, labels and metadata -> Frame.

        `clean`: the raw observations of the moment before degradation (default: `obs`); the 3D
        ground truth's observability (labels["objects"]) is measured on it."""
        t = time.perf_counter()
        images = {}
        for name in ("camera_left", "camera_right"):
            o = getattr(obs, name)
            img01 = cam_mod.expose(o) if o.exposure == 0.0 else cam_mod.expose(o, o.exposure)
            images[name] = cam_mod.to_uint8(img01)
        t = self._tick("camera_model", t)
        pts = lidar_mod.points(obs.lidar, self.calib)
        inst = obs.lidar.instance[obs.lidar.returned]
        inst = np.concatenate([inst, np.zeros(len(pts) - len(inst), np.int64)])
        lbev = lidar_mod.bev_image(pts, self.calib)
        fwd = lidar_mod.forward_image(pts, self.calib, "camera_right")
        t = self._tick("lidar_images", t)
        polar = radar_mod.to_counts(obs.radar.power)
        rbev = np.round(radar_mod.cartesian(polar.astype(np.float32), self.calib)).astype(np.uint8)
        t = self._tick("radar_images", t)
        geometry = {}  # the actors' boxes and sample points, shared by both cameras
        labels = {
            name: fwd_labels(getattr(obs, name).instance, getattr(obs, name).depth, scene.actors,
                             self.calib.camera(name), scene.ego.pose, geometry)
            for name in ("camera_left", "camera_right")
        }
        labels["bev"] = bev_labels(scene.actors, self.calib, scene.ego.pose, obs.lidar, obs.radar)
        labels["objects"] = object_labels(scene.actors, self.calib, scene.ego.pose, clean if clean is not None else obs)
        t = self._tick("labels", t)
        self.frames_done += 1
        meta = {
            "sequence_id": scene.sequence_id,
            "frame_index": scene.frame_index,
            "timestamp_s": round(scene.timestamp_s, 6),
            "context": scene.context.name,
            "layout": scene.context.layout,
            "conditions": list(scene.context.conditions),
            "severity": scene.severity,
            "weather": obs.weather.summary(),
            "light": {"sun_elevation_deg": round(light_for(obs.weather, scene.light.sun_azimuth_deg).sun_elevation_deg, 2),
                      "street_lamps_on": obs.weather.illuminance_lux < 50.0,
                      "headlights_on": obs.weather.illuminance_lux < 400.0},
            "exposure": {"camera_left": obs.camera_left.exposure, "camera_right": obs.camera_right.exposure},
            "camera_gain": {"camera_left": obs.camera_left.gain, "camera_right": obs.camera_right.gain},
            "degradation": degradation or {},
            "ego_pose": np.round(scene.ego.pose, 6).tolist(),
            "profile": self.profile.name,
            "calibration": self.calib.to_dict(),
        }
        return Frame(images["camera_left"], images["camera_right"], pts, inst, lbev, fwd, polar, rbev, labels, meta,
                     obs if keep_observations else None)
