"""The study's bounds, named for what they are, and the intervals that go with them (issue 36).

- The per-frame a-posteriori oracles (`A_POSTERIORI`: HydraFusion's optimal gate, EcoFusion's
  loss-based one) read the frame's own ground truth: a car cannot run them, they are labelled so
  (`label`) wherever they appear, and never read as "room" for a gate.
- The context oracle (`CONTEXT_ORACLE`): per context, the constant branch set among the fixed
  configurations the study scores (each single sensor, each EcoFusion configuration, late fusion,
  all branches) with the best mAP on that context's *test* frames, applied to them. It is the bound of
  any gate that reads only the context; chosen on test, it is a bound, not a method.
- Room for context (`ROOM`): context oracle minus all branches, with its paired interval. The choice
  is made again inside every bootstrap draw (`fusion.bounds.bootstrap_table`'s derived column), so the
  interval carries the luck of a max over configurations; a fixed choice would make it optimistic.
- `StudyMatches.intervals`: every method's bootstrap intervals (the draws and output of
  `study.engine.scoring.context_bootstrap`, classes "all") plus each paired difference's p-value
  (`fusion.intervals.bootstrap_p_value`, for the verdict's Holm correction) and the context oracle.
- `coverage_record`: the intervals' coverage over disjoint test sets
  (`study.experiments.interval_coverage.coverage_over_sets`).
- `best_single_on_validation`: the verdict's best single sensor per context, chosen on the
  validation frames and recorded in the `study.experiments.selection.SelectionLog`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from fusion.bounds import best_constant_map, best_constant_per_stratum, bootstrap_table, composite
from fusion.intervals import (
    bootstrap_p_value,
    design_draws,
    jackknife_p_value,
    jackknife_t_interval,
    leave_one_out_rows,
    percentile_interval,
)
from fusion.metrics import ImageMatches
from study.numbers import rounded, rounded_interval

A_POSTERIORI = ("hydrafusion:optimal", "ecofusion:loss_based")
A_POSTERIORI_LABEL = "a-posteriori oracle: uses the frame's own ground truth, not achievable"
CONTEXT_ORACLE = "context_oracle"
CONTEXT_ORACLE_LABEL = "context oracle (best constant per context, chosen on test: a bound, not a method)"
ROOM = "room for context"
ROOM_WHAT = ("context oracle minus all branches: what a gate that reads only the context could add over running "
             "every branch, at most")
OPTIMISTIC = ("The context oracle is chosen on the same test frames it is scored on, so its estimate is optimistic; "
              "its interval chooses the best constant per context again inside every bootstrap draw, which carries "
              "that luck into the interval (a fixed choice would make it too narrow).")
OPTIMAL_APPENDIX = ("HydraFusion's optimal gate ranks branches by their summed a-posteriori losses, which are not "
                    "comparable between BEV branches and camera branches (different heads, different loss scales): "
                    "its top k is not the best k branches, so it is kept in an appendix, not read as a bound.")
COVERAGE_SETS = 8
MIN_SEQUENCES_PER_SET = 2
"""A disjoint set needs this many sequences of every context for its within-context bootstrap to vary."""


def label(name: str) -> str:
    """`name` with what it is when it is a bound: a-posteriori oracles and the context oracle."""
    if name in A_POSTERIORI:
        return f"{name} ({A_POSTERIORI_LABEL})"
    if name == CONTEXT_ORACLE:
        return f"{name} ({CONTEXT_ORACLE_LABEL})"
    return name


def candidate_configurations(ev, singles: Sequence[str], late: Sequence[str]) -> dict[str, tuple[str, ...]]:
    """The constant branch sets the context oracle chooses among: each single sensor, late fusion, all
    branches and every EcoFusion configuration, {name: branches}, one name per branch set."""
    return constant_configurations(ev.ed.branches, ev.configs.members, singles, late)


def constant_configurations(branches: Sequence[str], members: Sequence[Sequence[str]], singles: Sequence[str],
                            late: Sequence[str]) -> dict[str, tuple[str, ...]]:
    """`candidate_configurations` of a network's `branches` and a configuration set's `members`
    (`fusion.eco.configurations.build_configurations`): {name: branches}, one name per branch set."""
    out: dict[str, tuple[str, ...]] = {f"single:{b}": (b,) for b in singles}
    out["late"] = tuple(late)
    out["all_branches"] = tuple(branches)
    seen = set(out.values())
    for m in members:
        if tuple(m) not in seen:
            out["+".join(m)] = tuple(m)
            seen.add(tuple(m))
    return out


class StudyMatches:
    """Each source's per-frame VOC matching on the test frames (rows in test order, every class),
    the frames' contexts and sequences: what the bounds, the intervals and the coverage read."""

    def __init__(self, matches: Mapping[str, ImageMatches], contexts: Sequence[str], sequences: Sequence,
                 candidates: Mapping[str, tuple[str, ...]] | None = None) -> None:
        self.matches, self.contexts, self.sequences = dict(matches), list(contexts), list(sequences)
        self.candidates = dict(candidates or {})

    @classmethod
    def of(cls, sources: Mapping[str, list], candidates: Mapping[str, tuple[str, ...]], candidate_frames: Mapping,
           reader, protocol) -> StudyMatches:
        """`sources` and `candidate_frames`: name -> [(meta, Detections)] per test frame, same frames."""
        from sim.actors import CLASSES
        from study.engine.scoring import ground_truth

        first = next(iter(sources.values()))
        metas = [m for m, _ in first]
        gts = [ground_truth(reader.labels(m["dataset_index"]), "camera_right", None, m, protocol) for m in metas]
        classes = list(range(1, len(CLASSES) + 1))

        def matched(frames):
            return ImageMatches.of([{"boxes": d.boxes, "scores": d.scores, "labels": d.labels} for _, d in frames],
                                   gts, classes=classes)

        matches = {n: matched(f) for n, f in {**candidate_frames, **sources}.items()}
        return cls(matches, [m["context"] for m in metas], [m["sequence_id"] for m in metas], candidates)

    def context_choice(self, rows: Sequence[int] | None = None) -> dict:
        """Per context, the candidate of best mAP on `rows` (all test frames by default)."""
        rows = range(len(self.contexts)) if rows is None else rows
        return best_constant_per_stratum(self.matches, list(self.candidates), list(rows), self.contexts)

    def context_oracle(self) -> tuple[list[tuple[str, ...]], dict]:
        """The context oracle's selection (per test frame, its context's chosen branches) and the choice
        {context: candidate}; its matching is added under `CONTEXT_ORACLE` for the coverage."""
        choice = self.context_choice()
        self.matches[CONTEXT_ORACLE] = composite(self.matches, [choice[c] for c in self.contexts])
        return [self.candidates[choice[c]] for c in self.contexts], choice

    def intervals(self, names: Sequence[str], resamples: int, seed: int = 0, design: str = "sequence") -> dict:
        """`study.engine.scoring.context_bootstrap`'s record (classes "all") for `names`, the same draws, plus
        "p_value" per pair; `CONTEXT_ORACLE` among `names` is re-chosen inside every draw. `design`:
        how sequences are drawn (`fusion.intervals.DESIGNS`; within one context "sequence" and
        "stratified" are the same draws)."""
        plain, derived = self.columns(names)
        cols = plain + list(derived)
        groups = {"all": range(len(self.contexts))}
        for r, c in enumerate(self.contexts):
            groups.setdefault(c, []).append(r)
        out = {"resamples": int(resamples), "unit": "sequence", "design": design, "seed": int(seed),
               "per_context": {}, "context_oracle_rechosen_per_draw": bool(derived),
               "per_context_interval": PER_CONTEXT_INTERVAL}
        for g, rows in groups.items():
            by_seq = self.by_sequence(rows)
            draws = bootstrap_table(self.matches, plain, by_seq, resamples, seed, derived,
                                    draws=self.draws(rows, resamples, seed, design))
            jack = None
            if g != "all" and len(by_seq) >= 2:  # the declared per-context interval: jackknife-t
                rows_all = [r for q in sorted(by_seq) for r in by_seq[q]]
                est = bootstrap_table(self.matches, plain, by_seq, 1, seed, derived, draws=[rows_all])[0]
                loo = leave_one_out_rows(by_seq)
                jack = (est, bootstrap_table(self.matches, plain, by_seq, len(loo), seed, derived, draws=loo))
            out["per_context"][g] = group_record(draws, cols, len(by_seq), jack)
        return out

    def draws(self, rows, resamples: int, seed: int, design: str = "sequence"):
        """Draws of whole sequences of `rows` by `design` (`fusion.intervals.design_draws`, strata: the
        contexts). "sequence" gives exactly `fusion.metrics.sequence_draws` over `by_sequence(rows)`."""
        by: dict = {}
        for r in rows:
            by.setdefault(self.contexts[r], {}).setdefault(self.sequences[r], []).append(r)
        return design_draws(by, resamples, seed, design)

    def columns(self, names: Sequence[str]) -> tuple[list[str], dict]:
        """(the names scored from their matching, {CONTEXT_ORACLE: its statistic re-chosen on a draw's
        rows} when it is among `names`)."""
        plain = [n for n in names if n != CONTEXT_ORACLE]
        derived = {}
        if CONTEXT_ORACLE in names:
            cands = list(self.candidates)
            derived[CONTEXT_ORACLE] = lambda rows: best_constant_map(self.matches, cands, rows, self.contexts)
        return plain, derived

    def by_sequence(self, rows) -> dict:
        """{sequence: [rows]} of `rows`: the unit the bootstrap draws."""
        by_seq: dict = {}
        for r in rows:
            by_seq.setdefault(self.sequences[r], []).append(r)
        return by_seq


