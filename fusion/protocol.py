"""Evaluation protocols: what counts as an object to find. A result without its protocol is not a
result (nuScenes names and versions its detection configs the same way).

- `reference` (default for fusion studies): world truth in each camera. Every actor in front of the
  camera within `r_max` of the radar that at least one sensor observes in the clean render, as the
  bounding rectangle of its projected 3D box (`sensors.labels.reference_labels`): RADIATE's radar
  annotations projected into the camera (HydraFusion 5.2.3, Appendix A). Difficult (ignored) only
  when no sensor observes it or its projected box is mostly outside the image. BEV branches train
  and are scored (natively) on the BEV boxes with the same rule (`reference_bev_labels`).
- `visible`: what a camera can see: the tight box of the visible pixels, difficult when under 8 px
  tall at 188 rows, > 80 % occluded or > 60 % truncated; BEV boxes difficult when the *degraded*
  lidar and radar missed them (the rule of dataset format 1).
- `bev`: each BEV branch against the BEV boxes on its own grid, RADIATE's native radar metric;
  labels as `reference` (camera-view branches still train on the reference boxes).

`r_max` defaults to the BEV grid's forward extent (`bev_size_px * bev_resolution_m / 2`: 51.2 m at
the `cpu` profile, 100 m at `paper`), so camera-frame and BEV ground truth cover the same objects.
Range bins (RANGE_BINS) split every mAP by the objects' range from the radar.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PROTOCOLS = ("reference", "visible", "bev")
DEFAULT_PROTOCOL = "reference"
PROTOCOL_VERSION = 1
RANGE_BINS = (0.0, 15.0, 30.0, 50.0, 100.0)  # [m], objects' range from the radar


@dataclass(frozen=True)
class Protocol:
    """A named evaluation protocol.

    Fields:
        name: reference | visible | bev.
        r_max_m: objects farther than this from the radar are not to be found [m]; None = the BEV
            grid's forward extent of each frame's calibration.
    """

    name: str = DEFAULT_PROTOCOL
    r_max_m: float | None = None

    def __post_init__(self) -> None:
        if self.name not in PROTOCOLS:
            raise ValueError(f"unknown protocol {self.name!r} (choose from: {', '.join(PROTOCOLS)})")
        if self.r_max_m is not None and not self.r_max_m > 0:
            raise ValueError(f"r_max_m must be > 0 m, got {self.r_max_m}")

    def r_max(self, calibration: dict) -> float:
        if self.r_max_m is not None:
            return float(self.r_max_m)
        return default_r_max(calibration)

    def describe(self) -> dict:
        return {"name": self.name, "version": PROTOCOL_VERSION, "r_max_m": self.r_max_m,
                "range_bins_m": list(RANGE_BINS)}


def default_r_max(calibration: dict) -> float:
    """The BEV grid's forward extent [m] (HydraFusion Appendix A grid)."""
    return float(calibration["bev_size_px"]) * float(calibration["bev_resolution_m"]) / 2.0


def as_protocol(protocol: Protocol | str | None) -> Protocol:
    if protocol is None:
        return Protocol("visible")
    return protocol if isinstance(protocol, Protocol) else Protocol(str(protocol))


def _bev_distances(lab: dict, calibration: dict) -> list[float]:
    from sensors.rig import Calibration

    centres = np.array(lab["boxes"], float).reshape(-1, 4) @ np.array([[.5, 0], [0, .5], [.5, 0], [0, .5]])
    xy = Calibration.from_dict(calibration).bev_to_radar(centres)
    return np.hypot(xy[:, 0], xy[:, 1]).tolist()


def frame_labels(labels: dict, meta: dict, protocol: Protocol | str | None) -> dict:
    """One frame's ground truth under `protocol`: {"camera_left", "camera_right", "bev"}, each
    columnar with at least ids, labels, boxes, difficult and distance_m (range bins)."""
    from sensors.labels import reference_bev_labels, reference_labels
    from sensors.rig import Calibration

    p = as_protocol(protocol)
    if p.name == "visible":
        bev = labels["bev"]
        if "distance_m" not in bev:
            bev = {**bev, "distance_m": _bev_distances(bev, meta["calibration"])}
        return {"camera_left": labels["camera_left"], "camera_right": labels["camera_right"], "bev": bev}
    if "objects" not in labels:
        raise ValueError("the frame has no 3D ground truth (labels['objects']); protocol "
                         f"{p.name!r} needs a dataset of format 2")
    r_max = p.r_max(meta["calibration"])
    calib = Calibration.from_dict(meta["calibration"])
    objects = labels["objects"]
    return {"camera_left": reference_labels(objects, calib, "camera_left", r_max),
            "camera_right": reference_labels(objects, calib, "camera_right", r_max),
            "bev": reference_bev_labels(labels["bev"], objects, r_max)}


def range_bin_names(edges=RANGE_BINS) -> list[str]:
    return [f"{lo:g}-{hi:g}" for lo, hi in zip(edges[:-1], edges[1:])]


def detection_ranges(boxes: np.ndarray, frame: str, calibration: dict) -> np.ndarray:
    """(N,) estimated range from the radar [m] of detections in `frame`, to bin them by range as
    their ground truth is binned (nuScenes filters predictions by their own distance the same way).

    BEV boxes: the box centre on the Appendix A grid. Camera boxes: the flat-ground range of the
    bottom-centre pixel (its ray meets the road, z_ego = 0, at the object's foot point); a box whose
    bottom edge is at or above the horizon gets inf (it is in no bin).
    """
    from sensors.rig import Calibration, transform_points

    boxes = np.asarray(boxes, float).reshape(-1, 4)
    calib = Calibration.from_dict(calibration)
    if len(boxes) == 0:
        return np.zeros(0)
    if frame == "bev":
        centres = np.column_stack([(boxes[:, 0] + boxes[:, 2]) / 2, (boxes[:, 1] + boxes[:, 3]) / 2])
        xy = calib.bev_to_radar(centres)
        return np.hypot(xy[:, 0], xy[:, 1])
    cam = calib.camera(frame)
    K, R, t = cam.K, cam.ego_from_camera[:3, :3], cam.ego_from_camera[:3, 3]
    rays = np.column_stack([((boxes[:, 0] + boxes[:, 2]) / 2 - K[0, 2]) / K[0, 0],
                            (boxes[:, 3] - K[1, 2]) / K[1, 1], np.ones(len(boxes))])
    d_ego = rays @ R.T
    out = np.full(len(boxes), np.inf)
    down = d_ego[:, 2] < -1e-9
    s = -t[2] / d_ego[down, 2]
    foot = t + s[:, None] * d_ego[down]
    radar_xy = transform_points(np.linalg.inv(calib.ego_from_radar), foot)[:, :2]
    out[down] = np.hypot(radar_xy[:, 0], radar_xy[:, 1])
    return out
