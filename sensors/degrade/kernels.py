"""Compiled cores of the camera degradations (numba, cached on disk).

Like sensors.kernels, every kernel repeats the library code it replaces operation by operation, in
the same precision and order, so its output is bit-identical (tests/sensors/test_degrade_kernels.py
compares them with scipy and numpy):

- `gaussian_blur` is scipy.ndimage.gaussian_filter(x, sigma=(s_rows, s_cols, 0)) on float32
  images: scipy's own kernel weights, its symmetric correlation (centre first, then the pairs of
  samples from the outermost inwards, summed in float64), the float32 result of the first pass fed
  to the second, and the 'reflect' boundary. scipy walks one image line at a time; here a pass
  sweeps whole rows, so the same sums run over contiguous memory.
- `zoom_linear` is scipy.ndimage.zoom(x, factors, order=1): scipy's sample positions, boundary
  taps and weights, and its float64 sum of the corner terms in the same order.
- `block_mean` and `channel_mean` are numpy's means over the pixel axes of an (H, W, C >= 2)
  float32 image, which numpy sums element after element in memory order (not pairwise).
- the blends (`airlight_blend`, `masked_mix`, `snow_cover`, `soiling_cover`) are the models'
  float32 numpy expressions in one pass, without full-size temporaries; Python-float factors are
  passed as the float32 scalars numpy would turn them into.
- no fused multiply-add (numba does not contract ``a * b + c`` without fastmath, nor does scipy's
  C code or numpy's elementwise loops), and no transcendental function: exp and pow stay in numpy.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numba import njit
from scipy.ndimage._filters import _gaussian_kernel1d

_F32 = np.float32


@lru_cache(maxsize=64)
def gaussian_weights(sigma: float) -> np.ndarray:
    """scipy.ndimage.gaussian_filter1d's correlation weights (truncate 4): 2 r + 1 float64 values,
    r = int(4 sigma + 0.5)."""
    return _gaussian_kernel1d(sigma, 0, int(4.0 * float(sigma) + 0.5))[::-1].copy()


@njit(cache=True)
def _reflect(i, n):
    """scipy.ndimage's 'reflect' boundary (d c b a | a b c d | d c b a): the index read for i."""
    m = i % (2 * n)
    return m if m < n else 2 * n - 1 - m


@njit(cache=True)
def _correlate_rows(x, w):
    """Symmetric correlation of float32 x (H, M) with weights w (2 r + 1,) along axis 0."""
    H, M = x.shape
    r = len(w) // 2
    out = np.empty((H, M), np.float32)
    acc = np.empty(M, np.float64)
    for h in range(H):
        centre = w[r]
        here = x[h]
        for m in range(M):
            acc[m] = np.float64(here[m]) * centre
        for k in range(r, 0, -1):
            above = x[_reflect(h - k, H)]
            below = x[_reflect(h + k, H)]
            wk = w[r - k]
            for m in range(M):
                acc[m] += (np.float64(above[m]) + np.float64(below[m])) * wk
        row = out[h]
        for m in range(M):
            row[m] = np.float32(acc[m])
    return out


@njit(cache=True)
def _correlate_cols(x, w):
    """Symmetric correlation of float32 x (H, W, C) with weights w (2 r + 1,) along axis 1."""
    H, W, C = x.shape
    r = len(w) // 2
    n = W * C
    out = np.empty((H, n), np.float32)
    line = np.empty((W + 2 * r) * C, np.float64)  # one row, extended by r samples on each side
    acc = np.empty(n, np.float64)
    for h in range(H):
        for j in range(W + 2 * r):
            src = _reflect(j - r, W)
            for c in range(C):
                line[j * C + c] = np.float64(x[h, src, c])
        centre = w[r]
        for m in range(n):
            acc[m] = line[r * C + m] * centre
        for k in range(r, 0, -1):
            left = line[(r - k) * C:(r - k) * C + n]  # the row shifted by -k and +k samples
            right = line[(r + k) * C:(r + k) * C + n]
            wk = w[r - k]
            for m in range(n):
                acc[m] += (left[m] + right[m]) * wk
        row = out[h]
        for m in range(n):
            row[m] = np.float32(acc[m])
    return out.reshape(H, W, C)


