"""Compiled cores of the camera shading and the lidar BEV image (numba, cached on disk).

Every kernel repeats the numpy code it replaces operation by operation, in the same precision and
the same order, so its output is bit-identical to the numpy reference (tests/sensors/test_kernels.py
compares them on real frames and random inputs). What that takes:

- float32 stays float32: every constant that numpy applies to a float32 array as a Python scalar
  (NEP 50 "weak" scalar, cast to float32 first) is written here as an explicit ``np.float32``;
  numba would otherwise promote the operation to float64 and round differently.
- sums of three products follow numpy's einsum order: float32 ``((x0 + x1) + x2)``; float64
  ``((x0 + x2) + x1)`` (numpy's baseline SSE2 loop keeps two lanes: x0 and x2 share one).
- no fused multiply-add: numba does not contract ``a * b + c`` without fastmath, nor does numpy's
  elementwise code.
- no transcendental functions, except in `artificial_light`: numpy's SIMD exp / log / pow differ
  from libm by an ulp on some CPUs. On the reference machine (AVX2, numpy 2.4) the lights' exp,
  pow and atan2 gave numpy's bits too (the 160-frame dataset, tests/sensors/test_kernels.py);
  elsewhere they may differ in the last bit, which the test tolerates.
- matrix products with BLAS (``P_cam @ R.T``) stay in numpy: OpenBLAS's kernels use FMA in a
  CPU-dependent order.

The speed comes from one pass over the image without the ~20 full-size temporaries of the numpy
version (rolls, masks, stacked cross products).
"""

from __future__ import annotations

import numpy as np
from numba import njit

_F32 = np.float32


@njit(cache=True, error_model="numpy")
def surface_normals(P, D, cam_pos, snap_material, material):
    """Per-pixel unit normals facing the camera (see `sensors.camera._normals_from_points`).

    Args:
        P: (H, W, 3) float32 world points of the pixels.
        D: (H, W) float32 depth used to pick the neighbour with the smaller jump (sky = 1e6).
        cam_pos: (3,) float32 camera centre (world).
        snap_material: (M,) bool, materials whose near-vertical normals snap to +z (ground).
        material: (H, W) uint8 material id per pixel.
    Returns:
        n: (H, W, 3) float32, flipped towards the camera, snapped to (0, 0, 1) on ground with n_z > 0.95.
    """
    H, W = D.shape
    n = np.empty((H, W, 3), np.float32)
    zero = _F32(0.0)
    tiny = _F32(1e-12)
    snap_z = _F32(0.95)
    for h in range(H):
        hp = h + 1 if h + 1 < H else 0  # np.roll wraps around
        hm = h - 1 if h > 0 else H - 1
        for w in range(W):
            wp = w + 1 if w + 1 < W else 0
            wm = w - 1 if w > 0 else W - 1
            d = D[h, w]
            # along W (axis 1): a
            dzf = abs(D[h, wp] - d)
            dzb = abs(d - D[h, wm])
            if dzf <= dzb or not np.isfinite(dzb):
                a0 = P[h, wp, 0] - P[h, w, 0]
                a1 = P[h, wp, 1] - P[h, w, 1]
                a2 = P[h, wp, 2] - P[h, w, 2]
            else:
                a0 = P[h, w, 0] - P[h, wm, 0]
                a1 = P[h, w, 1] - P[h, wm, 1]
                a2 = P[h, w, 2] - P[h, wm, 2]
            # along H (axis 0): b
            dzf = abs(D[hp, w] - d)
            dzb = abs(d - D[hm, w])
            if dzf <= dzb or not np.isfinite(dzb):
                b0 = P[hp, w, 0] - P[h, w, 0]
                b1 = P[hp, w, 1] - P[h, w, 1]
                b2 = P[hp, w, 2] - P[h, w, 2]
            else:
                b0 = P[h, w, 0] - P[hm, w, 0]
                b1 = P[h, w, 1] - P[hm, w, 1]
                b2 = P[h, w, 2] - P[hm, w, 2]
            c0 = a1 * b2 - a2 * b1
            c1 = a2 * b0 - a0 * b2
            c2 = a0 * b1 - a1 * b0
            norm = np.sqrt((c0 * c0 + c1 * c1) + c2 * c2)
            if norm > tiny:
                c0 = c0 / norm
                c1 = c1 / norm
                c2 = c2 / norm
            else:
                c0 = zero
                c1 = zero
                c2 = zero
            t0 = cam_pos[0] - P[h, w, 0]
            t1 = cam_pos[1] - P[h, w, 1]
            t2 = cam_pos[2] - P[h, w, 2]
            if (c0 * t0 + c1 * t1) + c2 * t2 < zero:
                c0 = -c0
                c1 = -c1
                c2 = -c2
            if snap_material[material[h, w]] and c2 > snap_z:
                c0 = zero
                c1 = zero
                c2 = _F32(1.0)
            n[h, w, 0] = c0
            n[h, w, 1] = c1
            n[h, w, 2] = c2
    return n


