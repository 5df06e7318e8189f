"""Random inputs for the box-fusion tests: several sources detecting the same scene."""

from __future__ import annotations

import numpy as np


def random_case(rng: np.random.Generator, *, max_lists: int = 7, max_boxes: int = 40,
                messy: bool = True) -> dict:
    """One random fusion input in the ensemble-boxes format.

    Boxes cluster around a few objects (so fusion has work to do), plus uniform clutter; scores in
    (0, 1], sometimes rounded to one decimal (ties); labels int or float from 1-4 classes. With
    `messy`, some cases have corners outside [0, 1], zero-area boxes or swapped corners (x2 < x1).

    Returns:
        {"boxes": T arrays (N_t, 4), "scores": T arrays (N_t,), "labels": T arrays (N_t,),
         "weights": None or T floats, "swapped": whether any box has x2 < x1 or y2 < y1}.
    """
    n_lists = int(rng.integers(1, max_lists + 1))
    empty = rng.random() < 0.03  # every source without detections
    n_classes = int(rng.choice([1, 2, 3, 4]))
    n_objects = int(rng.integers(1, 12))
    centre = rng.uniform(0.1, 0.9, (n_objects, 2))
    size = rng.uniform(0.03, 0.35, (n_objects, 2))
    obj_label = rng.integers(0, n_classes, n_objects)
    ties = rng.random() < 0.2
    out_of_range = messy and rng.random() < 0.2
    degenerate = messy and rng.random() < 0.2
    swapped = messy and rng.random() < 0.15
    float_labels = rng.random() < 0.3
    boxes, scores, labels = [], [], []
    for _ in range(n_lists):
        n = 0 if empty else int(rng.integers(0, max_boxes + 1))
        obj = rng.integers(0, n_objects, n)
        clutter = rng.random(n) < 0.3
        c = np.where(clutter[:, None], rng.uniform(0, 1, (n, 2)), centre[obj] + rng.normal(0, 0.03, (n, 2)))
        s = np.where(clutter[:, None], rng.uniform(0.02, 0.3, (n, 2)), size[obj] * rng.uniform(0.8, 1.2, (n, 2)))
        b = np.hstack([c - s / 2, c + s / 2])
        b = b if out_of_range else np.clip(b, 0.0, 1.0)
        if degenerate and n:
            pick = rng.random(n) < 0.2
            b[pick, 2] = b[pick, 0]
        if swapped and n:
            pick = rng.random(n) < 0.2
            b[pick] = b[pick][:, [2, 1, 0, 3]]
        sc = rng.uniform(0.0, 1.0, n)
        sc = np.round(sc, 1) + 0.05 if ties else np.maximum(sc, 1e-3)
        lab = np.where(clutter, rng.integers(0, n_classes, n), obj_label[obj])
        boxes.append(b)
        scores.append(sc)
        labels.append(lab.astype(np.float64) if float_labels else lab.astype(np.int64))
    weights = None if rng.random() < 0.4 else list(rng.uniform(0.2, 3.0, n_lists))
    has_swapped = any(len(b) and bool(((b[:, 2] < b[:, 0]) | (b[:, 3] < b[:, 1])).any()) for b in boxes)
    return {"boxes": boxes, "scores": scores, "labels": labels, "weights": weights, "swapped": has_swapped}


def canonical(result) -> np.ndarray:
    """(K, 6) rows [label, score, x1, y1, x2, y2] of a (boxes, scores, labels) result, sorted."""
    boxes, scores, labels = (np.asarray(a, np.float64) for a in result)
    rows = np.column_stack([labels, scores, boxes.reshape(-1, 4)])
    return rows[np.lexsort(rows.T[::-1])]


def assert_same_detections(ours, reference, atol: float = 1e-6, msg: str = "") -> None:
    """Same multiset of detections: labels equal, scores and boxes within atol, any order.

    Sorted rows are compared first; when two detections have nearly equal scores the sort may
    pair them differently, so a failing sorted comparison falls back to matching each row of
    `ours` with an unused row of `reference` within atol.
    """
    a, b = canonical(ours), canonical(reference)
    assert a.shape == b.shape, f"{msg}: {len(a)} detections vs {len(b)}"
    if np.array_equal(a[:, 0], b[:, 0]) and np.allclose(a[:, 1:], b[:, 1:], rtol=0, atol=atol):
        return
    free = np.ones(len(b), bool)
    for row in a:
        close = free & (b[:, 0] == row[0]) & (np.abs(b[:, 1:] - row[1:]) <= atol).all(1)
        assert close.any(), f"{msg}: detection {row.tolist()} has no counterpart within {atol}"
        free[np.flatnonzero(close)[0]] = False
