"""The crossover study (issue 37): at what physical severity fusing each sensor stops paying.

For each condition (fog, rain, snow, night) a *sweep set* of its own (`sweep_configs`: one dataset
per severity level, each with the same number of sequences, its own seed and its clear twins,
combined into one view) is run through the detectors once; then, at every severity step, each base
fusion (late fusion of the single-sensor branches; all branches) is scored with and without each
sensor, fused by the study's declared fusion, and the paired difference d = with - without is
bootstrapped by whole sequences within the step (`fusion.bounds.bootstrap_table`, the step's own
seed; steps are disjoint sequences, so their draws are independent). `fusion.crossover.crossover`
turns each curve into its crossover: the mildest step resolved below zero, and the interpolated zero
crossing with a percentile interval over the draws' own crossings.

The severity axis is what a car measures (`fusion.physical_gate.CAR_QUANTITY`: visibility in m,
rain and snow rate in mm/h, illuminance in lux), each step placed at the median of its frames'
values (the levels' intervals do not overlap, `sim.weather.SEVERITY_TABLE`, so the medians are
ordered). The same frames' clear twins are scored on the same draws: "twin" is d on the twins of
each step (the scene without the weather: what the sensor adds when nothing degrades it), and
"clear" pools every step's twins of the condition.

Dropping a sensor drops its modality's branches (`fusion.physical_gate.modality_of`): from late
fusion its single-sensor branch, from all branches every branch that reads it (radar_lidar loses
both its radar and its lidar). The record is what the physical knowledge gate's rules come from
(`fusion.physical_gate`) and what the report and the figures show (`plot_crossovers`).
"""

from __future__ import annotations

import json
import pickle
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from fusion.boxes import method_labels, method_name
from fusion.physical_gate import CAR_QUANTITY, modality_of
from sim.errors import UserError

SENSORS = ("camera_right", "lidar", "radar")
BASES = ("late", "all_branches")
BASE_LABEL = {"late": "late fusion (single-sensor branches)", "all_branches": "all branches"}
COLOURS = {"camera_right": "#1f77b4", "lidar": "#2ca02c", "radar": "#d62728"}


def level_seed(seed: int, severity: int) -> int:
    """The seed of the sweep set's level `severity` (each level is a dataset of its own)."""
    return int(seed) + int(severity)


def sweep_configs(sec, profile: str) -> dict[int, object]:
    """{severity: GenerateConfig} of the sweep set (`sec`: the study's `crossover` section): each level
    its own dataset of `sec.conditions`, `sec.frames_per_step` frames per condition in sequences of
    `sec.sequence_length`, seed `level_seed`, with clear twins."""
    from sensors.generate import GenerateConfig

    return {s: GenerateConfig(contexts=tuple(sec.conditions), frames_per_context=sec.frames_per_step,
                              seed=level_seed(sec.seed, s), profile=profile, sequence_length=sec.sequence_length,
                              frame_rate_hz=sec.frame_rate_hz, severities=(s,), twins=True)
            for s in sec.severities}


def generate_sweep_set(work: Path, sec, profile: str, workers: int, backend: str, progress: bool) -> Path:
    """Generate every level (each resumes its missing shards when run again) and their view; returns it."""
    from sensors.combine import combine
    from sensors.generate import generate

    parts = {}
    for s, gcfg in sweep_configs(sec, profile).items():
        out = work / "levels" / f"severity-{s}"
        generate(gcfg, out, workers=workers, progress=progress, backend=backend)
        parts[f"severity-{s}"] = out
    combine(parts, work / "data")
    return work / "data"


def drop_sets(branches: Sequence[str], branch_sensors: Mapping[str, Sequence[str]], singles: Sequence[str]) -> dict:
    """{base: {"with": branches, sensor: branches without that sensor's modality}} for `BASES`; a sensor
    no branch of the base reads, or whose removal leaves nothing, is left out."""
    bases = {"late": tuple(singles), "all_branches": tuple(branches)}
    out = {}
    for base, members in bases.items():
        out[base] = {"with": members}
        for s in SENSORS:
            m = modality_of(s)
            keep = tuple(b for b in members if m not in {modality_of(x) for x in branch_sensors[b]})
            if keep and keep != members:
                out[base][s] = keep
    return out


def _set_name(branches: Sequence[str]) -> str:
    return "+".join(branches)


