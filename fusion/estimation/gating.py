"""Chi-square innovation gating: the classical form of selective fusion.

A measurement z (m components) of a state with estimate x, covariance P, has the innovation

    y = z - H x,    S = H P H' + R

and, if x, P and R are honest, NIS = y' S^-1 y ~ chi2(m). The gate keeps z when
NIS <= chi2.ppf(prob, m); a measurement far outside what the estimate and the sensor's R allow
(a camera blinded by glare, a lidar return from fog) is dropped instead of dragging the estimate.
With prob = 0.99 an honest measurement is wrongly dropped 1 % of the time.

Two forms:
- `gated_update`: there is a prior (a track's prediction); each measurement is tested against it
  and the accepted ones are fused by Kalman updates.
- `gated_wls`: no prior (static fusion, Eq. 5); each sensor is tested against the WLS fusion of the
  others (leave-one-out) and, RAIM-style, a sensor beyond its gate is excluded only when its
  exclusion is the one that makes the others agree.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy import stats

from fusion.estimation._linalg import (
    NotObservableError,
    as_covariance,
    as_vector,
    check_prob,
    measurements,
    sensor_models,
    symmetrize,
)
from fusion.estimation.consistency import nis as nis_of
from fusion.estimation.sequential import static_kalman_filter
from fusion.estimation.wls import wls


def gate_threshold(dim_z: int, prob: float = 0.99) -> float:
    """Gate on the NIS of a dim_z-component measurement: chi2.ppf(prob, dim_z)."""
    if int(dim_z) != dim_z or dim_z < 1:
        raise ValueError(f"dim_z must be a positive integer, got {dim_z}")
    return float(stats.chi2.ppf(check_prob(prob), int(dim_z)))


def innovation(
    x: np.ndarray, P: np.ndarray, z: np.ndarray, R: np.ndarray, H: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Innovation y (m,) and its covariance S (m, m) of measurement z against estimate x, P.

    Arrays must already be validated: x (n,), P (n, n), z (m,), R (m, m), H (m, n).
    """
    y = z - H @ x  # y = z - H x
    S = symmetrize(H @ P @ H.T + R)  # S = H P H' + R
    return y, S


@dataclass(frozen=True)
class GatedFusion:
    """Result of a gated fusion.

    Fields:
        x: fused estimate from the kept measurements, shape (n,).
        P: its covariance, shape (n, n).
        kept: which measurements were fused, bool shape (N,) in input order.
        nis: each measurement's NIS in the test that decided it, shape (N,) (NaN if it could not be
            tested, see `gated_wls`).
        threshold: each measurement's gate chi2.ppf(prob, m_i), shape (N,).
    """

    x: np.ndarray
    P: np.ndarray
    kept: np.ndarray
    nis: np.ndarray
    threshold: np.ndarray


def gated_update(
    x,
    P,
    H_list: Sequence,
    R_list: Sequence,
    z_list: Sequence,
    prob: float = 0.99,
    reference: Literal["prior", "running"] = "prior",
) -> GatedFusion:
    """Gate each measurement against a prior, then fuse the accepted ones by Kalman updates.

    Args:
        x: prior estimate, shape (n,).
        P: prior covariance, shape (n, n), SPD.
        H_list, R_list, z_list: per sensor H_i (m_i, n), R_i (m_i, m_i) SPD, z_i (m_i,).
        prob: gate probability; z_i is kept when NIS_i <= chi2.ppf(prob, m_i).
        reference: "prior" tests every measurement against the prior (order does not matter);
            "running" tests each against the estimate updated with the measurements kept before it
            (sharper, but depends on the order).

    Returns:
        GatedFusion; with nothing rejected, x and P equal the Kalman update with every sensor.
    """
    Hs, Rs, n = sensor_models(H_list, R_list)
    zs, batch = measurements(z_list, Hs)
    if batch is not None:
        raise ValueError("z_list: gated_update takes one measurement vector (m_i,) per sensor")
    x = as_vector(x, "x", n)
    P = as_covariance(P, "P", n)
    if reference not in ("prior", "running"):
        raise ValueError(f"reference must be 'prior' or 'running', got {reference!r}")
    thresholds = np.array([gate_threshold(H.shape[0], prob) for H in Hs])
    nis = np.full(len(Hs), np.nan)
    kept = np.zeros(len(Hs), dtype=bool)
    kf = static_kalman_filter(x, P)
    for i, (H, R, z) in enumerate(zip(Hs, Rs, zs, strict=True)):
        ref_x, ref_P = (x, P) if reference == "prior" else (kf.x[:, 0], kf.P)
        y, S = innovation(ref_x, ref_P, z, R, H)  # y = z - H x ; S = H P H' + R
        nis[i] = nis_of(y, S)  # NIS = y' S^-1 y
        kept[i] = nis[i] <= thresholds[i]
        if kept[i]:
            kf.update(z.reshape(-1, 1), R=R, H=H)
    return GatedFusion(x=kf.x[:, 0].copy(), P=symmetrize(kf.P), kept=kept, nis=nis, threshold=thresholds)


