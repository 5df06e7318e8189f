"""The study's evaluation stage: every number of the report, from one trained run (the paper's
branches, gates trained), the early-fusion run, and the run's test split.

Everything is computed from each branch's detections on each test frame, computed once (the
EcoFusion configuration dataset holds them, `study.eco.data.EcoData`): a method is a per-frame
choice of branches whose detections are late-fused in the right camera and scored with VOC
mAP@0.5 under the run's protocol (`study.engine.scoring.score`). Fusing afterwards equals running only the
chosen branches (a branch depends only on its own sensors' stems; tested in tests/study). Methods:

- single sensors: one single-sensor branch (HydraFusion Table 2 (i), EcoFusion "none");
- early fusion: the input-level early-fusion models of the second run (Table 2 (ii));
- late fusion: the single-sensor branches fused (Table 2 (iii); EcoFusion "late");
- all branches: the seven fused (HydraFusion "All-Branches (Early + Late)");
- HydraFusion: a branch gate's top-k per frame (Table 2 (iv)); optimal = the k lowest a-posteriori
  branch losses (the oracle);
- EcoFusion: a configuration gate's choice at lambda_E, gamma (Eq. 7-9); loss_based = the oracle;
- the context oracle: per context, the best constant branch set on that context's test frames (a bound,
  not a method; `study.experiments.bounds`, which also computes every interval, room for context and the coverage).

Besides the papers' tables (HydraFusion 3, 6, 7 from `study.engine.gate_tables.evaluate_all_gates`; EcoFusion
1-3 and Figures 4-5 from `study.eco.sweep.sweep`) it measures what neither paper has: mAP against
severity per condition with the clear twins of the same frames, mAP per range bin per context,
each gate's regret against its oracle per context and how often its choice differs from the
oracle's, and each sensor's fusion regret (late fusion with it against late fusion without it).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fusion.boxes import FUSION_METHODS, method_label, method_name
from sim.errors import UserError
from sim.progress import progress as progress_bar
from study.engine.gate_training import IN_SAMPLE
from study.experiments.bounds import (
    ValidationFrames,
    add_context_constant,
    best_single_on_validation,
    evaluate_bounds,
)
from study.experiments.regrets import (
    config_index_of,
    eco_regret,
    fusion_regret,
    gate_selection_shares,
    hydra_regret,
    regret_intervals,
)
from study.numbers import rounded

FUSIONS = tuple(FUSION_METHODS.names())
LATE_COMBOS = (("camera_left", "camera_right"), ("camera_left", "camera_right", "lidar"), ("radar", "lidar"),
               ("radar", "camera_left", "camera_right", "lidar"))
"""HydraFusion Table 5's late-fusion sensor combinations (the branches present are used)."""



class Methods:
    """Per-frame branch selections on the test frames of an `EcoEval`, fused and scored on demand."""

    def __init__(self, ev, method: str) -> None:
        self.ev, self.method = ev, method
        self.memo: dict = {}
        self.branches = list(ev.ed.branches)
        self.frames = ev.model.branch_frames

    def fused(self, selection: list[tuple[str, ...]], method: str | None = None):
        from study.engine.scoring import fuse_selection

        method = method or self.method
        memo = self.memo.setdefault(method, {})
        return fuse_selection(list(zip(self.ev.metas, self.ev.dets)), selection, self.frames, method, memo=memo)

    def score(self, selection, method: str | None = None, keep=None) -> dict:
        from study.engine.scoring import score

        per = self.fused(selection, method)
        if keep is not None:
            per = [p for p, k in zip(per, keep) if k]
        return score(per, self.ev.reader, "camera_right", protocol=self.ev.ed.protocol)

    def fixed(self, branches: tuple[str, ...]) -> list[tuple[str, ...]]:
        """The selection that keeps `branches` on every test frame."""
        return [tuple(branches)] * len(self.ev.test)


