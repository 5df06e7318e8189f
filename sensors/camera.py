"""Stereo camera: pyrender (EGL) visibility pass + physically based deferred shading.

Rendering is split in two:
1. pyrender draws the world once per camera with flat colours that encode, per pixel, the
   instance index (16 bits in R, G) and the material id (B), and returns the depth. Multisampling
   is switched off for this pass so the codes are exact (pyrender only does that for SEG passes).
2. numpy shades every pixel in physical units: radiance L = albedo / pi * E + L_emissive [cd/m^2],
   with E the illuminance [lx] from the sky (isotropic hemisphere), the sun (Embree shadow rays),
   street lamps and headlights (inverse-square with beam patterns), so night scenes can have any
   number of lights. Emissive lamp heads and lights glow when switched on.

The observation keeps the HDR radiance, depth, instance and material maps: weather degradations act
on radiance with the true depth (Koschmieder) before the camera model (auto-exposure with a
maximum exposure, lens blur, sRGB encoding) turns it into an 8-bit image.
"""

from __future__ import annotations

import os
import sys

os.environ["PYOPENGL_PLATFORM"] = os.environ.get("PYOPENGL_PLATFORM", "egl") or "egl"
# Mesa's llvmpipe (EGL) and triton (pulled in by torch/torchvision) each load their own LLVM; when
# triton is imported after llvmpipe is up, the process segfaults. triton is only for GPU kernels,
# which hydrabench never uses: if it is not loaded yet, mark it unavailable for this process.
if "triton" not in sys.modules:
    sys.modules["triton"] = None  # type: ignore[assignment]

import contextlib  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from functools import lru_cache  # noqa: E402

import numpy as np  # noqa: E402
import pyrender  # noqa: E402
import pyrender.renderer as _pr  # noqa: E402
from OpenGL import GL  # noqa: E402

from sensors.materials import ALBEDO, EMISSIVE, MATERIAL_ID, MATERIALS, PER_INSTANCE, instance_colour  # noqa: E402
from sensors.rig import CameraCalibration, transform_points  # noqa: E402
from sensors.world_mesh import MeshSoup  # noqa: E402

OPTICAL_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV optical frame -> OpenGL camera frame
Z_NEAR, Z_FAR = 0.3, 400.0  # [m]

# Light sources (photometric, typical values)
SUN_COLOUR = np.array([1.0, 0.96, 0.88], np.float32)
SKY_COLOUR = np.array([0.80, 0.90, 1.10], np.float32)
LAMP_COLOUR = np.array([1.0, 0.86, 0.62], np.float32)  # warm-white / high-pressure sodium look
HEADLIGHT_COLOUR = np.array([1.0, 1.0, 0.95], np.float32)
LAMP_INTENSITY_CD = 2500.0  # peak luminous intensity of an ~8 klm urban street lantern [cd]
HEADLIGHT_INTENSITY_CD = 20000.0  # peak of a dipped (low) beam [cd] (UN R112 ~ 10-30 kcd)
HEADLIGHT_H_WIDTH_DEG, HEADLIGHT_V_WIDTH_DEG = 12.0, 5.0  # Gaussian widths of that beam [deg]
GROUND_ALBEDO = 0.12  # for the light reflected up from the ground
LIGHT_RANGE_M = 70.0  # lights farther than this from the camera are ignored
EXPOSURE_KEY = 0.18  # mid-grey target of the auto-exposure (Reinhard's key)
MAX_EXPOSURE = 0.01  # [1/(cd/m^2)]: longest exposure x base gain (~150x the daylight exposure)
MIN_EXPOSURE = 1e-6
PSF_SIGMA_PX = 0.5  # lens blur (also hides the aliasing of the single-sample pass)


@contextlib.contextmanager
def _no_multisample():
    """pyrender enables GL_MULTISAMPLE for every non-SEG pass; keep it off so codes stay exact."""
    original = _pr.glEnable

    def enable(cap):
        if cap == GL.GL_MULTISAMPLE:
            GL.glDisable(cap)
            return
        original(cap)

    _pr.glEnable = enable
    try:
        yield
    finally:
        _pr.glEnable = original


