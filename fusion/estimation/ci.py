"""Covariance intersection (Julier & Uhlmann 1997): fusing estimates with unknown cross-correlation.

Two estimates (x_a, P_a), (x_b, P_b) of the same state whose errors may be correlated by an
unknown amount (two trackers fed by the same sensor, a track and a map both built from the same
odometry) must not be fused as if independent: the naive (P_a^-1 + P_b^-1)^-1 can be far smaller
than the true error covariance. Covariance intersection uses a convex combination of information,

    P^-1 = w P_a^-1 + (1 - w) P_b^-1
    x    = P (w P_a^-1 x_a + (1 - w) P_b^-1 x_b)

which is consistent (P >= the true error covariance in the Loewner order) for every w in [0, 1] and
every cross-covariance, provided P_a and P_b are themselves consistent. w is chosen to minimise
trace(P) or det(P).

Two estimates: w by scipy's bounded scalar minimisation (Brent) on [0, 1], compared with the two
end points (the optimum can lie on the boundary, e.g. when one estimate is better in every
direction, and Brent never evaluates the end points).

N estimates: weights w on the simplex (w_i >= 0, sum w_i = 1) minimising trace(P) or log det(P)
with P = (sum w_i P_i^-1)^-1, by scipy SLSQP with analytic gradients
(d trace P / d w_i = -trace(P P_i^-1 P), d log det P / d w_i = -trace(P P_i^-1)), started at equal
weights and compared with every vertex (a single estimate). Both objectives are convex in w
(trace and -log det of the inverse of an affine matrix function), so the local optimum is global.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np
from scipy import optimize

from fusion.estimation._linalg import as_covariance, as_vector, symmetrize

Criterion = Literal["trace", "det"]


def ci_combine(x_list: Sequence, P_list: Sequence, weights: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """Covariance-intersection fusion with given weights (non-negative, summing to 1).

    Args:
        x_list: estimates, each shape (n,).
        P_list: their covariances, each (n, n) SPD.
        weights: one weight per estimate.

    Returns:
        x (n,), P (n, n) with P^-1 = sum w_i P_i^-1 and x = P sum w_i P_i^-1 x_i.
    """
    xs, Ps, infos = _estimates(x_list, P_list)
    w = np.asarray(weights, dtype=float)
    if w.shape != (len(xs),) or np.any(w < -1e-12) or not np.isclose(w.sum(), 1.0, atol=1e-9):
        raise ValueError(f"weights must be {len(xs)} non-negative numbers summing to 1, got {weights}")
    return _combine(xs, infos, np.clip(w, 0.0, None))


def covariance_intersection(
    x_a, P_a, x_b, P_b, criterion: Criterion = "trace"
) -> tuple[np.ndarray, np.ndarray, float]:
    """Fuse two estimates with unknown cross-correlation.

    Args:
        x_a, x_b: estimates of the same state, shape (n,).
        P_a, P_b: their covariances, (n, n) SPD.
        criterion: "trace" (minimise the mean squared error bound) or "det" (the volume of the
            uncertainty ellipsoid).

    Returns:
        x (n,), P (n, n), w: the weight of estimate a, in [0, 1].
    """
    xs, Ps, infos = _estimates([x_a, x_b], [P_a, P_b], names=("x_a", "x_b"), P_names=("P_a", "P_b"))
    cost = _cost(criterion)

    def cost_of(w: float) -> float:
        return cost(infos[0] * w + infos[1] * (1.0 - w))  # P^-1 = w P_a^-1 + (1-w) P_b^-1

    res = optimize.minimize_scalar(cost_of, bounds=(0.0, 1.0), method="bounded", options={"xatol": 1e-10})
    candidates = [0.0, 1.0, float(res.x)]
    w = min(candidates, key=cost_of)
    x, P = _combine(xs, infos, np.array([w, 1.0 - w]))
    return x, P, w


def covariance_intersection_n(
    x_list: Sequence, P_list: Sequence, criterion: Criterion = "trace"
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fuse N estimates with unknown cross-correlations (weights on the simplex, SLSQP).

    Args:
        x_list: estimates, each (n,).
        P_list: covariances, each (n, n) SPD.
        criterion: "trace" or "det" (see module docstring for the method).

    Returns:
        x (n,), P (n, n), weights (N,) non-negative summing to 1.
    """
    xs, Ps, infos = _estimates(x_list, P_list)
    N = len(xs)
    if N == 1:
        return xs[0].copy(), Ps[0].copy(), np.ones(1)
    cost = _cost(criterion)
    stacked = np.stack(infos)

    def fun(w: np.ndarray) -> tuple[float, np.ndarray]:
        Y = np.tensordot(w, stacked, axes=1)  # P^-1 = sum w_i P_i^-1
        P = np.linalg.inv(Y)
        if criterion == "trace":
            grad = -np.einsum("ij,kjl,li->k", P, stacked, P)  # d tr P / d w_k = -tr(P I_k P)
        else:
            grad = -np.einsum("ij,kji->k", P, stacked)  # d log det P / d w_k = -tr(P I_k)
        return cost(Y), grad

    res = optimize.minimize(
        fun,
        np.full(N, 1.0 / N),
        jac=True,
        method="SLSQP",
        bounds=[(0.0, 1.0)] * N,
        constraints=[{"type": "eq", "fun": lambda w: np.sum(w) - 1.0, "jac": lambda w: np.ones_like(w)}],
        options={"ftol": 1e-12, "maxiter": 200},
    )
    w_opt = np.clip(res.x, 0.0, None)
    w_opt /= w_opt.sum()
    candidates = [w_opt] + list(np.eye(N))
    w = min(candidates, key=lambda v: fun(v)[0])
    x, P = _combine(xs, infos, w)
    return x, P, w


