"""Camera degradations, in the radiance domain (before exposure) unless stated.

Order of application (registration order) follows the light path: wet road -> atmosphere
(Koschmieder) -> rain streaks / snow flakes in the air -> glare -> lens (drops, snow, soiling)
-> failures -> sensor noise (exposure gain and Poisson-Gaussian noise, applied by the camera model).
"""

from __future__ import annotations

import dataclasses
from functools import lru_cache

import numpy as np
from scipy.ndimage import map_coordinates

from sensors.camera import CameraObservation, pixel_rays
from sensors.degrade.base import Degradation, obstruction_probability, persistent, register
from sensors.degrade.kernels import (
    airlight_blend,
    blend_segments,
    block_mean,
    channel_mean,
    gaussian_blur,
    masked_mix,
    snow_cover,
    soiling_cover,
    zoom_linear,
)
from sensors.materials import MATERIAL_ID

ROAD_MATERIALS = [MATERIAL_ID[m] for m in ("asphalt", "lane_paint")]


def _copy(obs: CameraObservation, **changes) -> CameraObservation:
    return dataclasses.replace(obs, **changes)


def pixel_range(obs: CameraObservation, cam) -> np.ndarray:
    """Distance along each pixel's ray [m] (depth / cos of the off-axis angle); inf for sky."""
    return obs.depth / pixel_rays(cam)[..., 2]


def _scale(ctx) -> float:
    return ctx.calib.camera(ctx.camera).height / 188.0  # sizes are given at the cpu profile


@register
class WetRoad(Degradation):
    """A water film darkens the road (wet asphalt absorbs more) and mirrors the scene in it.

    Wetness w = min(1, film / 0.5 mm); diffuse radiance x (1 - 0.45 w); a mirror image about the
    horizon row, blurred by the asphalt's roughness (mostly vertically, the streaks of lights on wet
    roads) and weighted by a Fresnel reflectance ~0.08, adds reflections of the sky, vehicles and
    lights.
    """

    name = "wet_road"
    sensor = "camera"

    def sample_params(self, rng, weather, ctx):
        if weather.water_film_mm <= 0:
            return None
        return {"wetness": float(min(1.0, weather.water_film_mm / 0.5)), "fresnel": 0.08}

    def apply(self, obs, params, ctx):
        cam = ctx.calib.camera(ctx.camera)
        road = np.isin(obs.material, ROAD_MATERIALS)
        w = params["wetness"]
        H = obs.radiance.shape[0]
        horizon = cam.K[1, 2]
        rows = np.clip(np.round(2 * horizon - np.arange(H) - 1).astype(int), 0, H - 1)
        sc = _scale(ctx)
        mirror = gaussian_blur(obs.radiance[rows], 4.0 * sc, 1.5 * sc)
        # on the road: L * (1 - 0.45 w) + fresnel w * mirror, in float32
        L = masked_mix(obs.radiance, road, np.float32(1 - 0.45 * w), np.float32(params["fresnel"] * w), mirror)
        return _copy(obs, radiance=L)


@register
class Atmosphere(Degradation):
    """Koschmieder's law with the rendered depth: L = L0 t + A (1 - t), t = exp(-beta d).

    beta is the frame's total optical extinction (fog ln(20)/MOR + rain + snow, sim.weather), d the
    distance along the ray, A the horizon sky radiance (airlight). Apparent contrast against the
    airlight therefore falls as exp(-beta d) exactly.
    """

    name = "atmosphere"
    sensor = "camera"

    def sample_params(self, rng, weather, ctx):
        return {"beta_per_m": float(weather.extinction_per_m)}

    def apply(self, obs, params, ctx):
        d = pixel_range(obs, ctx.calib.camera(ctx.camera))
        t = np.exp(-params["beta_per_m"] * np.where(np.isfinite(d), d, np.inf)).astype(np.float32)
        return _copy(obs, radiance=airlight_blend(obs.radiance, t, obs.sky_radiance))  # L0 t + A (1 - t)


def _segments(L, depth, p0, p1, z, radiance, alpha, samples_per_px=2.0):
    """Alpha-blend line segments (n, 2) -> (n, 2) with per-segment radiance (n, 3) and alpha (n,),
    behind-geometry parts hidden by the depth buffer; each pixel takes its most opaque sample."""
    length = np.maximum(np.linalg.norm(p1 - p0, axis=1), 1.0)
    n_s = np.ceil(length * samples_per_px).astype(int)
    a = alpha / np.maximum(n_s / (length * samples_per_px) * 1.0, 1.0)  # per sample
    blend_segments(L, depth, p0, p1, z, n_s, a, radiance)


