"""Compat mode against the ensemble-boxes 1.0.9 package itself, on hundreds of seeded random inputs.

Each case has 1-7 sources of 0-40 boxes, 1-4 classes, weights or not, and (in a share of the cases)
out-of-range corners, zero-area boxes, swapped corners and tied scores. Our compat output must be
the package's: the same detections (boxes and scores within 1e-6) - and, for NMS and Soft-NMS,
in the same order.
"""

from __future__ import annotations

import contextlib
import copy
import io
import warnings

import ensemble_boxes
import numpy as np
import pytest

from fusion.boxes import nms, soft_nms, weighted_boxes_fusion
from tests.fusion.boxes.boxgen import assert_same_detections, random_case

N_CASES = 300


def reference(fn, case, **params):
    """Run an ensemble-boxes function on deep copies (it overwrites its inputs), silencing its
    prints and warnings. None when it raises on an input without any usable box (its NMS
    concatenates an empty list)."""
    args = copy.deepcopy([case["boxes"], case["scores"], case["labels"]])
    weights = copy.deepcopy(case["weights"])
    with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            return fn(*args, weights=weights, **params)
        except ValueError as exc:
            assert "need at least one array to concatenate" in str(exc)
            return None


def cases(seed: int, n: int = N_CASES):
    rng = np.random.default_rng(seed)
    return [random_case(rng) for _ in range(n)]


def _check(ours, theirs, msg, ordered):
    if theirs is None:
        assert len(ours[1]) == 0, msg
        return
    assert_same_detections(ours, theirs, msg=msg)
    if ordered:
        np.testing.assert_allclose(ours[1], theirs[1], rtol=0, atol=1e-6, err_msg=msg + " (order)")
        np.testing.assert_array_equal(np.asarray(ours[2], float), np.asarray(theirs[2], float), err_msg=msg)


def test_nms_matches_ensemble_boxes():
    for k, case in enumerate(cases(1)):
        iou_thr = [0.3, 0.4, 0.5, 0.7][k % 4]
        ours = nms(case["boxes"], case["scores"], case["labels"], iou_thr=iou_thr, weights=case["weights"],
                   compat=True)
        _check(ours, reference(ensemble_boxes.nms, case, iou_thr=iou_thr), f"case {k}", ordered=True)


@pytest.mark.parametrize("method", [1, 2, 3])
def test_soft_nms_matches_ensemble_boxes(method):
    for k, case in enumerate(cases(10 + method, N_CASES // 2)):
        params = dict(method=method, iou_thr=[0.3, 0.4, 0.55][k % 3], sigma=[0.5, 0.1][k % 2],
                      thresh=[0.001, 0.05][(k // 2) % 2])
        ours = soft_nms(case["boxes"], case["scores"], case["labels"], weights=case["weights"], compat=True,
                        **params)
        _check(ours, reference(ensemble_boxes.soft_nms, case, **params), f"case {k} {params}", ordered=True)


@pytest.mark.parametrize("conf_type", ["avg", "max", "box_and_model_avg", "absent_model_aware_avg"])
def test_wbf_matches_ensemble_boxes(conf_type):
    n = N_CASES if conf_type == "avg" else N_CASES // 3
    for k, case in enumerate(cases(20 + len(conf_type), n)):
        params = dict(iou_thr=[0.4, 0.55, 0.3, 0.7][k % 4], skip_box_thr=[0.0, 0.01, 0.2][k % 3],
                      conf_type=conf_type, allows_overflow=k % 5 == 0)
        ours = weighted_boxes_fusion(case["boxes"], case["scores"], case["labels"], weights=case["weights"],
                                     compat=True, **params)
        _check(ours, reference(ensemble_boxes.weighted_boxes_fusion, case, **params), f"case {k} {params}",
               ordered=True)


def test_large_single_class_inputs():
    """Up to 7 x 150 boxes of one class: long inner loops, many suppressions per kept box."""
    rng = np.random.default_rng(5)
    for k in range(6):
        case = random_case(rng, max_boxes=150, messy=False)
        case["labels"] = [np.zeros(len(s), np.int64) for s in case["scores"]]
        for fn, ref, params in [
            (nms, ensemble_boxes.nms, dict(iou_thr=0.4)),
            (soft_nms, ensemble_boxes.soft_nms, dict(sigma=0.5, thresh=0.001)),
            (weighted_boxes_fusion, ensemble_boxes.weighted_boxes_fusion, dict(iou_thr=0.4, skip_box_thr=0.01)),
        ]:
            ours = fn(case["boxes"], case["scores"], case["labels"], weights=case["weights"], compat=True, **params)
            _check(ours, reference(ref, case, **params), f"{fn.__name__} case {k}", ordered=fn is not weighted_boxes_fusion)


def test_the_generator_produces_the_hard_cases():
    """The comparisons above are only as good as their inputs: check they contain what they claim."""
    cs = cases(1)
    n_boxes = [sum(len(b) for b in c["boxes"]) for c in cs]
    assert sum(c["swapped"] for c in cs) > 20
    assert sum(any((np.asarray(b) < 0).any() or (np.asarray(b) > 1).any() for b in c["boxes"]) for c in cs) > 20
    assert sum(any(len(b) and (b[:, 2] == b[:, 0]).any() for b in c["boxes"]) for c in cs) > 20
    assert sum(c["weights"] is not None for c in cs) > 100
    assert sum(n == 0 for n in n_boxes) >= 1 and max(n_boxes) > 150
    ties = sum(len(s) != len(np.unique(s)) for c in cs for s in [np.concatenate(c["scores"])])
    assert ties > 30
