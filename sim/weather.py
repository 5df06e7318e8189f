"""One physical weather state per frame, in physical units, and its severity table.

Every sensor model derives its own parameters from a `WeatherState` (see sensors/degrade): fog
visibility gives the camera's Koschmieder beta, the lidar's extinction alpha and the radar's
liquid-water attenuation together. Severity 0-5 maps to intervals of one physical quantity per
condition (`SEVERITY_TABLE`); the other quantities of the state follow from documented relations.

Conventions: visibility is the meteorological optical range (MOR) at the 5 % contrast threshold,
so the optical extinction coefficient is ``alpha = ln(20) / MOR`` (REFERENCE.md, Fog; Koschmieder's
2 % threshold would use ln(50)). Precipitation rates are liquid-water equivalent in mm/h.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from sim.errors import UserError

CONDITIONS = ("rain", "fog", "snow", "night")
SEVERITIES = range(0, 6)
LN20 = math.log(20.0)  # 5 % contrast threshold (MOR definition, WMO)
DB_PER_NEPER = 10.0 / math.log(10.0)  # 4.343 dB per neper (power)

# --- severity table ------------------------------------------------------------------------------
# Level s (1..5) of a condition draws its primary quantity from the interval [lo, hi], log-uniform
# for quantities spanning decades. Intervals do not overlap, so every draw is monotone in severity.
SEVERITY_TABLE: dict[str, dict] = {
    "fog": {
        "quantity": "fog_visibility_m",
        "unit": "m",
        # Hahner et al. ICCV 2021: MOR 599/300/150/100/50 m for alpha 0.005/0.01/0.02/0.03/0.06.
        "levels": [(600.0, 1000.0), (300.0, 600.0), (150.0, 300.0), (75.0, 150.0), (30.0, 75.0)],
        "scale": "log",
        "worse": "lower",
    },
    "rain": {
        "quantity": "rain_mm_h",
        "unit": "mm/h",
        # AMS classes: light < 2.5, moderate 2.5-7.6, heavy > 7.6 mm/h; P.838 figures at 1..50 mm/h.
        "levels": [(0.5, 2.5), (2.5, 5.0), (5.0, 10.0), (10.0, 25.0), (25.0, 50.0)],
        "scale": "log",
        "worse": "higher",
    },
    "snow": {
        "quantity": "snow_mm_h",
        "unit": "mm/h (water equiv.)",
        # Hahner et al. CVPR 2022 simulate snowfall rates 0-2.5 mm/h.
        "levels": [(0.1, 0.3), (0.3, 0.6), (0.6, 1.0), (1.0, 1.7), (1.7, 2.5)],
        "scale": "linear",
        "worse": "higher",
    },
    "night": {
        "quantity": "illuminance_lux",
        "unit": "lux",
        # dusk ~ 400-50 lx, lit urban road 2-10 lx (EN 13201 classes), unlit road under a moon < 0.3 lx.
        "levels": [(50.0, 400.0), (10.0, 50.0), (2.0, 10.0), (0.3, 2.0), (0.01, 0.3)],
        "scale": "log",
        "worse": "lower",
    },
}

CLEAR_VISIBILITY_M = (10_000.0, 30_000.0)  # clean air / light haze
DAYLIGHT_LUX = (10_000.0, 100_000.0)  # overcast to direct sun
OVERCAST_LUX = (2_000.0, 20_000.0)  # daylight under precipitation or fog
OVERCAST_BELOW_MOR_M = 2_000.0  # fog denser than this hides the sun (WeatherState.sky_overcast)
# Raindrops / snow on the lens: maximum coverage per severity [%]; each camera draws its own.
LENS_COVERAGE_MAX_PCT = {"rain": (1.0, 3.0, 8.0, 15.0, 30.0), "snow": (1.0, 3.0, 6.0, 12.0, 25.0)}


def rain_optical_db_per_km(rain_mm_h: float) -> float:
    """Optical (visible/NIR) specific attenuation of rain, A = 1.076 R^0.67 dB/km.

    Carbonneau & Wisely (1998), the relation used for free-space optics (ITU-R P.1814 family).
    """
    return 1.076 * rain_mm_h**0.67 if rain_mm_h > 0 else 0.0


def snow_optical_db_per_km(snow_mm_h: float, wavelength_nm: float = 550.0) -> float:
    """Optical attenuation of dry snow, A = a S^b dB/km, a = 5.42e-5 lambda + 5.4958776, b = 1.38.

    Al Naboulsi et al. / ITU-R P.1817 style empirical law for dry snow, S in mm/h water equivalent.
    """
    if snow_mm_h <= 0:
        return 0.0
    a = 5.42e-5 * wavelength_nm + 5.4958776
    return a * snow_mm_h**1.38


def water_film_from_rain(rain_mm_h: float) -> float:
    """Water film depth on the road [mm] from rain rate.

    Gallaway et al. (1979) give film depth ~ I^0.59 for fixed drainage length, slope and texture;
    the constant is set so 25 mm/h gives 1.2 mm, the depth at which Hahner et al. (CVPR 2022)
    find specular reflection removes most ground returns.
    """
    return 1.2 * (rain_mm_h / 25.0) ** 0.59 if rain_mm_h > 0 else 0.0


@dataclass(frozen=True)
class WeatherState:
    """The physical weather of one frame; every sensor model derives its parameters from it.

    Fields (all scalars):
        fog_visibility_m: MOR of fog/haze alone [m], 5 % contrast; >= 10 km is clear air.
        rain_mm_h: rain rate [mm/h].
        snow_mm_h: snowfall rate, liquid water equivalent [mm/h].
        water_film_mm: water film depth on the road surface [mm].
        illuminance_lux: horizontal illuminance at road level from sky and sun [lx].
        lens_coverage_pct: fraction of each camera lens covered by drops or snow [%], (left, right).
        overcast: the sky is overcast (no direct sun; all light is diffuse sky light). None = follows
            the hydrometeors (overcast whenever fog below 2 km MOR, rain or snow is present); a
            counterfactual twin of a fog, rain or snow frame sets it True, so the twin keeps the
            frame's light and loses only the condition (issue 13, part 3).
    """

    fog_visibility_m: float = 20_000.0
    rain_mm_h: float = 0.0
    snow_mm_h: float = 0.0
    water_film_mm: float = 0.0
    illuminance_lux: float = 30_000.0
    lens_coverage_pct: tuple[float, float] = (0.0, 0.0)
    overcast: bool | None = None

    def __post_init__(self) -> None:
        if self.fog_visibility_m <= 0:
            raise UserError(f"fog_visibility_m must be > 0 m, got {self.fog_visibility_m}")
        for name in ("rain_mm_h", "snow_mm_h", "water_film_mm"):
            if getattr(self, name) < 0:
                raise UserError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.illuminance_lux <= 0:
            raise UserError(f"illuminance_lux must be > 0 lx, got {self.illuminance_lux}")
        if self.overcast is not None and not isinstance(self.overcast, (bool, np.bool_)):
            raise UserError(f"overcast must be True, False or None (follow the hydrometeors), got {self.overcast!r}")
        if len(self.lens_coverage_pct) != 2 or not all(0 <= c <= 100 for c in self.lens_coverage_pct):
            raise UserError(f"lens_coverage_pct must be two values in 0..100, got {self.lens_coverage_pct}")

    # -- derived optical quantities ------------------------------------------------------------
    @property
    def fog_alpha_per_m(self) -> float:
        """Fog extinction coefficient alpha = ln(20) / MOR [1/m] (REFERENCE.md, Fog)."""
        return LN20 / self.fog_visibility_m

    @property
    def rain_alpha_per_m(self) -> float:
        return rain_optical_db_per_km(self.rain_mm_h) / DB_PER_NEPER / 1000.0

    @property
    def snow_alpha_per_m(self) -> float:
        return snow_optical_db_per_km(self.snow_mm_h) / DB_PER_NEPER / 1000.0

    @property
    def extinction_per_m(self) -> float:
        """Total optical extinction [1/m]: fog + rain + snow (extinction coefficients add)."""
        return self.fog_alpha_per_m + self.rain_alpha_per_m + self.snow_alpha_per_m

    @property
    def visibility_m(self) -> float:
        """Meteorological optical range of all hydrometeors together [m]."""
        return LN20 / self.extinction_per_m

    @property
    def fog_liquid_water_g_m3(self) -> float:
        """Fog liquid water content M [g/m^3] from fog visibility.

        Power law through ITU-R P.840's reference points (0.05 g/m3 ~ 300 m, 0.5 g/m3 ~ 50 m):
        M = 0.05 (V / 300 m)^-1.285. Clear air (V >= 10 km) has no fog water.
        """
        if self.fog_visibility_m >= CLEAR_VISIBILITY_M[0]:
            return 0.0
        return 0.05 * (self.fog_visibility_m / 300.0) ** (-math.log(10) / math.log(6))

    @property
    def sky_overcast(self) -> bool:
        """No direct sun: set explicitly, or (overcast=None) whenever fog, rain or snow is present."""
        if self.overcast is not None:
            return bool(self.overcast)
        return self.rain_mm_h > 0 or self.snow_mm_h > 0 or self.fog_visibility_m < OVERCAST_BELOW_MOR_M

    @property
    def is_night(self) -> bool:
        return self.illuminance_lux < 400.0

    def summary(self) -> dict:
        return {
            "visibility_m": round(self.visibility_m, 1),
            "fog_visibility_m": round(self.fog_visibility_m, 1),
            "rain_mm_h": round(self.rain_mm_h, 2),
            "snow_mm_h": round(self.snow_mm_h, 3),
            "water_film_mm": round(self.water_film_mm, 3),
            "illuminance_lux": round(self.illuminance_lux, 3),
            "lens_coverage_pct": [round(c, 2) for c in self.lens_coverage_pct],
            "overcast": self.sky_overcast,
        }


@dataclass(frozen=True)
class Light:
    """Sun and artificial light of a frame, derived from the illuminance.

    Fields:
        sun_elevation_deg: sun elevation above the horizon [deg] (negative below it).
        sun_azimuth_deg: sun azimuth in the world frame, counter-clockwise from +x [deg].
        street_lamps_on: lamps are lit (illuminance below 50 lx, EN 13201 switching level).
        headlights_on: vehicles drive with dipped headlights (below 400 lx, dusk).
    """

    sun_elevation_deg: float
    sun_azimuth_deg: float
    street_lamps_on: bool
    headlights_on: bool


# Anchor points (illuminance [lx], sun elevation [deg]) for clear sky, from the usual twilight
# figures: sunrise ~ 400-700 lx, end of civil twilight (-6 deg) ~ 3 lx, nautical (-12 deg) ~ 0.01 lx;
# above 10 deg, E ~ 1.2e5 sin(h) lx.
_SUN_ANCHORS = np.array(
    [[0.005, -15.0], [0.01, -12.0], [3.0, -6.0], [400.0, 0.0], [2.1e4, 10.0], [1.2e5, 90.0]]
)


def sun_elevation_from_lux(lux: float) -> float:
    """Monotone piecewise log-linear map illuminance -> sun elevation (see `_SUN_ANCHORS`)."""
    x = np.log10(_SUN_ANCHORS[:, 0])
    return float(np.interp(math.log10(max(lux, 1e-4)), x, _SUN_ANCHORS[:, 1]))


def light_for(weather: WeatherState, sun_azimuth_deg: float) -> Light:
    return Light(
        sun_elevation_deg=sun_elevation_from_lux(weather.illuminance_lux),
        sun_azimuth_deg=sun_azimuth_deg,
        street_lamps_on=weather.illuminance_lux < 50.0,
        headlights_on=weather.illuminance_lux < 400.0,
    )


def _draw(rng: np.random.Generator, lo: float, hi: float, scale: str) -> float:
    if scale == "log":
        return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
    return float(rng.uniform(lo, hi))


def severity_interval(condition: str, severity: int) -> tuple[float, float]:
    """The [lo, hi] interval of the condition's primary quantity at severity 1..5."""
    if condition not in SEVERITY_TABLE:
        raise UserError(f"unknown condition {condition!r} (choose from: {', '.join(CONDITIONS)})")
    if not 1 <= severity <= 5:
        raise UserError(f"severity must be 1..5 for an active condition, got {severity}")
    return SEVERITY_TABLE[condition]["levels"][severity - 1]


