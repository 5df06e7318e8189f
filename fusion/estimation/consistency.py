"""Filter consistency tests (Bar-Shalom, Li, Kirubarajan 2001, ch. 5.4).

An estimator is consistent when its errors are as large as its covariance says, no larger and no
smaller. With the estimation error e = x_hat - x (n_x components) and covariance P, and the
innovation y = z - H x_prior with covariance S = H P_prior H' + R (n_z components):

    NEES  eps   = e' P^-1 e      ~ chi2(n_x)   if the filter is consistent (Gaussian errors)
    NIS   eps_y = y' S^-1 y      ~ chi2(n_z)

One run gives one draw; the two-sided 95 % interval of chi2(n) holds it 95 % of the time. Over M
independent Monte-Carlo runs M * mean(NEES) ~ chi2(M n_x), so the average has the much narrower
interval [chi2.ppf(0.025, M n) / M, chi2.ppf(0.975, M n) / M] around n: an average above it means
the filter is overconfident (P too small), below it underconfident (P too large).

NIS needs no ground truth, so it is the test a deployed filter can run on itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from fusion.estimation._linalg import check_prob


def _normalized_squared(e, P, e_name: str, P_name: str) -> np.ndarray:
    e = np.asarray(e, dtype=float)
    P = np.asarray(P, dtype=float)
    if e.ndim < 1:
        raise ValueError(f"{e_name} must have a last axis of state components, got a scalar")
    n = e.shape[-1]
    if P.ndim < 2 or P.shape[-2:] != (n, n):
        raise ValueError(
            f"{P_name} must have shape (..., {n}, {n}) to match {e_name} {e.shape}, got {P.shape}"
        )
    try:
        batch = np.broadcast_shapes(e.shape[:-1], P.shape[:-2])
    except ValueError:
        raise ValueError(f"{P_name} {P.shape} does not broadcast against {e_name} {e.shape}") from None
    try:
        L = np.linalg.cholesky(0.5 * (P + np.swapaxes(P, -1, -2)))  # P = L L'
    except np.linalg.LinAlgError:
        raise ValueError(f"{P_name} must be positive definite") from None
    L = np.broadcast_to(L, batch + (n, n))
    e = np.broadcast_to(e, batch + (n,))
    u = np.linalg.solve(L, e[..., None])[..., 0]  # u = L^-1 e
    return np.sum(u**2, axis=-1)  # e' P^-1 e = |L^-1 e|^2


def nees(e, P) -> np.ndarray:
    """Normalised estimation error squared e' P^-1 e.

    Args:
        e: estimation errors x_hat - x, shape (..., n_x).
        P: the filter's covariances, shape (..., n_x, n_x) broadcastable against e (one (n_x, n_x)
            matrix for all errors is fine); symmetric positive definite.

    Returns:
        NEES values, shape e.shape[:-1] (a 0-d array for one error vector).
    """
    return _normalized_squared(e, P, "e", "P")


def nis(y, S) -> np.ndarray:
    """Normalised innovation squared y' S^-1 y; y (..., n_z), S (..., n_z, n_z). See `nees`."""
    return _normalized_squared(y, S, "y", "S")


def chi2_interval(dof: int, prob: float = 0.95) -> tuple[float, float]:
    """Two-sided interval holding a chi2(dof) draw with probability `prob`: one run's NEES/NIS bounds."""
    return mean_chi2_interval(dof, 1, prob)


def mean_chi2_interval(dof: int, n_runs: int, prob: float = 0.95) -> tuple[float, float]:
    """Two-sided `prob` interval of the average of `n_runs` independent chi2(dof) draws.

    M * average ~ chi2(M dof), so the bounds are chi2.ppf((1 -+ prob) / 2, M dof) / M.
    """
    if int(dof) != dof or dof < 1:
        raise ValueError(f"dof must be a positive integer, got {dof}")
    if int(n_runs) != n_runs or n_runs < 1:
        raise ValueError(f"n_runs must be a positive integer, got {n_runs}")
    alpha = 1.0 - check_prob(prob)
    k = int(n_runs) * int(dof)
    lo = stats.chi2.ppf(alpha / 2.0, k) / n_runs  # r1 = chi2^-1(alpha/2; M n) / M
    hi = stats.chi2.ppf(1.0 - alpha / 2.0, k) / n_runs  # r2 = chi2^-1(1 - alpha/2; M n) / M
    return float(lo), float(hi)


