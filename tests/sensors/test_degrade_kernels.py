"""The compiled degradation kernels (sensors.degrade.kernels) against the scipy / numpy code they
replace, bit for bit, and the camera models that use them against their plain numpy formulation."""

import dataclasses

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter, map_coordinates, zoom

from sensors.degrade import DEGRADATIONS, DegradeContext
from sensors.degrade import camera as cam_deg
from sensors.degrade.kernels import (
    airlight_blend,
    block_mean,
    channel_mean,
    gaussian_blur,
    masked_mix,
    snow_cover,
    soiling_cover,
    zoom_linear,
)
from sim.scenario import Context

RNG = np.random.default_rng(7)


def _images():
    """Float32 (H, W, C) test images: radiance-like, with inf/NaN/-0, cancelling, tiny, one row/column."""
    rad = (RNG.lognormal(3.0, 2.0, (60, 90, 3))).astype(np.float32)
    special = RNG.uniform(0, 1, (9, 11, 3)).astype(np.float32)
    special[2, 3, 0] = np.inf
    special[5, 7, 1] = np.nan
    special[0, 0, :] = -0.0
    # huge values of both signs next to small ones: large cancelling float64 sums
    cancelling = RNG.choice(np.array([-1e12, 1e12, 1.0, 0.5], np.float32), (20, 30, 3))
    return [rad, special, cancelling, RNG.uniform(size=(1, 1, 3)).astype(np.float32),
            RNG.uniform(size=(1, 17, 3)).astype(np.float32), RNG.uniform(size=(13, 1, 2)).astype(np.float32),
            RNG.normal(size=(5, 4, 1)).astype(np.float32)]


def same(a, b):
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


@pytest.mark.parametrize("sigmas", [(4.0, 1.5), (2.0, 2.0), (5.0, 5.0), (0.1, 3.0), (3.0, 0.0), (0.0, 0.0),
                                    (1e-16, 0.7), (30.0, 12.0)])
def test_gaussian_blur_equals_scipy(sigmas):
    """Including radii longer than the image (scipy's 'reflect' then wraps around several times)."""
    for x in _images():
        ref = gaussian_filter(x, sigma=(sigmas[0], sigmas[1], 0))
        out = gaussian_blur(x, *sigmas)
        assert same(ref, out), (sigmas, x.shape)
        assert out is not x


def test_gaussian_blur_takes_float32_images_only():
    with pytest.raises(ValueError):
        gaussian_blur(np.zeros((4, 4, 3)), 1.0, 1.0)
    with pytest.raises(ValueError):
        gaussian_blur(np.zeros((4, 4), np.float32), 1.0, 1.0)


@pytest.mark.parametrize("factors", [(4, 4, 1), (2, 3, 1), (1, 1, 1), (0.5, 2, 1), (3, 4, 2), (1.3, 2.7, 1)])
def test_zoom_linear_equals_scipy(factors):
    """Order-1 zoom; some factors put the last sample a rounding error outside the input (cval 0)."""
    for x in _images() + [RNG.uniform(size=(47, 84, 3)).astype(np.float32)]:
        assert same(zoom(x, factors, order=1), zoom_linear(x, factors)), (factors, x.shape)


