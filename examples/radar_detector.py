"""A classical radar detector on a nuScenes export: a CFAR test on the points' RCS, clusters, typical boxes.

    python examples/radar_detector.py --export DIR --out radar.json

Per sample, from the RADAR_TOP scan alone (read with the devkit's RadarPointCloud, its default
filters; hydrabench's export writes a scanning radar's peaks as ARS-408 points with an `rcs` field,
docs/nuscenes.md):

1. the points into the ego frame; with a map (default), only those on the road and sidewalks
   (the devkit's MapMask, dilated MAP_DILATION_M) are kept: the scan's strongest returns are
   buildings, walls and guardrails beside the road;
2. an absolute floor, rcs >= RCS_FLOOR_DBSM (returns of rain and snow near the mast fall below it);
3. a CFAR test along range on the points: a point's background is the median rcs of the other kept
   points whose range differs from its own by GUARD_M to TRAIN_M (an ordered-statistic CFAR over the
   scan's point list rather than its cells: a strong neighbour does not mask a point as a mean would),
   and the point is kept when its rcs exceeds that by CFAR_MARGIN_DB (with fewer than MIN_TRAINING
   training points the floor is the background). RCS is compared at equal range because the exported
   estimate carries the range-dependent part of the rig's gain;
4. Euclidean clustering of the kept points (DBSCAN, CLUSTER_EPS_M, single points allowed);
5. a class per cluster (`classify`: a truck when it is long, else a car), a box of that class's typical
   size, heading along the cluster when it is long enough to show one (its principal axis), else along
   the ego's heading, its centre the cluster's centre moved away from the radar by half the box's depth
   (a radar sees an object's near side);
6. a score from the cluster's strongest excess over the CFAR background and its point count.

Written as nuScenes detection results, `meta` {"use_radar": true, "use_map": true (false with
--no-map), the rest false}. No learning: every constant below was chosen by hand on a dataset
other than the one the docs score (docs/nuscenes.md).
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

CHANNEL = "RADAR_TOP"
MAP_DILATION_M = 1.0
RCS_FLOOR_DBSM = -30.0
TRAIN_M = 15.0  # training points: range within this of the point's ...
GUARD_M = 3.0  # ... but not within this (the object's own returns)
MIN_TRAINING = 4
CFAR_MARGIN_DB = 3.0
CLUSTER_EPS_M = 2.0
MAX_RANGE_M = 100.0
LONG_SPAN_M = 6.0  # a cluster this long is a truck or a bus
HEADING_SPAN_M = 2.5  # a cluster this long shows its heading
SEEN_DEPTH_M = 2.0  # the depth of an object its returns already cover (they come from more than its near face)
SCORE_RANGE_M = 40.0  # an azimuth cell spans more metres further out: the score halves at this range

TYPICAL_SIZE = {  # (length, width, height) [m]: common real-world sizes
    "car": (4.5, 1.85, 1.5),
    "truck": (9.0, 2.5, 3.4),
}


def cfar(r: np.ndarray, rcs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(kept (N,) bool, excess over the background (N,) [dB]) of points at ranges `r` with `rcs`
    [dBsm]: the ordered-statistic CFAR of the module docstring, all points at once ((N, N) ring)."""
    d = np.abs(r[:, None] - r[None, :])
    ring = (d > GUARD_M) & (d <= TRAIN_M)
    count = ring.sum(axis=1)
    values = np.where(ring, rcs[None, :], np.nan)
    background = np.full(len(r), RCS_FLOOR_DBSM)
    enough = count >= MIN_TRAINING
    if enough.any():
        background[enough] = np.nanmedian(values[enough], axis=1)
    excess = rcs - np.maximum(background, RCS_FLOOR_DBSM)
    return excess >= CFAR_MARGIN_DB, excess


def classify(span: float) -> str:
    """A detection name from a cluster's span (largest distance between two of its points) [m]: long
    clusters are trucks (a radar cannot tell a bus), the rest cars (most of what drives). The RCS
    estimate does not tell a pedestrian from a car's weak corner here, so pedestrians and two-wheelers
    are never claimed: a radar that claims them only adds false positives."""
    return "truck" if span >= LONG_SPAN_M else "car"


def heading(xy: np.ndarray, span: float) -> float:
    """The cluster's principal axis [rad] when it spans HEADING_SPAN_M, else 0 (the ego's heading)."""
    if span < HEADING_SPAN_M or len(xy) < 2:
        return 0.0
    d = xy - xy.mean(axis=0)
    _, vecs = np.linalg.eigh(d.T @ d)
    v = vecs[:, -1]
    return math.atan2(v[1], v[0])


def detect(nusc, sample: dict, ctx: dict) -> list[Detection]:
    """The boxes of one sample's radar scan, in its ego frame (module docstring)."""
    from nuscenes.utils.data_classes import RadarPointCloud

    sd = sensor_data(nusc, sample, CHANNEL)
    ego_from_radar, global_from_ego = poses(nusc, sd)
    pts = RadarPointCloud.from_file(nusc.get_sample_data_path(sd["token"])).points
    pts = pts[:, np.isfinite(pts[:3]).all(axis=0)]
    xyz = transform(pts[:3].T.astype(np.float64), ego_from_radar)
    rcs = pts[5].astype(np.float64)
    sensor_xy = ego_from_radar[:2, 3]
    r = np.hypot(*(xyz[:, :2] - sensor_xy).T)
    keep = (r < MAX_RANGE_M) & (rcs >= RCS_FLOOR_DBSM)
    if ctx.get("use_map") and keep.any():
        g = transform(xyz, global_from_ego)
        keep &= map_mask_of(nusc, sample).is_on_mask(g[:, 0], g[:, 1], MAP_DILATION_M)
    xyz, rcs, r = xyz[keep], rcs[keep], r[keep]
    passed, excess = cfar(r, rcs)
    xyz, rcs, excess = xyz[passed], rcs[passed], excess[passed]
    out = []
    for idx in clusters(xyz[:, :2], CLUSTER_EPS_M, 1):
        xy = xyz[idx, :2]
        span = float(np.max(np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1)))) if len(idx) > 1 else 0.0
        name = classify(span)
        length, width, height = TYPICAL_SIZE[name]
        length = max(length, span)
        yaw = heading(xy, span)
        center = along_line_of_sight(xy.mean(axis=0), sensor_xy, yaw, length, width, SEEN_DEPTH_M)
        peak = float(excess[idx].max())
        reach = float(np.hypot(*(center - sensor_xy))) / SCORE_RANGE_M
        score = (1.0 - 0.5 ** len(idx)) / (1.0 + math.exp(-(peak - 8.0) / 4.0)) / (1.0 + reach * reach)
        out.append(Detection(np.array([center[0], center[1], height / 2]), (length, width, height), yaw, name, score))
    return out


if __name__ == "__main__":
    sys.exit(main(lambda: command(__doc__, CHANNEL, detect, "radar")))