def sample_weather(
    rng: np.random.Generator, conditions: tuple[str, ...], severity: int
) -> WeatherState:
    """Draw a WeatherState for the given conditions at one severity (0 = clear for all).

    The draw order is fixed (clear baseline first, then each condition in `CONDITIONS` order) so a
    seed gives the same state whatever order the conditions are written in.
    """
    return sample_weather_and_twin(rng, conditions, severity)[0]


def sample_weather_and_twin(
    rng: np.random.Generator, conditions: tuple[str, ...], severity: int
) -> tuple[WeatherState, WeatherState]:
    """`sample_weather`'s state and its counterfactual clear twin, from the same draws.

    The twin holds everything but the conditions' own quantities (DESIGN.md, "counterfactual
    twins"): the drawn clear-air visibility, and for fog, rain and snow the drawn light (overcast
    in both: the light is not what is studied); no fog, rain, snow, water film or lens cover. For
    night the light *is* the condition, so the twin gets the drawn daylight illuminance instead.
    """
    if not 0 <= severity <= 5:
        raise UserError(f"severity must be 0..5, got {severity}")
    for c in conditions:
        if c not in SEVERITY_TABLE:
            raise UserError(f"unknown condition {c!r} (choose from: {', '.join(CONDITIONS)})")
    active = set(conditions) if severity > 0 else set()
    # Baseline: clear air, daylight; overcast when any precipitation or fog is active.
    vis = _draw(rng, *CLEAR_VISIBILITY_M, "log")
    overcast = bool(active & {"rain", "fog", "snow"})
    lux = _draw(rng, *(OVERCAST_LUX if overcast else DAYLIGHT_LUX), "log")
    lens_u = rng.uniform(0.3, 1.0, size=2)  # per-camera share of the maximum coverage
    sky = True if overcast else None  # drawn with the light: the frame and its twin share it
    state = dict(fog_visibility_m=vis, illuminance_lux=lux, overcast=sky)
    lens = np.zeros(2)
    for c in CONDITIONS:
        if c not in active:
            continue
        spec = SEVERITY_TABLE[c]
        value = _draw(rng, *spec["levels"][severity - 1], spec["scale"])
        if c == "night":
            value = min(value, lux)
        state[spec["quantity"]] = value
        if c in LENS_COVERAGE_MAX_PCT:
            lens = np.maximum(lens, lens_u * LENS_COVERAGE_MAX_PCT[c][severity - 1])
    # overcast=True keeps the fog / rain / snow frame's diffuse sky in its twin (without it the clear
    # twin would get direct sun at the low elevation its overcast illuminance maps to)
    twin = WeatherState(fog_visibility_m=vis, illuminance_lux=lux, overcast=sky)
    return _state(state, (float(lens[0]), float(lens[1]))), twin


