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
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from sensors import SENSOR_MODEL_VERSION
from sim.errors import UserError
from study.cli import Formatter, emit, name_arg, nonneg_int, pos_int, severity_arg, workers_int
from study.cli import cache_dir as cache_dir_arg

LAYOUTS = ("city", "junction", "motorway", "rural")
SEVERITY_UNITS = {"fog": ("visibility", "m"), "rain": ("rain", "mm/h"), "snow": ("snowfall", "mm/h"),
                  "night": ("illuminance", "lx")}

EPILOG = """\
conditions: rain, fog, snow, night or combinations such as rain+night, on --layout (default
motorway: the layout with the most traffic in view, so every condition sees the same kind of
scene) unless a condition names its own layout (city+night: street lamps and glare). Severity 0 is
clear weather on the condition's layout, measured once per layout.

Sample size and confidence: with the defaults (40 frames per cell in 4 sequences, 10 s of driving
each) a motorway cell holds ~107 objects; the lidar measures ~80 % of them, the radar ~all, the camera
~25 % in clear weather (it stops at 27 m and rejects unconfident matches), so ~85 objects are seen
by both active sensors and compared (the camera fused where it matched). Errors are heavy-tailed:
an MSE from ~85 of them has a relative standard error of 20-40 % (--json gives each one in
details.mse_se), up to 90 % where one or two gross errors decide it (compare the median and the
trimmed mean printed beside it, and the gross-error lines), so read factors, not digits; a mean NEES from ~25-300 values separates "right" (~2)
from "wrong" (tens to 10^4) but not 2 from 3. --frames 160
--sequences 16 quarters the variances (about 15 minutes on 2 cores).
The default sweep takes ~4 minutes on 2 cores (21 cells, 840 frames); every later run with the same
settings reads the cache and takes about a minute (the analysis: two gated fusions per object).

examples:
  hydrabench theory                                   (all conditions, severities 0-5, ~4 min cold)
  hydrabench theory --conditions fog --severities 0 3 5 --json
  hydrabench theory --frames 200 --sequences 10 --workers 2 --cache /data/theory-cache
"""


def default_cache_dir() -> Path:
    """$HYDRABENCH_CACHE/theory, else $XDG_CACHE_HOME/hydrabench/theory, else ~/.cache/hydrabench/theory."""
    if os.environ.get("HYDRABENCH_CACHE"):
        return Path(os.environ["HYDRABENCH_CACHE"]) / "theory"
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "hydrabench" / "theory"


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
    from tqdm import tqdm

    from fusion.estimation.measurements import MeasurementSet

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
    bar = tqdm(total=frames_todo, unit="frame", desc="theory", file=sys.stderr, disable=not progress or None,
               dynamic_ncols=True)
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


