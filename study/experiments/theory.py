"""`hydrabench theory`: HydraFusion Sec. 1.1 (Eq. 1-5) measured on the simulated sensors.

For each condition and severity the command simulates sequences on one road layout, renders and
degrades every sensor, extracts object-level position measurements with their nominal R
(`fusion.estimation.measurements`) and compares, on the objects both active sensors (lidar, radar)
measured, each fusing the sensors that measured the object (`fusion.estimation.error_model`):

    mse_single        each sensor alone                                     [m^2]
    mse_full_nominal  HydraFusion Eq. 5 over all sensors with the nominal R [m^2]
    mse_full_true     Eq. 5 with each sensor's measured error second moment [m^2]
    mse_selective     Eq. 5 over the subset with the smallest measured MSE  [m^2]
    mse_gated         Eq. 5 after chi-square exclusion of disagreeing sensors (gated_wls, nominal R)
    nees_mean         mean NEES of full nominal fusion against its own P (2 if honest)
    nees_bounds       two-sided 95 % bounds of that mean for the number of objects

Errors are heavy-tailed, so details.<condition>.<severity> also carries, for every sensor and
strategy (gated_true: the same gate on the measured covariances), `robust`: the mean squared error
with its standard error beside the median and the 10 % trimmed mean; `paired_vs_best_single`: each
strategy's squared error minus the better of lidar and radar alone, object by object (mean, se);
and `gross`: the gross
errors, measurements whose NEES exceeds the chi-square 99.9 % bound (13.8) of the sensor's nominal
R or of its measured error second moment, counted per sensor and per cause (read from the
simulator's ground truth: another actor's data, weather returns, the static world, noise,
occlusion, the image border, few lidar returns, or the object's own data), with what each gate did
with them and the share of the fused squared error they carry (fusion.estimation.gross).

Every cell uses the same sequence seeds (common random numbers): the same traffic is measured in
every weather, so differences between cells come from the weather, not from the draw. Severity 0
is clear weather on the condition's layout, measured once for all conditions on that layout.
Measurements are cached per sequence in the cache directory, keyed by everything that determines
them (the extractor version included).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from sensors import SENSOR_MODEL_VERSION
from sim.errors import UserError

LAYOUTS = ("city", "junction", "motorway", "rural")
SEVERITY_UNITS = {"fog": ("visibility", "m"), "rain": ("rain", "mm/h"), "snow": ("snowfall", "mm/h"),
                  "night": ("illuminance", "lx")}

def default_cache_dir() -> Path:
    """theory/ in hydrabench's cache (`study.outputs.cache_root`: $HYDRABENCH_CACHE, else
    $XDG_CACHE_HOME/hydrabench, else ~/.cache/hydrabench), checked writable."""
    from study.outputs import cache_root

    return cache_root() / "theory"


@dataclass(frozen=True)
class TheoryConfig:
    """What `hydrabench theory` measures.

    Fields:
        conditions: condition names or '+' combinations ("fog", "rain+night").
        severities: severities 0..5 to measure (0 = clear, shared by all conditions).
        layout: road layout every condition is put on.
        frames: frames per condition and severity (split over the sequences).
        sequences: sequences per cell (>= 2: the strategies are cross-fitted over two folds).
        frame_rate_hz: frame rate within a sequence [Hz]; 2 Hz lets the traffic move between frames.
        seed: root seed; sequence j uses the seed stream(seed, "theory", j) in every cell.
        profile: sensor profile ("cpu" or "paper").
        gate_prob: chi-square gate probability of the gated fusion.
    """

    conditions: tuple[str, ...] = ("rain", "fog", "snow", "night")
    severities: tuple[int, ...] = (0, 1, 2, 3, 4, 5)
    layout: str = "motorway"
    frames: int = 40
    sequences: int = 4
    frame_rate_hz: float = 2.0
    seed: int = 0
    profile: str = "cpu"
    gate_prob: float = 0.99

    def __post_init__(self) -> None:
        from sensors.rig import profile_names

        if not self.conditions:
            raise UserError("conditions must name at least one condition")
        for c in self.conditions:
            condition_parts(c)
        if not self.severities or any(not 0 <= int(s) <= 5 for s in self.severities):
            raise UserError(f"severities must be values in 0..5, got {list(self.severities)}")
        if self.layout not in LAYOUTS:
            raise UserError(f"unknown layout {self.layout!r} (choose from: {', '.join(LAYOUTS)})")
        if self.sequences < 2:
            raise UserError(f"sequences must be >= 2 (the strategies are cross-fitted over two folds), got {self.sequences}")
        if self.frames < self.sequences:
            raise UserError(f"frames ({self.frames}) must be >= sequences ({self.sequences}): one frame per sequence at least")
        if not (self.frame_rate_hz > 0 and math.isfinite(self.frame_rate_hz)):
            raise UserError(f"frame_rate_hz must be > 0, got {self.frame_rate_hz}")
        if self.seed < 0:
            raise UserError(f"seed must be >= 0, got {self.seed}")
        if self.profile not in profile_names():
            raise UserError(f"unknown profile {self.profile!r} (choose from: {', '.join(profile_names())})")
        if not 0.0 < self.gate_prob < 1.0:
            raise UserError(f"gate_prob must be strictly between 0 and 1, got {self.gate_prob}")


def parse_condition(text: str, layout: str) -> tuple[str, tuple[str, ...]]:
    """(layout, conditions) of a condition name: "rain+night" on `layout`, or with its own layout
    ("city+night"); conditions in canonical order."""
    from sim.weather import CONDITIONS

    parts = [p.strip().lower() for p in str(text).split("+")]
    if not all(parts):
        raise UserError(f"condition {text!r} has an empty or dangling '+' (combine names as in rain+night)")
    layouts = [p for p in parts if p in LAYOUTS]
    conds = [p for p in parts if p in CONDITIONS]
    bad = [p for p in parts if p not in LAYOUTS and p not in CONDITIONS]
    if bad or not parts:
        raise UserError(f"unknown condition {bad[0] if bad else text!r} (choose from: {', '.join(CONDITIONS)}; "
                        "combine them as in rain+night, optionally on a layout as in city+night)")
    if not conds:
        raise UserError(f"condition {text!r} names no weather condition ({', '.join(CONDITIONS)})")
    if len(layouts) > 1:
        raise UserError(f"condition {text!r} names two road layouts")
    if len(set(conds)) != len(conds):
        raise UserError(f"condition {text!r} repeats a condition")
    return (layouts[0] if layouts else layout), tuple(c for c in CONDITIONS if c in conds)


def condition_parts(text: str) -> tuple[str, ...]:
    """The conditions of a condition name ("city+rain+night" -> ("rain", "night"))."""
    return parse_condition(text, LAYOUTS[0])[1]


def condition_name(text: str) -> str:
    """Canonical name: the conditions joined by '+', after the layout when one is named."""
    layout, conds = parse_condition(text, "")
    return "+".join(((layout,) if layout else ()) + conds)


def condition_layout(config: TheoryConfig, condition: str) -> str:
    return parse_condition(condition, config.layout)[0]


# The small study the notebook (notebooks/01_fusion_theory.ipynb) and the measured tests run: fog,
# rain and night on the motorway (one layout: every cell measures the same traffic) at severities 0,
# 3 and 5, 24 frames per cell in 2 sequences (under a minute on 2 cores, then cached).
SMALL_CONFIG = TheoryConfig(conditions=("fog", "rain", "night"), severities=(0, 3, 5), frames=24, sequences=2)


def cell_context(config: TheoryConfig, condition: str, severity: int) -> str:
    """The context simulated for a cell: the layout alone at severity 0, else layout+conditions."""
    from sim.scenario import Context

    layout, conds = parse_condition(condition, config.layout)
    if severity == 0:
        return layout
    return Context(layout, conds).name


def sequence_seeds(config: TheoryConfig) -> list[int]:
    """Seed of each sequence; the same in every cell (common random numbers)."""
    from sim.scenario import stream

    return [int(stream(config.seed, "theory", j).integers(2**31 - 1)) for j in range(config.sequences)]


def sequence_frames(config: TheoryConfig) -> list[int]:
    """Frames of each sequence: config.frames split as evenly as possible, earlier sequences longer."""
    base, extra = divmod(config.frames, config.sequences)
    return [base + (1 if j < extra else 0) for j in range(config.sequences)]


def sequence_specs(config: TheoryConfig, condition: str, severity: int) -> list:
    """The ScenarioSpecs of a cell's sequences."""
    from sim.scenario import ScenarioSpec

    context = cell_context(config, condition, severity)
    return [ScenarioSpec(context=context, severity=int(severity), seed=s, frames=f,
                         frame_rate_hz=config.frame_rate_hz, profile=config.profile, warmup_s=-1.0)
            for s, f in zip(sequence_seeds(config), sequence_frames(config))]


