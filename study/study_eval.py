"""The study's evaluation stage: every number of the report, from one trained run (the paper's
branches, gates trained), the early-fusion run, and the run's test split.

Everything is computed from each branch's detections on each test frame, computed once (the
EcoFusion configuration dataset holds them, `study.eco.data.EcoData`): a method is a per-frame
choice of branches whose detections are late-fused in the right camera and scored with VOC
mAP@0.5 under the run's protocol (`study.detect.score`). Fusing afterwards equals running only the
chosen branches (a branch depends only on its own sensors' stems; tested in tests/study). Methods:

- single sensors: one single-sensor branch (HydraFusion Table 2 (i), EcoFusion "none");
- early fusion: the input-level early-fusion models of the second run (Table 2 (ii));
- late fusion: the single-sensor branches fused (Table 2 (iii); EcoFusion "late");
- all branches: the seven fused (HydraFusion "All-Branches (Early + Late)");
- HydraFusion: a branch gate's top-k per frame (Table 2 (iv)); optimal = the k lowest a-posteriori
  branch losses (the oracle);
- EcoFusion: a configuration gate's choice at lambda_E, gamma (Eq. 7-9); loss_based = the oracle.

Besides the papers' tables (HydraFusion 3, 6, 7 from `study.branch_gate_study.evaluate_all_gates`; EcoFusion
1-3 and Figures 4-5 from `study.eco.sweep.sweep`) it measures what neither paper has: mAP against
severity per condition with the clear twins of the same frames, mAP per range bin per context,
each gate's regret against its oracle per context and how often its choice differs from the
oracle's, and each sensor's fusion regret (late fusion with it against late fusion without it).
"""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from sim.errors import UserError

FUSIONS = ("nms", "soft_nms", "wbf")
LATE_COMBOS = (("camera_left", "camera_right"), ("camera_left", "camera_right", "lidar"), ("radar", "lidar"),
               ("radar", "camera_left", "camera_right", "lidar"))
"""HydraFusion Table 5's late-fusion sensor combinations (the branches present are used)."""


def _r(v, nd: int = 4):
    return None if v is None or (isinstance(v, float) and not np.isfinite(v)) else round(float(v), nd)


class Methods:
    """Per-frame branch choices on the test frames of an `EcoEval`, fused and scored on demand."""

    def __init__(self, ev, method: str) -> None:
        self.ev, self.method = ev, method
        self.memo: dict = {}
        self.branches = list(ev.ed.branches)
        self.frames = ev.model.branch_frames

    def fused(self, members: list[tuple[str, ...]], method: str | None = None):
        from study.eco.data import fuse_choice

        method = method or self.method
        memo = self.memo.setdefault(method, {})
        return fuse_choice(self.ev.dets, self.ev.metas, self.branches, self.frames, members, method, memo)

    def score(self, members, method: str | None = None, keep=None) -> dict:
        from study.detect import score

        per = self.fused(members, method)
        if keep is not None:
            per = [p for p, k in zip(per, keep) if k]
        return score(per, self.ev.reader, "camera_right", protocol=self.ev.ed.protocol)

    def fixed(self, members: tuple[str, ...]) -> list[tuple[str, ...]]:
        return [tuple(members)] * len(self.ev.test)


def _summary(sc: dict) -> dict:
    keys = ("map", "map_vehicles", "map_per_context", "map_vehicles_per_context", "map_vehicles_per_severity",
            "map_vehicles_per_range", "map_vehicles_per_context_range")
    return {k: sc[k] for k in keys}


def hydra_predictions(run, data, ev, gates) -> dict[str, np.ndarray]:
    """Predicted (or, for optimal, a-posteriori) per-branch losses on the test frames, (n, n_branches)."""
    from study.branch_gate_study import load_trained_gate, make_gate, predict_losses
    from study.gate_data import GateData

    out = {}
    for g in gates:
        if g == "optimal":
            gd = GateData(run, data, ev.model)
            gd.ensure(ev.test, progress=False)
            out[g] = np.array([[row[b] for b in ev.ed.branches] for row in gd.branch_losses(ev.test)])
        elif g == "knowledge":
            out[g] = make_gate(g, ev.model, run).predict(None, ev.metas).numpy()
        else:
            out[g] = predict_losses(load_trained_gate(run, g, ev.model), ev.features)
    return out


