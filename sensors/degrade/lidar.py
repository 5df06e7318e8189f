"""Lidar degradations on the (beam, azimuth) sweep, in received-power units of sensors.lidar.

A return survives when its power stays >= sensors.lidar.P_MIN (`detect`), so dark and distant
targets are the first to vanish as the atmosphere thickens.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from sensors.degrade.base import Degradation, obstruction_probability, persistent, register
from sensors.lidar import P_MIN, detect
from sensors.materials import MATERIAL_ID

GROUND = [MATERIAL_ID[m] for m in ("asphalt", "lane_paint", "sidewalk")]
PAVEMENT_TEXTURE_MM = 1.2  # a film deeper than the texture depth turns the road into a mirror


def _with(obs, **changes):
    new = dataclasses.replace(obs, **{k: np.copy(v) for k, v in changes.items()})
    new.returned = detect(new.range, new.power) & (new.power > 0)
    return new


@register
class LidarWetGround(Degradation):
    """Wet road: specular reflection sends the pulse away, so the diffuse ground return drops by
    (1 - 0.95 s), s = min(1, film / 1.2 mm) (Hahner et al. CVPR 2022, wet-ground model)."""

    name = "lidar_wet_ground"
    sensor = "lidar"

    def sample_params(self, rng, weather, ctx):
        if weather.water_film_mm <= 0:
            return None
        return {"specular_share": float(min(1.0, weather.water_film_mm / PAVEMENT_TEXTURE_MM))}

    def apply(self, obs, params, ctx):
        ground = np.isin(obs.material, GROUND)
        power = np.where(ground, obs.power * (1 - 0.95 * params["specular_share"]), obs.power)
        return _with(obs, power=power.astype(np.float32))


@register
class LidarExtinction(Degradation):
    """Beer-Lambert two-way attenuation of every hard return: P' = P exp(-2 alpha R), with
    alpha = fog ln(20)/MOR + rain + snow optical extinction (sim.weather; Hahner et al. ICCV 2021,
    LISA). Returns whose attenuated power drops below P_MIN are lost."""

    name = "lidar_extinction"
    sensor = "lidar"

    def sample_params(self, rng, weather, ctx):
        alpha = weather.extinction_per_m
        if alpha <= 0:
            return None
        return {"alpha_per_m": float(alpha)}

    def apply(self, obs, params, ctx):
        R = np.where(np.isfinite(obs.range), obs.range, 0.0)
        power = (obs.power * np.exp(-2.0 * params["alpha_per_m"] * R)).astype(np.float32)
        return _with(obs, power=power)


@register
class LidarFogBackscatter(Degradation):
    """Fog returns (Hahner et al. ICCV 2021): the fog volume in front of the target backscatters

        P_soft(R) = pi * beta * dR * xi(R) * exp(-2 alpha R) / R^2 * eta

    with backscatter beta = 0.046 / MOR [1/(m sr)], dR = c tau / 2 = 3 m (20 ns pulse), the
    transmitter/receiver overlap xi ramping from 0 at 2 m to 1 at 6 m, and eta ~ LogNormal(0, 0.5)
    for fog inhomogeneity. Where the peak of P_soft before the hard target exceeds the attenuated
    hard return (and P_MIN), the point becomes a fog point near the sensor; otherwise the hard
    return is kept (or lost below P_MIN)."""

    name = "lidar_fog_backscatter"
    sensor = "lidar"
    R1, R2, PULSE_M = 2.0, 6.0, 3.0

    def sample_params(self, rng, weather, ctx):
        if weather.fog_visibility_m >= 2000:
            return None
        return {"beta_per_m_sr": 0.046 / weather.fog_visibility_m, "alpha_per_m": float(weather.fog_alpha_per_m),
                "r1_m": self.R1, "r2_m": self.R2, "pulse_m": self.PULSE_M, "seed": int(rng.integers(2**31))}

    def apply(self, obs, params, ctx):
        rng = np.random.default_rng(params["seed"])
        grid = np.linspace(params["r1_m"], 15.0, 281)  # 5 cm steps
        xi = np.clip((grid - params["r1_m"]) / (params["r2_m"] - params["r1_m"]), 0, 1)
        profile = np.pi * params["beta_per_m_sr"] * params["pulse_m"] * xi * np.exp(
            -2 * params["alpha_per_m"] * grid) / grid**2
        # the profile rises then falls, so its maximum over the fog in front of the target (grid
        # points closer than the hard hit) is the running maximum up to the target's range
        running = np.maximum.accumulate(profile)
        arg_running = np.array([int(np.argmax(profile[: i + 1])) for i in range(len(grid))])
        R = np.where(np.isfinite(obs.range), obs.range, np.inf)
        last = np.searchsorted(grid, R, side="left") - 1  # last grid point in front of the target
        has_fog = last >= 0
        idx = np.clip(last, 0, len(grid) - 1)
        peak = np.where(has_fog, running[idx], 0.0)
        r_peak = grid[arg_running[idx]]
        eta = rng.lognormal(0.0, 0.5, size=peak.shape)
        p_soft = peak * eta
        hard = np.where(obs.returned, obs.power, 0.0)
        fog = (p_soft > hard) & (p_soft >= P_MIN)
        r_soft = r_peak + rng.uniform(-0.25, 0.25, size=peak.shape)
        return _with(
            obs,
            range=np.where(fog, r_soft, obs.range).astype(np.float32),
            power=np.where(fog, p_soft, obs.power).astype(np.float32),
            instance=np.where(fog, 0, obs.instance),
            material=np.where(fog, 0, obs.material).astype(np.uint8),
            cos_incidence=np.where(fog, 1.0, obs.cos_incidence).astype(np.float32),
        )


def _particle_returns(obs, rng, p_hit, mean_range, rho_range):
    """Replace returns by particle (drop/flake) returns on a random subset of rays."""
    hit = rng.uniform(size=obs.range.shape) < p_hit
    r = 0.8 + rng.exponential(mean_range, size=obs.range.shape)
    rho = rng.uniform(*rho_range, size=obs.range.shape)
    p = rho / r**2
    R = np.where(np.isfinite(obs.range), obs.range, np.inf)
    take = hit & (r < R) & (p >= P_MIN)
    return take, r, p


@register
class LidarRain(Degradation):
    """Rain (LISA, Kilic et al.): drops near the sensor return points (probability 0.15 % R^0.7 per
    ray, range 0.8 m + Exp(3 m), weak partial-beam reflectance), and hard returns get range noise
    sigma = 2 cm (1 + R/25 mm/h). Attenuation is in lidar_extinction."""

    name = "lidar_rain"
    sensor = "lidar"

    def sample_params(self, rng, weather, ctx):
        if weather.rain_mm_h <= 0:
            return None
        return {"p_drop": float(0.0015 * weather.rain_mm_h**0.7), "mean_range_m": 3.0,
                "range_sigma_m": float(0.02 * (1 + weather.rain_mm_h / 25)), "seed": int(rng.integers(2**31))}

    def apply(self, obs, params, ctx):
        rng = np.random.default_rng(params["seed"])
        take, r, p = _particle_returns(obs, rng, params["p_drop"], params["mean_range_m"], (0.002, 0.05))
        noisy = obs.range + rng.normal(0, params["range_sigma_m"], obs.range.shape).astype(np.float32)
        rng_out = np.where(take, r, np.where(np.isfinite(obs.range), noisy, obs.range))
        return _with(obs, range=rng_out.astype(np.float32), power=np.where(take, p, obs.power).astype(np.float32),
                     instance=np.where(take, 0, obs.instance), material=np.where(take, 0, obs.material).astype(np.uint8))


@register
class LidarSnow(Degradation):
    """Snowfall (Hahner et al. CVPR 2022): flakes occlude beams and return clutter close to the
    sensor: probability 4 % S^0.8 per ray (S in mm/h), range 0.8 m + Exp(4 m), bright flakes
    (reflectance 0.9) partly filling the beam (0.01-0.3)."""

    name = "lidar_snow"
    sensor = "lidar"

    def sample_params(self, rng, weather, ctx):
        if weather.snow_mm_h <= 0:
            return None
        return {"p_flake": float(min(0.5, 0.04 * weather.snow_mm_h**0.8)), "mean_range_m": 4.0,
                "seed": int(rng.integers(2**31))}

    def apply(self, obs, params, ctx):
        rng = np.random.default_rng(params["seed"])
        take, r, p = _particle_returns(obs, rng, params["p_flake"], params["mean_range_m"], (0.009, 0.27))
        return _with(obs, range=np.where(take, r, obs.range).astype(np.float32),
                     power=np.where(take, p, obs.power).astype(np.float32),
                     instance=np.where(take, 0, obs.instance), material=np.where(take, 0, obs.material).astype(np.uint8))


@register
class LidarBeamLoss(Degradation):
    """Beam loss (Robo3D, Dong et al.): 8 or 16 of the 32 lasers stop returning for the sequence."""

    name = "lidar_beam_loss"
    sensor = "lidar"
    kind = "obstruction"

    def sample_params(self, rng, weather, ctx):
        p = obstruction_probability("lidar_beam_loss", ctx.context)

        def draw(r):
            if r.uniform() >= p:
                return None
            n = int(r.choice([8, 16]))
            return {"lost_beams": sorted(int(b) for b in r.choice(32, size=n, replace=False))}

        return persistent(ctx, "lidar_beam_loss", draw)

    def apply(self, obs, params, ctx):
        power = obs.power.copy()
        power[params["lost_beams"]] = 0.0
        return _with(obs, power=power)


@register
class LidarFovLoss(Degradation):
    """Field-of-view loss (Dong et al. CVPR 2023): a 90-270 deg azimuth sector returns nothing for
    the sequence (occluded window, misaligned cover)."""

    name = "lidar_fov_loss"
    sensor = "lidar"
    kind = "obstruction"

    def sample_params(self, rng, weather, ctx):
        p = obstruction_probability("lidar_fov_loss", ctx.context)

        def draw(r):
            if r.uniform() >= p:
                return None
            return {"start_deg": float(r.uniform(0, 360)), "width_deg": float(r.uniform(90, 270))}

        return persistent(ctx, "lidar_fov_loss", draw)

    def apply(self, obs, params, ctx):
        A = obs.range.shape[1]
        az = np.arange(A) * 360.0 / A
        lost = np.mod(az - params["start_deg"], 360.0) < params["width_deg"]
        power = obs.power.copy()
        power[:, lost] = 0.0
        return _with(obs, power=power)
