"""VOC AP@0.5 (HydraFusion Sec. 5.3, Eq. 16-17): hand-computed cases and torchmetrics' COCO-style
evaluator as an independent reference."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fusion.metrics import average_precision, box_iou, evaluate_detections, mean_average_precision

A = [0.1, 0.1, 0.3, 0.3]
B = [0.6, 0.6, 0.9, 0.9]
C = [0.1, 0.6, 0.3, 0.9]
NOWHERE = [0.4, 0.0, 0.5, 0.05]


def det(boxes, scores, labels):
    return {"boxes": np.array(boxes, float).reshape(-1, 4), "scores": np.array(scores, float),
            "labels": np.array(labels)}


def gt(boxes, labels, difficult=None):
    out = {"boxes": np.array(boxes, float).reshape(-1, 4), "labels": np.array(labels)}
    if difficult is not None:
        out["difficult"] = np.array(difficult, bool)
    return out


# --- IoU ------------------------------------------------------------------------------------


def test_box_iou_known_values():
    half = [0.2, 0.1, 0.4, 0.3]  # A shifted by half its width: overlap 1/2 of each, IoU 1/3
    iou = box_iou([A, B], [A, half, B, [0.5, 0.5, 0.5, 0.7]])
    np.testing.assert_allclose(iou, [[1, 1 / 3, 0, 0], [0, 0, 1, 0]], atol=1e-12)
    assert box_iou(np.zeros((0, 4)), [A]).shape == (0, 1)
    assert box_iou([[0.2, 0.2, 0.2, 0.2]], [[0.2, 0.2, 0.2, 0.2]])[0, 0] == 0.0  # 0 / 0 defined as 0
    rng = np.random.default_rng(0)
    p = np.sort(rng.uniform(0, 1, (20, 2, 2)), axis=1).transpose(0, 2, 1).reshape(20, 4)[:, [0, 2, 1, 3]]
    q = p[::-1]
    np.testing.assert_allclose(box_iou(p, q), box_iou(q, p).T)
    assert ((box_iou(p, q) >= 0) & (box_iou(p, q) <= 1)).all()


# --- the AP formula ---------------------------------------------------------------------------


def test_average_precision_of_a_known_curve():
    # ranked detections TP, FP, FP, TP, TP with 3 positives
    tp = np.array([1, 0, 0, 1, 1])
    rec, prec = np.cumsum(tp) / 3, np.cumsum(tp) / np.arange(1, 6)
    # precision envelope: 1 up to R = 1/3, then max(0.5, 0.6) = 0.6 at 2/3 and 0.6 at 1
    assert average_precision(rec, prec) == pytest.approx(1 / 3 * 1 + 1 / 3 * 0.6 + 1 / 3 * 0.6)
    # VOC2007: recall points 0, .1, .2, .3 see precision 1; .4 ... 1.0 see 0.6
    assert average_precision(rec, prec, "11") == pytest.approx((4 * 1 + 7 * 0.6) / 11)
    # COCO: 34 points 0 ... 0.33 see 1, the 67 points 0.34 ... 1 see 0.6
    assert average_precision(rec, prec, "101") == pytest.approx((34 * 1 + 67 * 0.6) / 101)
    assert average_precision([], []) == 0.0
    with pytest.raises(ValueError, match="interpolation"):
        average_precision(rec, prec, "voc")


# --- hand-computed evaluations ----------------------------------------------------------------


def test_perfect_detector_scores_one():
    gts = [gt([A, B], [1, 2]), gt([C], [1]), gt([], [])]
    dets = [det([A, B], [0.9, 0.8], [1, 2]), det([C], [0.7], [1]), det([], [], [])]
    r = evaluate_detections(dets, gts)
    assert r.ap == {1: 1.0, 2: 1.0} and r.mean_ap == 1.0 and r.excluded == ()
    assert r.n_positives == {1: 2, 2: 1} and r.n_true_positives == {1: 2, 2: 1}


def test_known_precision_recall_curve_across_images():
    """3 cars in two images; ranked detections TP, FP, TP, FP, TP -> P 1, 1/2, 2/3, 1/2, 3/5 at
    R 1/3, 1/3, 2/3, 2/3, 1. Interpolated precision 1, 2/3, 3/5 on the three recall steps."""
    gts = [gt([A, B], [1, 1]), gt([C], [1])]
    dets = [det([A, NOWHERE, B], [0.95, 0.9, 0.6], [1, 1, 1]), det([C, NOWHERE], [0.8, 0.7], [1, 1])]
    r = evaluate_detections(dets, gts)
    expected = (1 / 3) * 1 + (1 / 3) * (2 / 3) + (1 / 3) * (3 / 5)
    assert r.ap[1] == pytest.approx(expected) and r.mean_ap == pytest.approx(expected)
    np.testing.assert_allclose(r.precision[1], [1, 1 / 2, 2 / 3, 1 / 2, 3 / 5])
    np.testing.assert_allclose(r.recall[1], [1 / 3, 1 / 3, 2 / 3, 2 / 3, 1])


def test_iou_threshold_is_inclusive_at_one_half():
    box = [0.25, 0.25, 0.75, 0.75]
    half = [0.25, 0.25, 0.75, 0.5]  # half of the box, inside it: IoU 0.125 / 0.25 = 0.5 exactly
    assert box_iou([half], [box])[0, 0] == 0.5
    assert evaluate_detections([det([half], [0.9], [1])], [gt([box], [1])]).ap[1] == 1.0
    assert evaluate_detections([det([half], [0.9], [1])], [gt([box], [1])], iou_thr=0.51).ap[1] == 0.0


def test_duplicates_are_false_positives():
    """Two detections of A, then B: TP, FP (duplicate), TP -> AP = 1/2 * 1 + 1/2 * 2/3."""
    gts = [gt([A, B], [1, 1])]
    dets = [det([A, A, B], [0.9, 0.8, 0.7], [1, 1, 1])]
    r = evaluate_detections(dets, gts)
    assert r.ap[1] == pytest.approx(0.5 + 0.5 * 2 / 3)
    assert r.n_true_positives[1] == 2 and r.n_detections[1] == 3


def test_a_detection_only_matches_its_best_box_even_if_claimed():
    """VOC rule: the second detection overlaps A most (claimed) and D (free) less; it is a FP."""
    d = [0.1, 0.1, 0.3, 0.36]  # IoU with A 0.77, with D 0.5
    D = [0.1, 0.2, 0.3, 0.4]
    r = evaluate_detections([det([A, d], [0.9, 0.8], [1, 1])], [gt([A, D], [1, 1])])
    assert box_iou([d], [A, D])[0, 0] > box_iou([d], [A, D])[0, 1] >= 0.5
    assert r.n_true_positives[1] == 1 and r.ap[1] == pytest.approx(0.5)


def test_difficult_boxes_are_neither_required_nor_penalised():
    # A normal, B difficult. Ranked: hit on B (ignored), FP elsewhere, hit on A -> FP, TP, n_pos 1.
    gts = [gt([A, B], [1, 1], difficult=[False, True])]
    dets = [det([B, NOWHERE, A], [0.9, 0.85, 0.8], [1, 1, 1])]
    r = evaluate_detections(dets, gts)
    assert r.n_positives[1] == 1 and r.ap[1] == pytest.approx(0.5)
    np.testing.assert_allclose(r.precision[1], [0, 0.5])  # the ignored detection is not on the curve
    # the same scene with B not difficult: TP, FP, TP over 2 positives
    r_plain = evaluate_detections(dets, [gt([A, B], [1, 1])])
    assert r_plain.ap[1] == pytest.approx(0.5 * 1 + 0.5 * 2 / 3)
    # missing a difficult box costs nothing
    assert evaluate_detections([det([A], [0.9], [1])], gts).ap[1] == 1.0
    # duplicates of a difficult box are ignored too
    assert evaluate_detections([det([B, B, A], [0.9, 0.8, 0.7], [1, 1, 1])], gts).ap[1] == 1.0


def test_classes_without_ground_truth_are_excluded_from_the_mean():
    gts = [gt([A, C], [1, 3], difficult=[False, True])]
    dets = [det([A, B, C], [0.9, 0.8, 0.7], [1, 2, 3])]
    r = evaluate_detections(dets, gts)
    assert r.ap[1] == 1.0 and math.isnan(r.ap[2]) and math.isnan(r.ap[3])
    assert r.excluded == (2, 3) and r.mean_ap == 1.0
    # `classes` restricts the evaluation; a requested class absent from the data is excluded too
    r = evaluate_detections(dets, gts, classes=[1, 4])
    assert set(r.ap) == {1, 4} and math.isnan(r.ap[4]) and r.excluded == (4,) and r.mean_ap == 1.0
    # a class with ground truth but no detection counts, with AP 0
    r = evaluate_detections([det([A], [0.9], [1])], [gt([A, B], [1, 4])])
    assert r.ap == {1: 1.0, 4: 0.0} and r.mean_ap == 0.5
    assert math.isnan(evaluate_detections([det([A], [0.9], [2])], [gt([], [])]).mean_ap)


def test_image_order_and_input_formats_do_not_matter():
    rng = np.random.default_rng(1)
    gts, dets = random_scenes(rng, n_images=6)
    r = evaluate_detections(dets, gts)
    perm = rng.permutation(len(gts))
    r_perm = evaluate_detections([dets[i] for i in perm], [gts[i] for i in perm])
    assert r.ap == r_perm.ap
    as_tuples = evaluate_detections([(d["boxes"], d["scores"], d["labels"]) for d in dets],
                                    [(g["boxes"], g["labels"]) for g in gts])
    assert as_tuples.ap == r.ap
    assert mean_average_precision(dets, gts) == r.mean_ap
    import torch  # locked dependencies: a broken install fails here, it is not skipped
    as_tensors = evaluate_detections([{k: torch.as_tensor(v) for k, v in d.items()} for d in dets],
                                     [{k: torch.as_tensor(v) for k, v in g.items()} for g in gts])
    assert as_tensors.ap == r.ap


@pytest.mark.parametrize("dets,gts,words", [
    ([det([A], [0.9], [1])], [], ["detections has 1 images", "ground_truths has 0"]),
    ([det([A], [0.9, 0.8], [1])], [gt([A], [1])], ["detections[0]['scores']", "2 entries for 1 boxes"]),
    ([{"boxes": [[0.1, 0.2, 0.3]], "scores": [0.9], "labels": [1]}], [gt([A], [1])], ["detections[0]['boxes']"]),
    ([det([A], [np.nan], [1])], [gt([A], [1])], ["detections[0]['scores']", "NaN"]),
    ([det([A], [0.9], [1.5])], [gt([A], [1])], ["detections[0]['labels']", "integer"]),
    ([det([A], [0.9], [1])], [gt([A], [1], difficult=[True, False])], ["ground_truths[0]['difficult']"]),
    ([{"boxes": [A], "labels": [1]}], [gt([A], [1])], ["detections[0]", "'scores'"]),
])
def test_bad_input_names_the_field(dets, gts, words):
    with pytest.raises(ValueError) as err:
        evaluate_detections(dets, gts)
    assert all(w in str(err.value) for w in words), str(err.value)


# --- against torchmetrics (COCO protocol) -------------------------------------------------------


def random_scenes(rng, n_images=8, n_classes=3):
    """Images with up to 9 objects, one per cell of a 3x3 grid (so no detection can overlap two
    objects with IoU >= 0.5, and VOC's and COCO's matching rules agree), detected with jitter,
    misses, duplicates and clutter; continuous scores (no ties)."""
    gts, dets = [], []
    for _ in range(n_images):
        cells = rng.permutation(9)[: rng.integers(0, 10)]
        centre = np.stack([(cells % 3 + 0.5) / 3, (cells // 3 + 0.5) / 3], 1) + rng.uniform(-0.05, 0.05, (len(cells), 2))
        half = rng.uniform(0.03, 0.11, (len(cells), 2))  # centre +- 0.05 +- 0.11 stays in its 1/3 cell
        boxes = np.hstack([centre - half, centre + half])
        labels = rng.integers(1, n_classes + 1, len(cells))
        gts.append({"boxes": boxes, "labels": labels})
        found = rng.random(len(cells)) < 0.8
        d = boxes[found] + rng.normal(0, 0.25, (found.sum(), 4)) * np.hstack([half, half])[found]
        dl = np.where(rng.random(found.sum()) < 0.9, labels[found], rng.integers(1, n_classes + 1, found.sum()))
        dup = rng.random(len(d)) < 0.3
        d = np.vstack([d, d[dup] + rng.normal(0, 0.01, (dup.sum(), 4))])
        dl = np.concatenate([dl, dl[dup]])
        n_fp = rng.integers(0, 6)
        c = rng.uniform(0.1, 0.9, (n_fp, 2))
        d = np.vstack([d, np.hstack([c - 0.05, c + 0.05])])
        dl = np.concatenate([dl, rng.integers(1, n_classes + 1, n_fp)])
        d = np.hstack([np.minimum(d[:, :2], d[:, 2:]), np.maximum(d[:, :2], d[:, 2:])])
        dets.append({"boxes": d, "scores": rng.uniform(0.05, 1.0, len(d)), "labels": dl})
    return gts, dets


def metric_inputs(torch, dets, gts):
    def tensors(d):
        return {k: torch.as_tensor(v, dtype=torch.int64 if k == "labels" else torch.float64) for k, v in d.items()}
    return [tensors(d) for d in dets], [tensors(g) for g in gts]


def test_map_agrees_with_torchmetrics():
    """torchmetrics' MeanAveragePrecision (pycocotools backend) is COCO's protocol: 101-point
    interpolation. With our "101" interpolation the two must agree to float precision, class by
    class. Our VOC all-point AP is the exact area under the same precision envelope; the 101-point
    mean differs from that area by at most 1/100 per class (the envelope is non-increasing, so
    each 0.01-wide recall strip is bounded by its two end samples), hence the 0.01 tolerance."""
    import torch  # locked dependencies: a broken install fails here, it is not skipped
    from torchmetrics import detection
    rng = np.random.default_rng(2024)
    for trial in range(4):
        gts, dets = random_scenes(rng, n_images=10)
        # torchmetrics' default recall points come from a float32 torch.linspace (0.3 becomes
        # 0.30000001), which moves a point past a recall of exactly 3/10; pycocotools and we use
        # float64 np.linspace, so pass those points explicitly
        metric = detection.MeanAveragePrecision(iou_thresholds=[0.5], class_metrics=True,
                                                rec_thresholds=np.linspace(0.0, 1.0, 101).tolist())
        metric.update(*metric_inputs(torch, dets, gts))
        ref = metric.compute()
        ref_per_class = dict(zip(ref["classes"].tolist(), ref["map_per_class"].tolist(), strict=True))
        coco = evaluate_detections(dets, gts, interpolation="101")
        voc = evaluate_detections(dets, gts)
        for cls, value in ref_per_class.items():
            if value < 0:  # torchmetrics' marker for a class without ground truth
                assert cls in coco.excluded
                continue
            assert coco.ap[cls] == pytest.approx(value, abs=1e-6), (trial, cls)
            assert abs(voc.ap[cls] - value) <= 0.01 + 1e-9, (trial, cls)
        assert coco.mean_ap == pytest.approx(float(ref["map"]), abs=1e-6)
        assert abs(voc.mean_ap - float(ref["map"])) <= 0.01 + 1e-9
        assert 0.2 < voc.mean_ap < 0.95  # the scenes are neither trivial nor hopeless

        # torchmetrics exactly as users construct it: its float32 recall points can add one more
        # 1/101 step per class where a recall is a multiple of 1/100, hence 0.02
        default = detection.MeanAveragePrecision(iou_thresholds=[0.5])
        default.update(*metric_inputs(torch, dets, gts))
        assert abs(voc.mean_ap - float(default.compute()["map"])) <= 0.02


def test_operating_point_counts_vehicle_hits_at_one_threshold_per_severity():
    """Recall / precision at score >= 0.5 over car, van, truck, bus, by hand: frame 0 (severity 3)
    has a car found at 0.9, a van missed (its detection scores 0.4), and a false car at 0.7; frame 1
    (severity 5) has a truck found twice (the duplicate is a false positive), a difficult bus whose
    detection is ignored, and a pedestrian (not a vehicle) that plays no part."""
    from fusion.late import Detections
    from sim.actors import CLASSES
    from study.engine.scoring import operating_point

    car, van, truck, bus, ped = (CLASSES.index(c) + 1 for c in ("car", "van", "truck", "bus", "pedestrian"))
    labels = {0: {"camera_right": {"boxes": [A, B], "labels": [car, van], "difficult": [False, False]}},
              1: {"camera_right": {"boxes": [A, B, C], "labels": [truck, bus, ped], "difficult": [False, True, False]}}}

    class Reader:
        def labels(self, i):
            return labels[i]

    def d(boxes, scores, cls):
        return Detections(np.array(boxes, float).reshape(-1, 4), np.array(scores, float), np.array(cls, np.int64))

    frames = [({"dataset_index": 0, "severity": 3}, d([A, B, C], [0.9, 0.4, 0.7], [car, van, car])),
              ({"dataset_index": 1, "severity": 5}, d([A, A, B, C], [0.8, 0.6, 0.9, 0.95], [truck, truck, bus, ped]))]
    op = operating_point(frames, Reader())
    assert op["positives"] == 3 and op["recall"] == round(2 / 3, 4)
    assert op["detections"] == 4 and op["precision"] == 0.5  # car hit, false car, truck hit, duplicate
    assert op["per_severity"]["3"] == {"recall": 0.5, "precision": 0.5, "positives": 2, "detections": 2}
    assert op["per_severity"]["5"] == {"recall": 1.0, "precision": 0.5, "positives": 1, "detections": 2}
    low = operating_point(frames, Reader(), threshold=0.3)  # the van's detection now counts
    assert low["per_severity"]["3"]["recall"] == 1.0


def test_recall_by_visibility_bins_objects_by_distance_over_mor_and_adds_up_to_the_operating_point():
    """By hand: frame 0 (MOR 100 m) has a car at 10 m found, a van at 40 m missed and a truck at
    80 m found; frame 1 (MOR 40 m) a car at 30 m found twice (one hit), a bus at 50 m that is
    difficult (not counted) and a car at 60 m missed. d / MOR: 0.1, 0.4, 0.8 | 0.75, 1.25, 1.5."""
    from fusion.late import Detections
    from sim.actors import CLASSES
    from study.engine.scoring import operating_point, recall_by_visibility

    car, van, truck, bus = (CLASSES.index(c) + 1 for c in ("car", "van", "truck", "bus"))
    D = [0.5, 0.1, 0.7, 0.3]  # overlaps no other box
    labels = {0: {"camera_right": {"boxes": [A, B, C], "labels": [car, van, truck], "difficult": [False] * 3,
                                   "distance_m": [10.0, 40.0, 80.0]}},
              1: {"camera_right": {"boxes": [A, B, D], "labels": [car, bus, car], "difficult": [False, True, False],
                                   "distance_m": [30.0, 50.0, 60.0]}}}

    class Reader:
        def labels(self, i):
            return labels[i]

    def d(boxes, scores, cls):
        return Detections(np.array(boxes, float).reshape(-1, 4), np.array(scores, float), np.array(cls, np.int64))

    frames = [({"dataset_index": 0, "weather": {"visibility_m": 100.0}}, d([A, B, C], [0.9, 0.3, 0.6], [car, van, truck])),
              ({"dataset_index": 1, "weather": {"visibility_m": 40.0}}, d([A, A, B], [0.9, 0.8, 0.7], [car, car, bus]))]
    r = recall_by_visibility(frames, Reader())
    assert list(r) == ["0-0.25", "0.25-0.5", "0.5-1", ">=1"]
    assert [(v["objects"], v["found"]) for v in r.values()] == [(1, 1), (1, 0), (2, 2), (1, 0)]
    assert r["0.5-1"]["recall"] == 1.0 and r[">=1"]["recall"] == 0.0
    assert r["0.25-0.5"]["contrast"] == [round(np.exp(-np.log(20) * 0.25), 4), round(np.exp(-np.log(20) * 0.5), 4)]
    assert r[">=1"]["contrast"] == [0.05, 0.0]
    op = operating_point([({**m, "severity": 1}, x) for m, x in frames], Reader())
    assert op["recall"] == round(sum(v["found"] for v in r.values()) / sum(v["objects"] for v in r.values()), 4)
    # binned by another visibility (a clear twin binned by its degraded frame's MOR)
    r2 = recall_by_visibility(frames, Reader(), visibility={0: 1000.0, 1: 1000.0})
    assert [v["objects"] for v in r2.values()] == [5, 0, 0, 0]


def test_matched_ground_truth_marks_exactly_the_true_positives_of_evaluate_detections():
    from fusion.metrics import evaluate_detections, matched_ground_truth

    rng = np.random.default_rng(3)
    for _ in range(30):
        dets, gts = [], []
        for _ in range(int(rng.integers(1, 5))):
            g = int(rng.integers(0, 6))
            xy = rng.uniform(0, 80, (g, 2))
            gb = np.c_[xy, xy + rng.uniform(5, 30, (g, 2))]
            gts.append({"boxes": gb, "labels": rng.integers(1, 4, g), "difficult": rng.random(g) < 0.2})
            n = int(rng.integers(0, 8))
            src = gb[rng.integers(0, g, n)] if g else rng.uniform(0, 80, (n, 4))
            db = src + rng.normal(0, 3, (n, 4)) if g else np.c_[src[:, :2], src[:, :2] + 10]
            dets.append({"boxes": db, "scores": rng.random(n), "labels": rng.integers(1, 4, n)})
        r = evaluate_detections(dets, gts)
        hits = matched_ground_truth(dets, gts)
        for c, tp in r.n_true_positives.items():
            assert tp == sum(int((h & (g["labels"] == c) & ~g["difficult"]).sum()) for h, g in zip(hits, gts))
        assert not any((h & g["difficult"]).any() for h, g in zip(hits, gts))


@pytest.mark.parametrize("interpolation", ["all", "11", "101"])
def test_image_matches_give_evaluate_detections_ap_for_any_draw_of_images(interpolation):
    """The bootstrap's AP (matching done once per image, pooled per draw) is evaluate_detections'
    AP on the drawn list of images, bit for bit: repeats, ties across and within images (scores
    rounded to 0.1), difficult boxes, duplicates, images without ground truth or detections."""
    from fusion.metrics import ImageMatches

    rng = np.random.default_rng(11)
    gts, dets = random_scenes(rng, n_images=12)
    for g, d in zip(gts, dets):
        g["difficult"] = rng.random(len(g["boxes"])) < 0.2
        d["scores"] = np.round(d["scores"], 1)  # ties
    dets[3] = {"boxes": np.zeros((0, 4)), "scores": np.zeros(0), "labels": np.zeros(0, int)}
    gts[5] = {"boxes": np.zeros((0, 4)), "labels": np.zeros(0, int), "difficult": np.zeros(0, bool)}
    m = ImageMatches.of(dets, gts, classes=[1, 2, 3], interpolation=interpolation)
    checked = 0
    for _ in range(40):
        picks = rng.integers(0, 12, int(rng.integers(1, 20)))
        ref = evaluate_detections([dets[i] for i in picks], [gts[i] for i in picks], classes=[1, 2, 3],
                                  interpolation=interpolation)
        ours = m.ap(picks)
        assert set(ours) == set(ref.ap)
        for c, v in ref.ap.items():
            assert (np.isnan(v) and np.isnan(ours[c])) or v == ours[c], (c, picks)
            checked += not np.isnan(v)
        assert (np.isnan(ref.mean_ap) and np.isnan(m.mean_ap(picks))) or ref.mean_ap == m.mean_ap(picks)
    assert checked > 60
    with pytest.raises(ValueError, match="iou_thr"):
        ImageMatches.of(dets, gts, iou_thr=1.5)


def test_draw_scorer_gives_the_pooled_map_of_every_draw():
    """Ranked once and weighted by each draw's multiplicities, the mAP is the pooled one (each
    draw's detections ranked again) on every draw: repeats, images drawn 0 times, difficult boxes,
    duplicates, images without ground truth or detections; continuous scores take the weighted
    path (no class falls back)."""
    from fusion.metrics import DrawScorer, ImageMatches

    rng = np.random.default_rng(5)
    gts, dets = random_scenes(rng, n_images=40)
    for g in gts:
        g["difficult"] = rng.random(len(g["boxes"])) < 0.2
    dets[3] = {"boxes": np.zeros((0, 4)), "scores": np.zeros(0), "labels": np.zeros(0, int)}
    gts[5] = {"boxes": np.zeros((0, 4)), "labels": np.zeros(0, int), "difficult": np.zeros(0, bool)}
    m = ImageMatches.of(dets, gts, classes=[1, 2, 3])
    scorer = DrawScorer(m)
    assert scorer.fallback_classes == []
    draws = [rng.integers(0, 40, int(rng.integers(1, 60))).tolist() for _ in range(150)] + [[5], [3, 3]]
    new, old = scorer.mean_ap(draws), np.array([m.mean_ap(d) for d in draws])
    assert np.array_equal(np.isnan(new), np.isnan(old)) and np.isnan(old).sum() >= 1
    np.testing.assert_allclose(new[~np.isnan(old)], old[~np.isnan(old)], rtol=0, atol=1e-12)
    per = scorer.ap(draws)
    for r in range(0, 150, 7):
        ref = m.ap(draws[r])
        for c in m.classes:
            assert (np.isnan(ref[c]) and np.isnan(per[c][r])) or per[c][r] == pytest.approx(ref[c], abs=1e-12)
    assert len({round(v, 9) for v in new[~np.isnan(new)]}) > 100  # the draws differ: a real test
    with pytest.raises(ValueError, match="interpolation"):
        DrawScorer(ImageMatches.of(dets, gts, interpolation="11"))


def test_draw_scorer_follows_the_draws_order_where_equal_scores_mix_true_and_false_positives():
    """A tie between a true and a false positive is visited in the draw's order of images, which
    changes the curve (TP first: AP 1; FP first: 1/2); such a class is scored per draw, exactly."""
    from fusion.metrics import DrawScorer, ImageMatches

    box = np.array([[0.1, 0.1, 0.3, 0.3]])
    gts = [{"boxes": box, "labels": [1]}, {"boxes": np.zeros((0, 4)), "labels": np.zeros(0, int)}]
    dets = [{"boxes": box, "scores": [0.5], "labels": [1]}, {"boxes": box, "scores": [0.5], "labels": [1]}]
    m = ImageMatches.of(dets, gts, classes=[1])
    scorer = DrawScorer(m)
    assert scorer.fallback_classes == [1]
    draws = [[0, 1], [1, 0], [1, 0, 0], [0, 1, 0]]
    np.testing.assert_allclose(scorer.mean_ap(draws), [m.mean_ap(d) for d in draws], atol=1e-12)
    assert scorer.mean_ap(draws)[:2].tolist() == [1.0, 0.5]
    rng = np.random.default_rng(2)  # many ties (scores to 0.1) over random scenes: still every draw's pooled mAP
    gts, dets = random_scenes(rng, n_images=20)
    for d in dets:
        d["scores"] = np.round(d["scores"], 1)
    m = ImageMatches.of(dets, gts, classes=[1, 2, 3])
    draws = [rng.integers(0, 20, 25).tolist() for _ in range(30)]
    np.testing.assert_allclose(DrawScorer(m).mean_ap(draws), [m.mean_ap(d) for d in draws], atol=1e-12)