@njit(cache=True, error_model="numpy")
def sun_cosine(n, sun_dir):
    """(H, W) float64 cos of the sun's incidence, n . sun_dir (numpy einsum order in float64)."""
    H, W = n.shape[0], n.shape[1]
    out = np.empty((H, W), np.float64)
    s0, s1, s2 = sun_dir[0], sun_dir[1], sun_dir[2]
    for h in range(H):
        for w in range(W):
            out[h, w] = (np.float64(n[h, w, 0]) * s0 + np.float64(n[h, w, 2]) * s2) + np.float64(n[h, w, 1]) * s1
    return out


@njit(cache=True, error_model="numpy")
def sky_and_sun(nz, sky_lux, ground_albedo, sky_colour, lit, cos_s, sun_lux, sun_colour, with_sun):
    """(H, W, 3) float32 illuminance from the sky hemisphere, ground bounce and (if `with_sun`)
    the unshadowed sun: E = E_sky(n_z) * sky_colour + [lit] cos_s * E_sun * sun_colour.

    Scalars `sky_lux` and `ground_albedo` are applied in float32 (as numpy does with Python floats
    on float32 arrays); the sun term is added in float64 and rounded once (numpy's `E += x` with a
    float64 x).
    """
    H, W = nz.shape
    E = np.empty((H, W, 3), np.float32)
    one = _F32(1.0)
    two = _F32(2.0)
    lux = _F32(sky_lux)
    ga = _F32(ground_albedo)
    for h in range(H):
        for w in range(W):
            z = nz[h, w]
            sky_e = lux * ((one + z) / two + ga * (one - z) / two)
            if with_sun:
                s = (cos_s[h, w] if lit[h, w] else 0.0) * sun_lux
                for c in range(3):
                    E[h, w, c] = _F32(np.float64(sky_e * sky_colour[c]) + s * np.float64(sun_colour[c]))
            else:
                for c in range(3):
                    E[h, w, c] = sky_e * sky_colour[c]
    return E


@njit(cache=True, error_model="numpy")
def radiance(index, material, albedo, per_instance, colour_table, E, emissive_on, emissive, geo, sky_elev, sky_h,
             sky_h_strong, sky_colour):
    """(H, W, 3) float32 radiance L = albedo * E / pi + emission; sky pixels get the sky gradient.

    Args:
        index: (H, W) int64 instance index. material: (H, W) uint8. albedo: (M, 3) float32 albedo of
        the materials; per_instance: (M,) bool, materials whose albedo comes from
        colour_table[index, material] (float32) where index > 0. E: (H, W, 3) float32.
        emissive_on: (M,) bool, materials glowing in this frame; emissive: (M, 3) float32.
        geo: (H, W) bool, pixel sees a surface. sky_elev: (K,) float32 clipped elevation (z of the
        world ray) of the K sky pixels in row-major order; sky_h: horizon sky radiance [cd/m^2];
        sky_colour: (3,) float32.
        sky_h_strong: sky_h was a numpy float64 scalar, which numpy does not demote to float32
        (NEP 50), so the sky gradient is computed in float64 and rounded once; a Python float is
        applied in float32.
    """
    H, W = geo.shape
    L = np.empty((H, W, 3), np.float32)
    pi = _F32(np.pi)
    half = _F32(0.5)
    one = _F32(1.0)
    skyh32 = _F32(sky_h)
    k = 0
    for h in range(H):
        for w in range(W):
            if geo[h, w]:
                m = material[h, w]
                i = index[h, w]
                for c in range(3):
                    a = colour_table[i, m, c] if per_instance[m] and i > 0 else albedo[m, c]
                    v = a * E[h, w, c] / pi
                    if emissive_on[m]:
                        v = v + emissive[m, c]
                    L[h, w, c] = v
            else:
                t = one - half * sky_elev[k]
                k += 1
                if sky_h_strong:
                    g = sky_h * np.float64(t)
                    for c in range(3):
                        L[h, w, c] = _F32(g * np.float64(sky_colour[c]))
                else:
                    g32 = skyh32 * t
                    for c in range(3):
                        L[h, w, c] = g32 * sky_colour[c]
    return L


