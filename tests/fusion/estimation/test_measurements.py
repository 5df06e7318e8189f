"""The measurement extractors on synthetic sensor data whose answer is known exactly.

The rendered, degraded frames are measured in tests/study/test_theory_measured.py; here every
extractor is fed an input built by hand: a texture shifted by a known disparity, an edge at a known
column, a radar peak in a known cell, lidar returns on a known wall.
"""

import io

import numpy as np
import pytest
from scipy import ndimage

from fusion.estimation import measurements as M
from sensors.lidar import LidarObservation, beam_directions
from sensors.radar import RadarObservation
from sensors.rig import load_profile, make_calibration

CALIB = make_calibration(load_profile("cpu"))
CAR = 1  # class id of "car" (L 4.5 m, W 1.8 m, H 1.5 m)
TRUCK = 3  # 11 x 2.5 x 3.6 m: taller than the radar's 2.05 m mount


# --- truth -------------------------------------------------------------------------------------


def entry_by_marching(center, size, yaw, steps=200_001):
    """First point of the segment from the origin to center inside the rotated rectangle (brute force)."""
    origin = np.zeros(2)
    t = np.linspace(0.0, 1.0, steps)
    p = origin + t[:, None] * (np.asarray(center) - origin)
    c, s = np.cos(yaw), np.sin(yaw)
    d = p - center
    local = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
    inside = np.all(np.abs(local) <= np.asarray(size) / 2 + 1e-12, axis=1)
    return p[np.argmax(inside)]


@pytest.mark.parametrize(
    "center, size, yaw",
    [((20.0, 0.0), (4.0, 2.0), 0.0), ((20.0, 0.0), (4.0, 2.0), np.pi / 2), ((20.0, 5.0), (4.5, 1.8), 0.0),
     ((-15.0, 8.0), (11.0, 2.5), 0.7), ((30.0, -12.0), (0.5, 0.6), -2.0)],
)
def test_reference_point_is_where_the_line_of_sight_enters_the_footprint(center, size, yaw):
    got = M.reference_points(np.array([center]), np.array([size]), np.array([yaw]))[0]
    np.testing.assert_allclose(got, entry_by_marching(np.array(center), size, yaw), atol=1e-3)


def test_reference_point_of_a_box_around_the_origin_is_its_centre():
    got = M.reference_points(np.array([[0.5, 0.2]]), np.array([[4.0, 2.0]]), np.array([0.3]))
    np.testing.assert_allclose(got, [[0.5, 0.2]])


def test_polar_covariance_has_the_radial_and_lateral_variances_on_its_axes():
    b = np.radians(30.0)
    R = M.polar_covariance(b, 2.0, 0.5)
    radial, lateral = np.array([np.cos(b), np.sin(b)]), np.array([-np.sin(b), np.cos(b)])
    assert radial @ R @ radial == pytest.approx(4.0)
    assert lateral @ R @ lateral == pytest.approx(0.25)
    assert radial @ R @ lateral == pytest.approx(0.0, abs=1e-12)
    Q = M.los_frame(np.array([[10 * np.cos(b), 10 * np.sin(b)]]))[0]
    np.testing.assert_allclose(Q @ R @ Q.T, np.diag([4.0, 0.25]), atol=1e-12)


# --- nominal R ---------------------------------------------------------------------------------


def test_camera_depth_variance_grows_as_Z_to_the_fourth():
    """sigma_Z = Z^2 / (f b) sigma_d: doubling the depth multiplies its variance by 16."""
    cam = CALIB.camera_left
    f, cx, cy = cam.K[0, 0], cam.K[0, 2], cam.K[1, 2]
    fb = f * 0.12
    radial = []
    for Z in (10.0, 20.0):
        R = M.camera_R(Z, cx, cy, CALIB, CAR)
        p = cam.ego_from_camera[:2, 3] + np.array([Z, 0.0])
        radial.append((R - M.surface_R(p, CAR, "averaged"))[0, 0])  # straight ahead: x is radial
        assert radial[-1] == pytest.approx((Z**2 / fb * M.CAMERA_SIGMA_D_PX) ** 2, rel=1e-9)
    assert radial[1] / radial[0] == pytest.approx(16.0, rel=1e-9)