def _summary(sc: dict) -> dict:
    keys = ("map", "map_vehicles", "map_per_context", "map_vehicles_per_context", "map_vehicles_per_severity",
            "map_vehicles_per_range", "map_vehicles_per_context_range")
    return {k: sc[k] for k in keys}


def hydra_predictions(run, data, frames, gates) -> dict[str, np.ndarray]:
    """Predicted (or, for optimal, a-posteriori) per-branch losses, (n, n_branches), on the frames of
    `frames`: the test frames (an `EcoEval`) or the validation frames (a `ValidationFrames`)."""
    from study.engine.gate_data import GateData
    from study.engine.gate_tables import make_gate
    from study.engine.gate_training import load_trained_gate, predict_losses

    ev = getattr(frames, "ev", frames)
    indices = [int(m["dataset_index"]) for m in frames.metas]
    out = {}
    for g in gates:
        if g == "optimal":
            gd = GateData(run, data, ev.model)
            gd.ensure(indices, progress=False)
            out[g] = np.array([[row[b] for b in ev.ed.branches] for row in gd.branch_losses(indices)])
        elif g == "knowledge":
            out[g] = make_gate(g, ev.model, run).predict(None, frames.metas).numpy()
        else:
            out[g] = predict_losses(load_trained_gate(run, g, ev.model), frames.features, metas=frames.metas)
    return out