def _air_particles(rng_seed, n, cam, depth_range, fall_speed, exposure_s, size_m):
    """Random particles in the camera frustum: image start/end points, depth, size [px]."""
    rng = np.random.default_rng(rng_seed)
    W, H = cam.width, cam.height
    z = depth_range[0] + (depth_range[1] - depth_range[0]) * rng.uniform(0, 1, n) ** (1 / 3)  # uniform in volume
    u = rng.uniform(0, W, n)
    v = rng.uniform(0, H, n)
    fall_px = cam.K[1, 1] * fall_speed * exposure_s / z  # image y points down, like gravity here
    drift = rng.normal(0, 0.15, n) * fall_px
    p0 = np.column_stack([u, v])
    p1 = np.column_stack([u + drift, v + fall_px])
    size_px = cam.K[0, 0] * size_m / z
    return p0, p1, z, size_px


@register
class RainStreaks(Degradation):
    """Falling drops imaged as streaks during the exposure (Garg & Nayar style).

    n = 150 R^0.6 visible drops per 63k pixels (R in mm/h), 0.3-12 m from the lens, terminal velocity
    6-9 m/s, exposure 5 ms by day and 30 ms at night; a streak carries the airlight refracted
    through the drop (0.9 A) and its opacity falls with distance.
    """

    name = "rain_streaks"
    sensor = "camera"

    def sample_params(self, rng, weather, ctx):
        if weather.rain_mm_h <= 0:
            return None
        cam = ctx.calib.camera(ctx.camera)
        n = int(150 * weather.rain_mm_h**0.6 * cam.width * cam.height / 63168)
        return {"drops": n, "exposure_s": 0.005 if weather.illuminance_lux > 400 else 0.03,
                "fall_speed_m_s": float(rng.uniform(6, 9)), "seed": int(rng.integers(2**31))}

    def apply(self, obs, params, ctx):
        cam = ctx.calib.camera(ctx.camera)
        p0, p1, z, _ = _air_particles(params["seed"], params["drops"], cam, (0.3, 12.0),
                                      params["fall_speed_m_s"], params["exposure_s"], 0.002)
        alpha = np.clip(0.25 * (1.0 / z), 0.03, 0.35)
        radiance = np.repeat(0.9 * obs.sky_radiance[None], len(z), 0)
        L = obs.radiance.copy()
        _segments(L, obs.depth, p0, p1, z, radiance, alpha)
        return _copy(obs, radiance=L)


@register
class SnowFlakes(Degradation):
    """Snowflakes in the air: bright, slowly falling discs (size D ~ 2-8 mm, 1-1.5 m/s).

    n = 6000 S^0.8 flakes per 63k pixels (S in mm/h water equivalent) 0.8-20 m away, lit by the sky
    (0.9 A) and by lamps/headlights (a floor on their radiance at night), opacity = disc area / pixel
    area, and at most 0.6 for the near, defocused ones.
    """

    name = "snow_flakes"
    sensor = "camera"

    def sample_params(self, rng, weather, ctx):
        if weather.snow_mm_h <= 0:
            return None
        cam = ctx.calib.camera(ctx.camera)
        n = int(6000 * weather.snow_mm_h**0.8 * cam.width * cam.height / 63168)
        return {"flakes": n, "exposure_s": 0.005 if weather.illuminance_lux > 400 else 0.03,
                "seed": int(rng.integers(2**31))}

    def apply(self, obs, params, ctx):
        cam = ctx.calib.camera(ctx.camera)
        rng = np.random.default_rng(params["seed"] + 1)
        size_m = rng.uniform(0.002, 0.006, params["flakes"])
        p0, p1, z, size_px = _air_particles(params["seed"], params["flakes"], cam, (0.8, 20.0), 1.2,
                                            params["exposure_s"], size_m)
        alpha = np.clip(size_px**2, 0.15, 0.6)
        lum = np.maximum(0.9 * obs.sky_radiance, 0.5 * np.percentile(obs.radiance, 99, axis=(0, 1)))
        radiance = np.repeat(lum[None], len(z), 0)
        L = obs.radiance.copy()
        _segments(L, obs.depth, p0, p1, z, radiance, alpha)
        big = size_px > 1.5  # near flakes cover several pixels: paint discs
        for (u, v), r, zz in zip(p0[big], size_px[big] / 2, z[big]):
            u0, u1 = int(max(0, u - r)), int(min(cam.width, u + r + 1))
            v0, v1 = int(max(0, v - r)), int(min(cam.height, v + r + 1))
            if u1 <= u0 or v1 <= v0:
                continue
            yy, xx = np.mgrid[v0:v1, u0:u1]
            m = ((xx + 0.5 - u) ** 2 + (yy + 0.5 - v) ** 2 <= r**2) & (obs.depth[v0:v1, u0:u1] > zz)
            L[v0:v1, u0:u1][m] = 0.5 * L[v0:v1, u0:u1][m] + 0.5 * lum
        return _copy(obs, radiance=L)


