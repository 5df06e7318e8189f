"""study.experiments.bounds and what reads it: the context oracle picks the best constant per context on the test
frames and is re-chosen in every draw; room for context carries its interval and p-value; the verdict
Holm-corrects its per-context orders; the regret at k is the oracle's mAP minus the gate's with the
interval of the same draws; the best single sensor is chosen on the validation frames only; the
coverage check deals as many sets as the test set allows; the report and README name each bound
for what it is."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from fusion.metrics import ImageMatches
from study.experiments.bounds import (
    A_POSTERIORI_LABEL,
    CONTEXT_ORACLE,
    CONTEXT_ORACLE_LABEL,
    StudyMatches,
    best_single_on_validation,
    coverage_record,
    coverage_sets,
    room_for_context,
)
from study.experiments.regrets import hydra_regret, regret_intervals
from study.experiments.selection import SelectionLog, TestSplitLeak
from study.report.verdict import best_single, orders, verdict_sentences

ROOT = Path(__file__).resolve().parents[2]


def _image(rng, q):
    tp = rng.random() < q
    fp = rng.random() < 0.5
    scores = ([0.5 + 0.5 * rng.random()] if tp else []) + ([0.4 * rng.random()] if fp else [])
    return {1: (np.array(scores, float), np.array([True] * tp + [False] * fp, bool), 1)}


QUALITY = {"single:a": {"x": 0.9, "y": 0.2}, "single:b": {"x": 0.2, "y": 0.9}, "all_branches": {"x": 0.6, "y": 0.6},
           "late": {"x": 0.5, "y": 0.5}}


def _study_matches(seqs_per_context=8, frames=4, seed=0) -> StudyMatches:
    contexts = [c for c in ("x", "y") for _ in range(seqs_per_context * frames)]
    sequences = [f"{c}{i // frames}" for i, c in enumerate(contexts)]
    rng = np.random.default_rng(seed)
    matches = {s: ImageMatches([_image(rng, q[c]) for c in contexts], (1,), "all") for s, q in QUALITY.items()}
    cands = {"single:a": ("a",), "single:b": ("b",), "late": ("a", "b"), "all_branches": ("a", "b", "ab")}
    return StudyMatches(matches, contexts, sequences, cands)


def test_the_context_oracle_picks_the_best_constant_of_each_context_and_is_rechosen_in_each_draw():
    sm = _study_matches()
    selection, choice = sm.context_oracle()
    assert choice == {"x": "single:a", "y": "single:b"}
    assert selection == [("a",) if c == "x" else ("b",) for c in sm.contexts]
    iv = sm.intervals(["single:a", "late", "all_branches", CONTEXT_ORACLE], resamples=60)
    assert iv["context_oracle_rechosen_per_draw"]
    for g in ("all", "x", "y"):
        pg = iv["per_context"][g]
        assert set(pg["map"]) == {"single:a", "late", "all_branches", CONTEXT_ORACLE}
        assert set(pg["p_value"]) == set(pg["difference"])
    # overall, re-chosen in each draw: never below the best candidate on the same draw
    assert iv["per_context"]["all"]["difference"][f"all_branches - {CONTEXT_ORACLE}"][1] <= 0
    # per context, the declared jackknife-t: re-chosen in each leave-one-sequence-out set, centred on the estimate
    assert iv["per_context_interval"].startswith("per context: jackknife-t")
    assert iv["per_context"]["x"]["interval"] == "jackknife-t" and "interval" not in iv["per_context"]["all"]
    assert iv["per_context"]["all"]["p_value"][f"all_branches - {CONTEXT_ORACLE}"] < 0.05
    scores = {CONTEXT_ORACLE: {"map": 0.8, "map_per_context": {"x": 0.85, "y": 0.75}},
              "all_branches": {"map": 0.6, "map_per_context": {"x": 0.6, "y": 0.6}}}
    room = room_for_context(scores, iv)
    assert room["all"]["estimate"] == pytest.approx(0.2) and room["x"]["estimate"] == pytest.approx(0.25)
    lo, hi = room["all"]["interval"]
    assert lo > 0 and [-hi, -lo] == iv["per_context"]["all"]["difference"][f"all_branches - {CONTEXT_ORACLE}"]
    assert room["all"]["p_value"] == iv["per_context"]["all"]["p_value"][f"all_branches - {CONTEXT_ORACLE}"]
    assert room_for_context(scores, None)["all"]["interval"] is None


def test_per_context_intervals_are_jackknife_t_over_sequences_left_out_in_turn():
    """Issue 50 item 2 (`hydrabench bench coverage`): a context's interval is the estimate -+ t(n-1) times
    the leave-one-sequence-out standard error, computed here by hand; its p-value is below 0.05 exactly
    when the interval excludes 0."""
    from scipy.stats import t

    sm = _study_matches(seqs_per_context=6)
    names = ["single:a", "single:b", "late"]
    iv = sm.intervals(names, resamples=30)
    rows = [r for r, c in enumerate(sm.contexts) if c == "x"]
    seqs = sorted({sm.sequences[r] for r in rows})
    est = {n: sm.matches[n].mean_ap(rows) for n in names}
    loo = {n: np.array([sm.matches[n].mean_ap([r for r in rows if sm.sequences[r] != q]) for q in seqs]) for n in names}
    k = len(seqs)
    for a, b in (("single:a", "single:b"), ("single:a", "late"), ("single:b", "late")):
        d, jd = est[a] - est[b], loo[a] - loo[b]
        se = np.sqrt((k - 1) / k * np.sum((jd - jd.mean()) ** 2))
        half = t.ppf(0.975, k - 1) * se
        assert iv["per_context"]["x"]["difference"][f"{a} - {b}"] == pytest.approx([d - half, d + half], abs=6e-5)  # stored to 4 decimals
        p = iv["per_context"]["x"]["p_value"][f"{a} - {b}"]
        lo, hi = iv["per_context"]["x"]["difference"][f"{a} - {b}"]
        assert (p < 0.05) == (lo > 0 or hi < 0)
    se = np.sqrt((k - 1) / k * np.sum((loo["late"] - loo["late"].mean()) ** 2))
    assert iv["per_context"]["x"]["map"]["late"] == pytest.approx(
        [est["late"] - t.ppf(0.975, k - 1) * se, est["late"] + t.ppf(0.975, k - 1) * se], abs=6e-5)


def test_coverage_deals_as_many_sets_as_the_test_set_allows_or_says_why_not():
    assert coverage_sets(["x"] * 8 + ["y"] * 8, [f"s{i}" for i in range(16)]) == (4, None)
    assert coverage_sets(["x"] * 40 + ["y"] * 40, [f"s{i}" for i in range(80)])[0] == 8
    n, why = coverage_sets(["x"] * 3 + ["y"] * 8, [f"s{i}" for i in range(11)])
    assert n == 1 and "fewest test sequences of a context is 3" in why
    sm = _study_matches(seqs_per_context=4)
    sm.context_oracle()
    cov = coverage_record(sm, [("all_branches", "late"), (CONTEXT_ORACLE, "all_branches"), ("nope", "late")],
                          resamples=30)
    assert cov["sets"] == 2 and set(cov["pairs"]) == {"all_branches - late", f"{CONTEXT_ORACLE} - all_branches"}
    for v in cov["pairs"].values():
        assert v["sets"] == 2 and 0 <= v["covered"] <= 2 and 0.5 < v["expected_if_exact"] < 0.95
    few = coverage_record(_study_matches(seqs_per_context=3), [("all_branches", "late")], resamples=10)
    assert few["skipped"].startswith("skipped: the fewest test sequences of a context is 3")


def _m(all_, **ctx):
    return {"map": all_, "map_per_context": ctx}


CTX = [f"c{i}" for i in range(8)]


def _holm_report(p_first: float | None) -> dict:
    """Eight contexts; hydrafusion:deep's interval against late excludes 0 in c0 only, p = p_first there."""
    per = {"all": {"sequences": 64, "map": {}, "difference": {"hydrafusion:deep - late": [-0.01, 0.02]}}}
    for i, c in enumerate(CTX):
        per[c] = {"sequences": 8, "map": {}, "difference": {"hydrafusion:deep - late": [0.01, 0.05] if i == 0 else [-0.02, 0.03]}}
        if p_first is not None:
            per[c]["p_value"] = {"hydrafusion:deep - late": p_first if i == 0 else 0.5}
    return {"results": {"dataset": {"contexts": CTX}, "singles": [],
                        "methods": {"late": _m(0.4, **{c: 0.4 for c in CTX}),
                                    "hydrafusion:deep": _m(0.41, **{c: 0.41 for c in CTX})},
                        "intervals": {"resamples": 100, "unit": "sequence", "seed": 0, "per_context": per}}}


