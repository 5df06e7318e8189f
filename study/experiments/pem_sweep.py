"""The verdict over detector strength (`hydrabench pem sweep`): at each strength s, a perception error
model (`fusion.pem`) drawn on the test set (`study.experiments.pem.predict_pem`, draws seed `seed`) and,
with a gate set, on the gate set (draws seed `seed` + 1: the two sets' frames never share a random
stream); then, on the test frames, each comparison's difference in mAP with its 95 % sequence-bootstrap
interval and verdict (above / below / not resolved):

- `all_branches_minus_late`, `knowledge_minus_all_branches`, `knowledge_minus_late`:
  `study.experiments.compare.compare` on the drawn predictions (the knowledge gate keeps the top k).
- `context_constant_minus_all_branches` (needs the gate set): per context, the constant branch set of
  best mAP on the gate set's validation frames (its sequences alternately fitting and validation:
  `split_by_sequence`), among the study's constants
  (`study.experiments.bounds.constant_configurations`: each single sensor, late fusion, all branches and
  every other subset of the branches), run on the test frames; a context the validation frames lack
  takes the best overall. The study's per-context constant, chosen the same way.
- `physical_gate_minus_all_branches` (needs the gate set): the physical gate (`fusion.physical_gate`:
  drop a sensor's branches when a quantity a car measures passes a threshold). The study takes each
  rule's candidate thresholds from a measured crossover (a sweep set with clear-weather twins), which a
  PEM draw does not give; here every (sensor, condition) rule's candidates are the quantity's values
  seen on the gate set's fitting frames of that condition (`fusion.physical_gate.observed_candidates`),
  and the thresholds are chosen on its validation frames by `choose_thresholds`, as in the study.
- `room_for_context`: the context oracle (per context, the best constant chosen on the test frames: a
  bound) minus all branches, corrected for that choice as the study's report does
  (`study.experiments.bounds.corrected_room`, `fusion.context_room`): the split-sample estimate and its
  interval (the value and verdict), its null beside it, and the naive estimate.
- `a_posteriori_oracle_minus_all_branches`: per test frame, the constant chosen to raise the test
  set's pooled mAP with every frame's ground truth read (`fusion.bounds.greedy_choice`, coordinate
  ascent from all branches): the bound of any gate choosing among the constants per frame (a local
  optimum, at least all branches), not achievable. A PEM has no Faster R-CNN losses, so neither oracle
  here is HydraFusion's optimal gate.
- `utility_oracle_minus_all_branches`: per test frame, the constant whose fused detections score best
  on that frame's own ground truth by `frame_utility` (scores of
  detections finding a true box minus those finding none; all branches where it ties for best). Also
  a-posteriori; a frame's utility is not its share of the pooled mAP (it counts every false alarm at
  its score, where AP counts only those ranked above true positives), so this one is no bound.

Nothing is chosen on the test frames but what reads their ground truth by design, each named for what
it is: the two a-posteriori oracles and the context oracle inside room for context.
"""

from __future__ import annotations

import time
from pathlib import Path

from sim.errors import UserError
from study.experiments.bounds import CONTEXT_CONSTANT
from study.numbers import interval_text, rounded

PHYSICAL_GATE = "physical_gate"
ORACLE = "a_posteriori_oracle"
UTILITY_ORACLE = "utility_oracle"
WHAT = {
    CONTEXT_CONSTANT: "per context, the constant branch set of best mAP on the gate set's validation frames",
    PHYSICAL_GATE: ("physical gate: drops a sensor when visibility, rain or snow rate or illuminance passes a "
                    "threshold; candidates seen on the gate set's fitting frames, chosen on its validation frames"),
    ORACLE: ("a-posteriori oracle: per frame, the constant chosen by coordinate ascent on the test set's pooled mAP, "
             "every frame's ground truth read: the bound of a per-frame choice among the constants, not achievable "
             "(a PEM has no losses: not HydraFusion's optimal gate)"),
    UTILITY_ORACLE: ("per frame, the constant whose fused detections score best on the frame's own ground truth "
                     "(scores of detections finding a true box minus those finding none): a-posteriori, not "
                     "achievable, and no bound of mAP"),
    "room_for_context": ("context oracle (best constant per context, chosen on the test frames) minus all branches, "
                         "split-sample (chosen on half the sequences, scored on the other) with its null"),
}
NO_GATE_SET = ("no --gate-set: the per-context constant and the physical gate are chosen on a gate set's validation "
               "frames, so they are not measured")