@register
class Glare(Degradation):
    """Veiling glare at night: light from bright sources (head lamps, street lamps) scattered in the
    lens and by fog droplets. Radiance above `threshold` is convolved with a wide kernel
    (Gaussian halo of `radius_px`) and `strength` of it added; fog widens and strengthens halos."""

    name = "glare"
    sensor = "camera"

    def sample_params(self, rng, weather, ctx):
        if weather.illuminance_lux >= 400:
            return None
        scale = _scale(ctx)
        fog = min(1.0, 300.0 / weather.visibility_m)
        return {"threshold_cd_m2": 500.0, "radius_px": float(3 * scale * (1 + 2 * fog)),
                "strength": float(0.015 * (1 + 3 * fog))}

    def apply(self, obs, params, ctx):
        bright = np.clip(obs.radiance - params["threshold_cd_m2"], 0, None)
        if not bright.any():
            return obs
        f = 4  # the halo is smooth: blur a 4x smaller image (energy preserved by the mean pooling)
        H, W = bright.shape[:2]
        Hc, Wc = H // f * f, W // f * f
        small = block_mean(bright, f)
        r = params["radius_px"] / f
        halo_small = gaussian_blur(small, r, r)
        halo = np.zeros_like(bright)
        halo[:Hc, :Wc] = zoom_linear(halo_small, (f, f, 1))[:Hc, :Wc]
        return _copy(obs, radiance=(obs.radiance + params["strength"] * halo).astype(np.float32))


def _blobs(rng, n, H, W, r_range, scale):
    return [[float(rng.uniform(0, W)), float(rng.uniform(0, H)), float(rng.uniform(*r_range) * scale)]
            for _ in range(n)]


def _coverage_blobs(rng, coverage_pct, H, W, r_range, scale, cap=400, cluster=1):
    """Blobs [u, v, r] covering about coverage_pct of the image; with cluster > 1 each patch is a
    clump of `cluster` overlapping smaller blobs (irregular outlines, e.g. snow)."""
    blobs, area = [], 0.0
    target = coverage_pct / 100.0 * H * W
    while area < target and len(blobs) < cap:
        u, v, r = _blobs(rng, 1, H, W, r_range, scale)[0]
        if cluster > 1:
            for _ in range(cluster):
                rr = r * rng.uniform(0.35, 0.6)
                du, dv = rng.normal(0, 0.45 * r, 2)
                blobs.append([u + du, v + dv, rr])
            area += 0.6 * np.pi * r**2
        else:
            blobs.append([u, v, r])
            area += np.pi * r**2
    return blobs


@lru_cache(maxsize=64)
def _blobs_cached(seed: int, coverage_pct: float, H: int, W: int, r_range: tuple, scale: float, cluster: int = 1):
    """Blob layout and masks for a seed (lens faults persist over a sequence: compute once)."""
    blobs = _coverage_blobs(np.random.default_rng(seed), coverage_pct, H, W, r_range, scale, cluster=cluster)
    which, rad = _blob_mask(blobs, H, W)
    return blobs, which, rad


def _blob_mask(blobs, H, W):
    """(H, W) index of the blob covering each pixel (-1 none) and normalised radius r / R."""
    yy, xx = np.mgrid[0:H, 0:W] + 0.5
    which = np.full((H, W), -1, np.int32)
    rad = np.ones((H, W), np.float32)
    for k, (u, v, R) in enumerate(blobs):
        u0, u1 = int(max(0, u - R)), int(min(W, u + R + 1))
        v0, v1 = int(max(0, v - R)), int(min(H, v + R + 1))
        if u1 <= u0 or v1 <= v0:
            continue
        d = np.hypot(xx[v0:v1, u0:u1] - u, yy[v0:v1, u0:u1] - v) / R
        m = d < 1
        which[v0:v1, u0:u1][m] = k
        rad[v0:v1, u0:u1][m] = d[m]
    return which, rad


