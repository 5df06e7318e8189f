"""Compiled core of the lidar BEV image (numba, cached on disk).

`bev_cells` and `bev_pixels` together replace the numpy body of `sensors.lidar.bev_image` after the
points are moved into the radar frame, bit for bit (tests/sensors/test_lidar_kernels.py compares
them with that numpy formulation): the same float64 / float32 operations in the same order, no
fused multiply-add, and the one transcendental (log1p of the point counts) taken from a table that
numpy itself computes. The per-cell maxima follow `sensors.kernels.cell_max` (among equal values
the later one wins, NaN is the largest, the maximum is taken in the input precision and rounded
once to float32).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from sensors.kernels import take_max

_F32 = np.float32


@njit(cache=True, error_model="numpy")
def bev_cells(xyz, intensity, size, resolution, radar_height, h_low, h_span):
    """Per BEV cell (S * S, row-major, S = `size`): the maximum height channel, the point count and
    the maximum intensity of the points that fall on the grid. Reproduces

        uv = calib.radar_to_bev(xyz[:, :2])         # u = S/2 - y / res, v = S/2 - x / res (float64)
        u, v = floor(uv).astype(int); ok = 0 <= u, v < S; lin = v * S + u
        h01 = clip((xyz[ok, 2] + radar_height - h_low) / h_span, 0, 1)
        height = cell_max(lin, h01).astype(float32); count = bincount(lin); inten = cell_max(lin, intensity[ok])

    Args: xyz (N, 3) float64 radar-frame points; intensity (N,) float32; the rest Python floats.
    Returns (S * S,) float32 height, (S * S,) int64 count, (S * S,) float32 intensity.
    """
    n_cells = size * size
    half = size / 2.0
    h_best = np.zeros(n_cells, np.float64)
    h_state = np.zeros(n_cells, np.uint8)
    i_best = np.zeros(n_cells, intensity.dtype)
    i_state = np.zeros(n_cells, np.uint8)
    count = np.zeros(n_cells, np.int64)
    for k in range(xyz.shape[0]):
        u = int(np.floor(half - xyz[k, 1] / resolution))
        v = int(np.floor(half - xyz[k, 0] / resolution))
        if u < 0 or u >= size or v < 0 or v >= size:
            continue
        c = v * size + u
        h = ((xyz[k, 2] + radar_height) - h_low) / h_span
        if h < 0.0:
            h = 0.0
        elif h > 1.0:
            h = 1.0
        take_max(h_best, h_state, c, h)
        count[c] += 1
        take_max(i_best, i_state, c, intensity[k])
    return h_best.astype(np.float32), count, i_best.astype(np.float32)


@njit(cache=True, error_model="numpy")
def bev_pixels(height, count, density_of_count, intensity, size):
    """(S, S, 3) uint8 image of the cell channels: round(clip(x, 0, 1) * 255) in float32 per channel,
    the density channel being float32(density_of_count[count]) (numpy's log1p(count) / log(64))."""
    out = np.empty((size, size, 3), np.uint8)
    for c in range(size * size):
        r, col = c // size, c % size
        for ch in range(3):
            if ch == 0:
                x = height[c]
            elif ch == 1:
                x = _F32(density_of_count[count[c]])
            else:
                x = intensity[c]
            if x < _F32(0.0):
                x = _F32(0.0)
            elif x > _F32(1.0):
                x = _F32(1.0)
            out[r, col, ch] = np.uint8(np.rint(x * _F32(255.0)))
    return out


@njit(cache=True, error_model="numpy")
def forward_pixels(uv, z, width, height, min_depth):
    """Indices (M,) of the points in front of the camera (z > min_depth) whose floored pixel
    np.floor(uv).astype(int) lies in the image, in input order, with their pixel columns and rows."""
    n = z.shape[0]
    idx = np.empty(n, np.int64)
    us = np.empty(n, np.int64)
    vs = np.empty(n, np.int64)
    m = 0
    for k in range(n):
        if not z[k] > min_depth:
            continue
        u = int(np.floor(uv[k, 0]))
        v = int(np.floor(uv[k, 1]))
        if u >= 0 and u < width and v >= 0 and v < height:
            idx[m], us[m], vs[m] = k, u, v
            m += 1
    return idx[:m], us[:m], vs[:m]


@njit(cache=True, error_model="numpy")
def forward_raster(order, us, vs, depth, intensity, height_m, width, height, depth_max):
    """(H, W, 3) uint8 forward lidar image: the points written in `order` (a later point overwrites)
    as closeness clip(1 - depth / depth_max, 0, 1), intensity and clip(height_m / 4, 0, 1), each
    computed in float64 and stored in float32 (numpy's assignment into a float32 image), then
    round(x * 255) in float32 for every pixel."""
    img = np.zeros((height, width, 3), np.float32)
    for j in range(order.shape[0]):
        k = order[j]
        c = 1 - depth[k] / depth_max
        h = height_m[k] / 4.0
        img[vs[k], us[k], 0] = _F32(min(max(c, 0.0), 1.0)) if not np.isnan(c) else _F32(c)
        img[vs[k], us[k], 1] = intensity[k]
        img[vs[k], us[k], 2] = _F32(min(max(h, 0.0), 1.0)) if not np.isnan(h) else _F32(h)
    out = np.empty((height, width, 3), np.uint8)
    for r in range(height):
        for col in range(width):
            for ch in range(3):
                out[r, col, ch] = np.uint8(np.rint(img[r, col, ch] * _F32(255.0)))
    return out
