"""A constant-velocity Kalman tracker per object, fed position measurements from several sensors.

State x = [x, y, vx, vy] in the ground plane: metres and metres per second. Motion model: the
continuous white-noise acceleration model (Bar-Shalom, Li, Kirubarajan 2001, Sec. 6.2.2), whose
acceleration on each axis is white noise of power spectral density q [m^2/s^3]. Over a step of dt
seconds it gives

    F = [[I, dt I], [0, I]]
    Q = q [[dt^3/3 I, dt^2/2 I], [dt^2/2 I, dt I]]

(I the 2x2 identity). The continuous model, unlike the piecewise-constant one, composes exactly:
predicting over dt1 then dt2 equals predicting over dt1 + dt2, which matters when sensors at 4, 10
and 15 Hz interleave. Choosing q: the velocity changes over dt by about sqrt(q dt); q = 1 m^2/s^3
lets a car's speed wander ~1 m/s per second, typical of traffic that brakes and accelerates gently.

Each sensor reports the object's position z = H x + v, H = [I 0], v ~ N(0, R) with the sensor's
own R (2x2, m^2). Updates may be gated: a measurement whose NIS against the prediction exceeds
chi2.ppf(gate_prob, 2) is rejected (see `gating`). Association (which detection is which object)
is not this module's job: measurements carry an `object_id`.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import KalmanFilter

from fusion.estimation._linalg import as_covariance, as_vector, symmetrize
from fusion.estimation.consistency import nis as nis_of
from fusion.estimation.gating import gate_threshold, innovation

DIM_X = 4  # [x, y, vx, vy]
H_POSITION = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]])  # z = [x, y]
DEFAULT_Q = 1.0  # [m^2/s^3] acceleration noise power spectral density per axis
DEFAULT_VELOCITY_STD = 15.0  # [m/s] prior std of each velocity component when a track starts


def cv_model(dt: float, q: float) -> tuple[np.ndarray, np.ndarray]:
    """Transition F (4, 4) and process noise Q (4, 4) of the constant-velocity model over dt [s].

    q: acceleration noise power spectral density per axis [m^2/s^3].
    """
    if not np.isfinite(dt) or dt < 0:
        raise ValueError(f"dt must be a finite time step >= 0 s, got {dt}")
    _check_q(q)
    I2 = np.eye(2)
    F = np.block([[I2, dt * I2], [0 * I2, I2]])  # x_k+1 = x_k + dt v_k ; v_k+1 = v_k
    Q = q * np.block([[dt**3 / 3 * I2, dt**2 / 2 * I2], [dt**2 / 2 * I2, dt * I2]])  # Q = q int F G G' F'
    return F, Q


def cv_predict(x, P, dt: float, q: float) -> tuple[np.ndarray, np.ndarray]:
    """Stateless prediction over dt [s]: x = F x, P = F P F' + Q. x (4,), P (4, 4)."""
    x = as_vector(x, "x", DIM_X)
    P = as_covariance(P, "P", DIM_X)
    F, Q = cv_model(dt, q)
    x = F @ x  # x = F x
    P = symmetrize(F @ P @ F.T + Q)  # P = F P F' + Q
    return x, P


def position_update(x, P, z, R, gate_prob: float | None = None) -> tuple[np.ndarray, np.ndarray, bool, float]:
    """Stateless position update with optional chi-square gate.

    Args:
        x: state (4,) [m, m, m/s, m/s]; P: covariance (4, 4).
        z: measured position (2,) [m]; R: its noise covariance (2, 2) [m^2].
        gate_prob: if given, reject z when NIS > chi2.ppf(gate_prob, 2).

    Returns:
        x, P after the update (unchanged if rejected), accepted, NIS.
    """
    x = as_vector(x, "x", DIM_X)
    P = as_covariance(P, "P", DIM_X)
    z = as_vector(z, "z", 2)
    R = as_covariance(R, "R", 2)
    H = H_POSITION
    y, S = innovation(x, P, z, R, H)  # y = z - H x ; S = H P H' + R
    nis = float(nis_of(y, S))  # NIS = y' S^-1 y
    if gate_prob is not None and nis > gate_threshold(2, gate_prob):
        return x, P, False, nis
    K = P @ H.T @ np.linalg.inv(S)  # K = P H' S^-1
    x = x + K @ y  # x = x + K y
    I_KH = np.eye(DIM_X) - K @ H
    P = symmetrize(I_KH @ P @ I_KH.T + K @ R @ K.T)  # P = (I - K H) P (I - K H)' + K R K'
    return x, P, True, nis


