"""study.report.verdict: the sentences say exactly what the stored intervals say (checked against the
committed cpu study's report, interval by interval, and on a small report whose answer is known),
an interval that holds 0 is never a win, oracles are never counted as wins, the wording is
deterministic, and the figure is written."""

import json
import re
from pathlib import Path

import pytest

from study.engine.scoring import difference_interval
from study.report.verdict import (
    ORACLES,
    answer_sentences,
    best_single,
    groups,
    orders,
    verdict_figure,
    verdict_sentences,
)

ROOT = Path(__file__).resolve().parents[2]
STUDY = ROOT / "results" / "study_cpu" / "report.json"


def _resolved(iv) -> int:
    return 0 if iv is None or iv[0] <= 0 <= iv[1] else (1 if iv[0] > 0 else -1)


def _where(g, per):
    return f"Overall ({per[g]['sequences']} test sequences)" if g == "all" else f"In {g} ({per[g]['sequences']} test sequences)"


def _sentence(sentences, start):
    hits = [s for s in sentences if s.startswith(start)]
    assert len(hits) == 1, (start, hits)
    return hits[0]


def _names_in(sentence: str) -> set[str]:
    body = re.sub(r" \[[^\]]*\]| \(oracle\)", "", sentence.split(": ", 1)[1]).rstrip(".)")
    return {part.strip() for part in re.split(r"; |, ", body)}


@pytest.fixture(scope="module")
def study():
    return json.loads(STUDY.read_text())


def test_each_sentence_of_the_cpu_study_agrees_with_its_stored_interval(study):
    r = study["results"]
    per = r["intervals"]["per_context"]
    singles = [f"single:{b}" for b in r["singles"]]
    sentences = verdict_sentences(study)
    assert sentences == verdict_sentences(study)  # deterministic
    assert verdict_sentences(r) == sentences  # the "results" part gives the same
    for g in groups(study):
        where = _where(g, per)
        diff = {m: difference_interval(per[g], m, "late") for m in r["methods"] if m != "late"}
        s_signs = [_resolved(diff[s]) for s in singles]
        if all(v < 0 for v in s_signs):
            _sentence(sentences, f"{where}, late fusion beats every single sensor")
            assert not [s for s in sentences if s.startswith(f"{where}, late fusion does not beat")]
        else:
            every = _sentence(sentences, f"{where}, late fusion does not beat every single sensor")
            assert _names_in(every) == {s for s, v in zip(singles, s_signs, strict=True) if v >= 0}
        others = [m for m in diff if m not in singles]
        above = _sentence(sentences, f"{where}, resolved above late fusion: ")
        below = _sentence(sentences, f"{where}, resolved below late fusion: ")
        want_above = {m for m in others if _resolved(diff[m]) > 0}
        want_below = {m for m in others if _resolved(diff[m]) < 0}
        assert (_names_in(above) if want_above else {"none"}) == (want_above or {"none"})
        assert (_names_in(below) if want_below else {"none"}) == (want_below or {"none"})
        unres = {m for m in others if _resolved(diff[m]) == 0}
        if unres:
            assert _names_in(_sentence(sentences, f"{where}, not resolved against late fusion")) == unres
        for m in want_above | want_below:  # each interval is quoted as stored
            lo, hi = diff[m]
            assert f"{m}{' (oracle)' if m in ORACLES else ''} [{lo + 0.0:+.3f}, {hi + 0.0:+.3f}]" in (above + below)
        best = best_single(study, g)
        iv = difference_interval(per[g], "late", best)
        word = {1: "resolved above", -1: "resolved below", 0: "not resolved against"}[_resolved(iv)]
        assert _sentence(sentences, f"{where}, late fusion is ").startswith(
            f"{where}, late fusion is {word} its best single sensor, {best}:")


def test_the_cpu_study_answer_opens_the_verdict(study):
    r = study["results"]
    per = r["intervals"]["per_context"]
    answer = answer_sentences(study)
    assert verdict_sentences(study)[:len(answer)] == answer
    # the stored overall intervals: every single sensor minus late lies below 0
    assert all(difference_interval(per["all"], f"single:{b}", "late")[1] < 0 for b in r["singles"])
    assert answer[0] == "Overall, late fusion beats every single sensor."
    # the second sentence names exactly the methods that run without ground truth and whose overall
    # interval against late fusion lies above 0 (in the stored study: all_branches and HydraFusion's
    # attention gate), in the report's order
    deployable = [m for m in r["methods"] if m not in ORACLES and not m.startswith(("single:", "early:"))
                  and m != "late"]
    above = [m for m in deployable if difference_interval(per["all"], m, "late")[0] > 0]
    assert above == ["all_branches", "hydrafusion:attention"]
    assert answer[1].startswith(f"Overall, {', '.join(above[:-1])} and {above[-1]} are resolved above late fusion")
    # ecofusion:loss_based is resolved above late overall, and it is named as the oracle it is
    assert difference_interval(per["all"], "ecofusion:loss_based", "late")[0] > 0
    assert answer[1].endswith("the oracle ecofusion:loss_based is.")


def _m(all_, a, b):
    return {"map": all_, "map_per_context": {"a": a, "b": b}}