COMPARISONS = {
    "all_branches_minus_late": "all_branches - late",
    "knowledge_minus_all_branches": "knowledge gate - all_branches",
    "context_constant_minus_all_branches": "per-context constant - all_branches",
    "physical_gate_minus_all_branches": "physical gate - all_branches",
    "room_for_context": "room for context (split-sample)",
    "a_posteriori_oracle_minus_all_branches": "a-posteriori oracle - all_branches",
    "utility_oracle_minus_all_branches": "utility oracle - all_branches",
}
"""Each comparison of a point: its key and its title."""
PANELS = {"all_branches - late": ("all_branches_minus_late",),
          "knowledge gate - all_branches": ("knowledge_minus_all_branches",),
          "per-context constant - all_branches": ("context_constant_minus_all_branches",),
          "physical gate - all_branches": ("physical_gate_minus_all_branches",),
          "room for context (split-sample)": ("room_for_context",),
          "a-posteriori oracles - all_branches": ("a_posteriori_oracle_minus_all_branches",
                                                  "utility_oracle_minus_all_branches")}
"""The figure's panels: each one's title and the comparisons it draws."""
NEEDS_GATE_SET = ("context_constant_minus_all_branches", "physical_gate_minus_all_branches")


def constants_of(branches, sensors) -> dict[str, tuple[str, ...]]:
    """The study's constants for a network's branches: each single sensor, late fusion, all branches and
    every other non-empty subset of the branches ({name: branches})."""
    from fusion.eco.configurations import build_configurations
    from study.experiments.bounds import constant_configurations

    singles = [b for b in branches if len(sensors[b]) == 1]
    members = build_configurations({b: tuple(sensors[b]) for b in branches}).members
    return constant_configurations(branches, members, singles, singles)


def frame_utility(d, gt) -> float:
    """The scores of `d`'s detections that find a true box minus the scores of those that find none
    (IoU >= 0.5, greedy by score, difficult boxes left out): what a frame's AP rewards, per frame."""
    from fusion.pem import match

    m = match(d.boxes, d.scores, gt["boxes"][~gt["difficult"]])
    return float(d.scores[m >= 0].sum() - d.scores[m < 0].sum())


def split_by_sequence(per_frame: list, who: str = "the known-answer check") -> tuple[list, list]:
    """(fitting, validation) positions of `per_frame`: each context's sequences in order, alternately
    (UserError naming `who` when a context has one sequence)."""
    seqs: dict = {}
    for pos, (meta, _) in enumerate(per_frame):
        seqs.setdefault(meta["context"], {}).setdefault(meta["sequence_id"], []).append(pos)
    fit, val = [], []
    for ctx, by_seq in sorted(seqs.items()):
        if len(by_seq) < 2:
            raise UserError(f"the gate set has one sequence of {ctx}: {who} needs two per context "
                            "(one to fit on, one to choose on)")
        for j, sid in enumerate(sorted(by_seq)):
            (fit if j % 2 == 0 else val).extend(by_seq[sid])
    return sorted(fit), sorted(val)


class Constants:
    """Every constant (`constants`, {name: branches}) fused on every frame of `per_frame` by the one path
    (`study.engine.scoring.fuse_selection`) and matched to the frames' ground truth
    (`study.experiments.bounds.StudyMatches`), so that any per-frame choice among them is scored by
    composing their matchings."""

    def __init__(self, per_frame, constants, frames, method, reader, protocol) -> None:
        from study.engine.scoring import fuse_selection
        from study.experiments.bounds import StudyMatches

        memo: dict = {}  # each branch mapped to the right camera once per frame
        n = len(per_frame)
        self.constants, self.reader, self.protocol = dict(constants), reader, protocol
        self.fused = {c: fuse_selection(per_frame, [b] * n, frames, method, memo=memo) for c, b in constants.items()}
        self.sm = StudyMatches.of(self.fused, self.constants, {}, reader, protocol)
        self.metas = [m for m, _ in per_frame]
        self.name_of = {b: c for c, b in self.constants.items()}

    def frames_of(self, choice) -> list:
        """[(meta, Detections)]: each frame's fused detections of its constant `choice[i]`."""
        return [(m, self.fused[c][i][1]) for i, (m, c) in enumerate(zip(self.metas, choice, strict=True))]

    def map_of(self, choice) -> float:
        """The mAP (every class) of the per-frame choice `choice` (one constant's name per frame)."""
        from fusion.bounds import composite

        return composite(self.sm.matches, list(choice)).mean_ap(range(len(self.metas)))