def naive_fusion(x_list: Sequence, P_list: Sequence) -> tuple[np.ndarray, np.ndarray]:
    """Fusion that assumes independent errors: P^-1 = sum P_i^-1, x = P sum P_i^-1 x_i.

    Optimal for independent estimates, overconfident for correlated ones (the contrast CI is for).
    """
    xs, Ps, infos = _estimates(x_list, P_list)
    return _combine(xs, infos, np.ones(len(xs)))


def _estimates(x_list, P_list, names=None, P_names=None):
    if len(x_list) == 0:
        raise ValueError("x_list is empty: give at least one estimate")
    if len(P_list) != len(x_list):
        raise ValueError(f"P_list has {len(P_list)} entries but x_list has {len(x_list)}")
    names = names or [f"x_list[{i}]" for i in range(len(x_list))]
    P_names = P_names or [f"P_list[{i}]" for i in range(len(x_list))]
    n = np.asarray(x_list[0]).size
    xs = [as_vector(x, nm, n) for x, nm in zip(x_list, names, strict=True)]
    Ps = [as_covariance(P, nm, n) for P, nm in zip(P_list, P_names, strict=True)]
    infos = [symmetrize(np.linalg.inv(P)) for P in Ps]
    return xs, Ps, infos


def _combine(xs, infos, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    Y = sum(wi * Ii for wi, Ii in zip(w, infos, strict=True))  # P^-1 = sum w_i P_i^-1
    b = sum(wi * (Ii @ xi) for wi, Ii, xi in zip(w, infos, xs, strict=True))  # P^-1 x = sum w_i P_i^-1 x_i
    P = symmetrize(np.linalg.inv(Y))
    return P @ b, P


def _cost(criterion: str):
    if criterion == "trace":
        return lambda Y: float(np.trace(np.linalg.inv(Y)))  # trace P
    if criterion == "det":
        return lambda Y: -float(np.linalg.slogdet(Y)[1])  # log det P = -log det P^-1
    raise ValueError(f"criterion must be 'trace' or 'det', got {criterion!r}")
