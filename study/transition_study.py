"""Gates with memory on weather that changes (issue 37 item 3): the transitions stage.

A transition set of its own: long sequences (`duration_s` at the study's frame rate) whose weather
ramps (`onset`: clear to the condition, `clearing`: back, `bank`: in, hold, out), one dataset per
(kind, part) so every kind has the same number of sequences, each with its own seed; a validation
part (its own seeds) on which each temporal gate's one parameter is chosen, and a test part on which
everything is scored. Night has no ramp (the generator draws none for it), so the conditions are
fog, rain and snow.

Per frame, the cost of each branch is its a-posteriori per-branch loss against the frame's ground
truth (`study.gate_data.GateData`, as the study's top-1 regret); the a-posteriori best branch
changes along the sequence as the weather ramps. Each trained HydraFusion gate's predicted losses
are the scores its variants choose from (`fusion.temporal`):

- per-frame: argmin of the frame's scores (the gate as the study scores it, top 1);
- hysteresis: keep the held branch until another is predicted better by more than a margin;
- EMA: argmin of an exponential moving average of the scores;
- the best constant (the branch of lowest mean loss on the validation part) and the a-posteriori
  oracle (regret 0, its own switches shown for scale).

Scored per test sequence (`fusion.temporal.sequence_scores`): regret over the sequence and inside
the transition windows (frames within `radius` of a change of the best branch), switching lag,
switches per minute; with intervals over sequences (whole sequences redrawn, paired with the
per-frame gate). Clock gating over time (EcoFusion 5.5.2, `fusion.temporal.clock_schedule`): the
sensors a variant's choices want, each woken one full measurement period before it gives data, the
wake-ups and the frames a wanted sensor was still waking counted.

Not here: a recurrent gate over stem features trained on sequences (issue 37 item 3 (c)).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from sim.errors import UserError

KINDS = ("onset", "clearing", "bank")
PARTS = ("validation", "test")


def part_seed(seed: int, part: str, kind: str) -> int:
    """Each (part, kind) dataset's seed: seed + 10 * kind index (+ 5 for validation)."""
    return int(seed) + 10 * KINDS.index(kind) + (5 if part == "validation" else 0)


def transition_configs(sec, profile: str) -> dict[str, object]:
    """{"<part>-<kind>": GenerateConfig} of the transition set."""
    from sensors.generate import GenerateConfig

    length = int(round(sec.duration_s * sec.frame_rate_hz))
    out = {}
    for part in PARTS:
        n = sec.validation_sequences if part == "validation" else sec.sequences
        for kind in sec.kinds:
            out[f"{part}-{kind}"] = GenerateConfig(
                contexts=tuple(sec.conditions), frames_per_context=n * length, seed=part_seed(sec.seed, part, kind),
                profile=profile, sequence_length=length, frame_rate_hz=sec.frame_rate_hz,
                severities=tuple(sec.severities), transitions=(kind,), twins=False)
    return out


def sequences(metas: Sequence[Mapping]) -> dict[str, list[int]]:
    """{sequence_id: rows in time order}."""
    out: dict[str, list[int]] = {}
    for r, m in enumerate(metas):
        out.setdefault(m["sequence_id"], []).append(r)
    return {s: sorted(rows, key=lambda r: metas[r]["frame_index"]) for s, rows in out.items()}


def variant_choices(scores: np.ndarray, variant: str, value: float | None) -> np.ndarray:
    from fusion.temporal import ema_choice, hysteresis_choice, per_frame_choice

    if variant == "per-frame":
        return per_frame_choice(scores)
    if variant == "hysteresis":
        return hysteresis_choice(scores, margin=float(value))
    if variant == "ema":
        return ema_choice(scores, alpha=float(value))
    raise ValueError(f"unknown variant {variant!r}")


def choose_parameter(costs: Mapping[str, np.ndarray], scores: Mapping[str, np.ndarray], variant: str,
                     values: Sequence[float]) -> tuple[float, dict]:
    """The value of `variant`'s parameter with the lowest mean per-sequence regret over the validation
    sequences ({sequence: costs (T, n)}, {sequence: scores (T, n)}); ties to the earlier value."""
    from fusion.temporal import sequence_scores

    mean = {}
    for v in values:
        mean[v] = float(np.mean([sequence_scores(costs[s], variant_choices(scores[s], variant, v))["regret"]
                                 for s in costs]))
    best = min(values, key=lambda v: mean[v])
    return float(best), {str(v): round(m, 6) for v, m in mean.items()}


def _mean_or_none(values) -> float | None:
    v = [x for x in values if x is not None]
    return round(float(np.mean(v)), 6) if v else None


def _interval(values: np.ndarray, resamples: int, seed: int) -> list | None:
    """Percentile 95 % interval of the mean of per-sequence `values` over draws of sequences."""
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], dtype=float)
    if len(v) < 2:
        return None
    from fusion.intervals import percentile_interval

    rng = np.random.default_rng(seed)
    means = v[rng.integers(0, len(v), size=(resamples, len(v)))].mean(axis=1)
    return [round(x, 6) for x in percentile_interval(means)]


