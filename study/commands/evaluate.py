"""`hydrabench evaluate`: the command line of `study.engine.run_eval` (branches fused) and of the gate tables
of `study.engine.gate_tables` (--gate, --all-gates), with their text (`format_tables`: HydraFusion Tables 6, 7)."""

from __future__ import annotations

import sys
from pathlib import Path

from sim.errors import UserError
from study.cli import (
    FUSION_HELP,
    Formatter,
    bootstrap_int,
    checkpoint_arg,
    dataset_dir,
    emit,
    fusion_arg,
    name_arg,
    name_list,
    pos_int,
    training_run,
)
from study.commands.device import add_device_args
from study.engine import run_eval as evaluation
from study.engine.device import resolve_device

EPILOG = """\
examples:
  hydrabench evaluate runs/all data/train1600 --branches all --fusion soft-nms --json
  hydrabench evaluate runs/all data/train1600 --branches radar,camera_right --fusion wbf
  hydrabench evaluate runs/all data/fog_only --branches camera_right        (another dataset: all frames)
  hydrabench evaluate runs/all data/train1600 --gate attention --k 3 --fusion soft-nms --json
  hydrabench evaluate runs/all data/train1600 --all-gates --json                      (Tables 6 and 7)
"""


def add_parser(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=evaluation.__doc__, epilog=EPILOG, formatter_class=Formatter)
    p.add_argument("run_dir", metavar="RUN", type=training_run, help="training run directory (hydrabench train --out)")
    p.add_argument("data", type=dataset_dir, help="dataset directory")
    p.add_argument("--branches", type=name_list, default="all", help="comma-separated branch names, each once, or 'all'")
    p.add_argument("--fusion", type=fusion_arg, default="soft-nms", help=FUSION_HELP)
    p.add_argument("--split", default="auto", choices=["auto", "test", "train", "all", "data-test"],
                   help="auto: the run's test split on its own dataset, every frame on another; data-test: "
                   "DATA's own by-sequence test split (the run's split settings), i.e. the frames a run trained "
                   "on DATA is tested on, to compare two runs on the same frames")
    p.add_argument("--weights", type=name_list, default=None,
                   help="per-branch fusion weights (finite, >= 0), e.g. radar=2,camera_right=1")
    p.add_argument("--contexts", type=name_list, default=None, help="comma-separated contexts to score (e.g. city,junction,motorway,"
                   "rural for clear weather); default: every frame of the split")
    p.add_argument("--twins", action="store_true", help="also run on the clear-weather twins of the same frames "
                   "(a dataset generated with --twins) and report the vehicle mAP each branch keeps, per severity")
    p.add_argument("--bootstrap", type=bootstrap_int, default=0, metavar="N",
                   help="95%% intervals from N draws of whole sequences with replacement (frames of a sequence "
                   "share traffic and weather): each branch's and the fused vehicle mAP per context, and every "
                   "difference between them on the same draws (\"ci95\"); with --twins, each degraded, clear and "
                   "retained figure instead, overall and per severity (default: 0, none; 1000 for a table)")
    p.add_argument("--checkpoint", type=checkpoint_arg, default="latest", help="latest, or epoch-NNN")
    p.add_argument("--protocol", default=None, choices=("reference", "visible", "bev"),
                   help="ground truth (README, 'Evaluation protocols'); default: the protocol the run trained on")
    p.add_argument("--batch-size", type=pos_int, default=4, help="frames per forward pass")
    p.add_argument("--gate", type=name_arg, default=None, help="knowledge | deep | attention | optimal: the gate selects the branches")
    p.add_argument("--k", default=None, help="branches the gate keeps per frame: 1..number of branches, or all "
                   "(default 3, or all when the run has fewer)")
    p.add_argument("--all-gates", action="store_true",
                   help="Tables 6 and 7: every gate x nms/soft-nms/wbf x k in 1, 3, 5, all")
    add_device_args(p, purpose="eval")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(run=run)


