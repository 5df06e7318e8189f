"""True error distributions of measured sensors, and HydraFusion Sec. 1.1 on measured data.

`measurements` gives, per object, each sensor's measurement z_i of the object's reference point
with the nominal covariance R_i its spec implies. Here the *true* error e_i = z_i - x is compared
with R_i. Errors are studied in each object's line-of-sight frame (radial, lateral as seen from the
ego origin) and whitened by the nominal R:

    e_los = Q e,   R_los = Q R Q',   R_los = L L' (Cholesky),   w = L^-1 e_los

so w ~ (0, I) when the nominal R is right, whatever the range (the camera's depth variance grows as
Z^4). The true error model of a sensor under a condition is the mean m and covariance C of w over
many objects: its true covariance for an object is R_true = Q' L C L' Q and its bias Q' L m. C and
m scale the nominal model; they do not replace its dependence on range.

`evaluate_strategies` then fuses, for every object the active sensors (lidar and radar) both
measured, the sensors that measured it (HydraFusion Eq. 5 via `wls`; the camera joins when its
stereo match passed) in the ways the theory compares. The active sensors are the ones that report in
every condition: the camera's availability falls to a few percent in dense fog or heavy rain, so
requiring it would leave nothing to compare exactly where the theory matters. The strategies:
- each sensor alone;
- full fusion with the nominal R;
- full fusion with the true R: each sensor weighted by its measured error second moment
  Q' L (C + m m') L' Q (covariance plus squared bias: the bias cannot be removed without truth);
- selective fusion: the subset of sensors whose nominal fusion has the smallest measured MSE;
- chi-square-gated fusion (`gated_wls`, nominal R, RAIM-style exclusion);
- the same gate on the measured second moments ("gated_true"): does a gate with the right
  covariance remove what the nominal one cannot?
The true error model and the selected subset are estimated on one half of the sequences and
applied to the other (two-fold cross-fitting by sequence), so neither sees the errors it is scored
on; a subset picked on the same data would beat full fusion by selection bias alone.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy import stats

from fusion.estimation.consistency import mean_chi2_interval, nees
from fusion.estimation.gating import gated_wls
from fusion.estimation.gross import gate_outcome
from fusion.estimation.measurements import SENSORS, MeasurementSet, los_frame
from fusion.estimation.mismatch import fused_error
from fusion.estimation.wls import wls

CHI2_95_DOF2 = float(stats.chi2.ppf(0.95, 2))  # 5.99: the 95 % ellipse of a 2-D Gaussian
MIN_CALIBRATION = 3  # objects a sensor needs in a training fold to estimate its error model
MIN_PER_FOLD = 3  # objects seen by every required sensor needed in each fold to compare the strategies
REQUIRED = ("lidar", "radar")  # sensors every compared object was measured by (the active sensors)
STRATEGIES = ("full_nominal", "full_true", "selective", "gated", "gated_true")
GATES = {"gated": "nominal", "gated_true": "measured"}  # gated strategy -> the covariance its gate uses
H2 = np.eye(2)  # every sensor measures the reference point itself: z_i = I x + v_i


def whitened_errors(ms: MeasurementSet, sensor: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Line-of-sight errors of one sensor, whitened by its nominal R.

    Returns:
        rows: (n,) indices of the rows where the sensor measured the object.
        w: (n, 2) whitened (radial, lateral) errors L^-1 Q e.
        L: (n, 2, 2) Cholesky factors of the nominal R in the line-of-sight frame.
        Q: (n, 2, 2) rotations from ego x/y to line-of-sight axes.
    """
    k = ms.sensor(sensor)
    rows = np.flatnonzero(ms.available[:, k])
    Q = los_frame(ms.truth[rows])
    e = ms.z[rows, k] - ms.truth[rows]
    e_los = np.einsum("nij,nj->ni", Q, e)  # e_los = Q e
    R_los = np.einsum("nij,njk,nlk->nil", Q, ms.R[rows, k], Q)  # R_los = Q R Q'
    L = np.linalg.cholesky(0.5 * (R_los + np.swapaxes(R_los, 1, 2)))
    w = np.linalg.solve(L, e_los[..., None])[..., 0]  # w = L^-1 e_los
    return rows, w, L, Q


