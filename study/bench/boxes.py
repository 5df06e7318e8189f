"""Late-fusion benchmarks: our `fusion.boxes` against the `ensemble-boxes` package.

`bench_box_fusion` times NMS, Soft-NMS and WBF on identical synthetic inputs (the detections of
several branches looking at the same scene) and checks that compat mode returns what the package
returns. `compat_map_effect` measures what the package's deviations from the textbook methods do
to VOC mAP@0.5 on a synthetic detection problem. Neither asserts anything about time.
"""

from __future__ import annotations

import copy
import os
import platform
import time
import warnings
from collections.abc import Callable

import numpy as np


def synthetic_scene(rng: np.random.Generator, *, n_objects: int = 30, n_classes: int = 3) -> dict:
    """Ground truth of one synthetic image, in normalised image coordinates.

    Returns:
        {"boxes": (n_objects, 4) float64 [x1, y1, x2, y2] in 0..1, "labels": (n_objects,) int64
        class ids 1..n_classes}. Box sides are 0.02-0.2 of the image.
    """
    centre = rng.uniform(0.1, 0.9, (n_objects, 2))
    size = rng.uniform(0.02, 0.2, (n_objects, 2))
    boxes = np.clip(np.hstack([centre - size / 2, centre + size / 2]), 0.0, 1.0)
    return {"boxes": boxes, "labels": rng.integers(1, n_classes + 1, n_objects)}


def synthetic_detections(rng: np.random.Generator, scene: dict, *, n_lists: int = 7,
                         n_boxes: int = 100, recall: float = 0.8, jitter: float = 0.1,
                         duplicates: float = 0.2, n_classes: int | None = None):
    """What `n_lists` imperfect detectors (branches) report for `scene`.

    Each list detects a random `recall` share of the objects, with box corners moved by
    N(0, jitter * box side) and scores U(0.3, 1); a `duplicates` share of those detections is
    reported twice (a second, lower-scored, shifted box, as a detector without NMS would); the
    rest of its `n_boxes` are false positives placed uniformly with scores U(0, 0.6) and random
    classes.

    Returns:
        boxes_list, scores_list, labels_list: `n_lists` arrays of (n_boxes, 4) float64
        normalised [x1, y1, x2, y2], (n_boxes,) float64 and (n_boxes,) int64 - the
        `ensemble-boxes` input format.
    """
    gt, gl = scene["boxes"], scene["labels"]
    n_classes = n_classes or int(gl.max(initial=1))
    side = np.hstack([gt[:, 2:] - gt[:, :2]] * 2)
    boxes_list, scores_list, labels_list = [], [], []
    for _ in range(n_lists):
        hit = np.flatnonzero(rng.random(len(gt)) < recall)[:n_boxes]
        b = gt[hit] + rng.normal(0.0, jitter, (len(hit), 4)) * side[hit]
        s = rng.uniform(0.3, 1.0, len(hit))
        lab = gl[hit]
        dup = np.flatnonzero(rng.random(len(hit)) < duplicates)[: max(0, n_boxes - len(hit))]
        b = np.vstack([b, b[dup] + rng.normal(0.0, 2 * jitter, (len(dup), 4)) * side[hit][dup]])
        s = np.concatenate([s, s[dup] * rng.uniform(0.5, 1.0, len(dup))])
        lab = np.concatenate([lab, lab[dup]])
        n_fp = n_boxes - len(b)
        centre = rng.uniform(0.05, 0.95, (n_fp, 2))
        size = rng.uniform(0.02, 0.2, (n_fp, 2))
        b = np.vstack([b, np.hstack([centre - size / 2, centre + size / 2])])
        s = np.concatenate([s, rng.uniform(0.0, 0.6, n_fp)])
        lab = np.concatenate([lab, rng.integers(1, n_classes + 1, n_fp)])
        b = np.clip(np.hstack([np.minimum(b[:, :2], b[:, 2:]), np.maximum(b[:, :2], b[:, 2:])]), 0, 1)
        boxes_list.append(b)
        scores_list.append(s)
        labels_list.append(lab.astype(np.int64))
    return boxes_list, scores_list, labels_list


def _canonical(out) -> np.ndarray:
    boxes, scores, labels = (np.asarray(a, np.float64) for a in out)
    rows = np.column_stack([labels, scores, boxes.reshape(-1, 4)])
    return rows[np.lexsort(rows.T[::-1])]