def parse_weights(text) -> dict[str, float]:
    """'radar=2,camera_right=1' (or its items) -> {branch: weight}; each branch once, weights finite >= 0."""
    import math

    parts = text.split(",") if isinstance(text, str) else list(text or ())
    out = {}
    for part in filter(None, (t.strip() for t in parts)):
        name, _, value = part.partition("=")
        try:
            w = float(value)
        except ValueError:
            raise UserError(f"--weights: {part!r} is not name=number") from None
        if not (math.isfinite(w) and w >= 0):
            raise UserError(f"--weights: {part!r}: a weight is a finite number >= 0")
        if name.strip() in out:
            raise UserError(f"--weights: {name.strip()!r} is given twice")
        out[name.strip()] = w
    return out


def run_gates(args) -> int:
    from study.engine import gate_tables

    if args.gate and args.all_gates:
        raise UserError("--gate and --all-gates exclude each other (--all-gates evaluates every gate)")
    if args.contexts:
        raise UserError("--contexts is for evaluating branches; gated results report map_per_context")
    if args.twins or args.bootstrap:
        raise UserError("--twins and --bootstrap are for evaluating branches, not gates")
    if args.branches not in ("all", "", ("all",)):
        raise UserError("--branches cannot be combined with a gate: the gate chooses among all of the run's branches")
    weights = parse_weights(args.weights)
    if args.all_gates:
        if args.k is not None:
            raise UserError("--k is for --gate; --all-gates evaluates k = 1, 3, 5 and all")
        result = gate_tables.evaluate_all_gates(Path(args.run_dir), Path(args.data), split=args.split,
                                                      weights=weights, checkpoint=args.checkpoint,
                                                      batch_size=args.batch_size, setup=resolve_device(args, purpose="eval"))
        emit(result, args.json, format_tables)
        return 0
    result = gate_tables.evaluate_gate(Path(args.run_dir), Path(args.data), args.gate, args.k, args.fusion,
                                             args.split, weights, args.checkpoint, args.batch_size,
                                             setup=resolve_device(args, purpose="eval"))

    def text(r):
        k = str(r["k"])
        rates = r["selection_rate"][r["gate"]][k]
        return "\n".join([
            f"mAP@0.5 {r['map']} ({r['gate']} gate, top {k}, {r['fusion']}; {r['frames']} {r['split']} frames, "
            f"right camera, difficult boxes ignored; {r['branch_runs_per_frame']} branch runs per frame)",
            "  per class: " + ", ".join(f"{c} {v}" for c, v in r["ap_per_class"].items() if v is not None),
            "  per context: " + ", ".join(f"{c} {v}" for c, v in r["map_per_context"].items()),
            "  selected [% of frames]: " + ", ".join(f"{b} {v}" for b, v in rates.items()),
        ])

    emit(result, args.json, text)
    return 0