def evaluate_study(run, run_early, data, cfg, s, work: Path, setup=None, progress: bool = True,
                   crossover: dict | None = None) -> dict:
    """Every number of the study's report (module docstring). `cfg`: the StudyConfig; `s`: its
    EcoSettings; figures are written under `work`; `crossover`: the crossover stage's record, whose
    crossovers give the physical knowledge gate its rules (`study.experiments.physical_gate`)."""
    from fusion.eco.config_gates import CONFIG_GATES
    from fusion.nets.branch_gates import trainable_gates
    from study.eco.ecofusion_eval import GATE_ORDER, EcoEval
    from study.eco.sweep import sweep
    from study.engine.gate_tables import evaluate_all_gates
    from study.experiments.selection import SelectionLog

    e = cfg.evaluate
    run, data, work = Path(run), Path(data), Path(work)
    learned = tuple(cfg.gates.gates)
    hydra_gates = ["knowledge", *learned, "optimal"]
    eco_gates = [g for g in GATE_ORDER if g not in trainable_gates(CONFIG_GATES) or g in learned]
    ev = EcoEval(run, data, s, eco_gates, threads=setup.threads if setup else 2, progress=progress)
    log = SelectionLog.of(ev.test)
    val = ValidationFrames(ev, cfg.gates.val_fraction, cfg.gates.seed, log)
    singles, late = single_and_late(ev)
    # the fusion of every fused method: declared in advance (evaluate.fusion), or the best late fusion on
    # the validation frames
    declared = declared_fusion(e)
    method = declared or log.choose("late-fusion method (every fused method of the study)",
                                    {f: val.map(late, f) for f in FUSIONS}, val.indices, lower_is_better=False,
                                    measure="mAP of late fusion", sequences=val.sequences)
    # HydraFusion Tables 3, 6, 7: every branch once per frame, each gate's top-k fused afterwards
    hydra_tables = evaluate_all_gates(run, data, gates=tuple(hydra_gates), setup=setup,
                                      batch_size=cfg.train.batch_size, progress=progress)
    hydra_tables["table3"] = table3_on_validation(run, data, ev, val, hydra_tables, hydra_gates, e.k, log, declared)
    eco_tables = sweep(run, data, work / "eco", gamma=e.gamma, s=s, gates=eco_gates,
                       fig_gate=e.eco_gate if e.eco_gate in eco_gates else "knowledge", progress=progress, ev=ev)
    M = Methods(ev, method)
    contexts = [m["context"] for m in ev.metas]

    selections, kinds = fixed_selections(M, singles, late)
    context_constant = add_context_constant(ev, val, singles, late, method, log, selections, kinds)  # issue 50 1a
    hydra_selections, hydra_kinds = hydra_gate_selections(run, data, ev, hydra_gates, e.k)
    eco_config_index, eco_kinds = eco_gate_configurations(ev, eco_gates, e.lambda_e, e.gamma)
    selections |= hydra_selections | {f"ecofusion:{g}": [ev.configs.members[c] for c in ch] for g, ch in eco_config_index.items()}
    kinds |= hydra_kinds | eco_kinds
    from study.experiments.physical_gate import add_physical_gate, comparison

    physical = add_physical_gate(crossover, selections, kinds, ev, val, method, log)  # issue 37 (None without)
    scores = score_methods(M, selections, progress)
    early = early_fusion(run_early, data, ev, method, cfg.train.batch_size, setup)
    for b, sc in early.scores.items():
        scores[f"early:{b}"], kinds[f"early:{b}"] = sc, f"early fusion model ({'+'.join(early.sensors[b])})"
    index = config_index_of(ev)
    intervals, bounds = evaluate_bounds(M, ev, selections, kinds, scores, early.fused, singles, late, learned,
                                        e.bootstrap, energy_of=lambda n, sel: frame_costs(ev, n, sel, index)[2],
                                        design=e.interval)
    table2, table5 = hydra_tables_2_and_5(M, scores, singles, early.scores, e, val, log, declared)
    twins = clear_twins(ev, early.model, data, cfg.train.batch_size) if e.twins else None
    swept = swept_methods(scores, e)
    run_cfg = json.loads((run / "config.json").read_text())
    record = results_record(
        ev, setup, e, method, run_cfg, data, singles, late, kinds, scores, intervals, hydra_tables, eco_tables, work,
        hydra_table2=table2, hydra_table4=cost_table(ev, selections), hydra_table5=table5,
        severity=severity_sweeps(M, ev, scores, selections, early.fused, twins, swept, method, progress),
        range_per_context={name: scores[name]["map_vehicles_per_context_range"] for name in swept},
        regret=regret_intervals({"hydrafusion": hydra_regret(selections, scores, hydra_gates, contexts, k=e.k),
                                 "ecofusion": eco_regret(ev, eco_config_index, scores, contexts)}, intervals),
        fusion_regret=fusion_regret(M, ev, scores, late, contexts), picks=gate_selection_shares(selections, contexts),
        severity_clear_twins=twins is not None)
    record["gate_training"] = gate_training(run, s, learned)
    from study.experiments.regrets import learning_curve

    record["learning_curve"] = learning_curve(run, learned)
    record["lambda_front"] = lambda_front(eco_tables, ev)
    record["bounds"] = bounds
    if physical is not None:
        record |= {"physical_gate": physical | {"comparison": comparison(record)}, "crossover": crossover}
    record["best_single"] = best_single_on_validation(val, singles, method, log)
    record["context_constant"] = context_constant
    record["choices"] = log.choices
    record["fusion_rule"] = (f"declared in advance (evaluate.fusion {e.fusion}): every fused method, every table"
                             if declared else "the best late fusion on the validation frames, for every fused method "
                             "of the headline; Tables 2 and 3 choose per row on the validation frames")
    gate_set = "gate" in separate_sets(ev.reader.manifest)
    split = ("gate set" if gate_set else "gate split") if val.holdout else "train split"
    record["validation"] = {"frames": len(val.indices), "sequences": val.sequences, "carved": val.carved,
                            "holdout": val.holdout,
                            "what": (f"{cfg.gates.val_fraction:g} of the {split}'s sequences per context (seed "
                                     f"{cfg.gates.seed}): the frames every learned gate picks its epoch and objective "
                                     "on; " + (("a set generated apart from the detectors' data (data.gate)" if gate_set else
                                                "sequences the detectors never trained on (train.gate_holdout "
                                                f"{cfg.train.gate_holdout:g})") if val.holdout else
                                               "the detectors trained on them too")) if val.carved else
                            (f"every fitting frame of the {split}: too few sequences per context to carve a "
                             "validation share, so the selections read the gates' fitting frames (never test frames)")}
    from study.experiments.robustness_table import robustness_table

    record["robustness"] = robustness_table(record)  # MultiCorrupt's RA, Robo3D's RR and CE, against late fusion
    from study.experiments.one_path import one_path_record

    record["one_path"] = one_path_record(record)  # every table's cell of a method against its own mAP
    return record


