"""The true error of a WLS fusion whose assumed noise covariances are wrong (HydraFusion Sec. 1.1).

The estimator is built from assumed covariances R_hat_i; the sensors actually have noise
v_i ~ (b_i, R_i) (mean b_i, the bias; covariance R_i), independent across sensors. Eq. 5 is linear
in the measurements, y_hat = sum_i K_i z_i with the WLS gains

    P_hat = [sum_i H_i' R_hat_i^-1 H_i]^-1
    K_i   = P_hat H_i' R_hat_i^-1

and sum_i K_i H_i = I, so the error y_hat - x = sum_i K_i v_i whatever the state. Hence

    mean error   m      = sum_i K_i b_i
    covariance   P_true = sum_i K_i R_i K_i'
    MSE          E|y_hat - x|^2 = trace(P_true) + |m|^2

With R_hat_i = R_i and b_i = 0, P_true = P_hat and the fusion of more sensors never hurts. An
overconfident sensor (R_hat_i much smaller than R_i, a camera behind raindrops) gets a large gain
and drags P_true above the error of a subset that leaves it out. In one dimension with two sensors
of variance r1, r2 (assumed r1_hat, r2_hat):  var = w^2 r1 + (1 - w)^2 r2,  w = r2_hat / (r1_hat + r2_hat).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fusion.estimation._linalg import (
    NotObservableError,
    as_covariance,
    as_vector,
    check_lists,
    sensor_models,
    solve_spd,
    spd_inverse,
    symmetrize,
)


@dataclass(frozen=True)
class FusedError:
    """What a WLS fusion believes about its error and what its error really is.

    Fields:
        P_assumed: covariance the estimator reports, [sum H_i' R_hat_i^-1 H_i]^-1, shape (n, n).
        P_true: true error covariance sum K_i R_i K_i', shape (n, n).
        bias: true mean error sum K_i b_i, shape (n,).
        mse: true mean squared error trace(P_true) + |bias|^2 (square of the state's unit).
    """

    P_assumed: np.ndarray
    P_true: np.ndarray
    bias: np.ndarray
    mse: float


def wls_gains(
    H_list: Sequence, R_list: Sequence, R_name: str = "R_list"
) -> tuple[list[np.ndarray], np.ndarray]:
    """WLS gains K_i = P H_i' R_i^-1 (each (n, m_i)) and P = [sum H_i' R_i^-1 H_i]^-1, shape (n, n).

    `wls` returns sum_i K_i z_i; the gains are what makes the error analysis linear. R_name names
    the R list in error messages.
    """
    Hs, Rs, n = sensor_models(H_list, R_list, R_name)
    Y = np.zeros((n, n))
    RiHs = []
    for H, R in zip(Hs, Rs, strict=True):
        RiH = solve_spd(R, H)  # R^-1 H
        Y += H.T @ RiH  # Y = sum H' R^-1 H
        RiHs.append(RiH)
    P = spd_inverse(Y, "the information matrix sum_i H_i' R_i^-1 H_i")  # P = Y^-1
    K_list = [P @ RiH.T for RiH in RiHs]  # K_i = P H_i' R_i^-1
    return K_list, P


def fused_error(
    H_list: Sequence,
    R_assumed_list: Sequence,
    R_true_list: Sequence,
    bias_list: Sequence | None = None,
) -> FusedError:
    """True error statistics of the Eq. 5 fusion built from assumed covariances.

    Args:
        H_list: per sensor, H_i of shape (m_i, n).
        R_assumed_list: per sensor, the R_hat_i the estimator uses, (m_i, m_i) SPD.
        R_true_list: per sensor, the true noise covariance R_i, (m_i, m_i) symmetric PSD.
        bias_list: per sensor, the true noise mean b_i of shape (m_i,); None means unbiased.

    Returns:
        FusedError with P_assumed, P_true = sum K_i R_i K_i', bias = sum K_i b_i and the MSE.
    """
    K_list, P_hat = wls_gains(H_list, R_assumed_list, "R_assumed_list")
    check_lists(H_list=H_list, R_true_list=R_true_list, bias_list=bias_list)
    n = P_hat.shape[0]
    P_true = np.zeros((n, n))
    bias = np.zeros(n)
    for i, K in enumerate(K_list):
        m = K.shape[1]
        R_true = _as_psd(R_true_list[i], f"R_true_list[{i}]", m)
        P_true += K @ R_true @ K.T  # P_true = sum K_i R_i K_i'
        if bias_list is not None:
            bias += K @ as_vector(bias_list[i], f"bias_list[{i}]", m)  # m = sum K_i b_i
    P_true = symmetrize(P_true)
    mse = float(np.trace(P_true) + bias @ bias)  # MSE = trace(P_true) + |m|^2
    return FusedError(P_assumed=P_hat, P_true=P_true, bias=bias, mse=mse)


def scalar_fused_variance(r1_assumed: float, r2_assumed: float, r1_true: float, r2_true: float) -> float:
    """True variance of fusing two scalar measurements of one quantity with assumed variances.

    var = w^2 r1 + (1 - w)^2 r2 with w = r2_hat / (r1_hat + r2_hat), the weight Eq. 5 gives sensor 1.
    """
    for name, v in (("r1_assumed", r1_assumed), ("r2_assumed", r2_assumed)):
        if not v > 0:
            raise ValueError(f"{name} must be > 0, got {v}")
    for name, v in (("r1_true", r1_true), ("r2_true", r2_true)):
        if not v >= 0:
            raise ValueError(f"{name} must be >= 0, got {v}")
    w = r2_assumed / (r1_assumed + r2_assumed)  # w = (1/r1_hat) / (1/r1_hat + 1/r2_hat)
    return w**2 * r1_true + (1.0 - w) ** 2 * r2_true  # var = w^2 r1 + (1-w)^2 r2


def scalar_crossover(r1_true: float, r1_assumed: float, r2_assumed: float) -> float:
    """The true variance of sensor 2 above which fusing it makes the estimate worse than sensor 1
    alone, when the fusion weighs it by its assumed variance r2_hat: solve w^2 r1 + (1 - w)^2 r2 = r1
    for r2 (w = r2_hat / (r1_hat + r2_hat), sensor 1's weight):

        r2* = r1 (1 - w^2) / (1 - w)^2 = r1 (1 + w) / (1 - w)

    and with sensor 1's variance known (r1_hat = r1): r2* = r1 + 2 r2_hat. A sensor whose true noise
    grows with the weather (its nominal r2_hat does not) stops paying at the severity where its
    variance passes r2*: the covariance argument's crossover. With r2 known too (r2_hat = r2) there is
    none: r2* = r1 + 2 r2 > r2 always."""
    for name, v in (("r1_assumed", r1_assumed), ("r2_assumed", r2_assumed)):
        if not v > 0:
            raise ValueError(f"{name} must be > 0, got {v}")
    if not r1_true >= 0:
        raise ValueError(f"r1_true must be >= 0, got {r1_true}")
    w = r2_assumed / (r1_assumed + r2_assumed)
    return r1_true * (1.0 + w) / (1.0 - w)  # r2* = r1 (1 + w) / (1 - w)


def subset_errors(
    H_list: Sequence,
    R_assumed_list: Sequence,
    R_true_list: Sequence,
    bias_list: Sequence | None = None,
) -> dict[tuple[int, ...], FusedError]:
    """`fused_error` of every non-empty subset of sensors that observes the whole state.

    Returns a dict from the subset's sensor indices (sorted tuple) to its FusedError; subsets whose
    information matrix is singular are left out. 2^N - 1 subsets: meant for a handful of sensors.
    """
    n_sensors = check_lists(H_list=H_list, R_assumed_list=R_assumed_list)
    if n_sensors > 12:
        raise ValueError(f"H_list has {n_sensors} sensors: subset_errors enumerates 2^N subsets, at most 12")
    # The full set first: it validates every entry under its own index, and if it does not
    # observe the state no subset does (a subset's information is never larger).
    full = fused_error(H_list, R_assumed_list, R_true_list, bias_list)
    out: dict[tuple[int, ...], FusedError] = {}
    for k in range(1, n_sensors):
        for subset in itertools.combinations(range(n_sensors), k):
            try:
                out[subset] = fused_error(
                    [H_list[i] for i in subset],
                    [R_assumed_list[i] for i in subset],
                    [R_true_list[i] for i in subset],
                    None if bias_list is None else [bias_list[i] for i in subset],
                )
            except NotObservableError:
                continue
    out[tuple(range(n_sensors))] = full
    return out


def best_subset(
    H_list: Sequence,
    R_assumed_list: Sequence,
    R_true_list: Sequence,
    bias_list: Sequence | None = None,
) -> tuple[tuple[int, ...], FusedError]:
    """The subset of sensors whose Eq. 5 fusion has the smallest true MSE, and its FusedError.

    Ties go to the smaller subset (fewer sensors, cheaper), then to the lower indices.
    """
    errors = subset_errors(H_list, R_assumed_list, R_true_list, bias_list)
    subset = min(errors, key=lambda s: (errors[s].mse, len(s), s))
    return subset, errors[subset]


def _as_psd(C, name: str, dim: int) -> np.ndarray:
    """A symmetric positive semi-definite (dim, dim) matrix (a true covariance may be singular)."""
    try:
        return as_covariance(C, name, dim)
    except ValueError as err:
        if "positive definite" not in str(err):
            raise
    m = symmetrize(np.asarray(C, dtype=float).reshape(dim, dim))
    w = np.linalg.eigvalsh(m)
    if w[0] < -1e-12 * max(abs(w[-1]), 1.0):
        raise ValueError(f"{name} must be positive semi-definite (smallest eigenvalue {w[0]:.3g})")
    return m
