"""NMS and Soft-NMS over the detections of several sources, per class (HydraFusion Sec. 4.4).

Same arguments as `ensemble_boxes.nms` / `ensemble_boxes.soft_nms` 1.0.9 (boxes normalised to
0..1, one list entry per source; the package calls the first three ``boxes, scores, labels``,
so only callers passing those by keyword need to rename them), plus a keyword-only `compat`
switch: ``compat=False`` (default) is the textbook behaviour, ``compat=True`` reproduces
ensemble-boxes where it deviates. Differences (their effect on mAP is measured by
`study.bench.boxes.compat_map_effect`; figures in BENCHMARKS.md):

- Soft-NMS scores: Bodla et al. return every kept box with its *decayed* score; ensemble-boxes
  decays scores only to decide which boxes pass `thresh` and returns the kept boxes with their
  *undecayed* scores, so a suppressed duplicate keeps the rank of the box that suppressed it.
- Weights: here a source's scores are multiplied by ``w_t / max(w)``, so equal weights change
  nothing; ensemble-boxes multiplies by ``w_t / sum(w)``, so ``weights=[1] * T`` divides every
  score by T (and ``weights=None`` does not).
- Soft-NMS ``method=3`` (hard): here hard suppression followed by the `thresh` filter, like the
  other methods; ensemble-boxes runs its plain NMS instead and ignores `thresh`.
- Output order: here best score first; ensemble-boxes returns class by class (ascending class id),
  in selection order within a class.
- Equal scores: here the box from the earlier source (then earlier row) wins; ensemble-boxes
  visits equal scores in the order of numba's quicksort, which compat mode reproduces.
- Boxes with x2 < x1 or y2 < y1: ValueError here; ensemble-boxes swaps the corners.
- Bad input: ValueError naming the field here (NaN, inf, negative scores, mismatched lengths,
  wrong weights, in both modes); ensemble-boxes prints a warning and ignores weights of the
  wrong length, crashes on empty input, and overwrites the caller's `scores` list entries when
  weights are given. Nothing here mutates its inputs or prints.

Shared by both modes (as in ensemble-boxes): coordinates are clipped to [0, 1], boxes with zero
area after clipping are dropped, classes are processed independently, IoU > iou_thr suppresses
(IoU == iou_thr does not), and the Gaussian Soft-NMS decays every overlapping box, whatever its
IoU (iou_thr is used only by the linear and hard methods). That is Bodla et al.'s Gaussian;
HydraFusion Sec. 4.4 describes it loosely as decaying boxes "above a threshold IoU value".
"""

from __future__ import annotations

import math

from fusion.boxes.inputs import check_range, flatten, label_keys, raise_bad_value
from fusion.boxes.kernels import nms_kernel, prepare_kernel, soft_nms_kernel


def _prepare(boxes_list, scores_list, labels_list, weights, compat):
    """Checked, clipped, weighted detections grouped by class (see kernels.prepare_kernel)."""
    flat = flatten(boxes_list, scores_list, labels_list, weights)
    w, scale = flat.weights, 1.0
    if flat.weighted and len(w):
        if compat:
            scale = float(w.sum())  # the package's (score * w_t) / sum(w)
        else:
            w = w / w.max()  # score * (w_t / max(w)): exactly the score when the weights are equal
    status, bad_row, rows, boxes, scores, _, starts = prepare_kernel(
        flat.boxes, flat.scores, label_keys(flat), flat.counts, w, scale, compat, -math.inf, False)
    raise_bad_value(flat, status, bad_row)
    return flat, rows, boxes, scores, starts


