"""The physical knowledge gate in the study (issue 37 item 2): its rules from the crossover stage's
measured crossovers (`study.experiments.crossover`, on the sweep set), its thresholds chosen on the gate
set's validation frames, its choice on the test frames scored like every other method.

- Which rules: one per (sensor, condition) whose all-branches with-minus-without curve goes below
  zero on the sweep set (a crossing, or a step resolved below zero). All branches is the base
  because the gate chooses which branches to run; late fusion's curves are shown beside, not used.
- Which threshold: among `fusion.physical_gate.threshold_candidates` of that crossover (the rule off,
  the crossing, the mildest step resolved below zero, the crossing interval's ends), by coordinate
  ascent on the mAP of the whole gate on the validation frames (`choose_thresholds`), every pick
  recorded in the study's `SelectionLog` (which refuses a test frame).
- What it reads: each frame's weather record, reduced to what a car measures
  (`fusion.physical_gate.weather_of`); never the context label, the severity or the labels.
"""

from __future__ import annotations

from collections.abc import Mapping

from fusion.physical_gate import (
    CAR_QUANTITY,
    choose_thresholds,
    physical_selection,
    threshold_candidates,
    weather_of,
)

NAME = "physical_gate"
WHAT = ("physical knowledge gate: drops a sensor when a measured quantity (visibility, rain or snow rate, "
        "illuminance) passes that sensor's crossover; thresholds chosen on validation")
BASE = "all_branches"


def mild_end(condition: str) -> float:
    """The mild end of the severity table's first level of `condition` (in the quantity's unit)."""
    from sim.weather import SEVERITY_TABLE

    lo, hi = SEVERITY_TABLE[condition]["levels"][0]
    return hi if CAR_QUANTITY[condition][1] == "lower" else lo


def candidates_of(crossover: Mapping) -> dict[tuple[str, str], list]:
    """{(sensor, condition): candidate thresholds} for every curve of `BASE` that goes below zero."""
    out = {}
    for cond, c in crossover["conditions"].items():
        for sensor, cur in c["curves"].get(BASE, {}).items():
            opts = threshold_candidates(cur, bounds=(mild_end(cond), cur["steps"][-1]))
            if len(opts) > 1:
                out[(sensor, cond)] = opts
    return out


def add_physical_gate(crossover: Mapping | None, selections: dict, kinds: dict, ev, val, method: str, log) -> dict | None:
    """With a crossover record: the physical gate's test selection added to `selections` (and its
    description to `kinds`) as `NAME`; returns its record (None without a record)."""
    if crossover is None:
        return None
    selections[NAME], record = physical_gate(crossover, ev, val, method, log)
    kinds[NAME] = WHAT
    return record


def physical_gate(crossover: Mapping, ev, val, method: str, log) -> tuple[list[tuple[str, ...]], dict]:
    """(the gate's selection on the test frames of `ev`, its record: rules, candidates, the
    validation trace, how often each sensor is dropped per context on test)."""
    branches = list(ev.ed.branches)
    sensors_of = ev.model.branch_sensors
    cands = candidates_of(crossover)
    val_weather = [weather_of(m) for m in val.metas]

    def score(rules) -> float:
        return val.score([physical_selection(w, branches, sensors_of, rules) for w in val_weather], method)["map"]

    rules, trace = choose_thresholds(cands, score)
    log.record("physical knowledge gate: each rule's threshold (coordinate ascent on the gate's mAP)",
               [r.text() for r in rules], val.indices, "mAP of the physical gate",
               candidates={f"{s} / {c}": opts for (s, c), opts in cands.items()}, sequences=val.sequences)
    selection = [physical_selection(weather_of(m), branches, sensors_of, rules) for m in ev.metas]
    contexts = [m["context"] for m in ev.metas]
    share: dict = {}
    for ctx in sorted(set(contexts)):
        rows = [sel for sel, c in zip(selection, contexts) if c == ctx]
        share[ctx] = {"+".join(b): round(sum(1 for s in rows if s == b) / len(rows), 4)
                      for b in sorted(set(rows), key=lambda b: (-len(b), b))}
    record = {"what": WHAT, "base": BASE, "rules": [r.as_dict() for r in rules],
              "candidates": {f"{s} / {c}": opts for (s, c), opts in cands.items()},
              "chosen_on": {"frames": len(val.indices), "sequences": val.sequences, "measure": "mAP (all classes)"},
              "validation_trace": trace, "selection_share_per_context": share,
              "reads": sorted(q for q, _, _ in CAR_QUANTITY.values())}
    return selection, record


COMPARED = ("late", "all_branches", "hydrafusion:knowledge", "hydrafusion:deep", "hydrafusion:attention",
            "ecofusion:attention", "context_oracle")


def comparison(record: Mapping) -> dict:
    """The physical gate beside the paper's knowledge gate, the learned gates, late fusion, all
    branches and the context oracle on the test frames: mAP, mAP minus late fusion and the context
    oracle's margin over it (the regret of a context-only choice), each with its paired interval
    from the study's sequence draws, and mean energy (the cost table's accounting, lambda_E scale)."""
    from study.engine.scoring import difference_interval

    groups = (record.get("intervals") or {}).get("per_context") or {}
    pg = groups.get("all")
    methods = record["methods"]
    costs = record["hydra_table4"]
    rows = {}
    for name in (NAME, *COMPARED):
        if name not in methods:
            continue
        m = methods[name]["map"]
        rows[name] = {
            "map": m, "map_interval": (pg or {}).get("map", {}).get(name),
            "minus_late": None if name == "late" else round(m - methods["late"]["map"], 6),
            "minus_late_interval": difference_interval(pg, name, "late") if pg and name != "late" else None,
            "regret_vs_context_oracle": (None if "context_oracle" not in methods or name == "context_oracle"
                                         else round(methods["context_oracle"]["map"] - m, 6)),
            "regret_interval": (difference_interval(pg, "context_oracle", name)
                                if pg and "context_oracle" in methods and name != "context_oracle" else None),
            "energy": costs.get(name, {}).get("energy"), "branches": costs.get(name, {}).get("branches")}
    if pg and NAME in methods:
        for other in ("hydrafusion:knowledge", "all_branches"):
            if other in methods:
                rows[NAME][f"minus_{other}_interval"] = difference_interval(pg, NAME, other)
                rows[NAME][f"minus_{other}"] = round(methods[NAME]["map"] - methods[other]["map"], 6)
    return rows
