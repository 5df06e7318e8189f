"""Multisensor estimation: the theory behind selective fusion, in filterpy's notation.

- `wls`: batch weighted least squares, HydraFusion Eq. 5 (`wls`, `WLSFusion`, `information`).
- `sequential`: the same fusion as Kalman updates of a static state (`sequential_fusion`,
  `SequentialFusion`), equal to `wls` to round-off.
- `mismatch`: the true error of a fusion built on wrong R (`fused_error`, `wls_gains`,
  `scalar_fused_variance`, `subset_errors`, `best_subset`): when fusing more sensors hurts.
- `consistency`: NEES / NIS and their chi-square bounds (`nees`, `nis`, `chi2_interval`,
  `mean_chi2_interval`, `consistency_report`, `is_consistent`).
- `gating`: chi-square innovation gating (`gate_threshold`, `gated_update`, `gated_wls`).
- `gross`: robust figures and gross errors of measured sensors (`gross.robust_summary`,
  `gross.is_gross`, `gross.gross_cause`, `gross.gate_outcome`; `error_model.gross_errors` applies
  them to a cell's measurements).
- `ci`: covariance intersection for unknown correlation (`covariance_intersection`,
  `covariance_intersection_n`, `ci_combine`, `naive_fusion`).
- `tracker`: a constant-velocity Kalman tracker per object fed by several sensors (`CVTracker`,
  `run_cv_tracker`, `run_cv_trackers`, `cv_model`, `cv_predict`, `position_update`,
  `simulate_cv_truth`, `Measurement`, `TrackHistory`).

Names follow the textbook: x state, P its covariance, F transition, Q process noise, H measurement
matrix, R measurement noise, y innovation, S its covariance, K gain.
"""

from fusion.estimation._linalg import NotObservableError
from fusion.estimation.ci import ci_combine, covariance_intersection, covariance_intersection_n, naive_fusion
from fusion.estimation.consistency import (
    ConsistencyReport,
    chi2_interval,
    consistency_report,
    is_consistent,
    mean_chi2_interval,
    nees,
    nis,
)
from fusion.estimation.gating import GatedFusion, gate_threshold, gated_update, gated_wls, innovation
from fusion.estimation.mismatch import (
    FusedError,
    best_subset,
    fused_error,
    scalar_fused_variance,
    subset_errors,
    wls_gains,
)
from fusion.estimation.sequential import SequentialFusion, sequential_fusion, static_kalman_filter
from fusion.estimation.tracker import (
    CVTracker,
    Measurement,
    TrackHistory,
    cv_model,
    cv_predict,
    position_update,
    run_cv_tracker,
    run_cv_trackers,
    simulate_cv_truth,
)
from fusion.estimation.wls import WLSFusion, information, wls

__all__ = [
    "CVTracker",
    "ConsistencyReport",
    "FusedError",
    "GatedFusion",
    "Measurement",
    "NotObservableError",
    "SequentialFusion",
    "TrackHistory",
    "WLSFusion",
    "best_subset",
    "chi2_interval",
    "ci_combine",
    "consistency_report",
    "covariance_intersection",
    "covariance_intersection_n",
    "cv_model",
    "cv_predict",
    "fused_error",
    "gate_threshold",
    "gated_update",
    "gated_wls",
    "information",
    "innovation",
    "is_consistent",
    "mean_chi2_interval",
    "naive_fusion",
    "nees",
    "nis",
    "position_update",
    "run_cv_tracker",
    "run_cv_trackers",
    "scalar_fused_variance",
    "sequential_fusion",
    "simulate_cv_truth",
    "static_kalman_filter",
    "subset_errors",
    "wls",
    "wls_gains",
]
