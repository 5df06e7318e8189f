"""Lidar degradations on the (beam, azimuth) sweep, in received-power units of sensors.lidar.

A return survives when its power stays >= sensors.lidar.P_MIN (`detect`), so dark and distant
targets are the first to vanish as the atmosphere thickens.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import scipy.integrate

from sensors.degrade.base import Degradation, obstruction_probability, persistent, register
from sensors.lidar import P_MIN, P_SAT, detect
from sensors.materials import MATERIAL_ID
from sim.registry import Registry

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


FOG_ACTIVE_BELOW_M = 2000.0  # fog MOR under which a lidar fog model runs (above: haze, extinction only)


@register
class LidarExtinction(Degradation):
    """Beer-Lambert two-way attenuation of every hard return: P' = P exp(-2 alpha R), with
    alpha = fog ln(20)/MOR + rain + snow optical extinction (sim.weather; Hahner et al. ICCV 2021,
    LISA). Returns whose attenuated power drops below P_MIN are lost. When the selected lidar fog
    model attenuates the hard returns itself (`hahner`, active below FOG_ACTIVE_BELOW_M), the fog
    share is left to it and only rain + snow remain here."""

    name = "lidar_extinction"
    sensor = "lidar"

    def sample_params(self, rng, weather, ctx):
        model = LIDAR_FOG_MODELS.get(ctx.lidar_fog)
        if model.attenuates_hard_returns and weather.fog_visibility_m < FOG_ACTIVE_BELOW_M:
            alpha = weather.rain_alpha_per_m + weather.snow_alpha_per_m
        else:
            alpha = weather.extinction_per_m
        if alpha <= 0:
            return None
        return {"alpha_per_m": float(alpha)}

    def apply(self, obs, params, ctx):
        R = np.where(np.isfinite(obs.range), obs.range, 0.0)
        power = (obs.power * np.exp(-2.0 * params["alpha_per_m"] * R)).astype(np.float32)
        return _with(obs, power=power)


LIDAR_FOG_MODELS: Registry = Registry(
    "lidar fog model",
    "Degradation instances (not in DEGRADATIONS) for the fog backscatter of the lidar; the registered "
    "`lidar_fog_backscatter` runs the one named by DegradeContext.lidar_fog (GenerateConfig.lidar_fog) "
    "and stores its name as params['model']. attenuates_hard_returns: the model applies the fog's "
    "exp(-2 alpha R) itself (lidar_extinction then leaves the fog share out).",
)


class OursFogBackscatter(Degradation):
    """Fog returns, our model (physics of Hahner et al. ICCV 2021 in this sensor's power units):
    the fog volume in front of the target backscatters

        P_soft(R) = pi * beta * dR * xi(R) * exp(-2 alpha R) / R^2 * eta

    with backscatter beta = 0.046 / MOR [1/(m sr)], dR = c tau / 2 = 3 m (20 ns pulse), the
    transmitter/receiver overlap xi ramping from 0 at 2 m to 1 at 6 m, and eta ~ LogNormal(0, 0.5)
    for fog inhomogeneity. Where the peak of P_soft before the hard target exceeds the attenuated
    hard return (and P_MIN), the point becomes a fog point near the sensor; otherwise the hard
    return is kept (or lost below P_MIN). The hard attenuation is lidar_extinction's.

    Units: our hard return is P = rho cos(theta) / R^2 (sensors.lidar), i.e. the lidar equation's
    C_A P_0 (2/c) beta_0 / R^2 with beta_0 = rho cos / pi, so C_A P_0 (2/c) = pi and the volume
    return of a slab dR is pi beta dR / R^2: hard and soft returns share one radiometric scale."""

    name = "ours"
    sensor = "lidar"
    attenuates_hard_returns = False
    R1, R2, PULSE_M = 2.0, 6.0, 3.0

    def sample_params(self, rng, weather, ctx):
        if weather.fog_visibility_m >= FOG_ACTIVE_BELOW_M:
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
        arg_running = _running_argmax(profile)
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
        return replace_by_fog(obs, fog, r_soft, p_soft, obs.power)


def _running_argmax(values: np.ndarray) -> np.ndarray:
    """Index of the first maximum of values[: i + 1] for every i (np.argmax of each prefix)."""
    running = np.maximum.accumulate(values)
    new_max = np.r_[True, running[1:] > running[:-1]]
    return np.maximum.accumulate(np.where(new_max, np.arange(len(values)), 0))


def replace_by_fog(obs, fog, fog_range, fog_power, hard_power):
    """A copy of `obs` whose rays in `fog` return a fog point (range, power; no actor, material 0)
    and whose other rays carry `hard_power`; detection is then recomputed (sensors.lidar.detect)."""
    return _with(
        obs,
        range=np.where(fog, fog_range, obs.range).astype(np.float32),
        power=np.where(fog, fog_power, hard_power).astype(np.float32),
        instance=np.where(fog, 0, obs.instance),
        material=np.where(fog, 0, obs.material).astype(np.uint8),
        cos_incidence=np.where(fog, 1.0, obs.cos_incidence).astype(np.float32),
    )


# --- Hahner et al. ICCV 2021, as published -----------------------------------------------------
# "Fog Simulation on Real LiDAR Point Clouds for 3D Object Detection in Adverse Weather" (paper
# Sec. 3: the lidar equation P_R(R) = C_A int P_T(t) H(R - c t / 2) dt with hard- and soft-target
# responses, and its Algorithm 1) and its code, github.com/MartinHahner/LiDAR_fog_sim
# (fog_simulation.py: ParameterSet, P_R_fog_hard, P_R_fog_soft, simulate_fog(..., noise=10);
# generate_integral_lookup_table.py; theory.py). Re-implemented here, vectorised; their constants.
SPEED_OF_LIGHT_M_S = 299_792_458.0
HAHNER_TAU_H_S = 2e-8  # half-power pulse width tau_H [s] (ParameterSet.tau_h)
HAHNER_R1_M, HAHNER_R2_M = 0.9, 1.0  # overlap xi(R): 0 up to R1, linear, 1 from R2 (ParameterSet.r_1, r_2)
HAHNER_BETA0_PER_SR = 1e-6 / np.pi  # beta_0 = Gamma / pi, Gamma = 1e-6 for every point (their __main__)
HAHNER_BACKSCATTER = 0.046  # beta = 0.046 / MOR [1/(m sr)] (ParameterSet.beta)
HAHNER_NOISE_M = 10.0  # fog point range noise, variant 'v1' with noise = 10 (their __main__)
HAHNER_COUNTS = 255  # 8-bit intensity: hard returns are rounded to counts, fog responses capped at 255
HAHNER_TABLE_STEP_M, HAHNER_TABLE_MAX_M, HAHNER_N = 0.1, 200.0, 2000  # their lookup table grid


@functools.lru_cache(maxsize=32)
def hahner_soft_table(alpha_per_m: float, tau_h_s: float = HAHNER_TAU_H_S, r1_m: float = HAHNER_R1_M,
                      r2_m: float = HAHNER_R2_M) -> tuple[np.ndarray, np.ndarray]:
    """Hahner's integral lookup table for one alpha: (fog_distance [m], i_tmp [s/m^2]), each
    (2001,), indexed by the hard target range R0 on a 0.1 m grid over 0..200 m.

    The soft (fog) return of a target at R0 seen at range R (paper Sec. 3, theory.P_R_fog_soft)
    is P_soft(R) = C_A P_0 beta * I(R), with

        I(R) = int_0^{2 tau_H} sin^2(pi t / (2 tau_H)) exp(-2 alpha (R - c t / 2)) xi(R - c t / 2)
               / (R - c t / 2)^2 * U(R0 - R + c t / 2) dt

    (pulse P_T(t) = P_0 sin^2(pi t / (2 tau_H)) on [0, 2 tau_H]; xi linear from R1 to R2;
    1/r^2 taken as 0 where r <= R1). Their table stores, per R0, i_tmp = max_R I(R) over the
    receiver-range grid R in linspace(0, 200, 2000) restricted to R <= R0, and fog_distance = that
    argmax R (the 'original', unshifted tables that fog_simulation.py loads). For R <= R0 every
    r = R - c t / 2 <= R0, so U = 1 and I(R) does not depend on R0: the table is the running
    maximum of one curve I(R), computed here once per alpha (Simpson's rule over 2000 time steps
    as theirs) instead of their nine precomputed alphas (fog_simulation picks the nearest)."""
    c = SPEED_OF_LIGHT_M_S
    x = np.linspace(0.0, HAHNER_TABLE_MAX_M, HAHNER_N)  # receiver range R
    t = np.linspace(0.0, 2 * tau_h_s, HAHNER_N)
    # once every slab is past the overlap (R - c tau_H >= R2, xi = 1), the integrand
    # exp(-2 alpha r) / r^2 falls with R for every t, so I(R) only falls: the running maximum is
    # reached before, and the curve is evaluated up to there (+ 2 m) only
    n_rows = int(np.searchsorted(x, r2_m + c * tau_h_s + 2.0)) + 1
    r = x[:n_rows, None] - c * t[None, :] / 2  # range of the scattering fog slab (rows, 2000)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_sq = np.where(r > r1_m, 1.0 / np.maximum(r, r1_m) ** 2, 0.0)
    xi = np.clip((r - r1_m) / (r2_m - r1_m), 0.0, 1.0)
    integrand = np.sin(np.pi * t / (2 * tau_h_s))[None, :] ** 2 * np.exp(-2 * alpha_per_m * r) * inv_sq * xi
    curve = np.zeros(HAHNER_N)
    curve[:n_rows] = scipy.integrate.simpson(integrand, x=t, axis=1)
    running = np.maximum.accumulate(curve)
    arg = _running_argmax(curve)
    r0 = np.round(np.arange(int(round(HAHNER_TABLE_MAX_M / HAHNER_TABLE_STEP_M)) + 1) * HAHNER_TABLE_STEP_M, 1)
    last = np.searchsorted(x, r0, side="right") - 1  # last receiver range R <= R0
    fog_distance = np.where(running[last] > 0, x[arg[last]], 0.0)  # all-zero row: argmax 0 -> R = 0
    return fog_distance, running[last]


def hahner_decision(r0, i_clean, alpha_per_m, beta_per_m_sr, noise_u, beta0_per_sr=HAHNER_BETA0_PER_SR,
                    tau_h_s=HAHNER_TAU_H_S, r1_m=HAHNER_R1_M, r2_m=HAHNER_R2_M, noise_m=HAHNER_NOISE_M,
                    round_hard: bool = True):
    """Hahner et al.'s per-point decision (Algorithm 1; fog_simulation.simulate_fog) on arrays.

    Args: r0 hard target range [m]; i_clean clear-weather intensity [counts, 0..255]; noise_u
    uniform(0, 1) draws of the same shape (the fog points' range noise).
    Returns (fog, i_hard, i_soft, fog_range): fog bool (the point becomes a fog point),
    i_hard = round(i exp(-2 alpha R0)) (P_R_fog_hard), i_soft = min(255, i_tmp(R0) i R0^2 beta /
    beta_0) (C_A P_0 = i R0^2 / beta_0 from the clear-weather peak i = C_A P_0 beta_0 / R0^2),
    fog = i_soft > i_hard, fog_range = fog_distance(R0) * R0 / d with d ~ U(R0 - 10, R0 + 10) m
    (noise variant 'v1'); it can be negative or beyond the sensor's range for R0 < 10 m, as theirs.
    beta0_per_sr may be an array (one per point); round_hard=False skips the rounding to counts
    (both only for ablations: as published, beta_0 = 1e-6 / pi for every point and rounding on)."""
    fog_distance, i_tmp = hahner_soft_table(float(alpha_per_m), tau_h_s, r1_m, r2_m)
    key = np.clip(np.rint(np.asarray(r0, np.float64) / HAHNER_TABLE_STEP_M), 0, len(i_tmp) - 1).astype(np.int64)
    i_hard = np.exp(-2 * alpha_per_m * r0) * i_clean
    if round_hard:
        i_hard = np.round(i_hard)
    i_soft = np.minimum(i_tmp[key] * i_clean * r0**2 * beta_per_m_sr / beta0_per_sr, HAHNER_COUNTS)
    fog = i_soft > i_hard
    d = r0 - noise_m + 2 * noise_m * noise_u
    with np.errstate(divide="ignore", invalid="ignore"):
        fog_range = fog_distance[key] * (r0 / d)
    return fog, i_hard, i_soft, fog_range


class HahnerFog(Degradation):
    """Hahner et al. ICCV 2021 as published (hahner_decision): every detected point either keeps
    its hard return, attenuated by exp(-2 alpha R0) (alpha = ln(20) / MOR), or is replaced by the
    fog (soft-target) return at fog_distance with range noise, whichever intensity is larger.

    Mapping to this sensor: intensity counts i = 255 P / P_SAT clipped to 255 (the sensor's 8-bit
    intensity; P_SAT a white target at 5 m), fog power = i_soft P_SAT / 255. Their model decides
    only for points present in the cloud (rays without a return get no fog) and never removes a
    point; here the sensor's detection (P >= P_MIN, 0.05-100 m) then applies to both returns as to
    every other model. Not carried over: their nearest-of-nine precomputed alphas (exact alpha
    here) and their optional 'gain' rescaling (off in their __main__)."""

    name = "hahner"
    sensor = "lidar"
    attenuates_hard_returns = True

    def sample_params(self, rng, weather, ctx):
        if weather.fog_visibility_m >= FOG_ACTIVE_BELOW_M:
            return None
        return {"alpha_per_m": float(weather.fog_alpha_per_m),
                "beta_per_m_sr": HAHNER_BACKSCATTER / weather.fog_visibility_m,
                "beta0_per_sr": HAHNER_BETA0_PER_SR, "tau_h_s": HAHNER_TAU_H_S, "r1_m": HAHNER_R1_M,
                "r2_m": HAHNER_R2_M, "noise_m": HAHNER_NOISE_M, "full_scale_power": P_SAT,
                "seed": int(rng.integers(2**31))}

    @staticmethod
    def decide(obs, params, beta0_per_sr=None, round_hard: bool = True):
        """Their decision on `obs` before the sensor's detection: (fog (32, A) bool, fog range [m],
        fog power, attenuated hard power), P_R_fog_hard's power kept unquantised. beta0_per_sr
        and round_hard override the published choices (ablations, see hahner_decision)."""
        rng = np.random.default_rng(params["seed"])
        noise_u = rng.uniform(size=obs.range.shape)
        R = np.where(np.isfinite(obs.range), obs.range, 0.0).astype(np.float64)
        counts = HAHNER_COUNTS / params["full_scale_power"]
        i_clean = np.minimum(obs.power * counts, HAHNER_COUNTS)
        fog, _, i_soft, fog_range = hahner_decision(
            R, i_clean, params["alpha_per_m"], params["beta_per_m_sr"], noise_u,
            params["beta0_per_sr"] if beta0_per_sr is None else beta0_per_sr,
            params["tau_h_s"], params["r1_m"], params["r2_m"], params["noise_m"], round_hard)
        fog &= obs.returned  # only points of the cloud are processed
        hard_power = obs.power * np.exp(-2.0 * params["alpha_per_m"] * R)
        return fog, fog_range, i_soft / counts, hard_power

    def apply(self, obs, params, ctx):
        fog, fog_range, fog_power, hard_power = self.decide(obs, params)
        return replace_by_fog(obs, fog, fog_range, fog_power, hard_power)


LIDAR_FOG_MODELS.add("ours", OursFogBackscatter())
LIDAR_FOG_MODELS.add("hahner", HahnerFog())


@register
class LidarFogBackscatter(Degradation):
    """Fog backscatter by the selected lidar fog model (LIDAR_FOG_MODELS: `ours`, default, or
    `hahner`); the choice is stored as params['model'], so a frame replays with the model it was
    made with."""

    name = "lidar_fog_backscatter"
    sensor = "lidar"

    def sample_params(self, rng, weather, ctx):
        params = LIDAR_FOG_MODELS.get(ctx.lidar_fog).sample_params(rng, weather, ctx)
        return None if params is None else {"model": ctx.lidar_fog, **params}

    def apply(self, obs, params, ctx):
        return LIDAR_FOG_MODELS.get(params["model"]).apply(obs, params, ctx)


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