def run(args) -> int:
    if args.gate is not None or args.all_gates:
        return run_gates(args)
    if args.k is not None:
        raise UserError("--k needs --gate (the number of branches a gate keeps)")
    contexts = tuple(args.contexts or ())
    branches = args.branches if isinstance(args.branches, str) else ",".join(args.branches)
    result = evaluation.evaluate(Path(args.run_dir), Path(args.data), branches, args.fusion, args.split,
                      parse_weights(args.weights), args.checkpoint, args.batch_size, contexts, args.twins,
                      args.protocol, setup=resolve_device(args, purpose="eval"), bootstrap=args.bootstrap)

    if "warning" in result.get("twins", {}):
        print(f"warning: {result['twins']['warning']}", file=sys.stderr)

    def band(ci) -> str:
        """ ' [lo, hi]' of a bootstrap interval of the retained figure ('' without one)."""
        return f" [{ci['retained'][0]}, {ci['retained'][1]}]" if ci and ci["retained"] else ""

    def text(r):
        where = "" if r["contexts"] == "all" else f" of {', '.join(r['contexts'])}"
        proto = r["protocol"]["name"]
        if proto == "bev":
            lines = [f"protocol bev: each BEV branch on its own grid ({r['frames']} {r['split']} frames{where})"]
            for b, sc in r["per_branch"].items():
                lines.append(f"  {b}: mAP {sc['map']}, vehicles {sc['map_vehicles']}; per range: "
                             + ", ".join(f"{k} {v}" for k, v in sc["map_vehicles_per_range"].items()))
            return "\n".join(lines)
        lines = [f"mAP@0.5 {r['map']} ({r['fusion']} of {', '.join(r['branches'])}; {r['frames']} {r['split']} frames"
                 f"{where}, right camera, protocol {proto}, difficult boxes ignored)"]
        lines.append("  vehicles per range [m]: " + ", ".join(f"{k} {v}" for k, v in r["map_vehicles_per_range"].items()))
        lines.append("  per class: " + ", ".join(f"{k} {v}" for k, v in r["ap_per_class"].items() if v is not None))
        lines.append("  per context: " + ", ".join(f"{k} {v}" for k, v in r["map_per_context"].items()))
        lines.append(f"  vehicles (car, van, truck, bus): {r['map_vehicles']}; per context: "
                     + ", ".join(f"{k} {v}" for k, v in r["map_vehicles_per_context"].items()))
        lines.append("  each branch alone (own frame / right camera): " + ", ".join(
            f"{b} {r['map_per_branch_native'][b]}/{r['map_per_branch_reference'][b]}" for b in r["branches"]))
        if "ci95" in r:
            ci = r["ci95"]
            lines.append(f"  95% intervals of the vehicle mAP ({ci['resamples']} draws of whole sequences):")
            for g, v in ci["per_context"].items():
                lines.append(f"    {g} ({v['sequences']} sequences): " + ", ".join(
                    f"{n} [{c[0]}, {c[1]}]" for n, c in v["map_vehicles"].items() if c)
                    + "; fused - each: " + ", ".join(
                    f"{k.split(' - ')[1]} [{c[0]}, {c[1]}]" for k, c in v["difference"].items()
                    if c and k.startswith("fused - ")))
        if "twins" in r:
            lines.append("  same frames in clear weather (vehicles, own frame: degraded / clear = retained):")
            for b, t in [*r["twins"]["branches"].items(), ("fused", r["twins"]["fused"])]:
                op = t["at_score_0.5"]
                ci = t.get("ci95")
                lines.append(f"    {b}: {t['degraded']} / {t['clear']} = {t['retained']}"
                             + (band(ci["all"]) if ci else "") + "; per severity: " + ", ".join(
                    f"{s} {v['retained']}" + (band(ci["per_severity"].get(s)) if ci else "")
                    for s, v in t["per_severity"].items())
                    + f"; recall at score 0.5: {op['degraded']['recall']} / {op['clear']['recall']}")
                lines.append("      recall at 0.5 by distance / visibility (degraded / clear, objects): " + ", ".join(
                    f"{k} {v['degraded']} / {v['clear']} ({v['objects']})"
                    for k, v in op["by_distance_over_visibility"].items()))
        return "\n".join(lines)

    emit(result, args.json, text)
    return 0


def format_tables(r: dict) -> str:
    """Tables 6 and 7 as text."""
    ks = r["ks"]
    lines = [f"Table 6: mAP@0.5 per gate, fusion and k ({r['frames']} {r['split']} frames, right camera)",
             f"{'gate':10s} {'fusion':9s} " + " ".join(f"{'k=' + k:>7s}" for k in ks)]
    for g, per in r["map_table"].items():
        for f, row in per.items():
            lines.append(f"{g:10s} {f:9s} " + " ".join(
                f"{row[k]:7.4f}" if row.get(k) is not None else f"{'-':>7s}" for k in ks))
    lines.append("")
    lines.append("Table 7: branch selection rate [% of frames]")
    branches = r["branches"] if "branches" in r else list(next(iter(next(iter(r["selection_rate"].values())).values())))
    lines.append(f"{'k':>4s} {'gate':10s} " + " ".join(f"{b[:12]:>12s}" for b in branches))
    for k in ks:
        if k == "all":
            continue
        for g, per in r["selection_rate"].items():
            lines.append(f"{k:>4s} {g:10s} " + " ".join(f"{per[k][b]:12.2f}" for b in branches))
    if r.get("loss_mae"):
        lines.append("")
        lines.append("predicted-loss MAE on these frames: " + ", ".join(f"{g} {v}" for g, v in r["loss_mae"].items()))
    return "\n".join(lines)
