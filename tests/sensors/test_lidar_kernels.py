"""The lidar image kernels (sensors.lidar_kernels) give the bits of the numpy formulations of
sensors.lidar.bev_image and forward_image they replaced."""

import numpy as np
import pytest

from sensors import lidar as lidar_mod
from sensors.kernels import cell_max
from sensors.rig import invert, load_profile, make_calibration, transform_points

CALIB = make_calibration(load_profile("cpu"))


def bev_image_numpy(pts, calib):
    """sensors.lidar.bev_image before the kernels (commit f473f51)."""
    S = calib.bev_size_px
    xyz = transform_points(invert(calib.ego_from_radar) @ calib.ego_from_lidar, pts[:, :3])
    uv = calib.radar_to_bev(xyz[:, :2])
    u, v = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    ok = (u >= 0) & (u < S) & (v >= 0) & (v < S)
    u, v = u[ok], v[ok]
    height = xyz[ok, 2] + calib.radar_height_m
    lin = v * S + u
    img = np.zeros((3, S * S), np.float32)
    lo, hi = lidar_mod.HEIGHT_RANGE_M
    h01 = np.clip((height - lo) / (hi - lo), 0, 1)
    img[0] = cell_max(np.ascontiguousarray(lin, np.int64), np.ascontiguousarray(h01), S * S)
    img[1] = np.log1p(np.bincount(lin, minlength=S * S)) / np.log(64.0)
    img[2] = cell_max(np.ascontiguousarray(lin, np.int64), np.ascontiguousarray(pts[ok, 3]), S * S)
    return np.round(np.clip(img, 0, 1) * 255).astype(np.uint8).reshape(3, S, S).transpose(1, 2, 0)


def _points(n, seed):
    """(n, 5) float32 lidar-like points: some off the grid, many sharing cells, heights beyond
    HEIGHT_RANGE_M on both sides, intensities 0..1 with repeats."""
    rng = np.random.default_rng(seed)
    pts = np.zeros((n, 5), np.float32)
    pts[:, 0] = rng.uniform(-60, 60, n)
    pts[:, 1] = rng.uniform(-60, 60, n)
    pts[: n // 3, :2] = np.round(pts[: n // 3, :2] / 4.0) * 4.0  # dense cells (counts above 63)
    pts[:, 2] = rng.uniform(-4.0, 3.0, n)
    pts[:, 3] = np.round(rng.uniform(0, 1, n), 2)
    pts[:, 4] = rng.integers(0, 32, n)
    return pts


@pytest.mark.parametrize("n, seed", [(0, 0), (1, 1), (7, 2), (30000, 3)])
def test_bev_image_equals_numpy(n, seed):
    pts = _points(n, seed)
    fast, ref = lidar_mod.bev_image(pts, CALIB), bev_image_numpy(pts, CALIB)
    assert fast.dtype == ref.dtype and fast.shape == ref.shape
    assert fast.tobytes() == ref.tobytes()


def test_bev_image_of_a_rendered_sweep_equals_numpy(city):
    _, renderer, obs = city
    pts = lidar_mod.points(obs.lidar, renderer.calib)
    assert len(pts) > 1000
    assert lidar_mod.bev_image(pts, renderer.calib).tobytes() == bev_image_numpy(pts, renderer.calib).tobytes()


def forward_image_numpy(pts, calib, camera="camera_right"):
    """sensors.lidar.forward_image before the kernels (commit f473f51)."""
    cam = calib.camera(camera)
    ego = transform_points(calib.ego_from_lidar, pts[:, :3])
    uv, z = cam.project(ego)
    ok = z > 0.5
    u = np.floor(uv[ok, 0]).astype(int)
    v = np.floor(uv[ok, 1]).astype(int)
    inb = (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    u, v, zz = u[inb], v[inb], z[ok][inb]
    inten = pts[ok, 3][inb]
    height = ego[ok, 2][inb]
    order = np.argsort(-zz)
    img = np.zeros((cam.height, cam.width, 3), np.float32)
    img[v[order], u[order], 0] = np.clip(1 - zz[order] / lidar_mod.FWD_DEPTH_MAX_M, 0, 1)
    img[v[order], u[order], 1] = inten[order]
    img[v[order], u[order], 2] = np.clip(height[order] / 4.0, 0, 1)
    return np.round(img * 255).astype(np.uint8)


@pytest.mark.parametrize("n, seed", [(0, 0), (1, 1), (7, 2), (30000, 3)])
@pytest.mark.parametrize("camera", ["camera_left", "camera_right"])
def test_forward_image_equals_numpy(n, seed, camera):
    pts = _points(n, seed)
    pts[: n // 2, 0] = np.abs(pts[: n // 2, 0]) / 4.0  # many in front, up to 100 m (closeness clips)
    m = n // 8
    pts[n // 4: n // 4 + m] = pts[m: 2 * m]  # repeated points: equal depths on one pixel
    fast, ref = lidar_mod.forward_image(pts, CALIB, camera), forward_image_numpy(pts, CALIB, camera)
    assert fast.dtype == ref.dtype and fast.shape == ref.shape
    assert fast.tobytes() == ref.tobytes()


def test_forward_image_of_a_rendered_sweep_equals_numpy(city):
    _, renderer, obs = city
    pts = lidar_mod.points(obs.lidar, renderer.calib)
    fast = lidar_mod.forward_image(pts, renderer.calib)
    assert fast.any() and fast.tobytes() == forward_image_numpy(pts, renderer.calib).tobytes()
