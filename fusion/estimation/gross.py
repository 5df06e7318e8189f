"""Gross errors of measured sensors: robust figures, what causes them, and whether a gate removes them.

Measured errors are heavy-tailed: a handful of measurements that are wrong by metres (a radar peak
on the neighbouring car, a lidar range from a fog return) sit among hundreds that are right to
decimetres, and a mean squared error over ~100 objects is then decided by those few. Three tools:

- `robust_summary`: mean with its standard error, beside the median and the 10 % trimmed mean
  (`TRIM`, scipy.stats.trim_mean) of the same values. The mean is what the theory (HydraFusion
  Eq. 5, `mismatch.fused_error`) predicts; the median and trimmed mean say what a typical object
  sees. When the mean is many times the median, a few values decide it.
- `is_gross` / `gross_cause`: a measurement is a *gross error* when its NEES e' R^-1 e against a
  covariance R exceeds the chi-square 99.9 % bound of 2 degrees of freedom (`GROSS_PROB`,
  chi2.ppf(0.999, 2) = 13.8): an honest sensor produces one such value per thousand measurements.
  Two covariances are used by the callers: the sensor's *claimed* (nominal) R, and its *measured*
  error second moment (cross-fitted on other sequences, what "full fusion with the true R"
  weights by). The cause of each is read from the simulator's ground truth recorded with the
  measurement (`MeasurementSet.source`, `purity`, `occlusion`, `truncation`, `quality`), first
  match in the order of `CAUSES`.
- `gate_outcome`: what the chi-square NIS gate of `gating.gated_wls` did with a measurement.
"""

from __future__ import annotations

import numpy as np
from scipy import stats

from fusion.estimation.gating import GatedFusion
from fusion.estimation.measurements import SOURCE_NOISE, SOURCE_NONE, SOURCE_WEATHER, SOURCE_WORLD

TRIM = 0.1  # share cut from each end by the trimmed mean
GROSS_PROB = 0.999  # a gross error lies beyond the chi2(2) quantile of this probability
GROSS_BOUND = float(stats.chi2.ppf(GROSS_PROB, 2))  # 13.82
OCCLUDED = 0.25  # an object at least this share hidden in the camera counts as occluded
FEW_RETURNS = 10  # a lidar measurement from fewer returns counts as a low point count

CAUSES = ("association", "weather", "static_world", "noise", "common_mode", "occlusion", "out_of_field",
          "few_returns", "own_object")
CAUSE_TEXT = {
    "association": "the data came from another actor (radar peak on a neighbour, stereo match onto another object)",
    "weather": "returns from the air: fog backscatter, rain or snow in the lidar's cluster; radar clutter",
    "static_world": "the data came from the static world (guard rail, background pixels)",
    "noise": "the radar peak is receiver noise",
    "common_mode": "the object's own data, and another sensor is wrong the same way (the reference point "
                   "itself: a long vehicle seen obliquely shows its near end); no gate can see it",
    "occlusion": f"the object's own data, but at least {OCCLUDED:.0%} of it is hidden",
    "out_of_field": "the object's own data, but the object is cut by the image border",
    "few_returns": f"the object's own lidar data, from fewer than {FEW_RETURNS} returns",
    "own_object": "the object's own, unobstructed data: the sensor's R model of the surface is too narrow",
}
GATE_OUTCOMES = ("removed", "other_removed", "ambiguous", "inside_gate", "untestable")
GATE_TEXT = {
    "removed": "the gate excluded this measurement",
    "other_removed": "passed its gate; another sensor was excluded instead",
    "ambiguous": "beyond its gate, but excluding either of the disagreeing sensors explains the data "
                 "(two sensors, or several single exclusions): nothing is excluded",
    "inside_gate": "its NIS against the others is within the gate: the covariances allow the error",
    "untestable": "the other sensors alone do not observe the position",
}