@contextlib.contextmanager
def _draw_order(renderer: pyrender.OffscreenRenderer, nodes: list):
    """Draw the mesh nodes in this order. pyrender sorts opaque nodes by their distance to the
    camera and keeps the order of a Python set among equal distances (our static and actor meshes
    both sit at the origin), so which mesh won an exact depth tie (GL_LESS: the first drawn) changed
    from process to process with the objects' addresses: the world first, then the actors."""
    inner = renderer._renderer
    inner._sorted_mesh_nodes = lambda scene: nodes
    try:
        yield
    finally:
        del inner._sorted_mesh_nodes


def _code_colours(soup: MeshSoup) -> np.ndarray:
    inst = soup.instance.astype(np.int64)
    col = np.empty((len(inst), 4), np.uint8)
    col[:, 0] = inst & 255
    col[:, 1] = (inst >> 8) & 255
    col[:, 2] = soup.material
    col[:, 3] = 255
    return col


def _pyrender_mesh(soup: MeshSoup) -> pyrender.Mesh:
    material = pyrender.MetallicRoughnessMaterial(baseColorFactor=[1.0, 1.0, 1.0, 1.0], doubleSided=True)
    prim = pyrender.Primitive(
        positions=soup.vertices.astype(np.float32),
        indices=soup.faces.astype(np.uint32),
        color_0=_code_colours(soup),
        material=material,
        mode=pyrender.constants.GLTF.TRIANGLES,
    )
    return pyrender.Mesh([prim])


def _single_sample(renderer: pyrender.OffscreenRenderer) -> None:
    """Draw the code pass straight into pyrender's single-sample framebuffer and read it back there.

    pyrender draws into a 4-sample framebuffer and resolves it into a single-sample one with two
    blits before reading. With multisampling off (`_no_multisample`) every sample of a pixel is
    covered alike, so the resolve only copies; on llvmpipe the blits and the four-fold clear and
    fill were about a third of the pass. The codes are the same; the depth differs by the depth
    buffer's rounding (< 2e-4 relative): tests/sensors/test_camera_pass.py renders both ways.
    Sensor model 4 and later use this pass."""
    inner = renderer._renderer
    cls = type(inner)

    def configure() -> None:
        cls._configure_main_framebuffer(inner)
        inner._main_fb_ms = inner._main_fb  # the forward pass binds this one for drawing

    def read(scene, flags):
        width, height = inner._main_fb_dims
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, inner._main_fb)
        depth = np.frombuffer(GL.glReadPixels(0, 0, width, height, GL.GL_DEPTH_COMPONENT, GL.GL_FLOAT),
                              np.float32).reshape(height, width)[::-1]
        colour = np.frombuffer(GL.glReadPixels(0, 0, width, height, GL.GL_RGBA, GL.GL_UNSIGNED_BYTE),
                               np.uint8).reshape(height, width, 4)[::-1]
        return colour, linear_depth(depth, scene.main_camera_node.camera.znear, scene.main_camera_node.camera.zfar)

    inner._configure_main_framebuffer = configure
    inner._read_main_framebuffer = read


def linear_depth(buffer: np.ndarray, znear: float, zfar: float) -> np.ndarray:
    """Metric depth [m] from OpenGL depth-buffer values (0..1, 1 = nothing drawn -> 0), in float32
    as pyrender computes it: z_ndc = 2 d - 1, depth = 2 n f / (f + n - z_ndc (f - n))
    (`sensors.kernels.linear_depth`, the same bits as pyrender's numpy)."""
    from sensors.kernels import linear_depth as kernel

    return kernel(buffer, float(znear), float(zfar))


_RENDERERS: dict[tuple[int, int], pyrender.OffscreenRenderer] = {}


