"""The compiled kernels (sensors.kernels) give the same bits as the numpy code they replaced (the
lights kernel: within a few ulps, the same bits on the reference machine). That a whole generated
dataset keeps its bytes is tests/sensors/test_determinism.py."""


import numpy as np
import pytest
from numba import njit

from sensors import camera as cam_mod
from sensors import kernels
from sensors.camera import (
    ALBEDO,
    EMISSIVE,
    GROUND_ALBEDO,
    MATERIAL_ID,
    MATERIALS,
    PER_INSTANCE,
    SKY_COLOUR,
    SUN_COLOUR,
    _colour_table,
    _normals_from_points,
    pixel_rays,
)
from tests.sensors.conftest import render

GROUND = [MATERIAL_ID[m] for m in ("asphalt", "lane_paint", "grass", "sidewalk")]


def _bits_equal(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


# --- the numpy formulation of sensors.camera.shade before the kernels (commit 00daa53) ---------


def reference_normals(P, D, cam_pos, material):
    n = _normals_from_points(P, D)
    to_cam = cam_pos - P
    flip = np.einsum("hwc,hwc->hw", n, to_cam) < 0
    n = np.where(flip[..., None], -n, n)
    snap = np.isin(material, GROUND) & (n[..., 2] > 0.95)
    n[snap] = (0.0, 0.0, 1.0)
    return n


def reference_shade_without_lights(index, material, depth, cam, world_from_ego, actor_ids, lighting, caster=None):
    """sensors.camera.shade as it was, for frames without lamps and headlights."""
    H, W = depth.shape
    geo = np.isfinite(depth)
    rays = pixel_rays(cam)
    z = np.where(geo, depth, 0.0)[..., None]
    P_cam = rays / rays[..., 2:3] * z
    world_from_cam = (world_from_ego @ cam.ego_from_camera).astype(np.float32)
    P = P_cam @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]
    cam_pos = world_from_cam[:3, 3]
    n = reference_normals(P, np.where(geo, depth, np.float32(1e6)), cam_pos, material)
    albedo = ALBEDO[material].copy()
    per_inst = PER_INSTANCE[material] & (index > 0)
    if per_inst.any():
        table = _colour_table(tuple(int(i) for i in actor_ids))
        albedo[per_inst] = table[index[per_inst], material[per_inst]]
    nz = n[..., 2]
    sky_e = lighting.sky_lux * ((1 + nz) / 2 + GROUND_ALBEDO * (1 - nz) / 2)
    E = sky_e[..., None] * SKY_COLOUR
    if lighting.sun_normal_lux > 0:
        cos_s = np.einsum("hwc,c->hw", n, lighting.sun_dir)
        lit = geo & (cos_s > 0)
        if caster is not None and lit.any():
            sub = np.zeros_like(lit)
            sub[::2, ::2] = lit[::2, ::2]
            pts = P[sub] + n[sub] * 0.05
            hits = caster.cast(pts, np.broadcast_to(lighting.sun_dir, pts.shape), max_range=300.0)
            shadow_sub = np.zeros(lit[::2, ::2].shape, bool)
            shadow_sub[lit[::2, ::2]] = np.isfinite(hits.range)
            shadow = np.repeat(np.repeat(shadow_sub, 2, 0), 2, 1)[:H, :W]
            lit &= ~shadow
        E += (np.where(lit, cos_s, 0.0) * lighting.sun_normal_lux)[..., None] * SUN_COLOUR
    L = albedo * E / np.pi
    for m in MATERIALS:
        if m.emits_when and ((m.emits_when == "lamps" and lighting.lamps_on) or
                             (m.emits_when == "headlights" and lighting.headlights_on)):
            sel = material == MATERIAL_ID[m.name]
            L[sel] += EMISSIVE[MATERIAL_ID[m.name]]
    sky_h = (lighting.sky_lux + 0.2 * lighting.sun_normal_lux * max(lighting.sun_dir[2], 0)) / np.pi
    sky_h = max(sky_h, 1e-4)
    if not geo.all():
        ray_w = rays[~geo] @ world_from_cam[:3, :3].T
        elev = np.clip(ray_w[:, 2], 0, 1)
        L[~geo] = (sky_h * (1.0 - 0.5 * elev))[:, None] * SKY_COLOUR
    return L.astype(np.float32, copy=False)