@dataclass(frozen=True)
class SensorErrors:
    """A sensor's true errors against its nominal R, over one set of measurements.

    Fields:
        sensor: sensor name. n: objects it measured. availability: n / objects in the set.
        bias_sigma: (2,) mean whitened (radial, lateral) error, in nominal standard deviations.
        cov_sigma: (2, 2) covariance of the whitened error (the identity when R is right).
        variance_ratio: (2,) mean squared whitened error per axis: true / nominal variance
            (bias included; 1 when R is right).
        nees_mean: mean NEES e' R^-1 e against the nominal R (2 when R is right).
        nees_median: median NEES (chi2(2) median 1.386 when R is right; robust to outliers).
        nees_bounds: (lo, hi) two-sided 95 % bounds of the mean of n chi2(2) values.
        coverage95: share of errors inside the nominal 95 % ellipse (0.95 when R is right).
        rms_m: (2,) root-mean-square (radial, lateral) error [m]. bias_m: (2,) mean error [m].
    """

    sensor: str
    n: int
    availability: float
    bias_sigma: np.ndarray
    cov_sigma: np.ndarray
    variance_ratio: np.ndarray
    nees_mean: float
    nees_median: float
    nees_bounds: tuple[float, float]
    coverage95: float
    rms_m: np.ndarray
    bias_m: np.ndarray

    def to_dict(self) -> dict:
        """JSON-ready summary."""
        return {
            "n": self.n,
            "availability": round(self.availability, 4),
            "variance_ratio": [_round(v) for v in self.variance_ratio],
            "bias_sigma": [_round(v) for v in self.bias_sigma],
            "nees_mean": _round(self.nees_mean),
            "nees_median": _round(self.nees_median),
            "nees_bounds": [_round(v) for v in self.nees_bounds],
            "coverage95": _round(self.coverage95),
            "rms_m": [_round(v) for v in self.rms_m],
            "bias_m": [_round(v) for v in self.bias_m],
        }


def sensor_errors(ms: MeasurementSet, sensor: str) -> SensorErrors:
    """Compare one sensor's measured errors with its nominal R (see `SensorErrors`)."""
    rows, w, L, Q = whitened_errors(ms, sensor)
    n = len(rows)
    nan2 = np.full(2, np.nan)
    if n == 0:
        return SensorErrors(sensor, 0, 0.0, nan2, np.full((2, 2), np.nan), nan2, np.nan, np.nan,
                            (np.nan, np.nan), np.nan, nan2, nan2)
    v = np.sum(w**2, axis=1)  # NEES = e' R^-1 e = |L^-1 Q e|^2
    e_los = np.einsum("nij,nj->ni", L, w)
    return SensorErrors(
        sensor=sensor,
        n=n,
        availability=n / max(len(ms), 1),
        bias_sigma=w.mean(axis=0),
        cov_sigma=np.cov(w.T, bias=True) if n > 1 else np.zeros((2, 2)),
        variance_ratio=np.mean(w**2, axis=0),
        nees_mean=float(v.mean()),
        nees_median=float(np.median(v)),
        nees_bounds=mean_chi2_interval(2, n),
        coverage95=float(np.mean(v <= CHI2_95_DOF2)),
        rms_m=np.sqrt(np.mean(e_los**2, axis=0)),
        bias_m=e_los.mean(axis=0),
    )


