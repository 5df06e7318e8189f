"""Each degradation model against its physical law, on generated data: the same scene observed in
clear weather and under the degraded WeatherState (counterfactual twins of one moment)."""

import dataclasses
import math

import numpy as np
import pytest

from sensors.degrade import DEGRADATIONS, DegradeContext, Degrader
from sensors.degrade.base import OBSTRUCTION_PROBABILITY
from sensors.degrade.camera import pixel_range
from sensors.degrade.radar import p838_gamma, range_centres, two_way_loss_db
from sensors.lidar import P_MIN, detect
from sim.scenario import Context, stream
from sim.weather import WeatherState
from tests.sensors.conftest import render

CLEAR = WeatherState(illuminance_lux=30_000.0)


@pytest.fixture(scope="module")
def motorway():
    scenes, renderer = render("motorway", seed=11)
    scene = scenes[0]
    return scene, renderer, renderer.observe(scene, CLEAR)


def twin(renderer, scene, weather, context="motorway", obstructions=False):
    obs = renderer.observe(scene, weather)
    return Degrader(renderer.calib, context, 11, obstructions=obstructions).apply(obs, scene.frame_index)


def test_lidar_fog_law(motorway):
    """Object returns fall as exp(-2 alpha R), alpha = ln(20) / MOR, and vanish exactly where the
    attenuated power drops below the detection threshold (Hahner et al. 2021)."""
    scene, renderer, clear = motorway
    fog = WeatherState(fog_visibility_m=80.0, illuminance_lux=8000.0)
    foggy, params = twin(renderer, scene, fog)
    alpha = math.log(20) / 80.0
    assert params["lidar_extinction"]["alpha_per_m"] == pytest.approx(alpha)
    c, f = clear.lidar, foggy.lidar
    obj = c.returned & (c.instance > 0)
    assert obj.sum() > 50
    kept = obj & (f.instance == c.instance)  # not replaced by a fog (backscatter) point
    expected = c.power * np.exp(-2 * alpha * c.range)
    np.testing.assert_allclose(f.power[kept], expected[kept], rtol=1e-5)
    # returns vanish exactly where the attenuated power is below P_MIN
    np.testing.assert_array_equal(f.returned[kept], expected[kept] >= P_MIN)
    assert (kept & ~f.returned).any() and (kept & f.returned).any()
    # fog points appear near the sensor (backscatter), never beyond the hard target
    fogpts = f.returned & (f.instance == 0) & (f.material == 0)
    assert fogpts.sum() > 100 and np.all(f.range[fogpts] < 16.0)
    assert np.all(f.range[fogpts] <= np.where(np.isfinite(c.range[fogpts]), c.range[fogpts], np.inf) + 0.25)


def test_camera_contrast_follows_koschmieder(motorway):
    """Apparent contrast of objects against the airlight falls as exp(-beta d), beta from visibility."""
    scene, renderer, _ = motorway
    fog = WeatherState(fog_visibility_m=150.0, illuminance_lux=8000.0)
    raw = renderer.observe(scene, fog)
    ctx = DegradeContext(renderer.calib, Context.parse("fog"), {"_rng": stream(0, "x")}, camera="camera_right")
    model = DEGRADATIONS.get("atmosphere")
    params = model.sample_params(np.random.default_rng(0), fog, ctx)
    assert params["beta_per_m"] == pytest.approx(math.log(20) / 150.0 + 0.0)
    out = model.apply(raw.camera_right, params, ctx)
    A = raw.camera_right.sky_radiance
    d = pixel_range(raw.camera_right, renderer.calib.camera_right)
    geo = np.isfinite(d) & (raw.camera_right.instance > 0)
    c0 = (raw.camera_right.radiance[geo] - A) / A
    c1 = (out.radiance[geo] - A) / A
    ok = np.abs(c0) > 0.05
    ratio = (c1[ok] / c0[ok])
    np.testing.assert_allclose(ratio, np.repeat(np.exp(-params["beta_per_m"] * d[geo])[:, None], 3, 1)[ok], rtol=1e-4)
    # fitting the law to the data recovers beta, i.e. the visibility
    dd = np.repeat(d[geo][:, None], 3, 1)[ok]
    beta_fit = -np.polyfit(dd, np.log(ratio), 1)[0]
    assert math.log(20) / beta_fit == pytest.approx(150.0, rel=0.01)


