"""The report's sections on the study's bounds (`study.experiments.bounds`): room for context near the top, the
intervals' coverage over disjoint test sets, and the appendix that keeps HydraFusion's optimal gate
apart. Called by `study.report.build.build`; each section is absent from a report made before bounds were
recorded."""

from __future__ import annotations

from study.experiments.bounds import A_POSTERIORI_LABEL, CONTEXT_ORACLE_LABEL, label
from study.numbers import interval_text, number_text

APPENDIX = ("hydrafusion:optimal",)
"""Methods a report with bounds shows only in its appendix (`study.experiments.bounds.OPTIMAL_APPENDIX` says why)."""


def main_methods(r: dict) -> list[str]:
    """The methods of the report's main tables: all of them, less `APPENDIX` in a report with bounds."""
    return [m for m in r["methods"] if not (r.get("bounds") and m in APPENDIX)]


def named(r: dict, m: str) -> str:
    """A method's name in a table: labelled when it is a bound (`study.experiments.bounds.label`) in a report with bounds."""
    return label(m) if r.get("bounds") else m


def add_room(doc, r: dict, tag: str) -> None:
    """Room for context: the context oracle minus all branches, overall and per context, with the
    paired interval and p-value, what the oracle chose per context, and why its interval is optimistic."""
    b = r.get("bounds")
    if not b:
        return
    room, choice = b["room_for_context"], b["context_oracle"]["choice"]
    doc.h(2, "Room for context: what a gate reading only the context could add")
    doc.p(f"The {CONTEXT_ORACLE_LABEL}: per context, the constant branch set with the best mAP@0.5 on that "
          f"context's test frames, among {len(b['context_oracle']['candidates'])} fixed configurations (each single "
          "sensor, each EcoFusion configuration, late fusion, all branches). It is the bound of any gate that reads "
          f"only the context. Room for context = {b['room_what']}. {b['optimistic']} Not a room: the per-frame "
          f"oracles ({', '.join(b['a_posteriori'])}) are each an {A_POSTERIORI_LABEL}.")
    doc.table(f"Room for context, context oracle minus all_branches, mAP@0.5 ({tag})",
              ["group", "chosen constant", "room", "95 % interval", "p"],
              [[g, "per context" if g == "all" else choice.get(g, {}).get("candidate"), number_text(v["estimate"]),
                interval_text(v["interval"], signed=True), number_text(v["p_value"])] for g, v in room.items()])


def add_room_corrected(doc, r: dict, tag: str) -> None:
    """Room for context without its optimism (issue 50): the per-context constant chosen on validation (a
    method, with its paired interval against all branches), and the context oracle's room naive and
    split-sample, each beside its null of equal constants."""
    b = r.get("bounds") or {}
    rc, cc = b.get("room_corrected"), r.get("context_constant")
    if not rc and not cc:
        return
    doc.h(2, "Room for context, achievable and bounded")
    if cc:
        from study.engine.scoring import difference_interval

        group = ((r.get("intervals") or {}).get("per_context") or {}).get("all")
        methods = r.get("methods") or {}
        sc, every = methods.get("context_constant") or {}, methods.get("all_branches") or {}
        doc.p(f"The {cc['what']}. Its choice per context: "
              + ", ".join(f"{g}: {v['candidate']}" for g, v in cc["choice"].items() if g != "all")
              + f" (overall best on validation, for a context it lacks: {cc['choice']['all']['candidate']}).")
        if sc.get("map") is not None and every.get("map") is not None:
            doc.table(f"Per-context constant minus all_branches, mAP@0.5 ({tag})",
                      ["mAP", "minus all_branches", "95 % interval"],
                      [[number_text(sc["map"]), number_text(round(sc["map"] - every["map"], 6)),
                        interval_text(difference_interval(group, "context_constant", "all_branches") if group else None,
                                      signed=True)]])
    if rc:
        doc.p(rc["what"])
        doc.table(f"Room for context over all_branches, naive and split-sample, with their nulls, mAP@0.5 ({tag}; "
                  f"{rc['sequences']} test sequences, {rc['resamples']} draws, {rc['permutations']} permutations)",
                  ["estimate", "room", "95 % interval", "null mean", "null 95th percentile", "above its null"],
                  [[k, number_text(rc[k]["estimate"]), interval_text(rc[k]["interval"], signed=True),
                    number_text(rc[k]["null_mean"]), number_text(rc[k]["null_upper"]),
                    "yes" if rc[k]["above_null"] else "no"] if "skipped" not in rc[k] else
                   [k, rc[k]["skipped"], "", "", "", ""] for k in ("naive", "split")])