def gated_wls(H_list: Sequence, R_list: Sequence, z_list: Sequence, prob: float = 0.99) -> GatedFusion:
    """Eq. 5 fusion without a prior, excluding sensors that disagree with the others.

    Fault detection and exclusion in the manner of RAIM (receiver autonomous integrity monitoring):

    1. Detection: each kept sensor i is tested against the WLS fusion (x_-i, P_-i) of the other kept
       sensors, y = z_i - H_i x_-i, S = H_i P_-i H_i' + R_i (independent terms, so S is exact and
       the NIS is chi2(m_i) for honest sensors). A sensor without which the others do not observe
       the state is untestable (NaN NIS).
    2. Exclusion: for each sensor beyond its gate, would the others, without it, all pass their
       own leave-one-out gates? If exactly one such exclusion exists, that sensor is dropped. If
       several exist the data cannot say which sensor is wrong (two sensors that disagree, or a
       conflict in an axis only two sensors see): nothing more is dropped. If none exists (several
       faults), the least plausible sensor (smallest chi-square tail probability) is dropped,
       provided every sensor that was testable stays testable without it.
    3. Repeat until no sensor is beyond its gate or no drop is allowed.

    A kept sensor whose NIS exceeds its threshold marks a conflict the data could not resolve.

    Args:
        H_list, R_list, z_list: as for `wls`, single measurement vectors z_i (m_i,).
        prob: gate probability.

    Returns:
        GatedFusion: x, P = wls of the kept sensors; nis of a kept sensor is its leave-one-out NIS
        against the other kept sensors, of a dropped one its NIS against the final estimate.

    Raises:
        NotObservableError: the sensors together do not observe the state.
    """
    Hs, Rs, _ = sensor_models(H_list, R_list)
    zs, batch = measurements(z_list, Hs)
    if batch is not None:
        raise ValueError("z_list: gated_wls takes one measurement vector (m_i,) per sensor")
    N = len(Hs)
    thresholds = np.array([gate_threshold(H.shape[0], prob) for H in Hs])
    dims = np.array([H.shape[0] for H in Hs])
    kept = np.ones(N, dtype=bool)
    wls(Hs, Rs, zs)  # raises NotObservableError when even all sensors together fall short
    nis = _leave_one_out_nis(Hs, Rs, zs, kept)
    while True:
        testable = kept & np.isfinite(nis)
        suspects = np.flatnonzero(testable & (nis > thresholds))
        if suspects.size == 0:
            break
        trials = {}
        for c in suspects:
            trial = kept.copy()
            trial[c] = False
            trials[int(c)] = _leave_one_out_nis(Hs, Rs, zs, trial)
        # exclusions after which every remaining testable sensor passes its gate
        clearing = [c for c, t in trials.items() if not np.any(t > thresholds)]  # NaN compares False
        if len(clearing) > 1:
            break  # ambiguous: several single exclusions explain the data equally well
        if len(clearing) == 1:
            drop = clearing[0]
        else:
            keeps_checks = [
                c for c, t in trials.items() if not np.any(testable & (np.arange(N) != c) & ~np.isfinite(t))
            ]
            if not keeps_checks:
                break
            drop = min(
                keeps_checks, key=lambda c: (stats.chi2.logsf(nis[c], dims[c]), c)
            )  # log tail: no underflow
        kept[drop] = False
        nis = trials[drop]
    idx = np.flatnonzero(kept)
    x, P = wls([Hs[i] for i in idx], [Rs[i] for i in idx], [zs[i] for i in idx])
    for i in np.flatnonzero(~kept):
        y, S = innovation(x, P, zs[i], Rs[i], Hs[i])  # y = z - H x ; S = H P H' + R (z_i not in x)
        nis[i] = nis_of(y, S)
    return GatedFusion(x=x, P=P, kept=kept, nis=nis, threshold=thresholds)


def _leave_one_out_nis(Hs, Rs, zs, kept: np.ndarray) -> np.ndarray:
    """NIS of each kept sensor against the WLS fusion of the other kept sensors (NaN if untestable)."""
    out = np.full(len(Hs), np.nan)
    for i in np.flatnonzero(kept):
        others = [j for j in np.flatnonzero(kept) if j != i]
        if not others:
            continue
        try:
            x, P = wls([Hs[j] for j in others], [Rs[j] for j in others], [zs[j] for j in others])
        except NotObservableError:
            continue
        y, S = innovation(x, P, zs[i], Rs[i], Hs[i])  # y = z_i - H_i x_-i ; S = H_i P_-i H_i' + R_i
        out[i] = nis_of(y, S)  # NIS = y' S^-1 y
    return out
