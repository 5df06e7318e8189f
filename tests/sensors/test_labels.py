"""sensors.labels: the batched and shared computations give the labels of the per-actor formulation."""

import dataclasses

import numpy as np
import pytest
from scipy import ndimage

from sensors.label_kernels import instance_boxes, visible_samples
from sensors.labels import BEV_MIN_SIZE_PX, bev_labels, fwd_labels
from sensors.rig import invert, transform_points
from sim.actors import box_corners_2d


def bev_labels_per_actor(actors, calib, world_from_ego, lidar_obs, radar_obs):
    """sensors.labels.bev_labels before the footprints were batched (commit f473f51)."""
    out = {k: [] for k in ("ids", "labels", "boxes", "rotated", "lidar_points", "radar_visible", "difficult")}
    if len(actors) == 0:
        return out
    S, res = calib.bev_size_px, calib.bev_resolution_m
    centers = transform_points(invert(world_from_ego @ calib.ego_from_radar), actors.centers)
    yaws = actors.yaws - np.arctan2(world_from_ego[1, 0], world_from_ego[0, 0])
    uv_c = calib.radar_to_bev(centers[:, :2])
    on = (uv_c[:, 0] >= 0) & (uv_c[:, 0] < S) & (uv_c[:, 1] >= 0) & (uv_c[:, 1] < S)
    ids, cnt = np.unique(lidar_obs.instance[lidar_obs.returned & (lidar_obs.instance > 0)], return_counts=True)
    lid_counts = dict(zip(ids.tolist(), cnt.tolist()))
    strong = (radar_obs.instance > 0) & (radar_obs.signal > 3.0 * radar_obs.noise.mean())
    radar_seen = set(np.unique(radar_obs.instance[strong]).tolist())
    for i in np.flatnonzero(on):
        corners = box_corners_2d(centers[i:i + 1, :2], actors.sizes[i:i + 1, :2], yaws[i:i + 1])[0]
        uv = calib.radar_to_bev(corners)
        x1, y1 = np.clip(uv.min(axis=0), 0, S)
        x2, y2 = np.clip(uv.max(axis=0), 0, S)
        if x2 - x1 <= 0 or y2 - y1 <= 0:
            continue
        aid = int(actors.ids[i])
        n_lidar = int(lid_counts.get(aid, 0))
        r_vis = aid in radar_seen
        small = max(x2 - x1, y2 - y1) < BEV_MIN_SIZE_PX
        out["ids"].append(aid)
        out["labels"].append(int(actors.classes[i]))
        out["boxes"].append([round(float(x1), 2), round(float(y1), 2), round(float(x2), 2), round(float(y2), 2)])
        out["rotated"].append([round(float(uv_c[i, 0]), 2), round(float(uv_c[i, 1]), 2),
                               round(float(actors.sizes[i, 0] / res), 2), round(float(actors.sizes[i, 1] / res), 2),
                               round(float(np.arctan2(np.sin(yaws[i]), np.cos(yaws[i]))), 4)])
        out["lidar_points"].append(n_lidar)
        out["radar_visible"].append(bool(r_vis))
        out["difficult"].append(bool((n_lidar == 0 and not r_vis) or small))
    return out


def _moved(actors, rng):
    """The actors scattered around their positions with random headings (some off the grid)."""
    n = len(actors)
    return dataclasses.replace(actors, centers=actors.centers + np.column_stack([rng.uniform(-60, 60, (n, 2)), np.zeros(n)]),
                               yaws=rng.uniform(-7, 7, n))


@pytest.mark.parametrize("fixture", ["city", "junction"])
def test_bev_labels_equal_the_per_actor_formulation(fixture, request):
    scene, renderer, obs = request.getfixturevalue(fixture)
    args = (renderer.calib, scene.ego.pose, obs.lidar, obs.radar)
    ref = bev_labels_per_actor(scene.actors, *args)
    assert len(ref["ids"]) > 0
    assert bev_labels(scene.actors, *args) == ref
    rng = np.random.default_rng(0)
    for actors in (_moved(scene.actors, rng), _moved(scene.actors, rng), scene.actors[:1], scene.actors[:0]):
        assert bev_labels(actors, *args) == bev_labels_per_actor(actors, *args)