def same_detections(a, b, atol: float = 1e-6) -> bool:
    """Whether two (boxes, scores, labels) results hold the same detections in any order: equal
    labels, scores and box corners within atol (nearly equal scores may sort differently, so rows
    are matched one by one when the sorted comparison fails)."""
    ca, cb = _canonical(a), _canonical(b)
    if ca.shape != cb.shape:
        return False
    if np.array_equal(ca[:, 0], cb[:, 0]) and np.allclose(ca[:, 1:], cb[:, 1:], rtol=0.0, atol=atol):
        return True
    free = np.ones(len(cb), bool)
    for row in ca:
        close = free & (cb[:, 0] == row[0]) & (np.abs(cb[:, 1:] - row[1:]) <= atol).all(1)
        if not close.any():
            return False
        free[np.flatnonzero(close)[0]] = False
    return True


def _methods() -> dict[str, tuple[Callable, Callable, dict]]:
    import ensemble_boxes

    from fusion.boxes import HYDRAFUSION_PARAMS, nms, soft_nms, weighted_boxes_fusion

    return {
        "nms": (nms, ensemble_boxes.nms, HYDRAFUSION_PARAMS["nms"]),
        "soft_nms": (soft_nms, ensemble_boxes.soft_nms, HYDRAFUSION_PARAMS["soft_nms"]),
        "wbf": (weighted_boxes_fusion, ensemble_boxes.weighted_boxes_fusion, HYDRAFUSION_PARAMS["wbf"]),
    }


def _time_per_call(fn: Callable, args_fn: Callable, n: int) -> float:
    """CPU seconds per call of fn(*args_fn()) over n calls (argument copies made outside the
    clock). Process CPU time, not wall time: on a shared machine, time spent waiting for a core
    would otherwise be charged to whichever implementation happened to be running."""
    total = 0.0
    for _ in range(n):
        args = args_fn()
        t0 = time.process_time()
        fn(*args)
        total += time.process_time() - t0
    return total / n


def bench_box_fusion(n_lists: int = 7, n_boxes: int = 100, repeats: int = 30, seed: int = 0,
                     n_classes: int = 3, rounds: int = 5) -> dict:
    """Time our NMS, Soft-NMS and WBF against ensemble-boxes on identical random inputs.

    Inputs: one synthetic scene (30 objects, `n_classes` classes) seen by `n_lists` detectors of
    `n_boxes` boxes each (`synthetic_detections`), fused with HydraFusion's parameters (IoU 0.4,
    skip 0.01, sigma 0.5) and equal weights. Each implementation runs once before timing (numba
    compilation and caches), then `rounds` alternating rounds of `repeats` calls each, timed in
    process CPU time; the figure is the median round, so a busy shared machine slows both sides
    alike. ensemble-boxes gets fresh copies of its inputs every call (it overwrites its `scores`
    list when given weights).

    Returns:
        {"methods": {method: {"ours_ms", "ensemble_boxes_ms", "speedup", "equal_output",
        "n_out"}}, plus the parameters and the machine}. equal_output compares our compat mode
        with the package (same detections, boxes and scores within 1e-6, any order).
    """
    if min(n_lists, n_boxes, repeats, rounds) < 1:
        raise ValueError("n_lists, n_boxes, repeats and rounds must be >= 1")
    rng = np.random.default_rng(seed)
    scene = synthetic_scene(rng, n_classes=n_classes)
    inputs = synthetic_detections(rng, scene, n_lists=n_lists, n_boxes=n_boxes, n_classes=n_classes)
    weights = [1.0] * n_lists

    results = {}
    for name, (ours, theirs, params) in _methods().items():
        def ours_call(*a, _f=ours, _p=params):
            return _f(*a, weights=weights, compat=True, **_p)

        def theirs_call(*a, _f=theirs, _p=params):
            return _f(*a, weights=list(weights), **_p)

        def fresh():
            return copy.deepcopy(inputs)

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            equal = same_detections(ours_call(*fresh()), theirs_call(*fresh()))
            t_ours, t_theirs = [], []
            for _ in range(rounds):
                t_ours.append(_time_per_call(ours_call, fresh, repeats))
                t_theirs.append(_time_per_call(theirs_call, fresh, repeats))
        ms_ours = 1e3 * float(np.median(t_ours))
        ms_theirs = 1e3 * float(np.median(t_theirs))
        results[name] = {
            "ours_ms": round(ms_ours, 4),
            "ensemble_boxes_ms": round(ms_theirs, 4),
            "speedup": round(ms_theirs / ms_ours, 1),
            "equal_output": equal,
            "n_out": int(len(ours_call(*fresh())[1])),
        }
    return {
        "methods": results,
        "n_lists": n_lists,
        "n_boxes": n_boxes,
        "n_classes": n_classes,
        "repeats": repeats,
        "rounds": rounds,
        "seed": seed,
        "params": {k: v[2] for k, v in _methods().items()},
        "cores": os.cpu_count(),
        "machine": platform.machine(),
        "python": platform.python_version(),
    }