def front_record(sm: StudyMatches, scores: Mapping[str, dict], placed: Sequence[str],
                 energy: Mapping[str, np.ndarray], resamples: int, seed: int = 0, design: str = "sequence") -> dict:
    """What `study.experiments.energy_front` draws the mAP-energy front from: every fixed configuration (the
    context oracle's candidates: each single sensor, each EcoFusion configuration, late fusion, all
    branches) and every method `placed` on the front, each with its mAP, its mean energy per frame
    (`energy`: per test frame, rows in test order) and their 95 % intervals, and each pair's mAP
    difference; all from the same draws of whole test sequences as the study's overall intervals
    (all test frames, `seed`), the context oracle re-chosen inside each draw. A method's mAP is its
    score (`scores`), a configuration that is no method's is scored from its matching, as the context
    oracle's candidates are."""
    names = [*sm.candidates, *[n for n in placed if n not in sm.candidates]]
    plain, derived = sm.columns(names)
    cols = plain + list(derived)
    everything = range(len(sm.sequences))
    by_seq = sm.by_sequence(everything)
    picks_of = list(sm.draws(everything, resamples, seed, design))
    rec = group_record(bootstrap_table(sm.matches, plain, by_seq, resamples, seed, derived, draws=picks_of), cols,
                       len(by_seq))
    e_draws = np.array([[float(np.mean(energy[n][picks])) for n in cols] for picks in picks_of])
    everything = list(range(len(sm.contexts)))
    return {"configurations": {n: list(b) for n, b in sm.candidates.items()}, "placed": list(placed),
            "map_point": {n: rounded(scores[n]["map"] if n in scores else sm.matches[n].mean_ap(everything))
                          for n in cols},
            "energy_point": {n: rounded(float(np.mean(energy[n]))) for n in cols},
            "energy_ci95": {n: rounded_interval(percentile_interval(e_draws[:, i])) for i, n in enumerate(cols)},
            **rec, "resamples": int(resamples), "seed": int(seed), "design": design}


