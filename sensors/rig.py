"""Sensor profiles, the RADIATE-like rig, calibration records and coordinate transforms.

Frames (all right-handed, metres):
- ego: origin on the ground under the ego's box centre, x forward, y left, z up.
- lidar / radar: x forward, y left, z up, at their mounting points.
- camera (optical): x right, y down, z forward (OpenCV); pixels (u right, v down), pixel centres at
  integer + 0.5.
- BEV image (radar cartesian, RADIATE convention): the radar at the image centre, forward up,
  left to the left: pixel (u, v) -> x_fwd = (H/2 - v) * res, y_left = (W/2 - u) * res, for
  continuous pixel coordinates (a pixel's centre is at u + 0.5). This is HydraFusion Appendix A
  Eq. 18 written for a radar frame whose x points forward.
- radar polar image: row a is azimuth phi = a * 360 / A degrees counter-clockwise from the radar's
  x axis, column b covers ranges [b, b + 1) * range_resolution.

Every transform takes the calibration of the frame (stored with every frame), never constants.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from sim.actors import CLASS_HEIGHT, CLASSES
from sim.config import load_yaml
from sim.errors import UserError

PROFILE_DIR = Path(__file__).resolve().parents[1] / "configs" / "profiles"

# HDL-32E: 32 beams from +10.67 to -30.67 deg in 1.33 deg steps (Velodyne datasheet).
HDL32E_ELEVATIONS_DEG = np.linspace(-30.67, 10.67, 32)
LIDAR_MAX_RANGE_M = 100.0
LIDAR_MIN_RANGE_M = 0.05
RADAR_BEAMWIDTH_DEG = 1.8  # Navtech CTS350-X azimuth beam width (one-way, -3 dB)

# Mounting points in the ego frame [m] (RADIATE rig: Navtech on the roof, the HDL-32E 0.6 m ahead
# of it and 0.25 m higher, the ZED at the front of the roof).
RADAR_MOUNT = (0.0, 0.0, 2.05)
LIDAR_MOUNT = (0.6, -0.12, 2.30)
CAMERA_MOUNT = (0.5, 0.0, 1.95)  # stereo pair centre; eyes at +- baseline / 2 along y


@dataclass(frozen=True)
class CameraSpec:
    width: int = 336  # [px]
    height: int = 188  # [px]
    focal_px: float = 168.94  # [px]
    baseline_m: float = 0.12  # [m]
    rate_hz: float = 15.0  # [Hz]


@dataclass(frozen=True)
class LidarSpec:
    azimuth_steps: int = 900
    rate_hz: float = 10.0  # [Hz]


@dataclass(frozen=True)
class RadarSpec:
    azimuths: int = 400
    range_bins: int = 288
    range_resolution_m: float = 0.3472  # [m]
    rate_hz: float = 4.0  # [Hz]


@dataclass(frozen=True)
class BevSpec:
    size_px: int = 256
    resolution_m: float = 0.4  # [m/px]


@dataclass(frozen=True)
class SensorProfile:
    """Resolutions of every sensor (configs/profiles/<name>.yaml)."""

    camera: CameraSpec = field(default_factory=CameraSpec)
    lidar: LidarSpec = field(default_factory=LidarSpec)
    radar: RadarSpec = field(default_factory=RadarSpec)
    bev: BevSpec = field(default_factory=BevSpec)
    name: str = "cpu"


def profile_names() -> list[str]:
    return sorted(p.stem for p in PROFILE_DIR.glob("*.yaml"))


def load_profile(name: str) -> SensorProfile:
    """The sensor profile `name` from configs/profiles (strict: unknown keys are errors)."""
    path = PROFILE_DIR / f"{name}.yaml"
    if not path.exists():
        raise UserError(f"unknown profile {name!r} (choose from: {', '.join(profile_names())})")
    prof = load_yaml(SensorProfile, path)
    return SensorProfile(prof.camera, prof.lidar, prof.radar, prof.bev, name=name)


# ---------------------------------------------------------------------------------------------
# transforms


def translation(x: float, y: float, z: float) -> np.ndarray:
    t = np.eye(4)
    t[:3, 3] = (x, y, z)
    return t


# camera optical axes expressed in the ego frame: x_cam = -y_ego, y_cam = -z_ego, z_cam = x_ego
EGO_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def transform_points(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to (N, 3) points."""
    pts = np.asarray(pts, float)
    return pts @ T[:3, :3].T + T[:3, 3]