def test_fwd_labels_with_shared_geometry_equal_separate_calls(city):
    scene, renderer, obs = city
    geometry = {}
    for name in ("camera_left", "camera_right"):
        o, cam = getattr(obs, name), renderer.calib.camera(name)
        alone = fwd_labels(o.instance, o.depth, scene.actors, cam, scene.ego.pose)
        assert len(alone["ids"]) > 0
        assert fwd_labels(o.instance, o.depth, scene.actors, cam, scene.ego.pose, geometry) == alone
    assert geometry


def visible_samples_numpy(uv, z, instance, depth, actor_id, min_depth):
    """The occlusion test of sensors.labels.fwd_labels before the kernel (commit f473f51)."""
    with np.errstate(invalid="ignore"):
        u = np.floor(uv[:, 0]).astype(int)
        v = np.floor(uv[:, 1]).astype(int)
    inimg = (z > min_depth) & (u >= 0) & (u < instance.shape[1]) & (v >= 0) & (v < instance.shape[0])
    du, dv, dz = u[inimg], v[inimg], z[inimg]
    seen = (instance[dv, du] == actor_id) | (depth[dv, du] >= dz - (0.3 + 0.02 * dz))
    return int(inimg.sum()), int(seen.sum())


def test_visible_samples_equal_numpy(city):
    scene, renderer, obs = city
    rng = np.random.default_rng(0)
    checked = 0
    for name in ("camera_left", "camera_right"):
        o, cam = getattr(obs, name), renderer.calib.camera(name)
        ego_from_world = invert(scene.ego.pose)
        for i, aid in enumerate(scene.actors.ids.tolist()):
            pts = transform_points(ego_from_world, scene.actors.centers[i] + rng.normal(0, 2.0, (300, 3)))
            uv, z = cam.project(pts)
            args = (o.instance, o.depth, aid, 0.3)
            ref = visible_samples_numpy(uv, z, *args)
            assert visible_samples(uv, z, *args) == ref
            checked += ref[0] > 0
        # behind the camera (inf / NaN pixels), a single point, no points
        pts = np.array([[0.5, 0.06, 1.95], [-5.0, 0.0, 1.0], [0.6, 0.0, 1.95], [30.0, 1.0, 1.0]])
        with np.errstate(divide="ignore", invalid="ignore"):
            uv, z = cam.project(pts)
        for k in (4, 1, 0):
            assert visible_samples(uv[:k], z[:k], o.instance, o.depth, 0, 0.3) == \
                visible_samples_numpy(uv[:k], z[:k], o.instance, o.depth, 0, 0.3)
    assert checked > 3


def instance_boxes_scipy(instance, ids):
    """The visible-pixel boxes of sensors.labels.fwd_labels before the kernel (commit f473f51)."""
    compact = np.zeros(instance.shape, np.int32)
    sel = instance > 0
    compact[sel] = np.searchsorted(ids, instance[sel]) + 1
    return [[s[0].start, s[1].start, s[0].stop, s[1].stop] for s in ndimage.find_objects(compact)]


def test_instance_boxes_equal_scipys_find_objects(city):
    _, _, obs = city
    images = [obs.camera_left.instance, obs.camera_right.instance]
    one = np.zeros((5, 7), np.int64)
    one[4, 6] = 200084  # a single pixel in the last row and column
    images.append(one)
    rng = np.random.default_rng(0)
    images.append(np.where(rng.uniform(size=(40, 60)) < 0.1, rng.integers(1, 5, (40, 60)) * 1000, 0))
    for instance in images:
        ids = np.unique(instance[instance > 0])
        assert len(ids) > 0
        assert instance_boxes(instance, ids).tolist() == instance_boxes_scipy(instance, ids)
