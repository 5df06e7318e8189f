"""Sensors agree with each other and with the world: camera vs Embree, axes, calibration, Appendix A."""

import numpy as np
import pytest

from sensors import lidar as lidar_mod
from sensors.camera import pixel_rays
from sensors.rig import (
    Calibration,
    bev_boxes_to_camera,
    camera_boxes_to_camera,
    invert,
    load_profile,
    make_calibration,
    project_box3d,
    transform_points,
)
from tests.sensors.conftest import render


def iou(a, b):
    x1, y1 = max(a[0], b[0]), max(a[1], b[1])
    x2, y2 = min(a[2], b[2]), min(a[3], b[3])
    inter = max(0.0, x2 - x1) * max(0.0, y2 - y1)
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def test_rendered_depth_and_ids_agree_with_embree(city):
    scene, renderer, obs = city
    cam = renderer.calib.camera_right
    cam_obs = obs.camera_right
    H, W = cam_obs.depth.shape
    rng = np.random.default_rng(0)
    v, u = rng.integers(1, H - 1, 800), rng.integers(1, W - 1, 800)
    d = cam_obs.depth
    patch = np.stack([d[v + dv, u + du] for dv in (-1, 0, 1) for du in (-1, 0, 1)])
    finite = np.isfinite(patch).all(0)
    spread = np.ptp(np.where(np.isfinite(patch), patch, 0.0), axis=0)
    smooth = finite & (spread < 0.05 * np.where(finite, d[v, u], 1.0))
    v, u = v[smooth], u[smooth]
    rays_cam = pixel_rays(cam)[v, u]
    world_from_cam = scene.ego.pose @ cam.ego_from_camera
    dirs = rays_cam @ world_from_cam[:3, :3].T
    hits = renderer.caster.cast(world_from_cam[:3, 3], dirs)
    rendered_range = d[v, u] / rays_cam[:, 2]
    err = np.abs(hits.range - rendered_range)
    assert len(v) > 300
    assert np.mean(err < 0.03 + 0.003 * rendered_range) > 0.98, np.percentile(err, [50, 90, 99])
    ids = np.concatenate([[0], obs.actor_ids])[hits.instance]
    assert np.mean(ids == cam_obs.instance[v, u]) > 0.98


def test_left_of_the_ego_is_left_in_every_sensor(junction):
    scene, renderer, obs = junction
    calib = renderer.calib
    ego_from_world = invert(scene.ego.pose)
    rel = transform_points(ego_from_world, scene.actors.centers)
    cam = calib.camera_right
    checked = 0
    for aid, p in zip(scene.actors.ids, rel):
        uv, z = cam.project(p[None])
        if 6 < p[0] < 40 and abs(p[1]) > 2.0 and 0 <= uv[0, 0] < cam.width and (obs.camera_right.instance == aid).sum() > 20:
            cols = np.nonzero(obs.camera_right.instance == aid)[1]
            assert (cols.mean() < cam.K[0, 2]) == (p[1] > 0), (aid, p)
            checked += 1
        bev = calib.radar_to_bev(transform_points(invert(calib.ego_from_radar), p[None])[:, :2])[0]
        if abs(p[1]) > 1.0:
            assert (bev[0] < calib.bev_size_px / 2) == (p[1] > 0)
        if abs(p[0]) > 1.0:
            assert (bev[1] < calib.bev_size_px / 2) == (p[0] > 0)  # forward is up
    assert checked >= 1


def test_bev_and_calibration_roundtrip():
    calib = make_calibration(load_profile("cpu"))
    xy = np.random.default_rng(0).uniform(-50, 50, (100, 2))
    np.testing.assert_allclose(calib.bev_to_radar(calib.radar_to_bev(xy)), xy, atol=1e-9)
    again = Calibration.from_dict(calib.to_dict())
    np.testing.assert_array_equal(again.camera_left.K, calib.camera_left.K)
    np.testing.assert_array_equal(again.ego_from_lidar, calib.ego_from_lidar)
    # stereo: the right camera sits baseline metres to the right of the left one
    d = invert(calib.camera_left.ego_from_camera) @ calib.camera_right.ego_from_camera
    np.testing.assert_allclose(d[:3, 3], [0.12, 0.0, 0.0], atol=1e-12)
    paper = make_calibration(load_profile("paper"))
    assert paper.camera_right.width == 672 and paper.bev_size_px == 1152 and paper.radar_range_bins == 576


def test_lidar_points_lie_on_the_objects_they_hit(city):
    scene, renderer, obs = city
    pts = lidar_mod.points(obs.lidar, renderer.calib)
    inst = obs.lidar.instance[obs.lidar.returned]
    world = transform_points(scene.ego.pose @ renderer.calib.ego_from_lidar, pts[: len(inst), :3])
    row = {a: i for i, a in enumerate(scene.actors.ids)}
    inside = []
    for p, a in zip(world, inst):
        if a == 0:
            continue
        i = row[a]
        c, s = np.cos(-scene.actors.yaws[i]), np.sin(-scene.actors.yaws[i])
        q = p - scene.actors.centers[i]
        local = np.array([c * q[0] - s * q[1], s * q[0] + c * q[1], q[2]])
        inside.append(np.all(np.abs(local) <= scene.actors.sizes[i] / 2 + 0.1))
    assert len(inside) > 80 and np.mean(inside) > 0.99