def add_coverage(doc, r: dict, tag: str) -> None:
    """Do the intervals hold? Each pair's coverage over disjoint test sets against what an exact
    interval would reach, and the spread of the sets' estimates over the bootstrap's standard error."""
    cov = (r.get("bounds") or {}).get("coverage")
    if not cov:
        return
    doc.h(2, "Do the intervals hold? Coverage over disjoint test sets")
    if cov.get("skipped"):
        doc.p(f"Coverage check {cov['skipped']}.")
        return
    design = cov.get("design", "stratified")  # a report made before the designs drew within each context
    drawn = {"sequence": "draws of whole sequences from all of the set's, as the reported intervals",
             "stratified": "draws within each context, n of n",
             "rescaled": "draws within each context, n - 1 of n (Rao and Wu)"}.get(design, design)
    doc.p(f"The test frames dealt by sequence within each context into {cov['sets']} disjoint sets "
          f"({', '.join(map(str, cov['sequences_per_set']))} sequences); each set's 95 % interval ({cov['resamples']} "
          f"{drawn}) is checked against the estimate of the other sets pooled. An exact interval "
          "holds it with the expected share, not 0.95 (the rest's estimate is noisy too; "
          "`fusion.intervals.expected_rest_coverage`); spread over se near 1 says the interval's width is right, well "
          "above 1 says it is too narrow. The context oracle here is its choice on all test frames, held fixed.")
    doc.table(f"Coverage of the paired intervals over {cov['sets']} disjoint test sets ({tag})",
              ["pair", "covered k/n", "expected if exact", "spread over se"],
              [[p, f"{v['covered']}/{v['sets']}", number_text(v["expected_if_exact"]), number_text(v["spread_over_se"])]
               for p, v in cov["pairs"].items()])


def add_optimal_appendix(doc, r: dict, tag: str) -> None:
    """Appendix: the methods kept out of the main tables (HydraFusion's optimal gate), with the reason
    and every number the main tables would have shown."""
    b = r.get("bounds")
    shown = [m for m in APPENDIX if b and m in r["methods"]]
    if not shown:
        return
    from study.engine.scoring import difference_interval

    ctxs = r["dataset"]["contexts"]
    per = (r.get("intervals") or {}).get("per_context") or {}
    doc.h(2, "Appendix: HydraFusion's optimal gate")
    doc.p(f"{b['optimal_appendix']} Its numbers, as the main tables would show them:")
    doc.table(f"mAP@0.5 per context ({tag})", ["method", "what", "all", *ctxs],
              [[label(m), r["methods"][m]["what"], r["methods"][m]["map"],
                *[r["methods"][m]["map_per_context"].get(c) for c in ctxs]] for m in shown])
    if per:
        groups = ["all", *[c for c in ctxs if c in per]]
        doc.table(f"95 % intervals: its mAP@0.5, and minus late fusion's ({tag})", ["", *groups],
                  [[f"{m} mAP", *[interval_text(per[g]["map"].get(m)) for g in groups]] for m in shown] +
                  [[f"{m} minus late", *[interval_text(difference_interval(per[g], m, "late"), signed=True)
                                         for g in groups]] for m in shown if "late" in r["methods"]])
    ks = sorted({k for v in r["hydra_table6"].get("optimal", {}).values() for k in v}, key=lambda k: (k == "all", k))
    if ks:
        doc.table(f"HydraFusion Table 6 row of the optimal gate: mAP@0.5 per fusion and k ({tag})",
                  ["fusion", *[f"k={k}" for k in ks]],
                  [[f, *[row.get(k) for k in ks]] for f, row in r["hydra_table6"]["optimal"].items()])