def robust_summary(values) -> dict:
    """Mean, its standard error, median and TRIM-trimmed mean of the finite values, and their count.

    se = std(ddof=1) / sqrt(n) (NaN for n < 2); every figure NaN when there are no values.
    """
    v = np.asarray(values, float).ravel()
    v = v[np.isfinite(v)]
    n = len(v)
    if n == 0:
        return {"n": 0, "mean": np.nan, "se": np.nan, "median": np.nan, "trimmed": np.nan}
    return {"n": n, "mean": float(v.mean()), "se": float(v.std(ddof=1) / np.sqrt(n)) if n > 1 else np.nan,
            "median": float(np.median(v)), "trimmed": float(stats.trim_mean(v, TRIM))}


def is_gross(nees_values) -> np.ndarray:
    """NEES values beyond GROSS_BOUND (NaN: False)."""
    v = np.asarray(nees_values, float)
    return np.where(np.isfinite(v), v, 0.0) > GROSS_BOUND


def shares_error(e: np.ndarray, R: np.ndarray, others_e, others_R, prob: float = 0.99) -> bool:
    """Whether another sensor is wrong the same way: its error e_j agrees with e (the difference
    passes the chi-square gate, (e - e_j)' (R + R_j)^-1 (e - e_j) <= chi2.ppf(prob, 2)) and is at least
    half as large along e (e_j . e >= |e|^2 / 2). Such an error is common to the sensors: it cannot be
    seen by comparing them."""
    from fusion.estimation.consistency import nis
    from fusion.estimation.gating import gate_threshold

    e = np.asarray(e, float)
    thr = gate_threshold(2, prob)
    for ej, Rj in zip(others_e, others_R):
        ej = np.asarray(ej, float)
        if not np.all(np.isfinite(ej)):
            continue
        if float(nis(e - ej, np.asarray(R) + np.asarray(Rj))) <= thr and float(ej @ e) >= 0.5 * float(e @ e):
            return True
    return False


def gross_cause(sensor: str, actor_id: int, source: int, purity: float, quality: float, occlusion: float,
                truncation: float, shared: bool = False) -> str:
    """Why a measurement of object `actor_id` is wrong, from the ground truth recorded with it.

    Args:
        sensor: "camera", "lidar" or "radar".
        source, purity: where the measurement's data came from and the object's own share of it
            (`MeasurementSet.source`, `purity`).
        quality: the extractor's figure (lidar: number of returns).
        occlusion, truncation: shares of the object hidden / outside the left image.
        shared: another sensor is wrong the same way (`shares_error`).

    Returns:
        The first of CAUSES that applies: another actor's data ("association"); air returns or
        clutter, also a lidar cluster mostly made of them ("weather"); the static world; noise; then,
        for the object's own data, "common_mode" (shared with another sensor), "occlusion", "out_of_field", "few_returns" (lidar), else
        "own_object".
    """
    if source == SOURCE_NONE:
        raise ValueError("a measurement that was not made has no cause")
    if source > 0 and source != actor_id:
        return "association"
    if source == SOURCE_WEATHER or (sensor == "lidar" and np.isfinite(purity) and purity < 0.5):
        return "weather"
    if source == SOURCE_WORLD:
        return "static_world"
    if source == SOURCE_NOISE:
        return "noise"
    if shared:
        return "common_mode"
    if np.isfinite(occlusion) and occlusion >= OCCLUDED:
        return "occlusion"
    if np.isfinite(truncation) and truncation > 0.0:
        return "out_of_field"
    if sensor == "lidar" and np.isfinite(quality) and quality < FEW_RETURNS:
        return "few_returns"
    return "own_object"


def gate_outcome(index: int, gated: GatedFusion) -> str:
    """What `gated_wls` did with measurement `index` (one of GATE_OUTCOMES).

    A kept measurement with a NaN NIS was untestable; one kept beyond its gate marks a conflict the
    gate could not resolve ("ambiguous": with two sensors, dropping either leaves one sensor that
    cannot be tested, so both exclusions explain the data equally well).
    """
    if not gated.kept[index]:
        return "removed"
    nis, thr = gated.nis[index], gated.threshold[index]
    if not np.isfinite(nis):
        return "untestable"
    if nis > thr:
        return "ambiguous"
    return "other_removed" if not gated.kept.all() else "inside_gate"