def format_text(result: dict) -> str:
    """Readable tables: per condition, the strategies' MSE and the sensors' nominal-R check."""
    cfg = result["config"]
    lines = [
        f"hydrabench theory: layout {cfg['layout']}, {cfg['frames']} frames per cell in {cfg['sequences']} sequences "
        f"(seed {cfg['seed']}, {cfg['profile']} profile); {result['frames']['measured']} frames measured, "
        f"{result['frames']['cached']} from the cache, {result['seconds']} s",
        "MSE [m^2] on the objects lidar and radar measured (n; each fuses its sensors that measured the object),",
        "strategies cross-fitted over two folds of sequences;",
        "NEES of full fusion with the nominal R against its 95 % bounds; sensor check: true/nominal variance",
        "(radial, lateral) and mean NEES of each sensor alone against its nominal R (2 if right), availability.",
    ]
    for cond, by_sev in result["results"].items():
        lines.append("")
        lines.append(f"{cond} (layout {result['details'][cond][next(iter(by_sev))]['layout']})")
        lines.append(f"  {'sev':>3} {'weather':<26} {'n':>4} {'camera':>8} {'lidar':>8} {'radar':>8} | "
                     f"{'full_nom':>8} {'full_true':>9} {'selective':>9} {'subset':<13} {'gated':>8} | "
                     f"{'NEES':>7} {'95% bounds':<14}")
        for sev, res in by_sev.items():
            det = result["details"][cond][sev]
            if res["mse_full_nominal"] is None:
                lines.append(f"  {sev:>3} {det['weather']:<26} {det['compared']:>4}  {det['note']}")
                continue
            single = res["mse_single"]
            subset = "/".join(sorted({"+".join(s[0] for s in sub) for sub in det["selective_subsets"]}))
            lo, hi = res["nees_bounds"]
            lines.append(
                f"  {sev:>3} {det['weather']:<26} {det['compared']:>4} {_f(single['camera']):>8} {_f(single['lidar']):>8} "
                f"{_f(single['radar']):>8} | {_f(res['mse_full_nominal']):>8} {_f(res['mse_full_true']):>9} "
                f"{_f(res['mse_selective']):>9} {subset:<13} {_f(res['mse_gated']):>8} | "
                f"{_f(res['nees_mean']):>7} [{_f(lo)}, {_f(hi)}]")
        lines.append(f"  {'sev':>3} {'sensor check':<26} " + "  ".join(
            f"{s:<31}" for s in ("camera", "lidar", "radar")))
        for sev in by_sev:
            det = result["details"][cond][sev]
            cells = []
            for s in ("camera", "lidar", "radar"):
                e = det["sensors"][s]
                if not e["n"]:
                    cells.append(f"{'not measured':<31}")
                    continue
                vr = e["variance_ratio"]
                cells.append(f"{_f(vr[0]) + '/' + _f(vr[1]):>13} NEES {_f(e['nees_mean']):>6} {100 * e['availability']:3.0f}%")
            lines.append(f"  {sev:>3} {'':<26} " + "  ".join(f"{c:<31}" for c in cells))
        lines.extend(_robust_lines(result["details"][cond]))
        lines.extend(_gross_lines(result["details"][cond]))
    return "\n".join(lines)


ROBUST_COLUMNS = ("camera", "lidar", "radar", "full_nominal", "full_true", "selective", "gated", "gated_true")
ROBUST_FIGURES = (("mean", "mean"), ("se", "+- se"), ("median", "median"), ("trimmed", "trimmed"))


def _robust_lines(details: dict) -> list[str]:
    """Mean, its standard error, median and 10 % trimmed mean of the squared errors, per column; each
    strategy's paired difference from the better of lidar and radar alone (mean and its se)."""
    head = [f"{'camera':>8} {'lidar':>8} {'radar':>8}", f"{'full_nom':>8} {'full_true':>9} {'selective':>9} "
            f"{'gated':>8} {'gated_true':>10}"]
    lines = [f"  {'sev':>3} {'squared error':<14} {head[0]} | {head[1]}"]
    for sev, det in details.items():
        if "robust" not in det:
            continue
        rob = det["robust"]
        for i, (key, label) in enumerate(ROBUST_FIGURES):
            v = [_f(rob[c][key]) for c in ROBUST_COLUMNS]
            lines.append(f"  {sev if i == 0 else '':>3} {label:<14} {v[0]:>8} {v[1]:>8} {v[2]:>8} | {v[3]:>8} "
                         f"{v[4]:>9} {v[5]:>9} {v[6]:>8} {v[7]:>10}")
        paired = det["paired_vs_best_single"]
        for key, label in (("mean", f"- {paired['best_single']}"), ("se", "  +- se")):
            v = [_f(paired[c][key]) if key == "se" or paired[c][key] is None
                 else f"{paired[c][key]:+.3g}" for c in ROBUST_COLUMNS[3:]]
            lines.append(f"  {'':>3} {label:<14} {'':>8} {'':>8} {'':>8} | {v[0]:>8} {v[1]:>9} {v[2]:>9} {v[3]:>8} "
                         f"{v[4]:>10}")
    return lines