def context_constant(val: Constants) -> dict[str, str]:
    """Per context of the validation frames `val`, the constant of best mAP there
    (`fusion.bounds.best_constant_per_stratum`; ties: the first in order), and under "all" the best
    overall (for a context they lack)."""
    from fusion.bounds import best_constant_per_stratum

    rows = list(range(len(val.metas)))
    out = dict(sorted(val.sm.context_choice(rows).items()))
    out["all"] = best_constant_per_stratum(val.sm.matches, list(val.constants), rows, ["all"] * len(rows))["all"]
    return out


def physical_rules(val: Constants, fit_metas, branches, sensors) -> tuple[list, dict]:
    """The physical gate's rules: for every sensor and condition, candidates seen on the fitting frames
    (`fusion.physical_gate.observed_candidates` of the quantity on the frames of that condition), each
    threshold chosen by coordinate ascent on the gate's mAP on the validation frames `val`
    (`choose_thresholds`). Returns (the rules that are on, their record)."""
    from fusion.physical_gate import (
        CAR_QUANTITY,
        choose_thresholds,
        observed_candidates,
        physical_selection,
        weather_of,
    )

    sensor_names = list(dict.fromkeys(s for b in branches for s in sensors[b]))
    candidates = {}
    for cond, (quantity, _, _) in CAR_QUANTITY.items():
        seen = [weather_of(m)[quantity] for m in fit_metas if cond in (m.get("conditions") or [])]
        options = observed_candidates(seen, cond)
        if len(options) > 1:
            candidates.update({(s, cond): options for s in sensor_names})
    weather = [weather_of(m) for m in val.metas]

    def score(rules) -> float:
        return val.map_of([val.name_of[physical_selection(w, branches, sensors, rules)] for w in weather])

    rules, trace = choose_thresholds(candidates, score)
    return rules, {"rules": [r.as_dict() for r in rules], "validation_map": rounded(max(t["score"] for t in trace)),
                   "validation_map_all_branches": rounded(trace[0]["score"]),
                   "candidates": {f"{s} / {c}": o for (s, c), o in candidates.items()}, "evaluations": len(trace)}


def a_posteriori_choice(test: Constants) -> list[str]:
    """Per frame, the constant `fusion.bounds.greedy_choice` takes to raise the test frames' pooled mAP,
    starting from all branches."""
    from fusion.bounds import greedy_choice

    return greedy_choice(test.sm.matches, list(test.constants), "all_branches")


def utility_choice(test: Constants) -> list[str]:
    """Per frame, the constant whose fused detections have the highest `frame_utility` on the frame's own
    ground truth (all branches where it ties for the highest)."""
    from study.engine.scoring import frame_ground_truth
    out = []
    for i, meta in enumerate(test.metas):
        gt = frame_ground_truth(test.reader, meta, "camera_right", None, test.protocol)
        u = {c: frame_utility(f[i][1], gt) for c, f in test.fused.items()}
        out.append("all_branches" if u["all_branches"] == max(u.values()) else max(u, key=u.get))
    return out


def _difference(value, iv) -> dict:
    from study.experiments.compare import verdict

    return {"value": value, "ci95": iv, "verdict": verdict(iv)}