def declared_fusion(e) -> str | None:
    """evaluate.fusion as the fusion's internal name ("soft_nms"), or None: chosen on validation."""
    return None if e.fusion == "validation" else method_name(e.fusion)


def table3_on_validation(run, data, ev, val, hydra_tables: dict, gates, k: int, log,
                         declared: str | None = None) -> dict:
    """HydraFusion Table 3: per gate, the fusion method whose mAP of the gate's top k is best on the
    validation frames, and that method's test row of Table 6 (the paper picks the best per gate; a
    pick on the test frames would flatter every gate); with a `declared` fusion, that one for every gate."""
    from study.engine.gate_tables import top_k_selection

    branches = list(ev.ed.branches)
    preds = hydra_predictions(run, data, val, gates)
    out = {}
    for g in gates:
        if declared:
            label = method_label(declared)
            out[g] = {"fusion": label, "map": hydra_tables["map_table"][g][label], "chosen_on": "declared in advance"}
            continue
        selection = top_k_selection(preds[g], branches, k)
        label = method_label(log.choose(f"HydraFusion Table 3: fusion of the {g} gate's top {min(k, len(branches))}",
                                        {f: val.score(selection, f)["map"] for f in FUSIONS}, val.indices,
                                        lower_is_better=False, measure="mAP", sequences=val.sequences))
        out[g] = {"fusion": label, "map": hydra_tables["map_table"][g][label], "chosen_on": "validation"}
    return out


def gate_training(run, s, learned) -> dict:
    """What each learned gate was trained on and how its choice compares on the test frames (the
    gates stage's result.json): the targets and objective kept and every objective's validation
    regret, the epoch, and the choice beside the best constant, the per-context constant and the
    oracle; under "in_sample", the same gate trained on the detectors' own training frames
    (`GatesSection.compare_targets`), validated on the same frames: what held-out targets change."""
    keys = ("targets", "objective", "objectives", "best_epoch", "val_regret", "val_mae", "tau", "choice",
            "train_frames", "val_frames", "test_frames", "selected_on")
    out = {}
    for g in learned:
        for fam, d in (("hydrafusion", Path(run) / "gates" / g), ("ecofusion", s.gate_dir(run, g))):
            path = d / "result.json"
            if path.exists():
                r = json.loads(path.read_text())
                out[f"{fam}:{g}"] = {k: r.get(k) for k in keys}
                other = d / IN_SAMPLE / "result.json"
                if other.exists():
                    r = json.loads(other.read_text())
                    out[f"{fam}:{g}"]["in_sample"] = {k: r.get(k) for k in keys}
    return out




def lambda_front(eco_tables: dict, ev) -> dict:
    """How far lambda_E moves each EcoFusion gate: its mean energy at the smallest and largest
    lambda_E of the sweep, and that span as % of the range between the cheapest single-sensor
    configuration and late fusion (issue 26 asks >= 30 % for the best learned gate); the lambdas on
    the gate's Pareto front; and gamma on the same L_f scale."""
    curve = eco_tables["curve"]
    names = ev.configs.names
    singles = [i for i, n in enumerate(names) if n.startswith("none_") or len(ev.configs.members[i]) == 1]
    e_cheap = float(min(ev.e[i] for i in singles)) if singles else float(ev.e.min())
    late = ev.configs.baselines.get("late")
    e_late = float(ev.e[late]) if late is not None else float(ev.e.max())
    out = {"cheapest_single_energy": rounded(e_cheap), "late_energy": rounded(e_late), "loss_unit": ev.loss_label(),
           "gates": {}}
    for g, c in curve.items():
        lams = sorted(c, key=float)
        e0, e1 = c[lams[0]]["energy"], c[lams[-1]]["energy"]
        out["gates"][g] = {"lambda_from": lams[0], "lambda_to": lams[-1], "energy_from": e0, "energy_to": e1,
                           "span_pct": rounded(100.0 * (e0 - e1) / (e_late - e_cheap), 1) if e_late > e_cheap else None,
                           "pareto_lambdas": eco_tables.get("pareto_lambdas", {}).get(g)}
    return out