def test_holm_turns_a_resolved_per_context_order_into_not_resolved_when_it_should():
    def c0(report):
        return next(o for o in orders(report) if o.group == "c0" and o.a == "hydrafusion:deep")

    assert c0(_holm_report(None)).resolved and c0(_holm_report(None)).p_adjusted is None  # no p-values: interval only
    o = c0(_holm_report(0.01))
    assert o.p == 0.01 and o.p_adjusted == pytest.approx(0.08) and not o.resolved and o.sign == 0  # 0.01 x 8 contexts
    s = verdict_sentences(_holm_report(0.01))
    assert "In c0 (8 test sequences), resolved above late fusion: none." in s
    assert any("Holm-corrected together with every per-context order of this verdict (8: every pair in every "
               "context, one family), is below 0.05." in x for x in s)
    assert any("it would take at least 320 draws." in x for x in s)  # 100 draws: 2 / 101 x 8 >= 0.05
    kept = c0(_holm_report(0.004))
    assert kept.p_adjusted == pytest.approx(0.032) and kept.resolved and kept.sign == 1
    assert "In c0 (8 test sequences), resolved above late fusion: hydrafusion:deep [+0.010, +0.050]." in \
        verdict_sentences(_holm_report(0.004))
    # the overall group is one comparison: not corrected
    assert next(o for o in orders(_holm_report(0.01)) if o.group == "all").p_adjusted is None