SMALL = {"results": {
    "dataset": {"contexts": ["a", "b"]}, "singles": ["radar", "lidar"],
    "methods": {"single:radar": _m(0.2, 0.3, 0.1), "single:lidar": _m(0.3, 0.2, 0.4), "late": _m(0.35, 0.32, 0.38),
                "hydrafusion:attention": _m(0.40, 0.40, 0.39), "ecofusion:loss_based": _m(0.5, 0.5, 0.5)},
    "intervals": {"resamples": 100, "unit": "sequence", "seed": 0, "per_context": {
        "all": {"sequences": 20, "map": {}, "difference": {
            "single:radar - single:lidar": [-0.15, -0.05], "single:radar - late": [-0.2, -0.1],
            "single:lidar - late": [-0.1, -0.01], "late - hydrafusion:attention": [-0.08, -0.02],
            "late - ecofusion:loss_based": [-0.2, -0.1]}},
        "a": {"sequences": 10, "map": {}, "difference": {
            "single:radar - single:lidar": [0.02, 0.2], "single:radar - late": [-0.1, 0.0],
            "single:lidar - late": [-0.2, -0.05], "late - hydrafusion:attention": [-0.1, 0.02],
            "late - ecofusion:loss_based": [-0.3, -0.1]}},
        "b": {"sequences": 4, "map": {}, "difference": {
            "single:radar - single:lidar": [-0.4, -0.2], "single:radar - late": [-0.4, -0.2],
            "single:lidar - late": [0.01, 0.05], "late - hydrafusion:attention": [-0.02, 0.03],
            "late - ecofusion:loss_based": [-0.2, -0.05]}}}}}}


def test_a_small_report_whose_answer_is_known():
    s = verdict_sentences(SMALL)
    assert answer_sentences(SMALL) == [
        "Overall, late fusion beats every single sensor.",
        "Overall, hydrafusion:attention is resolved above late fusion; the oracle ecofusion:loss_based is.",
        "Per context, a fused method that runs without ground truth is resolved above late fusion in no context.",
        "Late fusion against its best single sensor per context: resolved above in no context; resolved below in "
        "b (single:lidar); not resolved in a.",
    ]
    assert "Overall (20 test sequences), resolved above late fusion: hydrafusion:attention [+0.020, +0.080]; " \
           "ecofusion:loss_based (oracle) [+0.100, +0.200]." in s
    assert "Overall (20 test sequences), resolved below late fusion: none." in s
    # an upper bound of exactly 0 holds 0: not resolved, never a win
    assert "In a (10 test sequences), late fusion does not beat every single sensor (not resolved below late: " \
           "single:radar [-0.100, +0.000])." in s
    assert "In a (10 test sequences), late fusion is not resolved against its best single sensor, single:radar: " \
           "late minus single:radar [-0.000, +0.100]." not in s  # negated zero prints as +0.000
    assert "In a (10 test sequences), late fusion is not resolved against its best single sensor, single:radar: " \
           "late minus single:radar [+0.000, +0.100]." in s
    assert "In a (10 test sequences), not resolved against late fusion (the interval holds 0): hydrafusion:attention." in s
    assert "In a (10 test sequences), among single sensors: single:radar above single:lidar [+0.020, +0.200]." in s
    assert "In b (4 test sequences), late fusion is resolved below its best single sensor, single:lidar: " \
           "late minus single:lidar [-0.050, -0.010]." in s
    assert "In b (4 test sequences), among single sensors: single:lidar above single:radar [+0.200, +0.400]." in s
    assert s[-1].startswith("Caution: b has fewer than 8 test sequences (down to 4); 4 sequences drawn "
                            "with replacement give only 35 distinct draws")
    kinds = {(o.group, o.a, o.b): o.sign for o in orders(SMALL)}
    assert kinds[("b", "single:lidar", "late")] == 1 and kinds[("a", "single:radar", "late")] == 0


def test_without_intervals_nothing_is_resolved(tmp_path):
    bare = {"results": {k: v for k, v in SMALL["results"].items() if k != "intervals"}}
    assert verdict_sentences(bare) == ["This study has no bootstrap intervals (evaluate.bootstrap = 0), so it "
                                       "resolves no order."]
    assert answer_sentences(bare) == [] and orders(bare) == []
    assert verdict_figure(bare, tmp_path / "v.png") is None and not (tmp_path / "v.png").exists()


def test_the_figure_is_written(tmp_path):
    out = verdict_figure(SMALL, tmp_path / "verdict.png")
    assert out == tmp_path / "verdict.png" and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_report_opens_with_the_answer_and_its_figure_and_ends_with_the_stages(tmp_path):
    """study.report.build.build on the stored cpu study: the answer (study.report.verdict) and the figure come before
    any table; the robustness table and the stage times follow the papers' tables."""
    import json
    from pathlib import Path

    from study.report.build import build
    from study.report.verdict import answer_sentences

    rep = json.loads((Path(__file__).parents[2] / "results/study_cpu/report.json").read_text())
    doc, _ = build(rep["results"], {"scale": "cpu", "stages": rep["stages"]}, tmp_path, tmp_path)
    md = doc.markdown(tmp_path)
    answer = md.index("## The answer")
    assert answer < md.index("|") and " ".join(answer_sentences(rep["results"])) in md
    assert (tmp_path / "verdict.png").stat().st_size > 10_000 and md.index("verdict.png") < md.index("|")
    assert md.index("## Robustness in the field's metrics") < md.index("## Stages")
    robust = md.split("## Robustness in the field's metrics")[1].split("\n## ")[0]
    late_row = next(line for line in robust.splitlines() if line.startswith("| late |"))
    assert late_row.split("|")[4].strip() == "1.000"  # late fusion is the mCE baseline: exactly 1