def _frozen(*arrays):
    """Mark cached arrays read-only (they are shared by every frame of the sequence)."""
    for a in arrays:
        a.flags.writeable = False
    return arrays


@lru_cache(maxsize=64)
def _drop_lenses(seed: int, coverage_pct: float, H: int, W: int, scale: float):
    """Raindrop layout of a seed -> (inside (H, W), source coordinates [rows, cols] of each inside
    pixel's view, shade (n, 1)) or None without drops; read-only, computed once per layout."""
    blobs, which, rad = _blobs_cached(seed, coverage_pct, H, W, (2.0, 10.0), scale)
    inside = which >= 0
    if not inside.any():
        return None
    centres = np.array([[b[0], b[1]] for b in blobs])
    yy, xx = np.mgrid[0:H, 0:W] + 0.5
    cu, cv = centres[which[inside], 0], centres[which[inside], 1]
    su = cu - (xx[inside] - cu) * 2.5  # inverted, minified view of a wider neighbourhood
    sv = cv - (yy[inside] - cv) * 2.5
    shade = (0.55 + 0.45 * (1 - rad[inside] ** 2))[:, None]  # darker towards the rim
    inside, rows, cols, shade = _frozen(inside, sv - 0.5, su - 0.5, shade)
    return inside, [rows, cols], shade


@lru_cache(maxsize=64)
def _snow_patches(seed: int, coverage_pct: float, H: int, W: int, scale: float):
    """Snow patch layout of a seed -> (inside (H, W), soft (H, W) float32 opacity) or None without
    patches; read-only, computed once per layout."""
    blobs, which, rad = _blobs_cached(seed, coverage_pct, H, W, (5.0, 16.0), scale, 4)
    inside = which >= 0
    if not inside.any():
        return None
    soft = 0.85 * np.clip(1 - rad, 0, 1) ** 0.6  # out of focus: soft, never fully opaque
    return _frozen(inside, soft)


@lru_cache(maxsize=64)
def _soiling_patches(seed: int, coverage_pct: float, opaque_share: float, H: int, W: int, scale: float):
    """Dirt layout of a seed -> (opaque (H, W), semi-transparent (H, W), soft (H, W) float32
    opacity); read-only, computed once per layout (the fault persists over the sequence)."""
    rng = np.random.default_rng(seed)
    blobs = _coverage_blobs(rng, coverage_pct, H, W, (6.0, 30.0), scale)
    which, rad = _blob_mask(blobs, H, W)
    inside = which >= 0
    opaque = np.array([rng.uniform() < opaque_share for _ in blobs] + [False])
    soft = np.clip((1 - rad) * 4, 0, 1)
    return _frozen(inside & opaque[which], inside & ~opaque[which], soft)


@register
class LensDrops(Degradation):
    """Raindrops on the lens: out-of-focus refractive blobs that do not move with the scene.

    Inside a drop the image is a blurred, inverted and minified view of its surroundings (a
    drop is a tiny fisheye lens), darker towards the rim. The drops cover the camera's
    lens_coverage_pct (sim.weather); their layout persists over the sequence.
    """

    name = "lens_drops"
    sensor = "camera"

    def sample_params(self, rng, weather, ctx):
        cov = weather.lens_coverage_pct[0 if ctx.camera == "camera_left" else 1]
        if weather.rain_mm_h <= 0 or cov <= 0:
            return None
        seed = persistent(ctx, f"lens_drops/{ctx.camera}", lambda r: int(r.integers(2**31)))
        return {"coverage_pct": float(cov), "seed": seed}

    def apply(self, obs, params, ctx):
        H, W = obs.depth.shape
        drops = _drop_lenses(params["seed"], round(params["coverage_pct"], 1), H, W, _scale(ctx))
        if drops is None:
            return obs
        inside, source, shade = drops
        blurred = gaussian_blur(obs.radiance, 2.0 * _scale(ctx), 2.0 * _scale(ctx))
        L = obs.radiance.copy()
        for c in range(3):
            L[..., c][inside] = map_coordinates(blurred[..., c], source, order=1, mode="nearest")
        L[inside] *= shade
        return _copy(obs, radiance=L)