@njit(cache=True)
def instance_ids(index, actor_ids):
    """(H, W) int64 simulator actor id per pixel: actor_ids[index - 1] where index > 0, else 0, as
    np.where(index > 0, concatenate([[0], actor_ids])[clip(index, 0, len(actor_ids))], 0)."""
    H, W = index.shape
    n = actor_ids.shape[0]
    out = np.zeros((H, W), np.int64)
    for h in range(H):
        for w in range(W):
            i = min(index[h, w], n)
            if index[h, w] > 0 and i > 0:
                out[h, w] = actor_ids[i - 1]
    return out


@njit(cache=True)
def take_max(best, state, c, v):
    """One step of `cell_max`: value v into cell c (state: 0 empty, 1 has a value, 2 holds NaN)."""
    if np.isnan(v):
        best[c] = v
        state[c] = 2
    elif state[c] == 0 or (state[c] == 1 and v >= best[c]):
        best[c] = v
        state[c] = 1


@njit(cache=True, error_model="numpy")
def cell_max(cells, values, n):
    """(n,) float32 per-cell maximum of `values` (0 where a cell has none), as
    `sensors.lidar._cell_max` (a stable sort by value, last per cell): among equal values the later
    one wins, NaN is the largest; the maximum is taken in the input precision and rounded once."""
    best = np.zeros(n, values.dtype)
    state = np.zeros(n, np.uint8)
    for i in range(cells.shape[0]):
        take_max(best, state, cells[i], values[i])
    return best.astype(np.float32)


# --- camera model ------------------------------------------------------------------------------


@njit(cache=True)
def _reflect(i, n):
    """Index i of a line of length n extended as scipy.ndimage's mode 'reflect' (d c b a | a b c d | d c b a)."""
    i = i % (2 * n)
    return i if i < n else 2 * n - 1 - i


@njit(cache=True, error_model="numpy")
def _taps5(out, c, l2, l1, r1, r2, w0, w1, w2):
    """out[k] = (c w2 + (l2 + r2) w0) + (l1 + r1) w1 in float64, rounded to out's dtype once."""
    for k in range(out.shape[0]):
        out[k] = (np.float64(c[k]) * w2 + (np.float64(l2[k]) + np.float64(r2[k])) * w0) + \
            (np.float64(l1[k]) + np.float64(r1[k])) * w1


