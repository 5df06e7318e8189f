"""Exact ground truth: FWD boxes per camera and BEV boxes on the radar/lidar grid.

FWD (per camera): the tight box of the object's *visible* pixels in the instance map, so occlusion
comes from the segmentation and truncation from the image border. For each box we also report
- occlusion: the share of the object's mesh sample points that are in the image but hidden by
  something else (depth-buffer test; self-occlusion does not count),
- truncation: 1 - (area of the projected 3D box inside the image) / (its full area),
- difficult: boxes a detector at this resolution cannot be expected to find (too small, mostly
  hidden or cut). VOC AP ignores difficult boxes (PASCAL VOC convention); every table says so.

BEV: every actor whose footprint centre lies on the BEV grid: the rotated box (cx, cy, length,
width, angle; pixels, angle counter-clockwise from the image's up = forward axis) and its
axis-aligned bounding box clipped to the image; `lidar_points` and `radar_visible` record whether
the active sensors saw it; it is difficult when neither did or when it is under 3 px.
"""

from __future__ import annotations

import numpy as np

from sensors.label_kernels import instance_boxes, visible_samples
from sensors.rig import Calibration, CameraCalibration, invert, transform_points
from sensors.world_mesh import class_template
from sim.actors import CLASSES, box_corners_2d

MIN_VISIBLE_PX = 6
DIFFICULT_HEIGHT_PX_AT_188 = 8.0  # boxes shorter than this at 188 rows are difficult (scaled by H)
DIFFICULT_OCCLUSION = 0.8
DIFFICULT_TRUNCATION = 0.6
BEV_MIN_SIZE_PX = 3.0


def _corners3d(center: np.ndarray, size: np.ndarray, yaw: float) -> np.ndarray:
    """(8, 3) corners of an actor box (bottom 4 then top 4), world frame."""
    xy = box_corners_2d(center[None, :2], size[None, :2], np.array([yaw]))[0]
    z0, z1 = center[2] - size[2] / 2, center[2] + size[2] / 2
    return np.vstack([np.column_stack([xy, np.full(4, z0)]), np.column_stack([xy, np.full(4, z1)])])


def _projected_area(corners_ego: np.ndarray, cam: CameraCalibration) -> tuple[float, float]:
    """(full area, area inside the image) of the projected 3D box [px^2] (points in front only)."""
    uv, z = cam.project(corners_ego)
    front = z > 0.1
    if front.sum() < 2:
        return 0.0, 0.0
    u, v = uv[front, 0], uv[front, 1]
    full = (u.max() - u.min()) * (v.max() - v.min())
    cu = np.clip([u.min(), u.max()], 0, cam.width)
    cv = np.clip([v.min(), v.max()], 0, cam.height)
    inside = max(0.0, cu[1] - cu[0]) * max(0.0, cv[1] - cv[0])
    return float(full), float(inside)


def _sample_points(cls: str, center, size, yaw) -> np.ndarray:
    if cls == "group_of_pedestrians":
        tpl = class_template("pedestrian")
        # the group's members are not needed for a visibility estimate: sample the box volume
        g = np.stack(np.meshgrid(np.linspace(-0.4, 0.4, 4), np.linspace(-0.4, 0.4, 4), np.linspace(0.1, 0.9, 4)), -1)
        v = g.reshape(-1, 3)
        del tpl
    else:
        v = class_template(cls).vertices
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    return (v * size) @ R.T + (center - np.array([0, 0, size[2] / 2]))