def nms(boxes_list, scores_list, labels_list, iou_thr=0.5, weights=None, *, compat=False):
    """Non-maximum suppression of the pooled detections of T sources, class by class.

    Args:
        boxes_list: T arrays (N_t, 4) [x1, y1, x2, y2], normalised image coordinates (0..1);
            coordinates outside [0, 1] are clipped, zero-area boxes dropped.
        scores_list: T arrays (N_t,), confidences (>= 0).
        labels_list: T arrays (N_t,), class ids.
        iou_thr: a box is suppressed by a better one of its class when their IoU is > iou_thr.
        weights: None or T per-source weights; scores are multiplied by ``w_t / max(w)``
            (compat: ``w_t / sum(w)``).
        compat: reproduce ensemble-boxes 1.0.9 (see the module docstring).

    Returns:
        boxes: (K, 4) float64 kept boxes (clipped).
        scores: (K,) float64 their (weighted) scores.
        labels: (K,) their class ids, dtype of the input labels.
        Best score first (compat: ascending class id, best first within a class).

    Raises:
        ValueError: naming the field for malformed input (see `fusion.boxes.inputs.flatten`).
    """
    iou_thr = check_range("iou_thr", iou_thr, 0.0, 1.0)
    flat, rows, boxes, scores, starts = _prepare(boxes_list, scores_list, labels_list, weights, compat)
    boxes, scores, kept = nms_kernel(boxes, scores, rows, starts, iou_thr, compat)
    return boxes, scores, flat.labels[kept]


def soft_nms(boxes_list, scores_list, labels_list, method=2, iou_thr=0.5, sigma=0.5, thresh=0.001,
             weights=None, *, compat=False):
    """Soft-NMS (Bodla et al. 2017) of the pooled detections of T sources, class by class.

    The best remaining box is selected, and every other box of its class has its score multiplied
    by f(IoU with it): method 2 (Gaussian, HydraFusion's choice with sigma 0.5)
    ``exp(-IoU^2 / sigma)``; method 1 (linear) ``1 - IoU`` when IoU > iou_thr; method 3 (hard)
    ``0`` when IoU > iou_thr. Boxes whose final score is > thresh are returned.

    Args:
        boxes_list: T arrays (N_t, 4) [x1, y1, x2, y2], normalised image coordinates (0..1);
            coordinates outside [0, 1] are clipped, zero-area boxes dropped.
        scores_list: T arrays (N_t,), confidences (>= 0).
        labels_list: T arrays (N_t,), class ids.
        method: 1 linear, 2 Gaussian, 3 hard.
        iou_thr: overlap above which the linear and hard methods decay (unused by Gaussian).
        sigma: Gaussian width (> 0), in IoU^2 units.
        thresh: boxes whose final (decayed) score is <= thresh are dropped.
        weights: None or T per-source weights; scores are multiplied by ``w_t / max(w)``
            (compat: ``w_t / sum(w)``).
        compat: reproduce ensemble-boxes 1.0.9 (see the module docstring).

    Returns:
        boxes: (K, 4) float64 kept boxes (clipped).
        scores: (K,) float64 their decayed scores, best first
            (compat: the undecayed weighted scores, ascending class id, selection order).
        labels: (K,) their class ids, dtype of the input labels.

    Raises:
        ValueError: naming the field for malformed input.
    """
    if method not in (1, 2, 3):
        raise ValueError(f"method must be 1 (linear), 2 (Gaussian) or 3 (hard), got {method!r}")
    iou_thr = check_range("iou_thr", iou_thr, 0.0, 1.0)
    sigma = check_range("sigma", sigma, 0.0, open_lo=True)
    thresh = check_range("thresh", thresh)
    if compat and method == 3:
        # ensemble-boxes runs its plain NMS for method 3: no decay, `thresh` ignored
        return nms(boxes_list, scores_list, labels_list, iou_thr=iou_thr, weights=weights, compat=True)
    flat, rows, boxes, scores, starts = _prepare(boxes_list, scores_list, labels_list, weights, compat)
    boxes, scores, kept = soft_nms_kernel(boxes, scores, rows, starts, int(method), iou_thr, sigma, thresh, compat)
    return boxes, scores, flat.labels[kept]
