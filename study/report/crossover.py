"""The report's sections on issue 37: the crossover severity of each sensor (`study.experiments.crossover`)
and the physical knowledge gate built from it (`study.experiments.physical_gate`)."""

from __future__ import annotations

from pathlib import Path

from study.numbers import interval_text, number_text


def _signed(v) -> str:
    return "-" if v is None else f"{v:+.3f}"


def add_crossover(doc, r: dict, tag: str, work: Path) -> dict | None:
    """Tables of every crossover and the figure; returns the summary rows for report.json (None
    when the study has no crossover stage)."""
    rec = r.get("crossover")
    if not rec:
        return None
    from study.experiments.crossover import BASE_LABEL, crossing_text, plot_crossovers, summary_rows

    doc.h(2, "When fusing a sensor stops paying: the crossover severity")
    hw = rec["half_width"]
    doc.p(f"On a sweep set of its own (seeds {', '.join(str(v) for v in rec['level_seeds'].values())}, never the test "
          f"set): {rec['frames_per_step']} frames per condition and severity level, in sequences of "
          f"{rec['sequence_length']}, each with its clear twin. At each level, each base fusion is scored with and "
          f"without each sensor (fused by {rec['fusion']}, all-class mAP@0.5), and the difference is drawn "
          f"{rec['resamples']} times by whole sequences of that level. The crossover is where the difference goes "
          "below zero: the mildest level whose interval lies wholly below zero (resolved), and the zero crossing "
          "of the estimate, interpolated on the quantity's axis, with the percentile interval of the draws' own "
          "crossings ('open' where more than 2.5 % of the draws never cross, or already cross at the mildest "
          "level). The axis is what a car measures: visibility, rain and snow rate, illuminance. "
          f"Per-level intervals are {number_text(hw['median'])} wide on each side at the median "
          f"(largest {number_text(hw['max'])}): a sensor's worth smaller than that is not resolved at one level.")
    rows = summary_rows(rec)
    for base in ("late", "all_branches"):
        doc.table(f"Crossover per sensor and condition, {BASE_LABEL[base]}: the zero crossing [95 % interval], the "
                  f"mildest level resolved below 0, with minus without on the clear twins ({tag})",
                  ["condition", "sensor", "crossing", "resolved below 0 from", "clear twins: with - without"],
                  [[x["condition"], x["sensor"], crossing_text(x),
                    "-" if x["first_resolved_below"] is None else f"{x['first_resolved_below']:.3g} {x['unit']}",
                    f"{_signed(x['clear']['estimate'])} {interval_text(x['clear']['interval'], signed=True)}"]
                   for x in rows if x["base"] == base])
    for cond, c in rec["conditions"].items():
        doc.table(f"{cond}: with minus without each sensor per level ({c['quantity']} in {c['unit']}, median of the "
                  f"level's frames), estimate [95 % interval] ({tag})",
                  ["base", "sensor", *[f"{s['x']:.3g} ({s['frames']} fr)" for s in c["steps"]]],
                  [[base, sensor, *[f"{_signed(e)} {interval_text(iv, signed=True)}"
                                    for e, iv in zip(cur["estimate"], cur["interval"])]]
                   for base, per in c["curves"].items() for sensor, cur in per.items()])
    paths = plot_crossovers(rec, work, f"{rec['machine']['cpu']}, {rec['machine']['cores']} cores")
    doc.img(f"With minus without each sensor against the physical severity ({tag})", paths[0])
    return {"rows": rows, "half_width": hw, "frames_per_step": rec["frames_per_step"]}


def add_physical_gate(doc, r: dict, tag: str) -> dict | None:
    """The physical knowledge gate's rules and its comparison on the test frames."""
    pg = r.get("physical_gate")
    if not pg:
        return None
    doc.h(2, "A knowledge gate from the measured crossovers")
    rules = "; ".join(x["text"] for x in pg["rules"]) or ("no rule: no all-branches curve goes below zero"
                                                           if not pg["candidates"] else
                                                           "no rule: none beat running every branch on validation")
    doc.p("Rules: one per sensor and condition whose all-branches curve goes below zero on the sweep set; each "
          "threshold chosen among that crossover's readings (the rule off, the crossing, the mildest level resolved "
          "below zero, the crossing interval's ends) by the gate's mAP on the gate set's "
          f"{pg['chosen_on']['frames']} validation frames ({pg['chosen_on']['sequences']} sequences), one rule at a "
          "time. The gate reads only the weather a car measures (" + ", ".join(pg["reads"]) + f"). Chosen: {rules}. "
          "Beside it: HydraFusion's hand-written knowledge gate, the learned gates, late fusion, all branches and "
          "the context oracle (chosen on test: a bound). Regret: the context oracle's margin over the method.")
    comp = pg["comparison"]
    doc.table(f"The physical knowledge gate and the others on the test frames, all-class mAP@0.5 ({tag})",
              ["method", "mAP", "minus late", "95 % interval", "regret vs context oracle", "95 % interval",
               "energy", "branches"],
              [[name, number_text(v["map"]), _signed(v["minus_late"]),
                interval_text(v["minus_late_interval"], signed=True),
                _signed(v["regret_vs_context_oracle"]), interval_text(v["regret_interval"], signed=True),
                number_text(v["energy"]), number_text(v["branches"])] for name, v in comp.items()])
    me = comp.get("physical_gate", {})
    extra = [f"minus {o}: {_signed(me.get(f'minus_{o}'))} "
             f"{interval_text(me.get(f'minus_{o}_interval'), signed=True)}"
             for o in ("hydrafusion:knowledge", "all_branches") if f"minus_{o}" in me]
    if extra:
        doc.p("The physical gate " + "; ".join(extra) + ".")
    share = pg["selection_share_per_context"]
    doc.table(f"What the physical gate runs, share of test frames per context ({tag})", ["context", "branch sets"],
              [[ctx, ", ".join(f"{k} {100 * v:.0f} %" for k, v in per.items())] for ctx, per in share.items()])
    return {"rules": pg["rules"], "comparison": comp}