def gate_choices(test: Constants, gate_pred, gate_data, method, branches, sensors,
                 gate_frames: dict | None = None) -> tuple[dict, dict]:
    """The per-context constant and the physical gate chosen on the gate set's predictions `gate_pred`:
    ({name: each test frame's constant}, their records). `gate_frames` (`sweep`'s): every frame of
    `gate_pred` is chosen on, and the physical gate's candidates are the values seen on the frames its
    "fit_metas" list; without it the gate set is split by sequence (`split_by_sequence`)."""
    from fusion.physical_gate import physical_selection, weather_of
    from sensors.dataset import DatasetReader
    from study.engine.predictions import load
    gp = load(gate_pred)
    if gate_frames is None:
        fit, val_pos = split_by_sequence(gp.per_frame, "pem sweep --gate-set")
        fit_metas = [gp.per_frame[p][0] for p in fit]
    else:
        fit_metas, val_pos = gate_frames["fit_metas"], list(range(len(gp.per_frame)))
    val = Constants([gp.per_frame[p] for p in val_pos], test.constants, gp.branch_frames, method,
                    DatasetReader(gate_data), test.protocol)
    chosen_on = {"frames": len(val_pos), "sequences": len({m["sequence_id"] for m in val.metas}),
                 "fitting_frames": len(fit_metas), **({"on": gate_frames["on"]} if gate_frames else {})}
    cc = context_constant(val)
    rules, rec = physical_rules(val, fit_metas, branches, sensors)
    choices = {CONTEXT_CONSTANT: [cc.get(m["context"], cc["all"]) for m in test.metas],
               PHYSICAL_GATE: [test.name_of[physical_selection(weather_of(m), branches, sensors, rules)]
                               for m in test.metas]}
    dropped = {}
    for m, c in zip(test.metas, choices[PHYSICAL_GATE]):
        dropped.setdefault(m["context"], []).append(len(test.constants[c]) < len(branches))
    records = {CONTEXT_CONSTANT: {"choice": cc, "chosen_on": chosen_on,
                                  "without": {g: [b for b in branches if b not in test.constants[n]] for g, n in cc.items()}},
               PHYSICAL_GATE: {**rec, "chosen_on": chosen_on,
                               "share_dropping_per_context": {c: rounded(sum(v) / len(v)) for c, v in sorted(dropped.items())}}}
    return choices, records


def verdict_at(test_pred, data, gate_pred, gate_data, *, fusion: str, resamples: int,
               gate_frames: dict | None = None) -> dict:
    """The comparisons of the module docstring that `compare` does not make, on the test predictions
    `test_pred` (and the gate set's `gate_pred`, or None): their values, intervals and verdicts, each
    method's mAP, per context the intervals against all branches, and what was chosen."""
    from sensors.dataset import DatasetReader
    from study.engine.predictions import load
    from study.engine.scoring import context_bootstrap, difference_interval, fusion_method
    from study.experiments.bounds import corrected_room

    tp = load(test_pred)
    method, protocol = fusion_method(fusion), tp.manifest["identity"]["protocol"]
    branches, sensors = list(tp.branches), tp.branch_sensors
    test = Constants(tp.per_frame, constants_of(branches, sensors), tp.branch_frames, method, DatasetReader(data),
                     protocol)
    choices, out = {}, {}
    if gate_pred is not None:
        choices, out = gate_choices(test, gate_pred, gate_data, method, branches, sensors, gate_frames)
    choices[ORACLE] = a_posteriori_choice(test)
    choices[UTILITY_ORACLE] = utility_choice(test)
    choices["all_branches"] = ["all_branches"] * len(test.metas)
    maps = {n: rounded(test.map_of(c)) for n, c in choices.items()}
    boot = None
    if resamples:
        boot = context_bootstrap({n: test.frames_of(c) for n, c in choices.items()}, test.reader, "camera_right",
                                 protocol=protocol, resamples=resamples, classes="all", desc="bootstrap the constants")
    per_context: dict = {}
    for n in (x for x in choices if x != "all_branches"):
        value = None if maps[n] is None or maps["all_branches"] is None else round(maps[n] - maps["all_branches"], 4)
        out[f"{n}_minus_all_branches"] = _difference(
            value, difference_interval(boot["per_context"]["all"], n, "all_branches") if boot else None)
        for g, group in ((boot or {}).get("per_context") or {}).items():
            if g != "all":
                per_context.setdefault(g, {})[f"{n}_minus_all_branches"] = difference_interval(group, n, "all_branches")
    out["room_for_context"] = room_record(corrected_room(test.sm, resamples)) if resamples else None
    out["maps"], out["per_context"] = maps, per_context
    return out


