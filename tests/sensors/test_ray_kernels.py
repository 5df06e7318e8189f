"""The compiled ray-casting and radar kernels (sensors.ray_kernels) give the same bits as the numpy
code they replaced, on random inputs with edge cases and on a rendered frame."""

import numpy as np
import pytest
import scipy.fft as sfft
from scipy.ndimage import map_coordinates

from sensors import lidar as lidar_mod
from sensors import radar as radar_mod
from sensors import ray_kernels
from sensors.materials import RADAR_GAMMA, RADAR_SPECULAR
from sensors.raycast import WorldCaster
from sim.scenario import stream


def _bits_equal(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


# --- the numpy formulations before the kernels (commit 1d839f9) --------------------------------


def reference_target(tfar, prim, ng, n):
    """sensors.raycast._Target.cast's post-processing of Embree's outputs (None: empty scene)."""
    if prim is None:
        return np.full(n, np.inf), np.full(n, -1, np.int64), np.zeros((n, 3))
    prim = np.asarray(prim, np.int64)
    return np.where(prim >= 0, np.asarray(tfar, np.float64), np.inf), prim, np.asarray(ng, np.float64)


def reference_merge(static, dynamic, tables_s, tables_d, dirs, max_range):
    """sensors.raycast.WorldCaster.cast after the two Embree runs; also returns the cos of incidence
    that sensors.lidar / sensors.radar computed from the result."""
    n = len(dirs)
    r_s, p_s, n_s = reference_target(*static, n)
    r_d, p_d, n_d = reference_target(*dynamic, n)
    use_d = r_d < r_s
    rng = np.where(use_d, r_d, r_s)
    normal = np.where(use_d[:, None], n_d, n_s)
    material = np.zeros(n, np.uint8)
    instance = np.zeros(n, np.int32)
    hit_s = (~use_d) & (p_s >= 0)
    hit_d = use_d & (p_d >= 0)
    if hit_s.any():
        material[hit_s] = tables_s[0][p_s[hit_s]]
        instance[hit_s] = tables_s[1][p_s[hit_s]]
    if hit_d.any():
        material[hit_d] = tables_d[0][p_d[hit_d]]
        instance[hit_d] = tables_d[1][p_d[hit_d]]
    norm = np.linalg.norm(normal, axis=1, keepdims=True)
    normal = np.divide(normal, norm, out=np.zeros_like(normal), where=norm > 0)
    flip = np.einsum("ij,ij->i", normal, dirs) > 0
    normal[flip] *= -1
    far = rng > max_range
    rng[far] = np.inf
    material[far] = 0
    instance[far] = 0
    return rng, normal, material, instance, np.abs(np.einsum("ij,ij->i", normal, dirs))


def reference_range_grid(p, x, ok, n_fine, B):
    fine_az = np.tile(np.arange(n_fine), len(p) // n_fine)
    b0 = np.floor(x).astype(int)
    frac = x - b0
    grid = np.zeros(n_fine * B)
    for b, w in ((b0, 1 - frac), (b0 + 1, frac)):
        sel = ok & (b >= 0) & (b < B)
        grid += np.bincount(fine_az[sel] * B + b[sel], weights=p[sel] * w[sel], minlength=n_fine * B)
    return grid.reshape(n_fine, B).astype(np.float32)


def reference_coarse_signal(smeared, oversample, speckle):
    A = smeared.shape[0] // oversample
    coarse = np.clip(smeared, 0, None).reshape(A, oversample, -1).sum(axis=1)
    return (coarse * (speckle if speckle is not None else 1.0)).astype(np.float32)


def reference_scan(caster, calib, world_from_ego, actor_ids, rng, speckle=True):
    """sensors.radar.scan as it was."""
    OVERSAMPLE = radar_mod.OVERSAMPLE
    A, B, dr = calib.radar_azimuths, calib.radar_range_bins, calib.radar_range_resolution_m
    n_fine = A * OVERSAMPLE
    az = 2 * np.pi * (np.arange(n_fine) - (OVERSAMPLE - 1) / 2) / n_fine
    el = np.radians(radar_mod.ELEVATIONS_DEG)
    dirs = np.stack(np.broadcast_arrays(
        (np.cos(el)[:, None] * np.cos(az)[None, :]),
        (np.cos(el)[:, None] * np.sin(az)[None, :]),
        (np.sin(el)[:, None] * np.ones_like(az)[None, :]),
    ), -1)
    world_from_radar = world_from_ego @ calib.ego_from_radar
    d_world = dirs.reshape(-1, 3) @ world_from_radar[:3, :3].T
    hits = caster.cast(world_from_radar[:3, 3], d_world, max_range=B * dr)
    R = hits.range
    ok = np.isfinite(R) & (R > 1.0)
    cos_i = np.abs(np.einsum("ij,ij->i", hits.normal, d_world))
    theta = np.degrees(np.arccos(np.clip(cos_i, 0, 1)))
    m = hits.material
    d_el = np.gradient(el).repeat(n_fine)
    area = R**2 * (2 * np.pi / n_fine) * d_el
    sigma = area * (RADAR_GAMMA[m] + RADAR_SPECULAR[m] * np.exp(-((theta / radar_mod.SPECULAR_WIDTH_DEG) ** 2)))
    w_el = np.repeat(radar_mod.elevation_weights(), n_fine)
    with np.errstate(divide="ignore", invalid="ignore"):
        p = np.where(ok, radar_mod.RADAR_CONSTANT * w_el * sigma / R**4, 0.0)
    fine_az = np.tile(np.arange(n_fine), len(el))
    x = np.where(ok, R / dr - 0.5, 0.0)
    grid = reference_range_grid(p, x, ok, n_fine, B).astype(np.float64)
    ids = np.concatenate([[0], actor_ids])
    act = ok & (hits.instance > 0)
    coarse = fine_az // OVERSAMPLE
    instance = np.zeros((A, B), np.int64)
    if act.any():
        cell = coarse[act] * B + np.clip(np.round(x[act]).astype(int), 0, B - 1)
        order = np.lexsort((p[act], cell))
        last = np.r_[cell[order][1:] != cell[order][:-1], True]
        instance.reshape(-1)[cell[order][last]] = ids[hits.instance[act][order][last]]
    K = radar_mod._kernel_spectrum(n_fine)
    smeared = sfft.irfft(sfft.rfft(grid.astype(np.float32), axis=0) * K[:, None], n=n_fine, axis=0)
    smeared = np.clip(smeared, 0, None)
    coarse_signal = smeared.reshape(A, OVERSAMPLE, B).sum(axis=1)
    speckle_draw = rng.exponential(1.0, size=(A, B))
    noise = radar_mod.NOISE_POWER * rng.exponential(1.0, size=(A, B))
    return radar_mod.RadarObservation(
        signal=(coarse_signal * (speckle_draw if speckle else 1.0)).astype(np.float32),
        noise=noise.astype(np.float32), instance=instance, clutter=np.zeros((A, B), np.float32))


# --- merge_hits ----------------------------------------------------------------------------------


def _embree_like(rng, n, n_faces, hit_share):
    """Random Embree outputs: tfar, primID (-1 = miss), Ng with stale values on misses, as Embree
    leaves them; some zero and tiny normals."""
    prim = np.where(rng.random(n) < hit_share, rng.integers(0, n_faces, n), -1).astype(np.int32)
    tfar = rng.uniform(0.01, 150.0, n).astype(np.float32)
    tfar[prim < 0] = 1e37  # embreex's initial tfar
    ng = (rng.normal(size=(n, 3)) * np.exp(rng.normal(size=(n, 1)) * 3)).astype(np.float32)
    ng[rng.random(n) < 0.03] = 0.0
    ng[rng.random(n) < 0.03] = (0.0, -0.0, 1e-30)
    return tfar, prim, ng


def _tables(rng, n_faces):
    return rng.integers(0, 20, n_faces).astype(np.uint8), rng.integers(0, 9, n_faces).astype(np.int32)


def _check_merge(static, dynamic, tables_s, tables_d, dirs, max_range):
    n = len(dirs)
    empty = (np.zeros(0, np.float32), np.zeros(0, np.int32), np.zeros((0, 3), np.float32))
    got = ray_kernels.merge_hits(*(empty if static[1] is None else static), *(empty if dynamic[1] is None else dynamic),
                                 dirs, float(max_range), *tables_s, *tables_d)
    want = reference_merge(static, dynamic, tables_s, tables_d, dirs, max_range)
    assert len(got[0]) == n
    for g, w in zip(got, want):
        assert _bits_equal(g, w)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("n", [0, 1, 2, 3, 7, 2000])
def test_merge_hits_equals_numpy(seed, n):
    rng = np.random.default_rng(seed)
    tables_s, tables_d = _tables(rng, 50), _tables(rng, 30)
    static, dynamic = _embree_like(rng, n, 50, 0.7), _embree_like(rng, n, 30, 0.2)
    dynamic[0][: n // 4] = static[0][: n // 4]  # ties go to the static scene
    dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    for d in (dirs, dirs.astype(np.float32), np.broadcast_to(dirs[0] if n else np.ones(3), (n, 3))):
        for max_range in (np.inf, 100.0):
            _check_merge(static, dynamic, tables_s, tables_d, d, max_range)
            _check_merge(static, (None, None, None), tables_s, tables_d, d, max_range)
            _check_merge((None, None, None), dynamic, tables_s, tables_d, d, max_range)
            _check_merge((None, None, None), (None, None, None), tables_s, tables_d, d, max_range)


def test_cast_equals_numpy_on_a_rendered_frame(city):
    scene, renderer, obs = city
    caster: WorldCaster = renderer.caster
    calib = renderer.calib
    world_from_lidar = scene.ego.pose @ calib.ego_from_lidar
    dirs = renderer.lidar_dirs.reshape(-1, 3) @ world_from_lidar[:3, :3].T
    sun = np.broadcast_to(np.array([0.3, 0.2, 0.93]), (500, 3))
    pts = world_from_lidar[:3, 3] + np.random.default_rng(0).uniform(-30, 30, (500, 3)) * (1, 1, 0)
    # a lidar sweep, and shadow rays towards the sun (the camera's: one broadcast direction)
    for origins, d, max_range in ((world_from_lidar[:3, 3], dirs, 100.0), (pts, sun, 300.0)):
        d32 = np.ascontiguousarray(d, np.float32)
        o32 = np.ascontiguousarray(np.broadcast_to(origins, d32.shape), np.float32)
        runs = []
        for target in (caster.static, caster.dynamic):
            r = target.scene.run(o32, d32, output=1) if not target.empty else {}
            runs.append((r.get("tfar"), r.get("primID"), r.get("Ng")))
        want = reference_merge(runs[0], runs[1], (caster.static.face_material, caster.static.face_instance),
                               (caster.dynamic.face_material, caster.dynamic.face_instance), d, max_range)
        hits = caster.cast(origins, d, max_range=max_range)
        assert not caster.dynamic.empty and np.isfinite(hits.range).any()
        for g, w in zip((hits.range, hits.normal, hits.material, hits.instance, hits.cos_incidence), want):
            assert _bits_equal(g, w)


# --- radar ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_radar_range_grid_equals_bincount(seed):
    rng = np.random.default_rng(seed)
    n_fine, B, E = 40, 8, 24  # many rays per cell: the order of the additions shows
    n = n_fine * E
    R = rng.uniform(-2.0, 10.0, n)  # some below bin 0, some beyond the last bin
    R[rng.random(n) < 0.1] = np.inf
    R[::7] = np.round(R[::7])  # on bin edges
    ok = np.isfinite(R) & (R > 1.0)
    x = np.where(ok, R - 0.5, 0.0)
    p = np.where(ok, np.exp(rng.normal(size=n) * 8), 0.0)
    assert _bits_equal(ray_kernels.radar_range_grid(p, x, ok, n_fine, B), reference_range_grid(p, x, ok, n_fine, B))
    none = np.zeros(n, bool)
    assert _bits_equal(ray_kernels.radar_range_grid(p, x, none, n_fine, B), reference_range_grid(p, x, none, n_fine, B))


def test_radar_range_grid_adds_the_near_bins_before_the_far_bins():
    """A float64 sum that lands on a float32 rounding tie: bin 1 gets 1 and 2^-24 as near-bin weights
    and two 0.375-ulp far-bin weights. Near then far: 1 + 2^-24 + 0.75 ulp rounds up in float32; in
    ray order the small weights would be lost one by one and the tie round down to 1."""
    c = 0.75 * 2.0**-53
    x = np.array([1.0, 0.5, 1.0, 0.5])  # rays 0 and 2 in bin 1 exactly; rays 1 and 3 half in bins 0, 1
    p = np.array([1.0, 2 * c, 2.0**-24, 2 * c])
    ok = np.ones(4, bool)
    got = ray_kernels.radar_range_grid(p, x, ok, 1, 3)
    assert _bits_equal(got, reference_range_grid(p, x, ok, 1, 3))
    assert got[0, 1] == np.nextafter(np.float32(1.0), np.float32(2.0))


@pytest.mark.parametrize("seed", [0, 1])
def test_radar_coarse_signal_equals_numpy(seed):
    rng = np.random.default_rng(seed)
    smeared = (rng.normal(size=(64, 37)) * np.exp(rng.normal(size=(64, 37)) * 5)).astype(np.float32)
    smeared[::5, ::3] = -0.0
    smeared[1::9, ::4] = 0.0
    smeared[3, 5] = np.nan
    speckle = rng.exponential(1.0, size=(16, 37))
    assert _bits_equal(ray_kernels.radar_coarse_signal(smeared, 4, speckle), reference_coarse_signal(smeared, 4, speckle))
    assert _bits_equal(ray_kernels.radar_coarse_signal(smeared, 4, None), reference_coarse_signal(smeared, 4, None))


def test_radar_scan_equals_the_numpy_formulation(city, junction):
    for scene, renderer, _ in (city, junction):
        args = (renderer.caster, renderer.calib, scene.ego.pose, np.array(renderer._ids[1:], np.int64))
        for speckle in (True, False):
            got = radar_mod.scan(*args, stream(3, "radar", 0), speckle=speckle)
            want = reference_scan(*args, stream(3, "radar", 0), speckle=speckle)
            assert (got.instance > 0).any() and (got.signal > 0).mean() > 0.5
            for f in ("signal", "noise", "instance", "clutter"):
                assert _bits_equal(getattr(got, f), getattr(want, f)), f


# --- lidar ---------------------------------------------------------------------------------------


def reference_points(dirs, range_m, power, returned):
    """sensors.lidar.points as it was (without the extra returns)."""
    m = returned
    xyz = dirs[m] * range_m[m][:, None]
    inten = np.clip(power[m] / lidar_mod.P_SAT, 0, 1)
    ring = np.broadcast_to(np.arange(dirs.shape[0])[:, None], m.shape)[m]
    return np.column_stack([xyz, inten, ring]).astype(np.float32)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_lidar_points_equal_numpy(dtype, city):
    _, renderer, obs = city
    dirs = lidar_mod.beam_directions(renderer.calib)
    rng = np.random.default_rng(0)
    shape = dirs.shape[:2]
    range_m = rng.uniform(0.0, 120.0, shape).astype(dtype)
    power = (np.exp(rng.normal(size=shape) * 3) * lidar_mod.P_SAT).astype(dtype)  # some saturate
    power[:, ::50] = np.nan
    power[:, 1::50] = -0.0
    cases = [(range_m, power, rng.random(shape) < 0.6), (range_m, power, np.zeros(shape, bool)),
             (obs.lidar.range, obs.lidar.power, obs.lidar.returned)]
    for r, p, m in cases:
        got = ray_kernels.lidar_points(dirs, r, p, m, p.dtype.type(lidar_mod.P_SAT))
        assert _bits_equal(got, reference_points(dirs, r, p, m))
    assert _bits_equal(lidar_mod.points(obs.lidar, renderer.calib), reference_points(dirs, *cases[-1]))


@pytest.mark.parametrize("shape", [(400, 288), (7, 5), (1, 2), (2, 1), (1, 1)])
def test_polar_to_cartesian_equals_map_coordinates(shape):
    rng = np.random.default_rng(shape[0] * 10 + shape[1])
    A, B = shape
    polar = (rng.random(shape) * 255).astype(np.float32)
    polar[rng.random(shape) < 0.3] = 100.0  # flat patches, like the counts of an empty scene
    n = 3000
    rows = rng.uniform(-1.5, A + 1.5, n)
    cols = rng.uniform(-1.5, B + 1.5, n)
    rows[:40] = np.arange(40) % (A + 2)  # exact sample positions, the last row, beyond it
    cols[40:80] = np.arange(40) % (B + 1) - 0.0
    cols[80] = -0.0
    outside = rng.random(n) < 0.2
    want = map_coordinates(np.vstack([polar, polar[:1]]), np.vstack([rows, cols]), order=1, mode="nearest")
    want[outside] = 0
    assert _bits_equal(ray_kernels.polar_to_cartesian(polar, rows, cols, outside), want)


def test_radar_cartesian_equals_map_coordinates(city):
    _, renderer, obs = city
    polar = radar_mod.to_counts(obs.radar.power).astype(np.float32)
    got = radar_mod.cartesian(polar, renderer.calib)
    coords, shape, outside = radar_mod._CART_CACHE[(polar.shape, renderer.calib.bev_size_px, renderer.calib.bev_resolution_m,
                                                    renderer.calib.radar_range_resolution_m)]
    want = map_coordinates(np.vstack([polar, polar[:1]]), coords, order=1, mode="nearest")
    want[outside] = 0
    assert _bits_equal(got, want.reshape(shape)) and got.max() > 0