def gaussian_blur(image: np.ndarray, sigma_rows: float, sigma_cols: float) -> np.ndarray:
    """scipy.ndimage.gaussian_filter(image, sigma=(sigma_rows, sigma_cols, 0)), bit for bit, for a
    float32 (H, W, C) image (mode 'reflect', truncate 4): rows first, then columns, a sigma of
    1e-15 or less skipping its axis as scipy does. Returns a new float32 array."""
    if image.dtype != np.float32 or image.ndim != 3:
        raise ValueError(f"gaussian_blur takes a float32 (H, W, C) image, got {image.dtype} {image.shape}")
    out = image
    H, W, C = image.shape
    if sigma_rows > 1e-15:
        rows = np.ascontiguousarray(out).reshape(H, W * C)  # a row pass treats (W, C) as one line
        out = _correlate_rows(rows, gaussian_weights(sigma_rows)).reshape(H, W, C)
    if sigma_cols > 1e-15:
        out = _correlate_cols(np.ascontiguousarray(out), gaussian_weights(sigma_cols))
    return out.copy() if out is image else out


@njit(cache=True)
def _linear_taps(n_in, n_out):
    """scipy.ndimage.zoom's order-1 sampling along one axis (mode 'constant', grid_mode False):
    for each output index, the two input indices, their weights and whether it lies outside."""
    zoom = (n_in - 1) / (n_out - 1) if n_out > 1 else 1.0
    index = np.empty((n_out, 2), np.int64)
    weight = np.empty((n_out, 2), np.float64)
    outside = np.zeros(n_out, np.bool_)
    for k in range(n_out):
        cc = np.float64(k) * zoom
        if cc < 0 or cc > n_in - 1:  # map_coordinate: constant mode maps it to -1, the cval
            outside[k] = True
            index[k, 0] = index[k, 1] = 0
            weight[k, 0] = weight[k, 1] = 0.0
            continue
        start = np.int64(np.floor(cc))
        for t in range(2):
            i = start + t
            if start < 0 or start + 1 >= n_in:  # scipy's edge taps: mirrored (spline boundary)
                i = _mirror(i, n_in)
            index[k, t] = i
        x = cc - np.floor(cc)
        weight[k, 0] = 1.0 - x
        weight[k, 1] = 1.0 - weight[k, 0]
    return index, weight, outside