@njit(cache=True, error_model="numpy")
def gaussian_blur5_hw(x, weights):
    """`scipy.ndimage.gaussian_filter(x, sigma=(s, s, 0))` of an (H, W, C) array with a 5-tap kernel
    (radius 2: sigma 0.5 with scipy's truncate 4), mode 'reflect'.

    As scipy's `correlate1d` computes a symmetric kernel: one pass along H, then one along W, the
    first rounded to x's dtype in between; each output in float64 as
    (x[i] w[2] + (x[i - 2] + x[i + 2]) w[0]) + (x[i - 1] + x[i + 1]) w[1], rounded once.

    Args:
        x: (H, W, C) float32 or float64. weights: (5,) float64 symmetric kernel
        (`sensors.camera._PSF_WEIGHTS`).
    Returns:
        (H, W, C) array of x's dtype.
    """
    H, W, C = x.shape
    w0, w1, w2 = weights[0], weights[1], weights[2]
    src = np.ascontiguousarray(x).reshape(H, W * C)
    tmp = np.empty((H, W * C), x.dtype)
    out = np.empty((H, W * C), x.dtype)
    for h in range(H):  # along H: whole rows
        _taps5(tmp[h], src[h], src[_reflect(h - 2, H)], src[_reflect(h - 1, H)], src[_reflect(h + 1, H)],
               src[_reflect(h + 2, H)], w0, w1, w2)
    n = W * C
    for h in range(H):  # along W: the row shifted by C elements; the two columns at each end reflected
        line, res = tmp[h], out[h]
        if W > 4:
            _taps5(res[2 * C:n - 2 * C], line[2 * C:n - 2 * C], line[:n - 4 * C], line[C:n - 3 * C],
                   line[3 * C:n - C], line[4 * C:], w0, w1, w2)
        for w in range(W):
            if 2 <= w < W - 2:
                continue
            a, b = _reflect(w - 2, W) * C, _reflect(w - 1, W) * C
            d, e = _reflect(w + 1, W) * C, _reflect(w + 2, W) * C
            k = w * C
            _taps5(res[k:k + C], line[k:k + C], line[a:a + C], line[b:b + C], line[d:d + C], line[e:e + C],
                   w0, w1, w2)
    return out.reshape(H, W, C)


@njit(cache=True, error_model="numpy")
def shot_and_read_noise_apply(electrons, low, poisson_draws, normal_hi, normal_read, read_noise_e):
    """Combine the draws of `sensors.camera.shot_and_read_noise` (float32 arithmetic as numpy's):
    out = Poisson draw where electrons < 30, lam + sqrt(lam) z otherwise, then + read_noise_e z'.

    Args:
        electrons: (N,) float32 or float64 (rounded to float32 where used, as numpy did); low: (N,) bool; poisson_draws: (low.sum(),) int64 in the order of
        the low pixels; normal_hi: (N - low.sum(),) float32; normal_read: (N,) float32.
    """
    n = electrons.shape[0]
    out = np.empty(n, np.float32)
    r = _F32(read_noise_e)
    i_low = 0
    i_hi = 0
    for i in range(n):
        if low[i]:
            v = np.float32(poisson_draws[i_low])
            i_low += 1
        else:
            lam = np.float32(electrons[i])
            v = lam + np.sqrt(lam) * normal_hi[i_hi]
            i_hi += 1
        out[i] = v + r * normal_read[i]
    return out


@njit(cache=True, error_model="numpy")
def exposed_electrons(blurred, k, full_well):
    """`np.clip(blurred * k, 0, 1) * full_well` of float32 `blurred` with Python-float k and
    full_well (applied in float32, NEP 50): the signal in electrons, float32, same shape."""
    flat = blurred.reshape(-1)
    out = np.empty(flat.shape[0], np.float32)
    k32 = _F32(k)
    fw = _F32(full_well)
    zero = _F32(0.0)
    one = _F32(1.0)
    for i in range(flat.shape[0]):
        v = flat[i] * k32
        if v < zero:
            v = zero
        elif v > one:
            v = one
        out[i] = v * fw
    return out.reshape(blurred.shape)


@njit(cache=True, error_model="numpy")
def noisy_srgb(noisy, full_well, gain, lut):
    """`srgb_lookup(noisy / full_well * gain, lut)` of float32 `noisy` [e-] with Python-float
    full_well and gain (applied in float32, NEP 50)."""
    flat = noisy.reshape(-1)
    out = np.empty(flat.shape[0], np.float32)
    fw = _F32(full_well)
    g = _F32(gain)
    zero = _F32(0.0)
    one = _F32(1.0)
    scale = _F32(65535.0)
    half = _F32(0.5)
    for i in range(flat.shape[0]):
        v = flat[i] / fw * g
        v = max(v, zero)
        v = min(v, one)
        out[i] = lut[np.int32(v * scale + half)]
    return out.reshape(noisy.shape)


