"""The study's report: `report.md`, a self-contained `report.html` (figures embedded as base64
PNG) and `report.json` (every number of both), from the evaluation stage's `results.json`.

Both documents are rendered from one list of blocks (headings, paragraphs, tables, figures), so
they hold the same tables. Every table's caption names the protocol, the scale, the dataset size
and the machine. A study whose numbers mean nothing (smoke, tests) says so in its first line.
"""

from __future__ import annotations

import base64
import html
import json
import os
from pathlib import Path

from fusion.boxes import FUSION_METHODS, method_label
from study.numbers import interval_text, number_text
from study.outputs import write_text_atomic
from study.report.bounds import (
    add_coverage,
    add_energy_front,
    add_learning_curve,
    add_optimal_appendix,
    add_room,
    add_room_corrected,
    main_methods,
    named,
)
from study.report.crossover import add_crossover, add_physical_gate, add_transitions
from study.report.pem import add_pem

REPORT_VERSION = 2



def settled(path: Path) -> Path:
    """Where a file written inside a stage's work directory (`<stage>-<key>.partial`, renamed to
    `<stage>-<key>` when the stage ends, `study.pipeline.cache.Study.stage`) will be: the Markdown links to
    that, not to the directory that is gone by the time anyone reads the report."""
    return Path(*[part.removesuffix(".partial") for part in Path(path).parts])


class Doc:
    def __init__(self) -> None:
        self.blocks: list[tuple] = []

    def h(self, level: int, text: str) -> None:
        self.blocks.append(("h", level, text))

    def p(self, text: str) -> None:
        self.blocks.append(("p", text))

    def table(self, caption: str, header: list[str], rows: list[list]) -> None:
        self.blocks.append(("table", caption, header, [[number_text(c) for c in r] for r in rows]))

    def img(self, caption: str, path: Path) -> None:
        if Path(path).is_file():
            self.blocks.append(("img", caption, Path(path)))

    def markdown(self, rel_to: Path) -> str:
        out = []
        for b in self.blocks:
            if b[0] == "h":
                out.append("#" * b[1] + " " + b[2])
            elif b[0] == "p":
                out.append(b[1])
            elif b[0] == "table":
                _, caption, header, rows = b
                out.append(f"*{caption}*\n")
                out.append("| " + " | ".join(header) + " |")
                out.append("|" + "|".join("---" for _ in header) + "|")
                out.extend("| " + " | ".join(r) + " |" for r in rows)
            elif b[0] == "img":
                out.append(f"![{b[1]}]({os.path.relpath(settled(b[2]), rel_to)})\n\n*{b[1]}*")
            out.append("")
        return "\n".join(out)

    def html(self, title: str) -> str:
        parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
                 "<style>body{font-family:sans-serif;max-width:1100px;margin:auto;padding:1em}"
                 "table{border-collapse:collapse;margin:0.5em 0 1.5em}td,th{border:1px solid #bbb;padding:2px 6px;"
                 "font-size:13px;text-align:right}th{background:#eee}td:first-child{text-align:left}"
                 "caption{caption-side:top;text-align:left;font-style:italic;font-size:13px;padding:4px}"
                 "img{max-width:100%}</style></head><body>"]
        for b in self.blocks:
            if b[0] == "h":
                parts.append(f"<h{b[1]}>{html.escape(b[2])}</h{b[1]}>")
            elif b[0] == "p":
                text = html.escape(b[1]).replace("**", "")
                parts.append(f"<p>{text}</p>")
            elif b[0] == "table":
                _, caption, header, rows = b
                parts.append(f"<table><caption>{html.escape(caption)}</caption><tr>"
                             + "".join(f"<th>{html.escape(x)}</th>" for x in header) + "</tr>")
                for r in rows:
                    parts.append("<tr>" + "".join(f"<td>{html.escape(x)}</td>" for x in r) + "</tr>")
                parts.append("</table>")
            elif b[0] == "img":
                data = base64.b64encode(b[2].read_bytes()).decode()
                parts.append(f"<figure><img alt='{html.escape(b[1])}' src='data:image/png;base64,{data}'>"
                             f"<figcaption>{html.escape(b[1])}</figcaption></figure>")
        parts.append("</body></html>")
        return "\n".join(parts)