def fwd_labels(instance: np.ndarray, depth: np.ndarray, actors, cam: CameraCalibration,
               world_from_ego: np.ndarray, geometry: dict | None = None) -> dict:
    """Ground-truth boxes of one camera. Returns columnar lists (JSON-ready):
    ids, labels (class ids 1..8), boxes [x1, y1, x2, y2] px, visible_px, occlusion, truncation,
    distance_m (camera to box centre), difficult (bool).

    `geometry`: a dict shared by the calls for the cameras of one moment (same actors and pose);
    each actor's box corners and mesh sample points in the ego frame are computed once into it."""
    H = instance.shape[0]
    out = {k: [] for k in ("ids", "labels", "boxes", "visible_px", "occlusion", "truncation", "distance_m", "difficult")}
    ids, counts = np.unique(instance[instance > 0], return_counts=True)
    if len(ids) == 0:
        return out
    boxes = instance_boxes(instance, ids).tolist()  # [row0, col0, row1, col1) of each id
    row_of = {int(a): i for i, a in enumerate(actors.ids)}
    ego_from_world = invert(world_from_ego)
    names = actors.class_names()
    min_h = DIFFICULT_HEIGHT_PX_AT_188 * H / 188.0
    cam_from_world = invert(world_from_ego @ cam.ego_from_camera)
    geometry = {} if geometry is None else geometry
    for actor_id, count, (r0, c0, r1, c1) in zip(ids.tolist(), counts.tolist(), boxes):
        if count < MIN_VISIBLE_PX or actor_id not in row_of:
            continue
        i = row_of[actor_id]
        box = [float(c0), float(r0), float(c1), float(r1)]
        center = actors.centers[i]
        if i not in geometry:
            size, yaw = actors.sizes[i], float(actors.yaws[i])
            geometry[i] = (transform_points(ego_from_world, _corners3d(center, size, yaw)),
                           transform_points(ego_from_world, _sample_points(names[i], center, size, yaw)))
        corners_ego, pts = geometry[i]
        full, inside = _projected_area(corners_ego, cam)
        truncation = 1.0 - inside / full if full > 0 else 1.0
        # sample points in the image (z > 0.3 m), seen when the pixel shows the actor or nothing
        # nearer than the point by more than 0.3 m + 2 % (label_kernels.visible_samples)
        uv, z = cam.project(pts)
        n_in, n_seen = visible_samples(uv, z, instance, depth, actor_id, 0.3)
        occlusion = 1.0 - n_seen / n_in if n_in else 1.0
        dist = float(np.linalg.norm(transform_points(cam_from_world, center[None])[0]))
        difficult = (box[3] - box[1] < min_h) or occlusion > DIFFICULT_OCCLUSION or truncation > DIFFICULT_TRUNCATION
        out["ids"].append(int(actor_id))
        out["labels"].append(int(actors.classes[i]))
        out["boxes"].append([round(b, 2) for b in box])
        out["visible_px"].append(int(count))
        out["occlusion"].append(round(occlusion, 3))
        out["truncation"].append(round(max(0.0, truncation), 3))
        out["distance_m"].append(round(dist, 2))
        out["difficult"].append(bool(difficult))
    return out


def bev_labels(actors, calib: Calibration, world_from_ego: np.ndarray, lidar_obs=None, radar_obs=None) -> dict:
    """BEV ground truth on the radar grid (see module docstring). Columnar, JSON-ready."""
    out = {k: [] for k in ("ids", "labels", "boxes", "rotated", "lidar_points", "radar_visible", "difficult")}
    if len(actors) == 0:
        return out
    S = calib.bev_size_px
    res = calib.bev_resolution_m
    radar_from_world = invert(world_from_ego @ calib.ego_from_radar)
    centers = transform_points(radar_from_world, actors.centers)
    ego_yaw = np.arctan2(world_from_ego[1, 0], world_from_ego[0, 0])
    yaws = actors.yaws - ego_yaw
    uv_c = calib.radar_to_bev(centers[:, :2])
    on = (uv_c[:, 0] >= 0) & (uv_c[:, 0] < S) & (uv_c[:, 1] >= 0) & (uv_c[:, 1] < S)
    lid_counts: dict[int, int] = {}
    if lidar_obs is not None:
        ids, cnt = np.unique(lidar_obs.instance[lidar_obs.returned & (lidar_obs.instance > 0)], return_counts=True)
        lid_counts = dict(zip(ids.tolist(), cnt.tolist()))
    radar_seen: set[int] = set()
    if radar_obs is not None:
        strong = (radar_obs.instance > 0) & (radar_obs.signal > 3.0 * radar_obs.noise.mean())
        radar_seen = set(np.unique(radar_obs.instance[strong]).tolist())
    rows = np.flatnonzero(on)
    # the axis-aligned boxes of all rotated footprints at once (row by row the same arithmetic)
    corners = box_corners_2d(centers[rows, :2], actors.sizes[rows, :2], yaws[rows])
    uv = calib.radar_to_bev(corners.reshape(-1, 2)).reshape(-1, 4, 2)
    lo, hi = np.clip(uv.min(axis=1), 0, S), np.clip(uv.max(axis=1), 0, S)
    for i, (x1, y1), (x2, y2) in zip(rows.tolist(), lo.tolist(), hi.tolist()):
        if x2 - x1 <= 0 or y2 - y1 <= 0:
            continue
        aid = int(actors.ids[i])
        n_lidar = int(lid_counts.get(aid, 0))
        r_vis = aid in radar_seen
        length_px, width_px = actors.sizes[i, 0] / res, actors.sizes[i, 1] / res
        small = max(x2 - x1, y2 - y1) < BEV_MIN_SIZE_PX
        out["ids"].append(aid)
        out["labels"].append(int(actors.classes[i]))
        out["boxes"].append([round(x1, 2), round(y1, 2), round(x2, 2), round(y2, 2)])
        out["rotated"].append([round(float(uv_c[i, 0]), 2), round(float(uv_c[i, 1]), 2), round(float(length_px), 2),
                               round(float(width_px), 2), round(float(np.arctan2(np.sin(yaws[i]), np.cos(yaws[i]))), 4)])
        out["lidar_points"].append(n_lidar)
        out["radar_visible"].append(bool(r_vis))
        out["difficult"].append(bool((n_lidar == 0 and not r_vis) or small))
    return out





