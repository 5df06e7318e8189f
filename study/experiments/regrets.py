"""What the study measures beyond the papers' tables, per context: each gate's regret against its
oracle (HydraFusion's against the optimal gate, EcoFusion's against the loss-based one) and how
often its selection differs from the oracle's, each sensor's fusion regret (late fusion with it
against late fusion without it), and the selections each gate makes most often. Called by
`study.pipeline.evaluation.evaluate_study`."""

from __future__ import annotations

from collections import defaultdict

import numpy as np

from study.numbers import rounded


def config_index_of(ev) -> dict[tuple[str, ...], int]:
    """Configuration (tuple of branch names) -> its index in the EcoFusion configuration set of `ev`."""
    return {m: i for i, m in enumerate(ev.configs.members)}


def _map_in(sc: dict, ctx: str):
    """A score's mAP in one context, or over all frames (ctx "all")."""
    return sc["map"] if ctx == "all" else sc["map_per_context"].get(ctx)


def hydra_regret(selections: dict, scores: dict, gates, contexts: list[str], k: int | None = None) -> dict:
    """Each HydraFusion gate against the optimal gate, per context and over all frames: both mAPs,
    the mAP regret and how often the two choose differently. `selections` hold each gate's top k
    (evaluate.k, the k of the mAP rows); `k` is recorded with each row."""
    opt, best = selections["hydrafusion:optimal"], scores["hydrafusion:optimal"]
    out = {}
    for g in gates:
        if g == "optimal":
            continue
        selection, sc = selections[f"hydrafusion:{g}"], scores[f"hydrafusion:{g}"]
        row = {}
        for ctx in [*sorted(set(contexts)), "all"]:
            frames_ = [k for k, c in enumerate(contexts) if ctx == "all" or c == ctx]
            a, o = _map_in(sc, ctx), _map_in(best, ctx)
            row[ctx] = {"map": a, "map_oracle": o, "regret_map": None if a is None or o is None else rounded(o - a),
                        "differs_pct": rounded(100.0 * np.mean([selection[k] != opt[k] for k in frames_]), 1),
                        "frames": len(frames_), "k": k}
        out[g] = row
    return out


def eco_regret(ev, eco_config_index: dict, scores: dict, contexts: list[str]) -> dict:
    """Each EcoFusion gate against the loss-based oracle, per context and over all frames: both mAPs,
    both mean L_f, the regrets and how often the two choose differently."""
    lb, best = eco_config_index["loss_based"], scores["ecofusion:loss_based"]
    rows_n = np.arange(len(ev.test))
    out = {}
    for g, ch in eco_config_index.items():
        if g == "loss_based":
            continue
        sc = scores[f"ecofusion:{g}"]
        row = {}
        for ctx in [*sorted(set(contexts)), "all"]:
            keep = np.array([ctx == "all" or c == ctx for c in contexts])
            a, o = _map_in(sc, ctx), _map_in(best, ctx)
            lf = ev.losses[rows_n, ch][keep].mean()
            lf_o = ev.losses[rows_n, lb][keep].mean()
            row[ctx] = {"map": a, "map_oracle": o, "regret_map": None if a is None or o is None else rounded(o - a),
                        "avg_loss": rounded(lf), "avg_loss_oracle": rounded(lf_o), "regret_loss": rounded(lf - lf_o),
                        "differs_pct": rounded(100.0 * float(np.mean(ch[keep] != lb[keep])), 1), "frames": int(keep.sum())}
        out[g] = row
    return out