def _twin_report(resamples: int = 1000) -> dict:
    """Two contexts; physical_gate scores c0 exactly as all_branches (same mAP, interval and p = 0.01),
    but the two differ in c1, where all_branches has a small p-value and physical_gate a large one."""
    ctx = ["c0", "c1"]
    per = {"all": {"sequences": 16, "map": {}, "difference": {}}}
    diff = {"c0": ([0.01, 0.05], [0.01, 0.05]), "c1": ([0.01, 0.05], [-0.02, 0.03])}
    pv = {"c0": (0.01, 0.01), "c1": (0.002, 0.6)}
    for c in ctx:
        per[c] = {"sequences": 8, "map": {},
                  "difference": {"all_branches - late": diff[c][0], "physical_gate - late": diff[c][1]},
                  "p_value": {"all_branches - late": pv[c][0], "physical_gate - late": pv[c][1]}}
    return {"results": {"dataset": {"contexts": ctx}, "singles": [],
                        "methods": {"late": _m(0.4, c0=0.4, c1=0.4), "all_branches": _m(0.42, c0=0.43, c1=0.43),
                                    "physical_gate": _m(0.42, c0=0.43, c1=0.41)},
                        "intervals": {"resamples": resamples, "unit": "sequence", "seed": 0, "per_context": per}}}


def test_the_per_context_orders_are_one_family_and_twins_get_the_same_verdict():
    os_ = {(o.group, o.a): o for o in orders(_twin_report())}
    ab, pg = os_[("c0", "all_branches")], os_[("c0", "physical_gate")]
    # one family of 4 (2 pairs x 2 contexts): sorted 0.002, 0.01, 0.01, 0.6 -> 0.008, 0.03, 0.03 (running max), 0.6
    assert ab.p_adjusted == pg.p_adjusted == pytest.approx(0.03) and ab.resolved and pg.resolved
    assert os_[("c1", "all_branches")].p_adjusted == pytest.approx(0.008)
    # a family per pair would have split the twins: all_branches' own family {0.01, 0.002} gives 0.01 x 1
    # while physical_gate's {0.01, 0.6} gives 0.02; one family keeps them equal whatever the other contexts do
    bh = {(o.group, o.a): o for o in orders(_twin_report(), correction="bh")}
    assert bh[("c0", "all_branches")].p_adjusted == bh[("c0", "physical_gate")].p_adjusted == pytest.approx(0.04 / 3)
    with pytest.raises(ValueError, match="correction must be one of"):
        orders(_twin_report(), correction="bonferroni")