def room_record(room: dict) -> dict:
    """`corrected_room`'s record as a comparison: the split-sample estimate, its interval and verdict,
    its null beside it (mean, 95th percentile, whether the estimate is above it), and the naive one."""
    split, naive = room["split"], room["naive"]
    if "skipped" in split:
        return {"value": None, "ci95": None, "verdict": "not resolved", "skipped": split["skipped"], "naive": naive}
    return {**_difference(split["estimate"], split["interval"]), "null_mean": split["null_mean"],
            "null_upper": split["null_upper"], "above_null": split["above_null"], "naive": naive,
            "resamples": room["resamples"], "permutations": room["permutations"]}


def sweep(run_dir, data, pem_path, strengths, out_dir, *, gate_set=None, seed: int = 0, resamples: int = 500,
          fusion: str = "soft-nms", k: int = 2, progress: bool = False, gate_frames: dict | None = None) -> dict:
    """The sweep of the module docstring -> a JSON-able dict, one point per strength in `strengths`; each
    strength's predictions in OUT_DIR/strength-<s> (the gate set's in OUT_DIR/gate-strength-<s>).
    `gate_frames` ({"fit": indices, "val": indices} of `gate_set`, which may be `data` itself: a study's
    gate split): the gate frames as the caller split them, in place of `split_by_sequence`; the PEM is
    drawn on "val" and chosen on there, the physical gate's candidates are the values seen on "fit"; with
    no "val" frames both are the "fit" frames (the PEM drawn on the frames it was fitted on: labelled)."""
    from study.engine.scoring import load_run
    from study.experiments.compare import compare
    from study.experiments.pem import load_pem, predict_pem

    load_run(run_dir)  # the model first: a damaged checkpoint is named before the PEM file is read
    doc = load_pem(pem_path)
    chosen = None
    if gate_set is not None and gate_frames is None:
        check_gate_set(gate_set, data)
    elif gate_set is not None:
        chosen = given_gate_frames(run_dir, data, gate_set, gate_frames)
    points = []
    for s in strengths:
        t0 = time.perf_counter()
        pred = Path(out_dir) / f"strength-{s:g}"
        predict_pem(pem_path, data, pred, strength=s, seed=seed)
        gate_pred = None
        if gate_set is not None:
            gate_pred = Path(out_dir) / f"gate-strength-{s:g}"
            predict_pem(pem_path, gate_set, gate_pred, strength=s, seed=seed + 1,
                        **({"indices": chosen["indices"], "on_fitting_frames": not gate_frames["val"]} if chosen else {}))
        t1 = time.perf_counter()
        r = compare(run_dir, data, gates=("knowledge",), k=k, fusion=fusion, resamples=resamples,
                    predictions=pred, progress=progress)
        t2 = time.perf_counter()
        m = r["methods"]
        point = {"strength": float(s), "maps": {n: row["map"] for n, row in m.items()},
                 "all_branches_minus_late": m.get("all_branches", {}).get("minus_late"),
                 "knowledge_minus_all_branches": m.get("hydrafusion:knowledge", {}).get("minus_all_branches"),
                 "knowledge_minus_late": m.get("hydrafusion:knowledge", {}).get("minus_late")}
        if "all_branches" not in m:  # every branch reads one sensor: all branches is late fusion itself
            point.update(all_branches_is_late(point, resamples))
        more = verdict_at(pred, data, gate_pred, gate_set, fusion=fusion, resamples=resamples, gate_frames=chosen)
        point["maps"].update({n: v for n, v in more.pop("maps").items() if n not in point["maps"]})
        point.update(more)
        t3 = time.perf_counter()
        point["seconds"] = round(t3 - t0, 1)
        point["seconds_parts"] = {"draw": round(t1 - t0, 1), "compare": round(t2 - t1, 1), "constants": round(t3 - t2, 1)}
        points.append(point)
    return {"data": str(data), "pem": str(pem_path), "seed": seed, "resamples": resamples, "fusion": fusion, "k": k,
            "gate_set": None if gate_set is None else str(gate_set), "gate_seed": None if gate_set is None else seed + 1,
            **({"gate_frames": {"fit": len(gate_frames["fit"]), "val": len(gate_frames["val"]), "on": chosen["on"]}}
               if chosen else {}),
            **({"without_gate_set": NO_GATE_SET} if gate_set is None else {}),
            "constants": {n: list(b) for n, b in constants_of(doc["branches"], doc["branch_sensors"]).items()},
            "what": WHAT, "points": points}