def score_variants(costs: Mapping[str, np.ndarray], choices: Mapping[str, Mapping[str, np.ndarray]],
                   wanted: Mapping[str, Mapping[str, list]], wake: Mapping[str, int], radius: int,
                   frame_rate_hz: float, resamples: int, seed: int, reference: str = "per-frame") -> dict:
    """Per variant ({variant: {sequence: choice (T,)}}): the mean over test sequences of the
    regret, the regret in transition windows, the switching lag (uncensored changes; the censored
    share beside it), switches per minute, the clock-gating wake-ups and frames a wanted sensor was
    still waking; each variant's regret minus the `reference` variant's with its interval over
    sequences (paired: the same sequences drawn)."""
    from fusion.temporal import clock_schedule, sequence_scores

    seqs = list(costs)
    per = {v: {s: sequence_scores(costs[s], ch[s], radius, frame_rate_hz) for s in seqs} for v, ch in choices.items()}
    out = {}
    for v, rows in per.items():
        lags = [lag for s in seqs for lag in rows[s]["lags"]]
        done = [lag for lag in lags if lag is not None]
        clock = [clock_schedule(wanted[v][s], wake) for s in seqs]
        minutes = sum(rows[s]["frames"] for s in seqs) / frame_rate_hz / 60.0
        rec = {"regret": round(float(np.mean([rows[s]["regret"] for s in seqs])), 6),
               "regret_interval": _interval(np.array([rows[s]["regret"] for s in seqs]), resamples, seed),
               "regret_transitions": _mean_or_none([rows[s]["regret_transitions"] for s in seqs]),
               "lag_mean_frames": round(float(np.mean(done)), 3) if done else None,
               "lag_censored_share": round(1 - len(done) / len(lags), 4) if lags else None,
               "changes_of_best": len(lags),
               "switches_per_minute": round(float(sum(rows[s]["switches"] for s in seqs) / minutes), 3),
               "wakes_per_minute": round(float(sum(sum(c.wakes.values()) for c in clock) / minutes), 3),
               "frames_waiting_for_a_sensor": int(sum(c.missing_frames() for c in clock))}
        if v != reference and reference in per:
            for key in ("regret", "regret_transitions"):
                d = np.array([(rows[s][key] - per[reference][s][key])
                              if rows[s][key] is not None and per[reference][s][key] is not None else np.nan
                              for s in seqs])
                rec[f"{key}_minus_{reference}"] = round(float(np.nanmean(d)), 6) if np.isfinite(d).any() else None
                rec[f"{key}_minus_{reference}_interval"] = _interval(d, resamples, seed)
        out[v] = rec
    return out