@dataclass(frozen=True)
class ErrorModel:
    """A sensor's true error model in nominal units: whitened mean m (2,) and covariance C (2, 2).

    For an object with nominal line-of-sight Cholesky factor L and rotation Q: bias Q' L m,
    covariance Q' L C L' Q. The identity model (m = 0, C = I) says the nominal R is right.
    """

    m: np.ndarray
    C: np.ndarray
    n: int

    @staticmethod
    def identity() -> ErrorModel:
        return ErrorModel(np.zeros(2), np.eye(2), 0)

    def apply(self, ms: MeasurementSet, sensor: str) -> tuple[np.ndarray, np.ndarray]:
        """(bias (N, 2), covariance (N, 2, 2)) in ego x/y of every row of `ms` the sensor measured
        (NaN elsewhere)."""
        N = len(ms)
        bias = np.full((N, 2), np.nan)
        cov = np.full((N, 2, 2), np.nan)
        rows, _, L, Q = whitened_errors(ms, sensor)
        A = np.swapaxes(Q, 1, 2) @ L  # Q' L: whitened -> ego
        bias[rows] = A @ self.m  # b = Q' L m
        cov[rows] = A @ self.C @ np.swapaxes(A, 1, 2)  # R_true = Q' L C L' Q
        return bias, cov


def fit_error_model(ms: MeasurementSet, sensor: str) -> ErrorModel:
    """The whitened mean and covariance of a sensor's errors in `ms`; the identity model when it
    measured fewer than MIN_CALIBRATION objects (nothing better is known)."""
    _, w, _, _ = whitened_errors(ms, sensor)
    if len(w) < MIN_CALIBRATION:
        return ErrorModel.identity()
    C = np.cov(w.T, bias=True) + 1e-9 * np.eye(2)
    return ErrorModel(w.mean(axis=0), C, len(w))


def subsets(n_sensors: int = len(SENSORS)) -> list[tuple[int, ...]]:
    """Every non-empty subset of sensor indices, smaller subsets first."""
    return [s for k in range(1, n_sensors + 1) for s in itertools.combinations(range(n_sensors), k)]