@njit(cache=True, error_model="numpy")
def srgb_lookup(x, lut):
    """`sensors.camera.srgb_encode_fast` of float32 `x` (any shape, flattened): lut[int(clip(x) * 65535 + 0.5)]."""
    flat = x.reshape(-1)
    out = np.empty(flat.shape[0], np.float32)
    zero = _F32(0.0)
    one = _F32(1.0)
    scale = _F32(65535.0)
    half = _F32(0.5)
    for i in range(flat.shape[0]):
        v = flat[i]
        v = max(v, zero)
        v = min(v, one)
        out[i] = lut[np.int32(v * scale + half)]
    return out.reshape(x.shape)


@njit(cache=True, error_model="numpy")
def to_uint8(x):
    """`sensors.camera.to_uint8` of float32 `x`: round-half-even(clip(x, 0, 1) * 255) as uint8."""
    flat = x.reshape(-1)
    out = np.empty(flat.shape[0], np.uint8)
    zero = _F32(0.0)
    one = _F32(1.0)
    scale = _F32(255.0)
    for i in range(flat.shape[0]):
        v = flat[i]
        v = max(v, zero)
        v = min(v, one)
        out[i] = np.uint8(np.rint(v * scale))
    return out.reshape(x.shape)


# --- visibility pass ---------------------------------------------------------------------------


@njit(cache=True, error_model="numpy")
def linear_depth(buffer, znear, zfar):
    """`sensors.camera.linear_depth` in float32 as numpy computes it with Python-float near and far:
    1 (nothing drawn) -> 0, else z_ndc = 2 d - 1, depth = f32(2 n f) / (f32(f + n) - z_ndc f32(f - n)).

    Args:
        buffer: (H, W) float32 depth-buffer values in 0..1 (any strides).
    Returns:
        (H, W) float32 [m].
    """
    H, W = buffer.shape
    out = np.empty((H, W), np.float32)
    two = _F32(2.0)
    one = _F32(1.0)
    num = _F32(2.0 * znear * zfar)
    fpn = _F32(zfar + znear)
    fmn = _F32(zfar - znear)
    for h in range(H):
        for w in range(W):
            d = buffer[h, w]
            out[h, w] = _F32(0.0) if d == one else num / (fpn - (two * d - one) * fmn)
    return out


@njit(cache=True)
def decode_codes(colour, depth):
    """Decode the flat-colour pass (`sensors.camera.StereoRenderer.codes`): instance index from
    R + 256 G, material from B, depth [m] (inf where nothing was drawn, alpha != 255, or depth <= 0).

    Args:
        colour: (H, W, 4) uint8 RGBA; depth: (H, W) float32 linear depth [m] (0 = background).
    Returns:
        index (H, W) int64, material (H, W) uint8, depth (H, W) float32.
    """
    H, W = depth.shape
    index = np.zeros((H, W), np.int64)
    material = np.zeros((H, W), np.uint8)
    out = np.empty((H, W), np.float32)
    for h in range(H):
        for w in range(W):
            if colour[h, w, 3] == 255:
                index[h, w] = np.int64(colour[h, w, 0]) | (np.int64(colour[h, w, 1]) << 8)
                material[h, w] = colour[h, w, 2]
                d = depth[h, w]
                out[h, w] = d if d > 0 else np.inf
            else:
                out[h, w] = np.inf
    return index, material, out


# --- artificial light ----------------------------------------------------------------------------


@njit(cache=True, error_model="numpy")
def _lamp_illuminance(tz, cos_i, dist2, lamp_cd):
    """np.float32(lamp_cd * min(max(tz, 0), 1) ** 1.5 * cos_i / max(dist2, 0.25)) (float64, libm pow).

    pow costs most of the lamps' time; c * sqrt(c) is within a few float64 ulps of c ** 1.5, and so
    is the illuminance computed from it (relative error < 2e-15). Where every value within 2^-40
    (relative) of it rounds to the same float32, so does the one computed with pow (rounding is
    monotonic); otherwise (about one in 10^5) pow decides.
    """
    c = min(max(tz, 0.0), 1.0)
    dmax = max(dist2, 0.25)
    e = lamp_cd * (c * np.sqrt(c)) * cos_i / dmax
    band = 9.094947017729282e-13  # 2^-40
    if np.float32(e * (1.0 - band)) == np.float32(e * (1.0 + band)):
        return np.float32(e)
    return np.float32(lamp_cd * c ** 1.5 * cos_i / dmax)