def cache_key(spec, sequence: int) -> dict:
    """Everything that determines a sequence's measurements."""
    from fusion.estimation.measurements import EXTRACTOR_VERSION

    return {"extractor_version": EXTRACTOR_VERSION, "sensor_model_version": SENSOR_MODEL_VERSION,
            "context": spec.context, "severity": spec.severity,
            "seed": spec.seed, "frames": spec.frames, "frame_rate_hz": spec.frame_rate_hz,
            "profile": spec.profile, "transition": spec.transition, "warmup_s": spec.warmup_s,
            "obstructions": False, "sequence": sequence}


def cache_path(cache_dir: Path, key: dict) -> Path:
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:24]
    name = f"{key['context'].replace('+', '_')}-s{key['severity']}-{digest}.npz"
    return Path(cache_dir) / name


def load_cached(path: Path, key: dict):
    """The MeasurementSet stored at `path` if it was made with `key`, else None."""
    from fusion.estimation.measurements import MeasurementSet

    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            if json.loads(str(data["key"])) != key:
                return None
            return MeasurementSet.from_arrays(data)
    except (OSError, ValueError, KeyError):
        return None  # unreadable or from another version: measure again


def measure_and_cache(spec, sequence: int, cache_dir: Path, on_frame=None):
    """Measure one sequence (or load it from the cache) and return its MeasurementSet."""
    from fusion.estimation.measurements import measure_sequence
    from study.outputs import atomic_path

    key = cache_key(spec, sequence)
    path = cache_path(cache_dir, key)
    cached = load_cached(path, key)
    if cached is not None:
        return cached
    ms = measure_sequence(spec, sequence=sequence, on_frame=on_frame)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, key=np.array(json.dumps(key, sort_keys=True)), **ms.arrays())
    return ms