def top_k_members(pred: np.ndarray, branches, k: int) -> list[tuple[str, ...]]:
    import torch

    from fusion.nets.branch_gates import top_k

    return top_k(torch.as_tensor(pred, dtype=torch.float32), branches, min(k, len(branches)))


def evaluate_study(run, run_early, data, cfg, s, work: Path, setup=None, progress: bool = True) -> dict:
    """Every number of the study's report (module docstring). `cfg`: the StudyConfig; `s`: its
    EcoSettings; figures are written under `work`."""
    from fusion.eco.configurations import SINGLE_SENSORS
    from study.branch_gate_study import evaluate_all_gates
    from study.detect import fusion_method
    from study.eco.energy import machine_description
    from study.eco.evaluate import GATE_ORDER, EcoEval
    from study.eco.sweep import sweep

    e = cfg.evaluate
    run, data, work = Path(run), Path(data), Path(work)
    method = fusion_method(s.fusion)
    learned = tuple(cfg.gates.gates)
    # HydraFusion Tables 3, 6, 7: every branch once per frame, each gate's top-k fused afterwards
    hydra_tables = evaluate_all_gates(run, data, gates=("knowledge", *learned, "optimal"), setup=setup,
                                      batch_size=cfg.train.batch_size, progress=progress)
    eco_gates = [g for g in GATE_ORDER if g in ("knowledge", "loss_based") or g in learned]
    ev = EcoEval(run, data, s, eco_gates, threads=setup.threads if setup else 2, progress=progress)
    eco_tables = sweep(run, data, work / "eco", gamma=e.gamma, s=s, gates=eco_gates,
                       fig_gate=e.eco_gate if e.eco_gate in eco_gates else "knowledge", progress=progress, ev=ev)
    M = Methods(ev, method)
    branches = M.branches
    sensors_of = ev.model.branch_sensors
    singles = [b for b in branches if len(sensors_of[b]) == 1 and sensors_of[b][0] in SINGLE_SENSORS]
    late = tuple(ev.configs.members[ev.configs.baselines["late"]]) if "late" in ev.configs.baselines else tuple(singles)
    n = len(ev.test)
    contexts = [m["context"] for m in ev.metas]
    severities = [int(m.get("severity", 0)) for m in ev.metas]

    # the methods' per-frame choices --------------------------------------------------------
    choices: dict[str, list[tuple[str, ...]]] = {}
    kinds: dict[str, str] = {}
    for b in singles:
        choices[f"single:{b}"], kinds[f"single:{b}"] = M.fixed((b,)), "single sensor"
    choices["late"], kinds["late"] = M.fixed(late), "late fusion of the single-sensor branches"
    choices["all_branches"], kinds["all_branches"] = M.fixed(tuple(branches)), "all branches (early + late)"
    hydra_gates = ["knowledge", *learned, "optimal"]
    preds = hydra_predictions(run, data, ev, hydra_gates)
    for g in hydra_gates:
        choices[f"hydrafusion:{g}"] = top_k_members(preds[g], branches, e.k)
        kinds[f"hydrafusion:{g}"] = f"HydraFusion, {g} gate, top {min(e.k, len(branches))}"
    eco_choice = {}
    for g in eco_gates:
        eco_choice[g] = ev.choose(g, e.lambda_e, e.gamma)
        choices[f"ecofusion:{g}"] = [ev.configs.members[c] for c in eco_choice[g]]
        kinds[f"ecofusion:{g}"] = f"EcoFusion, {g} gate, lambda_E {e.lambda_e:g}, gamma {e.gamma:g}"
    from sim.progress import progress as progress_bar

    bar = progress_bar(total=len(choices), desc="fuse and score the methods", unit="method", enabled=progress)
    scores = {}
    for name, ch in choices.items():
        scores[name] = M.score(ch)
        bar.update(1)
    bar.close()

    # the early-fusion run (Table 2 (ii)) ----------------------------------------------------
    early, early_fused, early_model = {}, {}, None  # early_fused: each early model's detections, fused once
    if run_early is not None:
        from study.detect import fused as fuse_frames
        from study.detect import load_run, run_branches, score

        early_model, _ = load_run(run_early, "latest", device=setup.device if setup else "cpu")
        enames = list(early_model.branches)
        early_per_frame = run_branches(early_model, data, ev.test, enames, batch_size=cfg.train.batch_size,
                                       progress="early fusion")
        for b in enames:
            early_fused[b] = fuse_frames(early_per_frame, [b], early_model.branch_frames, method)
            sc = score(early_fused[b], ev.reader, "camera_right", protocol=ev.ed.protocol)
            early[b] = sc
            scores[f"early:{b}"], kinds[f"early:{b}"] = sc, f"early fusion model ({'+'.join(early_model.branch_sensors[b])})"

    # 95 % intervals: whole test sequences drawn with replacement, every method on each draw ------
    intervals = None
    if e.bootstrap:
        from study.detect import context_bootstrap

        sources = {name: M.fused(ch) for name, ch in choices.items()}
        sources.update({f"early:{b}": per for b, per in early_fused.items()})
        intervals = context_bootstrap(sources, ev.reader, "camera_right", protocol=ev.ed.protocol,
                                      resamples=e.bootstrap, classes="all", desc="bootstrap the methods")

    # HydraFusion Table 2 --------------------------------------------------------------------
    table2 = {"single_sensors": {b: scores[f"single:{b}"]["map"] for b in singles},
              "early_fusion": {b: sc["map"] for b, sc in early.items()},
              "late_fusion": {}, "hydrafusion": {}}
    table5 = {}
    for combo in LATE_COMBOS:
        members = tuple(b for b in branches if b in combo)
        if len(members) < 2 or len(members) != len(combo):
            continue
        row = {f: M.score(M.fixed(members), f)["map"] for f in FUSIONS}
        table5["+".join(members)] = row
        best = max((v for v in row.values() if v is not None), default=None)
        table2["late_fusion"]["+".join(members)] = best
    table2["late_fusion"]["all_branches (early + late)"] = scores["all_branches"]["map"]
    table2["hydrafusion"] = {f"{e.hydra_gate} top {min(e.k, len(branches))}": scores[f"hydrafusion:{e.hydra_gate}"]["map"]}
    table2["ecofusion"] = {f"{e.eco_gate} lambda_E {e.lambda_e:g}": scores[f"ecofusion:{e.eco_gate}"]["map"]
                           if f"ecofusion:{e.eco_gate}" in scores else None}

    # HydraFusion Table 4 analogue: latency and energy per model ------------------------------
    cfg_index = {m: i for i, m in enumerate(ev.configs.members)}

    def cost(members_per_frame) -> dict:
        idx = np.array([cfg_index[tuple(m)] for m in members_per_frame])
        return {"latency_ms": _r(1000 * ev.t[idx].mean(), 2), "energy_j": _r(ev.e_raw[idx].mean()),
                "energy": _r(ev.e[idx].mean()), "branches": _r(np.mean([len(m) for m in members_per_frame]), 3)}

    table4 = {name: cost(ch) for name, ch in choices.items()}

    # severity sweeps per condition, with the clear twins of the same frames --------------------
    twins = None
    if e.twins and ev.reader.manifest["config"].get("twins"):
        from sensors.dataset import DatasetReader
        from study.detect import fused as fuse_frames
        from study.detect import run_branches, score

        clear_reader = DatasetReader(data, clear=True)
        clear_frames = run_branches(ev.model, data, ev.test, branches, batch_size=cfg.train.batch_size,
                                    progress="clear twins", clear=True)
        twins = {"paper": (clear_frames, ev.model.branch_frames)}
        if early_model is not None:
            twins["early"] = (run_branches(early_model, data, ev.test, list(early_model.branches),
                                           batch_size=cfg.train.batch_size, progress="clear twins (early)",
                                           clear=True),
                              early_model.branch_frames)
    conditions = sorted({c for c, sv in zip(contexts, severities) if sv > 0})
    sweep_rows: dict = {}
    swept = [m for m in scores if m.split(":")[0] in ("single", "early") or m in
             ("late", "all_branches", f"hydrafusion:{e.hydra_gate}", "hydrafusion:optimal",
              f"ecofusion:{e.eco_gate}", "ecofusion:loss_based")]
    bar = progress_bar(total=len(conditions) * len(swept), desc="severity sweeps", unit="curve", enabled=progress)
    for cond in conditions:
        keep = [c == cond for c in contexts]
        sweep_rows[cond] = {}
        for name in swept:
            if name.startswith("early:"):
                from study.detect import score

                per = [p for p, k in zip(early_fused[name.split(":", 1)[1]], keep) if k]
                deg = score(per, ev.reader, "camera_right", protocol=ev.ed.protocol)
            else:
                deg = M.score(choices[name], keep=keep)
            clear = None
            members = None
            if twins is not None and (name.startswith(("single:", "early:")) or name in ("late", "all_branches")):
                from study.detect import fused as fuse_frames
                from study.detect import score

                src = "early" if name.startswith("early:") else "paper"
                if src in twins:
                    frames_, bframes = twins[src]
                    members = ([name.split(":", 1)[1]] if ":" in name else list(choices[name][0]))
                    per = [p for p, k in zip(fuse_frames(frames_, members, bframes, method), keep) if k]
                    clear = score(per, clear_reader, "camera_right", protocol=ev.ed.protocol)
            sev = sorted(set(deg["map_vehicles_per_severity"]), key=int)
            sweep_rows[cond][name] = {
                sv: {"degraded": deg["map_vehicles_per_severity"].get(sv),
                     "clear": None if clear is None else clear["map_vehicles_per_severity"].get(sv),
                     "frames": int(sum(1 for c, x in zip(contexts, severities) if c == cond and str(x) == sv))}
                for sv in sev}
            bar.update(1)
    bar.close()

    # range bins per context -------------------------------------------------------------------
    range_rows = {name: scores[name]["map_vehicles_per_context_range"] for name in swept}

    # gate regret against the oracle, per context ---------------------------------------------
    ctx_list = sorted(set(contexts))
    regret: dict = {"hydrafusion": {}, "ecofusion": {}}
    opt = choices["hydrafusion:optimal"]
    for g in hydra_gates:
        if g == "optimal":
            continue
        ch = choices[f"hydrafusion:{g}"]
        row = {}
        for ctx in [*ctx_list, "all"]:
            keep = [ctx == "all" or c == ctx for c in contexts]
            a = scores[f"hydrafusion:{g}"]["map"] if ctx == "all" else scores[f"hydrafusion:{g}"]["map_per_context"].get(ctx)
            o = scores["hydrafusion:optimal"]["map"] if ctx == "all" else scores["hydrafusion:optimal"]["map_per_context"].get(ctx)
            frames_ = [k for k, x in enumerate(keep) if x]
            row[ctx] = {"map": a, "map_oracle": o, "regret_map": None if a is None or o is None else _r(o - a),
                        "differs_pct": _r(100.0 * np.mean([ch[k] != opt[k] for k in frames_]), 1),
                        "frames": len(frames_)}
        regret["hydrafusion"][g] = row
    lb = eco_choice["loss_based"]
    rows_n = np.arange(n)
    for g in eco_gates:
        if g == "loss_based":
            continue
        ch = eco_choice[g]
        row = {}
        for ctx in [*ctx_list, "all"]:
            keep = np.array([ctx == "all" or c == ctx for c in contexts])
            a = scores[f"ecofusion:{g}"]["map"] if ctx == "all" else scores[f"ecofusion:{g}"]["map_per_context"].get(ctx)
            o = scores["ecofusion:loss_based"]["map"] if ctx == "all" else scores["ecofusion:loss_based"]["map_per_context"].get(ctx)
            lf = ev.losses[rows_n, ch][keep].mean()
            lf_o = ev.losses[rows_n, lb][keep].mean()
            row[ctx] = {"map": a, "map_oracle": o, "regret_map": None if a is None or o is None else _r(o - a),
                        "avg_loss": _r(lf), "avg_loss_oracle": _r(lf_o), "regret_loss": _r(lf - lf_o),
                        "differs_pct": _r(100.0 * float(np.mean(ch[keep] != lb[keep])), 1), "frames": int(keep.sum())}
        regret["ecofusion"][g] = row

    # each sensor's fusion regret: late fusion with it against without it ------------------------
    fusion_regret = {}
    late_idx = cfg_index[tuple(late)]
    for b in late:
        rest = tuple(x for x in late if x != b)
        if not rest:
            continue
        without = M.score(M.fixed(rest))
        with_ = scores["late"]
        rest_idx = cfg_index[rest]
        row = {}
        for ctx in [*ctx_list, "all"]:
            keep = np.array([ctx == "all" or c == ctx for c in contexts])
            a = with_["map"] if ctx == "all" else with_["map_per_context"].get(ctx)
            w = without["map"] if ctx == "all" else without["map_per_context"].get(ctx)
            row[ctx] = {"map_with": a, "map_without": w,
                        "regret_map": None if a is None or w is None else _r(w - a),
                        "regret_loss": _r(ev.losses[keep, late_idx].mean() - ev.losses[keep, rest_idx].mean())}
        hurts = {c: v["regret_map"] for c, v in row.items() if c != "all" and v["regret_map"] is not None
                 and v["regret_map"] > 0}
        fusion_regret[b] = {"per_context": row, "hurts_in": hurts,
                            "worst_context": max(hurts, key=hurts.get) if hurts else None,
                            "worst_regret_map": max(hurts.values()) if hurts else 0.0}

    # what each gate picks, per context --------------------------------------------------------
    picks: dict = {"hydrafusion": {}, "ecofusion": {}}
    for name, ch in choices.items():
        fam = name.split(":")[0]
        if fam not in picks:
            continue
        by = defaultdict(lambda: defaultdict(int))
        for c, m in zip(contexts, ch):
            by[c]["+".join(m)] += 1
        picks[fam][name.split(":", 1)[1]] = {
            c: dict(sorted(((k, _r(100.0 * v / sum(d.values()), 1)) for k, v in d.items()), key=lambda kv: -kv[1])[:5])
            for c, d in sorted(by.items())}

    from study.detect import frames_for

    run_cfg = json.loads((run / "config.json").read_text())
    train_idx, _ = frames_for(run_cfg, data, "train")
    return {
        "protocol": ev.ed.protocol,
        "metric": "VOC all-point AP at IoU 0.5 in the right camera, difficult ground truth ignored; "
                  "vehicle mAP = mean over car, van, truck, bus",
        "fusion": method,
        "dataset": {"frames": len(ev.reader), "train_frames": len(train_idx), "test_frames": n,
                    "contexts": ctx_list, "twins": bool(ev.reader.manifest["config"].get("twins")),
                    "frames_per_context_test": {c: contexts.count(c) for c in ctx_list}},
        "machine": machine_description(setup.threads if setup else 1),
        "device": setup.describe() if setup else "cpu",
        "branches": branches, "singles": singles, "late": list(late),
        "k": min(e.k, len(branches)), "lambda_e": e.lambda_e, "gamma": e.gamma, "rule": e.rule,
        "hydra_gate": e.hydra_gate, "eco_gate": e.eco_gate,
        "methods": {name: {"what": kinds[name], **_summary(sc)} for name, sc in scores.items()},
        "intervals": intervals,
        "hydra_table2": table2, "hydra_table3": hydra_tables["table3"], "hydra_table4": table4,
        "hydra_table5": table5, "hydra_table6": hydra_tables["map_table"], "hydra_table7": hydra_tables["selection_rate"],
        "hydra_selection_per_context": hydra_tables["selection_rate_per_context"],
        "hydra_loss_mae": hydra_tables.get("loss_mae"),
        "eco": {k: v for k, v in eco_tables.items() if k not in ("curve",)},
        "eco_curve": eco_tables["curve"],
        "energy_unit": ev.energy_label(),
        "severity": sweep_rows, "severity_clear_twins": twins is not None,
        "range_per_context": range_rows,
        "regret": regret, "fusion_regret": fusion_regret, "picks": picks,
        "figures": {"figure4": str(Path(eco_tables["figures"][0]).relative_to(work)),
                    "figure5": str(Path(eco_tables["figures"][1]).relative_to(work))},
    }


def _check(results: dict) -> None:
    if "methods" not in results:
        raise UserError("results.json holds no study results")