def fuse(ms: MeasurementSet, subset: tuple[int, ...], R: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """HydraFusion Eq. 5 for every row: fused estimates (N, 2) and covariances (N, 2, 2).

    subset: sensor indices to fuse; a row fuses those of them that measured it (NaN if none did).
    R: (N, 3, 2, 2) covariances to weight by; default the nominal ms.R.
    """
    R = ms.R if R is None else R
    N = len(ms)
    avail = ms.available
    x = np.full((N, 2), np.nan)
    P = np.full((N, 2, 2), np.nan)
    for i in range(N):
        ks = [k for k in subset if avail[i, k]]
        if ks:
            x[i], P[i] = wls([H2] * len(ks), [R[i, k] for k in ks], [ms.z[i, k] for k in ks])
    return x, P


@dataclass(frozen=True)
class StrategyErrors:
    """Errors of every single sensor and fusion strategy on the objects the REQUIRED sensors measured.

    Fields:
        n: objects compared. folds: cross-fitting folds used (2).
        errors: {name: (n, 2) error [m]} for each sensor name (NaN rows: that sensor gave nothing)
            and each of STRATEGIES (each fuses the sensors of its set that measured the object).
        mse: {name: mean squared error [m^2]} (a sensor's over the objects it measured);
            mse_se: its standard error (std of |e|^2 / sqrt(n)); measured: {sensor: objects}.
        nees: (n,) NEES of full nominal fusion against its own covariance P.
        nees_bounds: two-sided 95 % bounds of the mean of n chi2(2) values.
        subsets: the selected subset (sensor names) of each fold.
        mse_full_nominal_predicted: the MSE of full nominal fusion the fitted error models predict
            through `fused_error` (trace(sum K R_true K') + |sum K b|^2, averaged over objects).
        rows: (n,) index in the evaluated MeasurementSet of each compared object, in the order of
            the error arrays.
        sensor_nees: {"nominal": (n, 3), "measured": (n, 3)} NEES of each sensor's error against its
            nominal R and against its measured (cross-fitted) error second moment; NaN where the
            sensor gave nothing.
        gate_outcomes: {"nominal": (n, 3), "measured": (n, 3)} what the gate of "gated" (nominal R)
            and "gated_true" (measured R) did with each measurement (`gross.gate_outcome`; "" where
            the sensor gave nothing).
    """

    n: int
    folds: int
    errors: dict
    mse: dict
    mse_se: dict
    nees: np.ndarray
    nees_bounds: tuple[float, float]
    subsets: tuple
    mse_full_nominal_predicted: float
    measured: dict
    rows: np.ndarray
    sensor_nees: dict
    gate_outcomes: dict

    @property
    def nees_mean(self) -> float:
        return float(np.mean(self.nees))


def compared(ms: MeasurementSet) -> np.ndarray:
    """(N,) bool: the rows every REQUIRED sensor measured (the objects the strategies are compared on)."""
    return ms.available[:, [SENSORS.index(s) for s in REQUIRED]].all(axis=1)


def evaluate_strategies(ms: MeasurementSet, gate_prob: float = 0.99) -> StrategyErrors | None:
    """Compare single sensors and the fusion strategies on the objects the REQUIRED sensors measured.

    Every strategy fuses, per object, the sensors of its set that measured it: "full" is every
    sensor that reported, as a running fusion system would have it. Folds are the parity of the
    sequence index; each fold is scored with error models and the selected subset fitted on the other
    fold (error models from every object a sensor measured there, the subset from the other fold's
    compared objects, among the subsets that hold a required sensor so that they always give an
    estimate). Returns None when a fold has fewer than MIN_PER_FOLD compared objects.
    """
    fold_of = ms.sequence % 2
    common = compared(ms)
    required = {SENSORS.index(s) for s in REQUIRED}
    candidates = [sub for sub in subsets() if set(sub) & required]
    for f in (0, 1):
        if np.sum(common & (fold_of == f)) < MIN_PER_FOLD:
            return None
    names = list(SENSORS) + list(STRATEGIES)
    errors: dict[str, list] = {name: [] for name in names}
    nees_all, predicted, chosen, rows = [], [], [], []
    sensor_nees: dict[str, list] = {"nominal": [], "measured": []}
    outcomes: dict[str, list] = {"nominal": [], "measured": []}
    for f in (0, 1):
        test_rows = np.flatnonzero((fold_of == f) & common)
        rows.append(test_rows)
        train, test = ms[fold_of != f], ms[test_rows]
        models = {s: fit_error_model(train, s) for s in SENSORS}
        applied = [models[s].apply(test, s) for s in SENSORS]
        bias = np.stack([a[0] for a in applied], axis=1)  # (n, 3, 2)
        cov = np.stack([a[1] for a in applied], axis=1)  # (n, 3, 2, 2)
        second = cov + np.einsum("nki,nkj->nkij", bias, bias)  # E[e e'] = C + b b'
        best = _best_subset(train[compared(train)], candidates)
        chosen.append(tuple(SENSORS[k] for k in best))
        truth = test.truth
        for k, s in enumerate(SENSORS):
            errors[s].append(test.z[:, k] - truth)
        e_k = test.z - truth[:, None, :]  # (n, 3, 2)
        sensor_nees["nominal"].append(_nees_or_nan(e_k, test.R))
        sensor_nees["measured"].append(_nees_or_nan(e_k, second))
        x, P = fuse(test, (0, 1, 2))
        errors["full_nominal"].append(x - truth)
        nees_all.append(nees(x - truth, P))
        errors["full_true"].append(fuse(test, (0, 1, 2), second)[0] - truth)
        errors["selective"].append(fuse(test, best)[0] - truth)
        gated = {name: np.empty((len(test), 2)) for name in GATES}
        fold_outcomes = {kind: np.full((len(test), len(SENSORS)), "", dtype=object) for kind in GATES.values()}
        for i in range(len(test)):
            ks = np.flatnonzero(test.available[i])
            for name, kind in GATES.items():
                Rs = test.R[i, ks] if kind == "nominal" else second[i, ks]
                g = gated_wls([H2] * len(ks), list(Rs), list(test.z[i, ks]), prob=gate_prob)
                gated[name][i] = g.x - truth[i]
                for j, k in enumerate(ks):
                    fold_outcomes[kind][i, k] = gate_outcome(j, g)
            predicted.append(fused_error([H2] * len(ks), list(test.R[i, ks]), list(cov[i, ks]), list(bias[i, ks])).mse)
        for name in GATES:
            errors[name].append(gated[name])
        for kind in outcomes:
            outcomes[kind].append(fold_outcomes[kind])
    err = {name: np.concatenate(v) for name, v in errors.items()}
    sq = {name: np.sum(e**2, axis=1) for name, e in err.items()}
    sq = {name: s[np.isfinite(s)] for name, s in sq.items()}  # a sensor's: the objects it measured
    n = len(err["full_nominal"])
    v = np.concatenate(nees_all)
    return StrategyErrors(
        n=n,
        folds=2,
        errors=err,
        mse={name: float(s.mean()) for name, s in sq.items()},
        mse_se={name: float(s.std(ddof=1) / np.sqrt(len(s))) if len(s) > 1 else float("nan")
                for name, s in sq.items()},
        nees=v,
        nees_bounds=mean_chi2_interval(2, n),
        subsets=tuple(chosen),
        mse_full_nominal_predicted=float(np.mean(predicted)),
        measured={s: int(len(sq[s])) for s in SENSORS},
        rows=np.concatenate(rows),
        sensor_nees={kind: np.concatenate(v) for kind, v in sensor_nees.items()},
        gate_outcomes={kind: np.concatenate(v) for kind, v in outcomes.items()},
    )


def _nees_or_nan(e: np.ndarray, R: np.ndarray) -> np.ndarray:
    """(n, k) NEES e' R^-1 e of (n, k, 2) errors against (n, k, 2, 2) covariances; NaN where e is NaN."""
    out = np.full(e.shape[:2], np.nan)
    ok = np.isfinite(e[..., 0])
    if ok.any():
        out[ok] = nees(e[ok], R[ok])
    return out


def _best_subset(ms: MeasurementSet, candidates: list[tuple[int, ...]] | None = None) -> tuple[int, ...]:
    """The candidate subset whose nominal fusion has the smallest MSE on `ms` (ties: fewer sensors
    first); each row fuses the subset's sensors that measured it, so every candidate must give an
    estimate on every row."""
    best, best_mse = None, np.inf
    for subset in candidates or subsets():
        x, _ = fuse(ms, subset)
        mse = float(np.mean(np.sum((x - ms.truth) ** 2, axis=1)))
        if mse < best_mse:
            best, best_mse = subset, mse
    assert best is not None
    return best


def _round(v) -> float | None:
    v = float(v)
    return None if not np.isfinite(v) else float(f"{v:.4g}")


def gross_errors(ms: MeasurementSet, st: StrategyErrors) -> dict:
    """The gross errors among the compared objects' measurements, their causes and the gates' verdicts.

    A measurement is gross under a covariance when its NEES exceeds `gross.GROSS_BOUND` (the
    chi2(2) 99.9 % quantile): "nominal" against the sensor's claimed R, "measured" against its
    cross-fitted error second moment (what full fusion with the true R weights by). Its cause is
    `gross.gross_cause` of the ground truth recorded with the measurement; the verdicts are those of
    the nominal-R gate ("gated") and the measured-R gate ("gated_true").

    Returns (JSON-ready):
        bound: the NEES bound. per_sensor: {kind: {sensor: {"n", "gross", "causes": {cause: count},
        "gate": {"nominal"|"measured": {outcome: count}}}}} for kind "nominal" and "measured".
        objects_with_gross: {kind: objects with at least one gross measurement of that kind}.
        sse_share: {"full_nominal": share of its summed squared error on objects with a nominal
        gross error, "full_true": on objects with a measured one}. mse_without_gross: {kind: {name:
        MSE over the objects with no gross error of that kind}} for every sensor and strategy (a
        diagnosis that uses the truth, not a strategy). records: one dict per gross measurement
        (either kind).
    """
    from fusion.estimation.gross import (
        CAUSES,
        GATE_OUTCOMES,
        GROSS_BOUND,
        gross_cause,
        is_gross,
        shares_error,
    )

    rows = st.rows
    flags = {kind: is_gross(v) for kind, v in st.sensor_nees.items()}  # (n, 3) each
    causes = np.full(flags["nominal"].shape, "", dtype=object)
    for i, k in zip(*np.nonzero(flags["nominal"] | flags["measured"])):
        r = rows[i]
        e = ms.z[r] - ms.truth[r]  # (3, 2)
        others = [j for j in range(len(SENSORS)) if j != k and ms.available[r, j]]
        shared = shares_error(e[k], ms.R[r, k], [e[j] for j in others], [ms.R[r, j] for j in others])
        causes[i, k] = gross_cause(SENSORS[k], int(ms.actor_ids[r]), int(ms.source[r, k]), float(ms.purity[r, k]),
                                   float(ms.quality[r, k]), float(ms.occlusion[r]), float(ms.truncation[r]), shared)
    per_sensor = {}
    for kind, flag in flags.items():
        per_sensor[kind] = {}
        for k, s in enumerate(SENSORS):
            sel = flag[:, k]
            per_sensor[kind][s] = {
                "n": int(np.isfinite(st.sensor_nees[kind][:, k]).sum()),
                "gross": int(sel.sum()),
                "causes": {c: int(np.sum(causes[sel, k] == c)) for c in CAUSES if np.any(causes[sel, k] == c)},
                "gate": {g: {o: int(np.sum(st.gate_outcomes[g][sel, k] == o)) for o in GATE_OUTCOMES
                             if np.any(st.gate_outcomes[g][sel, k] == o)} for g in st.gate_outcomes},
            }
    clean = {}  # a diagnosis by truth, not a strategy: what each would score without those objects
    for kind, flag in flags.items():
        keep = ~flag.any(axis=1)
        clean[kind] = {}
        for name, e in st.errors.items():
            sq = np.sum(e[keep] ** 2, axis=1)
            sq = sq[np.isfinite(sq)]
            clean[kind][name] = _round(sq.mean()) if len(sq) else None
    share = {}
    for name, kind in (("full_nominal", "nominal"), ("full_true", "measured")):
        sq = np.sum(st.errors[name] ** 2, axis=1)
        share[name] = _round(sq[flags[kind].any(axis=1)].sum() / sq.sum()) if sq.sum() > 0 else None
    records = []
    Q = los_frame(ms.truth[rows])
    for i, k in zip(*np.nonzero(flags["nominal"] | flags["measured"])):
        r = rows[i]
        e = Q[i] @ (ms.z[r, k] - ms.truth[r])
        records.append({
            "sensor": SENSORS[k], "sequence": int(ms.sequence[r]), "frame": int(ms.frame[r]),
            "actor": int(ms.actor_ids[r]), "class": int(ms.classes[r]),
            "range_m": _round(np.hypot(*ms.truth[r])), "error_m": [_round(e[0]), _round(e[1])],
            "nees_nominal": _round(st.sensor_nees["nominal"][i, k]),
            "nees_measured": _round(st.sensor_nees["measured"][i, k]),
            "gross": [kind for kind in ("nominal", "measured") if flags[kind][i, k]],
            "cause": causes[i, k], "source": int(ms.source[r, k]), "purity": _round(ms.purity[r, k]),
            "gate": {g: st.gate_outcomes[g][i, k] for g in st.gate_outcomes},
        })
    return {"bound": round(GROSS_BOUND, 3), "per_sensor": per_sensor,
            "objects_with_gross": {kind: int(f.any(axis=1).sum()) for kind, f in flags.items()},
            "sse_share": share, "mse_without_gross": clean, "records": records}