PER_CONTEXT_INTERVAL = (
    "per context: jackknife-t (the estimate -+ t(n-1) times the leave-one-sequence-out standard error, its "
    "p-value from the same t), declared after `hydrabench bench coverage` (docs/study.md: the percentile "
    "interval of a few sequences' AP sits above the truth, it misses high); overall: the bootstrap percentile")


def group_record(draws: np.ndarray, names: Sequence[str], sequences: int, jackknife=None) -> dict:
    """One group's intervals from its draws (resamples, names): each name's mAP, each pair's
    difference (stored once, "a - b" in `names`' order) and its two-sided p-value; by the bootstrap's
    percentiles, or, with `jackknife` = (estimates (names,), leave-one-out values (n, names)), by
    jackknife-t (`fusion.intervals.jackknife_t_interval`, `jackknife_p_value`)."""
    names = list(names)
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
    col = {n: i for i, n in enumerate(names)}

    def diff(a, b):
        return draws[:, col[a]] - draws[:, col[b]]

    if jackknife is not None:
        est, loo = jackknife
        return {"sequences": int(sequences), "interval": "jackknife-t",
                "map": {n: rounded_interval(jackknife_t_interval(est[i], loo[:, i])) for n, i in col.items()},
                "difference": {f"{a} - {b}": rounded_interval(jackknife_t_interval(est[col[a]] - est[col[b]],
                                                                                   loo[:, col[a]] - loo[:, col[b]]))
                               for a, b in pairs},
                "p_value": {f"{a} - {b}": rounded(jackknife_p_value(est[col[a]] - est[col[b]],
                                                                    loo[:, col[a]] - loo[:, col[b]]))
                            for a, b in pairs}}
    return {"sequences": int(sequences),
            "map": {n: rounded_interval(percentile_interval(draws[:, i])) for i, n in enumerate(names)},
            "difference": {f"{a} - {b}": rounded_interval(percentile_interval(diff(a, b))) for a, b in pairs},
            "p_value": {f"{a} - {b}": rounded(bootstrap_p_value(diff(a, b))) for a, b in pairs}}