def test_the_verdict_says_when_its_draws_are_too_few_for_any_per_context_order_to_pass_holm():
    few = " ".join(verdict_sentences(_twin_report(resamples=100)))  # 2 / 101 x 4 = 0.079 >= 0.05
    assert "With 100 draws the smallest p-value a difference can have is 0.0198, so over 4 orders this " \
           "correction resolves none; it would take at least 160 draws." in few
    assert "it would take" not in " ".join(verdict_sentences(_twin_report(resamples=1000)))
    # a report whose per-context p-values are jackknife-t's (from t, not from draws) has no such floor
    jack = _twin_report(resamples=100)
    jack["results"]["intervals"]["per_context_interval"] = "per context: jackknife-t (...)"
    text = " ".join(verdict_sentences(jack))
    assert "it would take" not in text and "Per-context intervals and p-values: per context: jackknife-t" in text


def test_the_regret_at_k_is_the_oracles_map_minus_the_gates_with_the_interval_of_the_same_draws():
    contexts = ["x", "x", "y", "y"]
    sel = {"hydrafusion:optimal": [("a", "b")] * 4, "hydrafusion:deep": [("a", "b"), ("a", "c"), ("b", "c"), ("a", "b")]}
    scores = {"hydrafusion:optimal": _m(0.50, x=0.60, y=0.40), "hydrafusion:deep": _m(0.42, x=0.55, y=0.25)}
    reg = hydra_regret(sel, scores, ["deep", "optimal"], contexts, k=2)["deep"]
    # by hand: oracle minus gate; the top-2 choices differ on frames 1 and 2
    assert reg["all"]["regret_map"] == pytest.approx(0.08) and reg["x"]["regret_map"] == pytest.approx(0.05)
    assert reg["y"]["regret_map"] == pytest.approx(0.15)
    assert (reg["x"]["differs_pct"], reg["y"]["differs_pct"], reg["all"]["differs_pct"]) == (50.0, 50.0, 50.0)
    assert reg["all"]["k"] == 2
    per = {g: {"sequences": 8, "map": {}, "difference": {"hydrafusion:deep - hydrafusion:optimal": [-0.1 - i, -0.02]}}
           for i, g in enumerate(("all", "x", "y"))}
    out = regret_intervals({"hydrafusion": {"deep": reg}}, {"per_context": per})
    assert out["hydrafusion"]["deep"]["all"]["regret_interval"] == [0.02, 0.1]  # the stored pair turned round
    assert out["hydrafusion"]["deep"]["y"]["regret_interval"] == [0.02, 2.1]
    assert regret_intervals({"hydrafusion": {"deep": dict(reg)}}, None)["hydrafusion"]["deep"]["x"]["regret_interval"] is None


class FakeValidation:
    """What `best_single_on_validation` reads of a `study.experiments.bounds.ValidationFrames`."""

    def __init__(self, indices, maps):
        self.indices, self.sequences, self.maps = list(indices), 4, maps

    def score(self, selection, method):
        assert len(selection) == len(self.indices)
        return self.maps[selection[0][0]]


def test_the_best_single_sensor_is_chosen_on_validation_and_changing_test_scores_changes_nothing():
    val = FakeValidation(range(10, 20), {"radar": _m(0.3, x=0.5, y=0.1), "lidar": _m(0.35, x=0.2, y=0.4)})
    log = SelectionLog.of(range(10))
    chosen = best_single_on_validation(val, ["radar", "lidar"], "wbf", log)
    assert chosen == {"all": "single:lidar", "x": "single:radar", "y": "single:lidar"}
    assert [c["what"] for c in log.choices] == ["best single sensor (overall), for the verdict",
                                               "best single sensor (x), for the verdict",
                                               "best single sensor (y), for the verdict"]
    with pytest.raises(TestSplitLeak):  # the guard refuses test frames
        best_single_on_validation(FakeValidation(range(5, 15), val.maps), ["radar"], "wbf", SelectionLog.of(range(10)))
    per = {g: {"sequences": 8, "map": {}, "difference": {"late - single:radar": [0.01, 0.1], "late - single:lidar": [-0.1, 0.1]}}
           for g in ("all", "x", "y")}
    report = {"results": {"dataset": {"contexts": ["x", "y"]}, "singles": ["radar", "lidar"], "best_single": chosen,
                          "methods": {"single:radar": _m(0.3, x=0.3, y=0.3), "single:lidar": _m(0.2, x=0.2, y=0.2),
                                      "late": _m(0.4, x=0.4, y=0.4)},
                          "intervals": {"resamples": 10, "unit": "sequence", "seed": 0, "per_context": per}}}
    before = [(o.group, o.b) for o in orders(report) if o.a == "late"]
    # test scores that make the other sensor best everywhere: the choice, and so the verdict's order, stay
    report["results"]["methods"]["single:lidar"] = _m(0.9, x=0.9, y=0.9)
    assert best_single(report, "x") == "single:radar" and best_single(report, "all") == "single:lidar"
    assert [(o.group, o.b) for o in orders(report) if o.a == "late"] == before == \
        [("all", "single:lidar"), ("x", "single:radar"), ("y", "single:lidar")]
    assert any("its best single sensor on the validation frames, single:radar" in s for s in verdict_sentences(report))