def test_lidar_beam_pattern_and_return_model(city):
    scene, renderer, obs = city
    calib = renderer.calib
    lid = obs.lidar
    pts = lidar_mod.points(lid, calib)
    elev = np.degrees(np.arctan2(pts[:, 2], np.hypot(pts[:, 0], pts[:, 1])))
    np.testing.assert_allclose(elev, calib.lidar_elevations_deg[pts[:, 4].astype(int)], atol=1e-3)
    assert np.unique(pts[:, 4]).size == 32 and calib.lidar_elevations_deg[0] == pytest.approx(-30.67)
    r = np.linalg.norm(pts[:, :3], axis=1)
    assert r.max() <= 100.0 + 1e-3 and r.min() >= 0.05
    # lidar equation for extended Lambertian targets: P = rho cos(theta) / R^2
    from sensors.materials import NIR

    m = lid.returned
    np.testing.assert_allclose(lid.power[m], NIR[lid.material[m]] * lid.cos_incidence[m] / lid.range[m] ** 2, rtol=1e-5)
    assert np.all(lid.power[m] >= lidar_mod.P_MIN)


def test_appendix_a_projects_bev_boxes_onto_camera_boxes():
    """HydraFusion Appendix A: projected BEV ground truth reaches IoU >= 0.5 with the camera box for
    at least 90 % of visible, unoccluded objects within 40 m."""
    ious = []
    for context, seed in (("junction", 3), ("city", 4), ("motorway", 5), ("rural", 6)):
        scenes, renderer = render(context, seed=seed, frames=2, warmup_s=4.0)
        for scene in scenes:
            obs = renderer.observe(scene)
            frame = renderer.finalize(scene, obs)
            fwd, bev = frame.labels["camera_right"], frame.labels["bev"]
            bev_row = {a: i for i, a in enumerate(bev["ids"])}
            for aid, box, occ, trunc, dist, lab in zip(fwd["ids"], fwd["boxes"], fwd["occlusion"], fwd["truncation"],
                                                      fwd["distance_m"], fwd["labels"]):
                if occ > 0.05 or trunc > 0 or dist > 40 or aid not in bev_row:
                    continue
                proj, keep = bev_boxes_to_camera(np.array([bev["boxes"][bev_row[aid]]]), np.array([lab]),
                                                 renderer.calib, "camera_right")
                ious.append(iou(proj[0], box) if keep[0] else 0.0)
    ious = np.array(ious)
    assert len(ious) >= 15, len(ious)
    assert np.mean(ious >= 0.5) >= 0.9, (np.mean(ious >= 0.5), np.sort(ious)[:10])


def test_left_camera_boxes_map_to_the_right_camera(junction):
    scene, renderer, obs = junction
    frame = renderer.finalize(scene, obs)
    left, right = frame.labels["camera_left"], frame.labels["camera_right"]
    rrow = {a: i for i, a in enumerate(right["ids"])}
    pairs = [(b, right["boxes"][rrow[a]]) for a, b, o, t in zip(left["ids"], left["boxes"], left["occlusion"], left["truncation"])
             if a in rrow and o < 0.05 and t == 0]
    assert pairs
    lefts = np.array([p[0] for p in pairs])
    rights = np.array([p[1] for p in pairs])
    mapped = camera_boxes_to_camera(lefts, renderer.calib)
    # the mapping shifts boxes left by the stereo disparity f b / Z: centres land within the
    # quantisation of the integer ground-truth boxes, and closer than the unmapped boxes
    centre = lambda b: (b[:, 0] + b[:, 2]) / 2  # noqa: E731
    assert np.all(np.abs(centre(mapped) - centre(rights)) < 0.75)
    assert np.all(mapped[:, 0] <= lefts[:, 0] + 1e-9)
    assert np.mean(np.abs(centre(mapped) - centre(rights))) < np.mean(np.abs(centre(lefts) - centre(rights)))


def test_project_box3d_handles_boxes_behind_the_camera():
    calib = make_calibration(load_profile("cpu"))
    cam = calib.camera_right
    corners = np.array([[x, y, z] for x in (-5, 10) for y in (-2, 2) for z in (0, 1.5)], float)
    box = project_box3d(corners, cam)
    assert box is not None and box[0] == 0 and box[2] == cam.width  # straddles the camera: clipped to the image
    assert project_box3d(corners - [20, 0, 0], cam) is None


def test_project_equals_the_inverse_formulation():
    """CameraCalibration.project (cached camera_from_ego) gives the bits of inverting per call."""
    calib = make_calibration(load_profile("cpu"))
    rng = np.random.default_rng(0)
    pts = np.vstack([rng.uniform(-50, 50, (200, 3)), [[0.5, 0.06, 1.95], [np.nan, 1.0, 2.0], [np.inf, 0.0, 1.0]]])
    for cam in (calib.camera_left, calib.camera_right):
        for p_in in (pts, pts[:1], pts[:0]):
            p = transform_points(invert(cam.ego_from_camera), p_in)
            with np.errstate(divide="ignore", invalid="ignore"):
                uv_ref = (p[:, :2] / p[:, 2:3]) * np.array([cam.K[0, 0], cam.K[1, 1]]) + cam.K[:2, 2]
            uv, z = cam.project(p_in)
            assert uv.tobytes() == uv_ref.tobytes() and z.tobytes() == p[:, 2].tobytes()
            assert uv.shape == (len(p_in), 2)