def single_and_late(ev) -> tuple[list[str], tuple[str, ...]]:
    """The run's single-sensor branches, and the branches late fusion fuses (the configuration set's
    "late" baseline, else the single-sensor branches)."""
    from fusion.eco.configurations import SINGLE_SENSORS

    sensors_of = ev.model.branch_sensors
    singles = [b for b in ev.ed.branches if len(sensors_of[b]) == 1 and sensors_of[b][0] in SINGLE_SENSORS]
    if "late" in ev.configs.baselines:
        return singles, tuple(ev.configs.members[ev.configs.baselines["late"]])
    return singles, tuple(singles)


def fixed_selections(M: Methods, singles, late) -> tuple[dict, dict]:
    """The methods that choose the same branches on every frame: ({name: selection},
    {name: what it is})."""
    selections, kinds = {}, {}
    for b in singles:
        selections[f"single:{b}"], kinds[f"single:{b}"] = M.fixed((b,)), "single sensor"
    selections["late"], kinds["late"] = M.fixed(late), "late fusion of the single-sensor branches"
    selections["all_branches"], kinds["all_branches"] = M.fixed(tuple(M.branches)), "all branches (early + late)"
    return selections, kinds


def hydra_gate_selections(run, data, ev, gates, k: int) -> tuple[dict, dict]:
    """HydraFusion's methods: each branch gate's top k per frame (Table 2 (iv))."""
    from study.engine.gate_tables import top_k_selection

    branches = list(ev.ed.branches)
    preds = hydra_predictions(run, data, ev, gates)
    selections = {f"hydrafusion:{g}": top_k_selection(preds[g], branches, k) for g in gates}
    kinds = {f"hydrafusion:{g}": f"HydraFusion, {g} gate, top {min(k, len(branches))}" for g in gates}
    return selections, kinds


def eco_gate_configurations(ev, gates, lambda_e: float, gamma: float) -> tuple[dict, dict]:
    """EcoFusion's methods: each configuration gate's choice per frame (configuration indices, Eq. 7-9),
    and what each is."""
    choice = {g: ev.choose(g, lambda_e, gamma) for g in gates}
    kinds = {f"ecofusion:{g}": f"EcoFusion, {g} gate, lambda_E {lambda_e:g}, gamma {gamma:g}" for g in gates}
    return choice, kinds


def score_methods(M: Methods, selections: dict, progress: bool) -> dict:
    """Each method's selections fused and scored: {name: `study.engine.scoring.score` result}."""
    bar = progress_bar(total=len(selections), desc="fuse and score the methods", unit="method", enabled=progress)
    scores = {}
    for name, selection in selections.items():
        scores[name] = M.score(selection)
        bar.update(1)
    bar.close()
    return scores


@dataclass
class EarlyFusion:
    """The early-fusion run's models on the test frames (Table 2 (ii)); empty without that run."""

    model: Any = None
    scores: dict = field(default_factory=dict)  # branch -> `score` result
    fused: dict = field(default_factory=dict)  # branch -> its detections per test frame, fused once
    sensors: dict = field(default_factory=dict)  # branch -> the sensors its model fuses


