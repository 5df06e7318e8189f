"""A known-answer world for the gates (issue 49, item 4): `hydrabench pem known-answer`.

A PEM drawn in `fusion.pem.known_answer_world`: in each context one single-sensor branch is drawn
strong (the camera in clear daylight, the lidar at night, the radar in fog, rain and snow) and every
other branch weak, so the best branch of each context is known before anything is scored. The world
is drawn on a gate set (split by sequence, alternately, into fitting and validation frames) and on a
test set (another seed of the draws); each gate picks one branch per test frame (k = 1), scored by
the one scoring path (`fuse_selection`, `score`, `context_bootstrap`) and against the answer:

- `answer`: the construction's branch per context; every other method is also scored minus it.
- `context_constant` (a learner): per context, the branch of best mAP on the validation frames.
- `measured_gate` (a learner): a gate of the gate protocol that reads what a car measures (its
  `GateFrame`: the road type and the weather readings, never the context label): one-vs-rest
  logistic regressions (`fusion.pem.fit_logistic`) on the standardised readings, fitted on the
  fitting frames to each frame's best branch (`study.experiments.pem_sweep.frame_utility`; a frame where branches tie is left out).
- `best_constant`: the one branch best on validation over every context. Blind to context, it must
  miss the rule wherever the answer is another branch: the check that this check can fail.
- `knowledge`: HydraFusion's Table 1 (`KnowledgeGate`), fixed by the paper and reading the context
  label: reported, not required to agree.
- `physical_gate`: the physical knowledge gate (`fusion.physical_gate`): a sensor is dropped where a
  weather quantity the car measures (visibility, rain or snow rate, illuminance) passes a threshold;
  every (sensor, condition) rule's threshold chosen among the values seen on the fitting frames and
  kept by validation mAP (`study.experiments.pem_sweep.physical_rules`, as `pem sweep` fits it). It
  runs the branches it keeps, fused. Its rules fire only under a condition, so in clear weather it
  keeps every branch: there the answer (the camera alone) is beyond what it can express. Where a
  condition holds (fog, rain, snow, night) the answer is one sensor the others' weakness leaves, and
  the gate recovers the rule when it runs that branch alone on at least `RECOVER` of those frames.
- `context_oracle`: per context the best branch on the test frames themselves, a bound: it checks
  the construction (it must be the answer).

A learner recovers the rule when it chooses the answer on at least `RECOVER` of the test frames of
every context. Nothing is chosen on the test frames but the oracle's bound.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from sim.errors import UserError

RECOVER = 0.9
LEARNERS = ("context_constant", "measured_gate")


def readings(view) -> list[float]:
    """What `measured_gate` reads from a `GateFrame`: the road type (one-hot) and the weather readings
    on log scales."""
    from sim.scenario import LAYOUT_NAMES

    w = view.weather
    return [*(float(view.road == r) for r in LAYOUT_NAMES), np.log10(max(w["visibility_m"], 1.0)),
            np.log1p(w["rain_mm_h"]), np.log1p(w["snow_mm_h"]), np.log10(1.0 + w["illuminance_lux"])]


class MeasuredGate:
    """A gate of the gate protocol (called with a `GateFrame`, returns one branch) fitted on frames'
    readings and each frame's best branch."""

    def __init__(self, branches, x: np.ndarray, best: list[str]):
        from fusion.pem import fit_logistic

        self.branches = list(branches)
        self.mean, self.sd = x.mean(axis=0), x.std(axis=0) + 1e-9
        z = (x - self.mean) / self.sd
        y = np.array(best)
        self.weights = {b: fit_logistic(z, (y == b).astype(float)) for b in self.branches if (y == b).any()}

    def __call__(self, view) -> str:
        z = (np.array(readings(view)) - self.mean) / self.sd
        logits = {b: w[0] + z @ w[1:] for b, w in self.weights.items()}
        return max(logits, key=logits.get)


def _value(m) -> float:
    """An mAP to rank by: an undefined one (no box to find) below every defined one."""
    return -1.0 if m is None else float(m)


def fit_physical_gate(gp, fit_pos, val_pos, gate_reader, tp, method, protocol, branches, sensors) -> tuple[list, dict]:
    """The physical gate fitted on the gate set's predictions `gp` (thresholds from its fitting frames,
    chosen on its validation frames' mAP over every branch set) -> (its selection on each test frame of
    `tp`, its record)."""
    from fusion.physical_gate import physical_selection, weather_of
    from study.experiments.pem_sweep import Constants, constants_of, physical_rules

    val = Constants([gp.per_frame[p] for p in val_pos], constants_of(branches, sensors), gp.branch_frames, method,
                    gate_reader, protocol)
    rules, record = physical_rules(val, [gp.per_frame[p][0] for p in fit_pos], branches, sensors)
    return [tuple(physical_selection(weather_of(m), branches, sensors, rules)) for m, _ in tp.per_frame], record