def _gross_lines(details: dict) -> list[str]:
    """Gross errors per sensor (count of measured, causes), the gate's verdicts, the fused SSE they carry."""
    lines = [f"  {'sev':>3} gross errors, NEES > {_f(_gross_bound())} against each sensor's nominal R (its gate: 'gated') "
             "or measured R (its gate: 'gated_true'):",
             f"  {'':>3} gross/measured (causes) | what the gate did | share of full fusion's summed squared error "
             "on those objects; MSE on the other objects"]
    for sev, det in details.items():
        if "gross" not in det:
            continue
        g = det["gross"]
        for i, (kind, fused) in enumerate((("nominal", "full_nominal"), ("measured", "full_true"))):
            parts, gate = [], {}
            for s, d in g["per_sensor"][kind].items():
                causes = ", ".join(f"{c} {n}" for c, n in d["causes"].items())
                parts.append(f"{s} {d['gross']}/{d['n']}" + (f" ({causes})" if causes else ""))
                for o, n in d["gate"][kind].items():
                    gate[o] = gate.get(o, 0) + n
            verdict = ", ".join(f"{o} {n}" for o, n in gate.items()) or "-"
            share = g["sse_share"][fused]
            without = g["mse_without_gross"][kind]
            rest = ", ".join(f"{name} {_f(without[name])}" for name in ("lidar", "radar", fused))
            lines.append(f"  {sev if i == 0 else '':>3} {kind + ' R:':<12} " + "; ".join(parts)
                         + f" | gate: {verdict} | {fused} SSE share {_pct(share)}; MSE without them: {rest}")
    return lines


def _gross_bound() -> float:
    from fusion.estimation.gross import GROSS_BOUND

    return GROSS_BOUND


def _pct(v) -> str:
    return "-" if v is None else f"{100 * v:.0f} %"


def _f(v) -> str:
    if v is None:
        return "-"
    v = float(v)
    if v == 0:
        return "0"
    if abs(v) >= 1000:
        return f"{v:.3g}"
    if abs(v) >= 10:
        return f"{v:.1f}"
    if abs(v) >= 0.01:
        return f"{v:.3f}"
    return f"{v:.1e}"


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


def add_parser(sub, name: str, help_text: str) -> None:
    p = sub.add_parser(name, help=help_text, description=help_text + "\n\n" + __doc__.split("\n\n", 1)[1],
                       epilog=EPILOG, formatter_class=Formatter)
    p.add_argument("--conditions", nargs="+", type=name_arg, default=list(TheoryConfig.conditions),
                   help="conditions (rain, fog, snow, night), combinations (rain+night), optionally on "
                        "their own layout (city+night)")
    p.add_argument("--severities", nargs="+", type=severity_arg, default=list(TheoryConfig.severities),
                   help="severities 0-5 (0 = clear, shared by all conditions)")
    p.add_argument("--layout", default=TheoryConfig.layout, choices=LAYOUTS,
                   help="road layout of the conditions that name none")
    p.add_argument("--frames", type=pos_int, default=TheoryConfig.frames, help="frames per condition and severity")
    p.add_argument("--sequences", type=pos_int, default=TheoryConfig.sequences,
                   help="sequences the frames of a cell are split into (>= 2)")
    p.add_argument("--seed", type=nonneg_int, default=TheoryConfig.seed, help="root random seed")
    p.add_argument("--profile", type=name_arg, default=TheoryConfig.profile, help="sensor profile (cpu, paper)")
    p.add_argument("--cache", type=cache_dir_arg, default=None,
                   help="cache directory for the measurements (default: $HYDRABENCH_CACHE/theory or "
                        "~/.cache/hydrabench/theory)")
    p.add_argument("--workers", type=workers_int, default=min(2, os.cpu_count() or 1),
                   help="parallel worker processes for uncached sequences")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(run=run)


def run(args) -> int:
    from study.outputs import check_writable_dir

    config = TheoryConfig(conditions=tuple(dict.fromkeys(condition_name(c) for c in args.conditions)),
                          severities=tuple(dict.fromkeys(int(s) for s in args.severities)),
                          layout=args.layout, frames=args.frames, sequences=args.sequences, seed=args.seed,
                          profile=args.profile)
    cache_dir = check_writable_dir(args.cache if args.cache is not None else default_cache_dir())
    result = run_theory(config, cache_dir, workers=args.workers, progress=True)
    emit(result, args.json, format_text)
    return 0