def _renderer(width: int, height: int) -> pyrender.OffscreenRenderer:
    key = (width, height)
    if key not in _RENDERERS:
        _RENDERERS[key] = pyrender.OffscreenRenderer(width, height)
        _single_sample(_RENDERERS[key])
    return _RENDERERS[key]


def gl_info() -> dict:
    """The OpenGL renderer that draws the code pass (e.g. "llvmpipe (LLVM 15.0.6, 256 bits)") and
    its version string (with Mesa's version), from a renderer's context."""
    r = _renderer(16, 16)
    r._platform.make_current()
    return {k: GL.glGetString(getattr(GL, f"GL_{k.upper()}")).decode(errors="replace") for k in ("renderer", "version")}


@dataclass
class CameraObservation:
    """What one camera sees of a frame, before the camera model.

    Fields:
        radiance: (H, W, 3) float32 scene radiance reaching the lens [cd/m^2] (linear RGB).
        depth: (H, W) float32 depth along the optical axis [m]; inf where the ray sees the sky.
        instance: (H, W) int64 simulator actor id of the surface (0 = static world / sky).
        material: (H, W) uint8 material id (sensors.materials; 0 = sky).
        sky_radiance: (3,) float32 radiance of the horizon sky [cd/m^2] (the airlight of fog).
        exposure: the auto-exposure the camera model chose [1/(cd/m^2)] (filled by `expose`).
        sensor_noise: low-light sensor parameters (full_well_e, read_noise_e, max_gain, seed) set by
            the low-light degradation; None = noise-free camera model.
        gain: analogue gain the camera model applied (filled by `expose`).
    """

    radiance: np.ndarray
    depth: np.ndarray
    instance: np.ndarray
    material: np.ndarray
    sky_radiance: np.ndarray
    exposure: float = 0.0
    sensor_noise: dict | None = None
    gain: float = 1.0


class StereoRenderer:
    """Renders both cameras of a sequence: the static mesh is uploaded once, actors per frame."""

    def __init__(self, static: MeshSoup, width: int, height: int) -> None:
        self.width, self.height = width, height
        self.scene = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 0.0], ambient_light=[1.0, 1.0, 1.0])
        self.static_node = self.scene.add(_pyrender_mesh(static)) if len(static.faces) else None
        self.dynamic_node = None
        self.cam_node = None

    def set_actors(self, soup: MeshSoup) -> None:
        if self.dynamic_node is not None:
            self.scene.remove_node(self.dynamic_node)
            self.dynamic_node = None
        if len(soup.faces):
            self.dynamic_node = self.scene.add(_pyrender_mesh(soup))

    def codes(self, cam: CameraCalibration, world_from_ego: np.ndarray):
        """(instance index (H,W) int64, material (H,W) uint8, depth (H,W) float32 [m], inf = sky)."""
        K = cam.K
        camera = pyrender.IntrinsicsCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], znear=Z_NEAR, zfar=Z_FAR)
        pose = world_from_ego @ cam.ego_from_camera @ OPTICAL_TO_GL
        if self.cam_node is not None:
            self.scene.remove_node(self.cam_node)
        self.cam_node = self.scene.add(camera, pose=pose)
        r = _renderer(cam.width, cam.height)
        nodes = [n for n in (self.static_node, self.dynamic_node) if n is not None]
        with _no_multisample(), _draw_order(r, nodes):
            colour, depth = r.render(self.scene, flags=pyrender.RenderFlags.FLAT | pyrender.RenderFlags.RGBA)
        from sensors.kernels import decode_codes

        return decode_codes(np.ascontiguousarray(colour), np.ascontiguousarray(depth, np.float32))


# ---------------------------------------------------------------------------------------------
# shading


_RAYS: dict = {}


def pixel_rays(cam: CameraCalibration) -> np.ndarray:
    key = (cam.width, cam.height, cam.K.tobytes())
    if key not in _RAYS:
        _RAYS[key] = cam.rays().astype(np.float32)
    return _RAYS[key]


