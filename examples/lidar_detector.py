"""A classical lidar detector on a nuScenes export: ground plane, clusters, L-shape boxes, a size rule.

    python examples/lidar_detector.py --export DIR --out lidar.json

Per sample, from the LIDAR_TOP sweep alone (read with the devkit's LidarPointCloud):

1. the points into the ego frame (the sweep's calibrated sensor);
2. ground removal: a plane fitted by RANSAC to the points within GROUND_FIT_RANGE_M (vectorised:
   RANSAC_ITERATIONS candidate planes scored at once, the best refined by least squares on its
   inliers); the points between MIN_HEIGHT_M and MAX_HEIGHT_M above it, within MAX_RANGE_M, are kept;
3. Euclidean clustering of the kept points' ground positions (x, y): DBSCAN with min_samples 1 at
   CLUSTER_EPS_M, on cells of VOXEL_M (each point takes its cell's cluster);
4. an oriented box per cluster by L-shape fitting (Zhang et al., "Efficient L-shape fitting for
   vehicle detection using laser scanners", IV 2017: the rectangle direction that maximises the
   closeness criterion, searched over 90 headings at 1 degree, all at once), from the ground to the
   cluster's highest point;
5. a class by a size rule (`classify`), then the box completed to the class's typical size where the
   sweep saw only the near side (the hidden part lies away from the sensor);
6. a score from the point count (n / (n + SCORE_HALF_POINTS)), lowered for a box the rule had to
   complete a lot; with a map (default), boxes whose centre is off the road and sidewalks are dropped.

The boxes are taken to the global frame by the sample's ego pose and written as nuScenes detection
results, `meta` {"use_lidar": true, "use_map": true (false with --no-map), the rest false}.
No learning: every threshold below is a constant chosen by hand on a dataset other than the one
the docs score (docs/nuscenes.md).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from classical_common import (  # noqa: E402
    Detection,
    along_line_of_sight,
    clusters,
    command,
    main,
    map_mask_of,
    poses,
    sensor_data,
    transform,
)

CHANNEL = "LIDAR_TOP"
GROUND_FIT_RANGE_M = 40.0  # points used to fit the ground plane
RANSAC_ITERATIONS = 64
RANSAC_SAMPLE = 2000  # points the candidate planes are scored on
RANSAC_TOL_M = 0.12  # a point within this of a plane is its inlier
MIN_HEIGHT_M = 0.25  # above the ground plane: lower points are road (curbs are ~0.15 m)
MAX_HEIGHT_M = 4.5  # tree crowns, building fronts above this are cut
MAX_RANGE_M = 80.0
CLUSTER_EPS_M = 1.0
CLUSTER_MIN_CELLS = 1  # DBSCAN's min_samples on the cells: 1 is Euclidean clustering
VOXEL_M = 0.2  # points are merged into cells this wide before clustering
MIN_POINTS = 3  # a cluster with fewer points is not boxed
MIN_OBJECT_HEIGHT_M = 0.5  # a cluster's top lower than this is clutter
MAX_OBJECT_HEIGHT_M = 4.3  # ... higher than this a tree or a building
MAX_LENGTH_M = 14.0  # a longer cluster is a wall or a row of parked cars
SCORE_HALF_POINTS = 25.0  # score 0.5 at this many points
MAP_DILATION_M = 0.0

TYPICAL_SIZE = {  # (length, width, height) [m] of each class: common real-world sizes
    "car": (4.5, 1.85, 1.5),
    "truck": (9.0, 2.5, 3.4),
    "bus": (12.0, 2.55, 3.1),
    "motorcycle": (2.1, 0.8, 1.45),
    "bicycle": (1.75, 0.6, 1.7),
    "pedestrian": (0.6, 0.6, 1.75),
}
ANGLES = np.deg2rad(np.arange(0.0, 90.0, 1.0))
DIRECTIONS = np.stack([np.cos(ANGLES), np.sin(ANGLES)])  # (2, 90)
NORMALS = np.stack([-np.sin(ANGLES), np.cos(ANGLES)])


def ground_plane(xyz: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(a, b, c) of the ground z = a x + b y + c fitted to `xyz` (N, 3), ego frame [m].

    RANSAC: RANSAC_ITERATIONS planes through random point triples, each scored by its inliers among
    RANSAC_SAMPLE points, planes tilted more than ~18 degrees skipped; the best one refined by least
    squares on its inliers among all the points. The fit uses the lowest points (below the 40th
    percentile of height + 1 m), where the ground is."""
    near = xyz[np.hypot(xyz[:, 0], xyz[:, 1]) < GROUND_FIT_RANGE_M]
    if len(near) < 3:
        return np.array([0.0, 0.0, float(np.min(xyz[:, 2])) if len(xyz) else 0.0])
    low = near[near[:, 2] < np.percentile(near[:, 2], 40) + 1.0]
    sub = low[rng.choice(len(low), min(RANSAC_SAMPLE, len(low)), replace=False)]
    tri = sub[rng.integers(0, len(sub), (RANSAC_ITERATIONS, 3))]  # (K, 3, 3)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-9
    n[ok] /= norm[ok, None]
    n *= np.sign(n[:, 2:3] + 1e-12)
    ok &= n[:, 2] > 0.95
    if not ok.any():
        return np.array([0.0, 0.0, float(np.median(low[:, 2]))])
    d = -(n * tri[:, 0]).sum(axis=1)
    inliers = (np.abs(sub @ n.T + d) < RANSAC_TOL_M).sum(axis=0)
    inliers[~ok] = -1
    best = int(np.argmax(inliers))
    keep = np.abs(low @ n[best] + d[best]) < RANSAC_TOL_M
    A = np.c_[low[keep, :2], np.ones(keep.sum())]
    coef, *_ = np.linalg.lstsq(A, low[keep, 2], rcond=None)
    return coef