def _matches(per_frame: list, sets: Mapping[str, tuple], frames: dict, method: str, reader, protocol) -> dict:
    from fusion.metrics import ImageMatches
    from sim.actors import CLASSES
    from study.engine.scoring import fused, ground_truth

    metas = [m for m, _ in per_frame]
    gts = [ground_truth(reader.labels(m["dataset_index"]), "camera_right", None, m, protocol) for m in metas]
    classes = list(range(1, len(CLASSES) + 1))
    out = {}
    for name, branches in sets.items():
        dets = [{"boxes": d.boxes, "scores": d.scores, "labels": d.labels}
                for _, d in fused(per_frame, branches, frames, method)]
        out[name] = ImageMatches.of(dets, gts, classes=classes)
    return out


def _interval(values: np.ndarray, level: float) -> list | None:
    """`fusion.intervals.percentile_interval` as a list (what the JSON record holds)."""
    from fusion.intervals import percentile_interval

    iv = percentile_interval(values, level)
    return None if iv is None else list(iv)


def curves_record(metas: Sequence[Mapping], matches: Mapping, twin_matches: Mapping, sets: Mapping[str, dict],
                  resamples: int, seed: int, level: float = 0.95) -> dict:
    """Every condition's with-minus-without curves and crossovers (module docstring) from the
    matchings of each fused branch set on the degraded frames (`matches`) and on their clear twins
    (`twin_matches`), rows in `metas`' order. `sets`: `drop_sets`."""
    from fusion.bounds import bootstrap_table
    from fusion.crossover import crossover
    from sim.weather import SEVERITY_TABLE

    names = sorted({_set_name(b) for d in sets.values() for b in d.values()})
    conditions = sorted({m["context"] for m in metas if m["context"] in CAR_QUANTITY})
    out: dict = {}
    for ci, cond in enumerate(conditions):
        quantity, worse, scale = CAR_QUANTITY[cond]
        rows = [r for r, m in enumerate(metas) if m["context"] == cond]
        levels = sorted({int(metas[r]["severity"]) for r in rows})
        steps, deg_draws, twin_draws = [], [], []
        all_twin_rows: dict = {}
        for li, sev in enumerate(levels):
            step_rows = [r for r in rows if int(metas[r]["severity"]) == sev]
            by_seq: dict = {}
            for r in step_rows:
                by_seq.setdefault(metas[r]["sequence_id"], []).append(r)
            all_twin_rows.update(by_seq)
            x = [float(metas[r]["weather"][quantity]) for r in step_rows]
            draw_seed = seed + 1000 * ci + li
            deg_draws.append(bootstrap_table(matches, names, by_seq, resamples, draw_seed))
            twin_draws.append(bootstrap_table(twin_matches, names, by_seq, resamples, draw_seed))
            steps.append({"severity": sev, "x": float(np.median(x)), "x_range": [float(min(x)), float(max(x))],
                          "frames": len(step_rows), "sequences": len(by_seq),
                          "point": {n: float(matches[n].mean_ap(step_rows)) for n in names},
                          "twin_point": {n: float(twin_matches[n].mean_ap(step_rows)) for n in names}})
        pooled = bootstrap_table(twin_matches, names, all_twin_rows, resamples, seed + 1000 * ci + 999)
        xs = [st["x"] for st in steps]
        curves: dict = {}
        for base, d in sets.items():
            w = names.index(_set_name(d["with"]))
            curves[base] = {}
            for sensor, without in d.items():
                if sensor == "with":
                    continue
                o = names.index(_set_name(without))
                est = [st["point"][_set_name(d["with"])] - st["point"][_set_name(without)] for st in steps]
                draws = np.stack([dd[:, w] - dd[:, o] for dd in deg_draws], axis=1)
                tw = np.stack([td[:, w] - td[:, o] for td in twin_draws], axis=1)
                c = crossover(xs, est, draws, scale=scale, level=level).as_dict()
                c["twin_estimate"] = [st["twin_point"][_set_name(d["with"])] - st["twin_point"][_set_name(without)]
                                      for st in steps]
                c["twin_interval"] = [_interval(tw[:, i], level) for i in range(len(steps))]
                # what the weather does to the sensor's worth: d minus the same frames' twin d, paired
                c["weather_effect_interval"] = [_interval(draws[:, i] - tw[:, i], level) for i in range(len(steps))]
                every = [r for rr in all_twin_rows.values() for r in rr]
                c["clear"] = {"estimate": float(twin_matches[_set_name(d["with"])].mean_ap(every)
                                                - twin_matches[_set_name(without)].mean_ap(every)),
                              "interval": _interval(pooled[:, w] - pooled[:, o], level)}
                c["without"] = list(without)
                curves[base][sensor] = c
        out[cond] = {"quantity": quantity, "unit": SEVERITY_TABLE[cond]["unit"], "worse": worse, "scale": scale,
                     "steps": [{k: v for k, v in st.items() if k not in ("point", "twin_point")} |
                               {"map": {n: round(v, 6) for n, v in st["point"].items()}} for st in steps],
                     "curves": curves}
    return out