def add_learning_curve(doc, r: dict, tag: str) -> None:
    """Each learned HydraFusion gate's test regret as its fitting set grows (`study.experiments.regrets.learning_curve`),
    beside the best constant and the per-context constant fitted on the same frames, with the intervals
    of the differences over test sequences."""
    curves = r.get("learning_curve")
    if not curves:
        return
    doc.h(2, "Learning curve: gate regret against the constants as the gate set grows")
    doc.p("Each learned HydraFusion gate trained again on fewer whole sequences per context of its fitting frames "
          "(`gates.curve`), validated and tested on the same frames as the full gate. Regret: the mean per-branch "
          "loss of the gate's one choice per frame minus the oracle's; gate minus constant below 0 (interval "
          "excluding it) = the gate chooses better than the best constant fitted on the same frames.")

    def iv(x):
        return "-" if not x else f"{number_text(x['estimate'])} {interval_text(x['interval'], signed=True)}"

    rows = [[g, c["fit_frames"], c["objective"], number_text(c["regret"]), number_text(c["constant_regret"]),
             number_text(c["context_regret"]), iv(c.get("minus_constant")), iv(c.get("minus_context"))]
            for g, cs in curves.items() for c in cs]
    doc.table(f"Learning curve of the learned gates' test regret ({tag})",
              ["gate", "fitting frames", "objective kept", "regret", "best constant's", "per-context constant's",
               "gate minus constant", "gate minus per-context constant"], rows)


def add_energy_front(doc, r: dict, tag: str, work) -> dict | None:
    """The mAP-energy front of the fixed configurations with every gate placed on it
    (`study.experiments.energy_front`); returns the record for report.json (None without costs or intervals)."""
    from study.experiments.energy_front import energy_front, front_figure, front_sentence

    front = energy_front(r)
    if front is None:
        return None
    doc.h(2, "The mAP-energy front: where a gate is worth running")
    with_e = any(p.get("energy_ci95") for p in front["placed"].values())
    doc.p("A gate is worth running only where it lies above what a fixed configuration gives for the same "
          f"energy or less. Fixed configurations: {front['configurations']}; their front is the Pareto "
          "set of (energy, mAP). Each other method is compared, by the study's paired sequence bootstrap, with the "
          "most accurate fixed configuration that costs no more (against); time-sharing between two front "
          "configurations would reach the chord between them, given as a point value (not scored, no interval). "
          "Energy: mean per frame, charged as in Table 4. " +
          ("Its 95 % interval comes from the same draws of whole test sequences as the mAP's (a fixed "
           "configuration's energy is the same on every frame, so its interval is a point). " if with_e else
           "A gate's energy varies with its choices; this report's evaluation drew no interval for it. ")
          + front_sentence(front))
    doc.table(f"Each method against the front at its energy, mAP@0.5 ({tag})",
              ["method", "energy [lambda_E scale]", "energy 95 %", "mAP", "against (front)", "minus against",
               "95 % interval", "minus chord (point)", "verdict"],
              [[p["what"], p["energy"], interval_text(p.get("energy_ci95")), p["map"], p["against"] or "-",
                number_text(p["point"]),
                interval_text(p["minus_front"], signed=True), number_text(p["minus_chord"]), p["verdict"]]
               for p in front["placed"].values()])
    path = front_figure(front, work / "energy_front.png")
    doc.img(f"mAP@0.5 against energy: the fixed configurations' front and every method placed on it ({tag})", path)
    return front