def l_shape(xy: np.ndarray) -> tuple[np.ndarray, float, float, float]:
    """The rectangle around the points `xy` (N, 2) whose sides the points hug best (the closeness
    criterion of L-shape fitting): (centre (2,), heading [rad], extent along it, extent across) [m]."""
    c1, c2 = xy @ DIRECTIONS, xy @ NORMALS  # (N, 90) each
    d1 = np.minimum(c1.max(axis=0) - c1, c1 - c1.min(axis=0))
    d2 = np.minimum(c2.max(axis=0) - c2, c2 - c2.min(axis=0))
    closeness = (1.0 / np.maximum(np.minimum(d1, d2), 0.01)).sum(axis=0)
    k = int(np.argmax(closeness))
    lo1, hi1, lo2, hi2 = c1[:, k].min(), c1[:, k].max(), c2[:, k].min(), c2[:, k].max()
    center = DIRECTIONS[:, k] * (lo1 + hi1) / 2 + NORMALS[:, k] * (lo2 + hi2) / 2
    return center, float(ANGLES[k]), float(hi1 - lo1), float(hi2 - lo2)


def classify(long_side: float, short_side: float, height: float) -> str | None:
    """A detection name from a cluster's footprint (its longer and shorter side) and its height [m],
    or None for what is no road user (walls, guardrails, poles, trees, low clutter).

    Most clusters show an object's near side only, so a side is at most what the class allows and
    the rule reads the longest visible side first: over 6.5 m a truck or a bus (a bus is long and
    under 3.4 m high), 2.7-6.5 m a car (a truck when over 2.6 m high), a 1.3-2.7 m side: a truck or
    a bus seen from one end when it is a flat face over 2 m wide and 2.3 m high, a car seen from one end
    when it is wide for a two-wheeler (over 0.9 m across, or the side at least 1.5 m), else a
    two-wheeler; a footprint within 1.3 m a pedestrian."""
    if long_side > MAX_LENGTH_M or short_side > 3.2 or height < MIN_OBJECT_HEIGHT_M or height > MAX_OBJECT_HEIGHT_M:
        return None
    if long_side > 6.5:
        if short_side < 1.2 and height < 2.0:
            return None  # a wall, a fence, a guardrail
        return "bus" if long_side > 10.0 and height < 3.4 else "truck"
    if long_side > 2.7:
        return "car" if height < 2.6 else "truck"
    if long_side > 1.3:
        if height > 2.3:  # a flat face 2-3 m wide is the end of a tall vehicle; else a tree or a post
            return "truck" if long_side >= 2.0 and short_side < 0.6 else None
        if short_side > 0.9 or long_side >= 1.5:
            return "car"
        return "motorcycle" if long_side > 1.9 else "bicycle"
    return "pedestrian" if 1.0 <= height <= 2.2 else None