def room_for_context(scores: Mapping[str, dict], intervals: dict | None) -> dict:
    """Context oracle minus all branches per group ("all", then each context): the point difference,
    its 95 % interval and p-value (None without intervals)."""
    from study.engine.scoring import difference_interval

    oracle, every = scores[CONTEXT_ORACLE], scores["all_branches"]
    per = (intervals or {}).get("per_context") or {}
    out = {}
    for g in ["all", *sorted(oracle["map_per_context"])]:
        a = oracle["map"] if g == "all" else oracle["map_per_context"].get(g)
        b = every["map"] if g == "all" else every["map_per_context"].get(g)
        pg = per.get(g)
        p = None
        if pg and "p_value" in pg:
            p = pg["p_value"].get(f"{CONTEXT_ORACLE} - all_branches", pg["p_value"].get(f"all_branches - {CONTEXT_ORACLE}"))
        out[g] = {"estimate": None if a is None or b is None else rounded(a - b),
                  "interval": difference_interval(pg, CONTEXT_ORACLE, "all_branches") if pg else None, "p_value": p}
    return out


ROOM_CORRECTED_WHAT = (
    "The context oracle's room over all branches without its selection optimism (fusion.context_room, issue 50): "
    "'naive' chooses and scores on the same test sequences (the room above, >= 0 by construction); 'split' chooses "
    "per context on one half of the test sequences and scores on the other, both ways, averaged over random halvings "
    "(conservative: a choice made on half the data). Each has a percentile interval over draws of whole sequences "
    "within contexts (re-chosen, re-split in each draw) and its null: the same statistic with the constants' labels "
    "permuted within every sequence (equal constants), its mean and its 95th percentile. A room above its null's "
    "95th percentile is more than noise alone makes.")
ROOM_RESAMPLES = 200
ROOM_PERMUTATIONS = 100


