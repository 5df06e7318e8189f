"""Properties of the late-fusion functions that follow from their definitions (HydraFusion Sec. 4.4,
Eq. 14-15; Bodla et al. 2017; Solovyev et al. 2021), in both modes."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fusion.boxes import FUSION_METHODS, HYDRAFUSION_PARAMS, nms, soft_nms, weighted_boxes_fusion
from tests.fusion.boxes.boxgen import assert_same_detections, canonical, random_case

METHODS = [nms, soft_nms, weighted_boxes_fusion]
MODES = [False, True]
FAST = settings(max_examples=60, deadline=None)


def iou(a, b) -> float:
    """HydraFusion Eq. 14 for two [x1, y1, x2, y2] boxes."""
    w = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    h = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = w * h
    return inter / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter)


@st.composite
def boxes_in_image(draw, min_side=0.01):
    x1 = draw(st.floats(0.0, 1.0 - min_side))
    y1 = draw(st.floats(0.0, 1.0 - min_side))
    x2 = draw(st.floats(x1 + min_side, 1.0))
    y2 = draw(st.floats(y1 + min_side, 1.0))
    return np.array([x1, y1, x2, y2])


scores_st = st.floats(0.01, 1.0)


# --- empty and trivial inputs ----------------------------------------------------------------


@pytest.mark.parametrize("fn", METHODS)
@pytest.mark.parametrize("compat", MODES)
@pytest.mark.parametrize("inputs", [
    ([], [], []),
    ([[]], [[]], [[]]),
    ([np.zeros((0, 4))] * 3, [np.zeros(0)] * 3, [np.zeros(0, np.int64)] * 3),
])
def test_empty_inputs_give_empty_outputs(fn, compat, inputs):
    boxes, scores, labels = fn(*inputs, compat=compat)
    assert boxes.shape == (0, 4) and scores.shape == (0,) and labels.shape == (0,)


@FAST
@given(box=boxes_in_image(), score=scores_st, label=st.integers(0, 7), n_lists=st.integers(1, 7),
       where=st.integers(0, 6))
def test_a_single_box_comes_back(box, score, label, n_lists, where):
    where %= n_lists
    boxes = [np.zeros((0, 4)) for _ in range(n_lists)]
    scores = [np.zeros(0) for _ in range(n_lists)]
    labels = [np.zeros(0, np.int64) for _ in range(n_lists)]
    boxes[where], scores[where], labels[where] = box[None], np.array([score]), np.array([label])
    for compat in MODES:
        for fn, expected in [(nms, score), (soft_nms, score), (weighted_boxes_fusion, score / n_lists)]:
            b, s, lab = fn(boxes, scores, labels, compat=compat)
            np.testing.assert_allclose(b, box[None], atol=1e-7)  # float32 rounding in compat WBF
            np.testing.assert_allclose(s, [expected], rtol=1e-12)
            assert lab.tolist() == [label]


@FAST
@given(box=boxes_in_image(), scores=st.lists(scores_st, min_size=1, max_size=7, unique=True),
       sigma=st.sampled_from([0.5, 0.3, 1.0]))
def test_identical_boxes_from_every_source(box, scores, sigma):
    n = len(scores)
    args = ([box[None].copy() for _ in scores], [np.array([s]) for s in scores], [np.array([3])] * n)
    ranked = sorted(scores, reverse=True)
    for compat in MODES:
        b, s, _ = nms(*args, compat=compat)  # IoU 1 > any threshold: only the best survives
        np.testing.assert_allclose(b, box[None]) and np.testing.assert_allclose(s, [ranked[0]])

        # Gaussian Soft-NMS: each selection multiplies every remaining score by exp(-1 / sigma),
        # so the k-th box (k = 0, 1, ...) comes out at s_(k) exp(-k / sigma).
        b, s, _ = soft_nms(*args, sigma=sigma, thresh=0.0, compat=compat)
        decayed = [r * math.exp(-k / sigma) for k, r in enumerate(ranked)]
        np.testing.assert_allclose(np.sort(s)[::-1], ranked if compat else decayed, rtol=1e-12)
        np.testing.assert_allclose(b, np.repeat(box[None], n, 0))

        # WBF: one cluster with all T boxes; its box is the box, its score the mean score.
        b, s, _ = weighted_boxes_fusion(*args, compat=compat)
        np.testing.assert_allclose(b, box[None], atol=1e-7)
        np.testing.assert_allclose(s, [np.mean(scores)], rtol=1e-6 if compat else 1e-12)


@pytest.mark.parametrize("compat", MODES)
def test_classes_never_interact(compat):
    box = np.array([[0.1, 0.1, 0.5, 0.5]])
    args = ([box, box, box], [np.array([0.9]), np.array([0.8]), np.array([0.7])],
            [np.array([1]), np.array([2]), np.array([3])])
    for fn in METHODS:
        b, s, lab = fn(*args, compat=compat)
        assert sorted(lab.tolist()) == [1, 2, 3], fn.__name__


# --- degenerate and out-of-range boxes -------------------------------------------------------


@pytest.mark.parametrize("fn", METHODS)
@pytest.mark.parametrize("compat", MODES)
def test_zero_area_boxes_are_dropped(fn, compat):
    rng = np.random.default_rng(7)
    for _ in range(40):
        case = random_case(rng, messy=False)
        with_degenerate = copy.deepcopy(case)
        for t, b in enumerate(with_degenerate["boxes"]):
            x = rng.uniform(0, 1, (3, 1))
            flat = np.hstack([x, x + 0.1, x, x + 0.3])  # x1 == x2: zero width
            line = np.hstack([x, x, x + 0.2, x])  # y1 == y2: zero height
            with_degenerate["boxes"][t] = np.vstack([b, flat, line])
            with_degenerate["scores"][t] = np.concatenate([case["scores"][t], [0.99] * 6])
            with_degenerate["labels"][t] = np.concatenate([case["labels"][t], [0] * 6]).astype(case["labels"][t].dtype)
        expected = fn(case["boxes"], case["scores"], case["labels"], weights=case["weights"], compat=compat)
        got = fn(with_degenerate["boxes"], with_degenerate["scores"], with_degenerate["labels"],
                 weights=case["weights"], compat=compat)
        assert_same_detections(got, expected, atol=0.0)


@FAST
@given(data=st.data())
def test_out_of_range_boxes_act_as_their_clipped_part(data):
    seed = data.draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    case = random_case(rng, messy=False, max_lists=4, max_boxes=15)
    wide = [b.copy() for b in case["boxes"]]
    for b in wide:  # push corners outside the image; a box fully outside becomes empty
        b[:, :2] -= rng.uniform(0, 0.5, (len(b), 2)) * (rng.random((len(b), 1)) < 0.5)
        b[:, 2:] += rng.uniform(0, 0.5, (len(b), 2)) * (rng.random((len(b), 1)) < 0.5)
        outside = rng.random(len(b)) < 0.1
        b[outside] = [1.2, 0.3, 1.5, 0.6]
    clipped = [np.clip(b, 0, 1) for b in wide]
    for fn in METHODS:
        for compat in MODES:
            got = fn(wide, case["scores"], case["labels"], compat=compat)
            expected = fn(clipped, case["scores"], case["labels"], compat=compat)
            assert_same_detections(got, expected, atol=0.0, msg=fn.__name__)
            slack = 1e-6 if compat else 0.0  # compat WBF rounds fused boxes to float32, like the package
            assert ((got[0] >= -slack) & (got[0] <= 1 + slack)).all()


# --- WBF: HydraFusion Eq. 15 written out ----------------------------------------------------


@settings(max_examples=80, deadline=None)
@given(data=st.data())
def test_wbf_box_is_the_confidence_weighted_mean(data):
    """Objects in separate cells of a 3x3 grid, each seen by every source with a small jitter, so
    each object is one cluster. Eq. 15: f = sum(C_i b_i) / sum(C_i) with C_i = w_t * s_i; the
    cluster's score is sum(C_i) / n * min(T, n) / sum(w) (WBF paper's rescaling)."""
    n_lists = data.draw(st.integers(1, 7))
    cells = data.draw(st.lists(st.integers(0, 8), min_size=1, max_size=9, unique=True))
    weights = data.draw(st.none() | st.lists(st.floats(0.1, 5.0), min_size=n_lists, max_size=n_lists))
    seed = data.draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    w = np.ones(n_lists) if weights is None else np.array(weights)
    truth = []
    for c in cells:
        cx, cy = (c % 3 + 0.5) / 3, (c // 3 + 0.5) / 3
        truth.append(np.array([cx - 0.1, cy - 0.1, cx + 0.1, cy + 0.1]))
    boxes = [np.array([t + rng.uniform(-0.005, 0.005, 4) for t in truth]) for _ in range(n_lists)]
    scores = [rng.uniform(0.05, 1.0, len(cells)) for _ in range(n_lists)]
    labels = [np.full(len(cells), 2) for _ in range(n_lists)]

    expected_boxes, expected_scores = [], []
    for k in range(len(cells)):
        c = np.array([w[t] * scores[t][k] for t in range(n_lists)])  # C_i
        b = np.array([boxes[t][k] for t in range(n_lists)])
        expected_boxes.append((c[:, None] * b).sum(0) / c.sum())  # Eq. 15, both corners
        expected_scores.append(c.sum() / n_lists * min(n_lists, n_lists) / w.sum())
    expected = (np.array(expected_boxes), np.array(expected_scores), np.full(len(cells), 2))

    for compat, atol in [(False, 1e-12), (True, 1e-6)]:
        got = weighted_boxes_fusion(boxes, scores, labels, weights=weights, iou_thr=0.55, compat=compat)
        assert_same_detections(got, expected, atol=atol)


def test_wbf_cluster_missing_sources_is_demoted():
    """A box only one of three sources reports keeps its place but scores min(T, 1) / T of it."""
    b = np.array([[0.1, 0.1, 0.3, 0.3]])
    got = weighted_boxes_fusion([b, np.zeros((0, 4)), np.zeros((0, 4))], [np.array([0.9]), [], []],
                                [np.array([1]), [], []])
    np.testing.assert_allclose(got[1], [0.9 / 3])


# --- Soft-NMS decay and the weights: where compat differs ------------------------------------


@FAST
@given(shift=st.floats(0.0, 0.15), s1=st.floats(0.5, 1.0), ratio=st.floats(0.1, 0.99),
       sigma=st.sampled_from([0.5, 0.25]), method=st.sampled_from([1, 2]))
def test_soft_nms_decays_the_weaker_box(shift, s1, ratio, sigma, method):
    a, b = np.array([0.2, 0.2, 0.5, 0.5]), np.array([0.2 + shift, 0.2, 0.5 + shift, 0.5])
    s2 = s1 * ratio
    u = iou(a, b)
    factor = math.exp(-u * u / sigma) if method == 2 else (1 - u if u > 0.3 else 1.0)
    args = ([a[None], b[None]], [np.array([s1]), np.array([s2])], [np.array([0]), np.array([0])])
    _, s, _ = soft_nms(*args, method=method, iou_thr=0.3, sigma=sigma, thresh=-1.0)  # keep all
    np.testing.assert_allclose(s, [s1, s2 * factor], rtol=1e-12)  # textbook: decayed, best first
    _, s, _ = soft_nms(*args, method=method, iou_thr=0.3, sigma=sigma, thresh=-1.0, compat=True)
    np.testing.assert_allclose(s, [s1, s2], rtol=1e-12)  # ensemble-boxes: undecayed


def test_soft_nms_method_3_in_compat_is_plain_nms():
    """ensemble-boxes routes method 3 to its NMS, so `thresh` is ignored there (and only there)."""
    args = ([np.array([[0.1, 0.1, 0.4, 0.4], [0.6, 0.6, 0.9, 0.9]])], [np.array([0.5, 0.004])], [np.array([1, 1])])
    assert len(soft_nms(*args, method=3, thresh=0.01)[1]) == 1
    assert len(soft_nms(*args, method=3, thresh=0.01, compat=True)[1]) == 2


@pytest.mark.parametrize("fn", METHODS)
def test_equal_weights_are_no_weights(fn):
    rng = np.random.default_rng(3)
    for _ in range(30):
        case = random_case(rng, messy=False)
        n = len(case["boxes"])
        plain = fn(case["boxes"], case["scores"], case["labels"])
        for w in ([1.0] * n, [2.5] * n):
            assert_same_detections(fn(case["boxes"], case["scores"], case["labels"], weights=w), plain, atol=1e-12)


@pytest.mark.parametrize("fn", [nms, soft_nms])
def test_compat_weights_divide_scores_by_their_sum(fn):
    """ensemble-boxes multiplies each source's scores by w_t / sum(w): equal weights divide by T."""
    case = random_case(np.random.default_rng(4), messy=False, max_lists=5)
    n = len(case["boxes"])
    plain = fn(case["boxes"], case["scores"], case["labels"], compat=True)
    weighted = fn(case["boxes"], case["scores"], case["labels"], weights=[1.0] * n, compat=True, **(
        {"thresh": 0.0} if fn is soft_nms else {}))
    if fn is soft_nms:
        plain = fn(case["boxes"], case["scores"], case["labels"], thresh=0.0, compat=True)
    np.testing.assert_allclose(np.sort(weighted[1]), np.sort(plain[1]) / n, rtol=1e-12)


