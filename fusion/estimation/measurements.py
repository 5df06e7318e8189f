"""Object-level position measurements extracted from the degraded sensor data of a frame.

The state of every object is its *reference point* in the ground plane of the ego frame (x forward,
y left, metres): the point where the line of sight from the ego origin (under the radar) to the
centre of the object's box footprint enters the footprint. It is the near-surface point on the
object's centre line: what all three sensors physically measure (a camera's disparity, a lidar's
ranges and a radar's echo all come from the surface facing the sensor), so no shape prior is needed
to compare them, and it is computed exactly from the box (`reference_points`).

Each extractor gets the object's region from the *clean* instance maps (a stand-in for a detector's
box or cluster: which pixels, rays or cells belong to the object) and measures only from the
*degraded* data of the frame; the region bounds where to look, the degraded data say where the object
is:

- camera: stereo block matching of the lower `CAMERA_BAND` of the object's pixels (the surface
  facing the camera; higher rows show roofs and rear windows farther back) between the exposed 8-bit
  left and right images: zero-mean NCC over integer disparities, then Gauss-Newton sub-pixel
  refinement with gain and offset; depth Z = f b / d; bearing from the object's left and right edges
  found in the left image within +-2 px of the region's boundary. Rejected when the match is not
  confident: NCC below `CAMERA_MIN_NCC`, predicted disparity precision worse than
  `CAMERA_MAX_PRED_SIGMA_PX`, too few pixels, a disparity below `CAMERA_MIN_DISPARITY_PX` (27 m) or
  no usable edges.
- lidar: the degraded returns on the rays that would hit the object (fog, rain and snow returns on
  those rays are included, as a clustering would include them): bearing = mean bearing of the
  returns, range = the `LIDAR_RANGE_QUANTILE` quantile of the horizontal ranges of the returns in
  the central third of the bearings (the surface facing the sensor; the plain centroid of a car's
  returns sits ~1 m behind it, on the roof and the side).
- radar: the peak of the degraded polar power (signal + clutter + noise) in a window of +-2 azimuth
  bins and +-3 range bins around the object's cells, refined by a parabola through the log power of
  the neighbouring bins, converted to x/y with the calibration's convention (row a at a * 360 / A
  deg), moved toward the radar by the expected depth of the echo behind the facing surface
  (`echo_depth`).

Each measurement carries a *nominal* R from the sensor's spec (`camera_R`, `lidar_R`, `radar_R`) plus
a surface term from the class's mean box (`surface_R`): the covariance a fusion would assume without
knowing the weather. Two constants were set on clear-weather data, as a sensor is commissioned in
good weather: the stereo confidence threshold and the obliquity term's form (see `surface_R`).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from sensors import lidar as lidar_mod
from sensors.rig import RADAR_BEAMWIDTH_DEG, Calibration, invert, transform_points
from sim.actors import CLASS_SIZE, CLASSES

SENSORS = ("camera", "lidar", "radar")
# Bump when an extractor, the nominal R or the evaluation set changes: cached measurements made by
# another version are measured again.
EXTRACTOR_VERSION = 6  # 5, 6: each measurement records where its data came from (source, purity)

# --- evaluation set --------------------------------------------------------------------------
MIN_RANGE_M, MAX_RANGE_M = 5.0, 60.0  # reference-point distance from the ego origin [m]
MAX_OCCLUSION = 0.5  # share of the object hidden in the left camera (sensors.labels)
MAX_TRUNCATION = 0.2  # share of the projected box outside the left image

# --- camera ------------------------------------------------------------------------------------
CAMERA_SIGMA_D_PX = 0.25  # nominal disparity std [px]: quarter-pixel sub-pixel matching
CAMERA_SIGMA_U_PX = 0.5  # nominal std of the region's column centre [px]
CAMERA_MIN_PIXELS = 30  # matched pixels after erosion: smaller regions match anything
# Confidence threshold of a match, set in clear weather. Sensor noise is independent in the two
# cameras, so even a perfect match of a weakly textured region has NCC < 1. With sensor model 2
# (shot and read noise at every light level) on the motorway (seeds 0 and 1, 20 frames each) the
# matches with NCC 0.85-0.9 had mean NEES 1.0 (10), 0.9-0.95 1.1 (7), above 0.95 2.2 (11), 0.5-0.8
# 2.3 and 0.3 (2); none exceeded the 99.9 % chi2(2) bound. (Sensor model 1, noiseless in daylight:
# the two matches at 0.85-0.9 had NEES 22, hence the earlier 0.9.)
CAMERA_MIN_NCC = 0.8
CAMERA_MAX_PRED_SIGMA_PX = 0.25
CAMERA_MIN_DISPARITY_PX = 0.75  # smaller disparities are rejected: Z > f b / 0.75 = 27 m (cpu profile)
CAMERA_EDGE_SEARCH_PX = 2  # edges are searched this far around the region's boundary [px]
CAMERA_MIN_EDGE = 3.0 / 255.0  # weakest usable edge step (three 8-bit levels)
CAMERA_BAND = 0.6  # share of the region's rows, from the bottom, that are matched

# --- lidar -------------------------------------------------------------------------------------
SURFACE_RELIEF_M = 0.1  # depth relief of an object's facing surface (bumpers, lamps, mirrors) [m]
LIDAR_SIGMA_RANGE_M = 0.02  # HDL-32E range accuracy (datasheet: < 2 cm)
LIDAR_DIVERGENCE_RAD = 2.79e-3  # HDL-32E beam divergence (datasheet: ~2.8 mrad)
LIDAR_RANGE_QUANTILE = 0.25
LIDAR_MIN_POINTS = 3

# --- radar -------------------------------------------------------------------------------------
RADAR_WINDOW_AZ, RADAR_WINDOW_RANGE = 2, 3  # search window half-widths [bins]
RADAR_MIN_SNR_DB = 6.0

# --- where a measurement's data came from (MeasurementSet.source) --------------------------------
# A positive value is the simulator id of the actor whose surface gave the data (the measured
# object's own id, or another actor's: a wrong association).
SOURCE_NONE = -1  # the sensor gave no measurement
SOURCE_WORLD = 0  # the static world or the sky (guard rails, buildings; background pixels)
SOURCE_WEATHER = -2  # returns from the air: fog backscatter, rain drops, snow flakes; radar clutter
SOURCE_NOISE = -3  # radar receiver noise


@dataclass(frozen=True)
class MeasurementSet:
    """Object-level measurements of many frames, one row per (frame, object); columnar.

    Sensor axis k follows SENSORS = ("camera", "lidar", "radar"). Positions are in the ego frame of
    the row's frame (x forward, y left, ground plane) [m].

    Fields:
        sequence: (N,) int64 index of the sequence the row comes from (for cross-validation folds).
        frame: (N,) int64 frame index within its sequence.
        actor_ids: (N,) int64 simulator ids. classes: (N,) int64 class ids 1..8.
        truth: (N, 2) reference point [m] (`reference_points`).
        z: (N, 3, 2) measured reference point per sensor [m], NaN where the sensor gave none.
        R: (N, 3, 2, 2) nominal covariance of z [m^2], NaN where z is NaN.
        quality: (N, 3) each extractor's own figure: camera NCC, lidar return count, radar peak SNR [dB].
        source: (N, 3) int64 where each measurement's data came from, read from the simulator's
            ground truth (clean instance maps, the degraded data's own bookkeeping of weather returns
            and clutter): an actor id (the object's own, or another's), or SOURCE_WORLD,
            SOURCE_WEATHER, SOURCE_NOISE; SOURCE_NONE where the sensor gave nothing. Camera: the
            actor most of the matched pixels land on in the clean right image; lidar: what the return
            that set the range hit; radar: the largest of the peak cell's signal (its actor, or the
            static world), clutter and noise.
        purity: (N, 3) share of the measurement's data that came from the object itself: camera,
            matched pixels landing on it; lidar, central returns from it (not weather); radar, its
            share of the peak cell's power. NaN where the sensor gave nothing.
        occlusion: (N,) share of the object hidden in the left camera; truncation: (N,) share of its
            projected box outside the left image (sensors.labels).
        Sets built without the last four fields get SOURCE_NONE / NaN.
    """

    sequence: np.ndarray
    frame: np.ndarray
    actor_ids: np.ndarray
    classes: np.ndarray
    truth: np.ndarray
    z: np.ndarray
    R: np.ndarray
    quality: np.ndarray
    source: np.ndarray | None = None
    purity: np.ndarray | None = None
    occlusion: np.ndarray | None = None
    truncation: np.ndarray | None = None

    def __post_init__(self) -> None:
        n, k = self.truth.shape[0], len(SENSORS)
        defaults = {"source": np.full((n, k), SOURCE_NONE, np.int64), "purity": np.full((n, k), np.nan),
                    "occlusion": np.full(n, np.nan), "truncation": np.full(n, np.nan)}
        for name, value in defaults.items():
            if getattr(self, name) is None:
                object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return int(self.truth.shape[0])

    def __getitem__(self, index) -> MeasurementSet:
        """Rows selected by a boolean mask or an index array."""
        return MeasurementSet(**{f: getattr(self, f)[index] for f in self.__dataclass_fields__})

    @property
    def available(self) -> np.ndarray:
        """(N, 3) bool: the sensor gave a measurement of the object."""
        return np.isfinite(self.z[..., 0])

    def sensor(self, name: str) -> int:
        """Index of a sensor name on the sensor axis."""
        if name not in SENSORS:
            raise ValueError(f"sensor must be one of {', '.join(SENSORS)}, got {name!r}")
        return SENSORS.index(name)

    def arrays(self) -> dict[str, np.ndarray]:
        """The fields as a dict of arrays (for np.savez)."""
        return {f: getattr(self, f) for f in self.__dataclass_fields__}

    @staticmethod
    def from_arrays(arrays) -> MeasurementSet:
        """Inverse of `arrays` (accepts an open np.load archive); checks the shapes."""
        ms = MeasurementSet(**{f: np.asarray(arrays[f]) for f in MeasurementSet.__dataclass_fields__})
        n, k = len(ms), len(SENSORS)
        expected = {"sequence": (n,), "frame": (n,), "actor_ids": (n,), "classes": (n,), "truth": (n, 2),
                    "z": (n, k, 2), "R": (n, k, 2, 2), "quality": (n, k), "source": (n, k), "purity": (n, k),
                    "occlusion": (n,), "truncation": (n,)}
        for f, shape in expected.items():
            if getattr(ms, f).shape != shape:
                raise ValueError(f"{f} must have shape {shape}, got {getattr(ms, f).shape}")
        return ms

    @staticmethod
    def empty() -> MeasurementSet:
        k = len(SENSORS)
        return MeasurementSet(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64),
                              np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, k, 2)), np.zeros((0, k, 2, 2)),
                              np.zeros((0, k)))

    @staticmethod
    def concat(parts) -> MeasurementSet:
        parts = list(parts)
        if not parts:
            return MeasurementSet.empty()
        return MeasurementSet(**{f: np.concatenate([getattr(p, f) for p in parts])
                                 for f in MeasurementSet.__dataclass_fields__})


# ---------------------------------------------------------------------------------------------
# truth


def reference_points(centers_xy: np.ndarray, sizes_lw: np.ndarray, yaws: np.ndarray,
                     origin: np.ndarray | None = None) -> np.ndarray:
    """Where the line of sight from `origin` to each footprint centre enters the footprint.

    Args:
        centers_xy: (N, 2) footprint centres [m]; sizes_lw: (N, 2) (length, width) [m];
        yaws: (N,) headings [rad], all in one ground-plane frame. origin: (2,) sensor point
        (default the frame's origin).

    Returns:
        (N, 2) entry points [m]; the centre itself when the origin lies inside the footprint.
    """
    c = np.asarray(centers_xy, float).reshape(-1, 2)
    o = np.zeros(2) if origin is None else np.asarray(origin, float)
    d = c - o  # ray p(t) = o + t d reaches the centre at t = 1
    cos, sin = np.cos(yaws), np.sin(yaws)
    # ray in box coordinates (axes along length and width)
    o_box = np.column_stack([cos * (o[0] - c[:, 0]) + sin * (o[1] - c[:, 1]),
                             -sin * (o[0] - c[:, 0]) + cos * (o[1] - c[:, 1])])
    d_box = np.column_stack([cos * d[:, 0] + sin * d[:, 1], -sin * d[:, 0] + cos * d[:, 1]])
    half = np.asarray(sizes_lw, float).reshape(-1, 2) / 2.0
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-half - o_box) / d_box
        t2 = (half - o_box) / d_box
    t_enter = np.nanmax(np.minimum(t1, t2), axis=1)  # slab method: last entry over the two axes
    t_enter = np.nan_to_num(t_enter, nan=1.0)
    t_enter = np.where(t_enter <= 0.0, 1.0, np.minimum(t_enter, 1.0))  # origin inside: the centre
    return o + t_enter[:, None] * d


# ---------------------------------------------------------------------------------------------
# geometry helpers


def polar_covariance(bearing: float, sigma_radial: float, sigma_lateral: float) -> np.ndarray:
    """2x2 covariance [m^2] of a point with independent radial and lateral errors, in x/y axes.

    R = Rot(bearing) diag(sigma_radial^2, sigma_lateral^2) Rot(bearing)'.
    """
    c, s = np.cos(bearing), np.sin(bearing)
    Rot = np.array([[c, -s], [s, c]])
    return Rot @ np.diag([sigma_radial**2, sigma_lateral**2]) @ Rot.T


def los_frame(points_xy: np.ndarray) -> np.ndarray:
    """(N, 2, 2) rotations whose rows are the radial and lateral unit vectors of each point (seen
    from the ego origin): e_los = Q e_xy."""
    p = np.asarray(points_xy, float).reshape(-1, 2)
    b = np.arctan2(p[:, 1], p[:, 0])
    c, s = np.cos(b), np.sin(b)
    return np.stack([np.stack([c, s], -1), np.stack([-s, c], -1)], 1)


# ---------------------------------------------------------------------------------------------
# camera


def luma(img01: np.ndarray) -> np.ndarray:
    """(H, W) Rec. 601 luma of an (H, W, 3) sRGB image in 0..1."""
    return (img01 @ np.array([0.299, 0.587, 0.114])).astype(np.float64)


def camera_R(Z: float, u: float, v: float, calib: Calibration, class_id: int,
             sigma_d_px: float = CAMERA_SIGMA_D_PX, sigma_u_px: float = CAMERA_SIGMA_U_PX) -> np.ndarray:
    """Nominal 2x2 ground-plane covariance [m^2] of a stereo point at depth Z [m], pixel (u, v).

    Depth from disparity Z = f b / d has sigma_Z = Z^2 / (f b) sigma_d; the column centre has
    sigma_u. Both are mapped to the ego ground plane through the Jacobian of the back-projection
    p_cam = (Z (u - cx) / f, Z (v - cy) / f, Z), then the camera's rotation; the surface term of an
    averaged measurement is added (`surface_R`).
    """
    cam = calib.camera_left
    f, cx, cy = cam.K[0, 0], cam.K[0, 2], cam.K[1, 2]
    fb = f * _baseline(calib)
    sigma_Z = Z**2 / fb * sigma_d_px  # sigma_Z = Z^2 / (f b) sigma_d
    dp_dZ = np.array([(u - cx) / f, (v - cy) / f, 1.0])
    dp_du = np.array([Z / f, 0.0, 0.0])
    J = cam.ego_from_camera[:2, :3] @ np.column_stack([dp_dZ, dp_du])  # d(x, y)_ego / d(Z, u)
    p = transform_points(cam.ego_from_camera, np.array([[(u - cx) / f * Z, (v - cy) / f * Z, Z]]))[0, :2]
    return J @ np.diag([sigma_Z**2, sigma_u_px**2]) @ J.T + surface_R(p, class_id, "averaged")


def _baseline(calib: Calibration) -> float:
    return float(np.linalg.norm(calib.camera_left.ego_from_camera[:3, 3] - calib.camera_right.ego_from_camera[:3, 3]))


@dataclass(frozen=True)
class StereoMatch:
    """Result of matching one region: disparity d [px] (NaN if rejected), NCC at d, the predicted
    disparity std from the fit's residual [px], matched pixel count, and why it was rejected ('' if
    accepted)."""

    disparity: float
    ncc: float
    pred_sigma_px: float
    pixels: int
    reason: str


def match_region(left: np.ndarray, right: np.ndarray, mask: np.ndarray, max_disparity: int) -> StereoMatch:
    """Disparity of the masked region of the left luma image in the right one (rectified pair).

    A left pixel (u, v) of a point at depth Z appears at (u - d, v) on the right, d = f b / Z.
    1. Zero-mean NCC over the eroded region at every integer d in 0..max_disparity.
    2. Gauss-Newton on (d, a, c) minimising sum (I_R(u - d) - a I_L(u) - c)^2 with cubic-spline
       interpolation of I_R along rows (gain and offset absorb the two auto-exposures).
    The predicted std of d is s_res sqrt([(J'J)^-1]_dd), s_res the residual rms.
    """
    core = ndimage.binary_erosion(mask, structure=np.ones((3, 3), bool))
    vs, us = np.nonzero(core)
    keep = us - max_disparity - 2 >= 0
    vs, us = vs[keep], us[keep]
    n = len(us)
    if n < CAMERA_MIN_PIXELS:
        return StereoMatch(np.nan, np.nan, np.nan, n, "too_small")
    a = left[vs, us]
    a0 = a - a.mean()
    na = np.sqrt(a0 @ a0)
    if na <= 0:
        return StereoMatch(np.nan, np.nan, np.nan, n, "no_texture")
    nccs = np.empty(max_disparity + 1)
    for d in range(max_disparity + 1):
        b = right[vs, us - d]
        b0 = b - b.mean()
        nb = np.sqrt(b0 @ b0)
        nccs[d] = (a0 @ b0) / (na * nb) if nb > 0 else -1.0
    k = int(np.argmax(nccs))
    d = float(k)
    if 0 < k < max_disparity:  # parabola through the three NCC values around the peak
        den = nccs[k - 1] - 2 * nccs[k] + nccs[k + 1]
        if den < 0:
            d = k + 0.5 * (nccs[k - 1] - nccs[k + 1]) / den
    coeffs = ndimage.spline_filter1d(right, order=3, axis=1, mode="mirror")
    gain, offset = 1.0, 0.0
    for _ in range(10):
        cols = us - d
        Ir = ndimage.map_coordinates(coeffs, [vs, cols], order=3, mode="mirror", prefilter=False)
        g = (ndimage.map_coordinates(coeffs, [vs, cols + 0.5], order=3, mode="mirror", prefilter=False)
             - ndimage.map_coordinates(coeffs, [vs, cols - 0.5], order=3, mode="mirror", prefilter=False))
        r = Ir - gain * a - offset  # residual
        J = np.column_stack([-g, -a, -np.ones(n)])  # dr / d(d, gain, offset)
        JtJ = J.T @ J
        try:
            step = np.linalg.solve(JtJ, -J.T @ r)
        except np.linalg.LinAlgError:
            return StereoMatch(np.nan, float(nccs[k]), np.nan, n, "no_texture")
        d += float(np.clip(step[0], -1.0, 1.0))
        gain += float(step[1])
        offset += float(step[2])
        if abs(step[0]) < 1e-3:
            break
    cols = us - d
    Ir = ndimage.map_coordinates(coeffs, [vs, cols], order=3, mode="mirror", prefilter=False)
    r = Ir - gain * a - offset
    s_res = np.sqrt(r @ r / max(n - 3, 1))
    try:
        pred = float(s_res * np.sqrt(np.linalg.inv(JtJ)[0, 0]))
    except np.linalg.LinAlgError:
        pred = np.inf
    I0 = Ir - Ir.mean()
    ncc = float((a0 @ I0) / (na * np.sqrt(I0 @ I0))) if I0 @ I0 > 0 else -1.0
    if not -0.5 <= d <= max_disparity + 0.5:
        return StereoMatch(np.nan, ncc, pred, n, "out_of_range")
    if d < CAMERA_MIN_DISPARITY_PX:
        return StereoMatch(np.nan, ncc, pred, n, "too_far")
    if ncc < CAMERA_MIN_NCC:
        return StereoMatch(np.nan, ncc, pred, n, "low_ncc")
    if not pred <= CAMERA_MAX_PRED_SIGMA_PX:
        return StereoMatch(np.nan, ncc, pred, n, "imprecise")
    return StereoMatch(d, ncc, pred, n, "")


def edge_centre(image: np.ndarray, mask: np.ndarray, search_px: int = CAMERA_EDGE_SEARCH_PX) -> tuple[float, int]:
    """Column centre [px, continuous] of an object from its left and right edges in the image.

    For every row of the mask, the object's left and right silhouette edges are searched in the
    image within +-search_px of the mask's boundaries: the strongest horizontal step |I[u] - I[u-1]|,
    refined by a parabola; the row's centre is the midpoint. Rows whose weaker edge is below
    CAMERA_MIN_EDGE (in image units 0..1) are skipped; the result is the median of the row centres
    (robust to a row crossing a raindrop or an occluder). Returns (centre, rows used); NaN if none.
    """
    H, W = image.shape
    grad = np.abs(np.diff(image, axis=1))  # grad[:, k] is the step at boundary u = k + 1
    centres = []
    for v in np.flatnonzero(mask.any(axis=1)):
        cols = np.flatnonzero(mask[v])
        edges = []
        for b in (int(cols[0]), int(cols[-1]) + 1):  # boundary positions (pixel edges)
            lo, hi = max(b - search_px, 1), min(b + search_px, W - 1)
            if hi < lo:
                break
            g = grad[v, lo - 1:hi]  # steps at boundaries lo..hi
            k = int(np.argmax(g))
            peak = float(g[k])
            if peak < CAMERA_MIN_EDGE:
                break
            off = 0.0
            if 0 < k < len(g) - 1:
                den = g[k - 1] - 2 * g[k] + g[k + 1]
                if den < 0:
                    off = 0.5 * (g[k - 1] - g[k + 1]) / den
            edges.append(lo + k + off)
        if len(edges) == 2:
            centres.append(0.5 * (edges[0] + edges[1]))
    if not centres:
        return np.nan, 0
    return float(np.median(centres)), len(centres)


def camera_band(mask: np.ndarray) -> np.ndarray:
    """The lower CAMERA_BAND of a region's rows (the surface facing the camera), as a mask."""
    rows = np.flatnonzero(mask.any(axis=1))
    cut = rows[-1] + 1 - CAMERA_BAND * (rows[-1] + 1 - rows[0])
    return mask & (np.arange(mask.shape[0])[:, None] >= cut)


def camera_source(instance_left: np.ndarray, instance_right: np.ndarray, actor_id: int,
                  disparity: float) -> tuple[int, float]:
    """Where a stereo match landed: (the actor id most of the matched band's pixels fall on in the
    clean right image, 0 for the static world or sky; the share that falls on the object itself).

    A left pixel (u, v) matched at disparity d is the right pixel (u - d, v); the clean right
    instance map says what surface is there. (SOURCE_NONE, NaN) when there is no match.
    """
    if not np.isfinite(disparity):
        return SOURCE_NONE, np.nan
    band = camera_band(instance_left == actor_id)
    vs, us = np.nonzero(band)
    ur = np.rint(us - disparity).astype(np.int64)
    ok = (ur >= 0) & (ur < instance_right.shape[1])
    if not ok.any():
        return SOURCE_WORLD, 0.0
    hit = instance_right[vs[ok], ur[ok]]
    ids, counts = np.unique(hit, return_counts=True)
    return int(ids[np.argmax(counts)]), float(np.mean(hit == actor_id))


def camera_measurement(left: np.ndarray, right: np.ndarray, instance_left: np.ndarray, actor_id: int,
                       calib: Calibration, class_id: int) -> tuple[np.ndarray, np.ndarray, StereoMatch]:
    """Stereo position of one object: (z (2,), R (2, 2), match); z and R are NaN when rejected.

    left, right: (H, W) luma of the exposed 8-bit images in 0..1; instance_left: (H, W) actor ids
    (the region). The disparity is matched over the bottom CAMERA_BAND of the region's rows (the
    surface facing the camera; higher rows show roofs and rear windows farther back) and the bearing
    comes from the object's edges in the left image (`edge_centre`).
    """
    cam = calib.camera_left
    f, cx, cy = cam.K[0, 0], cam.K[0, 2], cam.K[1, 2]
    fb = f * _baseline(calib)
    mask = instance_left == actor_id
    nan2, nan22 = np.full(2, np.nan), np.full((2, 2), np.nan)
    if not mask.any():
        return nan2, nan22, StereoMatch(np.nan, np.nan, np.nan, 0, "not_visible")
    band = camera_band(mask)
    rows = np.flatnonzero(mask.any(axis=1))
    max_d = int(np.ceil(fb / MIN_RANGE_M)) + 2
    m = match_region(left, right, band, max_d)
    if not np.isfinite(m.disparity):
        return nan2, nan22, m
    u, n_rows = edge_centre(left, band)
    if not np.isfinite(u):
        return nan2, nan22, StereoMatch(np.nan, m.ncc, m.pred_sigma_px, m.pixels, "no_edges")
    v = 0.5 * (rows[0] + rows[-1] + 1)
    Z = fb / m.disparity  # Z = f b / d
    p_cam = np.array([(u - cx) / f * Z, (v - cy) / f * Z, Z])
    z = transform_points(cam.ego_from_camera, p_cam[None])[0, :2]
    return z, camera_R(Z, u, v, calib, class_id), m


# ---------------------------------------------------------------------------------------------
# lidar


def lidar_R(range_m: float, bearing: float, class_id: int, point_xy: np.ndarray) -> np.ndarray:
    """Nominal 2x2 covariance [m^2] of a lidar reference point at `range_m`, `bearing` from the lidar.

    HDL-32E range accuracy (2 cm) radially and the beam divergence times range across, plus the
    surface term of an estimate averaged over the visible surface (`surface_R`).
    """
    sensor = polar_covariance(bearing, LIDAR_SIGMA_RANGE_M, LIDAR_DIVERGENCE_RAD * range_m)
    return sensor + surface_R(point_xy, class_id, "averaged")


def surface_R(point_xy: np.ndarray, class_id: int, kind: str, mount_height_m: float = 0.0,
              beamwidth_rad: float = 0.0) -> np.ndarray:
    """Covariance [m^2] of where a sensor's measurement lands on an object relative to its reference
    point, from the class's mean box (L, W, H); radial and lateral to the line of sight of point_xy.

    Every kind has an obliquity term: an object driving parallel to the ego and seen at bearing b
    shows its side over a projected extent g = (L / 2) |sin b| next to its facing end, and the
    line-of-sight entry point, the visible silhouette's centre and its nearest surface part company
    over that extent: uniform, std g / sqrt(3), radially and laterally.

    kind "averaged" (an estimate over the whole visible surface: the lidar's near-surface range and
    mean bearing, the camera's matched band and silhouette centre): radially the relief of the
    facing surface (SURFACE_RELIEF_M: bumpers, lamps, mirrors); laterally nothing more, since
    averaging over the silhouette centres the estimate on the object's width.
    kind "echo" (the strongest cell of a speckled return: the radar peak): laterally uniform across
    the object's width widened by the beam, sqrt(W^2 + (r theta_3dB)^2) / sqrt(12); radially
    `echo_depth`'s spread.
    """
    L, W, _ = _class_size(class_id)
    p = np.asarray(point_xy, float)
    bearing = float(np.arctan2(p[1], p[0]))
    g = 0.5 * L * abs(np.sin(bearing))  # projected extent of the visible side
    if kind == "averaged":
        radial, lateral = SURFACE_RELIEF_M, 0.0
    elif kind == "echo":
        r = float(np.hypot(p[0], p[1]))
        radial = echo_depth(class_id, mount_height_m)[1]
        lateral = np.hypot(W, r * beamwidth_rad) / np.sqrt(12.0)
    else:
        raise ValueError(f"kind must be 'averaged' or 'echo', got {kind!r}")
    side = g / np.sqrt(3.0)
    return polar_covariance(bearing, np.hypot(radial, side), np.hypot(lateral, side))


def echo_depth(class_id: int, mount_height_m: float) -> tuple[float, float]:
    """(mean, std) [m] of how far behind the facing surface a sensor's strongest echo lies.

    A sensor mounted above an object's top (a roof radar at 2.05 m over a 1.5 m car) looks over the
    facing surface: the main lobe lands on the rear window, roof and far edges, anywhere on the near
    half of the object's length: uniform on [0, L/2], mean L/4, std L / (4 sqrt(3)). An object taller
    than the mount fills the beam with its facing surface: mean 0, std SURFACE_RELIEF_M.
    """
    L, _, H = _class_size(class_id)
    if H < mount_height_m:
        return L / 4.0, L / (4.0 * np.sqrt(3.0))
    return 0.0, SURFACE_RELIEF_M


def _class_size(class_id: int) -> tuple[float, float, float]:
    L, W, H = CLASS_SIZE[CLASSES[int(class_id) - 1]][0]
    return float(L), float(W), float(H)


def lidar_measurement(clean_instance: np.ndarray, degraded, calib: Calibration, actor_id: int,
                      class_id: int, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Lidar position of one object: (z (2,), R (2, 2), number of returns used); NaN when < 3 returns.

    clean_instance: (32, A) actor id each ray would hit in clear air (the object's region);
    degraded: the frame's degraded LidarObservation; directions: (32, A, 3) beam directions.
    """
    nan2, nan22 = np.full(2, np.nan), np.full((2, 2), np.nan)
    ret = _lidar_returns(clean_instance, degraded, calib, actor_id, directions)
    if ret is None:
        return nan2, nan22, int(((clean_instance == actor_id) & degraded.returned).sum())
    region, rng, mean_az, central = ret
    r = float(np.quantile(rng[central], LIDAR_RANGE_QUANTILE))
    origin = calib.ego_from_lidar[:2, 3]
    z = origin + r * np.array([np.cos(mean_az), np.sin(mean_az)])
    return z, lidar_R(r, mean_az, class_id, z), int(region.sum())


def _lidar_returns(clean_instance, degraded, calib: Calibration, actor_id: int, directions: np.ndarray):
    """The degraded returns on the object's rays: (region (32, A) bool, horizontal ranges of the
    returns (n,) [m], their mean azimuth [rad], the central ones (n,) bool); None when < 3 returns."""
    region = (clean_instance == actor_id) & degraded.returned
    if int(region.sum()) < LIDAR_MIN_POINTS:
        return None
    pts = directions[region] * degraded.range[region][:, None].astype(np.float64)
    origin = calib.ego_from_lidar[:2, 3]
    xy = transform_points(calib.ego_from_lidar, pts)[:, :2] - origin
    rng = np.hypot(xy[:, 0], xy[:, 1])
    az = np.arctan2(xy[:, 1], xy[:, 0])
    mean_az = float(np.angle(np.mean(np.exp(1j * az))))
    off = np.angle(np.exp(1j * (az - mean_az)))
    spread = max(float(np.ptp(off)), 1e-9)
    # the central sixth of the object's azimuth span; when the returns fall in two clusters (an
    # occluder splits the object) the mean azimuth can lie in the gap: then take the nearest column
    width = max(spread / 6.0, 2 * np.pi / calib.lidar_azimuth_steps, float(np.abs(off).min()))
    return region, rng, mean_az, np.abs(off) <= width


def lidar_source(clean_instance: np.ndarray, degraded, calib: Calibration, actor_id: int,
                 directions: np.ndarray) -> tuple[int, float]:
    """Where a lidar measurement's data came from: (what the returns that set the range hit, the
    share of central returns that hit the object itself). The range is the LIDAR_RANGE_QUANTILE
    quantile of the central returns, interpolated between two of them: if either is a weather
    return, the range is (partly) the air's.

    The region holds only rays that hit the object in clear air, so a return on them hit either
    the object or the air: the degradation marks a weather return (fog backscatter, a rain drop, a
    snow flake) that replaced the surface return with instance 0 (sensors.degrade.lidar), here
    SOURCE_WEATHER. (SOURCE_NONE, NaN) when there are fewer than 3 returns.
    """
    ret = _lidar_returns(clean_instance, degraded, calib, actor_id, directions)
    if ret is None:
        return SOURCE_NONE, np.nan
    region, rng, _, central = ret
    own = degraded.instance[region][central] == actor_id
    order = np.argsort(rng[central], kind="stable")
    pos = LIDAR_RANGE_QUANTILE * (len(order) - 1)  # np.quantile interpolates between these two returns
    setters = order[[int(np.floor(pos)), int(np.ceil(pos))]]
    return (int(actor_id) if own[setters].all() else SOURCE_WEATHER), float(own.mean())


# ---------------------------------------------------------------------------------------------
# radar


def radar_R(range_m: float, bearing: float, snr_db: float, class_id: int, calib: Calibration,
            point_xy: np.ndarray) -> np.ndarray:
    """Nominal 2x2 covariance [m^2] of a radar peak at `range_m`, `bearing` from the radar.

    radial: the range bin's uniform quantisation dr / sqrt(12); azimuth: the beam-splitting accuracy
    theta_3dB / (1.6 sqrt(2 SNR)) (Skolnik, Introduction to Radar Systems, 3rd ed., Sec. 6.9) times
    range (for a steady point target; negligible at the SNRs of cars), plus the surface term of the
    strongest cell of a speckled extended target (`surface_R`, kind "echo"), which dominates.
    """
    dr = calib.radar_range_resolution_m
    snr = 10.0 ** (snr_db / 10.0)
    s_az = np.radians(RADAR_BEAMWIDTH_DEG) / (1.6 * np.sqrt(2.0 * snr))
    sensor = polar_covariance(bearing, dr / np.sqrt(12.0), s_az * range_m)
    return sensor + surface_R(point_xy, class_id, "echo", calib.radar_height_m, np.radians(RADAR_BEAMWIDTH_DEG))


def radar_measurement(clean_instance: np.ndarray, degraded, calib: Calibration, actor_id: int,
                      class_id: int, noise_floor: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Radar position of one object: (z (2,), R (2, 2), peak SNR [dB]); NaN when the object has no
    cells or its peak is below RADAR_MIN_SNR_DB.

    clean_instance: (A, B) actor id per polar cell in clear air (the object's cells); degraded: the
    frame's degraded RadarObservation; noise_floor: the scan's mean noise power estimate.
    """
    nan2, nan22 = np.full(2, np.nan), np.full((2, 2), np.nan)
    peak = radar_peak(clean_instance, degraded, actor_id)
    if peak is None:
        return nan2, nan22, np.nan
    a, b = peak
    P = degraded.power.astype(np.float64)
    A, B = P.shape
    snr_db = float(10 * np.log10(max(P[a, b] - noise_floor, 1e-12) / noise_floor))
    if snr_db < RADAR_MIN_SNR_DB:
        return nan2, nan22, snr_db
    logP = np.log(np.maximum(P, 1e-12))

    def vertex(lo, mid, hi):
        # parabola through three samples; the window's maximum need not be a local maximum of the
        # scan (a stronger neighbour just outside the window), and then the vertex can lie anywhere:
        # a peak's sub-cell offset is within half a cell
        den = lo - 2 * mid + hi
        return float(np.clip(0.5 * (lo - hi) / den, -0.5, 0.5)) if den < 0 else 0.0

    db = vertex(logP[a, b - 1], logP[a, b], logP[a, b + 1]) if 0 < b < B - 1 else 0.0
    da = vertex(logP[(a - 1) % A, b], logP[a, b], logP[(a + 1) % A, b])
    rng = (b + 0.5 + db) * calib.radar_range_resolution_m
    az = (a + da) * 2 * np.pi / A  # row a at a * 360 / A deg (sensors.rig convention)
    origin = calib.ego_from_radar[:2, 3]
    bearing = float(np.arctan2(np.sin(az), np.cos(az)))
    rng -= echo_depth(class_id, calib.radar_height_m)[0]  # the echo lies behind the facing surface
    z = origin + rng * np.array([np.cos(bearing), np.sin(bearing)])
    return z, radar_R(rng, bearing, snr_db, class_id, calib, z), snr_db


def radar_peak(clean_instance: np.ndarray, degraded, actor_id: int) -> tuple[int, int] | None:
    """(azimuth row, range column) of the strongest degraded cell within RADAR_WINDOW_AZ rows and
    RADAR_WINDOW_RANGE columns of the object's clear-air cells; None when it has no cells."""
    cells = clean_instance == actor_id
    if not cells.any():
        return None
    A = cells.shape[0]
    # window: dilate the cells by the half-widths (azimuth wraps around)
    win = ndimage.binary_dilation(np.vstack([cells[-RADAR_WINDOW_AZ:], cells, cells[:RADAR_WINDOW_AZ]]),
                                  structure=np.ones((2 * RADAR_WINDOW_AZ + 1, 2 * RADAR_WINDOW_RANGE + 1), bool))
    win = win[RADAR_WINDOW_AZ:RADAR_WINDOW_AZ + A]
    P = degraded.power.astype(np.float64)
    a, b = np.unravel_index(int(np.argmax(np.where(win, P, -np.inf))), P.shape)
    return int(a), int(b)


def radar_source(clean_instance: np.ndarray, degraded, actor_id: int) -> tuple[int, float]:
    """Where a radar peak came from: (the largest of the peak cell's three powers, read apart in
    the degraded scan: its signal's actor (sensors.radar: the actor contributing most power to the
    cell; 0 the static world), SOURCE_WEATHER for clutter or SOURCE_NOISE for receiver noise; the
    object's share of the cell's power, 0 when the cell's signal is another actor's).

    Computed for every object with cells (SOURCE_NONE, NaN without): the caller blanks those whose
    peak fell below RADAR_MIN_SNR_DB.
    """
    peak = radar_peak(clean_instance, degraded, actor_id)
    if peak is None:
        return SOURCE_NONE, np.nan
    sig, clut, noise = (float(np.asarray(x, np.float64)[peak]) for x in (degraded.signal, degraded.clutter,
                                                                          degraded.noise))
    owner = int(degraded.instance[peak])
    a, b = peak
    A = degraded.instance.shape[0]
    for da in range(1, RADAR_WINDOW_AZ + 1):  # the beam smears an echo over neighbouring azimuth rows
        if owner:
            break
        for side in (-da, da):
            if degraded.instance[(a + side) % A, b]:
                owner = int(degraded.instance[(a + side) % A, b])
                break
    total = max(sig + clut + noise, 1e-300)
    purity = sig / total if owner == actor_id else 0.0
    if sig >= clut and sig >= noise:
        return owner, purity
    return (SOURCE_WEATHER if clut >= noise else SOURCE_NOISE), purity


def noise_floor(radar_obs) -> float:
    """Mean noise power of a scan estimated from the data: the median cell power / ln 2 (the median
    of an exponential variable of mean N0 is N0 ln 2; most cells hold noise only)."""
    return float(np.median(radar_obs.power) / np.log(2.0))


# ---------------------------------------------------------------------------------------------
# one frame, one sequence


def exposed_images(observations) -> dict[str, np.ndarray]:
    """The cameras' 8-bit images as the dataset stores them (sensors.camera.expose, to_uint8), as
    floats 0..1: {"camera_left": (H, W, 3), "camera_right": (H, W, 3)}."""
    from sensors import camera as cam_mod

    return {name: cam_mod.to_uint8(cam_mod.expose(getattr(observations, name))).astype(np.float64) / 255.0
            for name in ("camera_left", "camera_right")}


def measure_frame(scene, clean, degraded, calib: Calibration, images: dict | None = None,
                  sequence: int = 0) -> MeasurementSet:
    """Measure every evaluated object of a frame with every sensor.

    Args:
        scene: the sim Scene (actors and ego pose: truth and the evaluation set only).
        clean: the frame's Observations before degradation (the regions: instance maps).
        degraded: the same frame's degraded Observations (what is measured).
        calib: the rig's Calibration.
        images: the degraded cameras' exposed images (`exposed_images(degraded)` if None).
        sequence: the sequence index stored in the rows.

    Returns:
        MeasurementSet with one row per object of `evaluation_set`.
    """
    ids, classes, truth, occlusion, truncation = evaluation_set(scene, clean, calib, with_visibility=True)
    n, k = len(ids), len(SENSORS)
    z = np.full((n, k, 2), np.nan)
    R = np.full((n, k, 2, 2), np.nan)
    q = np.full((n, k), np.nan)
    source = np.full((n, k), SOURCE_NONE, np.int64)
    purity = np.full((n, k), np.nan)
    if n:
        images = exposed_images(degraded) if images is None else images
        left, right = luma(images["camera_left"]), luma(images["camera_right"])
        dirs = lidar_mod.beam_directions(calib)
        floor = noise_floor(degraded.radar)
        for i, (aid, cls) in enumerate(zip(ids.tolist(), classes.tolist())):
            z[i, 0], R[i, 0], m = camera_measurement(left, right, clean.camera_left.instance, aid, calib, cls)
            q[i, 0] = m.ncc
            z[i, 1], R[i, 1], q[i, 1] = lidar_measurement(clean.lidar.instance, degraded.lidar, calib, aid, cls, dirs)
            z[i, 2], R[i, 2], q[i, 2] = radar_measurement(clean.radar.instance, degraded.radar, calib, aid, cls, floor)
            source[i, 0], purity[i, 0] = camera_source(clean.camera_left.instance, clean.camera_right.instance, aid,
                                                       m.disparity if np.isfinite(z[i, 0, 0]) else np.nan)
            source[i, 1], purity[i, 1] = lidar_source(clean.lidar.instance, degraded.lidar, calib, aid, dirs)
            source[i, 2], purity[i, 2] = radar_source(clean.radar.instance, degraded.radar, aid)
        gone = ~np.isfinite(z[..., 0])  # rejected measurements (low SNR, ...) have no source
        source[gone], purity[gone] = SOURCE_NONE, np.nan
    return MeasurementSet(np.full(n, sequence, np.int64), np.full(n, scene.frame_index, np.int64), ids,
                          classes.astype(np.int64), truth, z, R, q, source, purity, occlusion, truncation)


def measure_sequence(spec, sequence: int = 0, obstructions: bool = False, on_frame=None) -> MeasurementSet:
    """Simulate, render, degrade and measure every frame of a ScenarioSpec.

    Args:
        spec: sim.scenario.ScenarioSpec (context, severity, seed, frames, frame rate, profile, transition).
        sequence: the index stored in the rows' `sequence` field.
        obstructions: also apply the obstruction/failure models (lens soiling, beam loss, ...); the
            fusion theory studies weather, so False by default.
        on_frame: called after each frame (progress bars).

    Returns:
        MeasurementSet of all frames; a frame's weather is the scene's own (transitions included).
    """
    from sensors.degrade import Degrader
    from sensors.frame import SequenceRenderer
    from sensors.rig import load_profile
    from sim.scenario import Simulator

    sim = Simulator(spec)
    scenes = sim.scenes()
    first = next(scenes)
    renderer = SequenceRenderer(first, load_profile(spec.profile), seed=spec.seed)
    degrader = Degrader(renderer.calib, spec.context, spec.seed, obstructions=obstructions)
    parts = []
    for scene in itertools.chain([first], scenes):
        clean = renderer.observe(scene)
        degraded, _ = degrader.apply(clean, scene.frame_index)
        parts.append(measure_frame(scene, clean, degraded, renderer.calib, sequence=sequence))
        if on_frame is not None:
            on_frame()
    return MeasurementSet.concat(parts)


def evaluation_set(scene, clean, calib: Calibration, with_visibility: bool = False) -> tuple[np.ndarray, ...]:
    """The objects whose measurements are evaluated: reference point 5-60 m from the ego, visible in
    the left camera with at most MAX_OCCLUSION hidden and MAX_TRUNCATION cut by the image border
    (exact labels from the clean instance and depth maps). Returns (ids, classes, truth (N, 2)), and
    with_visibility also each object's occlusion (N,) and truncation (N,)."""
    from sensors.labels import fwd_labels

    lab = fwd_labels(clean.camera_left.instance, clean.camera_left.depth, scene.actors, calib.camera_left,
                     scene.ego.pose)
    if not lab["ids"]:
        empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)))
        return empty + (np.zeros(0), np.zeros(0)) if with_visibility else empty
    occ, trunc = np.array(lab["occlusion"], float), np.array(lab["truncation"], float)
    ok = (occ <= MAX_OCCLUSION) & (trunc <= MAX_TRUNCATION)
    ids = np.array(lab["ids"], np.int64)[ok]
    row = {int(a): i for i, a in enumerate(scene.actors.ids)}
    rows = np.array([row[int(a)] for a in ids], np.int64)
    A = scene.actors
    ego_from_world = invert(scene.ego.pose)
    centers = transform_points(ego_from_world, A.centers[rows])[:, :2] if len(rows) else np.zeros((0, 2))
    ego_yaw = np.arctan2(scene.ego.pose[1, 0], scene.ego.pose[0, 0])
    truth = reference_points(centers, A.sizes[rows, :2], A.yaws[rows] - ego_yaw)
    dist = np.hypot(truth[:, 0], truth[:, 1])
    keep = (dist >= MIN_RANGE_M) & (dist <= MAX_RANGE_M)
    out = (ids[keep], A.classes[rows][keep], truth[keep])
    return out + (occ[ok][keep], trunc[ok][keep]) if with_visibility else out
