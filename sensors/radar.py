"""Navtech CTS350-X-like scanning radar (76-77 GHz FMCW, 360 deg, no Doppler).

Physical model per scan:
1. Rays sample the antenna beam: `OVERSAMPLE` azimuths per 0.9 deg bin and a fan of elevations
   across the elevation beam; each ray's first hit gives range R, incidence theta and material.
   Shadowing behind nearer objects follows from first hits.
2. Each ray footprint is a distributed target of projected area A = R^2 dphi dtheta with radar
   cross-section sigma = A * (gamma + s * exp(-(theta / 5 deg)^2)) (materials.py: constant-gamma
   backscatter plus a specular lobe for flat man-made surfaces); received power follows the radar
   equation P = C * G_el^2 * sigma / R^4.
3. Power is binned in range (linear split between neighbouring bins), convolved over azimuth with
   the two-way antenna pattern G^2 (sinc^2 one-way pattern with a 1.8 deg -3 dB width, so the
   sidelobes of a strong target sit ~27 dB down as arcs around it), and summed into 0.9 deg bins.
4. Speckle: the power of each resolution cell is multiplied by an Exp(1) variable (Rayleigh
   amplitude of many scatterers); receiver noise adds N0 * Exp(1) per cell.
Signal and noise are kept apart so weather can attenuate the signal only (sensors.degrade).
The image is stored like Navtech's: 8-bit power with 0.5 dB per count.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import scipy.fft as sfft

from sensors import ray_kernels
from sensors.materials import RADAR_GAMMA, RADAR_SPECULAR
from sensors.raycast import WorldCaster
from sensors.rig import RADAR_BEAMWIDTH_DEG, Calibration

OVERSAMPLE = 4  # rays per azimuth bin
ELEVATIONS_DEG = np.array([-3.0, -2.0, -1.2, -0.6, 0.0, 0.6, 1.2, 2.0])  # fan across the beam
ELEVATION_BEAMWIDTH_DEG = 1.8  # one-way -3 dB (assumed equal to the azimuth width)
SPECULAR_WIDTH_DEG = 5.0
NOISE_POWER = 1.0  # receiver noise per cell (the unit of power)
# C such that a 10 m^2 target (a car) at 100 m sits 25 dB above the noise (3 dB at the CTS350-X's
# rated 350 m): C * 10 / 100^4 = 10^2.5 N0
RADAR_CONSTANT = 10**2.5 * NOISE_POWER * 100.0**4 / 10.0
DB_PER_COUNT = 0.5
DB_OFFSET = -10.0  # count 0 = -10 dB relative to the noise power


@dataclass
class RadarObservation:
    """One 360 deg scan in polar form.

    Fields (all (A, B): azimuth bins x range bins):
        signal: received power from the scene (speckled), in units of the noise power.
        noise: receiver noise power of this scan (same units).
        instance: simulator actor id contributing most power to the cell (0 = none / static).
    Extra terms added by weather (rain/snow clutter) go in `clutter` (A, B), zero when clear.
    """

    signal: np.ndarray
    noise: np.ndarray
    instance: np.ndarray
    clutter: np.ndarray

    def copy(self) -> RadarObservation:
        return RadarObservation(self.signal.copy(), self.noise.copy(), self.instance.copy(), self.clutter.copy())

    @property
    def power(self) -> np.ndarray:
        return self.signal + self.clutter + self.noise


def _one_way_gain(phi_deg: np.ndarray, beamwidth_deg: float) -> np.ndarray:
    """sinc^2 power pattern with the given -3 dB full width (first sidelobe -13.3 dB)."""
    x = 0.8859 * phi_deg / beamwidth_deg  # sinc^2(x) = 0.5 at x = 0.4430
    return np.sinc(x) ** 2


def azimuth_kernel(n_fine: int) -> np.ndarray:
    """Two-way azimuth pattern G^2 sampled on the fine circular grid (sums to 1 over the fine bins)."""
    dphi = 360.0 / n_fine
    phi = (np.arange(n_fine) - n_fine // 2) * dphi
    k = _one_way_gain(phi, RADAR_BEAMWIDTH_DEG) ** 2
    return np.roll(k / k.sum(), -(n_fine // 2))


@lru_cache(maxsize=8)
def _kernel_spectrum(n_fine: int) -> np.ndarray:
    return sfft.rfft(azimuth_kernel(n_fine).astype(np.float32))


def elevation_weights() -> np.ndarray:
    return _one_way_gain(ELEVATIONS_DEG, ELEVATION_BEAMWIDTH_DEG) ** 2


@lru_cache(maxsize=8)
def _fine_rays(n_fine: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The scan's rays in the radar frame, elevation-major (ray e * n_fine + a): unit directions
    (E * n_fine, 3), elevation spacing d_el [rad], elevation weight w_el and coarse azimuth bin per
    ray. Read-only (shared by every scan)."""
    # fine rays centred on their bin: row a = azimuth a * 360 / A (rig.py convention)
    az = 2 * np.pi * (np.arange(n_fine) - (OVERSAMPLE - 1) / 2) / n_fine
    el = np.radians(ELEVATIONS_DEG)
    dirs = np.stack(np.broadcast_arrays(
        (np.cos(el)[:, None] * np.cos(az)[None, :]),
        (np.cos(el)[:, None] * np.sin(az)[None, :]),
        (np.sin(el)[:, None] * np.ones_like(az)[None, :]),
    ), -1).reshape(-1, 3)
    d_el = np.gradient(el).repeat(n_fine)  # elevation spacing per ray [rad]
    w_el = np.repeat(elevation_weights(), n_fine)
    coarse = np.tile(np.arange(n_fine), len(el)) // OVERSAMPLE
    for a in (dirs, d_el, w_el, coarse):
        a.flags.writeable = False
    return dirs, d_el, w_el, coarse