@dataclass(frozen=True)
class Measurement:
    """One sensor's position measurement of one object.

    Fields:
        t: timestamp [s].
        sensor: sensor name ("radar", "lidar", "camera_left", ...).
        z: measured position [x, y] in the tracking frame [m], shape (2,).
        R: noise covariance the tracker should assume for it [m^2], shape (2, 2), SPD.
        object_id: which object it measures (association is given, not estimated).
    """

    t: float
    sensor: str
    z: np.ndarray
    R: np.ndarray
    object_id: int = 0

    def __post_init__(self) -> None:
        if not np.isfinite(self.t):
            raise ValueError(f"t must be a finite time [s], got {self.t}")
        object.__setattr__(
            self, "z", as_vector(self.z, f"z of the {self.sensor} measurement at t={self.t}", 2)
        )
        object.__setattr__(
            self, "R", as_covariance(self.R, f"R of the {self.sensor} measurement at t={self.t}", 2)
        )


class CVTracker:
    """Constant-velocity Kalman tracker of one object (filterpy KalmanFilter inside).

    Args:
        x0: initial state (4,) [m, m, m/s, m/s].
        P0: initial covariance (4, 4), SPD.
        t0: time of x0 [s].
        q: acceleration noise power spectral density per axis [m^2/s^3].
        gate_prob: chi-square gate probability for updates; None accepts every measurement.

    Attributes:
        kf: the filterpy KalmanFilter (x as a (4, 1) column).
        t: time of the current estimate [s].
    """

    def __init__(self, x0, P0, t0: float = 0.0, q: float = DEFAULT_Q, gate_prob: float | None = None) -> None:
        _check_q(q)
        if gate_prob is not None:
            gate_threshold(2, gate_prob)  # validates gate_prob
        self.q = float(q)
        self.gate_prob = gate_prob
        self.t = float(t0)
        self.kf = KalmanFilter(dim_x=DIM_X, dim_z=2)
        self.kf.x = as_vector(x0, "x0", DIM_X).reshape(DIM_X, 1)
        self.kf.P = as_covariance(P0, "P0", DIM_X)
        self.kf.H = H_POSITION.copy()

    @classmethod
    def from_measurement(
        cls,
        m: Measurement,
        q: float = DEFAULT_Q,
        gate_prob: float | None = None,
        velocity_std: float = DEFAULT_VELOCITY_STD,
    ) -> CVTracker:
        """Start a track at a first measurement: position z with covariance R, velocity 0 +- velocity_std [m/s]."""
        if not velocity_std > 0:
            raise ValueError(f"velocity_std must be > 0 m/s, got {velocity_std}")
        x0 = np.concatenate([m.z, np.zeros(2)])
        P0 = np.block([[m.R, np.zeros((2, 2))], [np.zeros((2, 2)), velocity_std**2 * np.eye(2)]])
        return cls(x0, P0, t0=m.t, q=q, gate_prob=gate_prob)

    @property
    def x(self) -> np.ndarray:
        """Current state (4,) [m, m, m/s, m/s]."""
        return self.kf.x[:, 0].copy()

    @property
    def P(self) -> np.ndarray:
        """Current covariance (4, 4)."""
        return symmetrize(self.kf.P)

    def predict(self, t: float) -> None:
        """Predict the state to time t [s] >= the current time (no retrodiction)."""
        dt = float(t) - self.t
        if dt < 0:
            raise ValueError(
                f"t={t} s is before the track's time {self.t} s: out-of-sequence measurements are not supported"
            )
        if dt > 0:
            F, Q = cv_model(dt, self.q)
            self.kf.predict(F=F, Q=Q)  # x = F x ; P = F P F' + Q
            self.t = float(t)

    def update(self, z, R) -> tuple[bool, float]:
        """Update with a position z (2,) [m] of covariance R (2, 2) [m^2]; returns (accepted, NIS)."""
        z = as_vector(z, "z", 2)
        R = as_covariance(R, "R", 2)
        y, S = innovation(self.kf.x[:, 0], self.kf.P, z, R, H_POSITION)  # y = z - H x ; S = H P H' + R
        nis = float(nis_of(y, S))  # NIS = y' S^-1 y
        if self.gate_prob is not None and nis > gate_threshold(2, self.gate_prob):
            return False, nis
        self.kf.update(z.reshape(2, 1), R=R, H=H_POSITION)  # K = P H' S^-1 ; x = x + K y ; Joseph P
        return True, nis

    def step(self, m: Measurement) -> tuple[bool, float]:
        """Predict to the measurement's time and update with it; returns (accepted, NIS)."""
        self.predict(m.t)
        return self.update(m.z, m.R)


@dataclass(frozen=True)
class TrackHistory:
    """A track's estimate after each measurement, in time order.

    Fields:
        object_id: the tracked object.
        t: measurement times [s], shape (N,).
        sensor: sensor name of each measurement, length N.
        x: state after each measurement [m, m, m/s, m/s], shape (N, 4).
        P: covariance after each measurement, shape (N, 4, 4).
        nis: NIS of each measurement against the prediction, shape (N,) (NaN for the measurement that
            started the track).
        accepted: whether each measurement passed the gate, bool shape (N,).
    """

    object_id: int
    t: np.ndarray
    sensor: tuple[str, ...]
    x: np.ndarray
    P: np.ndarray
    nis: np.ndarray
    accepted: np.ndarray