@njit(cache=True, error_model="numpy")
def artificial_light(P, n, geo, E, lamps, lamp_cd, lamp_colour, heads, axes, head_cd, head_colour,
                     h_width_deg, v_width_deg):
    """Add the illuminance [lx, RGB] of street lamps and dipped headlights to E at the surface pixels.

    Per light, as the numpy formulation in tests/sensors/test_kernels.py (`reference_lights`):
    inverse square law with the distance floored at 0.5 m, Lambert's cosine, and the source's beam
    pattern towards the point. Lamps: a cut-off luminaire, I = lamp_cd * cos^1.5 of the angle from
    straight down, nothing above the horizontal (`_lamp_illuminance`). Headlights: a Gaussian beam
    around `axes` (h_width_deg across, v_width_deg up-down) cut to 3 % above 0.5 deg up. Unlike the
    other kernels of this module, exp, pow and atan2 come from libm here: the same bits as numpy's
    on the reference machine, possibly one ulp apart on another (module docstring).

    Args:
        P, n: (H, W, 3) float32 surface points and unit normals (world). geo: (H, W) bool, the
        pixels with a surface. E: (H, W, 3) float32, updated in place: E += the lights' sum (in
        float32, in the order lamps then headlights, from 0), as numpy's E[geo] += Ef.
        lamps: (L, 3) float64 lamp heads; heads, axes: (K, 3) float64 headlight positions, unit axes.
        lamp_colour, head_colour: (3,) float32.
    """
    H, W = geo.shape
    deg = 180.0 / np.pi
    for hh in range(H):
        for ww in range(W):
            if not geo[hh, ww]:
                continue
            px = np.float64(P[hh, ww, 0])
            py = np.float64(P[hh, ww, 1])
            pz = np.float64(P[hh, ww, 2])
            nx = np.float64(n[hh, ww, 0])
            ny = np.float64(n[hh, ww, 1])
            nz = np.float64(n[hh, ww, 2])
            e0 = _F32(0.0)
            e1 = _F32(0.0)
            e2 = _F32(0.0)
            for k in range(lamps.shape[0] + heads.shape[0]):
                lamp = k < lamps.shape[0]
                if lamp:
                    dx = lamps[k, 0] - px
                    dy = lamps[k, 1] - py
                    dz = lamps[k, 2] - pz
                else:
                    j = k - lamps.shape[0]
                    dx = heads[j, 0] - px
                    dy = heads[j, 1] - py
                    dz = heads[j, 2] - pz
                dist2 = (dx * dx + dz * dz) + dy * dy
                dist = np.sqrt(dist2)
                inv = max(dist, 1e-6)
                tx = dx / inv
                ty = dy / inv
                tz = dz / inv
                cos_i = (nx * tx + nz * tz) + ny * ty
                if not cos_i > 0:
                    continue
                if lamp:
                    e = _lamp_illuminance(tz, cos_i, dist2, lamp_cd)
                    colour = lamp_colour
                else:
                    # the beam towards the point: direction = -to_light
                    ax, ay, az = axes[j, 0], axes[j, 1], axes[j, 2]
                    cos_axis = (-tx) * ax + (-ty) * ay + (-tz) * az
                    if not cos_axis > 0:
                        continue
                    side = (-tx) * ay + (-ty) * (-ax)  # direction . (axis x up), up = +z
                    h = np.arctan2(side, cos_axis) * deg
                    v = np.arctan2(-tz, cos_axis) * deg
                    w = np.exp(-((h / h_width_deg) ** 2) - ((v / v_width_deg) ** 2))
                    if v > 0.5:
                        w = w * 0.03
                    e = np.float32(head_cd * w * cos_i / max(dist2, 0.25))
                    colour = head_colour
                e0 += e * colour[0]
                e1 += e * colour[1]
                e2 += e * colour[2]
            E[hh, ww, 0] += e0
            E[hh, ww, 1] += e1
            E[hh, ww, 2] += e2