def early_fusion(run_early, data, ev, method: str, batch_size: int, setup) -> EarlyFusion:
    """Run and score every early-fusion model of `run_early` on the test frames (None: no run)."""
    if run_early is None:
        return EarlyFusion()
    from study.engine.scoring import fused as fuse_frames
    from study.engine.scoring import load_run, run_branches, score

    model, _ = load_run(run_early, "latest", device=setup.device if setup else "cpu")
    names = list(model.branches)
    per_frame = run_branches(model, data, ev.test, names, batch_size=batch_size, progress="early fusion")
    out = EarlyFusion(model=model, sensors=dict(model.branch_sensors))
    for b in names:
        out.fused[b] = fuse_frames(per_frame, [b], model.branch_frames, method)
        out.scores[b] = score(out.fused[b], ev.reader, "camera_right", protocol=ev.ed.protocol)
    return out


def hydra_tables_2_and_5(M: Methods, scores: dict, singles, early_scores: dict, e, val,
                         log, declared: str | None = None) -> tuple[dict, dict]:
    """HydraFusion Table 2 (mAP of each kind of method) and Table 5 (late fusion of sensor combinations
    by each fusion method, on the test frames; Table 2 takes the method best on the validation frames,
    or the `declared` one)."""
    branches = M.branches
    table2 = {"single_sensors": {b: scores[f"single:{b}"]["map"] for b in singles},
              "early_fusion": {b: sc["map"] for b, sc in early_scores.items()},
              "late_fusion": {}, "hydrafusion": {}}
    table5 = {}
    for combo in LATE_COMBOS:
        combo_branches = tuple(b for b in branches if b in combo)
        if len(combo_branches) < 2 or len(combo_branches) != len(combo):
            continue
        row = {f: M.score(M.fixed(combo_branches), f)["map"] for f in FUSIONS}
        table5["+".join(combo_branches)] = row
        pick = declared or log.choose(f"HydraFusion Table 2: fusion of late {'+'.join(combo_branches)}",
                          {f: val.map(combo_branches, f) for f in FUSIONS}, val.indices, lower_is_better=False,
                          measure="mAP", sequences=val.sequences)
        table2["late_fusion"]["+".join(combo_branches)] = row[pick]
    table2["late_fusion"]["all_branches (early + late)"] = scores["all_branches"]["map"]
    table2["hydrafusion"] = {f"{e.hydra_gate} top {min(e.k, len(branches))}": scores[f"hydrafusion:{e.hydra_gate}"]["map"]}
    table2["ecofusion"] = {f"{e.eco_gate} lambda_E {e.lambda_e:g}": scores[f"ecofusion:{e.eco_gate}"]["map"]
                           if f"ecofusion:{e.eco_gate}" in scores else None}
    return table2, table5


def cost_table(ev, selections: dict) -> dict:
    """HydraFusion Table 4 analogue: each method's mean latency, energy and branch count per frame.
    A learned gate (deep, attention: HydraFusion's or EcoFusion's) is charged the stems it reads that
    its chosen branches do not need and its own network's measured time (`EcoEval.gate_overhead`), as
    EcoFusion's Table 1 charges them: one accounting for every method of the report."""
    index = config_index_of(ev)

    def cost(name, selection) -> dict:
        t, e_raw, e, extra = frame_costs(ev, name, selection, index)
        return {"latency_ms": rounded(1000 * t.mean(), 2), "energy_j": rounded(e_raw.mean()),
                "energy": rounded(e.mean()), "gate_ms": rounded(1000 * extra.mean(), 2),
                "branches": rounded(np.mean([len(m) for m in selection]), 3)}

    return {name: cost(name, selection) for name, selection in selections.items()}


def frame_costs(ev, name: str, selection, index: dict | None = None):
    """Per test frame: latency [s], energy [J], energy (lambda_E scale) and the gate's own time [s]
    of method `name` running `selection`, as `cost_table` charges them."""
    from fusion.eco.config_gates import CONFIG_GATES
    from fusion.nets.branch_gates import GATES, trainable_gates

    index = config_index_of(ev) if index is None else index
    idx = np.array([index[tuple(m)] for m in selection])
    gate = name.split(":", 1)[1] if name.startswith(("hydrafusion:", "ecofusion:")) else None
    learned = trainable_gates(CONFIG_GATES if name.startswith("ecofusion:") else GATES)
    extra, _ = ev.gate_overhead(idx, gate if gate in learned else None, name.split(":", 1)[0])
    t = ev.t[idx] + extra
    scale = t / ev.t[idx]  # E = P t at the configuration's own power
    return t, ev.e_raw[idx] * scale, ev.e[idx] * scale, extra


