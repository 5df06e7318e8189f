"""Gates with memory on weather that changes (issue 37 item 3): the transitions stage.

A transition set of its own: long sequences (`duration_s` at the study's frame rate) whose weather
ramps (`onset`: clear to the condition, `clearing`: back, `bank`: in, hold, out), one dataset per
(kind, part) so every kind has the same number of sequences, each with its own seed; a validation
part (its own seeds) on which each temporal gate's one parameter is chosen, and a test part on which
everything is scored. Night has no ramp (the generator draws none for it), so the conditions are
fog, rain and snow.

Per frame, the cost of each branch is its a-posteriori per-branch loss against the frame's ground
truth (`study.engine.gate_data.GateData`, as the study's top-1 regret); the a-posteriori best branch
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

The recurrent gate (issue 37 item 3 (c), `fusion.nets.recurrent_gate`): a GRU over each frame's stem
channel means, trained on the gate set's fitting sequences (the epoch kept on its validation
sequences), run on a transition sequence over the last `window` frames (chosen on the validation
part) and, as its own memoryless twin, over one frame. Its entry is scored against that twin
("per-frame") and against the deep gate per frame.

Energy per variant (`variant_energy`): per frame, the compute energy of the chosen branch plus the
stems the gate reads and the gate's own measured time (E = P t on the study's energy scale, PX2 J by
default), and the sensors' energy (EcoFusion Eq. 10 over one fused frame, the paper's Table 3
period): with the gate's reads (a gate that reads a sensor's stem keeps it measuring: every sensor,
for these learned gates), and with clock gating by the choice alone (what the schedule of wake-ups
draws, a waking sensor at full power with no data: the saving a gate would get that did not read
the sensors it switches off).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
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


def variant_energy(choices: Mapping[str, Mapping[str, np.ndarray]], compute: Sequence[float],
                   wanted: Mapping[str, Mapping[str, list]], wake: Mapping[str, int], read: Sequence[str]) -> dict:
    """Per variant: the mean per frame over the test sequences of the compute energy of its chosen
    branch (`compute[b]`, on the study's energy scale), of the sensors' energy with the gate's `read`
    sensors kept measuring, and with clock gating by the choice alone (`fusion.temporal.clock_schedule`,
    a waking sensor at full power); in joules of EcoFusion Eq. 10 over one fused frame."""
    from fusion.eco.energy import total_energy
    from fusion.temporal import clock_schedule

    compute = np.asarray(compute, dtype=float)
    out = {}
    for v, per in choices.items():
        comp, with_reads, by_choice = [], [], []
        for s, ch in per.items():
            sched = clock_schedule(wanted[v][s], wake)
            comp.extend(compute[np.asarray(ch, dtype=int)])
            for powered in sched.powered:
                by_choice.append(total_energy(0.0, powered, "clock"))
                with_reads.append(total_energy(0.0, sorted(set(powered) | set(read)), "clock"))
        out[v] = {"energy_compute": round(float(np.mean(comp)), 4),
                  "energy_sensors_j": round(float(np.mean(with_reads)), 4),
                  "energy_sensors_clock_gated_by_choice_j": round(float(np.mean(by_choice)), 4)}
    return out


def branch_compute_energy(run: Path, branches: Sequence[str], branch_sensors: Mapping[str, Sequence[str]],
                          read: Sequence[str], gate_seconds: float, settings) -> list[float]:
    """Per branch, the compute energy of a frame on which a gate reading the stems of `read` (and
    taking `gate_seconds` of its own) chose that branch alone: the latency model of the gates stage
    (RUN/eco/latency.json, the same table as the study's energy), E = P t (or the counter's measured
    energies scaled by time), on the study's energy scale relative to late fusion of `branches`."""
    import json

    from fusion.eco.energy import LatencyModel, configuration_energy, power_model
    from fusion.eco.optimise import normalise_energy

    path = Path(run) / "eco" / "latency.json"
    if not path.is_file():
        raise UserError(f"{path}: no latency table (the gates stage measures it)")
    lat = LatencyModel.from_dict(json.loads(path.read_text())["model"])
    configs = [[b] for b in branches] + [list(branches)]
    t, e, _source = configuration_energy(lat, configs, power_model(settings.power))
    extra = np.array([gate_seconds + sum(lat.stems.get(x, 0.0) for x in set(read) - set(branch_sensors[b]))
                      for b in branches])
    e_b = e[:-1] * (t[:-1] + extra) / t[:-1]
    return [float(x) for x in normalise_energy(e_b, float(e[-1]), settings.energy_scale)]


def gate_set_sequences(reader, indices: Sequence[int], x: np.ndarray, y: np.ndarray) -> list[tuple]:
    """[(features (T, F), losses (T, n))] per sequence of the frames `indices` (rows of x and y in that
    order), frames in time order, sequences in order of their first index."""
    metas = [reader.meta(int(i)) for i in indices]
    return [(x[rows], y[rows]) for rows in sequences(metas).values()]


def train_recurrent(out: Path, run: Path, gate_data: Path, model, gates, sec, progress: bool):
    """The recurrent gate on the gate set's fitting sequences (the gates' own split: `gates.targets`,
    `val_fraction`, `seed`), its epoch kept on the validation sequences; saved in out/gate.pt with its
    history (reused when its settings match)."""
    import json
    import sys

    import torch

    from fusion.nets.recurrent_gate import RecurrentGate, channel_means, fit_recurrent
    from sensors.dataset import DatasetReader
    from study.engine.checkpoints import load_checkpoint
    from study.engine.gate_data import GateData
    from study.experiments.selection import gate_frames
    from study.outputs import torch_save_atomic, write_json_atomic

    run_cfg = json.loads((Path(run) / "config.json").read_text())
    frames = gate_frames(run_cfg, gate_data, gates.targets, gates.val_fraction, gates.seed, "transitions")
    reader = DatasetReader(gate_data)
    gd = GateData(run, gate_data, model)
    gd.ensure(frames.fit + frames.val, progress=progress)
    parts = {}
    for name, idx in (("fit", frames.fit), ("val", frames.val)):
        x, y = gd.load(idx)
        parts[name] = gate_set_sequences(reader, idx, channel_means(x), y)
    settings = {"epochs": sec.recurrent_epochs, "hidden": sec.recurrent_hidden, "seed": gates.seed,
                "data_key": gd.key, "fit_frames": len(frames.fit), "val_frames": len(frames.val)}
    n_in = parts["fit"][0][0].shape[1]
    gate = RecurrentGate(n_in, len(model.branches), hidden=sec.recurrent_hidden)
    path = out / "gate.pt"
    if path.is_file():
        saved = load_checkpoint(path, ("settings", "state", "info"))
        if saved["settings"] == settings:
            gate.load_state_dict(saved["state"])
            return gate.eval(), saved["info"]
    torch.manual_seed(gates.seed)
    gate = RecurrentGate(n_in, len(model.branches), hidden=sec.recurrent_hidden)

    def say(epoch, row):
        if progress:
            val = "" if row["val_regret"] is None else f", validation regret {row['val_regret']:.4f}"
            sys.stderr.write(f"recurrent gate: epoch {epoch}/{sec.recurrent_epochs}, training MAE "
                             f"{row['train_mae']:.4f}{val}\n")

    info = fit_recurrent(gate, parts["fit"], parts["val"], epochs=sec.recurrent_epochs, seed=gates.seed, progress=say)
    info.update(fit_sequences=len(parts["fit"]), val_sequences=len(parts["val"]), inputs=n_in,
                sequence_frames=sorted({len(x) for x, _ in parts["fit"]}), parameters=sum(
                    p.numel() for p in gate.parameters()))
    out.mkdir(parents=True, exist_ok=True)
    torch_save_atomic({"settings": settings, "state": gate.state_dict(), "info": info}, path)
    write_json_atomic(out / "history.json", info)
    return gate.eval(), info


def time_recurrent_step(gate, repeats: int = 200) -> float:
    """[s] the median of `repeats` single-frame steps of the GRU gate (one thread, state carried), the
    gate's own time per frame when it runs along a sequence."""
    import time

    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        x = torch.zeros(1, 1, gate.input_mean.numel())
        h, times = None, []
        with torch.no_grad():
            for _ in range(repeats + 10):
                t0 = time.perf_counter()
                _, h = gate(x, h)
                times.append(time.perf_counter() - t0)
        return float(np.median(times[10:]))
    finally:
        torch.set_num_threads(threads)


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


@dataclass
class TransitionSet:
    """What every gate's entry is scored on: the transition set's per-branch costs and sequences, the
    learned gates' predictions and the features, with what energy and clock gating need."""

    work: Path
    run: Path
    sec: object
    branches: list
    sensors_of: dict
    metas: list
    manifest: dict
    seqs: dict
    costs: dict
    preds: dict
    feats: np.ndarray
    constant: int
    wake: dict
    read_all: list
    own: dict
    settings: object

    def baselines(self) -> dict:
        test = self.costs["test"]
        return {f"best constant ({self.branches[self.constant]})": {s: np.full(len(c), self.constant)
                                                                    for s, c in test.items()},
                "a-posteriori oracle": {s: np.argmin(c, axis=1) for s, c in test.items()}}

    def wanted(self, choices) -> dict:
        return {v: {s: [sorted(self.sensors_of[self.branches[int(b)]]) for b in ch] for s, ch in per.items()}
                for v, per in choices.items()}

    def score(self, choices, seconds_of, reference: str = "per-frame") -> dict:
        """score_variants over the test sequences, with each variant's energy (`variant_energy`) when the
        study's energy settings are given: the baselines read no stem and take no gate time, the gate's
        variants read every stem it reads and take `seconds_of(variant)` of their own."""
        sec, wanted = self.sec, self.wanted(choices)
        scored = score_variants(self.costs["test"], choices, wanted, self.wake, sec.radius, sec.frame_rate_hz,
                                sec.bootstrap, 0, reference=reference)
        if self.settings is not None:
            for v in choices:
                gate = not v.startswith(("best constant", "a-posteriori"))
                read = self.read_all if gate else []
                compute = branch_compute_energy(self.run, self.branches, self.sensors_of, read,
                                                seconds_of(v) if gate else 0.0, self.settings)
                scored[v].update(variant_energy({v: choices[v]}, compute, wanted, self.wake, read)[v])
        return scored


def load_transition_set(work: Path, run: Path, sec, learned: Sequence[str], profile: str, setup, workers: int,
                        backend: str, batch_size: int, progress: bool, settings) -> tuple[TransitionSet, object]:
    """Generate the transition set (one dataset per part and kind), its gate data under `run`, each
    learned gate's predictions on it -> (the set, the run's network)."""
    from fusion.nets.branch_gates import gate_sensors
    from fusion.temporal import wake_frames_of
    from sensors.combine import combine, part_indices
    from sensors.dataset import DatasetReader
    from sensors.generate import generate
    from sensors.rig import load_profile
    from study.eco.latency_energy import read_gate_latency
    from study.engine.gate_data import GateData
    from study.engine.gate_training import load_trained_gate, predict_losses
    from study.engine.scoring import load_run

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
    rig = load_profile(profile)
    rates = {"camera_right": rig.camera.rate_hz, "camera_left": rig.camera.rate_hz, "lidar": rig.lidar.rate_hz,
             "fwd_lidar": rig.lidar.rate_hz, "radar": rig.radar.rate_hz}
    return TransitionSet(work=work, run=run, sec=sec, branches=branches, sensors_of=dict(model.branch_sensors),
                         metas=metas, manifest=manifest, seqs=seqs, costs=costs, preds=preds, feats=feats,
                         constant=int(np.argmin(losses[val_rows].mean(axis=0))),
                         wake=wake_frames_of(rates, sec.frame_rate_hz), read_all=list(gate_sensors(model)),
                         own=read_gate_latency(run), settings=settings), model


def learned_entry(ts: TransitionSet, g: str) -> tuple[dict, str]:
    """One learned HydraFusion gate per frame, with hysteresis and with an EMA (each parameter chosen on
    validation), beside the baselines; and the figure of one test sequence."""
    from fusion.physical_gate import CAR_QUANTITY
    from sensors.combine import part_indices

    sec, seqs = ts.sec, ts.seqs
    scores = {p: {s: ts.preds[g][rr] for s, rr in seqs[p].items()} for p in PARTS}
    margin, m_trace = choose_parameter(ts.costs["validation"], scores["validation"], "hysteresis", sec.margins)
    alpha, a_trace = choose_parameter(ts.costs["validation"], scores["validation"], "ema", sec.alphas)
    test = ts.costs["test"]
    choices = {"per-frame": {s: variant_choices(scores["test"][s], "per-frame", None) for s in test},
               f"hysteresis (margin {margin:g})": {s: variant_choices(scores["test"][s], "hysteresis", margin)
                                                   for s in test},
               f"EMA (alpha {alpha:g})": {s: variant_choices(scores["test"][s], "ema", alpha) for s in test},
               **ts.baselines()}
    scored = ts.score(choices, lambda v: ts.own.get(f"hydrafusion:{g}", 0.0))
    entry = {"chosen_on": "validation sequences (mean regret)", "margin": margin, "alpha": alpha,
             "margin_trace": m_trace, "alpha_trace": a_trace, "variants": scored}
    shown = set(part_indices(ts.manifest, f"test-{'bank' if 'bank' in sec.kinds else sec.kinds[0]}"))
    s0 = next(s for s, rr in seqs["test"].items() if rr[0] in shown)
    cond = ts.metas[seqs["test"][s0][0]]["context"]
    quantity = CAR_QUANTITY.get(cond, ("visibility_m",))[0]
    x = np.array([ts.metas[r]["weather"][quantity] for r in seqs["test"][s0]])
    fig = plot_sequence(ts.work / f"transition_{g}.png",
                        f"hydrafusion:{g} over one test sequence ({cond}); colour: the branch chosen",
                        x, quantity, {v: ch[s0] for v, ch in choices.items() if v != "a-posteriori oracle"},
                        np.argmin(test[s0], axis=1), ts.branches, sec.frame_rate_hz)
    return entry, fig.name


def recurrent_entry(ts: TransitionSet, model, gate_data: Path, gates, learned: Sequence[str], progress: bool) -> dict:
    """The recurrent gate: trained on the gate set's sequences, its window chosen on the validation
    part, scored beside its memoryless twin ("per-frame"), the deep gate per frame and the baselines."""
    from fusion.nets.recurrent_gate import channel_means

    sec, seqs, costs = ts.sec, ts.seqs, ts.costs
    gate, info = train_recurrent(ts.work / "recurrent", ts.run, gate_data, model, gates, sec, progress)
    means = channel_means(ts.feats)

    def choice(part, window):
        return {s: np.argmin(gate.predict_sequence(means[rr], None if window == 0 else window), axis=1)
                for s, rr in seqs[part].items()}

    trace = {}
    for w in sec.windows:
        ch = choice("validation", w)
        trace[w] = float(np.mean([sequence_scores_regret(costs["validation"][s], ch[s]) for s in ch]))
    window = min(sec.windows, key=lambda w: trace[w])
    name = f"recurrent ({'whole sequence' if window == 0 else f'window {window}'})"
    deep = "deep" if "deep" in learned else (learned[0] if learned else None)
    ref = f"hydrafusion:{deep} per-frame"
    choices = {"per-frame": choice("test", 1), name: choice("test", window)}
    if deep is not None:
        choices[ref] = {s: variant_choices(ts.preds[deep][rr], "per-frame", None) for s, rr in seqs["test"].items()}
    choices.update(ts.baselines())
    step = time_recurrent_step(gate)
    steps = {"per-frame": 1, name: window or 1}  # a window is run again from a zero state each frame

    def seconds(v):
        return steps[v] * step if v in steps else ts.own.get(f"hydrafusion:{deep}", 0.0)

    scored = ts.score(choices, seconds)
    if deep is not None:
        vs = ts.score({ref: choices[ref], name: choices[name]}, seconds, reference=ref)
        for key in ("regret", "regret_transitions"):
            for tail in ("", "_interval"):
                scored[name][f"{key}_minus_deep{tail}"] = vs[name][f"{key}_minus_{ref}{tail}"]
    return {"chosen_on": "validation sequences (mean regret)", "window": window,
            "window_trace": {str(w): round(m, 6) for w, m in trace.items()},
            "trained_on": "the gate set's fitting sequences; epoch kept on its validation sequences (top-1 regret)",
            "training": {k: v for k, v in info.items() if k != "history"}, "history": info["history"],
            "step_ms": round(1000 * step, 4), "variants": scored}


def run_transitions(work: Path, run: Path, sec, learned: Sequence[str], profile: str, setup, workers: int,
                    backend: str, batch_size: int, progress: bool, gate_data: Path | None = None, gates=None,
                    settings=None) -> dict:
    """The stage: the transition set, the per-branch losses and each learned gate's predictions on
    it, every variant chosen on validation and scored on test -> work/transitions.json and figures.
    `run`: the gates stage's run, farmed into the stage's folder (its gate data cache lands there).
    `gate_data`, `gates` (`GatesSection`): the gate set and its split, on which the recurrent gate
    trains (none without them, or with `sec.recurrent_epochs` 0); `settings` (`EcoSettings`): the
    energy scale and power model (energy per variant; none without)."""
    from study.outputs import write_json_atomic

    ts, model = load_transition_set(work, run, sec, learned, profile, setup, workers, backend, batch_size, progress,
                                    settings)
    record = {"what": "gates with memory on weather that changes (issue 37 item 3)", "branches": ts.branches,
              "frames": len(ts.metas), "sequence_seconds": sec.duration_s, "frame_rate_hz": sec.frame_rate_hz,
              "kinds": list(sec.kinds), "conditions": list(sec.conditions), "severities": list(sec.severities),
              "sequences": {p: len(ts.seqs[p]) for p in PARTS},
              "seeds": {n: c.seed for n, c in transition_configs(sec, profile).items()},
              "radius": sec.radius, "wake_frames": ts.wake, "best_constant": ts.branches[ts.constant],
              "cost": "per-branch loss against the frame's ground truth (top 1, as the study's regret)",
              "gates": {}, "figures": []}
    for g in learned:
        record["gates"][f"hydrafusion:{g}"], fig = learned_entry(ts, g)
        record["figures"].append(fig)
    if gate_data is not None and gates is not None and sec.recurrent_epochs > 0:
        record["gates"]["recurrent"] = recurrent_entry(ts, model, gate_data, gates, learned, progress)
    record["energy"] = None if settings is None else {
        "scale": settings.energy_scale, "power": settings.power,
        "compute": "chosen branch + the stems the gate reads + the gate's own measured time (E = P t)",
        "sensors": "EcoFusion Eq. 10 over one fused frame (J): with the gate's reads measuring, and clock-gated "
                   "by the choice alone (a waking sensor at full power)"}
    write_json_atomic(work / "transitions.json", record)
    return record


def sequence_scores_regret(costs, choice) -> float:
    from fusion.temporal import sequence_scores

    return sequence_scores(costs, choice)["regret"]


def check_kinds(kinds: Sequence[str]) -> None:
    bad = [k for k in kinds if k not in KINDS]
    if bad or not kinds or len(set(kinds)) != len(kinds):
        raise UserError(f"transitions.kinds must be distinct names of {', '.join(KINDS)}, got {list(kinds)}")


def check_section(sec) -> None:
    """UserError for a `transitions:` section (`study.pipeline.config.TransitionsSection`) out of range."""

    def _positive(where: str, value, lo=1) -> None:
        if value < lo:
            raise UserError(f"{where} must be >= {lo}, got {value}")

    check_kinds(sec.kinds)
    _positive("transitions.sequences", sec.sequences)
    _positive("transitions.validation_sequences", sec.validation_sequences)
    _positive("transitions.bootstrap", sec.bootstrap)
    _positive("transitions.radius", sec.radius, 0)
    _positive("transitions.seed", sec.seed, 0)
    if not (sec.duration_s > 0 and sec.frame_rate_hz > 0) or round(sec.duration_s * sec.frame_rate_hz) < 2:
        raise UserError("transitions: duration_s x frame_rate_hz must give at least 2 frames per sequence")
    bad = [c for c in sec.conditions if c not in ("fog", "rain", "snow")]
    if bad or not sec.conditions or len(set(sec.conditions)) != len(sec.conditions):
        raise UserError(f"transitions.conditions must be distinct names of fog, rain, snow (night has no ramp), "
                        f"got {list(sec.conditions)}")
    if not sec.severities or any(isinstance(v, bool) or v not in (1, 2, 3, 4, 5) for v in sec.severities):
        raise UserError(f"transitions.severities must be levels 1..5, got {list(sec.severities)}")
    if not sec.margins or any(m < 0 for m in sec.margins):
        raise UserError(f"transitions.margins must be >= 0, got {list(sec.margins)}")
    if not sec.alphas or any(not 0 < a <= 1 for a in sec.alphas):
        raise UserError(f"transitions.alphas must be in (0, 1], got {list(sec.alphas)}")
    _positive("transitions.recurrent_epochs", sec.recurrent_epochs, 0)
    _positive("transitions.recurrent_hidden", sec.recurrent_hidden)
    if not sec.windows or any(isinstance(w, bool) or not isinstance(w, int) or w < 0 for w in sec.windows) \
            or len(set(sec.windows)) != len(sec.windows):
        raise UserError(f"transitions.windows must be distinct whole numbers of frames >= 0 (0: the whole "
                        f"sequence), got {list(sec.windows)}")
