"""The report's section on the `pem:` stage (issue 49 item 3, `study.experiments.pem_section`): the verdict
as curves over detector strength, with intervals, the figure, the seconds per point, and whether the
curve at strength 1 agrees with the networks' own verdict (computed here from both records)."""

from __future__ import annotations

import shutil
from pathlib import Path

from study.numbers import interval_text, number_text


def _cell(d) -> str:
    """A comparison as "value [95 % interval] verdict" ("-" where it has no value)."""
    if not d or d.get("value") is None:
        return "-"
    return f"{d['value']:+.3f} {interval_text(d.get('ci95'), signed=True)} {d.get('verdict', '')}".rstrip()


def _overlap(a, b) -> bool:
    return a[0] <= b[1] and b[0] <= a[1]


def strength_one(r: dict, pem: dict) -> dict:
    """all_branches minus late of the networks (the evaluation's own mAPs and paired interval) and of the
    PEM at strength 1, their verdicts, and whether they agree (the same verdict: above, below or not
    resolved) -> a record with the sentence that says so."""
    from study.engine.scoring import difference_interval
    from study.experiments.compare import verdict

    m = r.get("methods", {})
    net_value = None
    if (m.get("all_branches") or {}).get("map") is not None and (m.get("late") or {}).get("map") is not None:
        net_value = round(m["all_branches"]["map"] - m["late"]["map"], 4)
    group = ((r.get("intervals") or {}).get("per_context") or {}).get("all")
    net_iv = difference_interval(group, "all_branches", "late") if group else None
    net = {"value": net_value, "ci95": net_iv, "verdict": verdict(net_iv)}
    point = next((p for p in pem["points"] if p["strength"] == 1.0), None)
    out = {"networks": net, "pem": None, "agree": None}
    if point is None:
        out["sentence"] = ("Strength 1 (the fitted PEM) is not among the strengths swept, so the curve cannot be set "
                           "beside the networks' verdict.")
        return out
    mine = point.get("all_branches_minus_late") or {}
    out["pem"] = mine
    if net_value is None or net_iv is None or mine.get("value") is None or not mine.get("ci95"):
        out["sentence"] = ("Does the curve at strength 1 agree with the networks' verdict? Not decided: "
                           + ("the evaluation has no interval of all_branches minus late (evaluate.bootstrap 0)"
                              if net_iv is None else "the PEM's all_branches minus late has no interval") + ".")
        return out
    out["agree"] = net["verdict"] == mine["verdict"]
    out["intervals_overlap"] = _overlap(net_iv, mine["ci95"])
    out["sentence"] = (
        f"Does the curve at strength 1 agree with the networks' verdict? "
        f"{'Yes' if out['agree'] else 'No'}: all_branches minus late is {_cell(net)} for the networks (the "
        f"evaluation, fused by {r.get('fusion')}) and {_cell(mine)} for the PEM at strength 1 (fused by "
        f"{pem.get('fusion')}), on the same test frames; their verdicts {'agree' if out['agree'] else 'differ'}, "
        f"and their intervals {'overlap' if out['intervals_overlap'] else 'do not overlap'}."
        + (f" Here {mine['note']}." if mine.get("note") else ""))
    return out


def add_pem(doc, r: dict, tag: str, work: Path) -> dict | None:
    """The curves' table (comparison x strength), the points' mAPs and seconds, the figure, what the gate
    frames chose and the sentence on strength 1; returns the summary for report.json (None without a
    pem stage)."""
    pem = r.get("pem")
    if not pem:
        return None
    from study.experiments.pem_sweep import COMPARISONS, WHAT

    fit, gf = pem["fit"], pem.get("gate_frames") or {}
    pts = pem["points"]
    gate = "set" if "gate" in ((r.get("dataset") or {}).get("sets") or {}) else "split"
    doc.h(2, "The verdict over detector strength: a perception error model")
    doc.p(f"A perception error model per branch (`fusion.pem`, docs/pem.md) fitted on the study's detectors' "
          f"predictions on {fit['frames']} frames: the fitting sequences of the gate {gate}, never a test "
          f"or validation frame. At each strength s (the odds of detection times s, box error and false-alarm "
          f"rates divided by s; 1 is the fitted model) it is drawn on the test frames (draws seed {pem['seed']}) "
          f"and on {gf.get('on', 'the gate frames')} (seed {pem['gate_seed']}, {gf.get('val') or gf.get('fit')} "
          f"frames), where the per-context constant (per context, the constant branch set of best mAP there) and "
          f"the physical gate (thresholds among the values seen on the fitting frames) are chosen. Fusion {pem['fusion']}, the knowledge gate's top {pem['k']}, {pem['resamples']} draws of whole "
          f"test sequences for each 95 % interval. Room for context: {WHAT['room_for_context']}.")
    doc.table(f"The verdict over strength: difference in all-class mAP@0.5 [95 % interval] verdict ({tag})",
              ["comparison", *[f"s = {p['strength']:g}" for p in pts]],
              [[title, *[_cell(p.get(key)) for p in pts]] for key, title in COMPARISONS.items()])
    doc.table(f"Each point's mAP and seconds (draw, compare, the constants) on {pem['machine'].get('cpu', '?')}, "
              f"{pem['machine'].get('threads', '?')} thread(s) ({tag})",
              ["strength", "late", "all_branches", "per-context constant", "physical gate", "seconds"],
              [[f"{p['strength']:g}", *[number_text(p["maps"].get(n)) for n in
                                        ("late", "all_branches", "context_constant", "physical_gate")],
                number_text(p["seconds"])] for p in pts])
    skipped = {p["room_for_context"]["skipped"] for p in pts if (p.get("room_for_context") or {}).get("skipped")}
    if skipped:
        doc.p("Room for context is not estimated: " + "; ".join(sorted(skipped)) + ".")
    chosen = []
    for p in pts:
        cc, pg = p.get("context_constant"), p.get("physical_gate")
        if cc:
            chosen.append(f"s = {p['strength']:g}: per-context constant "
                          + ", ".join(f"{c} -> {n}" for c, n in cc["choice"].items())
                          + "; physical gate " + ("; ".join(x["text"] for x in pg["rules"]) or "no rule"))
    if chosen:
        doc.p("Chosen on the gate frames: " + ". ".join(chosen) + ".")
    one = strength_one(r, pem)
    doc.p(one["sentence"])
    src = Path(pem.get("figures_dir", "")) / pem["figure"]
    if src.is_file():
        shutil.copyfile(src, work / pem["figure"])
        doc.img(f"The verdict over detector strength: each comparison minus its reference with its 95 % interval "
                f"({tag})", work / pem["figure"])
    return {"strength_one": one, "seconds_per_point": pem["seconds_per_point"], "fit_frames": fit["frames"]}
