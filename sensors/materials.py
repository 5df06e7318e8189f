"""Surface materials: what each sensor sees of a surface.

Each mesh face carries a material id. A material has:
- albedo: diffuse reflectance in linear RGB (visible; camera). Vehicle paint and clothing take
  a per-actor colour instead (`instance_colour`).
- nir: diffuse reflectance at 905 nm (lidar). Vegetation is bright in the near infrared, asphalt
  dark, lane paint and lamps retro-reflective.
- radar_gamma_db: radar backscatter gamma (sigma0 = gamma cos(theta)), so a ray footprint of
  projected area A contributes sigma = gamma * A [m^2]; metal and facades are strong, asphalt at
  grazing incidence weak. radar_specular_db adds a narrow specular lobe at normal incidence
  (flat man-made surfaces, car bodies).
- emissive: luminance [cd/m^2] when the light is on (lamp heads at night, head/tail lights).

Figures are typical published values (visible albedo of asphalt ~0.05-0.1, grass ~0.1-0.2; NIR
reflectance of vegetation ~0.4-0.5; 77 GHz backscatter of asphalt at grazing incidence ~ -25 to
-35 dB, of building walls ~ -5 to 0 dB, of cars ~ 10 m^2 total RCS).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np


@dataclass(frozen=True)
class Material:
    name: str
    albedo: tuple[float, float, float]
    nir: float
    radar_gamma_db: float
    radar_specular_db: float = -100.0
    emissive: tuple[float, float, float] = (0.0, 0.0, 0.0)
    emits_when: str = ""  # "lamps" | "headlights" | ""
    per_instance_colour: bool = False


MATERIALS: tuple[Material, ...] = (
    Material("sky", (0.0, 0.0, 0.0), 0.0, -100.0),
    Material("asphalt", (0.07, 0.07, 0.075), 0.10, -22.0),
    Material("lane_paint", (0.65, 0.65, 0.62), 0.55, -20.0),
    Material("sidewalk", (0.26, 0.25, 0.23), 0.30, -15.0),
    Material("grass", (0.07, 0.13, 0.04), 0.45, -12.0),
    Material("brick", (0.28, 0.12, 0.08), 0.35, -6.0, 8.0),
    Material("concrete", (0.36, 0.36, 0.34), 0.35, -6.0, 8.0),
    Material("plaster", (0.50, 0.46, 0.38), 0.45, -6.0, 8.0),
    Material("window", (0.04, 0.05, 0.06), 0.06, -3.0, 12.0),
    Material("bark", (0.10, 0.07, 0.04), 0.30, -10.0),
    Material("foliage", (0.04, 0.10, 0.03), 0.50, -11.0),
    Material("steel", (0.35, 0.36, 0.38), 0.40, 0.0, 15.0),
    Material("lamp_head", (0.7, 0.7, 0.65), 0.6, 0.0, 10.0, (8000.0, 6800.0, 4500.0), "lamps"),
    Material("paint", (0.4, 0.4, 0.4), 0.40, 0.0, 14.0, per_instance_colour=True),
    Material("car_glass", (0.03, 0.04, 0.05), 0.08, -3.0, 10.0),
    Material("tyre", (0.025, 0.025, 0.025), 0.05, -6.0),
    Material("headlight", (0.8, 0.8, 0.8), 0.80, 0.0, 10.0, (30000.0, 30000.0, 28000.0), "headlights"),
    Material("taillight", (0.55, 0.04, 0.03), 0.70, 0.0, 10.0, (1500.0, 60.0, 40.0), "headlights"),
    Material("clothing", (0.2, 0.2, 0.25), 0.40, -8.0, per_instance_colour=True),
    Material("skin", (0.50, 0.34, 0.27), 0.50, -8.0),
    Material("trailer", (0.70, 0.70, 0.68), 0.50, 0.0, 14.0),
)
MATERIAL_ID: dict[str, int] = {m.name: i for i, m in enumerate(MATERIALS)}
N_MATERIALS = len(MATERIALS)

ALBEDO = np.array([m.albedo for m in MATERIALS], np.float32)  # (M, 3)
NIR = np.array([m.nir for m in MATERIALS], np.float32)
RADAR_GAMMA = 10.0 ** (np.array([m.radar_gamma_db for m in MATERIALS]) / 10.0)
RADAR_SPECULAR = 10.0 ** (np.array([m.radar_specular_db for m in MATERIALS]) / 10.0)
EMISSIVE = np.array([m.emissive for m in MATERIALS], np.float32)
PER_INSTANCE = np.array([m.per_instance_colour for m in MATERIALS])

# Common car colours (linear RGB): white, black, silver, grey, blue, red, dark green, beige.
PAINT_PALETTE = np.array(
    [[0.70, 0.70, 0.70], [0.03, 0.03, 0.035], [0.45, 0.46, 0.48], [0.20, 0.20, 0.21],
     [0.05, 0.10, 0.30], [0.45, 0.04, 0.03], [0.04, 0.12, 0.06], [0.45, 0.38, 0.28]],
    np.float32,
)
PAINT_WEIGHTS = np.array([0.24, 0.22, 0.16, 0.15, 0.09, 0.08, 0.03, 0.03])
CLOTHING_PALETTE = np.array(
    [[0.03, 0.03, 0.04], [0.10, 0.12, 0.25], [0.35, 0.05, 0.05], [0.45, 0.45, 0.42],
     [0.08, 0.18, 0.10], [0.40, 0.30, 0.15], [0.55, 0.50, 0.10], [0.15, 0.15, 0.15]],
    np.float32,
)


@lru_cache(maxsize=65536)
def instance_colour(actor_id: int, material: int) -> np.ndarray:
    """Deterministic per-actor colour (linear RGB) for paint and clothing."""
    rng = np.random.default_rng(int(actor_id) * 7919 + material)
    if material == MATERIAL_ID["paint"]:
        return PAINT_PALETTE[rng.choice(len(PAINT_PALETTE), p=PAINT_WEIGHTS)]
    return CLOTHING_PALETTE[rng.integers(len(CLOTHING_PALETTE))]
