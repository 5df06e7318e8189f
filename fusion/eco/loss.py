"""The fused loss L_f(phi) of one frame (EcoFusion Section 3.3), defined on fused detections.

The paper defines L_f as Faster R-CNN's classification (cross-entropy) + regression (smooth L1)
loss [19] "after the outputs of phi are fused via late fusion". Fused boxes have no logits, no
proposals and no sampled RoIs, so that loss is not defined for them as it stands. Here it is
defined explicitly on what fusion returns (boxes, one score, one label per box):

1. Matching, exactly as VOC AP@0.5 matches (fusion.metrics): detections of a class in descending
   score; each goes to the ground-truth box of its class it overlaps most; IoU >= `iou_thr` with an
   unclaimed box: a true positive that claims it; with a *difficult* box: ignored; otherwise (low
   IoU, or the box already claimed: a duplicate) a false positive.
2. Score term (cross-entropy, the fused score read as the probability of the predicted class):
   a true positive costs -ln(s), a false positive -ln(1 - s) (it should have been background).
3. Box term (smooth L1 of Faster R-CNN's box deltas [19], beta 1/9 as torchvision): for every true
   positive, dx = (cx - cx*) / w*, dy = (cy - cy*) / h*, dw = ln(w / w*), dh = ln(h / h*),
   summed over the four.
4. Miss term: every non-difficult ground-truth box no detection claimed costs `miss_cost`,
   by default -ln(0.05) + 1.07 = 4.07: what the worst true positive the branches can return costs
   (a score at their threshold 0.05, `box_score_thresh`, and the largest smooth-L1 box term an
   IoU >= 0.5 match allows, `MAX_MATCHED_BOX_TERM`), so finding an object never costs more than
   missing it (a first definition with 3.0 made a found object dearer than a missed one and
   ranked configurations against AP).

    L_f = (sum_TP [-ln s + w_box * SL1] + w_fp * sum_FP [-ln(1 - s)] + miss_cost * n_miss)
          / max(n_pos, 1)

with n_pos the non-difficult ground-truth boxes (the per-object normalisation of [19]; frames with
many objects do not dominate an average over frames). Scores are clamped to [1e-4, 1 - 1e-4] in
the logarithms. Lower is better; 0 only for a perfect frame (every object found at score 1 with an
exact box, nothing else).

`loss_terms` returns the parts (so variants can be scored without fusing again); `fused_loss`
their combination. Plain numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

TERMS = ("tp_ce", "box", "fp_ce", "n_miss", "n_pos", "n_tp", "n_fp")
MAX_MATCHED_BOX_TERM = 1.07
"""Largest sum of the four smooth-L1 box terms (beta 1/9) of any box with IoU >= 0.5 with its
ground truth (found numerically: 1.06 over 8 million random boxes; the test checks the bound)."""
"""The columns `loss_terms` returns, in order."""


@dataclass(frozen=True)
class FusedLossSpec:
    """Weights and thresholds of L_f (see the module docstring).

    Fields:
        iou_thr: [IoU] a detection matches a ground-truth box at or above this (VOC: 0.5).
        box_weight: [1] weight of the smooth-L1 box term.
        fp_weight: [1] weight of the false-positive cross-entropy.
        miss_cost: [nats] cost of a ground-truth box no detection found (-ln 0.05 + 1.07 by default).
        beta: smooth-L1 transition point (torchvision's Faster R-CNN: 1/9).
    """

    iou_thr: float = 0.5
    box_weight: float = 1.0
    fp_weight: float = 1.0
    miss_cost: float = -math.log(0.05) + MAX_MATCHED_BOX_TERM
    beta: float = 1.0 / 9.0

    def combine(self, terms: np.ndarray) -> np.ndarray:
        """L_f from `loss_terms` rows (..., len(TERMS)) -> (...)."""
        t = np.asarray(terms, np.float64)
        num = t[..., 0] + self.box_weight * t[..., 1] + self.fp_weight * t[..., 2] + self.miss_cost * t[..., 3]
        return num / np.maximum(t[..., 4], 1.0)


SCORE_CLAMP = 1e-4


def _iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w = np.clip(np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0]), 0, None)
    h = np.clip(np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1]), 0, None)
    inter = w * h
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    union = area_a[:, None] + area_b[None, :] - inter
    return np.divide(inter, union, out=np.zeros_like(inter), where=union > 0)


def smooth_l1(x: np.ndarray, beta: float) -> np.ndarray:
    """0.5 x^2 / beta for |x| < beta, |x| - 0.5 beta otherwise (torch.nn.functional.smooth_l1_loss)."""
    a = np.abs(x)
    return np.where(a < beta, 0.5 * a * a / beta, a - 0.5 * beta)


def box_deltas(det: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Faster R-CNN regression targets of boxes `det` relative to `gt` (both (N, 4) x1, y1, x2, y2)."""
    wd, hd = det[:, 2] - det[:, 0], det[:, 3] - det[:, 1]
    wg, hg = gt[:, 2] - gt[:, 0], gt[:, 3] - gt[:, 1]
    cxd, cyd = det[:, 0] + 0.5 * wd, det[:, 1] + 0.5 * hd
    cxg, cyg = gt[:, 0] + 0.5 * wg, gt[:, 1] + 0.5 * hg
    eps = 1e-6
    return np.stack([(cxd - cxg) / np.maximum(wg, eps), (cyd - cyg) / np.maximum(hg, eps),
                     np.log(np.maximum(wd, eps) / np.maximum(wg, eps)),
                     np.log(np.maximum(hd, eps) / np.maximum(hg, eps))], axis=1)


def match(boxes, scores, labels, gt_boxes, gt_labels, gt_difficult=None, iou_thr: float = 0.5):
    """VOC matching of one frame. Returns (status (D,) int: 1 true positive, 0 false positive,
    -1 ignored (matched a difficult box); matched ground-truth index (D,) or -1)."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    scores = np.asarray(scores, np.float64).reshape(-1)
    labels = np.asarray(labels).reshape(-1)
    gt_boxes = np.asarray(gt_boxes, np.float64).reshape(-1, 4)
    gt_labels = np.asarray(gt_labels).reshape(-1)
    difficult = np.zeros(len(gt_labels), bool) if gt_difficult is None else np.asarray(gt_difficult, bool)
    status = np.zeros(len(scores), np.int64)
    matched = np.full(len(scores), -1, np.int64)
    if not len(scores) or not len(gt_labels):
        return status, matched
    order = np.argsort(-scores, kind="stable")
    iou = _iou(boxes, gt_boxes)
    claimed = np.zeros(len(gt_labels), bool)
    same = labels[:, None] == gt_labels[None, :]
    for d in order:
        cand = np.where(same[d], iou[d], -1.0)
        g = int(np.argmax(cand))
        if cand[g] < iou_thr:
            continue  # false positive
        if difficult[g]:
            status[d] = -1
        elif not claimed[g]:
            claimed[g] = True
            status[d] = 1
            matched[d] = g
    return status, matched


def loss_terms(boxes, scores, labels, gt_boxes, gt_labels, gt_difficult=None,
               spec: FusedLossSpec | None = None) -> np.ndarray:
    """The parts of L_f for one frame's fused detections, in `TERMS` order:
    (sum of -ln s over true positives, sum of smooth-L1 box terms over true positives,
    sum of -ln(1 - s) over false positives, missed non-difficult boxes, non-difficult boxes,
    true positives, false positives)."""
    spec = spec or FusedLossSpec()
    scores = np.clip(np.asarray(scores, np.float64).reshape(-1), SCORE_CLAMP, 1.0 - SCORE_CLAMP)
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    gt_boxes = np.asarray(gt_boxes, np.float64).reshape(-1, 4)
    difficult = (np.zeros(len(gt_boxes), bool) if gt_difficult is None else np.asarray(gt_difficult, bool))
    status, matched = match(boxes, scores, labels, gt_boxes, gt_labels, difficult, spec.iou_thr)
    tp, fp = status == 1, status == 0
    tp_ce = float(-np.log(scores[tp]).sum())
    box = float(smooth_l1(box_deltas(boxes[tp], gt_boxes[matched[tp]]), spec.beta).sum()) if tp.any() else 0.0
    fp_ce = float(-np.log1p(-scores[fp]).sum())
    n_pos = int((~difficult).sum())
    n_tp = int(tp.sum())
    return np.array([tp_ce, box, fp_ce, n_pos - n_tp, n_pos, n_tp, int(fp.sum())], np.float64)


def fused_loss(boxes, scores, labels, gt_boxes, gt_labels, gt_difficult=None,
               spec: FusedLossSpec | None = None) -> float:
    """L_f of one frame (module docstring)."""
    spec = spec or FusedLossSpec()
    return float(spec.combine(loss_terms(boxes, scores, labels, gt_boxes, gt_labels, gt_difficult, spec)))