_RAYS_PER_Z: dict = {}


def _rays_per_z(cam: CameraCalibration) -> np.ndarray:
    """The unit rays scaled to z = 1 (float32, as `rays / rays[..., 2:3]`): the point at depth z is z times this."""
    key = (cam.width, cam.height, cam.K.tobytes())
    if key not in _RAYS_PER_Z:
        rays = pixel_rays(cam)
        _RAYS_PER_Z[key] = rays / rays[..., 2:3]
    return _RAYS_PER_Z[key]


def _normals_from_points(P: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Per-pixel surface normals (H, W, 3) from a point map, using the neighbour on the side with
    the smaller depth jump so object edges do not bleed."""

    def diff(axis: int) -> np.ndarray:
        fwd = np.roll(P, -1, axis) - P
        bwd = P - np.roll(P, 1, axis)
        dz_f = np.abs(np.roll(depth, -1, axis) - depth)
        dz_b = np.abs(depth - np.roll(depth, 1, axis))
        use_f = (dz_f <= dz_b) | ~np.isfinite(dz_b)
        return np.where(use_f[..., None], fwd, bwd)

    a, b = diff(1), diff(0)
    n = np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                  a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                  a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], -1)
    norm = np.sqrt(np.einsum("hwc,hwc->hw", n, n))[..., None]
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 1e-12)


# materials whose normals snap to +z where nearly vertical (flat ground)
_SNAP_MATERIAL = np.isin(np.arange(len(MATERIALS)), [MATERIAL_ID[m] for m in ("asphalt", "lane_paint", "grass", "sidewalk")])


@dataclass
class Lighting:
    """Illumination of a frame in photometric units.

    sun_dir: (3,) unit vector towards the sun (world); sun_normal_lux: direct normal illuminance [lx];
    sky_lux: diffuse horizontal illuminance from the sky [lx]; lamps: (N, 3) lamp head positions;
    headlights: list of (position (3,), axis (3,)) for every lit headlight [m].
    """

    sun_dir: np.ndarray
    sun_normal_lux: float
    sky_lux: float
    lamps: np.ndarray
    headlights: list
    lamps_on: bool
    headlights_on: bool


_NO_COLOURS = np.zeros((1, len(ALBEDO), 3), np.float32)  # no pixel needs a per-actor colour


@lru_cache(maxsize=32)
def _colour_table(actor_ids: tuple) -> np.ndarray:
    """(1 + n_ids, n_materials, 3) albedo of per-instance materials (paint, clothing) by index."""
    mats = np.flatnonzero(PER_INSTANCE)
    table = np.zeros((len(actor_ids) + 1, len(ALBEDO), 3), np.float32)
    for i, aid in enumerate(actor_ids, start=1):
        for m in mats:
            table[i, m] = instance_colour(aid, int(m))
    return table


def lighting_for(weather, light, lamp_positions: np.ndarray, headlights: list) -> Lighting:
    elev = np.radians(light.sun_elevation_deg)
    az = np.radians(light.sun_azimuth_deg)
    sun_dir = np.array([np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)])
    direct_share = 0.0 if (weather.sky_overcast or elev <= np.radians(2)) else 0.75
    E = weather.illuminance_lux
    sun_normal = E * direct_share / max(np.sin(elev), 0.05) if direct_share else 0.0
    return Lighting(sun_dir, float(sun_normal), float(E * (1 - direct_share)), lamp_positions, headlights,
                    light.street_lamps_on, light.headlights_on)


def shade(
    index: np.ndarray,
    material: np.ndarray,
    depth: np.ndarray,
    cam: CameraCalibration,
    world_from_ego: np.ndarray,
    actor_ids: np.ndarray,
    lighting: Lighting,
    caster=None,
) -> CameraObservation:
    """Radiance of every pixel [cd/m^2] from the visibility pass and the frame's lighting.

    The per-pixel loops run in `sensors.kernels` (bit-identical to the numpy formulation kept in
    `_normals_from_points` and tests/sensors/test_kernels.py); BLAS products, Embree shadow rays
    and the light sources' beam patterns (exp, pow, atan2) stay in numpy.
    """
    from sensors import kernels

    H, W = depth.shape
    geo = np.isfinite(depth)
    rays = pixel_rays(cam)  # unit, optical frame
    z = np.where(geo, depth, 0.0)[..., None]
    P_cam = _rays_per_z(cam) * z
    world_from_cam = (world_from_ego @ cam.ego_from_camera).astype(np.float32)
    P = P_cam @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]
    cam_pos = world_from_cam[:3, 3]
    # normals from the point map, facing the camera, ground snapped flat
    n = kernels.surface_normals(P, np.where(geo, depth, np.float32(1e6)), np.ascontiguousarray(cam_pos),
                                _SNAP_MATERIAL, material)

    # albedo: per-actor paint / clothing colours where the material has them (in `kernels.radiance`)
    table = _NO_COLOURS
    if np.any(PER_INSTANCE[material] & (index > 0)):
        table = _colour_table(tuple(int(i) for i in actor_ids))

    # sky hemisphere seen by the surface + light bounced off the ground, both sky-coloured; the sun
    with_sun = lighting.sun_normal_lux > 0
    lit = geo
    cos_s = np.zeros((0, 0))
    if with_sun:
        cos_s = kernels.sun_cosine(n, np.asarray(lighting.sun_dir, np.float64))
        lit = geo & (cos_s > 0)
        if caster is not None and lit.any():
            # shadow rays towards the sun on a 2x2-subsampled grid, spread to each 2x2 block (the
            # lens blur is 0.5 px; shadow edges move by at most a pixel)
            sub = np.zeros_like(lit)
            sub[::2, ::2] = lit[::2, ::2]
            pts = P[sub] + n[sub] * 0.05
            hits = caster.cast(pts, np.broadcast_to(lighting.sun_dir, pts.shape), max_range=300.0)
            shadow_sub = np.zeros(lit[::2, ::2].shape, bool)
            shadow_sub[lit[::2, ::2]] = np.isfinite(hits.range)
            shadow = np.repeat(np.repeat(shadow_sub, 2, 0), 2, 1)[:H, :W]
            lit &= ~shadow
    E = kernels.sky_and_sun(n[..., 2], lighting.sky_lux, GROUND_ALBEDO, SKY_COLOUR, lit, cos_s,
                            lighting.sun_normal_lux, SUN_COLOUR, with_sun)
    artificial = (lighting.lamps_on and len(lighting.lamps)) or lighting.headlights_on
    if artificial:
        lamps = np.zeros((0, 3))
        if lighting.lamps_on and len(lighting.lamps):
            lamps = lighting.lamps[np.linalg.norm(lighting.lamps - cam_pos, axis=1) < LIGHT_RANGE_M]
        heads = [(pos, axis) for pos, axis in (lighting.headlights if lighting.headlights_on else [])
                 if np.linalg.norm(pos - cam_pos) <= LIGHT_RANGE_M]
        kernels.artificial_light(
            P, n, geo, E, np.ascontiguousarray(lamps, np.float64), LAMP_INTENSITY_CD, LAMP_COLOUR,
            np.array([p for p, _ in heads], np.float64).reshape(-1, 3),
            np.array([a for _, a in heads], np.float64).reshape(-1, 3), HEADLIGHT_INTENSITY_CD,
            HEADLIGHT_COLOUR, HEADLIGHT_H_WIDTH_DEG, HEADLIGHT_V_WIDTH_DEG)  # E += the lights

    # emissive surfaces that are switched on
    emissive_on = np.zeros(len(MATERIALS), bool)
    for m in MATERIALS:
        if m.emits_when and ((m.emits_when == "lamps" and lighting.lamps_on) or
                             (m.emits_when == "headlights" and lighting.headlights_on)):
            emissive_on[MATERIAL_ID[m.name]] = True

    # sky: brighter towards the horizon; its horizon value is the airlight used by fog
    sky_h = (lighting.sky_lux + 0.2 * lighting.sun_normal_lux * max(lighting.sun_dir[2], 0)) / np.pi
    sky_h = max(sky_h, 1e-4)
    if not geo.all():
        ray_w = rays[~geo] @ world_from_cam[:3, :3].T
        elev = np.ascontiguousarray(np.clip(ray_w[:, 2], 0, 1))
    else:
        elev = np.zeros(0, np.float32)
    # a numpy float64 sky_h keeps the gradient in float64, a Python float does not (NEP 50)
    L = kernels.radiance(index, material, ALBEDO, PER_INSTANCE, table, E, emissive_on, EMISSIVE, geo, elev,
                         float(sky_h), isinstance(sky_h, np.floating), SKY_COLOUR)
    instance = kernels.instance_ids(index, np.asarray(actor_ids, np.int64))
    return CameraObservation(L, depth, instance, material, (sky_h * SKY_COLOUR).astype(np.float32))


# ---------------------------------------------------------------------------------------------
# camera model


def _gaussian_weights(sigma: float, truncate: float = 4.0) -> np.ndarray:
    """The 1-D kernel of scipy.ndimage.gaussian_filter (radius round(truncate sigma), normalised)."""
    radius = int(truncate * sigma + 0.5)
    x = np.arange(-radius, radius + 1)
    phi = np.exp(-0.5 / (sigma * sigma) * x ** 2)
    return phi / phi.sum()


_PSF_WEIGHTS = _gaussian_weights(PSF_SIGMA_PX)
assert len(_PSF_WEIGHTS) == 5  # sensors.kernels.gaussian_blur5_hw


def lens_blur(radiance: np.ndarray) -> np.ndarray:
    """The lens PSF: scipy.ndimage.gaussian_filter(radiance, sigma=(PSF_SIGMA_PX, PSF_SIGMA_PX, 0)),
    same bits, in one compiled kernel (sensors.kernels.gaussian_blur5_hw)."""
    from sensors.kernels import gaussian_blur5_hw

    return gaussian_blur5_hw(radiance, _PSF_WEIGHTS)


def wanted_exposure(radiance: np.ndarray) -> float:
    """Exposure k that maps the log-average luminance to mid-grey (Reinhard's key) [1/(cd/m^2)]."""
    lum = radiance @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    log_avg = float(np.exp(np.mean(np.log(lum + 1e-4))))
    return EXPOSURE_KEY / max(log_avg, 1e-9)


def auto_exposure(radiance: np.ndarray) -> float:
    """The wanted exposure within the camera's limits (longest exposure x base gain)."""
    return float(np.clip(wanted_exposure(radiance), MIN_EXPOSURE, MAX_EXPOSURE))


def srgb_encode(x: np.ndarray) -> np.ndarray:
    """sRGB transfer function (IEC 61966-2-1) of linear values, clipped to 0..1."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


_SRGB_LUT = srgb_encode(np.linspace(0.0, 1.0, 65536)).astype(np.float32)


def srgb_encode_fast(x: np.ndarray) -> np.ndarray:
    """srgb_encode through a 65,536-entry table (error < 0.2 / 255 everywhere)."""
    if x.dtype == np.float32:
        from sensors.kernels import srgb_lookup

        return srgb_lookup(np.ascontiguousarray(x), _SRGB_LUT)
    idx = (np.clip(x, 0.0, 1.0) * 65535.0 + 0.5).astype(np.int32)
    return _SRGB_LUT[idx]


def shot_and_read_noise(rng: np.random.Generator, electrons: np.ndarray, read_noise_e: float) -> np.ndarray:
    """Poisson photon noise plus Gaussian read noise [e-]. Counts of 30 e- and more use the normal
    approximation N(lambda, sqrt(lambda)) of the Poisson law (exact Poisson below)."""
    from sensors.kernels import shot_and_read_noise_apply

    e = np.ascontiguousarray(electrons).reshape(-1)
    low = e < 30.0
    n_low = int(np.count_nonzero(low))
    # the draws in the order they always had: Poisson (low counts), normal (high), read noise
    poisson = rng.poisson(e[low]) if n_low else np.zeros(0, np.int64)
    normal_hi = rng.standard_normal(len(e) - n_low, dtype=np.float32)
    normal_read = rng.standard_normal(len(e), dtype=np.float32)
    out = shot_and_read_noise_apply(e, low, poisson.astype(np.int64, copy=False), normal_hi, normal_read,
                                    float(read_noise_e))
    return out.reshape(electrons.shape)


def expose(obs: CameraObservation, exposure: float | None = None) -> np.ndarray:
    """Camera model: lens blur, exposure, (low light: gain and Poisson-Gaussian noise), clipping,
    sRGB -> (H, W, 3) float in 0..1."""
    wanted = None
    if exposure is None:
        wanted = wanted_exposure(obs.radiance)
        k = float(np.clip(wanted, MIN_EXPOSURE, MAX_EXPOSURE))  # auto_exposure
    else:
        k = exposure
    obs.exposure = k
    blurred = lens_blur(obs.radiance)
    p = obs.sensor_noise
    if not p:
        return srgb_encode_fast(blurred * k)  # k: fraction of the full well per cd/m^2
    wanted = wanted_exposure(obs.radiance) if wanted is None else wanted
    gain = float(np.clip(wanted / k, 1.0, p["max_gain"]))
    obs.gain = gain
    rng = np.random.default_rng(p["seed"])
    full_well = p["full_well_e"]
    if blurred.dtype == np.float32 and type(k) is float and type(full_well) is float:
        # the arithmetic below in float32, fused (sensors.kernels, the same bits)
        from sensors import kernels

        noisy = shot_and_read_noise(rng, kernels.exposed_electrons(blurred, k, full_well), p["read_noise_e"])
        return kernels.noisy_srgb(noisy, full_well, gain, _SRGB_LUT)
    electrons = np.clip(blurred * k, 0, 1) * full_well
    return srgb_encode_fast(shot_and_read_noise(rng, electrons, p["read_noise_e"]) / full_well * gain)


def to_uint8(img01: np.ndarray) -> np.ndarray:
    if img01.dtype == np.float32:
        from sensors.kernels import to_uint8 as kernel

        return kernel(np.ascontiguousarray(img01))
    return np.round(np.clip(img01, 0, 1) * 255).astype(np.uint8)


def headlights_of(actors, ego_pose: np.ndarray, ego_size: np.ndarray) -> list:
    """(position, axis) of both headlights of every motor vehicle and of the ego (world frame)."""
    out = []
    names = actors.class_names()
    for c, size, yaw, cls, parked in zip(actors.centers, actors.sizes, actors.yaws, names, actors.parked):
        if parked or cls in ("pedestrian", "group_of_pedestrians", "bicycle"):
            continue
        axis = np.array([np.cos(yaw), np.sin(yaw), -0.02])
        axis /= np.linalg.norm(axis)
        left = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
        front = c[:2] + axis[:2] * size[0] / 2
        for s in ((-1, 1) if cls != "motorbike" else (0,)):
            out.append((np.array([*(front + left[:2] * s * size[1] * 0.35), 0.75]), axis))
    yaw = np.arctan2(ego_pose[1, 0], ego_pose[0, 0])
    axis = np.array([np.cos(yaw), np.sin(yaw), -0.02])
    axis /= np.linalg.norm(axis)
    for s in (-1, 1):
        p = transform_points(ego_pose, np.array([[ego_size[0] / 2, s * ego_size[1] * 0.35, 0.75]]))[0]
        out.append((p, axis))
    return out