def _worker_init() -> None:
    os.environ["LP_NUM_THREADS"] = "1"
    os.environ["OMP_NUM_THREADS"] = "1"
    os.environ["OPENBLAS_NUM_THREADS"] = "1"


def _measure_task(task: tuple) -> int:
    """Worker entry point: measure one sequence into the cache; returns its frame count."""
    spec_dict, sequence, cache_dir = task
    from sim.scenario import ScenarioSpec

    spec = ScenarioSpec(**spec_dict)
    measure_and_cache(spec, sequence, Path(cache_dir))
    return spec.frames


def collect(config: TheoryConfig, cache_dir: Path, workers: int = 1, progress: bool = True) -> tuple[dict, dict]:
    """Measure (or load) every cell. Returns ({(condition, severity): MeasurementSet}, frame counts)."""
    from fusion.estimation.measurements import MeasurementSet
    from sim.progress import progress as progress_bar

    cells = {}
    for c in config.conditions:
        for s in config.severities:
            cells[(condition_name(c), int(s))] = sequence_specs(config, c, int(s))
    unique = {}  # severity 0 is shared: measure each distinct spec once
    for specs in cells.values():
        for j, spec in enumerate(specs):
            unique[json.dumps(cache_key(spec, j), sort_keys=True)] = (spec, j)
    todo = [(spec, j) for spec, j in unique.values()
            if load_cached(cache_path(cache_dir, cache_key(spec, j)), cache_key(spec, j)) is None]
    frames_todo = sum(spec.frames for spec, _ in todo)
    bar = progress_bar(total=frames_todo, unit="frame", desc="theory", enabled=bool(progress))
    if workers <= 1 or len(todo) <= 1:
        for spec, j in todo:
            measure_and_cache(spec, j, cache_dir, on_frame=lambda: bar.update(1))
    else:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor, as_completed

        # spawn: a fresh interpreter per worker (EGL contexts do not survive fork); an executor
        # rather than a Pool, so a worker that dies raises here instead of being respawned forever
        tasks = [(asdict(spec), j, str(cache_dir)) for spec, j in todo]
        with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=_worker_init) as pool:
            for future in as_completed([pool.submit(_measure_task, t) for t in tasks]):
                bar.update(future.result())
    bar.close()
    data = {}
    for cell, specs in cells.items():
        data[cell] = MeasurementSet.concat(measure_and_cache(spec, j, cache_dir) for j, spec in enumerate(specs))
    n_frames = sum(spec.frames for spec, _ in unique.values())
    return data, {"measured": frames_todo, "cached": n_frames - frames_todo}