def _bounds_report() -> dict:
    ctx = {"city": 0, "fog": 0}
    per = {g: {"sequences": 8, "map": {"hydrafusion:optimal": [0.4, 0.6], "late": [0.3, 0.5]},
               "difference": {"hydrafusion:optimal - late": [0.05, 0.15], "context_oracle - all_branches": [0.01, 0.09],
                              "ecofusion:loss_based - late": [0.02, 0.2]},
               "p_value": {"hydrafusion:optimal - late": 0.01, "context_oracle - all_branches": 0.02,
                           "ecofusion:loss_based - late": 0.01}} for g in ("all", *ctx)}
    room = {g: {"estimate": 0.05, "interval": [0.01, 0.09], "p_value": 0.02} for g in ("all", *ctx)}
    methods = {"late": _m(0.4, city=0.5, fog=0.3), "all_branches": _m(0.41, city=0.5, fog=0.32),
               "hydrafusion:optimal": _m(0.5, city=0.55, fog=0.45), "ecofusion:loss_based": _m(0.47, city=0.52, fog=0.42),
               CONTEXT_ORACLE: _m(0.46, city=0.55, fog=0.37), "hydrafusion:attention": _m(0.45, city=0.5, fog=0.4),
               "ecofusion:attention": _m(0.43, city=0.5, fog=0.36)}
    for n, v in methods.items():
        v["what"] = n
    return {"scale": "cpu", "meaningless": False, "results": {
        "protocol": "reference", "hydra_gate": "attention", "eco_gate": "attention", "lambda_e": 0.01, "gamma": 0.5,
        "dataset": {"frames": 200, "train_frames": 100, "test_frames": 100, "contexts": list(ctx)},
        "machine": {"cpu": "AMD EPYC", "threads": 2}, "singles": [], "methods": methods,
        "intervals": {"resamples": 100, "unit": "sequence", "seed": 0, "per_context": per},
        "hydra_table4": {}, "hydra_table6": {"optimal": {"wbf": {2: 0.5}}}, "energy_unit": "-",
        "regret": {"hydrafusion": {"attention": {"all": {"regret_map": 0.05, "differs_pct": 40.0,
                                                         "regret_interval": [0.01, 0.09]}}}},
        "fusion_regret": {},
        "bounds": {"context_oracle": {"choice": {"city": {"candidate": "single:radar"}, "fog": {"candidate": "late"}},
                                      "candidates": {"single:radar": ["radar"], "late": ["radar", "lidar"]}},
                   "room_for_context": room, "room_what": "context oracle minus all branches",
                   "optimistic": "chosen on test: optimistic.", "optimal_appendix": "not comparable.",
                   "a_posteriori": {"hydrafusion:optimal": A_POSTERIORI_LABEL, "ecofusion:loss_based": A_POSTERIORI_LABEL},
                   "coverage": {"sets": 4, "sequences_per_set": [4, 4, 4, 4], "resamples": 100, "pairs": {
                       "all_branches - late": {"covered": 3, "sets": 4, "expected_if_exact": 0.91, "spread_over_se": 1.2}}}}}}


