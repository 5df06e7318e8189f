"""The compiled cores of NMS, Soft-NMS and WBF (numba, cached on disk).

`prepare_kernel` validates, clips, weights and groups the stacked detections of all sources in one
pass; the method kernels then work class by class: group g is rows starts[g]:starts[g + 1] of the
prepared arrays, so classes never interact. Boxes are float64 [x1, y1, x2, y2] in normalised image
coordinates with positive areas. Each public function makes one to three calls into this module.

NMS and Soft-NMS only need the pairs of boxes whose IoU can matter: IoU > iou_thr for NMS, IoU > 0
for Soft-NMS (f(0) is exactly 1 for every Soft-NMS method). `overlap_pairs` finds them by sweep
and prune along x, which at 7 sources x 100 boxes evaluates 4-8x fewer IoUs than a full matrix.
The arithmetic follows ensemble-boxes 1.0.9 operation by operation
(``inter / (area_a + area_b - inter)``), so compat mode reproduces its outputs to the last bit,
except where numpy's `exp` and libm's differ by an ulp.

Performance notes (measured, numba 0.6x): ``error_model="numpy"`` removes the zero-division check
that stops LLVM from vectorising a loop with a division; inner loops are written
``for k in range(n): j = base + k`` because ``for j in range(p + 1, e)`` indexing is ~3x slower;
arrays are never re-bound inside hot loops (growing an output array in the loop halved the speed).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from fusion.boxes.inputs import BAD_BOX, BAD_LABEL, BAD_SCORE, NEGATIVE_SCORE, OK, SWAPPED

SOFT_LINEAR, SOFT_GAUSSIAN, SOFT_HARD = 1, 2, 3  # ensemble-boxes' `method` codes
CONF_AVG, CONF_MAX, CONF_BOX_AND_MODEL_AVG, CONF_ABSENT_MODEL_AWARE_AVG = range(4)
SMALL_KEYS = 4096  # class ids 0..SMALL_KEYS-1 are grouped by counting sort, others by mergesort
SMALL_GROUP = 48  # up to this many boxes, overlap_pairs compares all pairs instead of sorting along x
NMS_DIRECT_MAX = 128  # up to this many boxes of a class, NMS compares kept boxes with all later ones


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


# --- pairs ----------------------------------------------------------------------------------


@njit(cache=True, error_model="numpy")
def overlap_pairs(x1, y1, x2, y2, area, iou_thr):
    """All pairs of boxes whose IoU is > iou_thr (iou_thr 0: every intersecting pair).

    Sweep and prune: with the boxes sorted by x1, a box j starting at or after box i can only
    reach IoU > t if x1_j - x1_i < (1 - t) * w_i (their x-overlap must exceed t * max(w_i, w_j)),
    so each box is compared with a window of its successors. A multiplication test
    (``inter > t * (1 - 1e-9) * union``, vectorised) screens the window; the exact ensemble-boxes
    division decides. Groups of up to SMALL_GROUP boxes compare all pairs.

    Args:
        x1, y1, x2, y2, area: (m,) float64 box coordinates and areas (> 0).
        iou_thr: keep pairs with IoU > iou_thr, in [0, 1].

    Returns:
        first, second: (E,) int64 box indices with first < second.
        iou: (E,) float64 their IoU, ``inter / (area_a + area_b - inter)`` (symmetric bit for bit).
    """
    m = len(x1)
    ends = np.empty(m, np.int64)
    if m <= SMALL_GROUP:
        by_x = np.arange(m)
        sx1, sy1, sx2, sy2, sa = x1, y1, x2, y2, area
        ends[:] = m
    else:
        by_x = _argsort_stable(x1)
        sx1, sy1, sx2, sy2, sa = np.empty(m), np.empty(m), np.empty(m), np.empty(m), np.empty(m)
        for k in range(m):
            r = by_x[k]
            sx1[k], sy1[k], sx2[k], sy2[k], sa[k] = x1[r], y1[r], x2[r], y2[r], area[r]
        reach_factor = (1.0 - iou_thr) + 1e-9
        for p in range(m):
            reach = sx1[p] + (sx2[p] - sx1[p]) * reach_factor
            lo, hi = p + 1, m  # first q > p with sx1[q] > reach (binary search)
            while lo < hi:
                mid = (lo + hi) >> 1
                if sx1[mid] <= reach:
                    lo = mid + 1
                else:
                    hi = mid
            ends[p] = lo
    n_candidates = 0
    for p in range(m):
        n_candidates += max(ends[p] - p - 1, 0)
    first = np.empty(n_candidates, np.int64)
    second = np.empty(n_candidates, np.int64)
    iou = np.empty(n_candidates)
    flag = np.empty(m, np.bool_)
    lim = iou_thr * (1.0 - 1e-9)
    e = 0
    for p in range(m):
        n = ends[p] - p - 1
        if n <= 0:
            continue
        ax1, ay1, ax2, ay2, aa = sx1[p], sy1[p], sx2[p], sy2[p], sa[p]
        for k in range(n):
            q = p + 1 + k
            w = max(min(ax2, sx2[q]) - max(ax1, sx1[q]), 0.0)
            h = max(min(ay2, sy2[q]) - max(ay1, sy1[q]), 0.0)
            inter = w * h
            flag[k] = inter > lim * (aa + sa[q] - inter)
        for k in range(n):
            if flag[k]:
                q = p + 1 + k
                w = max(0.0, min(ax2, sx2[q]) - max(ax1, sx1[q]))
                h = max(0.0, min(ay2, sy2[q]) - max(ay1, sy1[q]))
                inter = w * h
                v = inter / (aa + sa[q] - inter)
                if v > iou_thr:
                    i, j = by_x[p], by_x[q]
                    first[e], second[e], iou[e] = min(i, j), max(i, j), v
                    e += 1
    return first[:e], second[:e], iou[:e]


@njit(cache=True)
def _csr(first, second, iou, m, symmetric):
    """Adjacency lists: neighbours of box i are nbr[ptr[i]:ptr[i + 1]] (with their IoU in val)."""
    deg = np.zeros(m + 1, np.int64)
    for e in range(len(first)):
        deg[first[e] + 1] += 1
        if symmetric:
            deg[second[e] + 1] += 1
    ptr = np.cumsum(deg)
    fill = ptr[:-1].copy()
    nbr = np.empty(ptr[m], np.int64)
    val = np.empty(ptr[m])
    for e in range(len(first)):
        a, b = first[e], second[e]
        nbr[fill[a]], val[fill[a]] = b, iou[e]
        fill[a] += 1
        if symmetric:
            nbr[fill[b]], val[fill[b]] = a, iou[e]
            fill[b] += 1
    return ptr, nbr, val


# --- NMS ------------------------------------------------------------------------------------


@njit(cache=True, error_model="numpy")
def _nms_group_direct(x1, y1, x2, y2, area, iou_thr, suppressed):
    """Greedy NMS of one group in visiting order, comparing each kept box with all later boxes
    (cheapest for small groups: no sorting, no pair lists)."""
    m = len(x1)
    flag = np.empty(m, np.bool_)
    lim = iou_thr * (1.0 - 1e-9)
    for i in range(m):
        if suppressed[i]:
            continue
        ax1, ay1, ax2, ay2, aa = x1[i], y1[i], x2[i], y2[i], area[i]
        n = m - i - 1
        for k in range(n):  # screen (vectorised)
            j = i + 1 + k
            inter = max(min(ax2, x2[j]) - max(ax1, x1[j]), 0.0) * max(min(ay2, y2[j]) - max(ay1, y1[j]), 0.0)
            flag[k] = inter > lim * (aa + area[j] - inter)
        for k in range(n):  # decide with ensemble-boxes' arithmetic
            if flag[k]:
                j = i + 1 + k
                w = max(0.0, min(ax2, x2[j]) - max(ax1, x1[j]))
                h = max(0.0, min(ay2, y2[j]) - max(ay1, y1[j]))
                inter = w * h
                if inter / (aa + area[j] - inter) > iou_thr:
                    suppressed[j] = True


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
        if m <= NMS_DIRECT_MAX:
            _nms_group_direct(x1, y1, x2, y2, area, iou_thr, suppressed)
        else:
            first, second, iou = overlap_pairs(x1, y1, x2, y2, area, iou_thr)
            ptr, nbr, _ = _csr(first, second, iou, m, False)  # box i (visited first) -> later boxes
            for i in range(m):
                if not suppressed[i]:
                    for e in range(ptr[i], ptr[i + 1]):
                        suppressed[nbr[e]] = True
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


@njit(cache=True, fastmath=True)
def _max_from(sc, start):
    """max(sc[start:]); the maximum does not depend on the order of comparisons, so fastmath
    (which lets the loop vectorise) is exact here (scores are finite)."""
    best = sc[start]
    for k in range(len(sc) - start):
        best = max(best, sc[start + k])
    return best


@njit(cache=True)
def soft_nms_kernel(boxes, scores, rows, starts, method, iou_thr, sigma, thresh, compat):
    """Soft-NMS per group (Bodla et al. 2017), in ensemble-boxes' selection order.

    At step i the best remaining box is moved to position i (ties: the current box stays, else the
    first maximum in position order), then every later box's score is multiplied by f(IoU):
    linear ``1 - IoU`` if IoU > iou_thr; Gaussian ``exp(-IoU^2 / sigma)`` for every IoU (iou_thr
    unused); hard ``0`` if IoU > iou_thr. Boxes whose final score is > thresh are kept.

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
    nk = 0
    for g in range(len(starts) - 1):
        a, b = starts[g], starts[g + 1]
        m = b - a
        x1, y1, x2, y2, area = _gather(boxes, np.arange(a, b))
        first, second, iou = overlap_pairs(x1, y1, x2, y2, area, 0.0)
        ptr, nbr, val = _csr(first, second, iou, m, True)
        sc = scores[a:b].copy()  # by position
        box_at = np.arange(m)  # box at each position
        pos = np.arange(m)  # position of each box
        for i in range(m):
            if i < m - 1:
                top = _max_from(sc, i + 1)
                if sc[i] < top:
                    best = i + 1
                    while sc[best] != top:
                        best += 1
                    sc[i], sc[best] = sc[best], sc[i]
                    bi, bb = box_at[i], box_at[best]
                    box_at[i], box_at[best] = bb, bi
                    pos[bb], pos[bi] = i, best
            cur = box_at[i]
            for e in range(ptr[cur], ptr[cur + 1]):
                p = pos[nbr[e]]
                if p <= i:
                    continue
                ovr = val[e]
                if method == SOFT_LINEAR:
                    if ovr > iou_thr:
                        sc[p] = (1.0 - ovr) * sc[p]
                elif method == SOFT_GAUSSIAN:
                    sc[p] = math.exp(-(ovr * ovr) / sigma) * sc[p]
                elif ovr > iou_thr:
                    sc[p] = 0.0 * sc[p]
        for i in range(m):
            if sc[i] > thresh:
                keep[nk] = a + box_at[i]
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