def corrected_room(sm: StudyMatches, resamples: int, seed: int = 0, reference: str = "all_branches") -> dict:
    """`fusion.context_room.room_for_context` of the study's candidate constants over `reference`, on the
    test frames (pooled mAP per context, all classes), at most ROOM_RESAMPLES draws and ROOM_PERMUTATIONS
    null permutations: {"naive": {...}, "split": {...}, "what", "candidates", "sequences"}."""
    from fusion.context_room import matches_scorer
    from fusion.context_room import room_for_context as room

    names = list(sm.candidates)
    order = list(dict.fromkeys(sm.sequences))
    index = {q: i for i, q in enumerate(order)}
    context_of = {}
    for c, q in zip(sm.contexts, sm.sequences):
        context_of.setdefault(q, c)
    scorer = matches_scorer([sm.matches[n] for n in names], [index[q] for q in sm.sequences])
    out = room(scorer, [context_of[q] for q in order], names.index(reference), len(names),
               resamples=min(resamples, ROOM_RESAMPLES), seed=seed, permutations=min(resamples, ROOM_PERMUTATIONS))
    rec = {k: {"estimate": rounded(v["estimate"]), "interval": rounded_interval(v["interval"]),
               "null_mean": rounded(v["null_mean"]), "null_upper": rounded(v["null_upper"]),
               "above_null": bool(v["estimate"] > v["null_upper"])} for k, v in out.items()}
    per_context = {c: sum(1 for q in order if context_of[q] == c) for c in sorted(set(context_of.values()))}
    fewest = min(per_context.values())
    if fewest < 2:  # a context with one sequence cannot be halved: nothing is chosen apart from what is scored
        rec["split"] = {"skipped": f"a context has {fewest} test sequence; halving needs at least 2 in every context "
                                   f"(sequences per context: {per_context})"}
    return {**rec, "what": ROOM_CORRECTED_WHAT, "reference": reference, "candidates": names, "sequences": len(order),
            "sequences_per_context": per_context,
            "resamples": min(resamples, ROOM_RESAMPLES), "permutations": min(resamples, ROOM_PERMUTATIONS)}


def best_on_validation(val, candidates: Mapping[str, tuple[str, ...]], method: str, log, what: str) -> dict[str, str]:
    """Overall ("all") and per context, the candidate ({name: branches fused on every frame}) of best mAP on
    the validation frames (`ValidationFrames`), each choice recorded in `log` as "<what> (<group>)..."
    {group: candidate name}."""
    n = len(val.indices)
    scored = {name: val.score([tuple(b)] * n, method) for name, b in candidates.items()}
    contexts = sorted({c for sc in scored.values() for c in sc["map_per_context"]})
    out = {}
    for g in ["all", *contexts]:
        cands = {name: (sc["map"] if g == "all" else sc["map_per_context"].get(g)) for name, sc in scored.items()}
        if any(v is not None for v in cands.values()):
            out[g] = log.choose(what.format(group="overall" if g == "all" else g), cands, val.indices,
                                lower_is_better=False, measure="mAP", sequences=val.sequences)
    return out


def context_constant_on_validation(val, candidates: Mapping[str, tuple[str, ...]], method: str, log) -> dict[str, str]:
    """Issue 50 item 1a: per context, the candidate constant (`candidate_configurations`) of best mAP on
    the validation frames, each choice recorded in `log`; "all": the best overall, for a context the
    validation frames lack. {group: candidate name}."""
    return best_on_validation(val, candidates, method, log, "per-context constant ({group}), a method")


def add_context_constant(ev, val, singles, late, method: str, log, selections: dict, kinds: dict) -> dict:
    """Add the per-context constant (`context_constant_on_validation` among `candidate_configurations`) to
    `selections` and `kinds` as a method: on each test frame, its context's choice (the overall choice for a
    context the validation frames lack). Returns its record for the report."""
    candidates = candidate_configurations(ev, singles, late)
    choice = context_constant_on_validation(val, candidates, method, log)
    selections[CONTEXT_CONSTANT] = [candidates[choice.get(m["context"], choice["all"])] for m in ev.metas]
    kinds[CONTEXT_CONSTANT] = CONTEXT_CONSTANT_LABEL
    return {"what": CONTEXT_CONSTANT_LABEL, "chosen_on": "validation",
            "choice": {g: {"candidate": n, "branches": list(candidates[n])} for g, n in choice.items()}}


