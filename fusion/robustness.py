"""The robustness metrics of the corruption benchmarks, per condition c and severity s, as plain functions.

A score A is any "higher is better" figure in [0, 1] (here: mAP@0.5). Scores are passed as nested
mappings ``{condition: {severity: A}}``; a severity that was not measured is simply absent (or None /
NaN), and every mean below runs over the severities and conditions that were measured.

- Resistance ability / relative accuracy (MultiCorrupt: Beemelmanns et al., "MultiCorrupt: A
  Multi-Modal Robustness Dataset and Benchmark of LiDAR-Camera Fusion for 3D Object Detection",
  IEEE IV 2024, arXiv:2402.11677; the definitions as the authors' README "Metrics" writes them):
  ``RA_{c,s} = A_{c,s} / A_clean``, ``RA_c = 1/S sum_s RA_{c,s}``, ``mRA = 1/N sum_c RA_c``.
- Corruption error and resilience rate (Robo3D: Kong et al., "Robo3D: Towards Robust and Reliable 3D
  Perception against Corruptions", ICCV 2023; the definitions as the authors' README "Robo3D
  Benchmark" writes them, with 3 severity levels there):
  ``CE_c = sum_s (1 - A_{c,s}) / sum_s (1 - A^baseline_{c,s})``, ``mCE = 1/N sum_c CE_c``;
  ``RR_c = sum_s A_{c,s} / (S * A_clean)``, ``mRR = 1/N sum_c RR_c``.
  (Equation numbers of the papers are not quoted: only the repositories' READMEs were at hand.)

Paired twins. Where every degraded frame has a counterfactual clear twin (the same frame, only the
weather differs), the clean score of a severity is the twins' score of exactly that severity's frames
(`twin_relative_accuracy`), and the interval comes from drawing whole sequences with replacement,
numerator and denominator from the same draw (`fusion.metrics.sequence_draws`).

Severity in physical units: `severity_value` reads the project's one severity table
(`sim.weather.SEVERITY_TABLE`, via `sim.weather.representative_weather`).

Rule for an undefined ratio: a clean score that is 0, negative, missing or NaN makes RA and RR NaN
(a detector that finds nothing on clean data has no robustness to speak of); a baseline whose
errors sum to 0 makes CE NaN. NaN terms are left out of the means; a mean over nothing is NaN.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Callable, Hashable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from fusion.metrics import sequence_draws
from sim.weather import SEVERITY_TABLE, representative_weather, severity_interval

Scores = Mapping[str, Mapping[int, float | None]]
"""{condition: {severity: score}}; a missing severity is absent, None or NaN."""


def _finite(v) -> bool:
    return v is not None and not math.isnan(float(v))


def _mean(values) -> float:
    v = [x for x in values if _finite(x)]
    return float(np.mean(v)) if v else float("nan")


def _clean_of(clean: float | Scores | None, condition: str, severity: int):
    return clean.get(condition, {}).get(severity) if isinstance(clean, Mapping) else clean


def relative_accuracy(score: float | None, clean: float | None) -> float:
    """RA_{c,s} = A_{c,s} / A_clean (MultiCorrupt's resistance ability): 1 means no loss under the
    corruption, 0 nothing left. NaN when either score is missing or `clean` <= 0."""
    if not (_finite(score) and _finite(clean)) or clean <= 0:
        return float("nan")
    return float(score) / float(clean)


def relative_accuracies(scores: Scores, clean: float | Scores) -> dict[str, dict[int, float]]:
    """RA_{c,s} for every measured (c, s). `clean`: one clean score A_clean (the benchmarks' setting),
    or {condition: {severity: A}} of each severity's own clear twins (paired twins)."""
    return {c: {s: relative_accuracy(a, _clean_of(clean, c, s)) for s, a in per.items() if _finite(a)}
            for c, per in scores.items()}


def mean_relative_accuracy(ra: Scores) -> float:
    """mRA = 1/N sum_c RA_c with RA_c = 1/S_c sum_s RA_{c,s} (MultiCorrupt), over the severities
    measured of each condition and the conditions with at least one (a mean of means, so a condition
    with a missing severity weighs as much as one with all)."""
    return _mean(_mean(per.values()) for per in ra.values())


def corruption_error(scores: Mapping[int, float | None], baseline: Mapping[int, float | None]) -> float:
    """CE_c = sum_s (1 - A_{c,s}) / sum_s (1 - A^baseline_{c,s}) (Robo3D), over the severities both
    have a score at. Below 1: fewer errors than the baseline under this corruption. NaN when they
    share no severity or the baseline makes no error there."""
    common = [s for s, a in scores.items() if _finite(a) and _finite(baseline.get(s))]
    den = sum(1.0 - baseline[s] for s in common)
    if not common or den <= 0:
        return float("nan")
    return sum(1.0 - scores[s] for s in common) / den


def mean_corruption_error(scores: Scores, baseline: Scores) -> float:
    """mCE = 1/N sum_c CE_c (Robo3D) over the conditions both were measured under; the baseline
    (a named model, e.g. late fusion) has mCE = 1 against itself."""
    return _mean(corruption_error(per, baseline[c]) for c, per in scores.items() if c in baseline)


def resilience_rate(scores: Mapping[int, float | None], clean: float | Mapping[int, float | None]) -> float:
    """RR_c = sum_s A_{c,s} / (S * A_clean) (Robo3D), S the number of severities measured. With
    paired twins (`clean` a {severity: A} of each severity's twins) the denominator is the twins'
    sum over the same severities, sum_s A^twin_{c,s}, which is S * A_clean when the twins score alike.
    NaN when nothing is measured or the clean denominator is <= 0."""
    if isinstance(clean, Mapping):
        sev = [s for s, a in scores.items() if _finite(a) and _finite(clean.get(s))]
        den = sum(clean[s] for s in sev)
    else:
        sev = [s for s, a in scores.items() if _finite(a)]
        den = len(sev) * clean if _finite(clean) else float("nan")
    if not sev or not den > 0:
        return float("nan")
    return sum(scores[s] for s in sev) / den


def mean_resilience_rate(scores: Scores, clean: float | Scores) -> float:
    """mRR = 1/N sum_c RR_c (Robo3D); `clean` as in `relative_accuracies`."""
    return _mean(resilience_rate(per, clean.get(c, {}) if isinstance(clean, Mapping) else clean)
                 for c, per in scores.items())


# --- paired twins ----------------------------------------------------------------------------------

@dataclass(frozen=True)
class TwinRatio:
    """RA of one set of degraded frames against their clear twins, with a sequence-bootstrap interval.

    ra: A_degraded / A_twins over all the frames (NaN when the twins score <= 0).
    degraded, clear: the two scores.
    interval: [2.5th, 97.5th] percentile of the ratio over the draws (None without draws, or when no
        draw had a clear score > 0).
    sequences, frames: how many sequences and frames the estimate stands on.
    degraded_interval, clear_interval: the same percentiles of the two scores over the same draws.
    """

    ra: float
    degraded: float
    clear: float
    interval: tuple[float, float] | None
    sequences: int
    frames: int
    degraded_interval: tuple[float, float] | None = None
    clear_interval: tuple[float, float] | None = None


def _percentiles(values) -> tuple[float, float] | None:
    """[2.5th, 97.5th] percentile of the finite values (None when none is)."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    return (float(np.percentile(v, 2.5)), float(np.percentile(v, 97.5))) if len(v) else None


def twin_relative_accuracy(score_degraded: Callable[[Sequence[int]], float],
                           score_clear: Callable[[Sequence[int]], float],
                           sequence_of: Sequence[Hashable], *, resamples: int = 1000,
                           seed: int = 0, on_draw: Callable[[], object] | None = None) -> TwinRatio:
    """RA = A(degraded frames) / A(their clear twins), paired, with a cluster-bootstrap interval.

    Items are 0..n-1; item i is a degraded frame and its twin, `sequence_of[i]` its sequence.
    `score_degraded(items)` / `score_clear(items)` score a multiset of items (repeats allowed), e.g.
    `fusion.metrics.ImageMatches.mean_ap` of the degraded and of the twin frames in the same order.
    Each draw takes whole sequences with replacement (`fusion.metrics.sequence_draws`) and scores
    both on the same items, so the ratio's interval is paired: the scene content the two share
    cancels, and only the condition's effect varies. `on_draw`: called after each draw (a progress bar).
    """
    by_seq: dict = defaultdict(list)
    for i, q in enumerate(sequence_of):
        by_seq[q].append(i)
    items = list(range(len(sequence_of)))
    d, c = float(score_degraded(items)), float(score_clear(items))
    draws = np.empty((resamples, 3))
    for r, draw in enumerate(sequence_draws(by_seq, resamples, seed)):
        dd, cc = score_degraded(draw), score_clear(draw)
        draws[r] = (dd, cc, relative_accuracy(dd, cc))
        if on_draw is not None:
            on_draw()
    return TwinRatio(relative_accuracy(d, c), d, c, _percentiles(draws[:, 2]), len(by_seq), len(items),
                     _percentiles(draws[:, 0]), _percentiles(draws[:, 1]))


def twin_relative_accuracy_by_severity(score_degraded: Callable[[Sequence[int]], float],
                                       score_clear: Callable[[Sequence[int]], float],
                                       sequence_of: Sequence[Hashable], severity_of: Sequence[int], *,
                                       resamples: int = 1000, seed: int = 0,
                                       on_draw: Callable[[], object] | None = None) -> dict[int, TwinRatio]:
    """`twin_relative_accuracy` per severity: the RA at severity s comes from the frames at s and the
    twins of exactly those frames, its interval from resampling the sequences at s. Items and
    scorers as `twin_relative_accuracy`; `severity_of[i]` is item i's severity."""
    if len(severity_of) != len(sequence_of):
        raise ValueError(f"severity_of has {len(severity_of)} items, sequence_of {len(sequence_of)}")
    out = {}
    for s in sorted(set(severity_of)):
        idx = [i for i, v in enumerate(severity_of) if v == s]

        def sub(score, idx=idx):
            return lambda items: score([idx[j] for j in items])

        out[s] = twin_relative_accuracy(sub(score_degraded), sub(score_clear), [sequence_of[i] for i in idx],
                                        resamples=resamples, seed=seed, on_draw=on_draw)
    return out


# --- physical units --------------------------------------------------------------------------------

def severity_value(condition: str, severity: int) -> tuple[float, str]:
    """(value, unit) of a condition's primary quantity at severity 0..5: the centre of the level's
    interval in `sim.weather.SEVERITY_TABLE` (geometric for log-scaled quantities; the state
    `sim.weather.representative_weather` builds), e.g. ("fog", 3) -> (212.1, "m") of visibility.
    Severity 0 is the clear state's value (20 km visibility, 0 mm/h, 30 klx)."""
    if severity != 0:
        severity_interval(condition, severity)  # the one-line UserError for a bad condition or level
    elif condition not in SEVERITY_TABLE:
        severity_interval(condition, 1)
    spec = SEVERITY_TABLE[condition]
    return float(getattr(representative_weather(condition, severity), spec["quantity"])), spec["unit"]


def severity_quantity(condition: str) -> str:
    """The physical quantity a condition's severity is drawn in (`sim.weather.SEVERITY_TABLE`), e.g.
    "fog_visibility_m"."""
    if condition not in SEVERITY_TABLE:
        severity_interval(condition, 1)
    return SEVERITY_TABLE[condition]["quantity"]