# --- kernels on random inputs ------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_surface_normals_equal_numpy_on_random_point_maps(seed):
    rng = np.random.default_rng(seed)
    H, W = 37, 53
    # a noisy tilted plane with depth steps, sky pixels (1e6) and exact ties between neighbours
    vv, uu = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    plane = np.stack([uu * 0.3, vv * 0.3, 0.1 * uu + 0.05 * vv], -1)
    P = (plane + rng.normal(size=(H, W, 3)) * [0.05, 0.05, 0.02]).astype(np.float32)
    D = (10 + rng.integers(0, 3, size=(H, W)) * 2.5).astype(np.float32)  # many equal jumps
    D[rng.random((H, W)) < 0.1] = 1e6
    P[5, 7] = P[5, 8]  # a zero-length difference: zero normal
    material = rng.integers(0, len(MATERIALS), size=(H, W)).astype(np.uint8)
    cam_pos = np.array([3.0, -2.0, 25.0], np.float32)
    snap = np.isin(np.arange(len(MATERIALS)), GROUND)
    ours = kernels.surface_normals(P, D, cam_pos, snap, material)
    assert _bits_equal(ours, reference_normals(P, D, cam_pos, material))
    assert np.any(ours[..., 2] == 1.0) and np.any(np.all(ours == 0, axis=-1))  # snapping and the zero normal occur


def test_sun_cosine_follows_numpys_einsum_order():
    rng = np.random.default_rng(3)
    n = rng.normal(size=(64, 80, 3)).astype(np.float32)
    sun = rng.normal(size=3)
    assert _bits_equal(kernels.sun_cosine(n, sun), np.einsum("hwc,c->hw", n, sun))


def test_cell_max_equals_the_sort_reference():
    def by_sorting(cells, values, n):  # sensors.lidar._cell_max before the kernel
        out = np.zeros(n, np.float32)
        order = np.lexsort((values, cells))
        c = cells[order]
        last = np.r_[c[1:] != c[:-1], True]
        out[c[last]] = values[order][last]
        return out

    rng = np.random.default_rng(4)
    cells = rng.integers(0, 500, 5000)
    for values in (rng.random(5000), rng.integers(0, 4, 5000) / 4.0, rng.random(5000).astype(np.float32)):
        assert _bits_equal(kernels.cell_max(cells, values, 600), by_sorting(cells, values, 600))
    values = rng.random(5000)
    values[::97] = np.nan
    values[::89] = -0.0
    assert _bits_equal(kernels.cell_max(cells, values, 600), by_sorting(cells, values, 600))


def test_camera_model_kernels_equal_numpy():
    rng = np.random.default_rng(5)
    x = (rng.normal(0.5, 0.6, size=(40, 50, 3))).astype(np.float32)  # beyond 0..1 on both sides
    x[0, 0, 0], x[0, 0, 1] = 0.0, 1.0
    idx = (np.clip(x, 0.0, 1.0) * 65535.0 + 0.5).astype(np.int32)
    assert _bits_equal(kernels.srgb_lookup(x, cam_mod._SRGB_LUT), cam_mod._SRGB_LUT[idx])
    half_steps = (np.arange(512, dtype=np.float32) + 0.5) / 255  # ties of the rounding, half to even
    for y in (x, half_steps):
        assert _bits_equal(kernels.to_uint8(y), np.round(np.clip(y, 0, 1) * 255).astype(np.uint8))


def test_lens_blur_equals_scipys_gaussian_filter():
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(11)
    shapes = [(188, 336, 3), (1, 1, 3), (2, 3, 3), (1, 5, 1), (3, 1, 2), (4, 4, 3), (5, 6, 3), (7, 9, 2)]
    for shape in shapes:
        for x in (rng.gamma(0.5, 300.0, shape).astype(np.float32), rng.random(shape)):
            assert _bits_equal(cam_mod.lens_blur(x), gaussian_filter(x, sigma=(cam_mod.PSF_SIGMA_PX,) * 2 + (0,))), shape
    x = rng.random((6, 8, 3)).astype(np.float32)
    x[2, 3, 1], x[4, 0, 2] = np.inf, np.nan
    ref = gaussian_filter(x, sigma=(cam_mod.PSF_SIGMA_PX,) * 2 + (0,))
    assert _bits_equal(cam_mod.lens_blur(x), ref) and np.isnan(ref).any() and np.isinf(ref).any()
    y = rng.random((9, 7, 3)).astype(np.float32)[::-1, ::2]  # a strided view
    assert _bits_equal(cam_mod.lens_blur(y), gaussian_filter(y, sigma=(cam_mod.PSF_SIGMA_PX,) * 2 + (0,)))