SAME_AS_LATE = "every branch reads one sensor: all_branches is late fusion itself (the same boxes on every frame)"


def all_branches_is_late(point: dict, resamples: int) -> dict:
    """Where every branch is a single sensor `compare` has no all_branches row: all_branches is late fusion,
    so all_branches minus late is 0 on every draw, and the knowledge gate minus all_branches is its minus
    late (each marked with `SAME_AS_LATE`)."""
    knowledge = point.get("knowledge_minus_late")
    return {"all_branches_minus_late": {"value": 0.0, "ci95": [0.0, 0.0] if resamples else None,
                                        "verdict": "not resolved", "note": SAME_AS_LATE},
            "knowledge_minus_all_branches": None if knowledge is None else {**knowledge, "note": SAME_AS_LATE}}


GIVEN_ON = {True: "the gate frames' validation sequences", False: (
    "the gate frames' fitting sequences, which the PEM was fitted on (gates.val_fraction carves no validation "
    "sequence; the study's own choices fall back the same way)")}
"""Where `sweep` chooses with `gate_frames`: on their validation frames, or on the fitting ones."""


def given_gate_frames(run_dir, data, gate_set, gate_frames: dict) -> dict:
    """`sweep`'s `gate_frames` checked (UserError where a gate frame is a test frame or none is given) ->
    the frames the PEM is drawn on and chosen on, the fitting frames' metas, and where it chooses."""
    import json

    from sensors.dataset import DatasetReader
    from study.engine.gate_data import dataset_sha256
    from study.engine.scoring import frames_for

    fit, val = [int(i) for i in gate_frames["fit"]], [int(i) for i in gate_frames["val"]]
    if not fit:
        raise UserError(f"{gate_set}: no gate frames to fit the physical gate's candidates on")
    if dataset_sha256(gate_set) == dataset_sha256(data):
        test, _ = frames_for(json.loads((Path(run_dir) / "config.json").read_text()), data, "auto")
        if set(test) & set(fit + val):
            raise UserError(f"{gate_set}: a gate frame is a test frame; choose on other frames")
    reader = DatasetReader(gate_set)
    return {"indices": val or fit, "on": GIVEN_ON[bool(val)],
            "fit_metas": [dict(reader.meta(i), dataset_index=i) for i in fit]}


def check_gate_set(gate_set, data) -> None:
    """UserError, before anything is drawn, when the gate set cannot be split into fitting and validation
    sequences in every context, or holds the test set's frames."""
    from sensors.dataset import DatasetReader
    from study.engine.gate_data import dataset_sha256
    reader = DatasetReader(gate_set)
    split_by_sequence([(reader.meta(i), None) for i in range(len(reader))], "pem sweep --gate-set")
    if dataset_sha256(gate_set) == dataset_sha256(data):
        raise UserError(f"--gate-set {gate_set}: the same frames as the test set {data}; choose on another dataset")


def _cell(d) -> str:
    if not d or d.get("value") is None:
        return "-"
    iv = d.get("ci95")
    return f"{d['value']:+.3f}" + (f" {interval_text(iv, signed=True)} {d['verdict']}" if iv else "")