def plot_sequence(path: Path, title: str, x: np.ndarray, quantity: str, choices: Mapping[str, np.ndarray],
                  best: np.ndarray, branches: Sequence[str], frame_rate_hz: float) -> Path:
    """One sequence: the weather quantity over time, and below it each variant's branch per frame
    beside the a-posteriori best."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.arange(len(x)) / frame_rate_hz
    rows = {"a-posteriori best": best, **choices}
    fig, axes = plt.subplots(2, 1, figsize=(9, 4.8), sharex=True, gridspec_kw={"height_ratios": [1, 2]})
    axes[0].plot(t, x, color="k")
    axes[0].set_ylabel(quantity, fontsize=8)
    if quantity in ("visibility_m", "illuminance_lux"):
        axes[0].set_yscale("log")
    ax = axes[1]
    for i, ch in enumerate(rows.values()):
        ax.scatter(t, np.full(len(t), i) + (np.asarray(ch) - (len(branches) - 1) / 2) * 0.12, s=6,
                   c=[f"C{int(c)}" for c in ch])
    ax.set_yticks(range(len(rows)), list(rows), fontsize=8)
    for j, b in enumerate(branches):
        ax.scatter([], [], c=f"C{j}", s=12, label=b)
    ax.legend(fontsize=7, ncol=len(branches), loc="upper center", bbox_to_anchor=(0.5, -0.18))
    ax.set_xlabel("time [s]")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def run_transitions(work: Path, run: Path, sec, learned: Sequence[str], profile: str, setup, workers: int,
                    backend: str, batch_size: int, progress: bool) -> dict:
    """The stage: the transition set, the per-branch losses and each learned gate's predictions on
    it, every variant chosen on validation and scored on test -> work/transitions.json and figures.
    `run`: the gates stage's run, farmed into the stage's folder (its gate data cache lands there)."""
    from fusion.physical_gate import CAR_QUANTITY
    from fusion.temporal import wake_frames_of
    from sensors.combine import combine, part_indices
    from sensors.dataset import DatasetReader
    from sensors.generate import generate
    from sensors.rig import load_profile
    from study.branch_gate_study import load_trained_gate, predict_losses
    from study.gate_data import GateData
    from study.outputs import write_json_atomic
    from study.scoring import load_run

    parts = {}
    for name, gcfg in transition_configs(sec, profile).items():
        generate(gcfg, work / "sets" / name, workers=workers, progress=progress, backend=backend)
        parts[name] = work / "sets" / name
    combine(parts, work / "data")
    data = work / "data"
    model, _ = load_run(run, "latest", device=setup.device)
    reader = DatasetReader(data)
    every = list(range(len(reader)))
    gd = GateData(run, data, model)
    gd.ensure(every, batch_size=batch_size, progress=progress)
    branches = list(model.branches)
    losses = np.array([[row[b] for b in branches] for row in gd.branch_losses(every)])
    metas = [dict(reader.meta(i), dataset_index=i) for i in every]
    feats = gd.arrays(every, ["features"])["features"]
    preds = {g: predict_losses(load_trained_gate(run, g, model), feats, metas=metas) for g in learned}
    manifest = reader.manifest
    rows_of = {p: [r for k in sec.kinds for r in part_indices(manifest, f"{p}-{k}")] for p in PARTS}
    seqs = {p: sequences([metas[r] for r in rows_of[p]]) for p in PARTS}
    seqs = {p: {s: [rows_of[p][i] for i in rr] for s, rr in seqs[p].items()} for p in PARTS}
    costs = {p: {s: losses[rr] for s, rr in seqs[p].items()} for p in PARTS}
    val_rows = [r for rr in seqs["validation"].values() for r in rr]
    constant = int(np.argmin(losses[val_rows].mean(axis=0)))
    rig = load_profile(profile)
    rates = {"camera_right": rig.camera.rate_hz, "camera_left": rig.camera.rate_hz, "lidar": rig.lidar.rate_hz,
             "fwd_lidar": rig.lidar.rate_hz, "radar": rig.radar.rate_hz}
    wake = wake_frames_of(rates, sec.frame_rate_hz)
    sensors_of = model.branch_sensors
    record = {"what": "gates with memory on weather that changes (issue 37 item 3)", "branches": branches,
              "frames": len(every), "sequence_seconds": sec.duration_s, "frame_rate_hz": sec.frame_rate_hz,
              "kinds": list(sec.kinds), "conditions": list(sec.conditions), "severities": list(sec.severities),
              "sequences": {p: len(seqs[p]) for p in PARTS},
              "seeds": {n: c.seed for n, c in transition_configs(sec, profile).items()},
              "radius": sec.radius, "wake_frames": wake, "best_constant": branches[constant],
              "cost": "per-branch loss against the frame's ground truth (top 1, as the study's regret)",
              "gates": {}}
    figures = []
    for g in learned:
        scores = {p: {s: preds[g][rr] for s, rr in seqs[p].items()} for p in PARTS}
        margin, m_trace = choose_parameter(costs["validation"], scores["validation"], "hysteresis", sec.margins)
        alpha, a_trace = choose_parameter(costs["validation"], scores["validation"], "ema", sec.alphas)
        test = costs["test"]
        choices = {"per-frame": {s: variant_choices(scores["test"][s], "per-frame", None) for s in test},
                   f"hysteresis (margin {margin:g})": {s: variant_choices(scores["test"][s], "hysteresis", margin)
                                                       for s in test},
                   f"EMA (alpha {alpha:g})": {s: variant_choices(scores["test"][s], "ema", alpha) for s in test},
                   f"best constant ({branches[constant]})": {s: np.full(len(c), constant) for s, c in test.items()},
                   "a-posteriori oracle": {s: np.argmin(c, axis=1) for s, c in test.items()}}
        wanted = {v: {s: [sorted(sensors_of[branches[int(b)]]) for b in ch] for s, ch in per.items()}
                  for v, per in choices.items()}
        scored = score_variants(test, choices, wanted, wake, sec.radius, sec.frame_rate_hz, sec.bootstrap, 0)
        record["gates"][f"hydrafusion:{g}"] = {"chosen_on": "validation sequences (mean regret)", "margin": margin,
                                               "alpha": alpha, "margin_trace": m_trace, "alpha_trace": a_trace,
                                               "variants": scored}
        shown = set(part_indices(manifest, f"test-{'bank' if 'bank' in sec.kinds else sec.kinds[0]}"))
        s0 = next(s for s, rr in seqs["test"].items() if rr[0] in shown)
        cond = metas[seqs["test"][s0][0]]["context"]
        quantity = CAR_QUANTITY.get(cond, ("visibility_m",))[0]
        x = np.array([metas[r]["weather"][quantity] for r in seqs["test"][s0]])
        figures.append(plot_sequence(work / f"transition_{g}.png",
                                     f"hydrafusion:{g} over one test sequence ({cond}); colour: the branch chosen",
                                     x, quantity, {v: ch[s0] for v, ch in choices.items() if v != "a-posteriori oracle"},
                                     np.argmin(test[s0], axis=1), branches, sec.frame_rate_hz).name)
    record["figures"] = figures
    write_json_atomic(work / "transitions.json", record)
    return record


def check_kinds(kinds: Sequence[str]) -> None:
    bad = [k for k in kinds if k not in KINDS]
    if bad or not kinds or len(set(kinds)) != len(kinds):
        raise UserError(f"transitions.kinds must be distinct names of {', '.join(KINDS)}, got {list(kinds)}")