@dataclass
class Twins:
    """The clear-weather twins of the test frames: each model's detections on them."""

    reader: Any  # DatasetReader on the clear arrays
    frames: dict  # "paper" / "early" -> (per-frame branch detections, the model's branch_frames)


def clear_twins(ev, early_model, data, batch_size: int) -> Twins | None:
    """Run the paper's branches (and the early models) on the clear twins of the test frames; None
    when the dataset has no twins."""
    if not ev.reader.manifest["config"].get("twins"):
        return None
    from sensors.dataset import DatasetReader
    from study.engine.scoring import run_branches

    reader = DatasetReader(data, clear=True)
    clear_frames = run_branches(ev.model, data, ev.test, list(ev.ed.branches), batch_size=batch_size,
                                progress="clear twins", clear=True)
    frames = {"paper": (clear_frames, ev.model.branch_frames)}
    if early_model is not None:
        frames["early"] = (run_branches(early_model, data, ev.test, list(early_model.branches),
                                        batch_size=batch_size, progress="clear twins (early)", clear=True),
                           early_model.branch_frames)
    return Twins(reader, frames)


def swept_methods(scores: dict, e) -> list[str]:
    """The methods of the severity sweeps and range tables: the fixed ones, the early models, the
    chosen gates and the oracles."""
    return [m for m in scores if m.split(":")[0] in ("single", "early") or m in
            ("late", "all_branches", f"hydrafusion:{e.hydra_gate}", "hydrafusion:optimal",
             f"ecofusion:{e.eco_gate}", "ecofusion:loss_based")]


def severity_sweeps(M: Methods, ev, scores: dict, selections: dict, early_fused: dict, twins: Twins | None,
                    swept, method: str, progress: bool) -> dict:
    """Vehicle mAP against severity per condition, {condition: {method: {severity: {"degraded",
    "clear", "frames"}}}}; "clear" is the same frames' clear twins (fixed selections and early models)."""
    from study.engine.scoring import fused as fuse_frames
    from study.engine.scoring import score

    contexts = [m["context"] for m in ev.metas]
    severities = [int(m.get("severity", 0)) for m in ev.metas]
    conditions = sorted({c for c, sv in zip(contexts, severities) if sv > 0})
    rows: dict = {}
    bar = progress_bar(total=len(conditions) * len(swept), desc="severity sweeps", unit="curve", enabled=progress)
    for cond in conditions:
        keep = [c == cond for c in contexts]
        rows[cond] = {}
        for name in swept:
            if name.startswith("early:"):
                per = [p for p, k in zip(early_fused[name.split(":", 1)[1]], keep) if k]
                deg = score(per, ev.reader, "camera_right", protocol=ev.ed.protocol)
            else:
                deg = M.score(selections[name], keep=keep)
            clear = None
            if twins is not None and (name.startswith(("single:", "early:")) or name in ("late", "all_branches")):
                src = "early" if name.startswith("early:") else "paper"
                if src in twins.frames:
                    frames_, bframes = twins.frames[src]
                    branches_fused = ([name.split(":", 1)[1]] if ":" in name else list(selections[name][0]))
                    per = [p for p, k in zip(fuse_frames(frames_, branches_fused, bframes, method), keep) if k]
                    clear = score(per, twins.reader, "camera_right", protocol=ev.ed.protocol)
            sev = sorted(set(deg["map_vehicles_per_severity"]), key=int)
            rows[cond][name] = {
                sv: {"degraded": deg["map_vehicles_per_severity"].get(sv),
                     "clear": None if clear is None else clear["map_vehicles_per_severity"].get(sv),
                     "frames": int(sum(1 for c, x in zip(contexts, severities) if c == cond and str(x) == sv))}
                for sv in sev}
            bar.update(1)
    bar.close()
    return rows