def compat_map_effect(n_images: int = 100, n_lists: int = 7, n_boxes: int = 100, n_classes: int = 3,
                      seed: int = 0, score_thr: float = 0.5) -> dict:
    """What ensemble-boxes' deviations do to detection quality, on a synthetic problem.

    `n_images` synthetic scenes (30 objects, `n_classes` classes) are each seen by `n_lists`
    detectors (`synthetic_detections`: 80 % recall, jittered boxes, 20 % duplicates, clutter).
    Each method fuses them in textbook mode and in compat mode, without weights and with equal
    weights ``[1] * n_lists``, with HydraFusion's parameters. Reported per configuration: VOC
    mAP@0.5 (`fusion.metrics`) and the recall of the detections scoring >= `score_thr` (what a
    deployed detector with a confidence cut-off would find). A single detector's mAP is the
    baseline.

    Returns:
        {"single_list_map": float, "methods": {method: {"textbook" | "compat":
        {"no_weights" | "equal_weights": {"map", "recall_at_score_thr", "mean_score"}}}},
        plus the parameters}.
    """
    from fusion.boxes import HYDRAFUSION_PARAMS, nms, soft_nms, weighted_boxes_fusion
    from fusion.metrics import evaluate_detections

    if min(n_images, n_lists, n_boxes, n_classes) < 1:
        raise ValueError("n_images, n_lists, n_boxes and n_classes must be >= 1")
    rng = np.random.default_rng(seed)
    truths, inputs = [], []
    for _ in range(n_images):
        scene = synthetic_scene(rng, n_classes=n_classes)
        truths.append(scene)
        inputs.append(synthetic_detections(rng, scene, n_lists=n_lists, n_boxes=n_boxes, n_classes=n_classes))

    def summary(results):
        full = evaluate_detections(results, truths)
        confident = [(b[s >= score_thr], s[s >= score_thr], lab[s >= score_thr]) for b, s, lab in results]
        cut = evaluate_detections(confident, truths)
        n_pos = sum(cut.n_positives.values())
        scores = np.concatenate([s for _, s, _ in results]) if results else np.zeros(0)
        return {"map": round(full.mean_ap, 4),
                "recall_at_score_thr": round(sum(cut.n_true_positives.values()) / max(n_pos, 1), 4),
                "mean_score": round(float(scores.mean()) if len(scores) else 0.0, 4)}

    single = [(b[0], s[0], lab[0]) for b, s, lab in inputs]
    methods = {"nms": nms, "soft_nms": soft_nms, "wbf": weighted_boxes_fusion}
    out = {}
    for name, fn in methods.items():
        out[name] = {}
        for mode, compat in (("textbook", False), ("compat", True)):
            out[name][mode] = {}
            for label, weights in (("no_weights", None), ("equal_weights", [1.0] * n_lists)):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    results = [fn(b, s, lab, weights=weights, compat=compat, **HYDRAFUSION_PARAMS[name])
                               for b, s, lab in inputs]
                out[name][mode][label] = summary(results)
    return {
        "single_list_map": round(evaluate_detections(single, truths).mean_ap, 4),
        "methods": out,
        "n_images": n_images,
        "n_lists": n_lists,
        "n_boxes": n_boxes,
        "n_classes": n_classes,
        "score_thr": score_thr,
        "seed": seed,
        "params": {k: HYDRAFUSION_PARAMS[k] for k in methods},
    }