def test_exposure_kernels_equal_numpy():
    rng = np.random.default_rng(15)
    blurred = rng.gamma(0.5, 40.0, size=(30, 40, 3)).astype(np.float32)
    blurred[0, :3] = [0.0, np.inf, 1e-30]
    k, full_well, gain = 0.0123, 6000.0, 2.7
    ref = np.clip(blurred * k, 0, 1) * full_well
    assert _bits_equal(kernels.exposed_electrons(blurred, k, full_well), ref)
    noisy = (ref + rng.normal(0, 40, ref.shape)).astype(np.float32)  # beyond 0..full_well on both sides
    assert _bits_equal(kernels.noisy_srgb(noisy, full_well, gain, cam_mod._SRGB_LUT),
                       cam_mod.srgb_encode_fast(noisy / full_well * gain))


def test_expose_fast_path_equals_the_general_one():
    rng = np.random.default_rng(16)
    radiance = rng.gamma(0.5, 2.0, size=(24, 32, 3)).astype(np.float32)
    noise = {"full_well_e": 6000.0, "read_noise_e": 4.0, "max_gain": 4.0, "seed": 5}
    fast = cam_mod.expose(cam_mod.CameraObservation(radiance, None, None, None, None, sensor_noise=noise), 0.004)
    # a numpy float64 exposure is not weak (NEP 50): the general numpy path, float64 arithmetic
    general = cam_mod.expose(cam_mod.CameraObservation(radiance, None, None, None, None, sensor_noise=noise),
                             np.float64(0.004))
    assert general.dtype == np.float32 and fast.dtype == np.float32
    signal = np.clip(cam_mod.lens_blur(radiance) * 0.004, 0, 1) * 6000.0
    noisy = cam_mod.shot_and_read_noise(np.random.default_rng(5), signal, 4.0)
    gain = float(np.clip(cam_mod.wanted_exposure(radiance) / 0.004, 1.0, 4.0))
    assert _bits_equal(fast, cam_mod.srgb_encode_fast(noisy / 6000.0 * gain))
    signal64 = np.clip(cam_mod.lens_blur(radiance) * np.float64(0.004), 0, 1) * 6000.0
    assert signal64.dtype == np.float64
    noisy64 = cam_mod.shot_and_read_noise(np.random.default_rng(5), signal64, 4.0)
    assert _bits_equal(general, cam_mod.srgb_encode_fast(noisy64 / 6000.0 * gain))


@pytest.mark.parametrize("scale", [3.0, 1100.0])  # night (Poisson counts) and day (normal approximation)
def test_sensor_noise_draws_and_arithmetic_equal_numpy(scale):
    def reference(rng, electrons, read_noise_e):  # sensors.camera.shot_and_read_noise before the kernel
        out = np.empty(electrons.shape, np.float32)
        low = electrons < 30.0
        out[low] = rng.poisson(electrons[low])
        hi = ~low
        lam = electrons[hi].astype(np.float32)
        out[hi] = lam + np.sqrt(lam) * rng.standard_normal(lam.shape, dtype=np.float32)
        out += read_noise_e * rng.standard_normal(out.shape, dtype=np.float32)
        return out

    e64 = np.random.default_rng(6).gamma(1.0, scale, size=(30, 40, 3))
    for e in (e64.astype(np.float32), e64):  # the camera passes float32; float64 is rounded where numpy did
        ours = cam_mod.shot_and_read_noise(np.random.default_rng(9), e, 4.0)
        assert _bits_equal(ours, reference(np.random.default_rng(9), e, 4.0))


def test_decode_codes_equals_numpy():
    rng = np.random.default_rng(7)
    colour = rng.integers(0, 256, size=(20, 30, 4)).astype(np.uint8)
    colour[..., 3] = np.where(rng.random((20, 30)) < 0.7, 255, colour[..., 3])
    depth = rng.normal(20, 15, size=(20, 30)).astype(np.float32)  # some <= 0
    valid = colour[..., 3] == 255
    index = colour[..., 0].astype(np.int64) | (colour[..., 1].astype(np.int64) << 8)
    index[~valid] = 0
    ours = kernels.decode_codes(colour, depth)
    assert _bits_equal(ours[0], index)
    assert _bits_equal(ours[1], np.where(valid, colour[..., 2], 0).astype(np.uint8))
    assert _bits_equal(ours[2], np.where(valid & (depth > 0), depth, np.inf).astype(np.float32))


