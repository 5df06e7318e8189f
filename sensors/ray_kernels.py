"""Compiled cores of the ray caster, the radar scan and BEV image and the lidar point list (numba,
cached on disk).

Like sensors.kernels, every kernel repeats the numpy code it replaces operation by operation, in the
same precision and the same order, so its output is bit-identical to the numpy reference
(tests/sensors/test_ray_kernels.py keeps the numpy formulations and compares them on real scans
and random inputs). The speed comes from one pass over the rays instead of a dozen array
temporaries, and from touching only the cells the rays hit (the radar's fine polar grid has 460,800
cells for 12,800 rays). Sums of three products keep numpy's orders (float64): np.linalg.norm adds
``(x0 + x1) + x2``, np.einsum("ij,ij->i") adds ``(x0 + x2) + x1`` (see sensors.kernels).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, error_model="numpy")
def merge_hits(tfar_s, prim_s, ng_s, tfar_d, prim_d, ng_d, dirs, max_range, mat_s, inst_s, mat_d, inst_d):
    """Per-ray first hit of the static and the dynamic (actor) scene (sensors.raycast.WorldCaster.cast).

    Inputs are Embree's outputs per scene: tfar (N,) float32, primID (N,) int32 (-1: no hit) and
    geometric normal Ng (N, 3) float32; an empty scene passes arrays of length 0 (no hit). `dirs`
    (N, 3) are the ray directions (any float dtype and strides); the face tables give each triangle's
    material (uint8) and instance (int32). Reproduces, bit for bit,

        r_s = np.where(prim_s >= 0, tfar_s.astype(np.float64), np.inf)   # and r_d likewise
        use_d = r_d < r_s
        rng = np.where(use_d, r_d, r_s); normal = np.where(use_d[:, None], n_d, n_s)  # float64
        material, instance = the hit scene's face tables at the hit triangle (0 for no hit)
        norm = np.linalg.norm(normal, axis=1, keepdims=True)
        normal = np.divide(normal, norm, out=np.zeros_like(normal), where=norm > 0)
        dot = np.einsum("ij,ij->i", normal, dirs); normal[dot > 0] *= -1   # face the sensor
        rng[rng > max_range] = np.inf; material, instance = 0 there

    Returns (range, normal, material, instance, cos_incidence) where cos_incidence = |dot|, which
    equals np.abs(np.einsum("ij,ij->i", normal, dirs)) of the returned (flipped) normal.
    """
    n = len(dirs)
    has_s = len(prim_s) > 0
    has_d = len(prim_d) > 0
    rng = np.empty(n, np.float64)
    normal = np.empty((n, 3), np.float64)
    material = np.zeros(n, np.uint8)
    instance = np.zeros(n, np.int32)
    cos_i = np.empty(n, np.float64)
    for i in range(n):
        r_s = np.inf
        if has_s and prim_s[i] >= 0:
            r_s = np.float64(tfar_s[i])
        r_d = np.inf
        if has_d and prim_d[i] >= 0:
            r_d = np.float64(tfar_d[i])
        n0 = n1 = n2 = 0.0
        if r_d < r_s:
            rng[i] = r_d
            if has_d:
                n0, n1, n2 = np.float64(ng_d[i, 0]), np.float64(ng_d[i, 1]), np.float64(ng_d[i, 2])
            if prim_d[i] >= 0:
                material[i] = mat_d[prim_d[i]]
                instance[i] = inst_d[prim_d[i]]
        else:
            rng[i] = r_s
            if has_s:
                n0, n1, n2 = np.float64(ng_s[i, 0]), np.float64(ng_s[i, 1]), np.float64(ng_s[i, 2])
                if prim_s[i] >= 0:
                    material[i] = mat_s[prim_s[i]]
                    instance[i] = inst_s[prim_s[i]]
        norm = np.sqrt((n0 * n0 + n1 * n1) + n2 * n2)
        if norm > 0:
            n0, n1, n2 = n0 / norm, n1 / norm, n2 / norm
        else:
            n0 = n1 = n2 = 0.0
        dot = (n0 * np.float64(dirs[i, 0]) + n2 * np.float64(dirs[i, 2])) + n1 * np.float64(dirs[i, 1])
        if dot > 0:
            n0, n1, n2 = n0 * -1.0, n1 * -1.0, n2 * -1.0
        normal[i, 0] = n0
        normal[i, 1] = n1
        normal[i, 2] = n2
        cos_i[i] = abs(dot)
        if rng[i] > max_range:
            rng[i] = np.inf
            material[i] = 0
            instance[i] = 0
    return rng, normal, material, instance, cos_i


@njit(cache=True, error_model="numpy")
def radar_range_grid(p, x, ok, n_fine, B):
    """The radar's fine polar power grid (n_fine, B) float32: each ray's power split linearly between
    the two range bins around it.

    Rays are ordered elevation-major: ray i = e * n_fine + a lies at fine azimuth a. Reproduces

        b0 = np.floor(x).astype(int); frac = x - b0
        grid = np.zeros(n_fine * B)
        for b, w in ((b0, 1 - frac), (b0 + 1, frac)):
            sel = ok & (b >= 0) & (b < B)
            grid += np.bincount(fine_az[sel] * B + b[sel], weights=p[sel] * w[sel], minlength=n_fine * B)
        grid.reshape(n_fine, B).astype(np.float32)

    bit for bit: np.bincount adds the weights in ray order onto 0.0, once for the near bins and once
    for the far bins, and the grid is (0.0 + near) + far. A cell only receives rays of its own
    azimuth, so each azimuth row is summed in a small scratch row.

    Args:
        p: (N,) float64 received power per ray (0 where not ok).
        x: (N,) float64 continuous range bin (R / dr - 0.5) per ray.
        ok: (N,) bool, the ray's return counts.
        n_fine, B: fine azimuths and range bins.
    """
    n_el = len(p) // n_fine
    grid = np.zeros((n_fine, B), np.float32)
    near = np.zeros(B, np.float64)  # bincount of the near-bin weights of the current row
    far = np.zeros(B, np.float64)  # bincount of the far-bin weights
    b0 = np.empty(n_el, np.int64)
    for a in range(n_fine):
        for e in range(n_el):
            i = e * n_fine + a
            b = np.int64(np.floor(x[i]))
            b0[e] = b
            if not ok[i]:
                continue
            frac = x[i] - np.float64(b)
            if 0 <= b < B:
                near[b] += p[i] * (1.0 - frac)
            if 0 <= b + 1 < B:
                far[b + 1] += p[i] * frac
        for e in range(n_el):
            if ok[e * n_fine + a]:
                for b in (b0[e], b0[e] + 1):
                    if 0 <= b < B:
                        grid[a, b] = np.float32((0.0 + near[b]) + far[b])
        for e in range(n_el):
            for b in (b0[e], b0[e] + 1):
                if 0 <= b < B:
                    near[b] = 0.0
                    far[b] = 0.0
    return grid


@njit(cache=True, error_model="numpy")
def radar_coarse_signal(smeared, oversample, speckle):
    """(A, B) float32 coarse-bin signal from the smeared fine grid (A * oversample, B) float32.

    Reproduces ``(np.clip(smeared, 0, None).reshape(A, oversample, B).sum(axis=1) * speckle)
    .astype(np.float32)`` bit for bit: np.clip with no upper bound is np.maximum(x, 0) (NaN kept, and
    +0.0 for a -0.0 input); the float32 sum runs over the fine rows in order; the product with the
    float64 speckle draw is rounded to float32 once. `speckle` None: the sum itself.
    """
    n_fine, B = smeared.shape
    A = n_fine // oversample
    out = np.empty((A, B), np.float32)
    zero = np.float32(0.0)
    for a in range(A):
        for k in range(oversample):
            for b in range(B):
                v = smeared[a * oversample + k, b]
                if not (v > zero or np.isnan(v)):
                    v = zero
                out[a, b] = v if k == 0 else out[a, b] + v
        if speckle is not None:
            for b in range(B):
                out[a, b] = np.float32(np.float64(out[a, b]) * speckle[a, b])
    return out


@njit(cache=True, error_model="numpy")
def lidar_points(dirs, range_m, power, returned, p_sat):
    """(N, 5) float32 detected points x, y, z [m], intensity, ring (sensors.lidar.points).

    Reproduces, bit for bit (points in the C order of the (ring, azimuth) grid):

        m = returned
        xyz = dirs[m] * range_m[m][:, None]                  # float64 (float32 range promoted)
        inten = np.clip(power[m] / P_SAT, 0, 1)              # P_SAT: a Python float
        ring = np.broadcast_to(np.arange(n_rings)[:, None], m.shape)[m]
        np.column_stack([xyz, inten, ring]).astype(np.float32)

    `p_sat` is P_SAT as a scalar of power's dtype (numpy applies a Python float in the array's
    precision). np.clip replaces x only when x < 0 or x > 1 (NaN and -0.0 stay).
    """
    n_rings, n_az = returned.shape
    n = 0
    for r in range(n_rings):
        for a in range(n_az):
            if returned[r, a]:
                n += 1
    pts = np.empty((n, 5), np.float32)
    zero, one = np.float32(0.0), np.float32(1.0)
    k = 0
    for r in range(n_rings):
        for a in range(n_az):
            if not returned[r, a]:
                continue
            rng = np.float64(range_m[r, a])
            for c in range(3):
                pts[k, c] = np.float32(dirs[r, a, c] * rng)
            q = power[r, a] / p_sat
            if q < zero:
                q = zero
            elif q > one:
                q = one
            pts[k, 3] = q
            pts[k, 4] = np.float32(r)
            k += 1
    return pts


@njit(cache=True, error_model="numpy")
def _mirror_index(idx, n):
    """scipy.ndimage's tap index beyond the last sample (ni_interpolation.c, mirrored)."""
    if n <= 1:
        return 0
    s2 = 2 * n - 2
    if idx >= n:
        idx -= s2 * (idx // s2)
        if idx >= n:
            idx = s2 - idx
    return idx


@njit(cache=True, error_model="numpy")
def polar_to_cartesian(polar, rows, cols, outside):
    """Bilinear samples (N,) float32 of the polar image (A, B) float32 with its first row repeated
    after the last (azimuth wrap) at (rows, cols) (N,) float64; 0 where `outside`.

    Reproduces ``map_coordinates(np.vstack([polar, polar[:1]]), np.vstack([rows, cols]), order=1,
    mode="nearest")`` followed by ``out[outside] = 0`` bit for bit, as scipy.ndimage computes it
    (ni_interpolation.c, ni_splines.c): a coordinate beyond the edge is clamped to it; the taps are
    floor(c) and floor(c) + 1 (mirrored back inside at the last sample); the weights are
    w0 = 1 - (c - floor(c)) and w1 = 1 - w0; the value is t = 0.0 + (v00 * w0_r) * w0_c +
    (v01 * w0_r) * w1_c + (v10 * w1_r) * w0_c + (v11 * w1_r) * w1_c in float64, rounded once.
    """
    A, B = polar.shape
    n_rows = A + 1
    out = np.empty(len(rows), np.float32)
    for k in range(len(rows)):
        if outside[k]:
            out[k] = 0.0
            continue
        r = min(max(rows[k], 0.0), n_rows - 1.0)
        c = min(max(cols[k], 0.0), B - 1.0)
        r0 = np.int64(np.floor(r))
        c0 = np.int64(np.floor(c))
        wr0 = 1.0 - (r - np.floor(r))
        wr1 = 1.0 - wr0
        wc0 = 1.0 - (c - np.floor(c))
        wc1 = 1.0 - wc0
        r1 = _mirror_index(r0 + 1, n_rows)
        c1 = _mirror_index(c0 + 1, B)
        r0 = r0 if r0 < A else 0  # the repeated first row
        r1 = r1 if r1 < A else 0
        t = 0.0
        t += (np.float64(polar[r0, c0]) * wr0) * wc0
        t += (np.float64(polar[r0, c1]) * wr0) * wc1
        t += (np.float64(polar[r1, c0]) * wr1) * wc0
        t += (np.float64(polar[r1, c1]) * wr1) * wc1
        out[k] = np.float32(t)
    return out