CONTEXT_CONSTANT = "context_constant"
CONTEXT_CONSTANT_LABEL = ("per-context constant (per context, the fixed configuration of best mAP on the validation "
                          "frames, scored once on test: a method a car can run, the room a context-only gate can reach)")


def coverage_sets(contexts: Sequence[str], sequences: Sequence) -> tuple[int, str | None]:
    """How many disjoint test sets the coverage check can deal (at most `COVERAGE_SETS`, each with
    `MIN_SEQUENCES_PER_SET` sequences of every context), and why it is skipped (None when it is not)."""
    per: dict = {}
    for c, s in zip(contexts, sequences):
        per.setdefault(c, set()).add(s)
    fewest = min((len(v) for v in per.values()), default=0)
    n = min(COVERAGE_SETS, fewest // MIN_SEQUENCES_PER_SET)
    if n < 2:
        return n, (f"skipped: the fewest test sequences of a context is {fewest}; two disjoint sets need at least "
                   f"{2 * MIN_SEQUENCES_PER_SET} of every context ({MIN_SEQUENCES_PER_SET} each, so that a set's "
                   "bootstrap within a context varies)")
    return n, None


def coverage_record(sm: StudyMatches, pairs: Sequence[tuple[str, str]], resamples: int, seed: int = 0,
                    design: str = "sequence") -> dict:
    """`study.experiments.interval_coverage.coverage_over_sets` over as many disjoint sets as the test set allows
    (`coverage_sets`), for the pairs whose sources were scored; {"skipped": reason} when it cannot."""
    from study.experiments.interval_coverage import coverage_over_sets

    n, why = coverage_sets(sm.contexts, sm.sequences)
    pairs = [(a, b) for a, b in pairs if a in sm.matches and b in sm.matches]
    if why or not pairs:
        return {"skipped": why or "no pair to check", "sets": n}
    out = coverage_over_sets(sm.matches, sm.contexts, sm.sequences, pairs, n_sets=n, resamples=resamples, seed=seed,
                             design=design)
    for v in out["pairs"].values():
        v.pop("per_set", None)
    out["context_oracle_choice"] = "fixed: chosen once on all test frames" if any(
        CONTEXT_ORACLE in p for p in pairs) else None
    return out


class ValidationFrames:
    """The validation frames of the study (`study.experiments.selection.gate_frames`: whole sequences per context
    of the run's gate split, or of its train split when it has none; the ones the gates pick their
    epoch and objective on): each branch's cached detections there (`study.eco.data.EcoData`),
    fused and scored on demand. Every index passes the guard
    (`study.experiments.selection.SelectionLog.check`) before anything is read."""

    def __init__(self, ev, fraction: float, seed: int, log) -> None:
        from study.eco.data import detections_from_array, eco_gate_frames
        from study.experiments.selection import sequences_of

        frames = eco_gate_frames(ev.run_cfg, ev.data, 0, "auto", fraction, seed)
        val = frames.val
        self.carved, self.holdout = bool(val), frames.holdout
        if not val:  # too few sequences per context to carve any: choose on the fitting frames
            val = list(frames.fit)
        self.ev, self.indices = ev, log.check(val, "validation frames")
        self.sequences = sequences_of(ev.reader, self.indices)
        ev.ed.ensure(self.indices, progress=False)
        arr = ev.ed.arrays(self.indices, ["detections", "features"])
        self.dets = [detections_from_array(a, ev.ed.branches) for a in arr["detections"]]
        self.features = arr["features"]
        self.metas = [dict(ev.reader.meta(i), dataset_index=int(i)) for i in self.indices]
        self.memo: dict = {}

    def score(self, selection, method: str) -> dict:
        from study.engine.scoring import fuse_selection, score

        per = fuse_selection(list(zip(self.metas, self.dets)), selection, self.ev.model.branch_frames, method,
                             memo=self.memo.setdefault(method, {}))
        return score(per, self.ev.reader, "camera_right", protocol=self.ev.ed.protocol)

    def map(self, branches: tuple[str, ...], method: str):
        return self.score([tuple(branches)] * len(self.indices), method)["map"]


def best_single_on_validation(val, singles: Sequence[str], method: str, log) -> dict[str, str]:
    """The best single sensor overall ("all") and per context, by mAP on the validation frames
    (`study.experiments.bounds.ValidationFrames`), each choice recorded in `log`: {group: "single:<branch>"}."""
    return best_on_validation(val, {f"single:{b}": (b,) for b in singles}, method, log,
                              "best single sensor ({group}), for the verdict")


def evaluate_bounds(M, ev, selections: dict, kinds: dict, scores: dict, early_fused: dict, singles, late,
                    learned, resamples: int, energy_of=None, design: str = "sequence") -> tuple[dict | None, dict]:
    """Add the context oracle to `selections`, `kinds` and `scores` (scored by `M.score` like every
    method), and return the study's intervals (every method and the early models, `StudyMatches.intervals`;
    None when `resamples` is 0) and the bounds record (the choice, room for context, the coverage).
    `M`: the study's `study.pipeline.evaluation.Methods`; `design`: how the intervals draw sequences
    (`fusion.intervals.DESIGNS`), the coverage check the same."""
    candidates = candidate_configurations(ev, singles, late)
    sources = {n: M.fused(s) for n, s in selections.items()}
    sources.update({f"early:{b}": per for b, per in early_fused.items()})
    cand_frames = {n: M.fused(M.fixed(b)) for n, b in candidates.items() if n not in sources}
    sm = StudyMatches.of(sources, candidates, cand_frames, ev.reader, ev.ed.protocol)
    selection, choice = sm.context_oracle()
    selections[CONTEXT_ORACLE], kinds[CONTEXT_ORACLE] = selection, CONTEXT_ORACLE_LABEL
    scores[CONTEXT_ORACLE] = M.score(selection)
    names = [*selections, *[f"early:{b}" for b in early_fused]]
    intervals = sm.intervals(names, resamples, design=design) if resamples else None
    pairs = [*[(f"hydrafusion:{g}", "late") for g in learned], ("all_branches", "late"), (CONTEXT_ORACLE, "all_branches")]
    coverage = (coverage_record(sm, pairs, resamples, design=design) if resamples else
                {"skipped": "evaluate.bootstrap = 0: no intervals to check"})
    record = {"context_oracle": {"what": CONTEXT_ORACLE_LABEL, "chosen_on": "test",
                                 "choice": {c: {"candidate": n, "branches": list(candidates[n])} for c, n in sorted(choice.items())},
                                 "candidates": {n: list(b) for n, b in candidates.items()},
                                 "rechosen_per_draw": intervals is not None},
              "room_for_context": room_for_context(scores, intervals), "room_what": ROOM_WHAT, "optimistic": OPTIMISTIC,
              "room_corrected": corrected_room(sm, resamples) if resamples else None,
              "a_posteriori": {n: A_POSTERIORI_LABEL for n in A_POSTERIORI if n in scores},
              "optimal_appendix": OPTIMAL_APPENDIX if "hydrafusion:optimal" in scores else None,
              "coverage": coverage}
    if energy_of is not None and resamples:  # the mAP-energy front (`study.experiments.energy_front`)
        placed = [n for n in selections if n not in candidates]
        per = {**{n: M.fixed(b) for n, b in candidates.items()}, **{n: selections[n] for n in placed}}
        record["front"] = front_record(sm, scores, placed, {n: energy_of(n, sel) for n, sel in per.items()},
                                       resamples, design=design)
    return intervals, record