# --- shading of real frames ---------------------------------------------------------------------


def _frames():
    out = []
    for context, severity in (("city", 0), ("fog", 3), ("night", 2)):
        scenes, renderer = render(context, severity=severity, seed=7)
        scene = scenes[0]
        from sim.weather import light_for

        light = light_for(scene.weather, scene.light.sun_azimuth_deg)
        lighting = cam_mod.lighting_for(scene.weather, light, renderer.lamps,
                                        cam_mod.headlights_of(scene.actors, scene.ego.pose, scene.ego.size))
        ids = renderer._set_actors(scene)
        cam = renderer.calib.camera("camera_right")
        index, material, depth = renderer.stereo.codes(cam, scene.ego.pose)
        out.append((context, (index, material, depth, cam, scene.ego.pose, ids, lighting), renderer.caster))
    return out


@pytest.fixture(scope="module")
def frames():
    return _frames()


def test_shade_equals_the_numpy_formulation_on_rendered_frames(frames):
    for context, args, caster in frames:
        lighting = args[-1]
        if lighting.lamps_on or lighting.headlights_on:
            # the lights have their own tests below; compare the rest with them switched off
            import dataclasses

            args = (*args[:-1], dataclasses.replace(lighting, lamps_on=False, headlights_on=False))
        ours = cam_mod.shade(*args, caster)
        assert _bits_equal(ours.radiance, reference_shade_without_lights(*args, caster)), context
    assert any(a[-1].sun_normal_lux > 0 for _, a, _ in frames)  # the sun and shadow path ran


# --- artificial light: the numpy formulation of sensors.camera.shade up to sensor model 3 ---------


def _reference_beam(direction, axis, up, h_width_deg, v_width_deg):
    cos_axis = direction @ axis
    side = np.cross(axis, up)
    h = np.degrees(np.arctan2(direction @ side, cos_axis))
    v = np.degrees(np.arctan2(direction @ up, cos_axis))
    w = np.exp(-((h / h_width_deg) ** 2) - ((v / v_width_deg) ** 2))
    w = w * np.where(v > 0.5, 0.03, 1.0)  # dipped beam: sharp cut-off above the horizon
    return np.where(cos_axis > 0, w, 0.0)


def reference_lights(Pf, nf, lamps, heads):
    """Illuminance of lamps and headlights, one numpy pass per light (heads: [(pos, axis)])."""
    Ef = np.zeros((len(Pf), 3), np.float32)
    up = np.array([0.0, 0.0, 1.0])

    def add_light(pos, intensity_fn, colour):
        d = pos - Pf
        dist2 = np.einsum("ij,ij->i", d, d)
        dist = np.sqrt(dist2)
        to_light = d / np.maximum(dist, 1e-6)[:, None]
        cos_i = np.einsum("ij,ij->i", nf, to_light)
        e = np.where(cos_i > 0, intensity_fn(-to_light) * cos_i / np.maximum(dist2, 0.25), 0.0)
        Ef[:] += e[:, None].astype(np.float32) * colour

    for pos in lamps:
        add_light(pos, lambda dirs: cam_mod.LAMP_INTENSITY_CD * np.clip(-dirs[:, 2], 0, 1) ** 1.5, cam_mod.LAMP_COLOUR)
    for pos, axis in heads:
        add_light(pos, lambda dirs, a=axis: cam_mod.HEADLIGHT_INTENSITY_CD * _reference_beam(
            dirs, a, up, cam_mod.HEADLIGHT_H_WIDTH_DEG, cam_mod.HEADLIGHT_V_WIDTH_DEG), cam_mod.HEADLIGHT_COLOUR)
    return Ef


