"""The late-fusion benchmark runs and compares like with like (no timing is asserted)."""

from __future__ import annotations

import numpy as np
import pytest

from study.bench.boxes import (
    bench_box_fusion,
    compat_map_effect,
    same_detections,
    synthetic_detections,
    synthetic_scene,
)


def test_bench_reports_every_method_with_equal_outputs():
    r = bench_box_fusion(n_lists=3, n_boxes=30, repeats=1, rounds=1, seed=1)
    assert set(r["methods"]) == {"nms", "soft_nms", "wbf"}
    for name, m in r["methods"].items():
        assert m["equal_output"], name
        assert m["ours_ms"] > 0 and m["ensemble_boxes_ms"] > 0 and m["n_out"] > 0
        assert m["speedup"] == pytest.approx(m["ensemble_boxes_ms"] / m["ours_ms"], rel=0.05, abs=0.1)
    with pytest.raises(ValueError):
        bench_box_fusion(repeats=0)


def test_same_detections_is_order_free_but_not_blind():
    rng = np.random.default_rng(0)
    b, s, lab = synthetic_detections(rng, synthetic_scene(rng), n_lists=1, n_boxes=20)
    out = (b[0], s[0], lab[0])
    perm = rng.permutation(20)
    assert same_detections(out, (b[0][perm], s[0][perm], lab[0][perm]))
    moved = b[0].copy()
    moved[3, 0] += 1e-5
    assert not same_detections(out, (moved, s[0], lab[0]))
    assert not same_detections(out, (b[0][:-1], s[0][:-1], lab[0][:-1]))


def test_synthetic_detections_have_the_promised_shape():
    rng = np.random.default_rng(3)
    scene = synthetic_scene(rng, n_objects=30, n_classes=3)
    boxes, scores, labels = synthetic_detections(rng, scene, n_lists=7, n_boxes=100, n_classes=3)
    assert len(boxes) == 7 and all(b.shape == (100, 4) for b in boxes)
    assert all(((b >= 0) & (b <= 1)).all() and (b[:, 2:] >= b[:, :2]).all() for b in boxes)
    assert all(set(np.unique(lab)) <= {1, 2, 3} for lab in labels)
    assert all(((s >= 0) & (s <= 1)).all() for s in scores)


def test_compat_map_effect_reports_the_soft_nms_gap():
    r = compat_map_effect(n_images=6, seed=2)
    m = r["methods"]
    for name in m:
        for mode in ("textbook", "compat"):
            for w in ("no_weights", "equal_weights"):
                assert 0.0 <= m[name][mode][w]["map"] <= 1.0
    # the package's undecayed Soft-NMS scores rank suppressed duplicates high: mAP drops
    assert m["soft_nms"]["compat"]["no_weights"]["map"] < m["soft_nms"]["textbook"]["no_weights"]["map"] - 0.05
    # its weights divide every score by T: nothing passes a 0.5 cut-off, ranking (mAP) unchanged
    assert m["nms"]["compat"]["equal_weights"]["recall_at_score_thr"] == 0.0
    assert m["nms"]["compat"]["equal_weights"]["map"] == m["nms"]["textbook"]["equal_weights"]["map"]
    assert m["wbf"]["compat"]["no_weights"]["map"] == pytest.approx(m["wbf"]["textbook"]["no_weights"]["map"], abs=1e-3)
    assert 0 < r["single_list_map"] < m["wbf"]["textbook"]["no_weights"]["map"]
