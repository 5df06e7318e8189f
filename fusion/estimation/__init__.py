"""Multisensor estimation: the theory behind selective fusion, in filterpy's notation.

- `wls`: batch weighted least squares, HydraFusion Eq. 5 (`wls`, `WLSFusion`, `information`).
- `sequential`: the same fusion as Kalman updates of a static state (`sequential_fusion`,
  `SequentialFusion`), equal to `wls` to round-off.

Names follow the textbook: x state, P its covariance, F transition, Q process noise, H measurement
matrix, R measurement noise, y innovation, S its covariance, K gain.
"""

from fusion.estimation._linalg import NotObservableError
from fusion.estimation.sequential import SequentialFusion, sequential_fusion, static_kalman_filter
from fusion.estimation.wls import WLSFusion, information, wls

__all__ = [
    "NotObservableError",
    "SequentialFusion",
    "WLSFusion",
    "information",
    "sequential_fusion",
    "static_kalman_filter",
    "wls",
]