def _kernel_lights(Pf, nf, lamps, heads, E=None):
    """The kernel's E += lights on points as a (N, 1) image, all pixels surfaces; E defaults to zeros."""
    E = np.zeros((len(Pf), 1, 3), np.float32) if E is None else E.reshape(-1, 1, 3).copy()
    kernels.artificial_light(
        Pf.reshape(-1, 1, 3), nf.reshape(-1, 1, 3), np.ones((len(Pf), 1), bool), E,
        np.asarray(lamps, np.float64).reshape(-1, 3), cam_mod.LAMP_INTENSITY_CD, cam_mod.LAMP_COLOUR,
        np.array([p for p, _ in heads], np.float64).reshape(-1, 3),
        np.array([a for _, a in heads], np.float64).reshape(-1, 3), cam_mod.HEADLIGHT_INTENSITY_CD,
        cam_mod.HEADLIGHT_COLOUR, cam_mod.HEADLIGHT_H_WIDTH_DEG, cam_mod.HEADLIGHT_V_WIDTH_DEG)
    return E.reshape(-1, 3)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_artificial_light_equals_the_numpy_formulation(seed):
    rng = np.random.default_rng(seed)
    N = 4000
    Pf = np.column_stack([rng.uniform(-40, 40, N), rng.uniform(-40, 40, N), rng.uniform(0, 3, N)]).astype(np.float32)
    nf = rng.normal(size=(N, 3))
    nf[: N // 2] = (0.0, 0.0, 1.0)  # half of them ground
    nf = (nf / np.linalg.norm(nf, axis=1, keepdims=True)).astype(np.float32)
    lamps = np.column_stack([rng.uniform(-30, 30, 5), rng.uniform(-30, 30, 5), rng.uniform(6, 10, 5)])
    heads = []
    for _ in range(4):
        yaw = rng.uniform(0, 2 * np.pi)
        heads.append((np.array([rng.uniform(-20, 20), rng.uniform(-20, 20), 0.7]),
                      np.array([np.cos(yaw), np.sin(yaw), -0.02]) / np.hypot(1.0, 0.02)))
    ref = reference_lights(Pf, nf, lamps, heads)
    ours = _kernel_lights(Pf, nf, lamps, heads)
    assert ours.dtype == np.float32 and ours.shape == ref.shape
    assert (ref > 0).mean() > 0.3  # most points are lit
    # exp, pow and atan2 from libm against numpy's: a few float32 ulps
    np.testing.assert_allclose(ours, ref, rtol=2e-6, atol=1e-9)
    # each light alone: a lamp right above a ground point gives I / h^2
    one = _kernel_lights(np.array([[0, 0, 0]], np.float32), np.array([[0, 0, 1]], np.float32),
                         np.array([[0.0, 0.0, 8.0]]), [])
    np.testing.assert_allclose(one[0], cam_mod.LAMP_INTENSITY_CD / 64.0 * cam_mod.LAMP_COLOUR, rtol=1e-6)
    # a headlight 20 m straight ahead along its axis, on a surface facing it: I / d^2
    face = _kernel_lights(np.array([[20, 0, 0.7]], np.float32), np.array([[-1, 0, 0]], np.float32), np.zeros((0, 3)),
                          [(np.array([0.0, 0.0, 0.7]), np.array([1.0, 0.0, 0.0]))])
    np.testing.assert_allclose(face[0], cam_mod.HEADLIGHT_INTENSITY_CD / 400.0 * cam_mod.HEADLIGHT_COLOUR, rtol=1e-6)
    # behind the headlight and above a lamp: nothing
    behind = _kernel_lights(np.array([[-5, 0, 0.7]], np.float32), np.array([[1, 0, 0]], np.float32), np.zeros((0, 3)),
                            [(np.array([0.0, 0.0, 0.7]), np.array([1.0, 0.0, 0.0]))])
    above = _kernel_lights(np.array([[0, 0, 12]], np.float32), np.array([[0, 0, -1]], np.float32),
                           np.array([[0.0, 0.0, 8.0]]), [])
    assert not behind.any() and not above.any()


def test_lights_add_to_E_only_on_surface_pixels():
    rng = np.random.default_rng(12)
    P = rng.uniform(-20, 20, size=(6, 7, 3)).astype(np.float32)
    n = np.broadcast_to(np.array([0, 0, 1], np.float32), P.shape).copy()
    geo = rng.random((6, 7)) < 0.6
    E = rng.random((6, 7, 3)).astype(np.float32)
    E[0, 0] = -0.0
    lamps = np.array([[0.0, 0.0, 8.0], [5.0, -3.0, 9.0]])
    ours = E.copy()
    kernels.artificial_light(P, n, geo, ours, lamps, cam_mod.LAMP_INTENSITY_CD, cam_mod.LAMP_COLOUR, np.zeros((0, 3)),
                             np.zeros((0, 3)), cam_mod.HEADLIGHT_INTENSITY_CD, cam_mod.HEADLIGHT_COLOUR,
                             cam_mod.HEADLIGHT_H_WIDTH_DEG, cam_mod.HEADLIGHT_V_WIDTH_DEG)
    ref = E.copy()
    ref.reshape(-1, 3)[geo.reshape(-1)] += _kernel_lights(P[geo], n[geo], lamps, [])  # as shade did up to now
    assert _bits_equal(ours, ref) and not np.array_equal(ours[geo], E[geo]) and _bits_equal(ours[~geo], E[~geo])


@njit(cache=True)
def _lamp_with_pow(tz, cos_i, dist2, lamp_cd):  # the lamp term as the kernel computed it up to now
    return np.float32(lamp_cd * min(max(tz, 0.0), 1.0) ** 1.5 * cos_i / max(dist2, 0.25))


@njit(cache=True)
def _lamp_terms(f, tz, cos_i, dist2, lamp_cd):
    out = np.empty(len(tz), np.float32)
    for i in range(len(tz)):
        out[i] = f(tz[i], cos_i[i], dist2[i], lamp_cd)
    return out


def test_lamp_term_without_pow_equals_the_pow_formulation():
    rng = np.random.default_rng(13)
    N = 200_000
    tz = np.concatenate([rng.uniform(-0.2, 1.2, N), [0.0, 1.0, -0.0, 5e-324, 1e-300]])
    cos_i = np.concatenate([rng.uniform(0, 1, N), [0.5, 1.0, 0.5, 1.0, 1.0]])
    dist2 = np.concatenate([rng.uniform(0.0, 2e4, N), [1.0, 0.1, 4.0, 1.0, 1.0]])
    lamp_cd = cam_mod.LAMP_INTENSITY_CD
    # and illuminances right at a float32 rounding midpoint, where pow has to decide
    c = rng.uniform(0.05, 1.0, 2000)
    ci = rng.uniform(0.05, 1.0, 2000)
    num = lamp_cd * c ** 1.5 * ci
    f = (num / rng.uniform(1.0, 5000.0, 2000)).astype(np.float32)
    mid = (f.astype(np.float64) + np.nextafter(f, np.float32(np.inf)).astype(np.float64)) / 2
    tz, cos_i, dist2 = np.concatenate([tz, c]), np.concatenate([cos_i, ci]), np.concatenate([dist2, num / mid])
    e = lamp_cd * c * np.sqrt(c) * ci / (num / mid)
    band = 2.0 ** -40
    assert ((e * (1 - band)).astype(np.float32) != (e * (1 + band)).astype(np.float32)).mean() > 0.5  # pow decides
    ours = _lamp_terms(kernels._lamp_illuminance, tz, cos_i, dist2, lamp_cd)
    assert _bits_equal(ours, _lamp_terms(_lamp_with_pow, tz, cos_i, dist2, lamp_cd))


@pytest.mark.parametrize("n_ids", [0, 3])
def test_instance_ids_equal_numpy(n_ids):
    rng = np.random.default_rng(14)
    index = rng.integers(-1, 6, size=(9, 11))
    actor_ids = rng.integers(100, 10**9, n_ids).astype(np.int64)
    ref = np.where(index > 0, np.concatenate([[0], actor_ids])[np.clip(index, 0, len(actor_ids))], 0).astype(np.int64)
    assert _bits_equal(kernels.instance_ids(index, actor_ids), ref)


def test_lights_of_a_rendered_night_frame_equal_the_numpy_formulation(frames):
    context, args, caster = frames[2]
    lighting = args[-1]
    assert context == "night" and lighting.lamps_on and lighting.headlights_on and len(lighting.lamps)
    with_lights = cam_mod.shade(*args, caster).radiance
    import dataclasses

    dark = dataclasses.replace(lighting, lamps_on=False, headlights_on=False)
    without = cam_mod.shade(*args[:-1], dark, caster).radiance
    assert (with_lights > without).mean() > 0.2  # the lights light a good part of the image