def test_the_report_and_the_readme_block_name_each_bound_for_what_it_is(tmp_path):
    from study.report.bounds import add_coverage, add_optimal_appendix, add_room, main_methods
    from study.report.build import Doc

    report = _bounds_report()
    r = report["results"]
    doc = Doc()
    add_room(doc, r, "tag")
    add_coverage(doc, r, "tag")
    add_optimal_appendix(doc, r, "tag")
    md = doc.markdown(tmp_path)
    assert "Room for context" in md and "| all | per context | 0.050 | [+0.010, +0.090] | 0.020 |" in md
    assert "| city | single:radar |" in md and "chosen on test: optimistic." in md
    assert f"each an {A_POSTERIORI_LABEL}" in md
    assert "| all_branches - late | 3/4 | 0.910 | 1.200 |" in md
    assert "draws within each context, n of n" in md  # a report from before the designs: it drew so
    r["bounds"]["coverage"]["design"] = "sequence"
    doc = Doc()
    add_coverage(doc, r, "tag")
    assert "draws of whole sequences from all of the set's, as the reported intervals" in doc.markdown(tmp_path)
    assert "Appendix: HydraFusion's optimal gate" in md and "not comparable." in md
    assert "hydrafusion:optimal" not in main_methods(r) and CONTEXT_ORACLE in main_methods(r)
    s = verdict_sentences(report)
    assert not [x for x in s if "(oracle)" in x]
    assert any(f"ecofusion:loss_based ({A_POSTERIORI_LABEL}) [+0.020, +0.200]" in x for x in s)
    assert any(x.startswith(f"Room for context ({CONTEXT_ORACLE} ({CONTEXT_ORACLE_LABEL}) minus all_branches): overall "
                            "+0.050, 95 % interval [+0.010, +0.090]") for x in s)
    spec = importlib.util.spec_from_file_location("readme_results", ROOT / "scripts" / "readme_results.py")
    rr = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(rr)
    block = rr.results_block(report)
    assert f"| hydrafusion:optimal ({A_POSTERIORI_LABEL}) | 0.500 |" in block
    assert f"| ecofusion:loss_based ({A_POSTERIORI_LABEL}) | 0.470 |" in block
    assert f"| {CONTEXT_ORACLE} ({CONTEXT_ORACLE_LABEL}) | 0.460 |" in block
    assert "Room for context" in block and "every per-context order of this verdict (" in block
    assert "(95 % interval [+0.010, +0.090])" in block
    assert "room" not in " ".join(line for line in block.splitlines() if "a-posteriori" in line).lower()


def test_the_intervals_draw_by_the_declared_design_and_sequence_is_the_draws_they_always_had():
    """evaluate.interval: "sequence" (the default) gives exactly the draws of whole sequences from all
    test sequences the study always made, so a study keyed before the option existed reads the same;
    "stratified" keeps each context's count in every draw, "rescaled" draws one fewer of each; the
    front and the coverage record say which design they drew by."""
    from fusion.metrics import sequence_draws

    sm = _study_matches(seqs_per_context=6)
    rows = range(len(sm.contexts))
    assert list(sm.draws(rows, 7, 3)) == list(sequence_draws(sm.by_sequence(rows), 7, 3))
    per_ctx = {"x": 6, "y": 6}
    for design, less in (("stratified", 0), ("rescaled", 1)):
        for d in sm.draws(rows, 20, 3, design):
            seqs = [sm.sequences[r] for r in d]
            assert all(sum(1 for s in seqs[::4] if s.startswith(c)) == n - less for c, n in per_ctx.items())
    names = ["single:a", "late", "all_branches"]
    plain = sm.intervals(names, resamples=40)
    assert plain == sm.intervals(names, resamples=40, design="sequence") and plain["design"] == "sequence"
    strat = sm.intervals(names, resamples=40, design="stratified")
    # within one context the same interval (jackknife-t reads no draws)
    assert strat["per_context"]["x"]["map"] == plain["per_context"]["x"]["map"]
    assert strat["design"] == "stratified" and strat["per_context"]["all"] != plain["per_context"]["all"]
    with pytest.raises(ValueError, match="design"):
        sm.intervals(names, resamples=5, design="flat")
    cov = coverage_record(_study_matches(seqs_per_context=16), [("all_branches", "late")], resamples=20,
                          design="rescaled")
    assert cov["design"] == "rescaled"


def test_evaluate_interval_is_validated():
    from sim.errors import UserError
    from study.pipeline.config import EvaluateSection

    assert EvaluateSection().interval == "sequence"
    assert EvaluateSection(interval="rescaled").interval == "rescaled"
    with pytest.raises(UserError, match="evaluate.interval must be sequence, stratified, rescaled"):
        EvaluateSection(interval="flat")