def scan(caster: WorldCaster, calib: Calibration, world_from_ego: np.ndarray, actor_ids: np.ndarray,
         rng: np.random.Generator, speckle: bool = True) -> RadarObservation:
    """One scan of the radar at the ego pose (see module docstring). `speckle=False` returns the
    mean (unspeckled) signal, for tests of the radar equation."""
    A, B, dr = calib.radar_azimuths, calib.radar_range_bins, calib.radar_range_resolution_m
    n_fine = A * OVERSAMPLE
    dirs, d_el, w_el, coarse = _fine_rays(n_fine)
    world_from_radar = world_from_ego @ calib.ego_from_radar
    d_world = dirs @ world_from_radar[:3, :3].T
    max_range = B * dr
    hits = caster.cast(world_from_radar[:3, 3], d_world, max_range=max_range)
    R = hits.range
    ok = np.isfinite(R) & (R > 1.0)
    cos_i = hits.cos_incidence
    theta = np.degrees(np.arccos(np.clip(cos_i, 0, 1)))
    m = hits.material
    d_az = 2 * np.pi / n_fine
    area = R**2 * d_az * d_el  # projected footprint [m^2]
    sigma = area * (RADAR_GAMMA[m] + RADAR_SPECULAR[m] * np.exp(-((theta / SPECULAR_WIDTH_DEG) ** 2)))
    with np.errstate(divide="ignore", invalid="ignore"):
        p = np.where(ok, RADAR_CONSTANT * w_el * sigma / R**4, 0.0)
    # bin in range (linear split) on the fine azimuth grid
    x = np.where(ok, R / dr - 0.5, 0.0)
    grid = ray_kernels.radar_range_grid(p, x, ok, n_fine, B)  # (n_fine, B) float32
    # dominant actor per coarse cell
    ids = np.concatenate([[0], actor_ids])
    act = ok & (hits.instance > 0)
    instance = np.zeros((A, B), np.int64)
    if act.any():
        cell = coarse[act] * B + np.clip(np.round(x[act]).astype(int), 0, B - 1)
        pw = p[act]
        order = np.lexsort((pw, cell))  # by cell, then power ascending
        last = np.r_[cell[order][1:] != cell[order][:-1], True]
        instance.reshape(-1)[cell[order][last]] = ids[hits.instance[act][order][last]]
    # two-way azimuth pattern (circular convolution), then integrate into the coarse bins
    K = _kernel_spectrum(n_fine)
    spectrum = sfft.rfft(grid, axis=0)
    spectrum *= K[:, None]
    smeared = sfft.irfft(spectrum, n=n_fine, axis=0)
    speckle_draw = rng.exponential(1.0, size=(A, B))
    noise = NOISE_POWER * rng.exponential(1.0, size=(A, B))
    # clip the sidelobe ringing at 0, integrate into the coarse bins, speckle
    signal = ray_kernels.radar_coarse_signal(smeared, OVERSAMPLE, speckle_draw if speckle else None)
    return RadarObservation(
        signal=signal,
        noise=noise.astype(np.float32),
        instance=instance,
        clutter=np.zeros((A, B), np.float32),
    )


def to_counts(power: np.ndarray) -> np.ndarray:
    """Linear power (noise units) -> Navtech-like 8-bit counts (0.5 dB per count)."""
    db = 10.0 * np.log10(np.maximum(power, 1e-12))
    return np.clip(np.round((db - DB_OFFSET) / DB_PER_COUNT), 0, 255).astype(np.uint8)


def counts_to_db(counts: np.ndarray) -> np.ndarray:
    return counts.astype(np.float32) * DB_PER_COUNT + DB_OFFSET


_CART_CACHE: dict = {}


def cartesian(polar: np.ndarray, calib: Calibration) -> np.ndarray:
    """Polar image (A, B) -> (S, S) BEV on the radar grid by bilinear interpolation (azimuth wraps)."""
    key = (polar.shape, calib.bev_size_px, calib.bev_resolution_m, calib.radar_range_resolution_m)
    if key not in _CART_CACHE:
        S = calib.bev_size_px
        u, v = np.meshgrid(np.arange(S) + 0.5, np.arange(S) + 0.5)
        xy = calib.bev_to_radar(np.column_stack([u.ravel(), v.ravel()]))
        r = np.hypot(xy[:, 0], xy[:, 1])
        phi = np.mod(np.arctan2(xy[:, 1], xy[:, 0]), 2 * np.pi)
        A, B = polar.shape
        rows = phi / (2 * np.pi) * A
        cols = r / calib.radar_range_resolution_m - 0.5
        _CART_CACHE[key] = (np.vstack([rows, cols]), (S, S), cols > B)
    coords, shape, outside = _CART_CACHE[key]
    # bilinear, azimuth wrapping, as map_coordinates(order=1, mode="nearest") on the polar image
    # with its first row repeated after the last (sensors.ray_kernels)
    out = ray_kernels.polar_to_cartesian(np.asarray(polar, np.float32), coords[0], coords[1], outside)
    return out.reshape(shape)