def results_record(ev, setup, e, method: str, run_cfg: dict, data, singles, late, kinds: dict, scores: dict,
                   intervals, hydra_tables: dict, eco_tables: dict, work: Path, **measured) -> dict:
    """results.json: the protocol, the data and machine, the settings, every method's summary, the
    papers' tables and `measured` (Table 2, 4, 5, the severity sweeps, range bins, regrets, picks)."""
    from study.eco.latency_energy import machine_description
    from study.engine.scoring import frames_for

    contexts = [m["context"] for m in ev.metas]
    ctx_list = sorted(set(contexts))
    train_idx, _ = frames_for(run_cfg, data, "train")
    gate_idx, _ = frames_for(run_cfg, data, "gate")
    branches = list(ev.ed.branches)
    return {
        "protocol": ev.ed.protocol,
        "metric": "VOC all-point AP at IoU 0.5 in the right camera, difficult ground truth ignored; "
                  "vehicle mAP = mean over car, van, truck, bus",
        "fusion": method,
        "dataset": {"frames": len(ev.reader), "train_frames": len(train_idx), "gate_frames": len(gate_idx),
                    "test_frames": len(ev.test),
                    "contexts": ctx_list, "twins": bool(ev.reader.manifest["config"].get("twins")),
                    "frames_per_context_test": {c: contexts.count(c) for c in ctx_list},
                    "sets": separate_sets(ev.reader.manifest)},
        "machine": machine_description(setup.threads if setup else 1),
        "device": setup.describe() if setup else "cpu",
        "branches": branches, "singles": singles, "late": list(late),
        "k": min(e.k, len(branches)), "lambda_e": e.lambda_e, "gamma": e.gamma, "rule": e.rule,
        "hydra_gate": e.hydra_gate, "eco_gate": e.eco_gate,
        "methods": {name: {"what": kinds[name], **_summary(sc)} for name, sc in scores.items()},
        "intervals": intervals,
        "hydra_table2": measured["hydra_table2"], "hydra_table3": hydra_tables["table3"],
        "hydra_table4": measured["hydra_table4"], "hydra_table5": measured["hydra_table5"],
        "hydra_table6": hydra_tables["map_table"], "hydra_table7": hydra_tables["selection_rate"],
        "hydra_selection_per_context": hydra_tables["selection_rate_per_context"],
        "hydra_loss_mae": hydra_tables.get("loss_mae"),
        "eco": {k: v for k, v in eco_tables.items() if k not in ("curve",)},
        "eco_curve": eco_tables["curve"],
        "energy_unit": ev.energy_label(), "loss_unit": ev.loss_label(),
        "severity": measured["severity"], "severity_clear_twins": measured["severity_clear_twins"],
        "range_per_context": measured["range_per_context"],
        "regret": measured["regret"], "fusion_regret": measured["fusion_regret"], "picks": measured["picks"],
        "figures": {"figure4": str(Path(eco_tables["figures"][0]).relative_to(work)),
                    "figure5": str(Path(eco_tables["figures"][1]).relative_to(work))},
    }


def separate_sets(manifest: dict) -> dict:
    """The gate and test sets generated apart from the detectors' data (`data.gate`, `data.test`), by
    part: frames, seed, frames per context, sequence length ({} for one split dataset)."""
    parts = manifest.get("parts") or {}
    return {p: {"frames": v["stop"] - v["start"], "seed": v["config"]["seed"],
                "frames_per_context": v["config"]["frames_per_context"],
                "sequence_length": v["config"]["sequence_length"]}
            for p, v in parts.items() if p != "detectors"}


def _check(results: dict) -> None:
    if "methods" not in results:
        raise UserError("results.json holds no study results")
