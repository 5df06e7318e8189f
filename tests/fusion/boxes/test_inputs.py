"""Bad input raises a ValueError that names the field; odd but valid input works."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.boxes import nms, soft_nms, weighted_boxes_fusion

METHODS = [nms, soft_nms, weighted_boxes_fusion]


def good(n_lists=3, n=4, seed=0):
    rng = np.random.default_rng(seed)
    c = rng.uniform(0.2, 0.8, (n_lists, n, 2))
    boxes = [np.hstack([ci - 0.1, ci + 0.1]) for ci in c]
    return boxes, [rng.uniform(0.1, 1, n) for _ in range(n_lists)], [rng.integers(0, 3, n) for _ in range(n_lists)]


def with_value(lists, which, t, i, value):
    out = [[x.copy() for x in lst] for lst in lists]
    if i is None:
        out[which][t] = value
    else:
        out[which][t][i] = value
    return out


BAD = [
    # (description, mutate(boxes, scores, labels) -> (boxes, scores, labels), expected words)
    ("scores list too short", lambda b, s, lab: (b, s[:-1], lab), ["scores_list", "2 entries", "3"]),
    ("labels list too long", lambda b, s, lab: (b, s, lab + [lab[0]]), ["labels_list", "4 entries"]),
    ("boxes with 3 columns", lambda b, s, lab: with_value((b, s, lab), 0, 1, None, b[1][:, :3]),
     ["boxes_list[1]", "(N, 4)"]),
    ("boxes 1-d", lambda b, s, lab: with_value((b, s, lab), 0, 2, None, b[2].ravel()), ["boxes_list[2]"]),
    ("one score short", lambda b, s, lab: with_value((b, s, lab), 1, 0, None, s[0][:-1]),
     ["scores_list[0]", "(4,)"]),
    ("labels 2-d", lambda b, s, lab: with_value((b, s, lab), 2, 1, None, lab[1][:, None]), ["labels_list[1]"]),
    ("NaN corner", lambda b, s, lab: with_value((b, s, lab), 0, 1, 2, [0.1, np.nan, 0.3, 0.4]),
     ["boxes_list[1][2]", "NaN"]),
    ("inf corner", lambda b, s, lab: with_value((b, s, lab), 0, 0, 0, [0.1, 0.1, np.inf, 0.4]),
     ["boxes_list[0][0]", "inf"]),
    ("NaN score", lambda b, s, lab: with_value((b, s, lab), 1, 2, 3, np.nan), ["scores_list[2][3]", "NaN"]),
    ("negative score", lambda b, s, lab: with_value((b, s, lab), 1, 1, 0, -0.5), ["scores_list[1][0]", "negative"]),
    ("NaN label", lambda b, s, lab: with_value((b, s, lab.copy()), 2, 0, None, np.array([1.0, np.nan, 2, 1])),
     ["labels_list[0][1]", "NaN"]),
    ("text scores", lambda b, s, lab: with_value((b, s, lab), 1, 0, None, ["a", "b", "c", "d"]), ["scores_list[0]"]),
    ("boolean labels", lambda b, s, lab: with_value((b, s, lab), 2, 0, None, np.ones(4, bool)), ["labels_list[0]"]),
]


@pytest.mark.parametrize("fn", METHODS)
@pytest.mark.parametrize("compat", [False, True])
@pytest.mark.parametrize("description,mutate,words", BAD, ids=[d for d, _, _ in BAD])
def test_bad_input_names_the_field(fn, compat, description, mutate, words):
    boxes, scores, labels = mutate(*good())
    with pytest.raises(ValueError) as err:
        fn(boxes, scores, labels, compat=compat)
    for word in words:
        assert word in str(err.value), (description, str(err.value))


@pytest.mark.parametrize("fn", METHODS)
@pytest.mark.parametrize("weights,words", [
    ([1.0, 1.0], ["weights", "one entry per source (3)"]),
    ([1.0, -1.0, 1.0], ["weights", ">= 0"]),
    ([1.0, np.nan, 1.0], ["weights", "finite"]),
    ([0.0, 0.0, 0.0], ["weights", "not all zero"]),
    ([[1.0, 1.0, 1.0]], ["weights"]),
])
def test_bad_weights_are_refused_in_both_modes(fn, weights, words):
    for compat in (False, True):
        with pytest.raises(ValueError) as err:
            fn(*good(), weights=weights, compat=compat)
        assert all(w in str(err.value) for w in words), str(err.value)


@pytest.mark.parametrize("fn,params,name", [
    (nms, {"iou_thr": 1.5}, "iou_thr"),
    (nms, {"iou_thr": -0.1}, "iou_thr"),
    (soft_nms, {"sigma": 0.0}, "sigma"),
    (soft_nms, {"thresh": float("nan")}, "thresh"),
    (soft_nms, {"method": 4}, "method"),
    (weighted_boxes_fusion, {"conf_type": "mean"}, "conf_type"),
    (weighted_boxes_fusion, {"skip_box_thr": "high"}, "skip_box_thr"),
    (weighted_boxes_fusion, {"iou_thr": float("nan")}, "iou_thr"),
])
def test_bad_parameters_name_themselves(fn, params, name):
    with pytest.raises(ValueError, match=name):
        fn(*good(), **params)


@pytest.mark.parametrize("fn", METHODS)
@pytest.mark.parametrize("value", [None, 3, "boxes"])
def test_lists_must_be_lists(fn, value):
    with pytest.raises(ValueError, match="boxes_list"):
        fn(value, [], [])


@pytest.mark.parametrize("fn", METHODS)
def test_swapped_corners_raise_by_default_and_are_swapped_in_compat(fn):
    boxes, scores, labels = good()
    b = boxes[1].copy()
    b[2] = b[2][[2, 1, 0, 3]]
    boxes[1] = b
    with pytest.raises(ValueError, match=r"boxes_list\[1\]\[2\].*x2 < x1"):
        fn(boxes, scores, labels)
    fixed = [x.copy() for x in boxes]
    fixed[1][2] = fixed[1][2][[2, 1, 0, 3]]
    got, expected = fn(boxes, scores, labels, compat=True), fn(fixed, scores, labels, compat=True)
    for x, y in zip(got, expected, strict=True):
        np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("fn", METHODS)
def test_plain_python_lists_and_int_scores_work(fn):
    boxes, scores, labels = good()
    as_lists = fn([b.tolist() for b in boxes], [s.tolist() for s in scores], [lab.tolist() for lab in labels])
    as_arrays = fn(boxes, scores, labels)
    for x, y in zip(as_lists, as_arrays, strict=True):
        np.testing.assert_array_equal(x, y)
    ones = fn(boxes, [np.ones(4, np.int64)] * 3, labels)
    assert ones[1].dtype == np.float64 and len(ones[1])


def test_float_labels_keep_their_values_and_compat_wbf_truncates_like_the_package():
    b = np.array([[0.1, 0.1, 0.4, 0.4]])
    args = ([b, b + 0.5], [np.array([0.9]), np.array([0.8])], [np.array([1.7]), np.array([1.2])])
    assert sorted(weighted_boxes_fusion(*args)[2].tolist()) == [1.2, 1.7]
    assert weighted_boxes_fusion(*args, compat=True)[2].tolist() == [1.0, 1.0]
    assert sorted(nms(*args, compat=True)[2].tolist()) == [1.2, 1.7]


def test_zero_confidence_boxes_are_ignored_by_wbf():
    """The package would make a NaN box of a cluster of zero-score boxes (0 / 0 in Eq. 15)."""
    b = np.array([[0.1, 0.1, 0.4, 0.4]])
    for compat in (False, True):
        boxes, scores, _ = weighted_boxes_fusion([b, b], [np.array([0.0]), np.array([0.0])],
                                                 [np.array([1]), np.array([1])], compat=compat)
        assert len(boxes) == 0 and not np.isnan(scores).any()