def physical_row(selection, tp, answer, scored, boot) -> dict:
    """The physical gate's row: per context the share of test frames on which it runs the answer alone
    (`agreement`) and on which it runs the answer among others (`keeps_answer`); it recovers the rule
    when it runs the answer alone on `RECOVER` of the frames of every context with a condition."""
    from study.engine.scoring import difference_interval

    ctx_of = [meta["context"] for meta, _ in tp.per_frame]
    conditioned = {meta["context"] for meta, _ in tp.per_frame if meta.get("conditions")}

    def share(test) -> dict:
        return {c: round(float(np.mean([test(sel, c) for sel, cc in zip(selection, ctx_of) if cc == c])), 4)
                for c in answer}

    agree = share(lambda sel, c: tuple(sel) == (answer[c],))
    row = {"map": scored["physical_gate"]["map"], "map_per_context": scored["physical_gate"]["map_per_context"],
           "agreement": agree, "agreement_all": round(float(np.mean([tuple(s) == (answer[c],) for s, c in
                                                                     zip(selection, ctx_of)])), 4),
           "keeps_answer": share(lambda sel, c: answer[c] in sel),
           "recovers_the_rule": bool(conditioned) and all(agree[c] >= RECOVER for c in conditioned),
           "expressible_contexts": sorted(conditioned)}
    if boot:
        row["minus_answer_ci95"] = difference_interval(boot["per_context"]["all"], "physical_gate", "answer")
    return row