# --- 3D ground truth (world truth, nuScenes / KITTI style) ---------------------------------------
# Stored per frame under labels["objects"] (dataset format 2). Observability comes from the *clean*
# render (before weather and faults), like nuScenes' num_lidar_pts / num_radar_pts: what a sensor
# could see of the object, not what the weather left of it, so the ground truth of a frame does not
# change with the condition being studied.
OBJECT_FIELDS = ("ids", "labels", "center", "size", "yaw", "velocity", "range_m", "camera_left_px",
                 "camera_right_px", "lidar_points", "radar_cells", "observed")
MIN_LIDAR_POINTS = 1  # nuScenes keeps boxes with >= 1 lidar or radar point
MIN_RADAR_CELLS = 1
RADAR_CELL_SNR = 3.0  # a radar cell "sees" an object when its power exceeds 3x the mean noise


def object_labels(actors, calib: Calibration, world_from_ego: np.ndarray, clean) -> dict:
    """Every actor within the active sensors' range (the radar's range bins x resolution, 100 m for
    RADIATE's rig) as a 3D box in the ego frame, with its observability in the clean render.

    `clean`: the raw Observations of the moment (sensors.frame.Observations, before degradation).
    Columnar, JSON-ready (OBJECT_FIELDS):
        ids (N,) actor ids; labels (N,) class ids 1..8;
        center (N, 3) box centre, ego frame (x forward, y left, z up) [m];
        size (N, 3) length, width, height [m]; yaw (N,) heading in the ego frame, counter-clockwise
        from +x [rad]; velocity (N, 3) velocity over ground in ego-frame axes [m/s];
        range_m (N,) horizontal distance of the centre from the radar / lidar mast [m];
        camera_left_px, camera_right_px (N,) visible pixels in each camera's clean render;
        lidar_points (N,) clean lidar returns on the object; radar_cells (N,) clean polar radar
        cells it dominates at >= RADAR_CELL_SNR x the noise;
        observed (N,) bool: some sensor sees it (>= MIN_VISIBLE_PX pixels in a camera, >=
        MIN_LIDAR_POINTS returns or >= MIN_RADAR_CELLS cells).
    """
    out = {k: [] for k in OBJECT_FIELDS}
    if len(actors) == 0:
        return out
    max_range = calib.radar_range_bins * calib.radar_range_resolution_m
    ego_from_world = invert(world_from_ego)
    centers = transform_points(ego_from_world, actors.centers)
    radar_xy = transform_points(invert(calib.ego_from_radar), centers)[:, :2]
    ranges = np.hypot(radar_xy[:, 0], radar_xy[:, 1])
    ego_yaw = np.arctan2(world_from_ego[1, 0], world_from_ego[0, 0])
    R = world_from_ego[:3, :3]
    velocities = actors.velocities @ R  # R^T v: world velocity in ego axes

    def counts(instance: np.ndarray) -> dict[int, int]:
        ids, cnt = np.unique(instance[instance > 0], return_counts=True)
        return dict(zip(ids.tolist(), cnt.tolist()))

    px = {name: counts(getattr(clean, name).instance) for name in ("camera_left", "camera_right")}
    lid = clean.lidar
    lidar_pts = counts(np.where(lid.returned, lid.instance, 0))
    rad = clean.radar
    radar_cells = counts(np.where(rad.signal > RADAR_CELL_SNR * rad.noise.mean(), rad.instance, 0))
    for i in np.flatnonzero(ranges <= max_range):
        aid = int(actors.ids[i])
        n_left, n_right = px["camera_left"].get(aid, 0), px["camera_right"].get(aid, 0)
        n_lidar, n_radar = lidar_pts.get(aid, 0), radar_cells.get(aid, 0)
        yaw = float(actors.yaws[i] - ego_yaw)
        out["ids"].append(aid)
        out["labels"].append(int(actors.classes[i]))
        out["center"].append([round(float(v), 4) for v in centers[i]])
        out["size"].append([round(float(v), 4) for v in actors.sizes[i]])
        out["yaw"].append(round(float(np.arctan2(np.sin(yaw), np.cos(yaw))), 5))
        out["velocity"].append([round(float(v), 4) for v in velocities[i]])
        out["range_m"].append(round(float(ranges[i]), 3))
        out["camera_left_px"].append(int(n_left))
        out["camera_right_px"].append(int(n_right))
        out["lidar_points"].append(int(n_lidar))
        out["radar_cells"].append(int(n_radar))
        out["observed"].append(bool(max(n_left, n_right) >= MIN_VISIBLE_PX or n_lidar >= MIN_LIDAR_POINTS
                                    or n_radar >= MIN_RADAR_CELLS))
    return out


