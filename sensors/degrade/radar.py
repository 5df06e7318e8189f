"""Radar degradations at 77 GHz on the polar power image (noise units, sensors.radar).

Attenuation is two-way over the range of each bin centre: L = 2 gamma r [dB], gamma in dB/km.
The receiver noise is not attenuated; clutter from hydrometeors is added per cell.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from sensors.degrade.base import Degradation, obstruction_probability, persistent, register
from sensors.radar import ELEVATION_BEAMWIDTH_DEG, RADAR_CONSTANT
from sensors.rig import RADAR_BEAMWIDTH_DEG

# ITU-R P.840 specific attenuation coefficient of cloud/fog liquid water at 77 GHz:
# gamma_c = K_l M; K_l ~ 3.2 (dB/km)/(g/m^3) (0.16 dB/km at 0.05 g/m^3, REFERENCE.md).
K_L_77GHZ = 3.2
# ITU-R P.838-3 at 77 GHz: gamma_R = k R^alpha dB/km (1.1 / 5.9 / 11.4 / 18.8 dB/km at 1/10/25/50 mm/h).
P838_K, P838_ALPHA = 1.13, 0.72
WAVELENGTH_M = 3e8 / 77e9
# At 77 GHz (3.9 mm) rain drops and snowflakes are Mie scatterers: the Rayleigh formula overstates
# their backscatter; we apply a -10 dB correction to eta (our assumption, order of the Mie/Rayleigh
# ratio for mm-sized drops at this wavelength).
MIE_CORRECTION_DB = -10.0


def range_centres(ctx) -> np.ndarray:
    c = ctx.calib
    return (np.arange(c.radar_range_bins) + 0.5) * c.radar_range_resolution_m


def two_way_loss_db(gamma_db_per_km: float, r_m: np.ndarray) -> np.ndarray:
    """Two-way path loss [dB] over range r: 2 * gamma * r / 1000."""
    return 2.0 * gamma_db_per_km * np.asarray(r_m) / 1000.0


def p838_gamma(rain_mm_h: float) -> float:
    """ITU-R P.838-3 specific attenuation at 77 GHz [dB/km]."""
    return P838_K * rain_mm_h**P838_ALPHA


def _attenuate(obs, gamma, ctx):
    loss = 10.0 ** (-two_way_loss_db(gamma, range_centres(ctx)) / 10.0)
    return dataclasses.replace(obs, signal=(obs.signal * loss[None, :]).astype(np.float32),
                               clutter=obs.clutter.copy())


def clutter_mean(eta_m2_m3: float, ctx, gamma_db_km: float) -> np.ndarray:
    """Mean volume-clutter power per range bin [noise units]:
    C * eta * V / R^4, V = R^2 * 1.13 theta_az theta_el * dR (Gaussian beam), two-way attenuated."""
    r = range_centres(ctx)
    omega = 1.13 * np.radians(RADAR_BEAMWIDTH_DEG) * np.radians(ELEVATION_BEAMWIDTH_DEG)
    mean = RADAR_CONSTANT * eta_m2_m3 * omega * ctx.calib.radar_range_resolution_m / r**2
    return mean * 10.0 ** (-two_way_loss_db(gamma_db_km, r) / 10.0)


def eta_from_z(z_mm6_m3: float, k2: float) -> float:
    """Volume reflectivity eta = pi^5 |K|^2 Z / lambda^4 [m^2/m^3] (Rayleigh approximation), with
    the Mie correction MIE_CORRECTION_DB."""
    return np.pi**5 * k2 * z_mm6_m3 * 1e-18 / WAVELENGTH_M**4 * 10 ** (MIE_CORRECTION_DB / 10)


@register
class RadarFog(Degradation):
    """ITU-R P.840 fog attenuation: gamma = K_l M with M the fog's liquid water content
    (sim.weather: 0.05 g/m^3 at 300 m visibility, 0.5 g/m^3 at 50 m): ~0.3 dB over 100 m and back
    at 50 m visibility, ~0.6 dB at severity 5's 30 m (measured in notebook 02); radar barely notices fog."""

    name = "radar_fog"
    sensor = "radar"

    def sample_params(self, rng, weather, ctx):
        m = weather.fog_liquid_water_g_m3
        if m <= 0:
            return None
        return {"liquid_water_g_m3": float(m), "gamma_db_per_km": float(K_L_77GHZ * m)}

    def apply(self, obs, params, ctx):
        return _attenuate(obs, params["gamma_db_per_km"], ctx)