def test_weights_scale_sources_relative_to_the_heaviest():
    b = np.array([[0.1, 0.1, 0.3, 0.3]])
    far = np.array([[0.6, 0.6, 0.8, 0.8]])
    args = ([b, far], [np.array([0.8]), np.array([0.8])], [np.array([1]), np.array([1])])
    _, s, _ = nms(*args, weights=[2.0, 1.0])
    np.testing.assert_allclose(np.sort(s), [0.4, 0.8])
    _, s, _ = nms(*args, weights=[2.0, 1.0], compat=True)
    np.testing.assert_allclose(np.sort(s), [0.8 / 3, 1.6 / 3])


# --- invariants ----------------------------------------------------------------------------


@pytest.mark.parametrize("fn", METHODS)
def test_source_order_does_not_matter(fn):
    rng = np.random.default_rng(11)
    for _ in range(30):
        case = random_case(rng, messy=False)
        while has_ties(case):
            case = random_case(rng, messy=False)  # ties would make the choice order-dependent
        n = len(case["boxes"])
        perm = rng.permutation(n)
        w = case["weights"]
        got = fn([case["boxes"][i] for i in perm], [case["scores"][i] for i in perm],
                 [case["labels"][i] for i in perm], weights=None if w is None else [w[i] for i in perm])
        assert_same_detections(got, fn(case["boxes"], case["scores"], case["labels"], weights=w), atol=1e-12)