def invert(T: np.ndarray) -> np.ndarray:
    inv = np.eye(4)
    inv[:3, :3] = T[:3, :3].T
    inv[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return inv


@dataclass(frozen=True)
class CameraCalibration:
    """One camera.

    Fields:
        width, height: image size [px].
        K: (3, 3) intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] [px].
        ego_from_camera: (4, 4) pose of the optical frame (x right, y down, z forward) in the ego frame.
    """

    width: int
    height: int
    K: np.ndarray
    ego_from_camera: np.ndarray

    @cached_property
    def camera_from_ego(self) -> np.ndarray:
        """(4, 4) inverse of ego_from_camera (computed once per calibration)."""
        return invert(self.ego_from_camera)

    @cached_property
    def _focal(self) -> np.ndarray:
        return np.array([self.K[0, 0], self.K[1, 1]])

    def project(self, pts_ego: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) ego points -> (N, 2) pixel coordinates and (N,) depth along the optical axis [m]."""
        p = transform_points(self.camera_from_ego, pts_ego)
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (p[:, :2] / z[:, None]) * self._focal + self.K[:2, 2]
        return uv, z

    def rays(self) -> np.ndarray:
        """(H, W, 3) unit ray directions in the optical frame through each pixel centre."""
        u = np.arange(self.width) + 0.5
        v = np.arange(self.height) + 0.5
        uu, vv = np.meshgrid(u, v)
        d = np.stack([(uu - self.K[0, 2]) / self.K[0, 0], (vv - self.K[1, 2]) / self.K[1, 1], np.ones_like(uu)], -1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def to_dict(self) -> dict:
        return {"width": self.width, "height": self.height, "K": self.K.tolist(),
                "ego_from_camera": self.ego_from_camera.tolist()}

    @staticmethod
    def from_dict(d: dict) -> CameraCalibration:
        return CameraCalibration(int(d["width"]), int(d["height"]), np.array(d["K"], float),
                                 np.array(d["ego_from_camera"], float))


@dataclass(frozen=True)
class Calibration:
    """Everything needed to relate the sensors, stored with every frame.

    Fields:
        camera_left, camera_right: CameraCalibration.
        ego_from_lidar, ego_from_radar: (4, 4) sensor poses in the ego frame.
        lidar_elevations_deg: (32,) beam elevations [deg]; lidar_azimuth_steps: rays per ring.
        radar_azimuths, radar_range_bins: polar image size; radar_range_resolution_m [m].
        bev_size_px, bev_resolution_m: BEV grid (radar frame at its centre, forward up) [px], [m/px].
    """

    camera_left: CameraCalibration
    camera_right: CameraCalibration
    ego_from_lidar: np.ndarray
    ego_from_radar: np.ndarray
    lidar_elevations_deg: np.ndarray
    lidar_azimuth_steps: int
    radar_azimuths: int
    radar_range_bins: int
    radar_range_resolution_m: float
    bev_size_px: int
    bev_resolution_m: float

    def camera(self, name: str) -> CameraCalibration:
        if name not in ("camera_left", "camera_right"):
            raise ValueError(f"camera must be camera_left or camera_right, got {name!r}")
        return getattr(self, name)

    # --- BEV grid (HydraFusion Appendix A, Eq. 18) --------------------------------------------
    def bev_to_radar(self, uv: np.ndarray) -> np.ndarray:
        """(N, 2) continuous BEV pixel coordinates (u, v) -> (N, 2) radar-frame (x fwd, y left) [m]."""
        uv = np.asarray(uv, float)
        half = self.bev_size_px / 2.0
        res = self.bev_resolution_m
        return np.column_stack([(half - uv[:, 1]) * res, (half - uv[:, 0]) * res])

    def radar_to_bev(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) radar-frame (x fwd, y left) [m] -> (N, 2) continuous BEV pixel (u, v)."""
        xy = np.asarray(xy, float)
        half = self.bev_size_px / 2.0
        res = self.bev_resolution_m
        return np.column_stack([half - xy[:, 1] / res, half - xy[:, 0] / res])

    @property
    def radar_height_m(self) -> float:
        return float(self.ego_from_radar[2, 3])

    def to_dict(self) -> dict:
        return {
            "camera_left": self.camera_left.to_dict(),
            "camera_right": self.camera_right.to_dict(),
            "ego_from_lidar": self.ego_from_lidar.tolist(),
            "ego_from_radar": self.ego_from_radar.tolist(),
            "lidar_elevations_deg": self.lidar_elevations_deg.tolist(),
            "lidar_azimuth_steps": self.lidar_azimuth_steps,
            "radar_azimuths": self.radar_azimuths,
            "radar_range_bins": self.radar_range_bins,
            "radar_range_resolution_m": self.radar_range_resolution_m,
            "bev_size_px": self.bev_size_px,
            "bev_resolution_m": self.bev_resolution_m,
        }

    @staticmethod
    def from_dict(d: dict) -> Calibration:
        return Calibration(
            camera_left=CameraCalibration.from_dict(d["camera_left"]),
            camera_right=CameraCalibration.from_dict(d["camera_right"]),
            ego_from_lidar=np.array(d["ego_from_lidar"], float),
            ego_from_radar=np.array(d["ego_from_radar"], float),
            lidar_elevations_deg=np.array(d["lidar_elevations_deg"], float),
            lidar_azimuth_steps=int(d["lidar_azimuth_steps"]),
            radar_azimuths=int(d["radar_azimuths"]),
            radar_range_bins=int(d["radar_range_bins"]),
            radar_range_resolution_m=float(d["radar_range_resolution_m"]),
            bev_size_px=int(d["bev_size_px"]),
            bev_resolution_m=float(d["bev_resolution_m"]),
        )


def make_calibration(profile: SensorProfile) -> Calibration:
    """The rig of a profile: ideal rectified stereo pair (same K, parallel axes) and roof sensors."""
    cam = profile.camera
    K = np.array([[cam.focal_px, 0.0, cam.width / 2.0], [0.0, cam.focal_px, cam.height / 2.0], [0.0, 0.0, 1.0]])

    def cam_pose(dy: float) -> np.ndarray:
        T = translation(CAMERA_MOUNT[0], CAMERA_MOUNT[1] + dy, CAMERA_MOUNT[2])
        T[:3, :3] = EGO_FROM_OPTICAL
        return T

    half_b = cam.baseline_m / 2.0
    return Calibration(
        camera_left=CameraCalibration(cam.width, cam.height, K.copy(), cam_pose(+half_b)),
        camera_right=CameraCalibration(cam.width, cam.height, K.copy(), cam_pose(-half_b)),
        ego_from_lidar=translation(*LIDAR_MOUNT),
        ego_from_radar=translation(*RADAR_MOUNT),
        lidar_elevations_deg=HDL32E_ELEVATIONS_DEG.copy(),
        lidar_azimuth_steps=profile.lidar.azimuth_steps,
        radar_azimuths=profile.radar.azimuths,
        radar_range_bins=profile.radar.range_bins,
        radar_range_resolution_m=profile.radar.range_resolution_m,
        bev_size_px=profile.bev.size_px,
        bev_resolution_m=profile.bev.resolution_m,
    )


# ---------------------------------------------------------------------------------------------
# box transforms between frames

_BOX_EDGES = np.array(
    [[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4], [0, 4], [1, 5], [2, 6], [3, 7]]
)


def project_box3d(corners_ego: np.ndarray, cam: CameraCalibration, near: float = 0.1,
                  clip: bool = True) -> np.ndarray | None:
    """Tight image box [x1, y1, x2, y2] of a 3D box's 8 corners (ego frame), clipped to the image.

    Edges crossing the camera's near plane are clipped there, so boxes partly behind the camera are
    handled exactly. Returns None when nothing of the box is in front of the camera or in the image.
    `clip=False`: the box on the unbounded image plane (for the share of it outside the image).
    """
    p = transform_points(invert(cam.ego_from_camera), corners_ego)
    pts = [p[i] for i in range(8) if p[i, 2] > near]
    for a, b in _BOX_EDGES:
        za, zb = p[a, 2] - near, p[b, 2] - near
        if za * zb < 0:
            t = za / (za - zb)
            pts.append(p[a] + t * (p[b] - p[a]))
    if not pts:
        return None
    q = np.array(pts)
    u = q[:, 0] / q[:, 2] * cam.K[0, 0] + cam.K[0, 2]
    v = q[:, 1] / q[:, 2] * cam.K[1, 1] + cam.K[1, 2]
    if not clip:
        return np.array([u.min(), v.min(), u.max(), v.max()])
    x1, x2 = np.clip([u.min(), u.max()], 0, cam.width)
    y1, y2 = np.clip([v.min(), v.max()], 0, cam.height)
    if x2 - x1 <= 0 or y2 - y1 <= 0:
        return None
    return np.array([x1, y1, x2, y2])


def class_height(label: int) -> float:
    """Average height [m] of RADIATE class id `label` (1..8), used by Appendix A."""
    if not 1 <= int(label) <= len(CLASSES):
        raise ValueError(f"label must be a class id in 1..{len(CLASSES)}, got {label}")
    return CLASS_HEIGHT[CLASSES[int(label) - 1]]


def bev_boxes_to_camera(
    boxes: np.ndarray, labels: np.ndarray, calib: Calibration, camera: str = "camera_right"
) -> tuple[np.ndarray, np.ndarray]:
    """Map axis-aligned BEV boxes to a camera image (HydraFusion Appendix A, Eq. 18-21).

    BEV pixel -> metric in the radar frame (Eq. 18) -> a 3D box from the ground (flat road at the
    radar's mounting height below it) up to the class's average height -> ego -> camera frame
    (Eq. 19, from the stored extrinsics) -> pixels through the intrinsics (Eq. 20-21).

    Args:
        boxes: (N, 4) [u1, v1, u2, v2] BEV pixels.
        labels: (N,) class ids 1..8.
        calib: the frame's Calibration.
        camera: "camera_right" (the fused reference frame) or "camera_left".
    Returns:
        (M, 4) camera boxes [x1, y1, x2, y2] px clipped to the image, and the (N,) bool mask of the
        input boxes that are visible in the camera (M = mask.sum()).
    """
    boxes = np.asarray(boxes, float).reshape(-1, 4)
    labels = np.asarray(labels).reshape(-1)
    if len(labels) != len(boxes):
        raise ValueError(f"labels has {len(labels)} entries for {len(boxes)} boxes")
    cam = calib.camera(camera)
    ground = -calib.radar_height_m  # z of the road in the radar frame
    out, keep = [], np.zeros(len(boxes), bool)
    for i, (b, lab) in enumerate(zip(boxes, labels)):
        corners_uv = np.array([[b[0], b[1]], [b[2], b[1]], [b[2], b[3]], [b[0], b[3]]])
        xy = calib.bev_to_radar(corners_uv)
        h = class_height(lab)
        bottom = np.column_stack([xy, np.full(4, ground)])
        top = np.column_stack([xy, np.full(4, ground + h)])
        corners = transform_points(calib.ego_from_radar, np.vstack([bottom, top]))
        box = project_box3d(corners, cam)
        if box is not None:
            out.append(box)
            keep[i] = True
    return (np.array(out).reshape(-1, 4), keep)


def camera_boxes_to_camera(
    boxes: np.ndarray, calib: Calibration, source: str = "camera_left", target: str = "camera_right"
) -> np.ndarray:
    """Map image boxes from one camera to the other through the flat-ground depth of their bottom edge.

    The bottom-centre pixel's ray meets the road plane (z_ego = 0) at the object's foot point; the
    box becomes a fronto-parallel rectangle at that depth, which is moved into the target camera
    with the extrinsics and projected. For the rectified pair this is the stereo disparity shift
    d = f b / Z. Boxes whose bottom edge is above the horizon (no ground intersection) keep their
    pixel coordinates.
    """
    boxes = np.asarray(boxes, float).reshape(-1, 4)
    src, dst = calib.camera(source), calib.camera(target)
    if len(boxes) == 0:
        return boxes.copy()
    K = src.K
    R, t = src.ego_from_camera[:3, :3], src.ego_from_camera[:3, 3]
    out = boxes.copy()
    for i, (x1, y1, x2, y2) in enumerate(boxes):
        ray = np.array([((x1 + x2) / 2 - K[0, 2]) / K[0, 0], (y2 - K[1, 2]) / K[1, 1], 1.0])
        d_ego = R @ ray
        if d_ego[2] >= -1e-6:
            continue  # ray does not reach the ground
        s = -t[2] / d_ego[2]  # depth along the optical axis (ray has z_cam = 1)
        corners_cam = np.array(
            [[(x - K[0, 2]) / K[0, 0] * s, (y - K[1, 2]) / K[1, 1] * s, s] for x, y in ((x1, y1), (x2, y2))]
        )
        ego_pts = transform_points(src.ego_from_camera, corners_cam)
        uv, z = dst.project(ego_pts)
        if np.all(z > 0):
            out[i] = [uv[0, 0], uv[0, 1], uv[1, 0], uv[1, 1]]
    return out