@register
class LensSnow(Degradation):
    """Snow on the lens: translucent white patches scattering ambient light (persist per sequence)."""

    name = "lens_snow"
    sensor = "camera"

    def sample_params(self, rng, weather, ctx):
        cov = weather.lens_coverage_pct[0 if ctx.camera == "camera_left" else 1]
        if weather.snow_mm_h <= 0 or cov <= 0:
            return None
        seed = persistent(ctx, f"lens_snow/{ctx.camera}", lambda r: int(r.integers(2**31)))
        return {"coverage_pct": float(cov), "seed": seed, "transmission": 0.4}

    def apply(self, obs, params, ctx):
        H, W = obs.depth.shape
        patches = _snow_patches(params["seed"], round(params["coverage_pct"], 1), H, W, _scale(ctx))
        if patches is None:
            return obs
        inside, soft = patches
        blurred = gaussian_blur(obs.radiance, 4.0 * _scale(ctx), 4.0 * _scale(ctx))
        # snow is white and lit from everywhere: brighter than the average scene
        ambient = np.maximum(obs.sky_radiance, channel_mean(obs.radiance)) * 1.2
        t = params["transmission"]
        # inside: (1 - soft) L + soft (t blurred + (1 - t) ambient)
        L = snow_cover(obs.radiance, inside, soft, blurred, np.float32(t), np.float32(1 - t) * ambient)
        return _copy(obs, radiance=L)


@register
class LensSoiling(Degradation):
    """Dirt on the lens (WoodScape soiling types): opaque patches (mud) and semi-transparent ones
    (dried water, dust) that blur and dim the scene. Drawn once per sequence with the context's
    probability (degrade.base.OBSTRUCTION_PROBABILITY)."""

    name = "lens_soiling"
    sensor = "camera"
    kind = "obstruction"

    def sample_params(self, rng, weather, ctx):
        p = obstruction_probability("lens_soiling", ctx.context)

        def draw(r):
            if r.uniform() >= p:
                return None
            return {"coverage_pct": float(r.uniform(5, 35)), "opaque_share": float(r.uniform(0, 1)),
                    "seed": int(r.integers(2**31))}

        return persistent(ctx, f"lens_soiling/{ctx.camera}", draw)

    def apply(self, obs, params, ctx):
        H, W = obs.depth.shape
        opaque, semi, soft = _soiling_patches(params["seed"], params["coverage_pct"], params["opaque_share"], H, W,
                                              _scale(ctx))
        blurred = gaussian_blur(obs.radiance, 5.0 * _scale(ctx), 5.0 * _scale(ctx))
        mud = np.array([0.02, 0.015, 0.01], np.float32) * np.mean(obs.radiance)
        # opaque: (1 - soft) L + soft mud; semi-transparent: (1 - soft) L + soft 0.5 blurred
        L = soiling_cover(obs.radiance, opaque, semi, soft, mud, blurred)
        return _copy(obs, radiance=L)


@register
class CameraBlackout(Degradation):
    """Camera failure (RoboBEV 'camera crash'): the image is black for a span of the sequence."""

    name = "camera_blackout"
    sensor = "camera"
    kind = "obstruction"

    def sample_params(self, rng, weather, ctx):
        p = obstruction_probability("camera_blackout", ctx.context)

        def draw(r):
            if r.uniform() >= p:
                return None
            start = int(r.integers(0, 10))
            return {"from_frame": start, "to_frame": start + int(r.integers(2, 20))}

        span = persistent(ctx, f"camera_blackout/{ctx.camera}", draw)
        if span is None or not span["from_frame"] <= ctx.frame_index < span["to_frame"]:
            return None
        return dict(span)

    def apply(self, obs, params, ctx):
        return _copy(obs, radiance=np.zeros_like(obs.radiance), sky_radiance=np.zeros(3, np.float32))


@register
class CameraNoise(Degradation):
    """Image sensor noise at every light level: Poisson photon shot noise on a 6,000 e- full well
    plus 4 e- read noise (Poisson-Gaussian, as in the low-light corruptions of MultiCorrupt and
    RoboBEV, but driven by the frame's illuminance). By day the auto-exposure keeps mid-grey at
    ~1,100 e- (about 3 % noise); when the exposure hits the camera's limit
    (sensors.camera.MAX_EXPOSURE, dusk and night) the camera raises its analogue gain up to 4x, which
    brightens the image and its noise together. Applied by the camera model (sensors.camera.expose).
    """

    name = "camera_noise"
    sensor = "camera"

    def sample_params(self, rng, weather, ctx):
        return {"full_well_e": 6000.0, "read_noise_e": 4.0, "max_gain": 4.0, "seed": int(rng.integers(2**31))}

    def apply(self, obs, params, ctx):
        return _copy(obs, sensor_noise=dict(params))