def add_transitions(doc, r: dict, tag: str, work: Path) -> dict | None:
    """The learned gates with memory on weather that changes (`study.experiments.transitions`)."""
    tx = r.get("transitions")
    if not tx:
        return None
    import shutil

    doc.h(2, "Weather that changes: gates with memory")
    doc.p(f"A transition set of its own: {tx['sequences']['test']} test and {tx['sequences']['validation']} validation "
          f"sequences of {tx['sequence_seconds']:g} s at {tx['frame_rate_hz']:g} Hz whose weather ramps "
          f"({', '.join(tx['kinds'])}) in {', '.join(tx['conditions'])}, to severity {tx['severities']}. Cost of a "
          f"branch on a frame: {tx['cost']}; regret: the chosen branch's cost minus the frame's best. Transition "
          f"windows: frames within {tx['radius']} of a change of the best branch. Each gate's hysteresis margin and "
          "EMA weight are chosen on the validation sequences (mean regret); intervals redraw the test sequences, "
          "paired with the per-frame gate. Clock gating (EcoFusion 5.5.2): a sensor no chosen branch reads is "
          f"switched off and woken one measurement period before it gives data again ("
          + ", ".join(f"{k} {v} frame(s)" for k, v in tx["wake_frames"].items() if k in ("camera_right", "lidar", "radar"))
          + "). The best constant is the "
          f"branch of lowest mean cost on validation ({tx['best_constant']}); the a-posteriori oracle reads the "
          "frame's ground truth (not achievable; its switches are shown for scale).")
    rc = tx["gates"].get("recurrent")
    if rc:
        tr = rc["training"]
        doc.p(f"The recurrent gate (item 3 (c)): a GRU of {tr['parameters']} parameters over each frame's stem channel "
              f"means, trained on the gate set's {tr['fit_sequences']} fitting sequences of "
              f"{', '.join(str(n) for n in tr['sequence_frames'])} frames, epoch {tr['best_epoch']} kept "
              + (f"on its {tr['val_sequences']} validation sequences (top-1 regret {tr['val_regret']:.4f})"
                 if tr.get("val_regret") is not None else "(the last: the gate set has no validation sequences)")
              + "; on a transition sequence it runs over "
              + ("the whole sequence" if not rc["window"] else f"the last {rc['window']} frames")
              + " (chosen on the validation part among "
              + ", ".join(("whole" if w == "0" else w) for w in rc["window_trace"]) + "). Its \"per-frame\" row is "
              f"the same network over one frame (no memory); its own step takes {rc['step_ms']:.3f} ms.")
    en = tx.get("energy")
    if en:
        doc.p(f"Energy per frame: compute ({en['scale']} scale) = {en['compute']}; sensors = {en['sensors']}. A "
              "learned gate reads every stem, so every sensor keeps measuring whatever it chooses; the clock-gated "
              "column is what its choices alone would draw.")
    for g, rec in tx["gates"].items():
        rows = []
        for v, s in rec["variants"].items():
            rows.append([v, number_text(s["regret"]), interval_text(s["regret_interval"]),
                         number_text(s["regret_transitions"]),
                         _signed(s.get("regret_minus_per-frame")), interval_text(s.get("regret_minus_per-frame_interval"), signed=True),
                         _signed(s.get("regret_transitions_minus_per-frame")),
                         interval_text(s.get("regret_transitions_minus_per-frame_interval"), signed=True),
                         number_text(s["lag_mean_frames"]), number_text(s["lag_censored_share"]),
                         number_text(s["switches_per_minute"]), number_text(s["wakes_per_minute"]),
                         s["frames_waiting_for_a_sensor"], number_text(s.get("energy_compute")),
                         number_text(s.get("energy_sensors_j")),
                         number_text(s.get("energy_sensors_clock_gated_by_choice_j"))])
        chosen = (("the whole sequence" if not rec["window"] else f"window {rec['window']}") if g == "recurrent"
                  else f"margin {rec['margin']:g}, alpha {rec['alpha']:g}")
        doc.table(f"{g} over the test sequences: regret, lag, switches and energy per variant ({chosen}, chosen on "
                  f"validation) ({tag})",
                  ["variant", "regret", "95 %", "regret in transitions", "minus per-frame", "95 %",
                   "in transitions minus per-frame", "95 %", "lag [frames]", "lag censored", "switches / min",
                   "wake-ups / min", "frames waiting", "compute energy", "sensors [J]", "sensors clock-gated [J]"],
                  rows)
        if g == "recurrent":
            x = next(s for v, s in rec["variants"].items() if v.startswith("recurrent ("))
            if x.get("regret_minus_deep_interval"):
                doc.p(f"The recurrent gate minus the deep gate per frame: regret {_signed(x['regret_minus_deep'])} "
                      f"{interval_text(x['regret_minus_deep_interval'], signed=True)}, in transitions "
                      f"{_signed(x.get('regret_transitions_minus_deep'))} "
                      f"{interval_text(x.get('regret_transitions_minus_deep_interval'), signed=True)} ({tag}).")
    src = Path(tx.get("figures_dir", ""))
    for f in tx.get("figures", []):
        if (src / f).is_file():
            shutil.copyfile(src / f, work / f)
            doc.img(f"One test sequence: the weather and each variant's branch per frame ({tag})", work / f)
    return {g: rec["variants"] for g, rec in tx["gates"].items()}
