"""HDL-32E-like lidar: Embree ray casting, a physical return-power model, BEV and forward images.

Return model (clean air). A ray hits a Lambertian surface of NIR reflectance rho at range R and
incidence theta; the received power relative to a reference is

    P = rho * cos(theta) * (R_ref / R)^2                      (extended target, lidar equation)

and the return is detected when P >= P_min. P_min is set so a 10 % target at normal incidence is
detected out to 50 m (equivalently a 40 % target to 100 m, the HDL-32E's rated range), which also
makes dark road surfaces at grazing incidence fade with range as on real scans. The reported
intensity is P / P_sat clipped to 1 (P_sat: a white target at 5 m). Atmospheric attenuation
(fog, rain, snow) multiplies P by exp(-2 alpha R) in sensors.degrade.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from sensors import lidar_kernels, ray_kernels
from sensors.materials import NIR
from sensors.raycast import WorldCaster
from sensors.rig import LIDAR_MAX_RANGE_M, LIDAR_MIN_RANGE_M, Calibration, invert, transform_points

R_REF_M = 1.0
P_MIN = 0.10 / 50.0**2  # a 10 % target at 50 m
P_SAT = 1.0 / 5.0**2  # a white target at 5 m saturates the intensity
HEIGHT_RANGE_M = (-0.5, 3.5)  # BEV height channel span above the road [m]
FWD_DEPTH_MAX_M = 80.0


@dataclass
class LidarObservation:
    """One sweep on the (beam, azimuth) grid, lidar frame.

    Fields (all (32, A)):
        range: hit distance [m], inf for no surface within 100 m.
        power: received power relative to R_ref (see module docstring); 0 for no hit.
        instance: simulator actor id hit (0 = static world / nothing).
        material: material id hit.
        cos_incidence: cos of the angle between the ray and the surface normal.
        returned: bool, the return is detected (power >= P_MIN and range within 0.05-100 m).
    Extra returns that do not come from the first surface (fog backscatter, snow flakes) are in
    `extra_points` (K, 5): x, y, z [m] in the lidar frame, intensity, ring.
    """

    range: np.ndarray
    power: np.ndarray
    instance: np.ndarray
    material: np.ndarray
    cos_incidence: np.ndarray
    returned: np.ndarray
    extra_points: np.ndarray

    def copy(self) -> LidarObservation:
        return LidarObservation(*(np.copy(getattr(self, f)) for f in self.__dataclass_fields__))


def beam_directions(calib: Calibration) -> np.ndarray:
    """(32, A, 3) unit ray directions in the lidar frame; azimuth a * 360 / A deg ccw from +x."""
    return _beam_directions(tuple(calib.lidar_elevations_deg), calib.lidar_azimuth_steps).copy()


@lru_cache(maxsize=8)
def _beam_directions(elevations_deg: tuple[float, ...], azimuth_steps: int) -> np.ndarray:
    el = np.radians(np.array(elevations_deg))[:, None]
    az = 2 * np.pi * np.arange(azimuth_steps)[None, :] / azimuth_steps
    dirs = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) * np.ones_like(az)], -1)
    dirs.flags.writeable = False  # shared by every call
    return dirs


def detect(range_m: np.ndarray, power: np.ndarray) -> np.ndarray:
    return (power >= P_MIN) & (range_m >= LIDAR_MIN_RANGE_M) & (range_m <= LIDAR_MAX_RANGE_M)


def scan(caster: WorldCaster, calib: Calibration, world_from_ego: np.ndarray,
         actor_ids: np.ndarray, directions: np.ndarray | None = None) -> LidarObservation:
    """Cast the whole sweep at one instant (rolling-shutter motion is not modelled)."""
    dirs = beam_directions(calib) if directions is None else directions
    shape = dirs.shape[:2]
    world_from_lidar = world_from_ego @ calib.ego_from_lidar
    d_world = dirs.reshape(-1, 3) @ world_from_lidar[:3, :3].T
    hits = caster.cast(world_from_lidar[:3, 3], d_world, max_range=LIDAR_MAX_RANGE_M)
    rng = hits.range.reshape(shape)
    cos_i = hits.cos_incidence.reshape(shape)
    rho = NIR[hits.material].reshape(shape)
    with np.errstate(divide="ignore"):
        power = np.where(np.isfinite(rng), rho * cos_i * (R_REF_M / rng) ** 2, 0.0)
    ids = np.concatenate([[0], actor_ids])
    instance = ids[np.clip(hits.instance, 0, len(actor_ids))].reshape(shape)
    return LidarObservation(
        range=rng.astype(np.float32),
        power=power.astype(np.float32),
        instance=instance.astype(np.int64),
        material=hits.material.reshape(shape),
        cos_incidence=cos_i.astype(np.float32),
        returned=detect(rng, power),
        extra_points=np.zeros((0, 5), np.float32),
    )


def points(obs: LidarObservation, calib: Calibration) -> np.ndarray:
    """(N, 5) detected points in the lidar frame: x, y, z [m], intensity (0..1), ring (0..31)."""
    dirs = _beam_directions(tuple(calib.lidar_elevations_deg), calib.lidar_azimuth_steps)
    pts = ray_kernels.lidar_points(dirs, obs.range, obs.power, obs.returned, obs.power.dtype.type(P_SAT))
    if len(obs.extra_points):
        pts = np.vstack([pts, obs.extra_points.astype(np.float32)])
    return pts


def bev_image(pts: np.ndarray, calib: Calibration) -> np.ndarray:
    """(S, S, 3) uint8 BEV on the radar grid: max height above the road, log density, max intensity."""
    S = calib.bev_size_px
    xyz = transform_points(invert(calib.ego_from_radar) @ calib.ego_from_lidar, pts[:, :3])
    # per cell of the grid (lidar_kernels.bev_cells): uv = calib.radar_to_bev(xyz[:, :2]) floored;
    # the height above the road scaled to HEIGHT_RANGE_M and clipped to 0..1, its maximum; the
    # number of points; the maximum intensity
    height, count, inten = lidar_kernels.bev_cells(
        xyz, np.ascontiguousarray(pts[:, 3]), S, float(calib.bev_resolution_m), calib.radar_height_m,
        HEIGHT_RANGE_M[0], HEIGHT_RANGE_M[1] - HEIGHT_RANGE_M[0])
    density = np.log1p(np.arange(count.max() + 1)) / np.log(64.0)  # log density, 1 at 63 points
    return lidar_kernels.bev_pixels(height, count, density, inten, S)


def forward_image(pts: np.ndarray, calib: Calibration, camera: str = "camera_right") -> np.ndarray:
    """(H, W, 3) uint8 points projected into a camera (HydraFusion's forward lidar input):
    closeness 1 - depth / 80 m, intensity, height above the road / 4 m; nearest point wins."""
    cam = calib.camera(camera)
    ego = transform_points(calib.ego_from_lidar, pts[:, :3])
    uv, z = cam.project(ego)
    # points in front (z > 0.5 m) on the image (lidar_kernels.forward_pixels), drawn far first so
    # the nearest point of a pixel wins
    idx, u, v = lidar_kernels.forward_pixels(uv, z, cam.width, cam.height, 0.5)
    zz = z[idx]
    order = np.argsort(-zz)
    return lidar_kernels.forward_raster(order, u, v, zz, np.ascontiguousarray(pts[idx, 3]), ego[idx, 2], cam.width,
                                        cam.height, FWD_DEPTH_MAX_M)