@pytest.mark.parametrize("fn", METHODS)
def test_default_output_is_best_first_and_inputs_are_untouched(fn):
    rng = np.random.default_rng(12)
    for _ in range(20):
        case = random_case(rng)
        if case["swapped"]:
            continue
        before = copy.deepcopy(case)
        boxes, scores, labels = fn(case["boxes"], case["scores"], case["labels"], weights=case["weights"])
        assert (np.diff(scores) <= 0).all()
        assert labels.dtype == np.concatenate(case["labels"]).dtype
        for key in ("boxes", "scores", "labels"):
            for x, y in zip(case[key], before[key], strict=True):
                np.testing.assert_array_equal(x, y)
        if fn is not weighted_boxes_fusion:
            # NMS keeps input boxes: every output row is one of the (clipped) inputs
            pool = np.concatenate([np.clip(b, 0, 1) for b in case["boxes"]])
            assert all(np.isclose(pool, row, atol=0).all(1).any() for row in boxes)


def has_ties(case) -> bool:
    s = np.concatenate(case["scores"]) if case["scores"] else np.zeros(0)
    return len(np.unique(s)) != len(s)


def test_nms_default_and_compat_keep_the_same_boxes():
    """Without weights, the modes differ only in output order and in how equal scores are visited."""
    rng = np.random.default_rng(13)
    for _ in range(50):
        case = random_case(rng, messy=False)
        if has_ties(case):
            continue
        case["weights"] = None
        assert_same_detections(nms(case["boxes"], case["scores"], case["labels"]),
                               nms(case["boxes"], case["scores"], case["labels"], compat=True), atol=0.0)


def test_nms_keeps_no_pair_above_the_threshold():
    rng = np.random.default_rng(14)
    for _ in range(50):
        case = random_case(rng, messy=False)
        thr = rng.uniform(0.1, 0.9)
        boxes, _, labels = nms(case["boxes"], case["scores"], case["labels"], iou_thr=thr)
        for i in range(len(boxes)):
            for j in range(i + 1, len(boxes)):
                if labels[i] == labels[j]:
                    assert iou(boxes[i], boxes[j]) <= thr


def test_registry_entries_run_with_hydrafusion_parameters():
    case = random_case(np.random.default_rng(15), messy=False)
    assert set(FUSION_METHODS.names()) == {"nms", "soft_nms", "wbf"} == set(HYDRAFUSION_PARAMS)
    for name, fn in FUSION_METHODS.items():
        boxes, scores, labels = fn(case["boxes"], case["scores"], case["labels"], weights=case["weights"],
                                   **HYDRAFUSION_PARAMS[name])
        assert boxes.shape == (len(scores), 4) and labels.shape == scores.shape
        assert len(canonical((boxes, scores, labels))) == len(scores)