def test_radar_R_is_the_beam_splitting_accuracy_plus_the_echo_spread():
    """Straight ahead: lateral variance (r theta / (1.6 sqrt(2 SNR)))^2 + (W^2 + (r theta_3dB)^2) / 12,
    radial variance dr^2 / 12 + the echo-depth variance; both grow with range only laterally."""
    theta = np.radians(1.8)
    snr = 10.0**3.0
    dr = CALIB.radar_range_resolution_m
    for r in (10.0, 40.0):
        R = M.radar_R(r, 0.0, 30.0, CAR, CALIB, np.array([r, 0.0]))
        lateral = (r * theta / (1.6 * np.sqrt(2 * snr))) ** 2 + (1.8**2 + (r * theta) ** 2) / 12
        radial = dr**2 / 12 + M.echo_depth(CAR, CALIB.radar_height_m)[1] ** 2
        np.testing.assert_allclose(R, np.diag([radial, lateral]), rtol=1e-12, atol=1e-15)


def test_echo_depth_depends_on_whether_the_sensor_looks_over_the_object():
    L_car = 4.5
    assert M.echo_depth(CAR, 2.05) == pytest.approx((L_car / 4, L_car / (4 * np.sqrt(3))))
    assert M.echo_depth(TRUCK, 2.05) == (0.0, M.SURFACE_RELIEF_M)


# --- camera ------------------------------------------------------------------------------------


def textured_pair(d: float, seed: int = 0, quantise: bool = True):
    """A smooth random texture and the same texture seen d px further left (right camera)."""
    rng = np.random.default_rng(seed)
    left = ndimage.gaussian_filter(rng.uniform(size=(80, 120)), 1.5)
    left = (left - left.min()) / np.ptp(left)
    right = ndimage.shift(left, (0.0, -d), order=3, mode="nearest")  # I_R(u) = I_L(u + d)
    if quantise:
        left, right = np.round(left * 255) / 255, np.round(right * 255) / 255
    return left, right


@pytest.mark.parametrize("d", [0.8, 1.37, 2.5, 3.9])
def test_stereo_matching_recovers_a_subpixel_disparity(d):
    left, right = textured_pair(d)
    mask = np.zeros(left.shape, bool)
    mask[20:60, 30:90] = True
    m = M.match_region(left, right, mask, max_disparity=6)
    assert m.reason == ""
    assert m.disparity == pytest.approx(d, abs=0.02)
    assert m.ncc > 0.99 and m.pred_sigma_px < 0.01


def test_stereo_matching_rejects_what_it_cannot_match():
    left, right = textured_pair(1.0)
    mask = np.zeros(left.shape, bool)
    mask[20:60, 30:90] = True
    noise = np.random.default_rng(5).uniform(size=left.shape)  # the right eye sees something else
    assert M.match_region(left, noise, mask, 6).reason == "low_ncc"
    flat = np.full(left.shape, 0.4)
    assert M.match_region(flat, flat, mask, 6).reason == "no_texture"
    small = np.zeros(left.shape, bool)
    small[30:35, 40:45] = True  # 9 pixels after erosion
    assert M.match_region(left, right, small, 6).reason == "too_small"


def test_edge_centre_finds_the_object_between_its_edges():
    H, W = 60, 200
    cols = np.arange(W) + 0.5
    x1, x2 = 80.3, 121.9  # object edges [px], continuous
    row = np.clip(cols - x1 + 0.5, 0, 1) * np.clip(x2 - cols + 0.5, 0, 1)  # area-sampled box
    image = 0.2 + 0.5 * np.tile(row, (H, 1))
    mask = np.tile((cols > x1) & (cols < x2), (H, 1))
    centre, rows = M.edge_centre(image, mask)
    assert rows == H
    assert centre == pytest.approx((x1 + x2) / 2, abs=0.1)
    faded = 0.2 + 0.005 * np.tile(row, (H, 1))  # contrast below CAMERA_MIN_EDGE: no edge found
    assert np.isnan(M.edge_centre(faded, mask)[0])


# --- lidar -------------------------------------------------------------------------------------


def wall_observation(horizontal_range, rings, azimuths, actor_id=7):
    """Clean lidar sweep with an object at a given horizontal range on the given rays."""
    A = CALIB.lidar_azimuth_steps
    shape = (32, A)
    rng = np.full(shape, np.inf, np.float32)
    el = np.radians(CALIB.lidar_elevations_deg)
    inst = np.zeros(shape, np.int64)
    for r in rings:
        rng[r, azimuths] = horizontal_range / np.cos(el[r])
        inst[r, azimuths] = actor_id
    returned = np.isfinite(rng)
    obs = LidarObservation(rng, returned.astype(np.float32), inst, np.zeros(shape, np.uint8),
                           np.ones(shape, np.float32), returned, np.zeros((0, 5), np.float32))
    return obs