def half_widths(conditions: Mapping) -> dict:
    """The median and largest half-width of the per-step intervals of d, over every curve: how finely
    the sweep set resolves a step (what its size buys)."""
    hw = [(iv[1] - iv[0]) / 2 for c in conditions.values() for base in c["curves"].values()
          for cur in base.values() for iv in cur["interval"] if iv is not None]
    return {"median": float(np.median(hw)) if hw else None, "max": float(max(hw)) if hw else None, "curves": len(hw)}


def summary_rows(record: Mapping) -> list[dict]:
    """One row per (base, condition, sensor): the crossover in the condition's unit, for tables."""
    rows = []
    for cond, c in record["conditions"].items():
        for base, per in c["curves"].items():
            for sensor, cur in per.items():
                rows.append({"base": base, "condition": cond, "sensor": sensor, "unit": c["unit"],
                             "quantity": c["quantity"], "crossing": cur["crossing"], "kind": cur["crossing_kind"],
                             "interval": cur["crossing_interval"], "first_resolved_below": cur["first_resolved_below"],
                             "censored": cur["censored"], "clear": cur["clear"]})
    return rows


def crossing_text(row: Mapping) -> str:
    """'none up to the strongest step', 'at or before the mildest step (X unit)', or 'X unit [a, b]'."""
    unit = row["unit"]
    if row["kind"] == "none":
        return "none up to the strongest step"

    def num(v):
        return "open" if v is None else f"{v:.3g}"

    lo, hi = row["interval"]
    if row["kind"] == "at_mildest":
        return f"at or before the mildest step ({row['crossing']:.3g} {unit}) [{num(lo)}, {num(hi)}]"
    return f"{row['crossing']:.3g} {unit} [{num(lo)}, {num(hi)}]"