def complete(center: np.ndarray, yaw: float, along: float, across: float, name: str,
             sensor_xy: np.ndarray) -> tuple[np.ndarray, float, float, float, float]:
    """The box a class's typical size makes of a partly seen cluster: its longer side becomes the
    length unless it is at most 1.5 times the class's width and nearer its width than its length (a
    car seen from one end); each side is at least the typical one, grown away from the sensor.
    Returns (centre, yaw, length, width, share of the box's footprint that was seen)."""
    length, width, _ = TYPICAL_SIZE[name]
    if across > along:
        along, across, yaw = across, along, yaw + math.pi / 2
    if along <= 1.5 * width and abs(along - width) < abs(along - length):
        along, across, yaw = across, along, yaw + math.pi / 2  # its longer side is as wide as the class: its end
    full_l, full_w = max(along, length), max(across, width)
    seen_depth = _depth_along_sight(center - sensor_xy, yaw, along, across)
    c = along_line_of_sight(center, sensor_xy, yaw, full_l, full_w, seen_depth)
    return c, yaw, full_l, full_w, (along * across) / (full_l * full_w)


def _depth_along_sight(u: np.ndarray, yaw: float, length: float, width: float) -> float:
    n = float(np.hypot(*u))
    if n < 1e-6:
        return 0.0
    ux, uy = u / n
    c, s = math.cos(yaw), math.sin(yaw)
    return abs(length * (ux * c + uy * s)) + abs(width * (-ux * s + uy * c))


def detect(nusc, sample: dict, ctx: dict) -> list[Detection]:
    """The boxes of one sample's lidar sweep, in its ego frame (module docstring)."""
    from nuscenes.utils.data_classes import LidarPointCloud

    sd = sensor_data(nusc, sample, CHANNEL)
    ego_from_lidar, global_from_ego = poses(nusc, sd)
    pc = LidarPointCloud.from_file(nusc.get_sample_data_path(sd["token"]))
    xyz = transform(pc.points[:3].T.astype(np.float64), ego_from_lidar)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    rng = np.random.default_rng(0)  # the same sweep gives the same boxes
    a, b, c = ground_plane(xyz, rng)
    height = xyz[:, 2] - (a * xyz[:, 0] + b * xyz[:, 1] + c)
    r = np.hypot(xyz[:, 0], xyz[:, 1])
    keep = (height > MIN_HEIGHT_M) & (height < MAX_HEIGHT_M) & (r < MAX_RANGE_M)
    pts, h = xyz[keep], height[keep]
    sensor_xy = ego_from_lidar[:2, 3]
    out = []
    for idx in clusters(pts[:, :2], CLUSTER_EPS_M, CLUSTER_MIN_CELLS, VOXEL_M):
        if len(idx) < MIN_POINTS:
            continue
        center, yaw, along, across = l_shape(pts[idx, :2])
        top = float(h[idx].max())
        name = classify(max(along, across), min(along, across), top)
        if name is None:
            continue
        center, yaw, length, width, seen = complete(center, yaw, along, across, name, sensor_xy)
        box_h = max(top, 0.8 * TYPICAL_SIZE[name][2])
        ground = a * center[0] + b * center[1] + c
        score = len(idx) / (len(idx) + SCORE_HALF_POINTS) * (0.5 + 0.5 * min(seen / 0.5, 1.0))
        out.append(Detection(np.array([center[0], center[1], ground + box_h / 2]), (length, width, box_h),
                             yaw, name, score))
    if ctx.get("use_map") and out:
        g = transform(np.array([d.center for d in out]), global_from_ego)
        on = map_mask_of(nusc, sample).is_on_mask(g[:, 0], g[:, 1], MAP_DILATION_M)
        out = [d for d, keep_it in zip(out, on) if keep_it]
    return out


if __name__ == "__main__":
    sys.exit(main(lambda: command(__doc__, CHANNEL, detect, "lidar")))