@njit(cache=True)
def _mirror(i, n):
    """scipy.ndimage's map_coordinate in 'mirror' mode (c b | a b c d | c b) for an integer index."""
    if n <= 1:
        return 0
    period = 2 * n - 2
    if i < 0:
        i = period * ((-i) // period) + i
        return i + period if i <= 1 - n else -i
    if i > n - 1:
        i -= period * (i // period)
        if i >= n:
            i = period - i
    return i


@njit(cache=True)
def _zoom_linear(x, Ho, Wo, Co):
    H, W, C = x.shape
    ri, rw, rout = _linear_taps(H, Ho)
    ci, cw, cout = _linear_taps(W, Wo)
    ki, kw, kout = _linear_taps(C, Co)
    out = np.zeros((Ho, Wo, Co), np.float32)  # outside samples: cval 0
    top = np.empty((W, C), np.float64)  # the output row's two source rows, times their weights
    bottom = np.empty((W, C), np.float64)
    for i in range(Ho):
        if rout[i]:
            continue
        for s in range(W):
            for ch in range(C):
                top[s, ch] = np.float64(x[ri[i, 0], s, ch]) * rw[i, 0]
                bottom[s, ch] = np.float64(x[ri[i, 1], s, ch]) * rw[i, 1]
        for j in range(Wo):
            if cout[j]:
                continue
            j0, j1 = ci[j, 0], ci[j, 1]
            c0, c1 = cw[j, 0], cw[j, 1]
            for k in range(Co):
                if kout[k]:
                    continue
                k0, k1 = ki[k, 0], ki[k, 1]
                q0, q1 = kw[k, 0], kw[k, 1]
                t = 0.0  # scipy's tap order: the last axis fastest
                t += (top[j0, k0] * c0) * q0
                t += (top[j0, k1] * c0) * q1
                t += (top[j1, k0] * c1) * q0
                t += (top[j1, k1] * c1) * q1
                t += (bottom[j0, k0] * c0) * q0
                t += (bottom[j0, k1] * c0) * q1
                t += (bottom[j1, k0] * c1) * q0
                t += (bottom[j1, k1] * c1) * q1
                out[i, j, k] = np.float32(t)
    return out


def zoom_linear(x: np.ndarray, factors: tuple) -> np.ndarray:
    """scipy.ndimage.zoom(x, factors, order=1), bit for bit, for a float32 (H, W, C) array (mode
    'constant', cval 0): each output sample sums its 8 corner terms ((value * w_row) * w_col) *
    w_channel in scipy's order, in float64, and rounds to float32 once."""
    if x.dtype != np.float32 or x.ndim != 3:
        raise ValueError(f"zoom_linear takes a float32 (H, W, C) array, got {x.dtype} {x.shape}")
    if all(f == 1 for f in factors):
        return x.copy()  # scipy returns the input unchanged (no interpolation of inf / NaN neighbours)
    shape = [int(round(n * f)) for n, f in zip(x.shape, factors)]
    return _zoom_linear(x, *shape)


@njit(cache=True)
def airlight_blend(radiance, t, airlight):
    """Koschmieder's blend ``radiance * t[..., None] + airlight * (1 - t[..., None])`` of float32
    radiance (H, W, C), transmittance t (H, W) and airlight (C,), all float32 as numpy computes it."""
    H, W, C = radiance.shape
    out = np.empty((H, W, C), np.float32)
    one = _F32(1.0)
    for h in range(H):
        for w in range(W):
            tt = t[h, w]
            rest = one - tt
            for c in range(C):
                out[h, w, c] = radiance[h, w, c] * tt + airlight[c] * rest
    return out


@njit(cache=True)
def masked_mix(radiance, mask, keep, add, other):
    """A float32 copy of radiance (H, W, C) where, inside mask (H, W), each value becomes
    ``radiance * keep + add * other`` (numpy: ``L[mask] = L[mask] * keep + add * other[mask]`` with
    float32 scalars keep and add)."""
    H, W, C = radiance.shape
    out = radiance.copy()
    for h in range(H):
        for w in range(W):
            if mask[h, w]:
                for c in range(C):
                    out[h, w, c] = radiance[h, w, c] * keep + add * other[h, w, c]
    return out


@njit(cache=True)
def snow_cover(radiance, inside, soft, blurred, t, ambient_part):
    """Snow patches on the lens: a float32 copy of radiance (H, W, C) where, inside (H, W), each
    value becomes ``(1 - soft) * L + soft * (t * blurred + ambient_part)``, soft (H, W) float32,
    t a float32 scalar and ambient_part = (1 - t) * ambient (C,) float32 (numpy's
    ``np.where(inside[..., None], (1 - soft) * L + soft * mix, L)`` with
    ``mix = t * blurred + (1 - t) * ambient``)."""
    H, W, C = radiance.shape
    out = radiance.copy()
    one = _F32(1.0)
    for h in range(H):
        for w in range(W):
            if inside[h, w]:
                s = soft[h, w]
                for c in range(C):
                    mix = t * blurred[h, w, c] + ambient_part[c]
                    out[h, w, c] = (one - s) * radiance[h, w, c] + s * mix
    return out


@njit(cache=True)
def soiling_cover(radiance, opaque, semi, soft, mud, blurred):
    """Dirt on the lens: a float32 copy of radiance (H, W, C) where opaque pixels (H, W) become
    ``(1 - soft) * L + soft * mud`` (mud (C,)) and semi-transparent ones
    ``(1 - soft) * L + soft * 0.5 * blurred``, soft (H, W), all float32 in numpy's order."""
    H, W, C = radiance.shape
    out = radiance.copy()
    one = _F32(1.0)
    half = _F32(0.5)
    for h in range(H):
        for w in range(W):
            s = soft[h, w]
            if opaque[h, w]:
                for c in range(C):
                    out[h, w, c] = (one - s) * radiance[h, w, c] + s * mud[c]
            elif semi[h, w]:
                for c in range(C):
                    out[h, w, c] = (one - s) * radiance[h, w, c] + s * half * blurred[h, w, c]
    return out


@njit(cache=True)
def _block_sums(x, f):
    H, W, C = x.shape
    out = np.empty((H // f, W // f, C), np.float32)
    for i in range(H // f):
        for j in range(W // f):
            for c in range(C):
                s = _F32(0.0)  # numpy's reduction starts from its identity, then adds in memory order
                for a in range(f):
                    for b in range(f):
                        s += x[i * f + a, j * f + b, c]
                out[i, j, c] = s
    return out


def block_mean(x: np.ndarray, f: int) -> np.ndarray:
    """Mean pooling of x (H, W, C) over f x f blocks, bit for bit numpy's
    ``x[:H // f * f, :W // f * f].reshape(H // f, f, W // f, f, C).mean(axis=(1, 3))`` for a
    C-contiguous float32 x with C >= 2 channels: numpy then sums in float32 in memory order (with a
    single channel the summed axis is innermost and numpy sums pairwise), then divides by the count."""
    _check_pixels(x, "block_mean")
    sums = _block_sums(x, f)
    return np.true_divide(sums, np.intp(f * f), out=sums, casting="unsafe")


@njit(cache=True)
def _channel_sums(x):
    H, W, C = x.shape
    out = np.zeros(C, np.float32)  # numpy's reduction starts from its identity, then adds in memory order
    for h in range(H):
        for w in range(W):
            for c in range(C):
                out[c] += x[h, w, c]
    return out


def channel_mean(x: np.ndarray) -> np.ndarray:
    """Per-channel mean, bit for bit ``np.mean(x, axis=(0, 1))`` for a C-contiguous float32 x
    (H, W, C) with C >= 2 channels (numpy then sums pixel after pixel in float32, not pairwise) and
    at least one pixel."""
    _check_pixels(x, "channel_mean")
    sums = _channel_sums(x)
    return np.true_divide(sums, np.intp(x.shape[0] * x.shape[1]), out=sums, casting="unsafe")


def _check_pixels(x: np.ndarray, what: str) -> None:
    if x.dtype != np.float32 or x.ndim != 3 or x.shape[2] < 2 or x.size == 0 or not x.flags.c_contiguous:
        raise ValueError(f"{what} takes a non-empty C-contiguous float32 (H, W, C >= 2) array, "
                         f"got {x.dtype} {x.shape}")


@njit(cache=True)
def blend_segments(L, depth, p0, p1, z, n_samples, alpha, radiance):
    """Alpha-blend sampled line segments into float32 L (H, W, C), in place.

    Segment i is sampled at n_samples[i] points p0 + (p1 - p0) t, t = k / max(n - 1, 1); a sample
    lands in pixel (floor u, floor v) when that is inside the image and the segment (depth z[i]) is
    in front of depth[v, u]. Each pixel is blended once, with the sample of the largest alpha (the
    earliest of equal ones): L = (1 - a) L + a radiance[i], in float64, stored as float32. This is
    numpy's lexsort((-a, pixel)) selection of camera._segments, sample for sample."""
    H, W, C = L.shape
    best = np.full(H * W, -1, np.int64)  # segment of the chosen sample per pixel
    best_a = np.zeros(H * W, np.float64)
    touched = np.empty(H * W, np.int64)
    n_touched = 0
    for i in range(len(n_samples)):
        n = n_samples[i]
        denom = max(n - 1, 1)
        for k in range(n):
            t = k / denom
            u = np.int64(np.floor(p0[i, 0] + (p1[i, 0] - p0[i, 0]) * t))
            v = np.int64(np.floor(p0[i, 1] + (p1[i, 1] - p0[i, 1]) * t))
            if u < 0 or u >= W or v < 0 or v >= H or not z[i] < depth[v, u]:
                continue
            pix = v * W + u
            if best[pix] < 0:
                touched[n_touched] = pix
                n_touched += 1
                best[pix] = i
                best_a[pix] = alpha[i]
            elif alpha[i] > best_a[pix]:
                best[pix] = i
                best_a[pix] = alpha[i]
    for j in range(n_touched):
        pix = touched[j]
        i = best[pix]
        a = best_a[pix]
        h, w = pix // W, pix % W
        for c in range(C):
            L[h, w, c] = np.float32((1.0 - a) * np.float64(L[h, w, c]) + a * np.float64(radiance[i, c]))
