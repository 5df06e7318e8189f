"""Batch weighted least squares: the minimum-variance unbiased fusion of HydraFusion Eq. 5.

Measurement model of sensor i (HydraFusion Eq. 1, with the paper's measurement x written z and its
parameter y written x, as in filterpy):

    z_i = H_i x + v_i,   E[v_i] = 0,   E[v_i v_i'] = R_i,   v_i independent across sensors.

Eq. 5 fuses n sensors in one batch:

    P     = [sum_i H_i' R_i^-1 H_i]^-1          (the fused error covariance)
    y_hat = P sum_i H_i' R_i^-1 z_i

It is Eq. 4 applied to the stacked measurement [z_1; ...; z_n] with block-diagonal R. When every
R_i is the true noise covariance, y_hat is the best linear unbiased estimate and P its true error
covariance; when an R_i is wrong, P is only what the estimator believes (see `mismatch`).

Units: x, z, H, R in the caller's units (R in the square of z's unit; P in the square of x's).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from fusion.estimation._linalg import (
    as_covariance,
    as_matrix,
    as_vector,
    measurements,
    sensor_models,
    solve_spd,
    spd_inverse,
)


def information(H_list: Sequence, R_list: Sequence) -> np.ndarray:
    """The fused information matrix Y = sum_i H_i' R_i^-1 H_i, shape (n, n).

    Args:
        H_list: per sensor, H_i of shape (m_i, n).
        R_list: per sensor, R_i of shape (m_i, m_i), symmetric positive definite (a scalar if m_i = 1).
    """
    Hs, Rs, n = sensor_models(H_list, R_list)
    Y = np.zeros((n, n))
    for H, R in zip(Hs, Rs, strict=True):
        Y += H.T @ solve_spd(R, H)  # Y += H' R^-1 H
    return Y


def wls(H_list: Sequence, R_list: Sequence, z_list: Sequence) -> tuple[np.ndarray, np.ndarray]:
    """Fuse n sensors by HydraFusion Eq. 5 (batch WLS / minimum-variance unbiased estimate).

    Args:
        H_list: per sensor, measurement matrix H_i of shape (m_i, n).
        R_list: per sensor, noise covariance R_i of shape (m_i, m_i), symmetric positive definite.
        z_list: per sensor, measurement z_i of shape (m_i,) (or (m_i, 1)); or, to fuse K independent
            measurement sets at once (Monte Carlo), every z_i of shape (K, m_i).

    Returns:
        y_hat: fused estimate, shape (n,) (or (K, n) for batched z).
        P: fused error covariance [sum H_i' R_i^-1 H_i]^-1, shape (n, n); the true error covariance
            only if every R_i is the true one.

    Raises:
        ValueError: a list is empty, the lists differ in length, or an entry has the wrong shape or
            a non-SPD R (the message names the entry, e.g. ``R_list[2]``).
        NotObservableError (a ValueError): the stacked H does not have full column rank.
    """
    Hs, Rs, n = sensor_models(H_list, R_list)
    zs, _ = measurements(z_list, Hs)
    Y = np.zeros((n, n))
    b = np.zeros(zs[0].shape[:-1] + (n,))
    for H, R, z in zip(Hs, Rs, zs, strict=True):
        RiH = solve_spd(R, H)  # R^-1 H
        Y += H.T @ RiH  # Y = sum H' R^-1 H
        b += z @ RiH  # b = sum H' R^-1 z   (written z' R^-1 H so rows of a batch broadcast)
    P = spd_inverse(Y, "the information matrix sum_i H_i' R_i^-1 H_i")  # P = Y^-1
    y_hat = b @ P  # y_hat = P b   (P symmetric)
    return y_hat, P


class WLSFusion:
    """Accumulating form of `wls`: add sensors one at a time, read the Eq. 5 estimate at any point.

    Keeps the information matrix Y = sum H_i' R_i^-1 H_i and vector b = sum H_i' R_i^-1 z_i, so the
    order of the updates does not matter and no prior is needed.

    Args:
        dim_x: number of state components n.

    Attributes:
        Y: information matrix, shape (n, n).
        b: information vector, shape (n,).
        count: number of sensors fused so far.
    """

    def __init__(self, dim_x: int) -> None:
        if int(dim_x) != dim_x or dim_x < 1:
            raise ValueError(f"dim_x must be a positive integer, got {dim_x}")
        self.dim_x = int(dim_x)
        self.Y = np.zeros((self.dim_x, self.dim_x))
        self.b = np.zeros(self.dim_x)
        self.count = 0

    def update(self, z, R, H) -> None:
        """Add one sensor: z (m,), R (m, m) SPD, H (m, n). Argument order follows filterpy."""
        H = as_matrix(H, "H", (None, self.dim_x))
        R = as_covariance(R, "R", H.shape[0])
        z = as_vector(z, "z", H.shape[0])
        RiH = solve_spd(R, H)  # R^-1 H
        self.Y += H.T @ RiH  # Y = Y + H' R^-1 H
        self.b += z @ RiH  # b = b + H' R^-1 z
        self.count += 1

    @property
    def P(self) -> np.ndarray:
        """Fused covariance Y^-1, shape (n, n); NotObservableError while Y is singular."""
        return spd_inverse(self.Y, f"the information matrix of the {self.count} sensors fused so far")

    @property
    def x(self) -> np.ndarray:
        """Fused estimate P b, shape (n,)."""
        return self.P @ self.b

    def estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """(y_hat, P) as `wls` returns them for the sensors added so far."""
        P = self.P
        return P @ self.b, P