def test_lidar_measures_the_facing_surface_and_ignores_a_minority_of_fog_returns():
    rings, az = range(12, 20), np.arange(10, 31)  # 21 rays of 0.4 deg: bearing 8 deg from the lidar
    obs = wall_observation(25.0, rings, az)
    dirs = beam_directions(CALIB)
    z, R, n = M.lidar_measurement(obs.instance, obs, CALIB, 7, CAR, dirs)
    bearing = np.radians(20 * 360 / CALIB.lidar_azimuth_steps)
    expected = CALIB.ego_from_lidar[:2, 3] + 25.0 * np.array([np.cos(bearing), np.sin(bearing)])
    assert n == 8 * 21
    np.testing.assert_allclose(z, expected, atol=1e-3)
    assert np.all(np.linalg.eigvalsh(R) > 0)
    # fog backscatter at 4 m on 1 ray in 5 of the region: the near-surface quantile (25 %) holds
    fog = obs.copy()
    fog.range[12:20, az[::5]] = 4.0
    z_fog, _, _ = M.lidar_measurement(obs.instance, fog, CALIB, 7, CAR, dirs)
    np.testing.assert_allclose(z_fog, expected, atol=1e-3)
    # ... but when fog returns are the majority the measurement collapses onto the fog
    fog.range[12:20, az[::2]] = 4.0
    z_fog, _, _ = M.lidar_measurement(obs.instance, fog, CALIB, 7, CAR, dirs)
    assert np.linalg.norm(z_fog - CALIB.ego_from_lidar[:2, 3]) == pytest.approx(4.0, abs=0.1)


def test_lidar_survives_an_object_split_in_two_by_an_occluder():
    # returns in two clusters (a pole in front of the car hides columns 16-24): the mean azimuth
    # falls in the gap, where no column returned; the nearest columns still give the range
    az = np.r_[np.arange(10, 16), np.arange(25, 31)]
    obs = wall_observation(25.0, range(12, 20), az)
    z, R, n = M.lidar_measurement(obs.instance, obs, CALIB, 7, CAR, beam_directions(CALIB))
    assert n == 8 * 12
    assert np.linalg.norm(z - CALIB.ego_from_lidar[:2, 3]) == pytest.approx(25.0, abs=0.05)
    assert np.all(np.isfinite(R))


def test_lidar_needs_three_returns():
    obs = wall_observation(25.0, [15], np.array([10, 11]))
    z, R, n = M.lidar_measurement(obs.instance, obs, CALIB, 7, CAR, beam_directions(CALIB))
    assert n == 2 and np.all(np.isnan(z)) and np.all(np.isnan(R))


# --- radar -------------------------------------------------------------------------------------


def radar_observation(row, col, peak, actor_id=9):
    A, B = CALIB.radar_azimuths, CALIB.radar_range_bins
    signal = np.zeros((A, B), np.float32)
    for da, wa in ((-1, 0.5), (0, 1.0), (1, 0.5)):  # symmetric around the peak cell
        for db, wb in ((-1, 0.5), (0, 1.0), (1, 0.5)):
            signal[(row + da) % A, col + db] = peak * wa * wb
    inst = np.zeros((A, B), np.int64)
    inst[row - 1:row + 2, col - 2:col + 3] = actor_id
    return RadarObservation(signal, np.ones((A, B), np.float32), inst, np.zeros((A, B), np.float32))


@pytest.mark.parametrize("cls", [CAR, TRUCK])
def test_radar_peak_becomes_range_and_bearing(cls):
    row, col = 20, 80  # 18 deg, bin 80
    obs = radar_observation(row, col, 1000.0)
    z, R, snr = M.radar_measurement(obs.instance, obs, CALIB, 9, cls, noise_floor=1.0)
    r = (col + 0.5) * CALIB.radar_range_resolution_m - M.echo_depth(cls, CALIB.radar_height_m)[0]
    b = np.radians(row * 360 / CALIB.radar_azimuths)
    np.testing.assert_allclose(z, CALIB.ego_from_radar[:2, 3] + r * np.array([np.cos(b), np.sin(b)]), atol=1e-9)
    assert snr == pytest.approx(10 * np.log10(1001.0 - 1.0))
    assert np.all(np.linalg.eigvalsh(R) > 0)