def plot_crossovers(record: Mapping, out_dir: Path, machine: str = "") -> list[Path]:
    """crossover.png (rows: the bases, columns: the conditions) and crossover_<condition>.png (one
    condition, both bases): with-minus-without against the severity, mild to strong from left to
    right, one line per sensor with its 95 % band, the same frames' clear twins dotted, the crossing
    and its interval marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    conds = list(record["conditions"])
    paths = []

    def panel(ax, cond, base):
        c = record["conditions"][cond]
        for sensor, cur in c["curves"].get(base, {}).items():
            x = np.array(cur["steps"])
            est = np.array(cur["estimate"])
            lo = np.array([np.nan if iv is None else iv[0] for iv in cur["interval"]])
            hi = np.array([np.nan if iv is None else iv[1] for iv in cur["interval"]])
            col = COLOURS.get(sensor, "k")
            ax.plot(x, est, "-o", color=col, ms=3, label=sensor)
            ax.fill_between(x, lo, hi, color=col, alpha=0.15, lw=0)
            ax.plot(x, cur["twin_estimate"], ":", color=col, lw=1)
            if cur["crossing_kind"] != "none" and cur["first_resolved_below"] is not None:
                ax.axvline(cur["crossing"], color=col, lw=1, ls="--")
                a, b = cur["crossing_interval"]
                xs = sorted(v for v in (a if a is not None else x[0], b if b is not None else x[-1]))
                ax.axvspan(xs[0], xs[1], ymin=0.0, ymax=0.04, color=col, alpha=0.6)
        ax.axhline(0, color="k", lw=0.8)
        if c["scale"] == "log":
            from matplotlib.ticker import FuncFormatter, NullFormatter

            ax.set_xscale("log")
            ax.set_xticks([st["x"] for st in c["steps"]])
            ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:.3g}"))
            ax.xaxis.set_minor_formatter(NullFormatter())
        if c["worse"] == "lower":
            ax.invert_xaxis()
        ax.set_xlabel(f"{c['quantity']} [{c['unit']}]\nmild → strong", fontsize=8)
        ax.set_title(f"{cond}: {BASE_LABEL[base]}", fontsize=9)
        ax.grid(alpha=0.3)

    n = len(conds)
    fig, axes = plt.subplots(len(BASES), n, figsize=(3.6 * n, 6.2), squeeze=False)
    for j, cond in enumerate(conds):
        for i, base in enumerate(BASES):
            panel(axes[i][j], cond, base)
            if j == 0:
                axes[i][j].set_ylabel("mAP with − without the sensor")
    axes[0][0].legend(fontsize=8, loc="best")
    fig.suptitle(f"When fusing a sensor stops paying: {record['frames_per_step']} frames per condition and step, "
                 f"{record['resamples']} sequence draws, fusion {record['fusion']}\nband: 95 % interval per step; "
                 "dotted: the same frames' clear twins;\ndashed: the zero crossing of a curve with a step resolved "
                 "below 0, bar: its 95 % interval" + (f"\n{machine}" if machine else ""), fontsize=9)
    fig.tight_layout()
    p = out_dir / "crossover.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)
    for cond in conds:
        fig, axes = plt.subplots(1, len(BASES), figsize=(9, 3.6), squeeze=False)
        for i, base in enumerate(BASES):
            panel(axes[0][i], cond, base)
        axes[0][0].set_ylabel("mAP with − without the sensor")
        axes[0][0].legend(fontsize=8)
        fig.tight_layout()
        p = out_dir / f"crossover_{cond}.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(p)
    return paths


def run_crossover(work: Path, run_paper: Path, sec, profile: str, fusion: str, setup, workers: int, backend: str,
                  batch_size: int, progress: bool) -> dict:
    """The whole stage: the sweep set, the detectors over it and its twins (cached in
    work/detections.pkl, so a run killed while scoring does not detect again), the curves and the
    figures -> work/crossover.json."""
    from sensors.dataset import DatasetReader
    from study.eco.latency_energy import machine_description
    from study.engine.scoring import load_run, run_branches
    from study.engine.train import run_protocol
    from study.outputs import write_json_atomic

    data = generate_sweep_set(work, sec, profile, workers, backend, progress)
    model, run_cfg = load_run(run_paper, "latest", device=setup.device)
    reader, clear = DatasetReader(data), DatasetReader(data, clear=True)
    indices = list(range(len(reader)))
    branches = list(model.branches)
    cache = work / "detections.pkl"
    if cache.is_file():
        deg, twin = pickle.loads(cache.read_bytes())
    else:
        deg = run_branches(model, data, indices, branches, batch_size=batch_size, progress="crossover: detect")
        twin = run_branches(model, data, indices, branches, batch_size=batch_size, progress="crossover: clear twins",
                            clear=True)
        tmp = cache.with_suffix(".tmp")
        tmp.write_bytes(pickle.dumps((deg, twin)))
        tmp.replace(cache)
    from fusion.eco.configurations import SINGLE_SENSORS

    sensors_of = model.branch_sensors
    singles = [b for b in branches if len(sensors_of[b]) == 1 and sensors_of[b][0] in SINGLE_SENSORS]
    sets = drop_sets(branches, sensors_of, singles)
    every = {_set_name(b): tuple(b) for d in sets.values() for b in d.values()}
    if fusion not in method_labels():
        raise UserError(f"crossover.fusion must be one of {', '.join(method_labels())} (declared in advance), got "
                        f"{fusion!r}")
    method = method_name(fusion)
    protocol = run_protocol(run_cfg)
    metas = [m for m, _ in deg]
    matches = _matches(deg, every, model.branch_frames, method, reader, protocol)
    twin_matches = _matches(twin, every, model.branch_frames, method, clear, protocol)
    conditions = curves_record(metas, matches, twin_matches, sets, sec.bootstrap, sec.seed, sec.level)
    machine = machine_description(setup.threads if setup else 1)
    record = {"what": "late fusion and all branches with minus without each sensor, against the physical severity "
                      "(issue 37)", "fusion": fusion, "frames_per_step": sec.frames_per_step,
              "sequence_length": sec.sequence_length, "resamples": sec.bootstrap, "level": sec.level,
              "seed": sec.seed, "level_seeds": {str(s): level_seed(sec.seed, s) for s in sec.severities},
              "frames": len(reader), "sets": {b: {k: list(v) for k, v in d.items()} for b, d in sets.items()},
              "conditions": conditions, "half_width": half_widths(conditions), "machine": machine,
              "protocol": protocol}
    record["figures"] = [p.name for p in plot_crossovers(record, work, f"{machine['cpu']}, {machine['cores']} cores")]
    write_json_atomic(work / "crossover.json", record)
    return record


def load_crossover(path: Path) -> dict:
    rec = json.loads(Path(path).read_text())
    if "conditions" not in rec:
        raise UserError(f"{path}: not a crossover record")
    return rec
