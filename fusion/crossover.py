"""The severity at which fusing a sensor stops paying: where "with the sensor minus without it"
turns negative along a physical severity axis, with intervals.

Inputs are curves over ordered severity steps x_0 .. x_{S-1} (visibility in m, rain or snow rate in
mm/h, illuminance in lux), ordered from mild to strong: for fog and night the quantity falls as the
weather worsens, for rain and snow it rises; `order_steps` puts any of them mild-first. A curve is
the difference d(x) = score(with) - score(without) at each step, estimated on the test frames of
that step, with bootstrap draws of it (whole sequences drawn, with and without scored on the same
draw: paired).

Two readings of the crossover, both reported:

- `first_resolved_below`: the mildest step whose interval of d lies wholly below 0 (the
  conservative statement: "from here on, fusing it costs, resolved"); None when no step is.
- `zero_crossing`: where the curve first passes from >= 0 to < 0, linearly interpolated between the
  two steps around it (on the log of the quantity where the severity table is log-spaced), with a
  percentile interval over the draws' own crossings. A draw that never crosses is "beyond the
  strongest step"; a draw already below 0 at the mildest step crosses "at or before the mildest".
  When more than the interval's tail share of the draws is censored on a side, that bound is open
  (None) and says so.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


def order_steps(values: Sequence[float], worse: str) -> np.ndarray:
    """Indices that order severity `values` from mild to strong; `worse` is "higher" (rain, snow:
    more mm/h is worse) or "lower" (fog visibility, night illuminance)."""
    if worse not in ("higher", "lower"):
        raise ValueError(f"worse must be 'higher' or 'lower', got {worse!r}")
    v = np.asarray(values, dtype=float)
    return np.argsort(v if worse == "higher" else -v, kind="stable")


def _axis(x: np.ndarray, scale: str) -> np.ndarray:
    if scale == "log":
        if np.any(x <= 0):
            raise ValueError("a log-scaled severity needs positive values")
        return np.log(x)
    if scale != "linear":
        raise ValueError(f"scale must be 'linear' or 'log', got {scale!r}")
    return x


def crossing_of(x: Sequence[float], d: Sequence[float], scale: str = "linear") -> tuple[float, str]:
    """Where the curve d over mild-to-strong steps x first goes from >= 0 to < 0, interpolated
    linearly (in log x for `scale` "log"). Returns (value, kind): kind "crossed" (value inside the
    steps), "at_mildest" (d < 0 already at x_0: value x_0), "none" (never below 0: value nan).
    Non-finite d values are skipped."""
    x, d = np.asarray(x, dtype=float), np.asarray(d, dtype=float)
    ok = np.isfinite(d)
    x, d = x[ok], d[ok]
    if not len(d):
        return float("nan"), "none"
    if d[0] < 0:
        return float(x[0]), "at_mildest"
    below = np.flatnonzero(d < 0)
    if not len(below):
        return float("nan"), "none"
    j = int(below[0])
    a = _axis(x[[j - 1, j]], scale)
    t = d[j - 1] / (d[j - 1] - d[j])  # d[j-1] >= 0 > d[j], so 0 <= t < 1
    at = a[0] + t * (a[1] - a[0])
    return float(math.exp(at) if scale == "log" else at), "crossed"


@dataclass(frozen=True)
class Crossover:
    """The crossover of one sensor's with-minus-without curve (module docstring).

    steps: the severity values, mild to strong; estimate / interval: d and its percentile interval
    per step; first_resolved_below: the mildest step whose interval is below 0 (None: none);
    crossing / crossing_kind: the estimate's zero crossing; crossing_interval: percentile interval
    of the draws' crossings as (milder end, stronger end) -- for fog and night the milder end is the
    larger number -- a bound None where censored draws reach into that tail; censored:
    shares of draws at or before the mildest step and beyond the strongest.
    """

    steps: tuple
    estimate: tuple
    interval: tuple
    first_resolved_below: float | None
    crossing: float
    crossing_kind: str
    crossing_interval: tuple
    censored: dict
    level: float

    def as_dict(self) -> dict:
        def num(v):
            return None if v is None or (isinstance(v, float) and not math.isfinite(v)) else round(float(v), 6)

        return {"steps": [num(s) for s in self.steps], "estimate": [num(v) for v in self.estimate],
                "interval": [None if iv is None else [num(iv[0]), num(iv[1])] for iv in self.interval],
                "first_resolved_below": num(self.first_resolved_below), "crossing": num(self.crossing),
                "crossing_kind": self.crossing_kind,
                "crossing_interval": [num(v) for v in self.crossing_interval], "censored": self.censored,
                "level": self.level}


def crossover(steps: Sequence[float], estimate: Sequence[float], draws, scale: str = "linear",
              level: float = 0.95) -> Crossover:
    """`Crossover` of the curve `estimate` (S,) over mild-to-strong `steps` (S,), with bootstrap
    `draws` (B, S) of the same curve (NaN where a draw holds no frame of a step)."""
    x = np.asarray(steps, dtype=float)
    est = np.asarray(estimate, dtype=float)
    dr = np.asarray(draws, dtype=float)
    if x.ndim != 1 or est.shape != x.shape or dr.ndim != 2 or dr.shape[1] != len(x) or not len(dr):
        raise ValueError(f"crossover: steps (S,), estimate (S,), draws (B, S); got {x.shape}, {est.shape}, {dr.shape}")
    if len(x) > 1 and not (np.all(np.diff(_axis(x, scale)) > 0) or np.all(np.diff(_axis(x, scale)) < 0)):
        raise ValueError("crossover: steps must be strictly monotone (order them mild to strong)")
    tail = 50.0 * (1.0 - level)
    intervals = []
    for s in range(len(x)):
        col = dr[:, s][np.isfinite(dr[:, s])]
        intervals.append((float(np.percentile(col, tail)), float(np.percentile(col, 100 - tail))) if len(col) else None)
    resolved = [s for s, iv in enumerate(intervals) if iv is not None and iv[1] < 0]
    value, kind = crossing_of(x, est, scale)
    crossings, kinds = zip(*(crossing_of(x, row, scale) for row in dr))
    kinds = np.array(kinds)
    share_low, share_high = float(np.mean(kinds == "at_mildest")), float(np.mean(kinds == "none"))
    # order every draw along the axis: "at or before the mildest" below all, "none" above all
    a = _axis(x, scale)
    lo_end, hi_end = (a[0], a[-1])
    sign = 1.0 if hi_end >= lo_end else -1.0  # position along mild -> strong
    pos = np.array([-np.inf if k == "at_mildest" else np.inf if k == "none" else sign * _axis(np.array([c]), scale)[0]
                    for c, k in zip(crossings, kinds)])
    q = np.percentile(pos, [tail, 100 - tail], method="inverted_cdf")

    def back(p):
        if not np.isfinite(p):
            return None
        v = sign * p
        return float(math.exp(v) if scale == "log" else v)

    lo, hi = back(q[0]), back(q[1])
    return Crossover(steps=tuple(float(v) for v in x), estimate=tuple(float(v) for v in est),
                     interval=tuple(intervals),
                     first_resolved_below=float(x[resolved[0]]) if resolved else None,
                     crossing=value, crossing_kind=kind, crossing_interval=(lo, hi),
                     censored={"at_or_before_mildest": share_low, "beyond_strongest": share_high},
                     level=float(level))
