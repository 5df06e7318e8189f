"""The test-split guard: every choice the study makes from data goes through `SelectionLog`, which
refuses test frames; the study's validation frames are wired through it."""

from types import SimpleNamespace

import pytest

from study.selection import SelectionLog, TestSplitLeak


def test_a_choice_on_validation_frames_is_recorded_with_its_candidates():
    log = SelectionLog.of([10, 11, 12])
    pick = log.choose("late-fusion method", {"nms": 0.30, "soft_nms": 0.31, "wbf": None}, [1, 2, 3],
                      lower_is_better=False, measure="mAP", sequences=1)
    assert pick == "soft_nms"
    assert log.choose("epoch", {"a": 0.2, "b": 0.1}, [4], lower_is_better=True, measure="regret") == "b"
    assert log.choose("tie", {"x": 1.0, "y": 1.0}, [4], lower_is_better=True, measure="m") == "x"  # first wins
    c = log.choices[0]
    assert c["on"] == "validation" and c["frames"] == 3 and c["sequences"] == 1 and c["chosen"] == "soft_nms"
    assert c["candidates"] == {"nms": 0.3, "soft_nms": 0.31, "wbf": None}


@pytest.mark.parametrize("indices", [[10], [1, 2, 12], range(9, 13)])
def test_any_test_frame_among_the_choice_frames_is_refused(indices):
    log = SelectionLog.of([10, 11, 12])
    with pytest.raises(TestSplitLeak, match="test frames"):
        log.choose("late-fusion method", {"nms": 0.3}, indices, lower_is_better=False, measure="mAP")
    with pytest.raises(TestSplitLeak):
        log.record("objective", "mae", indices, "regret")
    assert log.choices == []


def test_no_frames_and_no_values_are_errors_not_silent_choices():
    log = SelectionLog.of([5])
    with pytest.raises(TestSplitLeak, match="no validation frames"):
        log.check([], "fusion")
    with pytest.raises(ValueError, match="no candidate"):
        log.choose("fusion", {"nms": None}, [1], lower_is_better=False, measure="mAP")


def test_the_study_validation_frames_pass_the_guard(monkeypatch):
    """study_eval.ValidationFrames reads the validation split through the guard: a split that hands
    it a test frame (a bug in the carve) stops the evaluation before anything is scored."""
    import study.selection as selection
    from study.study_eval import ValidationFrames

    manifest = {"frames": [{"context": "fog", "shard": f"s{i // 2}"} for i in range(12)]}
    ev = SimpleNamespace(reader=SimpleNamespace(manifest=manifest), train=list(range(8)), test=[8, 9, 10, 11])
    log = SelectionLog.of(ev.test)
    monkeypatch.setattr(selection, "validation_split", lambda reader, idx, fraction, seed: (list(idx), [7, 8]))
    with pytest.raises(TestSplitLeak, match="validation frames"):
        ValidationFrames(ev, 0.15, 0, log)