def cell_report(ms, gate_prob: float) -> tuple[dict, dict]:
    """(the seven result keys, details) of one cell's measurements."""
    from fusion.estimation.error_model import evaluate_strategies, sensor_errors
    from fusion.estimation.measurements import SENSORS

    sensors = {s: sensor_errors(ms, s) for s in SENSORS}
    details = {
        "objects": len(ms),
        "availability": {s: round(e.availability, 4) for s, e in sensors.items()},
        "sensors": {s: e.to_dict() for s, e in sensors.items()},
    }
    st = evaluate_strategies(ms, gate_prob=gate_prob)
    if st is None:
        from fusion.estimation.error_model import REQUIRED, compared

        details["compared"] = int(compared(ms).sum())
        details["note"] = f"too few objects measured by {' and '.join(REQUIRED)} in one of the two folds: no comparison"
        result = {"mse_single": {s: None for s in SENSORS}, "mse_full_nominal": None, "mse_full_true": None,
                  "mse_selective": None, "mse_gated": None, "nees_mean": None, "nees_bounds": None}
        return result, details
    from fusion.estimation.error_model import REQUIRED, STRATEGIES, gross_errors
    from fusion.estimation.gross import robust_summary

    r = _sig
    robust = {}
    for name in list(SENSORS) + list(STRATEGIES):
        summary = robust_summary(np.sum(st.errors[name] ** 2, axis=1))
        robust[name] = {k: (v if k == "n" else r(v)) for k, v in summary.items()}
    # each strategy against the best of the sensors every compared object has, object by object
    best = min(REQUIRED, key=lambda s: st.mse[s])
    sq_best = np.sum(st.errors[best] ** 2, axis=1)
    paired = {"best_single": best}
    for name in STRATEGIES:
        diff = np.sum(st.errors[name] ** 2, axis=1) - sq_best
        diff[np.abs(diff) < 1e-9 * (1.0 + sq_best)] = 0.0  # the same estimate (round-off)
        d = robust_summary(diff)
        paired[name] = {"mean": r(d["mean"]), "se": r(d["se"])}
    result = {
        "mse_single": {s: r(st.mse[s]) for s in SENSORS},
        "mse_full_nominal": r(st.mse["full_nominal"]),
        "mse_full_true": r(st.mse["full_true"]),
        "mse_selective": r(st.mse["selective"]),
        "mse_gated": r(st.mse["gated"]),
        "nees_mean": r(st.nees_mean),
        "nees_bounds": [r(st.nees_bounds[0]), r(st.nees_bounds[1])],
    }
    details.update({
        "compared": st.n,
        "mse_se": {k: r(v) for k, v in st.mse_se.items()},
        "selective_subsets": [list(s) for s in st.subsets],
        "measured": st.measured,
        "mse_full_nominal_predicted": r(st.mse_full_nominal_predicted),
        "robust": robust,
        "paired_vs_best_single": paired,
        "gross": gross_errors(ms, st),
    })
    return result, details


def run_theory(config: TheoryConfig, cache_dir: Path | None = None, workers: int = 1, progress: bool = True) -> dict:
    """Measure every cell of `config` and compare the strategies. Returns the command's JSON object."""
    t0 = time.perf_counter()
    cache_dir = default_cache_dir() if cache_dir is None else Path(cache_dir)
    data, frames = collect(config, cache_dir, workers=workers, progress=progress)
    results: dict = {}
    details: dict = {}
    for (cond, sev), ms in data.items():
        res, det = cell_report(ms, config.gate_prob)
        det["context"] = cell_context(config, cond, sev)
        det["layout"] = condition_layout(config, cond)
        det["weather"] = weather_text(cond, sev)
        results.setdefault(cond, {})[str(sev)] = res
        details.setdefault(cond, {})[str(sev)] = det
    cfg = asdict(config)
    cfg = {k: list(v) if isinstance(v, tuple) else v for k, v in cfg.items()}
    return {"config": cfg, "cache": str(cache_dir), "results": results, "details": details,
            "frames": frames, "seconds": round(time.perf_counter() - t0, 2)}