def test_radar_bearing_stays_in_the_window_when_a_stronger_neighbour_lies_just_outside():
    # power rising steadily in azimuth towards a strong target beyond the window: the window's
    # maximum sits on its edge, and a parabola through nearly collinear log powers has its vertex
    # tens of cells away; the sub-cell offset is clipped to half a cell
    A, B = CALIB.radar_azimuths, CALIB.radar_range_bins
    row, col, w = 20, 80, M.RADAR_WINDOW_AZ
    rows = np.arange(A)
    logp = np.where(np.abs(rows - row) <= w + 4, 0.5 * (rows - row) - 1e-3 * (rows - row) ** 2, -30.0)
    power = np.zeros((A, B), np.float32)
    power[:, col] = np.exp(logp + 10.0)
    inst = np.zeros((A, B), np.int64)
    inst[row - 1:row + 2, col - 2:col + 3] = 9
    obs = RadarObservation(power, np.ones((A, B), np.float32), inst, np.zeros((A, B), np.float32))
    z, _, _ = M.radar_measurement(obs.instance, obs, CALIB, 9, CAR, noise_floor=1.0)
    bearing = np.degrees(np.arctan2(*(z - CALIB.ego_from_radar[:2, 3])[::-1]))
    edge = (row + 1 + w) * 360 / A
    assert edge - 180 / A <= bearing <= edge + 180 / A


def test_radar_rejects_a_peak_below_the_snr_threshold():
    obs = radar_observation(20, 80, 1.5)  # 1.8 dB above the noise
    z, _, snr = M.radar_measurement(obs.instance, obs, CALIB, 9, CAR, noise_floor=1.0)
    assert np.all(np.isnan(z)) and snr < M.RADAR_MIN_SNR_DB


def test_noise_floor_of_exponential_noise():
    A, B = CALIB.radar_azimuths, CALIB.radar_range_bins
    noise = np.random.default_rng(2).exponential(3.0, size=(A, B)).astype(np.float32)
    obs = RadarObservation(np.zeros((A, B), np.float32), noise, np.zeros((A, B), np.int64),
                           np.zeros((A, B), np.float32))
    assert M.noise_floor(obs) == pytest.approx(3.0, rel=0.02)


# --- the record --------------------------------------------------------------------------------


def random_set(n: int, seed: int = 0, sequence: int = 0) -> M.MeasurementSet:
    rng = np.random.default_rng(seed)
    k = len(M.SENSORS)
    z = rng.normal(size=(n, k, 2))
    z[rng.uniform(size=(n, k)) < 0.3] = np.nan
    R = np.broadcast_to(np.eye(2), (n, k, 2, 2)).copy()
    return M.MeasurementSet(np.full(n, sequence), np.arange(n), rng.integers(1, 100, n), np.ones(n, np.int64),
                            rng.normal(size=(n, 2)), z, R, rng.uniform(size=(n, k)))


def test_measurement_set_round_trips_through_npz_and_concatenates():
    a, b = random_set(5, 1, sequence=0), random_set(3, 2, sequence=1)
    buf = io.BytesIO()
    np.savez(buf, **a.arrays())
    buf.seek(0)
    back = M.MeasurementSet.from_arrays(np.load(buf))
    for f in a.arrays():
        np.testing.assert_array_equal(getattr(back, f), getattr(a, f))
    both = M.MeasurementSet.concat([a, b])
    assert len(both) == 8 and list(both.sequence) == [0] * 5 + [1] * 3
    sub = both[both.sequence == 1]
    np.testing.assert_array_equal(sub.z, b.z)
    np.testing.assert_array_equal(both.available, np.isfinite(both.z[..., 0]))
    assert len(M.MeasurementSet.concat([])) == 0


def test_measurement_set_checks_shapes():
    arrays = random_set(4).arrays()
    arrays["R"] = arrays["R"][:, :2]
    with pytest.raises(ValueError, match="R must have shape"):
        M.MeasurementSet.from_arrays(arrays)
    with pytest.raises(ValueError, match="sensor must be one of"):
        random_set(2).sensor("sonar")