def fusion_regret(M, ev, scores: dict, late, contexts: list[str]) -> dict:
    """Each sensor's fusion regret: late fusion with its branch against late fusion without it, per
    context (mAP and L_f), and the contexts where adding it lowers the mAP. `M`: the study's
    `study.pipeline.evaluation.Methods`."""
    index = config_index_of(ev)
    late_idx = index[tuple(late)]
    with_ = scores["late"]
    out = {}
    for b in late:
        rest = tuple(x for x in late if x != b)
        if not rest:
            continue
        without = M.score(M.fixed(rest))
        rest_idx = index[rest]
        row = {}
        for ctx in [*sorted(set(contexts)), "all"]:
            keep = np.array([ctx == "all" or c == ctx for c in contexts])
            a, w = _map_in(with_, ctx), _map_in(without, ctx)
            row[ctx] = {"map_with": a, "map_without": w,
                        "regret_map": None if a is None or w is None else rounded(w - a),
                        "regret_loss": rounded(ev.losses[keep, late_idx].mean() - ev.losses[keep, rest_idx].mean())}
        hurts = {c: v["regret_map"] for c, v in row.items() if c != "all" and v["regret_map"] is not None
                 and v["regret_map"] > 0}
        out[b] = {"per_context": row, "hurts_in": hurts,
                  "worst_context": max(hurts, key=hurts.get) if hurts else None,
                  "worst_regret_map": max(hurts.values()) if hurts else 0.0}
    return out


def gate_selection_shares(selections: dict, contexts: list[str]) -> dict:
    """What each gate picks per context: its five most frequent selections, % of the context's frames."""
    shares: dict = {"hydrafusion": {}, "ecofusion": {}}
    for name, selection in selections.items():
        fam = name.split(":")[0]
        if fam not in shares:
            continue
        by = defaultdict(lambda: defaultdict(int))
        for c, m in zip(contexts, selection):
            by[c]["+".join(m)] += 1
        shares[fam][name.split(":", 1)[1]] = {
            c: dict(sorted(((k, rounded(100.0 * v / sum(d.values()), 1)) for k, v in d.items()), key=lambda kv: -kv[1])[:5])
            for c, d in sorted(by.items())}
    return shares


REGRET_ORACLE = {"hydrafusion": "hydrafusion:optimal", "ecofusion": "ecofusion:loss_based"}


def regret_intervals(regret: dict, intervals: dict | None) -> dict:
    """Add to each regret row (`hydra_regret`, `eco_regret`) the 95 % interval of its mAP regret, oracle
    minus gate, from the study's bootstrap (the same draws of test sequences as every other
    interval; `study.engine.scoring.difference_interval`), None without intervals. Returns `regret`."""
    from study.engine.scoring import difference_interval

    per = (intervals or {}).get("per_context") or {}
    for fam, gates in regret.items():
        oracle = REGRET_ORACLE[fam]
        for g, row in gates.items():
            for ctx, v in row.items():
                pg = per.get(ctx)
                v["regret_interval"] = difference_interval(pg, oracle, f"{fam}:{g}") if pg else None
    return regret


def learning_curve(run, learned) -> dict:
    """Each learned HydraFusion gate's test regret against the best constant and the per-context
    constant as its fitting set grows (`GatesSection.curve`; the gates stage's result.json of each
    size and of the full gate): {gate: [{fit_frames, regret, constant_regret, context_regret,
    minus_constant, minus_context}, ...]} by fitting frames (intervals over test sequences)."""
    import json
    from pathlib import Path

    out = {}
    for g in learned:
        d = Path(run) / "gates" / g
        paths = [d / "result.json", *sorted((d / "curve").glob("*/result.json"))]
        rows = []
        for p in paths:
            if p.is_file():
                r = json.loads(p.read_text())
                c = r.get("choice") or {}
                rows.append({"fit_frames": r["train_frames"], "objective": r.get("objective"),
                             "regret": c.get("regret"), "constant_regret": c.get("constant_regret"),
                             "context_regret": c.get("context_regret"), "minus_constant": c.get("minus_constant"),
                             "minus_context": c.get("minus_context"), "test_frames": r.get("test_frames")})
        if len(rows) > 1:
            out[f"hydrafusion:{g}"] = sorted(rows, key=lambda x: x["fit_frames"])
    return out
