"""A knowledge gate whose rules come from measured crossovers (issue 37): drop a sensor when a
physical quantity a car can measure passes the severity at which fusing that sensor stops paying.

HydraFusion's knowledge gate (`fusion.nets.branch_gates.KnowledgeGate`) ranks branches with a
hand-written table of reliabilities. This one has no table: each rule says "drop every branch that
reads sensor S when quantity Q is at or beyond T", where (S, Q) is a sensor and a condition whose
measured with-minus-without curve turns negative (`fusion.crossover`) and T is chosen among that
crossover's readings (`threshold_candidates`) on validation frames (`choose_thresholds`).

What it reads (`CAR_QUANTITY`): only what a car measures, from the frame's weather record:

- fog: the visibility (meteorological optical range, m) that a forward-scatter visibility sensor
  gives: `visibility_m`, every extinction together (fog, rain, snow), not the fog's own share;
- rain and snow: the precipitation rate (mm/h, snow as water equivalent) of a rain sensor or a
  disdrometer: `rain_mm_h`, `snow_mm_h`;
- night: the ambient illuminance (lux) of a light sensor (what switches on headlights):
  `illuminance_lux`.

Never the severity level, the context label, the lens coverage or anything drawn from the labels:
`physical_selection` is given the weather record alone (`weather_of` takes it out of a frame's
meta), so it cannot read ground truth.

A rule drops a *modality* (`fusion.nets.branch_gates.MODALITY`): the camera rule drops both
cameras' branches (a stereo pair sees the same weather), the lidar rule every branch that reads
the lidar, early-fusion branches included. When every branch would go, all are kept: a car that
drops every sensor sees nothing, and the rules were measured one sensor at a time.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

CAR_QUANTITY: dict[str, tuple[str, str, str]] = {
    "fog": ("visibility_m", "lower", "log"),
    "rain": ("rain_mm_h", "higher", "log"),
    "snow": ("snow_mm_h", "higher", "linear"),
    "night": ("illuminance_lux", "lower", "log"),
}
"""Condition -> (the weather record's quantity a car measures, which way is worse, the axis scale
the severity table draws it on: `sim.weather.SEVERITY_TABLE`)."""

NEVER = None
"""The candidate threshold that keeps the sensor whatever the quantity (the rule is off)."""


@dataclass(frozen=True)
class DropRule:
    """Drop the branches reading `sensor`'s modality when `quantity` is at or beyond `threshold`
    (at or below it when `worse` is "lower", at or above when "higher")."""

    sensor: str
    condition: str
    quantity: str
    worse: str
    threshold: float

    def fires(self, weather: Mapping[str, float]) -> bool:
        if self.quantity not in weather:
            raise KeyError(f"the weather record has no {self.quantity!r} (the {self.condition} rule reads it)")
        v = float(weather[self.quantity])
        return v <= self.threshold if self.worse == "lower" else v >= self.threshold

    def text(self) -> str:
        op = "<=" if self.worse == "lower" else ">="
        return f"drop {self.sensor} when {self.quantity} {op} {self.threshold:.4g}"

    def as_dict(self) -> dict:
        return {"sensor": self.sensor, "condition": self.condition, "quantity": self.quantity, "worse": self.worse,
                "threshold": self.threshold, "text": self.text()}


def rule(sensor: str, condition: str, threshold: float) -> DropRule:
    """The rule for `sensor` under `condition` at `threshold` (in `CAR_QUANTITY`'s unit)."""
    if condition not in CAR_QUANTITY:
        raise ValueError(f"unknown condition {condition!r} (known: {', '.join(CAR_QUANTITY)})")
    if not math.isfinite(threshold):
        raise ValueError(f"the {condition} threshold must be finite, got {threshold}")
    quantity, worse, _ = CAR_QUANTITY[condition]
    return DropRule(sensor, condition, quantity, worse, float(threshold))


def weather_of(meta: Mapping) -> dict[str, float]:
    """The quantities of a frame's meta that a car measures (`CAR_QUANTITY`), and nothing else."""
    w = meta.get("weather")
    if not isinstance(w, Mapping):
        raise ValueError("the frame's meta has no weather record ('weather'): the physical gate reads it")
    return {q: float(w[q]) for q, _, _ in CAR_QUANTITY.values()}


def modality_of(sensor: str) -> str:
    from fusion.nets.branch_gates import MODALITY

    if sensor not in MODALITY:
        raise ValueError(f"unknown sensor {sensor!r} (known: {', '.join(MODALITY)})")
    return MODALITY[sensor]


def dropped(weather: Mapping[str, float], rules: Sequence[DropRule]) -> set[str]:
    """The modalities the rules drop for this weather."""
    return {modality_of(r.sensor) for r in rules if r.fires(weather)}


def physical_selection(weather: Mapping[str, float], branches: Sequence[str],
                       branch_sensors: Mapping[str, Sequence[str]], rules: Sequence[DropRule]) -> tuple[str, ...]:
    """The branches the gate runs for a frame of this `weather` (`weather_of`): every branch but
    those reading a dropped modality; all of them when that would leave none."""
    drop = dropped(weather, rules)
    keep = tuple(b for b in branches if not {modality_of(s) for s in branch_sensors[b]} & drop)
    return keep or tuple(branches)


def threshold_candidates(crossover: Mapping, bounds: tuple[float, float] | None = None) -> list[float | None]:
    """The thresholds a rule may take from one measured crossover (`fusion.crossover.Crossover.as_dict`):
    `NEVER` (the rule off), the zero crossing of the estimate, the mildest step resolved below zero,
    and the two ends of the crossing's interval, each where it exists; a crossing "at or before the
    mildest step" reads as the mild end of the sweep (`bounds` (mild, strong) of the quantity, else
    the mildest step). Nothing but `NEVER` when the curve never goes below zero."""
    out: list[float | None] = [NEVER]
    mild = bounds[0] if bounds else (crossover["steps"][0] if crossover.get("steps") else None)
    kind = crossover.get("crossing_kind")
    if kind == "crossed":
        out.append(crossover["crossing"])
    elif kind == "at_mildest" and mild is not None:
        out.append(mild)
    out.append(crossover.get("first_resolved_below"))
    ends = crossover.get("crossing_interval") or [None, None]
    if kind != "none" or crossover.get("first_resolved_below") is not None:
        out.extend(ends)
    seen, uniq = set(), []
    for v in out:
        key = None if v is None else round(float(v), 9)
        if (v is None or math.isfinite(float(v))) and key not in seen:
            seen.add(key)
            uniq.append(None if v is None else float(v))
    return uniq


OBSERVED_QUANTILES = (0.0, 0.25, 0.5, 0.75, 1.0)
"""Where `observed_candidates` puts a rule's thresholds: these quantiles of the observed values, counted
from the worst end (0: the worst value seen, 1: the mildest)."""


def observed_candidates(values: Sequence[float], condition: str,
                        quantiles: Sequence[float] = OBSERVED_QUANTILES) -> list[float | None]:
    """The thresholds a rule under `condition` may take when no crossover was measured: `NEVER`, then
    the values of its quantity (`CAR_QUANTITY`) at `quantiles` of `values` (the quantity on frames where
    the condition holds, e.g. a gate set's fitting frames), counted from the worst end and each one a
    value that was seen: at 0 the rule fires on the worst frame only, at 1 on every frame seen. Ordered
    NEVER first, then from the worst end, so that `choose_thresholds`, which keeps the earlier candidate
    on a tie, keeps a sensor and then drops it on as few frames as it can. Nothing but `NEVER` without values."""
    if condition not in CAR_QUANTITY:
        raise ValueError(f"unknown condition {condition!r} (known: {', '.join(CAR_QUANTITY)})")
    v = [float(x) for x in values if math.isfinite(float(x))]
    out: list[float | None] = [NEVER]
    if not v:
        return out
    ordered = sorted(v, reverse=CAR_QUANTITY[condition][1] == "higher")  # worst first
    for q in quantiles:
        if not 0.0 <= q <= 1.0:
            raise ValueError(f"quantiles must lie in [0, 1], got {q}")
        t = ordered[min(len(ordered) - 1, int(math.floor(q * (len(ordered) - 1) + 0.5)))]
        if t not in out:
            out.append(t)
    return out


def choose_thresholds(candidates: Mapping[tuple[str, str], Sequence[float | None]],
                      score: Callable[[list[DropRule]], float], passes: int = 2) -> tuple[list[DropRule], list[dict]]:
    """Coordinate ascent over the rules: for each (sensor, condition) in `candidates`' order, the
    candidate threshold that maximises `score(rules)` (mAP on validation frames) with the other rules
    at their current value, starting from every rule off; `passes` sweeps or until nothing changes.
    Ties keep the earlier candidate (`NEVER` first: a sensor is dropped only for a strict gain).
    Returns (the rules that are on, the trace of every evaluation)."""
    current: dict[tuple[str, str], float | None] = {k: NEVER for k in candidates}

    def rules_of(assign) -> list[DropRule]:
        return [rule(s, c, t) for (s, c), t in assign.items() if t is not None]

    trace: list[dict] = []
    cache: dict[tuple, float] = {}

    def value(assign) -> float:
        key = tuple(sorted((k, v) for k, v in assign.items() if v is not None))
        if key not in cache:
            cache[key] = float(score(rules_of(assign)))
        return cache[key]

    best = value(current)
    trace.append({"rules": [], "score": best})
    for _ in range(max(1, passes)):
        changed = False
        for key, options in candidates.items():
            for t in options:
                if t == current[key]:
                    continue
                trial = {**current, key: t}
                v = value(trial)
                trace.append({"rules": [r.text() for r in rules_of(trial)], "score": v})
                if v > best:
                    best, current, changed = v, trial, True
        if not changed:
            break
    return rules_of(current), trace