def road_film(rain_mm_h: float, snow_mm_h: float) -> float:
    """Water on the road [mm]: from rain (Gallaway), or melting snow (thinner: 0.3 mm per mm/h)."""
    return max(water_film_from_rain(rain_mm_h), 0.3 * snow_mm_h)


def _state(values: dict, lens: tuple[float, float]) -> WeatherState:
    """A WeatherState from primary quantities; the road film follows from rain and snow."""
    rain, snow = values.get("rain_mm_h", 0.0), values.get("snow_mm_h", 0.0)
    return WeatherState(
        fog_visibility_m=values["fog_visibility_m"],
        rain_mm_h=rain,
        snow_mm_h=snow,
        water_film_mm=road_film(rain, snow),
        illuminance_lux=values["illuminance_lux"],
        lens_coverage_pct=lens,
        overcast=values.get("overcast"),
    )


def clear_like(state: WeatherState) -> WeatherState:
    """The same moment without hydrometeors: no fog, rain, snow, water film or lens cover.

    Light is kept (night stays night): this is the "clear" end of a weather transition.
    """
    vis = state.fog_visibility_m if state.fog_visibility_m >= CLEAR_VISIBILITY_M[0] else 20_000.0
    return WeatherState(fog_visibility_m=vis, illuminance_lux=state.illuminance_lux)


