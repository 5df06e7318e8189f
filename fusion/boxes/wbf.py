"""Weighted Boxes Fusion over the detections of several sources (HydraFusion Sec. 4.4, Eq. 15).

Same arguments as `ensemble_boxes.weighted_boxes_fusion` 1.0.9 plus a keyword-only `compat`
switch. The clustering and the confidence rules are the package's (which are the WBF paper's):
per class, boxes are visited best weighted score first (C_i = w_t * score_i); each joins the
cluster whose current fused box it overlaps most if that IoU is > iou_thr. A cluster's box is
the C-weighted mean of its members (Eq. 15); its confidence, for ``conf_type='avg'``, is
``mean(C_i) * min(T, n) / sum(w)`` for n members of T sources (``n / sum(w)`` with
allows_overflow), so clusters that few sources agree on are demoted.

Differences from ensemble-boxes (``compat=True`` reproduces it):

- Precision: ensemble-boxes accumulates fused boxes and their confidences in float32 (and later
  matches against the rounded boxes); here float64. Effect: ~1e-7 on coordinates.
- Labels: ensemble-boxes truncates them with ``int()`` (1.7 -> 1) and returns float64; here
  classes are the given values, returned with the input dtype.
- Output order: both best first; ties in score are kept in cluster order here.
- Boxes with x2 < x1 or y2 < y1: ValueError here; ensemble-boxes swaps the corners.
- Out-of-range corners are clipped silently here; ensemble-boxes issues one `warnings.warn` per
  corner, which also costs time.
- Bad input: ValueError naming the field here, in both modes (NaN, inf, negative scores,
  mismatched lengths, weights of the wrong length, unknown conf_type); ensemble-boxes prints and
  calls ``exit()``, or silently resets weights of the wrong length to ones.

Shared by both modes: coordinates are clipped to [0, 1]; boxes with score < skip_box_thr
(unweighted, strict) or zero area after clipping are dropped. Unlike ensemble-boxes, boxes whose
weighted confidence C_i is 0 (score 0, or a source of weight 0) are dropped too, in both modes:
they carry no weight in Eq. 15, and ensemble-boxes turns a cluster made of them into a NaN box.
"""

from __future__ import annotations

import numpy as np

from fusion.boxes.inputs import check_range, flatten, label_keys, raise_bad_value
from fusion.boxes.kernels import prepare_kernel, sort_groups_desc, wbf_kernel

CONF_TYPES = ("avg", "max", "box_and_model_avg", "absent_model_aware_avg")


def weighted_boxes_fusion(boxes_list, scores_list, labels_list, weights=None, iou_thr=0.55,
                          skip_box_thr=0.0, conf_type="avg", allows_overflow=False, *, compat=False):
    """Fuse the detections of T sources into one box per cluster of overlapping same-class boxes.

    Args:
        boxes_list: T arrays (N_t, 4) [x1, y1, x2, y2], normalised image coordinates (0..1);
            coordinates outside [0, 1] are clipped, zero-area boxes dropped.
        scores_list: T arrays (N_t,), confidences (>= 0).
        labels_list: T arrays (N_t,), class ids.
        weights: None (all ones) or T per-source weights w_t.
        iou_thr: a box joins a cluster when its IoU with the cluster's fused box is > iou_thr
            (HydraFusion uses 0.4).
        skip_box_thr: boxes with score < skip_box_thr are ignored (HydraFusion uses 0.01).
        conf_type: fused confidence of a cluster of n boxes with weighted scores C_i:
            'avg' ``sum(C_i) / n * min(T, n) / sum(w)``; 'max' ``max(C_i) / max(w)``;
            'box_and_model_avg' ``sum(C_i) / sum(w_i) * sum(w of distinct sources) / sum(w)``;
            'absent_model_aware_avg' ``sum(C_i) / (sum(w_i) + sum(w of absent sources))``.
        allows_overflow: with 'avg', use n instead of min(T, n) (the score may then exceed 1).
        compat: reproduce ensemble-boxes 1.0.9 (float32 fused boxes, int() labels).

    Returns:
        boxes: (K, 4) float64 fused boxes (Eq. 15: sum(C_i b_i) / sum(C_i)).
        scores: (K,) float64 fused confidences, best first.
        labels: (K,) class ids (input dtype; compat: float64 of int(label)).

    Raises:
        ValueError: naming the field for malformed input or parameters.
    """
    if conf_type not in CONF_TYPES:
        raise ValueError(f"conf_type must be one of {CONF_TYPES}, got {conf_type!r}")
    iou_thr = check_range("iou_thr", iou_thr, 0.0, 1.0)
    skip_box_thr = check_range("skip_box_thr", skip_box_thr)
    flat = flatten(boxes_list, scores_list, labels_list, weights)
    w = flat.weights
    keys = label_keys(flat, truncate=compat)
    status, bad_row, rows, boxes, wscores, sources, starts = prepare_kernel(
        flat.boxes, flat.scores, keys, flat.counts, w, 1.0, compat, skip_box_thr, True)
    raise_bad_value(flat, status, bad_row)

    order, ties = sort_groups_desc(wscores, starts)
    if compat and ties:
        # ensemble-boxes sorts each class with numpy's `argsort()[::-1]`, which orders equal
        # scores its own way: the same call on the same values gives the same order
        for g in range(len(starts) - 1):
            a, b = starts[g], starts[g + 1]
            order[a:b] = a + np.argsort(wscores[a:b])[::-1]
    fused, scores, group, best, ties = wbf_kernel(
        boxes, wscores, sources, order, starts, flat.n_sources, w, iou_thr, compat,
        CONF_TYPES.index(conf_type), bool(allows_overflow), float(w.sum()), float(w.max()) if len(w) else 1.0)
    labels = (keys if compat else flat.labels)[rows[starts[:-1]]][group]
    if compat and ties:
        # ensemble-boxes lists classes by first appearance, then sorts with `argsort()[::-1]`
        n_groups = len(starts) - 1
        first_seen = np.full(n_groups, len(flat.scores))
        np.minimum.at(first_seen, np.repeat(np.arange(n_groups), np.diff(starts)), rows)
        by_class = np.argsort(first_seen[group], kind="stable")
        best = by_class[np.argsort(scores[by_class])[::-1]]
    return fused[best], scores[best], labels[best]
