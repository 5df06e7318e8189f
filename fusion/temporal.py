"""Gates with memory, and how to score a gate over a sequence whose weather changes.

A per-frame gate reads one frame and picks argmin of its scores (lower is better, as everywhere in
`fusion.gate_objectives`). Over a sequence that is noisy: a gate that flips between two near-equal
choices switches sensors on and off for nothing. Two classic remedies, as plain functions of the
per-frame scores (T, n) of one sequence, in time order:

- `hysteresis_choice`: keep the current choice until another beats it by `margin` (in score
  units), and for at least `min_dwell` frames after a switch. On an input that never changes it
  never switches.
- `ema_choice`: argmin of an exponential moving average of the scores, s~_t = a s_t + (1 - a)
  s~_{t-1}: the lag after a step change of the best choice is about ln(...)/ln(1 - a) frames
  (`ema_lag_bound` gives the exact bound for a step).

Scoring over a sequence (`sequence_scores`): regret over all frames and inside transition windows
(frames within `radius` of a change of the a-posteriori best choice), the switching lag (frames from
each change of the best choice until the gate holds the new best; censored at the sequence's end),
and the number of switches.

Sensor clock gating over time (EcoFusion Section 5.5.2): a sensor no chosen configuration uses is
clock-gated (its motor keeps spinning, its measurement power P^meas is off); one that is needed again
must be woken first, which takes its wake-up time (a sweep at its own rate: `wake_frames`), during
which it draws full power but gives no data. `clock_schedule` turns a gate's wanted sensors per frame
into the sensors actually available and powered per frame, with the wake-ups counted.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np


def _scores(scores) -> np.ndarray:
    s = np.asarray(scores, dtype=float)
    if s.ndim != 2 or not s.shape[0] or not s.shape[1]:
        raise ValueError(f"scores: expected a non-empty (T, n) array, got shape {s.shape}")
    return s


def per_frame_choice(scores) -> np.ndarray:
    """argmin per frame (ties to the first choice): the gate without memory."""
    return np.argmin(_scores(scores), axis=1)


def hysteresis_choice(scores, margin: float, min_dwell: int = 0) -> np.ndarray:
    """Per frame, the choice held: start at frame 0's argmin; switch to frame t's argmin only when its
    score is lower than the held choice's by more than `margin` and the held choice has been kept for
    at least `min_dwell` frames."""
    s = _scores(scores)
    if margin < 0 or min_dwell < 0:
        raise ValueError(f"margin and min_dwell must be >= 0, got {margin!r}, {min_dwell!r}")
    out = np.empty(len(s), dtype=int)
    held, since = int(np.argmin(s[0])), 0
    for t, row in enumerate(s):
        best = int(np.argmin(row))
        if best != held and row[held] - row[best] > margin and since >= min_dwell:
            held, since = best, 0
        out[t] = held
        since += 1
    return out


def ema_scores(scores, alpha: float) -> np.ndarray:
    """s~_0 = s_0, s~_t = alpha s_t + (1 - alpha) s~_{t-1}; alpha in (0, 1] (1: no memory)."""
    s = _scores(scores)
    if not 0.0 < alpha <= 1.0:
        raise ValueError(f"alpha must be in (0, 1], got {alpha!r}")
    out = np.empty_like(s)
    out[0] = s[0]
    for t in range(1, len(s)):
        out[t] = alpha * s[t] + (1.0 - alpha) * out[t - 1]
    return out


def ema_choice(scores, alpha: float) -> np.ndarray:
    """argmin of `ema_scores` per frame."""
    return np.argmin(ema_scores(scores, alpha), axis=1)


def ema_lag_bound(alpha: float, gap_before: float, gap_after: float) -> int:
    """Frames an EMA gate needs to follow a step change of two choices' scores: before the step
    choice A leads B by `gap_before` (> 0), after it B leads A by `gap_after` (> 0). The averaged
    difference B - A after k frames is gap_before (1-a)^k - gap_after (1 - (1-a)^k); the gate switches
    at the first k where it is negative: k > ln(gap_after / (gap_before + gap_after)) / ln(1 - a).
    Returns that k (0-based frames after the step, so 0 means "on the step's own frame")."""
    if not 0.0 < alpha <= 1.0 or gap_before <= 0 or gap_after <= 0:
        raise ValueError("ema_lag_bound: alpha in (0, 1], both gaps > 0")
    if alpha == 1.0:
        return 0
    k = math.log(gap_after / (gap_before + gap_after)) / math.log(1.0 - alpha)
    # the EMA at the step's own frame already holds one step of the new value: k counts those
    return max(0, math.floor(k))


def switches(choice: Sequence[int]) -> int:
    """How often the choice changes from one frame to the next."""
    c = np.asarray(choice)
    return int(np.sum(c[1:] != c[:-1])) if len(c) > 1 else 0


def change_points(best: Sequence[int]) -> np.ndarray:
    """Frames t where the best choice differs from frame t-1's."""
    b = np.asarray(best)
    return np.flatnonzero(b[1:] != b[:-1]) + 1