Transition = Literal["none", "onset", "clearing", "bank"]
TRANSITIONS: tuple[str, ...] = ("none", "onset", "clearing", "bank")


def interpolate_weather(clear: WeatherState, target: WeatherState, f: float) -> WeatherState:
    """Blend two states, f=0 -> clear, f=1 -> target.

    Visibility and illuminance blend in log space (perception and extinction are logarithmic),
    rates, film and lens coverage linearly. The sky: where the two ends disagree (a sunlit clear end,
    an overcast target), the blend's sky follows its hydrometeors (`overcast=None`): the sun goes
    when rain or snow starts or the fog thickens below 2 km.
    """
    f = float(np.clip(f, 0.0, 1.0))

    def log_mix(a: float, b: float) -> float:
        return float(math.exp((1 - f) * math.log(a) + f * math.log(b)))

    def lin(a: float, b: float) -> float:
        return (1 - f) * a + f * b

    return replace(
        target,
        fog_visibility_m=log_mix(clear.fog_visibility_m, target.fog_visibility_m),
        rain_mm_h=lin(clear.rain_mm_h, target.rain_mm_h),
        snow_mm_h=lin(clear.snow_mm_h, target.snow_mm_h),
        water_film_mm=lin(clear.water_film_mm, target.water_film_mm),
        illuminance_lux=log_mix(clear.illuminance_lux, target.illuminance_lux),
        lens_coverage_pct=(
            lin(clear.lens_coverage_pct[0], target.lens_coverage_pct[0]),
            lin(clear.lens_coverage_pct[1], target.lens_coverage_pct[1]),
        ),
        overcast=target.overcast if clear.overcast == target.overcast else None,
    )