def test_radar_rain_matches_p838_over_two_way_path(motorway):
    scene, renderer, clear = motorway
    rain = WeatherState(rain_mm_h=25.0, illuminance_lux=8000.0)
    rainy, params = twin(renderer, scene, rain)
    g = params["radar_rain"]["gamma_db_per_km"]
    assert g == pytest.approx(11.4, rel=0.02)  # ITU-R P.838-3 at 77 GHz, 25 mm/h
    for r_mm_h, ref in ((1, 1.1), (10, 5.9), (50, 18.8)):
        assert p838_gamma(r_mm_h) == pytest.approx(ref, rel=0.03)
    c, w = clear.radar.signal, rainy.radar.signal
    m = c > 0
    ctx = DegradeContext(renderer.calib, Context.parse("rain"))
    loss_db = 10 * np.log10(w[m] / c[m])
    expected = -two_way_loss_db(g, np.broadcast_to(range_centres(ctx), c.shape)[m])
    np.testing.assert_allclose(loss_db, expected, atol=1e-3)
    # the clutter is heavy-tailed: its max/mean ratio is far above an exponential's
    clut = rainy.radar.clutter[:, 20:]
    assert clut.max() / clut.mean() > 50


def test_radar_barely_notices_fog_while_lidar_and_camera_do(motorway):
    scene, renderer, clear = motorway
    fog = WeatherState(fog_visibility_m=50.0, illuminance_lux=8000.0)
    foggy, params = twin(renderer, scene, fog)
    # ITU-R P.840: 0.5 g/m3 -> ~1.6 dB/km: under 0.35 dB two-way at 100 m
    assert params["radar_fog"]["liquid_water_g_m3"] == pytest.approx(0.5, rel=1e-6)
    ratio = foggy.radar.signal[clear.radar.signal > 0] / clear.radar.signal[clear.radar.signal > 0]
    assert 10 * np.log10(ratio.min()) > -0.35
    hard = (foggy.lidar.instance > 0) & foggy.lidar.returned
    assert hard.sum() < 0.5 * ((clear.lidar.instance > 0) & clear.lidar.returned).sum()


def test_night_leaves_lidar_and_radar_bit_identical(motorway):
    scene, renderer, _ = motorway
    night = WeatherState(illuminance_lux=0.5)
    a, pa = twin(renderer, scene, CLEAR, obstructions=True)
    b, pb = twin(renderer, scene, night, obstructions=True)
    fa, fb = renderer.finalize(scene, a, pa), renderer.finalize(scene, b, pb)
    for name in ("lidar_points", "lidar_instance", "lidar_bev", "fwd_lidar", "radar_polar", "radar_bev"):
        assert np.array_equal(getattr(fa, name), getattr(fb, name)), name
    assert not np.array_equal(fa.camera_right, fb.camera_right)
    assert fb.camera_right.mean() < 0.5 * fa.camera_right.mean()  # and the camera does see the night
    # sensor noise is on in both; at night the exposure limit forces analogue gain (and more noise)
    assert "camera_noise" in pa and "camera_noise" in pb
    assert fa.meta["camera_gain"]["camera_right"] == 1.0 < fb.meta["camera_gain"]["camera_right"]


@pytest.mark.parametrize("name", DEGRADATIONS.names())
def test_every_registered_model_samples_applies_and_is_pure(name, motorway):
    scene, renderer, _ = motorway
    model = DEGRADATIONS.get(name)
    heavy = WeatherState(fog_visibility_m=60.0, rain_mm_h=30.0, snow_mm_h=2.0, water_film_mm=1.0,
                         illuminance_lux=1.0, lens_coverage_pct=(20.0, 20.0))
    obs = renderer.observe(scene, heavy)
    target = "camera_right" if model.sensor == "camera" else model.sensor
    seq = {"_rng": stream(1, "seq")}
    ctx = DegradeContext(renderer.calib, Context.parse("snow"), seq, camera=target if model.sensor == "camera" else "")
    params = None
    for k in range(200):  # obstructions are rare: draw sequences until one is active
        ctx.sequence.clear()
        ctx.sequence["_rng"] = stream(k, "seq")
        params = model.sample_params(np.random.default_rng(k), heavy, ctx)
        if params is not None:
            break
    assert params is not None, name
    import json

    json.dumps(params)  # stored with the frame
    before = getattr(obs, target)
    snapshot = {f.name: np.copy(getattr(before, f.name)) for f in dataclasses.fields(before)
                if isinstance(getattr(before, f.name), np.ndarray)}
    after = model.apply(before, params, ctx)
    for field_name, arr in snapshot.items():
        assert np.array_equal(getattr(before, field_name), arr), f"{name} modified its input ({field_name})"
        assert getattr(after, field_name).shape == arr.shape
    changed = any(not np.array_equal(getattr(after, f), snapshot[f]) for f in snapshot) or \
        (model.sensor == "camera" and after.sensor_noise is not None)
    assert changed, f"{name} changed nothing"