@dataclass(frozen=True)
class ConsistencyReport:
    """Outcome of a chi-square consistency test over Monte-Carlo runs.

    Fields:
        dof: degrees of freedom of one value (n_x for NEES, n_z for NIS).
        n_runs: number of runs M averaged at each step.
        mean: run-averaged value per step, shape (T,) (T = 1 for a single quantity per run).
        lower, upper: two-sided `prob` bounds of the M-run average.
        fraction_inside: share of the T steps whose average lies inside [lower, upper].
        min_fraction: share required for the verdict "consistent".
        consistent: fraction_inside >= min_fraction.
        verdict: "consistent", "overconfident" (averages too high: P smaller than the errors) or
            "underconfident" (averages too low).
    """

    dof: int
    n_runs: int
    mean: np.ndarray
    lower: float
    upper: float
    fraction_inside: float
    min_fraction: float
    consistent: bool
    verdict: str


def consistency_report(
    values, dof: int, prob: float = 0.95, min_fraction: float | None = None
) -> ConsistencyReport:
    """Chi-square test of NEES or NIS values from M independent Monte-Carlo runs.

    Args:
        values: NEES or NIS values, shape (M,) (one per run) or (M, T) (runs x time steps).
        dof: degrees of freedom of one value (n_x for NEES, n_z for NIS).
        prob: coverage of the two-sided bounds (0.95 in Bar-Shalom's examples).
        min_fraction: share of the T run-averages that must lie inside the bounds. Default: the
            expected share `prob` less three binomial standard deviations, prob - 3 sqrt(prob (1 -
            prob) / T), which for T = 1 just asks that the single average be inside. The steps of one
            run are correlated, so this is a rule of thumb, not an exact test, for T > 1.

    Returns:
        ConsistencyReport.
    """
    v = np.asarray(values, dtype=float)
    if v.ndim == 1:
        v = v[:, None]
    if v.ndim != 2 or v.shape[0] < 1 or v.shape[1] < 1:
        raise ValueError(f"values must have shape (M,) or (M, T), got {np.shape(values)}")
    if not np.all(np.isfinite(v)) or np.any(v < 0):
        raise ValueError("values must be finite and non-negative (NEES and NIS are squared norms)")
    M, T = v.shape
    lo, hi = mean_chi2_interval(dof, M, prob)
    mean = v.mean(axis=0)
    inside = (mean >= lo) & (mean <= hi)
    fraction = float(inside.mean())
    if min_fraction is None:
        min_fraction = prob - 3.0 * np.sqrt(prob * (1.0 - prob) / T)
    elif not 0.0 <= min_fraction <= 1.0:
        raise ValueError(f"min_fraction must be in [0, 1], got {min_fraction}")
    consistent = bool(fraction >= min_fraction)
    if consistent:
        verdict = "consistent"
    else:
        verdict = "overconfident" if np.sum(mean > hi) >= np.sum(mean < lo) else "underconfident"
    return ConsistencyReport(
        dof=int(dof),
        n_runs=M,
        mean=mean,
        lower=lo,
        upper=hi,
        fraction_inside=fraction,
        min_fraction=float(min_fraction),
        consistent=consistent,
        verdict=verdict,
    )


def is_consistent(values, dof: int, prob: float = 0.95) -> bool:
    """Whether NEES/NIS values of shape (M,) or (M, T) pass `consistency_report`'s test."""
    return consistency_report(values, dof, prob).consistent