def run(pem_path, gate_data, test_data, work, *, strong: float = 8.0, weak: float = 0.125, seed: int = 0,
        resamples: int = 500, fusion: str = "soft-nms") -> dict:
    """The known-answer check (module docstring) -> a JSON-able dict; predictions in `work`/gate, /test."""
    from fusion.pem import known_answer_world
    from sensors.dataset import DatasetReader
    from study.engine.predictions import load
    from study.engine.scoring import (
        context_bootstrap,
        difference_interval,
        frame_ground_truth,
        fuse_selection,
        fusion_method,
        score,
    )
    from study.experiments.gate_protocol import gate_frame
    from study.experiments.pem import load_pem, predict_pem
    from study.experiments.pem_sweep import frame_utility, split_by_sequence

    t0 = time.perf_counter()
    doc = load_pem(pem_path)
    sensors = {b: tuple(s) for b, s in doc["branch_sensors"].items()}
    branches = list(doc["branches"])
    readers = {"gate": DatasetReader(gate_data), "test": DatasetReader(test_data)}
    contexts = sorted({r.meta(i)["context"] for r in readers.values() for i in range(len(r))})
    try:
        world, answer = known_answer_world(sensors, contexts, strong, weak)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    split_by_sequence([(readers["gate"].meta(i), None) for i in range(len(readers["gate"]))])  # refused before drawing
    work = Path(work)
    for part, data, s in (("gate", gate_data, seed), ("test", test_data, seed + 1)):
        predict_pem(pem_path, data, work / part, seed=s, world=world)
    gp, tp = load(work / "gate"), load(work / "test")
    method, protocol = fusion_method(fusion), doc["protocol"]
    frames = tp.branch_frames

    def per_context(per_frame, reader, branch):
        sel = [(branch,)] * len(per_frame)
        return score(fuse_selection(per_frame, sel, frames, method), reader, "camera_right", protocol=protocol)

    fit_pos, val_pos = split_by_sequence(gp.per_frame)
    val = [gp.per_frame[p] for p in val_pos]
    val_scores = {b: per_context(val, readers["gate"], b) for b in branches}
    best_constant = max(branches, key=lambda b: _value(val_scores[b]["map"]))
    context_constant = {c: max(branches, key=lambda b: _value(val_scores[b]["map_per_context"].get(c)))
                        for c in contexts}
    x, best = [], []
    for p in fit_pos:
        meta, per = gp.per_frame[p]
        gt = frame_ground_truth(readers["gate"], meta, "camera_right", None, protocol)
        u = {b: frame_utility(per[b], gt) for b in branches}
        top = max(u.values())
        if sum(v == top for v in u.values()) > 1:
            continue  # no one best branch (a frame with nothing found): it teaches the gate nothing
        x.append(readings(gate_frame(meta, per, sensors)))
        best.append(max(branches, key=u.get))
    gate = MeasuredGate(branches, np.array(x), best)
    physical, physical_record = fit_physical_gate(gp, fit_pos, val_pos, readers["gate"], tp, method, protocol,
                                                  branches, sensors)
    test_scores = {b: per_context(tp.per_frame, readers["test"], b) for b in branches}
    oracle = {c: max(branches, key=lambda b: _value(test_scores[b]["map_per_context"].get(c))) for c in contexts}
    ctx_of = [meta["context"] for meta, _ in tp.per_frame]
    picks = {
        "answer": [answer[c] for c in ctx_of],
        "context_constant": [context_constant[c] for c in ctx_of],
        "measured_gate": [gate(gate_frame(meta, per, sensors)) for meta, per in tp.per_frame],
        "best_constant": [best_constant] * len(ctx_of),
        "knowledge": [s[0] for s in tp.selection("knowledge", 1)],
        "context_oracle": [oracle[c] for c in ctx_of],
    }
    memo: dict = {}
    sources = {n: fuse_selection(tp.per_frame, [(b,) for b in p], frames, method, memo=memo) for n, p in picks.items()}
    sources["physical_gate"] = fuse_selection(tp.per_frame, physical, frames, method, memo=memo)
    scored = {n: score(s, readers["test"], "camera_right", protocol=protocol) for n, s in sources.items()}
    boot = (context_bootstrap(sources, readers["test"], "camera_right", protocol=protocol, resamples=resamples,
                              classes="all", desc="bootstrap the gates") if resamples else None)
    methods = {}
    for n, p in picks.items():
        agree = {c: round(float(np.mean([b == answer[c] for b, cc in zip(p, ctx_of) if cc == c])), 4) for c in contexts}
        row = {"map": scored[n]["map"], "map_per_context": scored[n]["map_per_context"], "agreement": agree,
               "agreement_all": round(float(np.mean([b == answer[c] for b, c in zip(p, ctx_of)])), 4)}
        if boot and n != "answer":
            row["minus_answer_ci95"] = difference_interval(boot["per_context"]["all"], n, "answer")
        if n in LEARNERS or n == "best_constant":
            row["recovers_the_rule"] = all(a >= RECOVER for a in agree.values())
        methods[n] = row
    methods["physical_gate"] = physical_row(physical, tp, answer, scored, boot)
    return {
        "world": {"answer": answer, "strong": strong, "weak": weak, "strengths": world},
        "construction_holds": methods["context_oracle"]["agreement_all"] == 1.0,
        "methods": methods, "chosen_on_validation": {"context_constant": context_constant, "best_constant": best_constant},
        "frames": {"fit": len(fit_pos), "validation": len(val_pos), "test": len(tp.per_frame)},
        "measured_gate_targets": {b: best.count(b) for b in branches}, "physical_gate": physical_record,
        "recover": RECOVER, "fusion": fusion, "k": 1, "seed": seed, "bootstrap": resamples,
        "predictions": {"gate": str(work / "gate"), "test": str(work / "test")},
        "seconds": round(time.perf_counter() - t0, 1),
    }


def format_result(r: dict) -> str:
    w = r["world"]
    lines = [f"known answer (strong {w['strong']:g}, weak {w['weak']:g}): "
             + ", ".join(f"{c} -> {b}" for c, b in w["answer"].items()),
             f"construction: the test set's own per-context best is the answer in every context: "
             f"{'yes' if r['construction_holds'] else 'NO'}",
             f"{r['frames']['test']} test frames; agreement with the answer, mAP and minus the answer (95 % interval):"]
    for n, m in r["methods"].items():
        ci = m.get("minus_answer_ci95")
        iv = f"[{ci[0]:+.3f}, {ci[1]:+.3f}]" if ci else ""
        verdict = ("" if "recovers_the_rule" not in m else
                   "  recovers the rule" if m["recovers_the_rule"] else "  DOES NOT recover the rule")
        judged = m.get("expressible_contexts") or list(m["agreement"])
        worst = min(judged, key=m["agreement"].get)
        lines.append(f"  {n:17s} agrees {100 * m['agreement_all']:5.1f} % (least: {worst} {100 * m['agreement'][worst]:.0f} %)"
                     f"  mAP {m['map'] if m['map'] is not None else '-'} {iv}{verdict}")
        if "expressible_contexts" in m:
            lines.append(f"  {'':17s} (the answer alone; its rules fire only under a condition: judged on "
                         f"{', '.join(m['expressible_contexts'])}; in clear weather it runs every branch)")
    return "\n".join(lines)