def switching_lags(best: Sequence[int], choice: Sequence[int]) -> list[int | None]:
    """Per change of the best choice (at frame t), frames until the gate holds the new best (0: at t);
    None when it never does before the next change or the sequence's end (censored)."""
    b, c = np.asarray(best), np.asarray(choice)
    if b.shape != c.shape:
        raise ValueError("switching_lags: best and choice must have the same length")
    points = list(change_points(b))
    out: list[int | None] = []
    for i, t in enumerate(points):
        end = points[i + 1] if i + 1 < len(points) else len(b)
        hits = np.flatnonzero(c[t:end] == b[t])
        out.append(int(hits[0]) if len(hits) else None)
    return out


def transition_mask(best: Sequence[int], radius: int) -> np.ndarray:
    """Frames within `radius` frames (either side) of a change of the best choice."""
    b = np.asarray(best)
    mask = np.zeros(len(b), dtype=bool)
    for t in change_points(b):
        mask[max(0, t - radius):min(len(b), t + radius + 1)] = True
    return mask


def sequence_scores(costs, choice: Sequence[int], radius: int = 3, frame_rate_hz: float | None = None) -> dict:
    """A gate's choice over one sequence against the a-posteriori best per frame (costs (T, n),
    lower is better): regret over all frames and in the transition windows, lags, switches (and
    switches per minute given the frame rate)."""
    c = _scores(costs)
    ch = np.asarray(choice, dtype=int)
    if ch.shape != (len(c),):
        raise ValueError(f"choice: expected ({len(c)},), got {ch.shape}")
    best = np.argmin(c, axis=1)
    gap = c[np.arange(len(c)), ch] - c.min(axis=1)
    window = transition_mask(best, radius)
    lags = switching_lags(best, ch)
    n_sw = switches(ch)
    out = {"frames": len(c), "regret": float(gap.mean()),
           "regret_transitions": float(gap[window].mean()) if window.any() else None,
           "transition_frames": int(window.sum()), "changes_of_best": len(lags), "lags": lags,
           "switches": n_sw, "best_switches": switches(best)}
    if frame_rate_hz:
        out["switches_per_minute"] = n_sw / (len(c) / frame_rate_hz / 60.0)
    return out


@dataclass(frozen=True)
class ClockSchedule:
    """Per frame: the sensors the gate wanted, those whose data it had (awake), and those powered
    (awake or waking). wakes: how many times each sensor was woken."""

    wanted: tuple
    usable: tuple
    powered: tuple
    wakes: dict

    def missing_frames(self) -> int:
        """Frames where some wanted sensor gave no data (it was still waking)."""
        return sum(1 for w, u in zip(self.wanted, self.usable) if not set(w) <= set(u))


def clock_schedule(wanted: Sequence[Sequence[str]], wake_frames: Mapping[str, int],
                   initially_on: Sequence[str] | None = None) -> ClockSchedule:
    """Which sensors are usable and powered per frame when the gate's wanted sensors are followed
    with clock gating: a sensor not wanted is gated at once; a gated sensor wanted at frame t gives
    data from frame t + wake_frames[s] on (full power from t), as long as it stays wanted.
    `initially_on`: sensors awake at frame 0 (default: those wanted at frame 0)."""
    awake = set(initially_on if initially_on is not None else (wanted[0] if len(wanted) else ()))
    ready_at: dict[str, int] = {}
    wakes: dict[str, int] = {}
    usable, powered = [], []
    for t, w in enumerate(wanted):
        w = set(w)
        unknown = w - set(wake_frames)
        if unknown:
            raise ValueError(f"clock_schedule: no wake-up time for {sorted(unknown)}")
        for s in list(awake):
            if s not in w:
                awake.discard(s)
        for s in list(ready_at):
            if s not in w:
                del ready_at[s]  # no longer wanted while waking: gated again
        for s in w - awake - set(ready_at):
            ready_at[s] = t + int(wake_frames[s])
            wakes[s] = wakes.get(s, 0) + 1
        for s, at in list(ready_at.items()):
            if at <= t:
                awake.add(s)
                del ready_at[s]
        usable.append(tuple(sorted(awake & w)))
        powered.append(tuple(sorted(awake | set(ready_at))))
    return ClockSchedule(wanted=tuple(tuple(sorted(w)) for w in wanted), usable=tuple(usable),
                         powered=tuple(powered), wakes=wakes)


def wake_frames_of(rates_hz: Mapping[str, float], frame_rate_hz: float) -> dict[str, int]:
    """A clock-gated sensor's wake-up in frames: one full measurement period at its own rate (its
    motor still spins, so the next complete sweep or exposure is the first usable), rounded up to
    frames of the study's rate."""
    if frame_rate_hz <= 0 or any(r <= 0 for r in rates_hz.values()):
        raise ValueError("wake_frames_of: rates must be > 0")
    return {s: max(1, math.ceil(frame_rate_hz / r - 1e-9)) for s, r in rates_hz.items()}
