"""Sequential fusion: the batch WLS of Eq. 5 computed as Kalman updates of a static state.

With a static state (F = I, Q = 0) a Kalman filter that processes the sensors one by one ends at
exactly the batch estimate of `wls`, provided it starts from exact information rather than from a
vague prior (a "huge P0" leaves a bias of order P0^-1 and loses digits to cancellation). So the
filter is initialised from the WLS solution of the shortest prefix of sensors that observes the
whole state (usually the first sensor alone), and every later sensor is a filterpy
`KalmanFilter.update` with its own H and R:

    y = z - H x
    S = H P H' + R
    K = P H' S^-1
    x = x + K y
    P = (I - K H) P (I - K H)' + K R K'     (filterpy's Joseph form)
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from filterpy.kalman import KalmanFilter

from fusion.estimation._linalg import (
    NotObservableError,
    as_covariance,
    as_matrix,
    as_vector,
    measurements,
    sensor_models,
    symmetrize,
)
from fusion.estimation.wls import WLSFusion


def static_kalman_filter(x: np.ndarray, P: np.ndarray) -> KalmanFilter:
    """A filterpy KalmanFilter for a static state: F = I, Q = 0, starting at x (n,), P (n, n)."""
    n = x.shape[0]
    kf = KalmanFilter(dim_x=n, dim_z=1)
    kf.x = x.reshape(n, 1).copy()
    kf.P = P.copy()
    kf.F = np.eye(n)  # x_k+1 = x_k
    kf.Q = np.zeros((n, n))  # no process noise: the state does not change
    return kf


class SequentialFusion:
    """Fuse sensors one at a time with filterpy's KalmanFilter; equals `wls` on the same sensors.

    Until the sensors seen so far observe the whole state, they are accumulated as information
    (`WLSFusion`); the first time the information is invertible the filter is initialised from it,
    and from then on each sensor is one Kalman update.

    Args:
        dim_x: number of state components n.

    Attributes:
        kf: the filterpy KalmanFilter (None until the state is observable).
        count: number of sensors fused so far.
    """

    def __init__(self, dim_x: int) -> None:
        self._prefix = WLSFusion(dim_x)
        self.dim_x = self._prefix.dim_x
        self.kf: KalmanFilter | None = None
        self.count = 0

    def update(self, z, R, H) -> None:
        """Fuse one sensor: z (m,), R (m, m) SPD, H (m, n)."""
        if self.kf is None:
            self._prefix.update(z, R, H)
            self.count += 1
            try:
                x, P = self._prefix.estimate()
            except NotObservableError:
                return
            self.kf = static_kalman_filter(x, P)
            return
        H = as_matrix(H, "H", (None, self.dim_x))
        R = as_covariance(R, "R", H.shape[0])
        z = as_vector(z, "z", H.shape[0])
        self.kf.predict()  # x = F x = x ;  P = F P F' + Q = P
        self.kf.update(z.reshape(-1, 1), R=R, H=H)  # y, S, K, x, P as in the module docstring
        self.count += 1

    @property
    def x(self) -> np.ndarray:
        """Current estimate, shape (n,); NotObservableError before the state is observable."""
        if self.kf is None:
            return self._prefix.x
        return self.kf.x[:, 0].copy()

    @property
    def P(self) -> np.ndarray:
        """Current covariance, shape (n, n); NotObservableError before the state is observable."""
        if self.kf is None:
            return self._prefix.P
        return symmetrize(self.kf.P)


def sequential_fusion(H_list: Sequence, R_list: Sequence, z_list: Sequence) -> tuple[np.ndarray, np.ndarray]:
    """Stateless twin of `SequentialFusion`: Kalman updates of a static state, one per sensor.

    Same arguments, result and errors as `wls` (single measurement vectors only, z_i of shape
    (m_i,)); the result equals `wls` to round-off.
    """
    Hs, Rs, n = sensor_models(H_list, R_list)
    zs, batch = measurements(z_list, Hs)
    if batch is not None:
        raise ValueError("z_list: sequential_fusion takes one measurement vector (m_i,) per sensor")
    fusion = SequentialFusion(n)
    for z, R, H in zip(zs, Rs, Hs, strict=True):
        fusion.update(z, R, H)
    return fusion.x, fusion.P