# A reference box is difficult when more than this share of its projected 3D box is outside the image.
REFERENCE_MAX_OUTSIDE = 0.5


def reference_labels(objects: dict, calib: Calibration, camera: str, r_max: float) -> dict:
    """World-truth boxes in one camera (the `reference` evaluation protocol, fusion.protocol): the
    bounding rectangle of each object's projected 3D box (8 corners, near-plane clipped), clipped
    to the image, for every object whose centre is in front of the camera and within `r_max` [m] of
    the radar (horizontal range); RADIATE's radar annotations projected into the camera (HydraFusion
    5.2.3, Appendix A), with the true height and position instead of class averages.

    difficult: no sensor observes the object in the clean render, or more than
    REFERENCE_MAX_OUTSIDE of its projected box lies outside the image. Columnar: ids, labels, boxes
    [x1, y1, x2, y2] px, truncation, distance_m (= range_m), observed, difficult.
    """
    from sensors.rig import project_box3d

    cam = calib.camera(camera)
    out = {k: [] for k in ("ids", "labels", "boxes", "truncation", "distance_m", "observed", "difficult")}
    for k, aid in enumerate(objects["ids"]):
        rng = float(objects["range_m"][k])
        if rng > r_max:
            continue
        center = np.asarray(objects["center"][k], float)
        size = np.asarray(objects["size"][k], float)
        _, depth = cam.project(center[None])
        if not depth[0] > 0:
            continue
        corners = _corners3d(center, size, float(objects["yaw"][k]))
        box = project_box3d(corners, cam)
        if box is None:
            continue
        full = project_box3d(corners, cam, clip=False)
        full_area = (full[2] - full[0]) * (full[3] - full[1])
        area = (box[2] - box[0]) * (box[3] - box[1])
        truncation = 1.0 - area / full_area if full_area > 0 else 1.0
        observed = bool(objects["observed"][k])
        out["ids"].append(int(aid))
        out["labels"].append(int(objects["labels"][k]))
        out["boxes"].append([float(b) for b in box])
        out["truncation"].append(float(max(0.0, truncation)))
        out["distance_m"].append(rng)
        out["observed"].append(observed)
        out["difficult"].append(bool(not observed or truncation > REFERENCE_MAX_OUTSIDE))
    return out


def reference_bev_labels(bev: dict, objects: dict, r_max: float) -> dict:
    """The stored BEV boxes with the `reference` protocol's difficulty: an object is to be found
    when some sensor observes it in the clean render and it is within `r_max` of the radar (the
    stored flag uses the degraded observations, which would excuse what the weather hid), and its
    box is at least BEV_MIN_SIZE_PX. Adds distance_m (the object's range)."""
    row = {int(a): k for k, a in enumerate(objects["ids"])}
    out = {k: list(v) for k, v in bev.items()}
    out["difficult"], out["distance_m"] = [], []
    for aid, (x1, y1, x2, y2) in zip(bev["ids"], bev["boxes"]):
        k = row.get(int(aid))
        rng = float(objects["range_m"][k]) if k is not None else float("inf")
        seen = k is not None and bool(objects["observed"][k])
        small = max(x2 - x1, y2 - y1) < BEV_MIN_SIZE_PX
        out["difficult"].append(bool(not seen or rng > r_max or small))
        out["distance_m"].append(rng)
    return out
__all__ = ["fwd_labels", "bev_labels", "object_labels", "reference_labels", "reference_bev_labels", "CLASSES"]
