"""Input checking shared by the box-fusion functions: per-source lists in, one table out.

The late-fusion functions take what `ensemble-boxes` takes: for T sources (branches, models),
`boxes_list[t]` is an (N_t, 4) array of [x1, y1, x2, y2] in normalised image coordinates (0..1),
`scores_list[t]` an (N_t,) array of confidences and `labels_list[t]` an (N_t,) array of class ids.
`flatten` checks the structure (list lengths, shapes) and stacks the sources into one
`FlatDetections` table; the values (NaN, inf, negative scores, swapped corners) are checked in the
same compiled pass that clips the boxes (`kernels.prepare_kernel`), and `raise_bad_value` turns
its status code into a ValueError naming the field (``boxes_list[2][17]``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

F64 = np.dtype(np.float64)
# status codes of kernels.prepare_kernel
OK, BAD_BOX, BAD_SCORE, NEGATIVE_SCORE, BAD_LABEL, SWAPPED = range(6)


@dataclass(slots=True)
class FlatDetections:
    """All sources' detections in one table of N rows (source 0's rows first, then source 1's...).

    Fields:
        boxes: (N, 4) float64, [x1, y1, x2, y2] as given, normalised image coordinates (0..1).
        scores: (N,) float64, confidences as given.
        labels: (N,) class ids with the dtype of the inputs (float64 when there are no rows).
        counts: (T,) int64, rows per source.
        weights: (T,) float64, per-source weights (ones when the caller passed none).
        weighted: whether the caller passed weights.
    """

    boxes: np.ndarray
    scores: np.ndarray
    labels: np.ndarray
    counts: np.ndarray
    weights: np.ndarray
    weighted: bool

    @property
    def n_sources(self) -> int:
        return len(self.counts)

    def source_of(self, row: int) -> tuple[int, int]:
        """(t, i): row `row` of the table is row i of source t."""
        ends = np.cumsum(self.counts)
        t = int(np.searchsorted(ends, row, side="right"))
        return t, int(row - (ends[t - 1] if t else 0))

    def sources(self) -> np.ndarray:
        """(N,) int64 source index of each row."""
        return np.repeat(np.arange(self.n_sources, dtype=np.int64), self.counts)


def _as_list(value, name: str):
    if isinstance(value, str | bytes) or not hasattr(value, "__len__") or not hasattr(value, "__getitem__"):
        raise ValueError(f"{name} must be a list with one entry per source, got {type(value).__name__}")
    return value


def _numeric(value, field: str, t: int | None = None, dtype=None) -> np.ndarray:
    name = field if t is None else f"{field}[{t}]"
    try:
        arr = np.asarray(value, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} is not a numeric array ({exc})") from None
    if arr.dtype.kind not in "iuf":
        raise ValueError(f"{name} must hold numbers, got dtype {arr.dtype}")
    return arr


def flatten(boxes_list, scores_list, labels_list, weights=None) -> FlatDetections:
    """Check the per-source lists' structure and stack them into a `FlatDetections` table.

    Args:
        boxes_list: T array-likes of shape (N_t, 4) [x1, y1, x2, y2], normalised (0..1); an empty
            entry ([] or shape (0,) / (0, 4)) is a source without detections.
        scores_list: T array-likes of shape (N_t,), confidences.
        labels_list: T array-likes of shape (N_t,), numeric class ids.
        weights: None or T finite non-negative per-source weights, not all zero.

    Raises:
        ValueError: naming the field when the lists differ in length, an entry is not numeric or
            has the wrong shape or length, or the weights are invalid.
    """
    boxes_list = _as_list(boxes_list, "boxes_list")
    scores_list = _as_list(scores_list, "scores_list")
    labels_list = _as_list(labels_list, "labels_list")
    n = len(boxes_list)
    if len(scores_list) != n:
        raise ValueError(f"scores_list has {len(scores_list)} entries but boxes_list has {n} (one per source)")
    if len(labels_list) != n:
        raise ValueError(f"labels_list has {len(labels_list)} entries but boxes_list has {n} (one per source)")

    boxes, scores, labels = [None] * n, [None] * n, [None] * n
    counts = np.zeros(n, np.int64)
    for t in range(n):
        b, s, lab = boxes_list[t], scores_list[t], labels_list[t]
        # fast path: float64 / numeric ndarrays are used as they are
        if type(b) is not np.ndarray or b.dtype is not F64:
            b = _numeric(b, "boxes_list", t, np.float64)
        if type(s) is not np.ndarray or s.dtype is not F64:
            s = _numeric(s, "scores_list", t, np.float64)
        if type(lab) is not np.ndarray or lab.dtype.kind not in "iuf":
            lab = _numeric(lab, "labels_list", t)
        if b.ndim != 2 or b.shape[1] != 4:
            if b.size:
                raise ValueError(f"boxes_list[{t}] must have shape (N, 4) [x1, y1, x2, y2], got {b.shape}")
            b = b.reshape(0, 4)
        k = b.shape[0]
        if s.shape != (k,):
            raise ValueError(f"scores_list[{t}] must have shape ({k},) like boxes_list[{t}], got {s.shape}")
        if lab.shape != (k,):
            raise ValueError(f"labels_list[{t}] must have shape ({k},) like boxes_list[{t}], got {lab.shape}")
        boxes[t], scores[t], labels[t] = b, s, lab
        counts[t] = k

    if n:
        all_boxes, all_scores, all_labels = np.concatenate(boxes), np.concatenate(scores), np.concatenate(labels)
    else:
        all_boxes, all_scores, all_labels = np.zeros((0, 4)), np.zeros(0), np.zeros(0)

    if weights is None:
        w = np.ones(n)
    else:
        w = _numeric(weights, "weights", None, np.float64)
        if w.shape != (n,):
            raise ValueError(f"weights must have one entry per source ({n}), got shape {w.shape}")
        values = w.tolist()
        if n and not (all(0.0 <= v < math.inf for v in values) and max(values) > 0):
            raise ValueError(f"weights must be finite, >= 0 and not all zero, got {values}")
    return FlatDetections(all_boxes, all_scores, all_labels, counts, w, weights is not None)


def label_keys(flat: FlatDetections, *, truncate: bool = False) -> np.ndarray:
    """(N,) float64 grouping key per row: the class id (int() of it with truncate, ensemble-boxes' WBF)."""
    keys = flat.labels.astype(np.float64)
    return np.trunc(keys) if truncate else keys


def raise_bad_value(flat: FlatDetections, status: int, row: int) -> None:
    """Raise the ValueError for a `prepare_kernel` status (no-op for OK)."""
    if status == OK:
        return
    t, i = flat.source_of(row)
    if status == BAD_BOX:
        raise ValueError(f"boxes_list[{t}][{i}] = {flat.boxes[row].tolist()} contains NaN or inf")
    if status == BAD_SCORE:
        raise ValueError(f"scores_list[{t}][{i}] = {flat.scores[row]} is NaN or inf")
    if status == NEGATIVE_SCORE:
        raise ValueError(f"scores_list[{t}][{i}] = {flat.scores[row]} is negative (confidences are >= 0)")
    if status == BAD_LABEL:
        raise ValueError(f"labels_list[{t}][{i}] = {flat.labels[row]} is NaN or inf")
    raise ValueError(
        f"boxes_list[{t}][{i}] = {flat.boxes[row].tolist()} has x2 < x1 or y2 < y1 "
        "(boxes are [x1, y1, x2, y2]; compat=True swaps the corners like ensemble-boxes)"
    )


def check_range(name: str, value, lo: float | None = None, hi: float | None = None, *, open_lo=False) -> float:
    """A finite float parameter inside [lo, hi] (or (lo, hi] with open_lo), else ValueError naming it."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    ok = math.isfinite(v)
    if lo is not None:
        ok = ok and (v > lo if open_lo else v >= lo)
    if hi is not None:
        ok = ok and v <= hi
    if not ok:
        left = "(" if open_lo else "["
        raise ValueError(f"{name} must be finite and in {left}{lo}, {hi}], got {value!r}")
    return v