def format_sweep(r: dict) -> str:
    """The sweep as text: per comparison one line per strength (value, 95 % interval, verdict), then what
    the gate set chose."""
    gate = (f"gate set {r['gate_set']} (draws seed {r['gate_seed']})" if r.get("gate_set")
            else r.get("without_gate_set", ""))
    lines = [f"PEM {r['pem']} on {r['data']} (draws seed {r['seed']}, {r['resamples']} sequence draws, k {r['k']}); {gate}",
             f"{'strength':>8s} {'late':>6s} {'all':>6s} s"]
    for p in r["points"]:
        mp = p["maps"]
        lines.append(f"{p['strength']:8g} {mp.get('late') or 0:6.3f} {mp.get('all_branches') or 0:6.3f} {p['seconds']}")
    for key, title in COMPARISONS.items():
        lines.append(f"{title}:")
        for p in r["points"]:
            d, extra = p.get(key), ""
            if key == "room_for_context" and d and "null_upper" in d:
                extra = f"  (null: 95th percentile {d['null_upper']:+.3f}, {'above' if d['above_null'] else 'not above'} it)"
            elif d is None and key in NEEDS_GATE_SET and r.get("without_gate_set"):
                extra = " (no --gate-set)"
            lines.append(f"  {p['strength']:8g}  {_cell(d)}{extra}")
    for p in r["points"]:
        cc, pg = p.get(CONTEXT_CONSTANT), p.get(PHYSICAL_GATE)
        if cc:
            lines.append(f"strength {p['strength']:g}: per-context constant " + ", ".join(
                f"{c} -> {n}" for c, n in cc["choice"].items()))
        if pg:
            lines.append(f"strength {p['strength']:g}: physical gate " + ("; ".join(x["text"] for x in pg["rules"]) or
                                                                        "no rule (every branch always)"))
    return "\n".join(lines)


COLOURS = ("#1f5fa8", "#2ca02c")


def _curve(ax, s, pts, key, colour, label) -> bool:
    """One comparison over strength on `ax`: the estimates joined, the 95 % intervals as a band and
    bars; the room's null (95th percentile) dashed. False when no point has a value."""
    rows = [(x, p[key]) for x, p in zip(s, pts) if p.get(key) and p[key].get("value") is not None]
    if not rows:
        return False
    band = [(a, d["value"], d["ci95"]) for a, d in rows if d.get("ci95")]
    if band:
        xs, vs, ivs = zip(*band)
        ax.fill_between(xs, [iv[0] for iv in ivs], [iv[1] for iv in ivs], color=colour, alpha=0.18, lw=0)
        ax.errorbar(xs, vs, yerr=[[v - iv[0] for v, iv in zip(vs, ivs)], [iv[1] - v for v, iv in zip(vs, ivs)]],
                    fmt="none", ecolor=colour, capsize=3, lw=1)
    ax.plot([a for a, _ in rows], [d["value"] for _, d in rows], "o-", color=colour, label=f"{label} (95 % interval)")
    if key == "room_for_context" and all("null_upper" in d for _, d in rows):
        ax.plot([a for a, _ in rows], [d["null_upper"] for _, d in rows], "x--", color="#c05a00",
                label="its null, 95th percentile")
    return True


def plot_sweep(r: dict, path) -> None:
    """One panel per entry of `PANELS`: each comparison's difference over strength (log2 axis) with its
    95 % interval as a band and bars, and the zero line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from study.outputs import savefig_atomic

    pts = r["points"]
    s = [p["strength"] for p in pts]
    fig, axes = plt.subplots(2, 3, figsize=(13.5, 7.5), sharex=True)
    for ax, (title, keys) in zip(axes.flat, PANELS.items()):
        ax.axhline(0, color="k", lw=0.8)
        drawn = [_curve(ax, s, pts, key, colour, COMPARISONS[key].split(" - ")[0])
                 for key, colour in zip(keys, COLOURS)]
        if any(drawn):
            lo, hi = ax.get_ylim()
            ax.set_ylim(lo, hi + 0.3 * (hi - lo))  # room for the legend above the curves
            ax.legend(fontsize=7, loc="upper left")
        else:
            ax.text(0.5, 0.5, "not measured\n(no --gate-set)" if r.get("without_gate_set") else "no value",
                    transform=ax.transAxes, ha="center", va="center", color="grey")
        ax.set_xscale("log", base=2)
        ax.set_xticks(s, [f"{x:g}" for x in s])
        ax.minorticks_off()
        ax.set_title(f"{title} (mAP)", fontsize=10)
    for ax in axes[-1]:
        ax.set_xlabel("detector strength s (1: the fitted PEM)")
    gate = f", gate set {Path(r['gate_set']).name}" if r.get("gate_set") else ""
    fig.suptitle(f"The verdict over strength: PEM {Path(r['pem']).name} on {Path(r['data']).name} (draws seed "
                 f"{r['seed']}{gate}; {r['resamples']} sequence draws)", fontsize=11)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    savefig_atomic(fig, path)
    plt.close(fig)