def test_obstruction_rates_follow_the_per_context_table():
    n = 4000
    for kind, model_name in (("lens_soiling", "lens_soiling"), ("radar_blocked_sector", "radar_blocked_sector")):
        model = DEGRADATIONS.get(model_name)
        for ctx_name in ("motorway", "snow"):
            p = OBSTRUCTION_PROBABILITY[kind][ctx_name]
            hits = 0
            for k in range(n):
                ctx = DegradeContext(None, Context.parse(ctx_name), {"_rng": stream(k, "s")}, camera="camera_left")
                hits += model.sample_params(np.random.default_rng(k), CLEAR, ctx) is not None
            sd = math.sqrt(p * (1 - p) / n)
            assert abs(hits / n - p) < 4 * sd, (kind, ctx_name, hits / n, p)


def test_lidar_loses_more_returns_as_fog_thickens(motorway):
    scene, renderer, _ = motorway
    counts = []
    for vis in (5000.0, 600.0, 150.0, 50.0):
        obs, _ = twin(renderer, scene, WeatherState(fog_visibility_m=vis, illuminance_lux=8000.0))
        far = obs.lidar.range > 20.0
        counts.append(int((obs.lidar.returned & (obs.lidar.material != 0) & far).sum()))
    # hard returns beyond 20 m: monotone in fog density, nearly all gone at 50 m visibility
    assert counts == sorted(counts, reverse=True) and counts[-1] < 0.1 * counts[0], counts


def test_detect_threshold_definition():
    r = np.array([10.0, 50.0, 50.0, 120.0])
    p = np.array([1e-3, 0.1 / 2500, 0.099 / 2500, 1.0])
    np.testing.assert_array_equal(detect(r, p), [True, True, False, False])


def test_camera_noise_is_poisson_gaussian():
    """Variance = mean + read noise^2 (photon counting), whichever branch of the sampler is used."""
    from sensors.camera import shot_and_read_noise, srgb_encode, srgb_encode_fast

    rng = np.random.default_rng(0)
    for lam in (3.0, 25.0, 40.0, 1000.0):
        e = shot_and_read_noise(rng, np.full(200_000, lam), 4.0)
        assert e.mean() == pytest.approx(lam, rel=0.01, abs=0.05)
        assert e.var() == pytest.approx(lam + 16.0, rel=0.03)
    x = np.random.default_rng(1).uniform(0, 1, 10_000)
    assert np.max(np.abs(srgb_encode_fast(x) - srgb_encode(x))) < 0.2 / 255


def test_model_streams_are_derived_on_first_draw(motorway, monkeypatch):
    """Degrader derives a model's stream only when sample_params draws from it; draws, params and
    observations are those of eagerly derived streams."""
    import sensors.degrade as degrade_pkg

    lazy = degrade_pkg._Stream(5, "degrade", 3, "rain_streaks", "camera_left")
    assert lazy._rng is None
    ref = stream(5, "degrade", 3, "rain_streaks", "camera_left")
    assert lazy.uniform(6, 9) == ref.uniform(6, 9) and lazy.integers(2**31) == ref.integers(2**31)

    scene, renderer, _ = motorway
    heavy = WeatherState(fog_visibility_m=60.0, rain_mm_h=30.0, snow_mm_h=2.0, water_film_mm=1.0,
                         illuminance_lux=1.0, lens_coverage_pct=(20.0, 20.0))
    obs = renderer.observe(scene, heavy)
    results = []
    for make in (degrade_pkg._Stream, stream):
        monkeypatch.setattr(degrade_pkg, "_Stream", make)
        out, params = Degrader(renderer.calib, "snow", 11).apply(obs, scene.frame_index)
        results.append((repr(params), out.camera_left.radiance.tobytes(), out.lidar.power.tobytes(),
                        out.radar.clutter.tobytes()))
    assert results[0] == results[1]