def _severity_figure(results: dict, path: Path) -> bool:
    """mAP (vehicles) against severity per condition, one line per method; dashed: clear twins."""
    sev = results.get("severity") or {}
    if not sev:
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    from study.outputs import savefig_atomic

    conds = list(sev)
    fig, axes = plt.subplots(1, len(conds), figsize=(4.2 * len(conds), 3.6), squeeze=False, sharey=True)
    for ax, cond in zip(axes[0], conds):
        for name, rows in sev[cond].items():
            xs = [int(s) for s in rows if rows[s]["degraded"] is not None]
            ys = [rows[str(s)]["degraded"] for s in xs]
            if not xs:
                continue
            line, = ax.plot(xs, ys, "o-", label=name, lw=1.2, ms=4)
            xc = [int(s) for s in rows if rows[s]["clear"] is not None]
            if xc:
                ax.plot(xc, [rows[str(s)]["clear"] for s in xc], ":", color=line.get_color(), lw=1)
        ax.set_title(cond)
        ax.set_xlabel("severity")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))  # severities are levels 1-5
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("vehicle mAP@0.5 (dotted: clear twins)")
    axes[0][-1].legend(fontsize=6, loc="best")
    fig.suptitle("mAP against severity per condition (test frames; twins differ only by the weather)", fontsize=10)
    savefig_atomic(fig, path, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return True


def build(results: dict, context: dict, work: Path, eval_dir: Path) -> tuple[Doc, dict]:
    """The report (the papers' tables in their order, then what neither paper has) and its summary."""
    r = results
    tag = run_tag(r, context["scale"])
    doc = Doc()
    add_intro(doc, r, context, tag)
    add_verdict(doc, r, tag, work)
    add_room(doc, r, tag)
    add_room_corrected(doc, r, tag)
    add_hydra_table2(doc, r, tag)
    add_intervals(doc, r, tag)
    add_coverage(doc, r, tag)
    add_hydra_table3(doc, r, tag)
    add_hydra_table4(doc, r, tag)
    front = add_energy_front(doc, r, tag, work)
    add_hydra_table5(doc, r, tag)
    add_hydra_tables_6_7(doc, r, tag)
    add_eco_tables(doc, r, tag, eval_dir)
    add_severity(doc, r, tag, work)
    crossover = add_crossover(doc, r, tag, work)
    physical = add_physical_gate(doc, r, tag)
    transitions = add_transitions(doc, r, tag, work)
    pem = add_pem(doc, r, tag, work)
    add_range_bins(doc, r, tag)
    add_gate_regret(doc, r, tag)
    add_gate_training(doc, r, tag)
    add_learning_curve(doc, r, tag)
    add_fusion_regret(doc, r, tag)
    add_gate_picks(doc, r, tag)
    add_robustness(doc, r, tag)
    add_choices(doc, r, tag)
    add_optimal_appendix(doc, r, tag)
    add_stages(doc, context, tag)
    summary = {"scale": context["scale"], "meaningless": bool(context.get("meaningless")), "protocol": r["protocol"],
               "dataset": r["dataset"], "machine": r["machine"], "device": r.get("device"), "tag": tag,
               **({"energy_front": front} if front else {}), **({"crossover": crossover} if crossover else {}),
               **({"physical_gate": physical} if physical else {}),
               **({"transitions": transitions} if transitions else {}), **({"pem": pem} if pem else {})}
    return doc, summary


def run_tag(r: dict, scale: str) -> str:
    """What every caption names: the protocol, the scale, the dataset's size and the machine."""
    ds, m = r["dataset"], r["machine"]
    dev = r.get("device")
    dev = dev.get("device", "") if isinstance(dev, dict) else str(dev or "")
    machine = f"{m.get('cpu') or m.get('platform', '?')}, {m.get('threads', '?')} thread(s), device {dev}"
    sets = ds.get("sets") or {}
    gate = (f"{ds['gate_frames']} gate {'set (seed ' + str(sets['gate']['seed']) + ')' if 'gate' in sets else 'split'}, "
            if ds.get("gate_frames") else "")
    test = f"{ds['test_frames']} test" + (f" set (seed {sets['test']['seed']})" if "test" in sets else "")
    return (f"protocol {r['protocol']}; scale {scale}; dataset {ds['frames']} frames ({ds['train_frames']} train, "
            f"{gate}{test}); machine {machine}")


def add_intro(doc: Doc, r: dict, context: dict, tag: str) -> None:
    """The warning of a meaningless scale, the title, what is measured how, and the stages' times."""
    ds, scale = r["dataset"], context["scale"]
    if context.get("meaningless"):
        doc.p(f"**These numbers mean nothing**: scale `{scale}` trains for minutes on a handful of frames, to check "
              "that every stage runs; read a `cpu` or `paper` study for results.")
    doc.h(1, f"hydrabench study: selective against fixed fusion (scale {scale})")
    rule = f" ({r['fusion_rule']})" if r.get("fusion_rule") else ""
    doc.p(f"{tag}. Metric: {r['metric']}. Late fusion method: {r['fusion']}{rule}. Every method is scored on the "
          f"same {ds['test_frames']} test frames (contexts: {', '.join(ds['contexts'])}).")
    one = r.get("one_path")
    if one:
        if one["disagreements"]:
            doc.p(f"**One scoring path broken**: {len(one['disagreements'])} of {one['checked']} table cells show a "
                  "method with another mAP than its own: " + "; ".join(
                      f"{d['where']}: {d['shown']} (its own {d['own']})" for d in one["disagreements"]) + ".")
        else:
            doc.p(f"One scoring path: the {one['checked']} table cells that show a method ({len(one['methods'])} "
                  "methods) hold its own mAP (`study.experiments.one_path`).")


def add_verdict(doc: Doc, r: dict, tag: str, work: Path) -> None:
    """The answer first: what the intervals resolve (`study.report.verdict`), and each method's mAP minus late
    fusion's per context with its interval."""
    from study.report.verdict import answer_sentences, verdict_figure

    answer = answer_sentences(r)
    if not answer:
        return
    doc.h(2, "The answer")
    doc.p(" ".join(answer))
    if verdict_figure(r, work / "verdict.png"):
        doc.img(f"mAP@0.5 minus late fusion's per context, 95 % intervals; hollow: not resolved ({tag})",
                work / "verdict.png")


def add_stages(doc: Doc, context: dict, tag: str) -> None:
    """The stages' keys and times (what ran, what was reused)."""
    stages = context.get("stages", {})
    if stages:
        doc.h(2, "Stages")
        doc.table(f"Stages (seconds when each ran; {tag})", ["stage", "key", "seconds"],
                  [[n, s.get("key"), s.get("seconds")] for n, s in stages.items()])


def add_robustness(doc: Doc, r: dict, tag: str) -> None:
    """The field's robustness metrics (`study.experiments.robustness_table`): per method mRA and mRR on the clear
    twins (MultiCorrupt, Robo3D), mCE against late fusion, and RA per condition."""
    from study.experiments.robustness_table import robustness_table

    table = r.get("robustness") or robustness_table(r)
    methods = table.get("methods") or {}
    if not methods:
        return
    conds = sorted({c for t in methods.values() for c in t["conditions"]})
    doc.h(2, "Robustness in the field's metrics")
    doc.p("RA = mAP under the condition / mAP of the same frames' clear twins, averaged over severities, and mRA its "
          "mean over conditions (MultiCorrupt); RR = the sum over severities of the degraded mAP / the sum of the "
          "clear twins', mRR its mean (Robo3D); CE = the sum over severities of (1 - mAP) / the same sum of the "
          f"baseline's ({table.get('baseline', 'late')}), mCE its mean (Robo3D). Point estimates: each severity "
          "stands on the test frames of that severity only.")
    doc.table(f"Robustness per method ({tag})", ["method", "mRA", "mRR", "mCE", *[f"RA {c}" for c in conds]],
              [[m, number_text(t.get("mra")), number_text(t.get("mrr")), number_text(t.get("mce")),
                *[number_text(t["conditions"].get(c, {}).get("ra")) for c in conds]] for m, t in methods.items()])


def _gate_ks(r: dict) -> list:
    """The k of the gate tables (HydraFusion Tables 3, 6, 7): numbers ascending, then "all"."""
    return sorted({k for v in r["hydra_table3"].values() for k in v["map"]}, key=lambda k: (k == "all", k))


def add_hydra_table2(doc: Doc, r: dict, tag: str) -> None:
    """HydraFusion Table 2 (single sensors, early, late, HydraFusion) and every method per context."""
    doc.h(2, "HydraFusion Table 2 analogue: single sensors, early, late, HydraFusion")
    t2 = r["hydra_table2"]
    rows = []
    for group, label in (("single_sensors", "(i) single sensor"), ("early_fusion", "(ii) early fusion"),
                         ("late_fusion", "(iii) late fusion (method chosen on validation)"),
                         ("hydrafusion", "(iv) HydraFusion"), ("ecofusion", "EcoFusion")):
        for name, v in t2.get(group, {}).items():
            rows.append([label, name, v])
    doc.table(f"mAP@0.5 ({tag})", ["set", "model", "mAP"], rows)
    ctxs = r["dataset"]["contexts"]
    rows = [[named(r, name), r["methods"][name]["what"], r["methods"][name]["map"],
             *[r["methods"][name]["map_per_context"].get(c) for c in ctxs]] for name in main_methods(r)]
    doc.table(f"mAP@0.5 per context, every method ({tag})", ["method", "what", "all", *ctxs], rows)


def add_intervals(doc: Doc, r: dict, tag: str) -> None:
    """The bootstrap intervals of every method's mAP and of its difference from late fusion."""
    ctxs = r["dataset"]["contexts"]
    ci = r.get("intervals")
    if ci:
        from study.engine.scoring import difference_interval

        doc.h(2, "How sure: 95 % intervals of every method's mAP and of its difference from late fusion")
        doc.p(f"{ci['resamples']} draws of whole test sequences with replacement (frames of a sequence share traffic "
              "and weather), overall from all sequences and per context from the context's own; every method is "
              "scored on each draw, so a difference is paired. An interval of a difference that excludes 0 says the "
              "order would hold on another draw of sequences like these; one that includes 0 says this study "
              "cannot order the two.")
        per = ci["per_context"]
        groups = ["all", *[c for c in ctxs if c in per]]

        def cell(lo_hi) -> str:
            return interval_text(lo_hi or None)

        doc.table(f"mAP@0.5: 95 % interval per context ({tag})", ["method", *[f"{g} ({per[g]['sequences']} seq)" for g in groups]],
                  [[named(r, n), *[cell(per[g]["map"].get(n)) for g in groups]] for n in main_methods(r)])
        from study.report.verdict import verdict_sentences

        for sentence in verdict_sentences(r):
            doc.p(sentence)
        if "late" in r["methods"]:
            doc.table(f"mAP@0.5 minus late fusion's: 95 % interval of the paired difference per context ({tag})",
                      ["method", *groups],
                      [[named(r, n), *[cell(difference_interval(per[g], n, "late")) for g in groups]]
                       for n in main_methods(r) if n != "late"])


def add_hydra_table3(doc: Doc, r: dict, tag: str) -> None:
    """HydraFusion Table 3: each gate's best fusion method per k."""
    t3, ks = r["hydra_table3"], _gate_ks(r)
    doc.h(2, "HydraFusion Table 3 analogue: best fusion per gate and k")
    chosen = "chosen on the validation frames at k = " + str(r["k"]) if any(
        v.get("chosen_on") == "validation" for v in t3.values()) else "best on the test frames"
    doc.table(f"mAP@0.5 on the test frames of each gate's fusion method, {chosen} ({tag})", ["gate", "fusion", *[f"k={k}" for k in ks]],
              [[g, v["fusion"], *[v["map"].get(k) for k in ks]] for g, v in t3.items()])


def add_hydra_table4(doc: Doc, r: dict, tag: str) -> None:
    """HydraFusion Table 4: latency and energy per method."""
    doc.h(2, "HydraFusion Table 4 analogue: latency and energy per model")
    doc.p(f"Latency: the additive model of measured stem, branch and fusion latencies on this machine (batch 1); "
          f"energy: {r['energy_unit']}. Gated methods: the mean over frames of the chosen branches.")
    doc.p("A learned gate (deep, attention) is charged the stems it reads that its chosen branches do not need "
          "and its own network's measured time (gate), as EcoFusion Table 1 charges the stems.")
    doc.table(f"Latency and energy ({tag})", ["method", "branches run", "latency [ms]", "gate [ms]", "energy [J]",
                                              "energy (lambda_E scale)"],
              [[n, v["branches"], v["latency_ms"], v.get("gate_ms", v.get("gate_stems_ms", 0.0)), v["energy_j"],
                v["energy"]] for n, v in r["hydra_table4"].items()])


def add_hydra_table5(doc: Doc, r: dict, tag: str) -> None:
    """HydraFusion Table 5: the late fusion methods on sensor combinations (when any was run)."""
    if r["hydra_table5"]:
        doc.h(2, "HydraFusion Table 5 analogue: late fusion methods")
        names = FUSION_METHODS.names()  # every registered method (fusion.boxes), one column each
        doc.table(f"mAP@0.5 of late-fused single-sensor branches ({tag})", ["sensors", *map(method_label, names)],
                  [[c, *(v.get(n) for n in names)] for c, v in r["hydra_table5"].items()])


def add_hydra_tables_6_7(doc: Doc, r: dict, tag: str) -> None:
    """HydraFusion Tables 6 and 7: mAP per gate, fusion and k; branch selection rates."""
    ks = _gate_ks(r)
    doc.h(2, "HydraFusion Tables 6 and 7 analogues: gates x fusion x k; branch selection rates")
    rows = []
    for g, per in r["hydra_table6"].items():
        if f"hydrafusion:{g}" not in main_methods(r):
            continue  # the appendix shows it
        for f, row in per.items():
            rows.append([g, f, *[row.get(k) for k in ks]])
    doc.table(f"mAP@0.5 per gate, fusion and k ({tag})", ["gate", "fusion", *[f"k={k}" for k in ks]], rows)
    branches = r["branches"]
    rows = []
    for k in ks:
        if k == "all":
            continue
        for g, per in r["hydra_table7"].items():
            if f"hydrafusion:{g}" not in main_methods(r):
                continue
            rows.append([k, g, *[per[k].get(b) for b in branches]])
    doc.table(f"Branch selection rate [% of test frames] ({tag})", ["k", "gate", *branches], rows)


def add_eco_tables(doc: Doc, r: dict, tag: str, eval_dir: Path) -> None:
    """EcoFusion Tables 1-3 and Figures 4-5 (the figures read from `eval_dir`)."""
    eco = r["eco"]
    doc.h(2, "EcoFusion Table 1 analogue: energy and performance")
    doc.p(f"Energy: {r['energy_unit']}; loss: {r.get('loss_unit', 'L_f as computed (raw)')}; gamma {r['gamma']}, Eq. 7 rule {r['rule']}.")
    doc.table(f"mAP, energy and latency ({tag})", ["model", "configuration", "mAP", "energy", "energy [J]", "latency [ms]"],
              [[n, v.get("configuration", ""), v.get("map"), v.get("energy"), v.get("energy_j"), v.get("latency_ms")]
               for n, v in eco["table1"].items()])
    doc.h(2, "EcoFusion Table 2 analogue: gates x lambda_E")
    rows = []
    for lam, per in eco["table2"].items():
        for g, v in per.items():
            rows.append([lam, g, v.get("map"), v.get("avg_loss"), v.get("energy")])
    doc.table(f"mAP, mean fused loss L_f and energy per gate ({tag})", ["lambda_E", "gate", "mAP", "avg L_f", "energy"],
              rows)
    doc.h(2, "EcoFusion Table 3 analogue: sensor clock gating per scene")
    if not eco.get("table3"):
        doc.p("Not computable here: Table 3 compares against late fusion of camera_left, camera_right, radar and "
              f"lidar, and this study's branches ({', '.join(r['branches'])}) do not include all four.")
    else:
        t3e = eco["table3"]
        scenes = sorted({c for v in t3e.values() for c in v})
        period = eco.get("table3_period", "each sensor over one measurement at its own rate")
        doc.table(f"Platform + sensor energy per fused frame, clock-gated where unused; {period} ({tag})",
                  ["method", *scenes],
                  [[n, *[v.get(c) for c in scenes]] for n, v in t3e.items()])
    figs = r.get("figures", {})
    doc.img(f"EcoFusion Figure 4 analogue: loss against energy per gate, lambda_E colour-coded ({tag})",
            eval_dir / figs.get("figure4", "missing.png"))
    front = r.get("lambda_front")
    if front:
        doc.p(f"How far lambda_E moves each gate: its mean energy from lambda_E {_lam_range(front)}, as a share of "
              f"the range between the cheapest single sensor ({front['cheapest_single_energy']}) and late fusion "
              f"({front['late_energy']}). L_f is {front['loss_unit']}, so lambda_E and gamma ({r['gamma']}) weigh "
              f"the same L_f on every dataset: gamma {r['gamma']} admits configurations whose predicted L_f is within "
              f"{r['gamma']} x late fusion's mean training L_f of the best one.")
        doc.table(f"lambda_E front per EcoFusion gate ({tag})",
                  ["gate", "energy at the first lambda_E", "energy at the last", "span [% of single..late]",
                   "lambdas on the Pareto front"],
                  [[g, v["energy_from"], v["energy_to"], v["span_pct"], " ".join(v.get("pareto_lambdas") or [])]
                   for g, v in front["gates"].items()])
    doc.img(f"EcoFusion Figure 5 analogue: loss and energy per scene ({tag})", eval_dir / figs.get("figure5", "missing.png"))


def _lam_range(front: dict) -> str:
    g = next(iter(front["gates"].values()), {})
    return f"{g.get('lambda_from')} to {g.get('lambda_to')}"


def add_gate_training(doc: Doc, r: dict, tag: str) -> None:
    """What each learned gate adds beyond a constant choice and beyond the context (`gate_training`),
    and, with a gate split, what held-out targets change against the detectors' training frames."""
    gt = r.get("gate_training")
    if not gt:
        return
    doc.h(2, "Learned gates against the best constant and the per-context constant")
    doc.p("Each learned gate was trained with every objective (`fusion.gate_objectives`); the one with the lowest "
          "regret on the validation sequences was kept, its epoch picked the same way. On the test frames: the mean "
          "cost (per-branch loss for HydraFusion, L_f for EcoFusion) of the gate's one choice per frame minus the "
          "oracle's (regret), beside the best constant choice and the per-context constant (one choice per context, "
          "both fitted on the gate's fitting frames), and how often the gate's choice differs from the constant's. "
          "A gate adds something when its regret is below both. Two candidates are the router targets of the "
          "literature (issue 36 item 7): 'best_label' classifies which choice is best on the frame (the "
          "best-configuration label), 'context' classifies the frame's context as weather-conditioned routing does "
          "(it regresses its context's row of the per-context table, so it routes as the context it recognises); "
          "each is kept or dropped by its validation regret like the loss objectives.")
    if "test" in (r["dataset"].get("sets") or {}):
        doc.p("With a test set apart from the detectors' data, these regrets are measured by the gates stage on the "
              "detectors' own test split (frames no gate fitted on, but not the study's test set, which the gates "
              "stage never reads); every mAP, interval and regret elsewhere in this report is on the test set.")

    def row(name, v):
        c = v.get("choice") or {}
        objectives = v.get("objectives") or {}
        return [name, v.get("targets"), v.get("train_frames"), v.get("objective"),
                " ".join(f"{o} {x.get('val_regret')}" for o, x in objectives.items()),
                c.get("regret"), c.get("constant_regret"), c.get("context_regret"), c.get("constant"),
                None if c.get("differs_from_constant") is None else round(100 * c["differs_from_constant"], 1)]

    header = ["gate", "targets", "fitting frames", "objective", "validation regret per objective", "test regret",
              "best constant's", "per-context constant's", "best constant", "differs from it [%]"]
    doc.table(f"Learned gates: objective kept (validation regret of each), test regret against the oracle ({tag})",
              header, [row(name, v) for name, v in gt.items()])
    pairs = {name: v for name, v in gt.items() if v.get("in_sample")}
    if pairs:
        doc.p("Held-out against in-sample targets: each gate trained again on the detectors' own training frames "
              "(targets 'train'), where a branch that overfits looks better than it is, and validated on the same "
              "gate-split sequences as the gate above (targets 'holdout': frames no detector trained on). The "
              "validation regret decides nothing here; it and the test regret measure what held-out targets change "
              "(the constants beside each are fitted on that gate's own fitting frames).")
        rows = []
        for name, v in pairs.items():
            for label, w in (("holdout", v), ("train (in-sample)", v["in_sample"])):
                c = w.get("choice") or {}
                rows.append([name, label, w.get("train_frames"), w.get("objective"), w.get("val_regret"),
                             c.get("regret"), c.get("constant_regret"), c.get("context_regret"), c.get("constant"),
                             None if c.get("differs_from_constant") is None
                             else round(100 * c["differs_from_constant"], 1)])
        doc.table(f"Gate targets: held-out gate split against the detectors' training frames ({tag})",
                  ["gate", "targets", "fitting frames", "objective", "validation regret", "test regret",
                   "best constant's", "per-context constant's", "best constant", "differs from it [%]"], rows)


def add_choices(doc: Doc, r: dict, tag: str) -> None:
    """Every choice the study made from data, and where (`study.experiments.selection.SelectionLog`)."""
    ch = r.get("choices")
    if not ch:
        return
    doc.h(2, "What was chosen where")
    v = r.get("validation") or {}
    doc.p(f"Every choice below was made on the validation frames ({v.get('frames')} frames of {v.get('sequences')} "
          f"sequences: {v.get('what', '')}); none reads a test frame (`study.experiments.selection` refuses it). Gate epochs and "
          "objectives: see the learned-gates table. Fixed in advance, not chosen: the fusion thresholds "
          "(`fusion.late`), L_f's weights (`fusion.eco.loss.FusedLossSpec`, EcoFusion 3.3; `eco-data` reports "
          "their rank correlation with AP on the validation frames), k, lambda_E and gamma (the papers').")
    doc.table(f"Choices made on validation frames ({tag})", ["what", "chosen", "measure", "candidates"],
              [[c["what"], c["chosen"], c["measure"],
                ", ".join(f"{k} {number_text(x)}" for k, x in (c.get("candidates") or {}).items())] for c in ch])


def add_severity(doc: Doc, r: dict, tag: str, work: Path) -> None:
    """mAP against severity per condition beside the clear twins; the figure is written in `work`."""
    doc.h(2, "mAP against severity per condition")
    doc.p("Vehicle mAP@0.5 of the test frames of each condition at each severity; beside it the same frames' "
          "clear-weather twins (everything but the condition held: the difference is the weather alone). "
          + ("Gated methods choose per frame from the degraded frame, so they have no twin column."
             if r.get("severity_clear_twins") else "This dataset has no twins."))
    for cond, per in r["severity"].items():
        sevs = sorted({s for v in per.values() for s in v}, key=int)
        rows = [[name, *[f"{number_text(v.get(s, {}).get('degraded'))} / {number_text(v.get(s, {}).get('clear'))}" for s in sevs]]
                for name, v in per.items()]
        frames = {s: next((v[s]["frames"] for v in per.values() if s in v), 0) for s in sevs}
        doc.table(f"{cond}: vehicle mAP degraded / clear twin per severity ({tag})", ["method",
                  *[f"sev {s} ({frames[s]} fr)" for s in sevs]], rows)
    if _severity_figure(r, work / "severity.png"):
        doc.img(f"mAP against severity per condition ({tag})", work / "severity.png")


def add_range_bins(doc: Doc, r: dict, tag: str) -> None:
    """Vehicle mAP per range bin per context, per method."""
    doc.h(2, "mAP per range bin per context")
    for name, per in r["range_per_context"].items():
        bins = sorted({b for v in per.values() for b in v}, key=lambda b: float(b.split("-")[0]))
        doc.table(f"{name}: vehicle mAP@0.5 per range bin [m] per context ({tag})", ["context", *bins],
                  [[c, *[v.get(b) for b in bins]] for c, v in per.items()])


def add_gate_regret(doc: Doc, r: dict, tag: str) -> None:
    """Each gate against its oracle, per context."""
    doc.h(2, "Gate regret against the oracle, per context")
    doc.p(f"HydraFusion: each gate's top-{r['k']} against Optimal gating (the k lowest a-posteriori branch losses); "
          f"EcoFusion at lambda_E {r['lambda_e']:g}: each gate against Loss-based (the a-posteriori L_f). regret = "
          "oracle minus gate (mAP; for L_f gate minus oracle): positive = the gate loses that much; differs = "
          "percent of frames where the gate's choice is not the oracle's; the regret's 95 % interval comes from the "
          "same draws of test sequences as every other interval." +
          (" Both oracles are a-posteriori oracles (they use the frame's own ground truth, not achievable); "
           "HydraFusion's optimal gate ranks by losses not comparable between branches (see the appendix)."
           if r.get("bounds") else ""))
    for fam, per in r["regret"].items():
        for g, rows_ in per.items():
            cols = list(rows_)
            rows = [["mAP", *[rows_[c]["map"] for c in cols]], ["oracle mAP", *[rows_[c]["map_oracle"] for c in cols]],
                    ["regret (mAP)", *[rows_[c]["regret_map"] for c in cols]]]
            if any("regret_interval" in rows_[c] for c in cols):
                rows.append(["regret: 95 % interval",
                             *[interval_text(rows_[c].get("regret_interval"), signed=True) for c in cols]])
            if fam != "hydrafusion":
                rows.append(["regret (L_f)", *[rows_[c]["regret_loss"] for c in cols]])
            rows.append(["differs [%]", *[rows_[c]["differs_pct"] for c in cols]])
            k = next(iter(rows_.values())).get("k")
            at = f", top {min(k, len(r['branches']))} (evaluate.k)" if k and fam == "hydrafusion" else ""
            doc.table(f"{fam} {g} gate against the oracle{at} ({tag})", ["", *cols], rows)


def add_fusion_regret(doc: Doc, r: dict, tag: str) -> None:
    """Each sensor's fusion regret: late fusion with it against without it, per context."""
    doc.h(2, "Each sensor's fusion regret")
    doc.p("Late fusion of the single-sensor branches with the sensor against without it, per context: regret = "
          "mAP without minus mAP with (positive: fusing the sensor costs that much there); L_f regret = mean fused "
          "loss with minus without.")
    fr = r["fusion_regret"]
    if fr:
        cols = list(next(iter(fr.values()))["per_context"])
        doc.table(f"mAP regret of fusing each sensor, per context ({tag})", ["sensor", *cols, "hurts in"],
                  [[b, *[v["per_context"][c]["regret_map"] for c in cols],
                    ", ".join(f"{c} ({number_text(x)})" for c, x in v["hurts_in"].items()) or "nowhere"] for b, v in fr.items()])
        doc.table(f"L_f regret of fusing each sensor, per context ({tag})", ["sensor", *cols],
                  [[b, *[v["per_context"][c]["regret_loss"] for c in cols]] for b, v in fr.items()])


def add_gate_picks(doc: Doc, r: dict, tag: str) -> None:
    """What each gate picks per context."""
    doc.h(2, "What each gate picks per context")
    for fam, per in r["picks"].items():
        for g, by in per.items():
            doc.table(f"{fam} {g}: most chosen branch sets [% of the context's test frames] ({tag})",
                      ["context", "choices"],
                      [[c, "; ".join(f"{k} {number_text(v)}" for k, v in d.items())] for c, d in by.items()])


def write_report(results: dict, context: dict, work: Path, eval_dir: Path, rel_to: Path | None = None) -> dict:
    """Write report.md, report.html and report.json into `work`; returns the report JSON. The
    Markdown's image links are relative to `rel_to` (where report.md is copied; default `work`)."""
    work, eval_dir = Path(work), Path(eval_dir)
    doc, summary = build(results, context, work, eval_dir)
    report = {**summary, "report_version": REPORT_VERSION, "config": context.get("config"),
              "stages": {n: {"key": s.get("key"), "seconds": s.get("seconds"),
                             "compute": s.get("compute")} for n, s in context.get("stages", {}).items()},
              "results": results}
    for name, text in (("report.md", doc.markdown(Path(rel_to or work))), ("report.html", doc.html(f"hydrabench study ({summary['scale']})")),
                       ("report.json", json.dumps(report, indent=1, default=str))):
        write_text_atomic(work / name, text)
    return report