def weather_text(condition: str, severity: int) -> str:
    """The physical interval of a cell's conditions, e.g. 'visibility 75-150 m'."""
    from sim.weather import SEVERITY_TABLE

    if severity == 0:
        return "clear"
    parts = []
    for c in condition_parts(condition):
        lo, hi = SEVERITY_TABLE[c]["levels"][severity - 1]
        label, unit = SEVERITY_UNITS[c]
        parts.append(f"{label} {lo:g}-{hi:g} {unit}")
    return ", ".join(parts)


def _sig(v) -> float | None:
    v = float(v)
    return None if not math.isfinite(v) else float(f"{v:.4g}")


@dataclass(frozen=True)
class BankTracks:
    """One object tracked through a fog bank by constant-velocity Kalman trackers.

    Fields:
        t: (T,) frame times [s]. visibility_m: (T,) fog visibility of each frame [m].
        object_id: the tracked actor. truth: (T, 2) its reference point in each frame's ego frame [m].
        available: {sensor: (T,) bool} which sensors measured it in each frame.
        errors: {tracker: (T, 2)} position error after each frame's updates [m] for the trackers
            "all sensors", "all sensors, gated" and "camera + radar".
        rejected: {sensor: (T,) bool} measurements the gated tracker rejected.
    """

    t: np.ndarray
    visibility_m: np.ndarray
    object_id: int
    truth: np.ndarray
    available: dict
    errors: dict
    rejected: dict


def fog_bank_tracks(cache_dir: Path | None = None, seed: int = 0, frames: int = 30, frame_rate_hz: float = 5.0,
                    severity: int = 5, layout: str = "motorway", gate_prob: float = 0.99) -> BankTracks:
    """Drive through a fog bank (transition "bank": clear, fog rolls in, holds, rolls out) and track
    the object seen longest by the radar with every sensor at its nominal R, with and without a
    chi-square gate, and with the camera and radar only (the selective choice for fog).

    The tracker state lives in the ego frame (the ego's own motion is absorbed by the constant-
    velocity model: on a motorway the relative motion is slow and steady).
    """
    from fusion.estimation.measurements import SENSORS
    from fusion.estimation.tracker import Measurement, run_cv_tracker
    from sim.scenario import Context, ScenarioSpec, Simulator

    cache_dir = default_cache_dir() if cache_dir is None else Path(cache_dir)
    context = Context(layout, ("fog",)).name
    spec = ScenarioSpec(context=context, severity=severity, seed=sequence_seeds(TheoryConfig(seed=seed))[0],
                        frames=frames, frame_rate_hz=frame_rate_hz, transition="bank")
    ms = measure_and_cache(spec, 0, cache_dir)
    weather = Simulator(spec).weather
    t = np.arange(frames) / frame_rate_hz
    radar = ms.available[:, SENSORS.index("radar")]
    if not radar.any():
        raise UserError("no object was measured by the radar in the fog-bank sequence: try another seed")
    ids, counts = np.unique(ms.actor_ids[radar], return_counts=True)
    oid = int(ids[np.argmax(counts)])
    rows = {int(f): i for i, f in enumerate(ms.frame) if ms.actor_ids[i] == oid}
    truth = np.full((frames, 2), np.nan)
    available = {s: np.zeros(frames, bool) for s in SENSORS}
    meas = []
    for f, i in sorted(rows.items()):
        truth[f] = ms.truth[i]
        for k, s in enumerate(SENSORS):
            if ms.available[i, k]:
                available[s][f] = True
                meas.append(Measurement(t=float(t[f]), sensor=s, z=ms.z[i, k], R=ms.R[i, k], object_id=oid))
    variants = {"all sensors": (None, SENSORS), "all sensors, gated": (gate_prob, SENSORS),
                "camera + radar": (None, ("camera", "radar"))}
    errors, rejected = {}, {s: np.zeros(frames, bool) for s in SENSORS}
    for name, (gate, sensors) in variants.items():
        track = run_cv_tracker([m for m in meas if m.sensor in sensors], gate_prob=gate)
        est = np.full((frames, 2), np.nan)
        for row, (tm, s) in enumerate(zip(track.t, track.sensor)):
            f = int(round(tm * frame_rate_hz))
            est[f] = track.x[row, :2]  # the last update of a frame wins
            if gate is not None and not track.accepted[row]:
                rejected[s][f] = True
        errors[name] = est - truth
    vis = np.array([weather.state_at(x).fog_visibility_m for x in t])
    return BankTracks(t, vis, oid, truth, available, errors, rejected)
