"""The compiled cores of NMS, Soft-NMS and WBF (numba, cached on disk).

`prepare_kernel` validates, clips, weights and groups the stacked detections of all sources in one
pass; the method kernels then work class by class: group g is rows starts[g]:starts[g + 1] of the
prepared arrays, so classes never interact. Boxes are float64 [x1, y1, x2, y2] in normalised image
coordinates with positive areas. Each public function makes two or three calls into this module.

Every kernel follows ensemble-boxes 1.0.9 step by step and operation by operation (IoU is
``inter / (area_a + area_b - inter)``, thresholds are strict, ties resolve the same way), so
compat mode reproduces its outputs to the last bit, except where numpy's `exp` and libm's differ
by an ulp. The speed comes from doing the same arithmetic without temporaries: within a class the
coordinates are copied to contiguous arrays in visiting order and each box is compared with all
later ones in one branch-free, vectorised loop (at 7 sources x 100 boxes this beat building IoU
matrices with numpy, and also beat sweep-and-prune pair lists, whose bookkeeping cost more than
the IoUs it saved).

Performance notes (measured, numba 0.6x): ``error_model="numpy"`` removes the zero-division check
that stops LLVM from vectorising a loop with a division; inner loops are written
``for k in range(n): j = base + k`` because ``for j in range(p + 1, e)`` indexing ran ~3x slower;
arrays are never re-bound inside hot loops (growing an output array in a loop halved the speed);
a max over a slice uses four running maxima, as LLVM does not vectorise a float max reduction.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from fusion.boxes.inputs import BAD_BOX, BAD_LABEL, BAD_SCORE, NEGATIVE_SCORE, OK, SWAPPED

SOFT_LINEAR, SOFT_GAUSSIAN, SOFT_HARD = 1, 2, 3  # ensemble-boxes' `method` codes
CONF_AVG, CONF_MAX, CONF_BOX_AND_MODEL_AVG, CONF_ABSENT_MODEL_AWARE_AVG = range(4)
SMALL_KEYS = 4096  # class ids 0..SMALL_KEYS-1 are grouped by counting sort, others by mergesort


# --- preparation -----------------------------------------------------------------------------


@njit(cache=True)
def _argsort_stable(values):
    """Stable ascending argsort (mergesort), the one sort every kernel shares."""
    return np.argsort(values, kind="mergesort")


@njit(cache=True)
def _stable_order_by_key(keys, rows):
    """rows reordered by keys[rows] ascending, stable (input order kept among equal keys)."""
    top = 0
    for r in rows:
        k = keys[r]
        if not (k >= 0.0 and k < SMALL_KEYS and k == math.floor(k)):
            return rows[_argsort_stable(keys[rows])]
        top = max(top, int(k))
    count = np.zeros(top + 2, np.int64)
    for r in rows:
        count[int(keys[r]) + 1] += 1
    for c in range(top + 1):
        count[c + 1] += count[c]
    out = np.empty(len(rows), np.int64)
    for r in rows:
        c = int(keys[r])
        out[count[c]] = r
        count[c] += 1
    return out


@njit(cache=True)
def prepare_kernel(boxes, scores, keys, counts, weights, scale, swap_corners, skip_box_thr, positive_only):
    """Validate, clip, weight, filter and group the stacked detections.

    Args:
        boxes: (N, 4) float64 [x1, y1, x2, y2] as given.
        scores: (N,) float64 confidences as given.
        keys: (N,) float64 class ids (grouping keys).
        counts: (T,) int64 rows per source (rows are source-major).
        weights: (T,) float64 per-source weights; a row's score becomes ``(score * w_t) / scale``.
        scale: divisor of the weighted scores (> 0).
        swap_corners: order a box's corners (ensemble-boxes) instead of reporting SWAPPED.
        skip_box_thr: rows whose *unweighted* score is < skip_box_thr are dropped.
        positive_only: drop rows whose weighted score is 0 (WBF).

    Returns:
        status: OK or the first problem found (inputs.BAD_BOX, ...), with
        bad_row: its row (-1 when OK);
        rows: (M,) int64 kept rows, grouped by key ascending, input order within a group;
        out_boxes: (M, 4) float64 their clipped boxes; out_scores: (M,) their weighted scores;
        out_sources: (M,) int64 their source index; starts: (G + 1,) int64 group bounds.
        Rows with zero area after clipping are dropped.
    """
    n = boxes.shape[0]
    valid = np.zeros(n, np.bool_)
    clipped = np.empty((n, 4))
    wscores = np.empty(n)
    source = np.empty(n, np.int64)
    status, bad_row = OK, -1
    row = 0
    for t in range(len(counts)):
        for _ in range(counts[t]):
            source[row] = t
            row += 1
    for i in range(n):
        x1, y1, x2, y2 = boxes[i, 0], boxes[i, 1], boxes[i, 2], boxes[i, 3]
        s = scores[i]
        if not (math.isfinite(x1) and math.isfinite(y1) and math.isfinite(x2) and math.isfinite(y2)):
            status = BAD_BOX
        elif not math.isfinite(s):
            status = BAD_SCORE
        elif s < 0.0:
            status = NEGATIVE_SCORE
        elif not math.isfinite(keys[i]):
            status = BAD_LABEL
        elif x2 < x1 or y2 < y1:
            if swap_corners:
                x1, x2 = min(x1, x2), max(x1, x2)
                y1, y2 = min(y1, y2), max(y1, y2)
            else:
                status = SWAPPED
        if status != OK:
            bad_row = i
            break
        x1 = min(max(x1, 0.0), 1.0)
        y1 = min(max(y1, 0.0), 1.0)
        x2 = min(max(x2, 0.0), 1.0)
        y2 = min(max(y2, 0.0), 1.0)
        clipped[i, 0], clipped[i, 1], clipped[i, 2], clipped[i, 3] = x1, y1, x2, y2
        ws = (s * weights[source[i]]) / scale
        wscores[i] = ws
        valid[i] = (x2 - x1) * (y2 - y1) > 0.0 and s >= skip_box_thr and (ws > 0.0 or not positive_only)
    n_kept = 0
    kept = np.empty(n, np.int64)
    if status == OK:
        for i in range(n):
            if valid[i]:
                kept[n_kept] = i
                n_kept += 1
    rows = _stable_order_by_key(keys, kept[:n_kept])
    m = len(rows)
    out_boxes = np.empty((m, 4))
    out_scores = np.empty(m)
    out_sources = np.empty(m, np.int64)
    starts = np.empty(m + 1, np.int64)
    g = 0
    for k in range(m):
        r = rows[k]
        out_boxes[k, 0], out_boxes[k, 1] = clipped[r, 0], clipped[r, 1]
        out_boxes[k, 2], out_boxes[k, 3] = clipped[r, 2], clipped[r, 3]
        out_scores[k] = wscores[r]
        out_sources[k] = source[r]
        if k == 0 or keys[r] != keys[rows[k - 1]]:
            starts[g] = k
            g += 1
    starts[g] = m
    return status, bad_row, rows, out_boxes, out_scores, out_sources, starts[: g + 1]


@njit(cache=True)
def _gather(boxes, rows):
    m = len(rows)
    x1, y1, x2, y2 = np.empty(m), np.empty(m), np.empty(m), np.empty(m)
    for k in range(m):
        r = rows[k]
        x1[k], y1[k], x2[k], y2[k] = boxes[r, 0], boxes[r, 1], boxes[r, 2], boxes[r, 3]
    return x1, y1, x2, y2, (x2 - x1) * (y2 - y1)


@njit(cache=True)
def _best_first(scores):
    """Stable order of scores, highest first."""
    return _argsort_stable(-scores)


# --- NMS ------------------------------------------------------------------------------------


@njit(cache=True, error_model="numpy")
def _nms_group(x1, y1, x2, y2, area, iou_thr, suppressed):
    """Greedy NMS of one group given in visiting order: each box that is still kept suppresses
    every later box with IoU > iou_thr (ensemble-boxes' arithmetic; the inner loop vectorises)."""
    m = len(x1)
    for i in range(m):
        if suppressed[i]:
            continue
        ax1, ay1, ax2, ay2, aa = x1[i], y1[i], x2[i], y2[i], area[i]
        for k in range(m - i - 1):
            j = i + 1 + k
            w = max(0.0, min(ax2, x2[j]) - max(ax1, x1[j]))
            h = max(0.0, min(ay2, y2[j]) - max(ay1, y1[j]))
            inter = w * h
            suppressed[j] |= inter / (aa + area[j] - inter) > iou_thr


@njit(cache=True)
def _select(boxes, scores, rows, keep, out_scores, best_first):
    """Rows `keep` of the prepared table as (boxes (K, 4), scores (K,), rows (K,)), scores taken
    from out_scores (one per kept row); best_first re-orders them by score, stable."""
    k_n = len(keep)
    order = _best_first(out_scores) if best_first else np.arange(k_n)
    ob = np.empty((k_n, 4))
    os_ = np.empty(k_n)
    orows = np.empty(k_n, np.int64)
    for k in range(k_n):
        i = keep[order[k]]
        ob[k, 0], ob[k, 1], ob[k, 2], ob[k, 3] = boxes[i, 0], boxes[i, 1], boxes[i, 2], boxes[i, 3]
        os_[k] = out_scores[order[k]]
        orows[k] = rows[i]
    return ob, os_, orows


@njit(cache=True)
def nms_kernel(boxes, scores, rows, starts, iou_thr, package_order):
    """Greedy NMS per group: keep the best box, drop every later box with IoU > iou_thr.

    Args:
        boxes: (N, 4) float64 boxes, grouped by class (prepare_kernel's output).
        scores: (N,) float64 confidences.
        rows: (N,) int64 input row of each box.
        starts: (G + 1,) int64 group bounds.
        iou_thr: suppression threshold (strict: IoU == iou_thr is kept, as in ensemble-boxes).
        package_order: True reproduces ensemble-boxes: a group is visited in
            ``scores.argsort()[::-1]`` order (numba's quicksort, what it runs, so ties resolve the
            same way) and the output stays class by class in that order; False visits in stable
            descending order and returns best first overall.

    Returns:
        boxes (K, 4), scores (K,), rows (K,) of the kept boxes.
    """
    keep = np.empty(boxes.shape[0], np.int64)
    nk = 0
    for g in range(len(starts) - 1):
        a, b = starts[g], starts[g + 1]
        if package_order:
            order = np.argsort(scores[a:b])[::-1] + a
        else:
            order = _best_first(scores[a:b]) + a
        m = b - a
        x1, y1, x2, y2, area = _gather(boxes, order)
        suppressed = np.zeros(m, np.bool_)
        _nms_group(x1, y1, x2, y2, area, iou_thr, suppressed)
        for i in range(m):
            if not suppressed[i]:
                keep[nk] = order[i]
                nk += 1
    keep = keep[:nk]
    kept_scores = np.empty(nk)
    for k in range(nk):
        kept_scores[k] = scores[keep[k]]
    return _select(boxes, scores, rows, keep, kept_scores, not package_order)


# --- Soft-NMS -------------------------------------------------------------------------------


@njit(cache=True)
def _max_from(sc, start):
    """max(sc[start:]) with four running maxima (the maximum does not depend on the order of
    comparisons, and four independent chains run ~2.5x faster than one)."""
    n = len(sc) - start
    b0 = b1 = b2 = b3 = sc[start]
    k = 0
    while k + 4 <= n:
        b0 = max(b0, sc[start + k])
        b1 = max(b1, sc[start + k + 1])
        b2 = max(b2, sc[start + k + 2])
        b3 = max(b3, sc[start + k + 3])
        k += 4
    while k < n:
        b0 = max(b0, sc[start + k])
        k += 1
    return max(max(b0, b1), max(b2, b3))


@njit(cache=True, error_model="numpy")
def _ious_after(i, x1, y1, x2, y2, area, out):
    """out[k] = IoU(box i, box i + 1 + k) for every later box (ensemble-boxes' arithmetic,
    ``inter / (area_i + area_j - inter)``; vectorises)."""
    ax1, ay1, ax2, ay2, aa = x1[i], y1[i], x2[i], y2[i], area[i]
    for k in range(len(x1) - i - 1):
        j = i + 1 + k
        w = max(0.0, min(ax2, x2[j]) - max(ax1, x1[j]))
        h = max(0.0, min(ay2, y2[j]) - max(ay1, y1[j]))
        inter = w * h
        out[k] = inter / (aa + area[j] - inter)


@njit(cache=True)
def soft_nms_kernel(boxes, scores, rows, starts, method, iou_thr, sigma, thresh, compat):
    """Soft-NMS per group (Bodla et al. 2017), step for step as ensemble-boxes runs it.

    At step i the best remaining box is moved to position i (ties: the current box stays, else the
    first maximum in position order), then every later box's score is multiplied by f(IoU):
    linear ``1 - IoU`` if IoU > iou_thr; Gaussian ``exp(-IoU^2 / sigma)`` for every IoU (iou_thr
    unused); hard ``0`` if IoU > iou_thr. f(0) is exactly 1, so boxes that do not overlap are
    skipped. Boxes whose final score is > thresh are kept.

    Args:
        boxes: (N, 4) float64 boxes, grouped by class (prepare_kernel's output).
        scores: (N,) float64 confidences.
        rows: (N,) int64 input row of each box.
        starts: (G + 1,) int64 group bounds.
        method: 1 linear, 2 Gaussian, 3 hard (ensemble-boxes' codes).
        iou_thr, sigma, thresh: as above.
        compat: return ensemble-boxes' output: the *undecayed* scores, class by class in selection
            order; else the decayed scores, best first.

    Returns:
        boxes (K, 4), scores (K,), rows (K,) of the kept boxes.
    """
    n = boxes.shape[0]
    keep = np.empty(n, np.int64)
    decayed = np.empty(n)
    ious = np.empty(n)
    nk = 0
    for g in range(len(starts) - 1):
        a, b = starts[g], starts[g + 1]
        m = b - a
        idx = np.arange(a, b)  # box (prepared row) at each position
        x1, y1, x2, y2, area = _gather(boxes, idx)
        sc = scores[a:b].copy()
        for i in range(m):
            if i < m - 1:
                top = _max_from(sc, i + 1)
                if sc[i] < top:
                    best = i + 1
                    while sc[best] != top:
                        best += 1
                    x1[i], x1[best] = x1[best], x1[i]
                    y1[i], y1[best] = y1[best], y1[i]
                    x2[i], x2[best] = x2[best], x2[i]
                    y2[i], y2[best] = y2[best], y2[i]
                    area[i], area[best] = area[best], area[i]
                    sc[i], sc[best] = sc[best], sc[i]
                    idx[i], idx[best] = idx[best], idx[i]
            _ious_after(i, x1, y1, x2, y2, area, ious)
            for k in range(m - i - 1):
                ovr = ious[k]
                if ovr == 0.0:
                    continue
                j = i + 1 + k
                if method == SOFT_LINEAR:
                    if ovr > iou_thr:
                        sc[j] = (1.0 - ovr) * sc[j]
                elif method == SOFT_GAUSSIAN:
                    sc[j] = math.exp(-(ovr * ovr) / sigma) * sc[j]
                elif ovr > iou_thr:
                    sc[j] = 0.0 * sc[j]
        for i in range(m):
            if sc[i] > thresh:
                keep[nk] = idx[i]
                decayed[nk] = sc[i]
                nk += 1
    keep = keep[:nk]
    if compat:
        for k in range(nk):
            decayed[k] = scores[keep[k]]
    return _select(boxes, scores, rows, keep, decayed[:nk], not compat)


# --- WBF ------------------------------------------------------------------------------------


@njit(cache=True)
def sort_groups_desc(scores, starts):
    """Stable descending order of scores within each group; also whether a group has tied scores."""
    order = np.empty(len(scores), np.int64)
    ties = False
    for g in range(len(starts) - 1):
        a, b = starts[g], starts[g + 1]
        o = _best_first(scores[a:b]) + a
        order[a:b] = o
        for k in range(1, b - a):
            if scores[o[k]] == scores[o[k - 1]]:
                ties = True
    return order, ties


@njit(cache=True)
def _wbf_scores(count, conf_sum, conf_max, weight_sum, present_weight, absent_weight, conf_type,
               allows_overflow, n_sources, total_weight, max_weight, float32_store):
    """Fused confidence per cluster (ensemble-boxes' rules, operation by operation).

    A cluster's stored confidence is conf_sum / count ('max': conf_max) and its stored weight
    weight_sum; ensemble-boxes keeps a merged cluster's in float32 (float32_store), a lone box's
    in float64. Then: 'avg' ``stored * min(T, n) / total_weight`` (n with allows_overflow);
    'max' ``stored / max_weight``; 'box_and_model_avg'
    ``stored * n / stored_weight * present_weight / total_weight``; 'absent_model_aware_avg'
    ``stored * n / (stored_weight + absent_weight)``.
    """
    k_n = len(count)
    out = np.empty(k_n)
    for k in range(k_n):
        n = count[k]
        stored = conf_max[k] if conf_type == CONF_MAX else conf_sum[k] / n
        stored_w = weight_sum[k]
        if float32_store and n > 1:
            stored = np.float64(np.float32(stored))
            stored_w = np.float64(np.float32(stored_w))
        if conf_type == CONF_BOX_AND_MODEL_AVG:
            out[k] = stored * n / stored_w * present_weight[k] / total_weight
        elif conf_type == CONF_ABSENT_MODEL_AWARE_AVG:
            out[k] = stored * n / (stored_w + absent_weight[k])
        elif conf_type == CONF_MAX:
            out[k] = stored / max_weight
        elif allows_overflow:
            out[k] = stored * n / total_weight
        else:
            out[k] = stored * min(n_sources, n) / total_weight
    return out


@njit(cache=True, error_model="numpy")
def wbf_kernel(boxes, wscores, sources, order, starts, n_sources, weights, iou_thr, float32_boxes,
               conf_type, allows_overflow, total_weight, max_weight):
    """Weighted Boxes Fusion clustering (Solovyev et al. 2021) per group.

    Rows of a group are visited in `order` (best weighted score first). Each row joins the cluster
    whose *current fused box* it overlaps most (first maximum) if that IoU is > iou_thr, else it
    opens a cluster. A cluster's fused box is the confidence-weighted mean of its members
    (HydraFusion Eq. 15 with C_i = w_t * score_i); a one-member cluster's box is the member itself.

    Args:
        boxes: (N, 4) float64 boxes, grouped by class (prepare_kernel's output).
        wscores: (N,) float64 weighted confidences C_i = w_t * score_i (> 0).
        sources: (N,) int64 source index t of each row.
        order: (N,) int64 visiting order, a permutation within each group.
        starts: (G + 1,) int64 group bounds.
        n_sources: T.
        weights: (T,) float64 per-source weights.
        iou_thr: match threshold (strict >).
        float32_boxes: reproduce ensemble-boxes' float32 accumulation of fused boxes and stored
            confidences (``np.zeros(8, np.float32)`` in its get_weighted_box) instead of float64.
        conf_type, allows_overflow, total_weight (sum(w)), max_weight (max(w)): see _wbf_scores.

    Returns:
        fused: (K, 4) float64 fused boxes, class by class in creation order.
        scores: (K,) float64 their confidences.
        group: (K,) int64 group index of each cluster.
        best: (K,) int64 stable best-first order of the clusters.
        ties: whether two clusters have equal scores (ensemble-boxes' unstable sort may then order
            them differently).
    """
    n = boxes.shape[0]
    # fused boxes of the clusters, one array per coordinate (contiguous for the matching loop)
    fx1, fy1, fx2, fy2, farea = np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    acc = np.zeros((n, 4))
    acc32 = np.zeros((n, 4), np.float32)
    group = np.empty(n, np.int64)
    count = np.zeros(n, np.int64)
    conf_sum = np.zeros(n)
    conf_max = np.zeros(n)
    weight_sum = np.zeros(n)
    present = np.zeros((n, n_sources), np.bool_)
    ious = np.empty(n)
    k_n = 0
    for g in range(len(starts) - 1):
        k0 = k_n
        for jj in range(starts[g], starts[g + 1]):
            j = order[jj]
            bx1, by1, bx2, by2 = boxes[j, 0], boxes[j, 1], boxes[j, 2], boxes[j, 3]
            barea = (bx2 - bx1) * (by2 - by1)
            # IoU with every cluster of the class, branch-free so that the loop vectorises
            n_k = k_n - k0
            for kk in range(n_k):
                k = k0 + kk
                inter = (max(min(fx2[k], bx2) - max(fx1[k], bx1), 0.0)
                         * max(min(fy2[k], by2) - max(fy1[k], by1), 0.0))
                ious[kk] = inter / (farea[k] + barea - inter)
            best = -1
            best_iou = -1.0
            for kk in range(n_k):
                if ious[kk] > best_iou:  # first maximum, like np.argmax
                    best_iou = ious[kk]
                    best = k0 + kk
            c = wscores[j]
            if best < 0 or best_iou <= iou_thr:
                k = k_n
                k_n += 1
                group[k] = g
                fx1[k], fy1[k], fx2[k], fy2[k], farea[k] = bx1, by1, bx2, by2, barea
                for d in range(4):
                    acc[k, d] = c * boxes[j, d]
                    acc32[k, d] = np.float32(c * boxes[j, d])
                conf_sum[k] = c
                conf_max[k] = c
            else:
                k = best
                conf_sum[k] += c
                conf_max[k] = max(conf_max[k], c)
                for d in range(4):
                    acc[k, d] += c * boxes[j, d]
                    acc32[k, d] = np.float32(np.float64(acc32[k, d]) + c * boxes[j, d])
                if float32_boxes:
                    fx1[k] = np.float64(np.float32(np.float64(acc32[k, 0]) / conf_sum[k]))
                    fy1[k] = np.float64(np.float32(np.float64(acc32[k, 1]) / conf_sum[k]))
                    fx2[k] = np.float64(np.float32(np.float64(acc32[k, 2]) / conf_sum[k]))
                    fy2[k] = np.float64(np.float32(np.float64(acc32[k, 3]) / conf_sum[k]))
                else:
                    fx1[k] = acc[k, 0] / conf_sum[k]
                    fy1[k] = acc[k, 1] / conf_sum[k]
                    fx2[k] = acc[k, 2] / conf_sum[k]
                    fy2[k] = acc[k, 3] / conf_sum[k]
                farea[k] = (fx2[k] - fx1[k]) * (fy2[k] - fy1[k])
            count[k] += 1
            weight_sum[k] += weights[sources[j]]
            present[k, sources[j]] = True
    fused = np.empty((k_n, 4))
    present_weight = np.zeros(k_n)
    absent_weight = np.zeros(k_n)
    for k in range(k_n):
        fused[k, 0], fused[k, 1], fused[k, 2], fused[k, 3] = fx1[k], fy1[k], fx2[k], fy2[k]
        for t in range(n_sources):
            if present[k, t]:
                present_weight[k] += weights[t]
            else:
                absent_weight[k] += weights[t]
    scores = _wbf_scores(count[:k_n], conf_sum[:k_n], conf_max[:k_n], weight_sum[:k_n], present_weight,
                         absent_weight, conf_type, allows_overflow, n_sources, total_weight, max_weight,
                         float32_boxes)
    best = _best_first(scores)
    ties = False
    for k in range(1, k_n):
        if scores[best[k]] == scores[best[k - 1]]:
            ties = True
    return fused, scores, group[:k_n], best, ties