def run_cv_tracker(
    measurements: Iterable[Measurement],
    q: float = DEFAULT_Q,
    gate_prob: float | None = None,
    x0=None,
    P0=None,
    t0: float | None = None,
    velocity_std: float = DEFAULT_VELOCITY_STD,
) -> TrackHistory:
    """Run one object's constant-velocity tracker over timestamped measurements from several sensors.

    Measurements are processed in time order (stable: simultaneous ones in the given order), each a
    prediction to its time and an update with its own R. The stateless twin of `CVTracker`.

    Args:
        measurements: Measurement records of one object (any sensors, any order).
        q: acceleration noise power spectral density [m^2/s^3].
        gate_prob: chi-square gate probability; None fuses everything.
        x0, P0: initial state (4,) and covariance (4, 4); if None the track starts at the first
            measurement (`CVTracker.from_measurement`, velocity 0 +- velocity_std).
        t0: time of x0 [s]; defaults to the first measurement's time.
        velocity_std: prior velocity std when starting from a measurement [m/s].

    Returns:
        TrackHistory with one row per measurement.
    """
    ms = sorted(measurements, key=lambda m: m.t)
    if not ms:
        raise ValueError("measurements is empty: nothing to track")
    ids = {m.object_id for m in ms}
    if len(ids) > 1:
        raise ValueError(f"measurements mix objects {sorted(ids)}: use run_cv_trackers")
    if (x0 is None) != (P0 is None):
        raise ValueError("x0 and P0 must be given together (or neither, to start at the first measurement)")
    rows_x, rows_P, nis, accepted = [], [], [], []
    if x0 is None:
        tracker = CVTracker.from_measurement(ms[0], q=q, gate_prob=gate_prob, velocity_std=velocity_std)
        rows_x.append(tracker.x)
        rows_P.append(tracker.P)
        nis.append(np.nan)
        accepted.append(True)
        rest = ms[1:]
    else:
        tracker = CVTracker(x0, P0, t0=ms[0].t if t0 is None else t0, q=q, gate_prob=gate_prob)
        rest = ms
    for m in rest:
        ok, v = tracker.step(m)
        rows_x.append(tracker.x)
        rows_P.append(tracker.P)
        nis.append(v)
        accepted.append(ok)
    return TrackHistory(
        object_id=ms[0].object_id,
        t=np.array([m.t for m in ms]),
        sensor=tuple(m.sensor for m in ms),
        x=np.array(rows_x),
        P=np.array(rows_P),
        nis=np.array(nis),
        accepted=np.array(accepted, dtype=bool),
    )


def run_cv_trackers(measurements: Iterable[Measurement], **kwargs) -> dict[int, TrackHistory]:
    """`run_cv_tracker` for every object_id in the measurements; keyword arguments are passed on."""
    by_object: dict[int, list[Measurement]] = {}
    for m in measurements:
        by_object.setdefault(m.object_id, []).append(m)
    return {oid: run_cv_tracker(ms, **kwargs) for oid, ms in sorted(by_object.items())}


def simulate_cv_truth(rng: np.random.Generator, x0, times: Sequence[float], q: float) -> np.ndarray:
    """Draw a trajectory of the constant-velocity model itself (for tests and notebooks).

    Args:
        rng: the run's random generator.
        x0: state at times[0] (4,) [m, m, m/s, m/s].
        times: non-decreasing times [s], shape (T,).
        q: acceleration noise power spectral density [m^2/s^3].

    Returns:
        states (T, 4): x_k = F(dt_k) x_k-1 + w_k, w_k ~ N(0, Q(dt_k)), exactly the tracker's model.
    """
    t = np.asarray(times, dtype=float)
    if t.ndim != 1 or t.size == 0 or np.any(np.diff(t) < 0):
        raise ValueError("times must be a non-empty, non-decreasing 1-D sequence [s]")
    out = np.empty((t.size, DIM_X))
    out[0] = as_vector(x0, "x0", DIM_X)
    for k in range(1, t.size):
        F, Q = cv_model(t[k] - t[k - 1], q)
        w = _gaussian(rng, Q)
        out[k] = F @ out[k - 1] + w  # x_k = F x_k-1 + w_k
    return out


def _gaussian(rng: np.random.Generator, C: np.ndarray) -> np.ndarray:
    """One draw of N(0, C) for a PSD C (zero for C = 0, i.e. dt = 0)."""
    w, V = np.linalg.eigh(C)
    return V @ (np.sqrt(np.clip(w, 0.0, None)) * rng.standard_normal(C.shape[0]))


def _check_q(q: float) -> None:
    if not np.isfinite(q) or q < 0:
        raise ValueError(f"q must be a finite spectral density >= 0 m^2/s^3, got {q}")