@register
class RadarRain(Degradation):
    """Rain: ITU-R P.838-3 two-way attenuation plus rain clutter. Clutter mean from the
    Marshall-Palmer reflectivity Z = 200 R^1.6 (|K|^2 = 0.7 for water at 77 GHz); per cell it is
    multiplied by an inverse-gamma variable (mean 1, shape a = max(1.5, 3 - 0.02 R)) whose
    heavier tail in heavier rain gives the spiky clutter seen in measurements (Gupta, Varga & Hein)."""

    name = "radar_rain"
    sensor = "radar"

    def sample_params(self, rng, weather, ctx):
        R = weather.rain_mm_h
        if R <= 0:
            return None
        return {"rain_mm_h": float(R), "gamma_db_per_km": float(p838_gamma(R)),
                "eta_m2_m3": float(eta_from_z(200.0 * R**1.6, 0.7)),
                "shape": float(max(1.5, 3.0 - 0.02 * R)), "seed": int(rng.integers(2**31))}

    def apply(self, obs, params, ctx):
        out = _attenuate(obs, params["gamma_db_per_km"], ctx)
        rng = np.random.default_rng(params["seed"])
        a = params["shape"]
        spikes = (a - 1.0) / rng.gamma(a, 1.0, size=obs.signal.shape)  # inverse-gamma, mean 1
        clutter = clutter_mean(params["eta_m2_m3"], ctx, params["gamma_db_per_km"])[None, :] * spikes
        out.clutter = (out.clutter + clutter).astype(np.float32)
        return out


@register
class RadarSnow(Degradation):
    """Snow: dry-snow attenuation gamma = 0.00349 S^1.6 / lambda^4 + 0.00224 S / lambda (Gunn & East,
    lambda in cm: ~0.65 dB/km at 2.5 mm/h) and clutter from Z = 1780 S^2.21 (Sekhon & Srivastava,
    |K|^2 = 0.176 for ice), exponential per cell."""

    name = "radar_snow"
    sensor = "radar"

    def sample_params(self, rng, weather, ctx):
        S = weather.snow_mm_h
        if S <= 0:
            return None
        lam_cm = WAVELENGTH_M * 100
        gamma = 0.00349 * S**1.6 / lam_cm**4 + 0.00224 * S / lam_cm
        return {"snow_mm_h": float(S), "gamma_db_per_km": float(gamma),
                "eta_m2_m3": float(eta_from_z(1780.0 * S**2.21, 0.176)), "seed": int(rng.integers(2**31))}

    def apply(self, obs, params, ctx):
        out = _attenuate(obs, params["gamma_db_per_km"], ctx)
        rng = np.random.default_rng(params["seed"])
        clutter = clutter_mean(params["eta_m2_m3"], ctx, params["gamma_db_per_km"])[None, :] * rng.exponential(
            1.0, size=obs.signal.shape)
        out.clutter = (out.clutter + clutter).astype(np.float32)
        return out


@register
class RadarBlockedSector(Degradation):
    """A blocked azimuth sector (snow, ice or mud on the radome): 20-90 deg wide, 20-30 dB loss, for
    the whole sequence."""

    name = "radar_blocked_sector"
    sensor = "radar"
    kind = "obstruction"

    def sample_params(self, rng, weather, ctx):
        p = obstruction_probability("radar_blocked_sector", ctx.context)

        def draw(r):
            if r.uniform() >= p:
                return None
            return {"start_deg": float(r.uniform(0, 360)), "width_deg": float(r.uniform(20, 90)),
                    "loss_db": float(r.uniform(20, 30))}

        return persistent(ctx, "radar_blocked_sector", draw)

    def apply(self, obs, params, ctx):
        A = obs.signal.shape[0]
        az = np.arange(A) * 360.0 / A
        blocked = np.mod(az - params["start_deg"], 360.0) < params["width_deg"]
        f = np.where(blocked, 10.0 ** (-params["loss_db"] / 10.0), 1.0)[:, None]
        return dataclasses.replace(obs, signal=(obs.signal * f).astype(np.float32),
                                   clutter=(obs.clutter * f).astype(np.float32))