def test_block_and_channel_means_equal_numpy():
    """numpy sums these layouts in memory order (not pairwise) in float32, from +0."""
    xs = [x for x in _images() if x.shape[2] >= 2]
    xs += [-np.zeros((8, 8, 3), np.float32), (RNG.uniform(size=(188, 336, 3)) * 3e4).astype(np.float32),
           RNG.uniform(size=(31, 45, 4)).astype(np.float32)]
    for x in xs:
        H, W, C = x.shape
        for f in (1, 2, 4):
            if H >= f and W >= f:
                ref = x[:H // f * f, :W // f * f].reshape(H // f, f, W // f, f, C).mean(axis=(1, 3))
                assert same(ref, block_mean(x, f)), (x.shape, f)
        assert same(np.mean(x, axis=(0, 1)), channel_mean(x)), x.shape


def test_means_refuse_layouts_numpy_sums_differently():
    for bad in (np.ones((6, 6, 1), np.float32), np.ones((6, 6, 3)), np.ones((6, 6, 3), np.float32)[:, ::2],
                np.ones((0, 6, 3), np.float32)):
        with pytest.raises(ValueError):
            channel_mean(bad)
        with pytest.raises(ValueError):
            block_mean(bad, 2)


def test_blend_kernels_equal_numpy():
    for x in _images():
        H, W, C = x.shape
        t = np.exp(-RNG.uniform(0, 3, (H, W))).astype(np.float32)
        t.flat[0] = np.nan  # exp(-0 * inf) of a sky pixel in clear air
        A = RNG.uniform(1, 100, C).astype(np.float32)
        ref = (x * t[..., None] + A * (1 - t[..., None])).astype(np.float32)
        assert same(ref, airlight_blend(x, t, A))

        other = RNG.uniform(0, 50, x.shape).astype(np.float32)
        for mask in (RNG.uniform(size=(H, W)) < 0.4, np.zeros((H, W), bool), np.ones((H, W), bool)):
            w, fresnel = 0.7, 0.08
            ref = x.copy()
            ref[mask] = ref[mask] * (1 - 0.45 * w) + fresnel * w * other[mask]
            assert same(ref, masked_mix(x, mask, np.float32(1 - 0.45 * w), np.float32(fresnel * w), other))

            soft = (0.85 * np.clip(1 - RNG.uniform(0, 1.2, (H, W)).astype(np.float32), 0, 1) ** 0.6)
            tr = 0.4
            mix = tr * other + (1 - tr) * A
            ref = np.where(mask[..., None], (1 - soft[..., None]) * x + soft[..., None] * mix, x).astype(np.float32)
            assert same(ref, snow_cover(x, mask, soft, other, np.float32(tr), np.float32(1 - tr) * A))

            opaque = mask & (RNG.uniform(size=(H, W)) < 0.5)
            semi = mask & ~opaque
            mud = np.array([0.02, 0.015, 0.01], np.float32)[:C] * np.float32(3.0)
            s3 = soft[..., None]
            ref = np.where(opaque[..., None], (1 - s3) * x + s3 * mud, x)
            ref = np.where(semi[..., None], (1 - s3) * ref + s3 * 0.5 * other, ref).astype(np.float32)
            assert same(ref, soiling_cover(x, opaque, semi, soft, mud, other))


# --- the camera models against their numpy formulation ---------------------------------------------


def _reference(name, obs, params, ctx):
    """The straightforward numpy / scipy formulation of the camera models that use the kernels."""
    H, W = obs.depth.shape
    sc = cam_deg._scale(ctx)
    cam = ctx.calib.camera(ctx.camera)
    if name == "wet_road":
        road = np.isin(obs.material, cam_deg.ROAD_MATERIALS)
        w = params["wetness"]
        L = obs.radiance.copy()
        rows = np.clip(np.round(2 * cam.K[1, 2] - np.arange(H) - 1).astype(int), 0, H - 1)
        mirror = gaussian_filter(obs.radiance[rows], sigma=(4.0 * sc, 1.5 * sc, 0))
        L[road] = L[road] * (1 - 0.45 * w) + params["fresnel"] * w * mirror[road]
        return L
    if name == "atmosphere":
        d = cam_deg.pixel_range(obs, cam)
        t = np.exp(-params["beta_per_m"] * np.where(np.isfinite(d), d, np.inf)).astype(np.float32)
        A = obs.sky_radiance[None, None, :]
        return (obs.radiance * t[..., None] + A * (1 - t[..., None])).astype(np.float32)
    if name == "glare":
        bright = np.clip(obs.radiance - params["threshold_cd_m2"], 0, None)
        f = 4
        Hc, Wc = H // f * f, W // f * f
        small = bright[:Hc, :Wc].reshape(Hc // f, f, Wc // f, f, 3).mean(axis=(1, 3))
        r = params["radius_px"] / f
        halo = np.zeros_like(bright)
        halo[:Hc, :Wc] = zoom(gaussian_filter(small, sigma=(r, r, 0)), (f, f, 1), order=1)[:Hc, :Wc]
        return (obs.radiance + params["strength"] * halo).astype(np.float32)
    if name == "lens_drops":
        blobs, which, rad = cam_deg._blobs_cached(params["seed"], round(params["coverage_pct"], 1), H, W,
                                                  (2.0, 10.0), sc)
        inside = which >= 0
        centres = np.array([[b[0], b[1]] for b in blobs])
        yy, xx = np.mgrid[0:H, 0:W] + 0.5
        cu, cv = centres[which[inside], 0], centres[which[inside], 1]
        su = cu - (xx[inside] - cu) * 2.5
        sv = cv - (yy[inside] - cv) * 2.5
        blurred = gaussian_filter(obs.radiance, sigma=(2.0 * sc, 2.0 * sc, 0))
        L = obs.radiance.copy()
        for c in range(3):
            L[..., c][inside] = map_coordinates(blurred[..., c], [sv - 0.5, su - 0.5], order=1, mode="nearest")
        L[inside] *= (0.55 + 0.45 * (1 - rad[inside] ** 2))[:, None]
        return L
    if name == "lens_snow":
        blobs, which, rad = cam_deg._blobs_cached(params["seed"], round(params["coverage_pct"], 1), H, W,
                                                  (5.0, 16.0), sc, 4)
        inside = which >= 0
        blurred = gaussian_filter(obs.radiance, sigma=(4.0 * sc, 4.0 * sc, 0))
        ambient = np.maximum(obs.sky_radiance, np.mean(obs.radiance, axis=(0, 1))) * 1.2
        soft = (0.85 * np.clip(1 - rad, 0, 1) ** 0.6)[..., None]
        t = params["transmission"]
        mix = t * blurred + (1 - t) * ambient
        return np.where(inside[..., None], (1 - soft) * obs.radiance + soft * mix, obs.radiance).astype(np.float32)
    assert name == "lens_soiling"
    rng = np.random.default_rng(params["seed"])
    blobs = cam_deg._coverage_blobs(rng, params["coverage_pct"], H, W, (6.0, 30.0), sc)
    which, rad = cam_deg._blob_mask(blobs, H, W)
    inside = which >= 0
    opaque = np.array([rng.uniform() < params["opaque_share"] for _ in blobs] + [False])
    blurred = gaussian_filter(obs.radiance, sigma=(5.0 * sc, 5.0 * sc, 0))
    soft = np.clip((1 - rad) * 4, 0, 1)[..., None]
    mud = np.array([0.02, 0.015, 0.01], np.float32) * np.mean(obs.radiance)
    L = np.where((inside & opaque[which])[..., None], (1 - soft) * obs.radiance + soft * mud, obs.radiance)
    L = np.where((inside & ~opaque[which])[..., None], (1 - soft) * L + soft * 0.5 * blurred, L)
    return L.astype(np.float32)


@pytest.mark.parametrize("name", ["wet_road", "atmosphere", "glare", "lens_drops", "lens_snow", "lens_soiling"])
def test_camera_models_equal_their_numpy_formulation(name, city):
    scene, renderer, raw = city
    obs = dataclasses.replace(raw.camera_right)
    obs.radiance = obs.radiance.copy()
    obs.radiance[40:60, 100:140] = 4000.0  # lamps bright enough for glare
    ctx = DegradeContext(renderer.calib, Context.parse("city"), {}, camera="camera_right")
    params_list = {
        "wet_road": [{"wetness": 0.6, "fresnel": 0.08}, {"wetness": 1.0, "fresnel": 0.08}],
        "atmosphere": [{"beta_per_m": 0.0}, {"beta_per_m": 0.02}, {"beta_per_m": 3e-4}],
        "glare": [{"threshold_cd_m2": 500.0, "radius_px": 3.0, "strength": 0.015},
                  {"threshold_cd_m2": 500.0, "radius_px": 9.0, "strength": 0.06}],
        "lens_drops": [{"coverage_pct": 12.0, "seed": 5}, {"coverage_pct": 3.3, "seed": 77}],
        "lens_snow": [{"coverage_pct": 20.0, "seed": 9, "transmission": 0.4}],
        "lens_soiling": [{"coverage_pct": 25.0, "opaque_share": 0.5, "seed": 3},
                         {"coverage_pct": 8.0, "opaque_share": 0.0, "seed": 4}],
    }[name]
    model = DEGRADATIONS.get(name)
    for params in params_list:
        for _ in range(2):  # the second call runs from the per-layout caches
            with np.errstate(invalid="ignore"):  # clear air: 0 * inf for the sky
                out = model.apply(obs, params, ctx)
                assert same(_reference(name, obs, params, ctx), out.radiance), params


def test_cached_lens_layouts_are_read_only():
    for layout in (cam_deg._drop_lenses(5, 12.0, 40, 60, 1.0), cam_deg._snow_patches(9, 20.0, 40, 60, 1.0),
                   cam_deg._soiling_patches(3, 25.0, 0.5, 40, 60, 1.0)):
        arrays = [a for item in layout for a in (item if isinstance(item, list) else [item])]
        assert arrays and all(not a.flags.writeable for a in arrays)


def _segments_reference(L, depth, p0, p1, z, radiance, alpha, samples_per_px=2.0):
    """camera._segments in numpy: every sample, then per pixel the most opaque (lexsort)."""
    H, W = depth.shape
    length = np.maximum(np.linalg.norm(p1 - p0, axis=1), 1.0)
    n_s = np.ceil(length * samples_per_px).astype(int)
    idx = np.repeat(np.arange(len(p0)), n_s)
    starts = np.repeat(np.cumsum(n_s) - n_s, n_s)
    t = (np.arange(len(idx)) - starts) / np.maximum(np.repeat(n_s - 1, n_s), 1)
    pts = p0[idx] + (p1[idx] - p0[idx]) * t[:, None]
    u, v = np.floor(pts[:, 0]).astype(int), np.floor(pts[:, 1]).astype(int)
    ok = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    u, v, idx = u[ok], v[ok], idx[ok]
    front = z[idx] < depth[v, u]
    u, v, idx = u[front], v[front], idx[front]
    if len(idx) == 0:
        return
    a = (alpha[idx] / np.maximum(n_s[idx] / (length[idx] * samples_per_px) * 1.0, 1.0))[:, None]
    flat = v * W + u
    order = np.lexsort((-a[:, 0], flat))
    first = np.r_[True, flat[order][1:] != flat[order][:-1]]
    sel = order[first]
    Lf = L.reshape(-1, 3)
    Lf[flat[sel]] = (1 - a[sel]) * Lf[flat[sel]] + a[sel] * radiance[idx[sel]]


def test_segments_equal_the_lexsort_formulation():
    H, W = 40, 64
    depth = RNG.uniform(1, 30, (H, W)).astype(np.float32)
    depth[:5] = np.inf  # sky
    for n, spread in ((400, 6.0), (1, 3.0), (2000, 0.0), (300, 40.0)):  # 0: one sample pixel, equal alphas
        p0 = np.column_stack([RNG.uniform(-5, W + 5, n), RNG.uniform(-5, H + 5, n)])
        p1 = p0 + RNG.normal(0, spread, (n, 2))
        z = RNG.uniform(0.5, 25, n)
        alpha = np.clip(RNG.uniform(0, 0.8, n), 0.15, 0.6)  # clipped: many equal alphas
        radiance = RNG.uniform(1, 9, (n, 3)).astype(np.float32)
        base = RNG.uniform(0, 50, (H, W, 3)).astype(np.float32)
        ref, out = base.copy(), base.copy()
        _segments_reference(ref, depth, p0, p1, z, radiance, alpha)
        cam_deg._segments(out, depth, p0, p1, z, radiance, alpha)
        assert same(ref, out), n
    hidden = base.copy()  # every sample behind the geometry: nothing changes
    cam_deg._segments(hidden, np.zeros((H, W), np.float32), p0, p1, z, radiance, alpha)
    assert same(hidden, base)