@dataclass(frozen=True)
class WeatherTrack:
    """Weather along a sequence: a clear state, a target state and how the frame moves between them.

    kind:
        none: the target weather all along.
        onset: clear until `start_s`, then a smooth ramp to the target over `ramp_s` (rain starting).
        clearing: the reverse of onset.
        bank: clear, ramp into the target at `start_s`, hold for `hold_s`, ramp out (a fog bank).
    """

    clear: WeatherState
    target: WeatherState
    kind: str = "none"
    start_s: float = 0.0
    ramp_s: float = 1.0
    hold_s: float = 1.0
    extra: dict = field(default_factory=dict)

    def fraction(self, t: float) -> float:
        """How much of the target applies at time t [s] (0..1), smoothstep ramps."""

        def ramp(x: float) -> float:
            x = min(max(x, 0.0), 1.0)
            return x * x * (3 - 2 * x)

        r = max(self.ramp_s, 1e-6)
        if self.kind == "none":
            return 1.0
        if self.kind == "onset":
            return ramp((t - self.start_s) / r)
        if self.kind == "clearing":
            return 1.0 - ramp((t - self.start_s) / r)
        if self.kind == "bank":
            up = ramp((t - self.start_s) / r)
            down = ramp((t - self.start_s - r - self.hold_s) / r)
            return up * (1.0 - down)
        raise UserError(f"unknown weather transition {self.kind!r} (choose from: {', '.join(TRANSITIONS)})")

    def state_at(self, t: float) -> WeatherState:
        f = self.fraction(t)
        if f >= 1.0:
            return self.target
        if f <= 0.0:
            return self.clear
        return interpolate_weather(self.clear, self.target, f)


def representative_weather(condition: str, severity: int) -> WeatherState:
    """A typical state of one condition at one severity (no randomness): the interval's centre
    (geometric for log-scaled quantities), lens coverage at 65 % of the level's maximum, overcast
    daylight (8 klx) for rain/fog/snow. Severity 0 is clear daylight (30 klx)."""
    if severity == 0:
        return WeatherState(illuminance_lux=30_000.0)
    lo, hi = severity_interval(condition, severity)
    spec = SEVERITY_TABLE[condition]
    value = math.sqrt(lo * hi) if spec["scale"] == "log" else (lo + hi) / 2
    state = {"fog_visibility_m": 20_000.0, "illuminance_lux": 8_000.0}
    state[spec["quantity"]] = value
    cover = 0.65 * LENS_COVERAGE_MAX_PCT[condition][severity - 1] if condition in LENS_COVERAGE_MAX_PCT else 0.0
    return _state(state, (cover, cover * 0.8))
