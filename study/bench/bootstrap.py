"""The sequence bootstrap's cost: every source's mAP on every draw, scored the old way (each draw's
detections pooled and ranked again, `fusion.intervals.map_draws(scoring="pooled")`) and the new way
(ranked once, each draw a weighting, `scoring="weighted"`), on a synthetic test set of the
verdict's shape; the two must agree to 1e-9 on every draw both score. Asserts nothing about time."""

from __future__ import annotations

import time

import numpy as np

CONTEXTS = ("city", "fog", "junction", "motorway", "night", "rain", "rural", "snow")


def synthetic_test_set(frames: int, sequence_length: int, methods: int, detections: int, classes: int, seed: int):
    """({method: ImageMatches}, context of each frame, sequence of each frame): `frames` frames in
    sequences of `sequence_length`, dealt round the eight contexts; per frame 2-10 objects of
    `classes` classes (a fifth difficult), and per method about `detections` detections: each
    object found with a method-dependent recall, its box jittered, the rest false positives."""
    from fusion.metrics import ImageMatches

    rng = np.random.default_rng(seed)
    n_seq = -(-frames // sequence_length)
    sequences = [f"s{j // sequence_length:05d}" for j in range(frames)]
    contexts = [CONTEXTS[(j // sequence_length) % len(CONTEXTS)] for j in range(frames)]
    gts = []
    for _ in range(frames):
        n = int(rng.integers(2, 11))
        xy = rng.uniform(0, 300, (n, 2))
        wh = rng.uniform(8, 80, (n, 2))
        gts.append({"boxes": np.c_[xy, xy + wh], "labels": rng.integers(1, classes + 1, n),
                    "difficult": rng.random(n) < 0.2})
    out = {}
    for m in range(methods):
        recall = 0.4 + 0.4 * m / max(methods - 1, 1)
        dets = []
        for g in gts:
            found = rng.random(len(g["boxes"])) < recall
            tb = g["boxes"][found]
            tb = tb + rng.normal(0, 0.1, tb.shape) * (tb[:, 2:] - tb[:, :2]).repeat(2, axis=1)
            n_fp = max(int(rng.poisson(detections)) - len(tb), 0)
            xy = rng.uniform(0, 300, (n_fp, 2))
            fb = np.c_[xy, xy + rng.uniform(8, 80, (n_fp, 2))]
            dets.append({"boxes": np.r_[tb, fb],
                         "scores": np.r_[rng.uniform(0.3, 1.0, len(tb)), rng.uniform(0.05, 0.7, n_fp)],
                         "labels": np.r_[g["labels"][found], rng.integers(1, classes + 1, n_fp)]})
        out[f"method{m:02d}"] = ImageMatches.of(dets, gts, classes=range(1, classes + 1))
    assert len(set(sequences)) == n_seq
    return out, contexts, sequences


def bench_bootstrap(frames: int = 1152, sequence_length: int = 3, methods: int = 11, detections: int = 60,
                    classes: int = 8, resamples: int = 500, pooled_resamples: int = 20, seed: int = 0) -> dict:
    """Time the bootstrap of `study.engine.scoring.context_bootstrap` (overall and per context, `resamples`
    draws each) both ways. The pooled way is timed on its first `pooled_resamples` draws of each
    group (the same draws: the generator is seeded) and scaled to `resamples` (its cost is the same
    per draw); the weighted way runs in full. Returns the times, the per-draw agreement and the set's
    size."""
    from fusion.intervals import map_draws
    from fusion.metrics import DrawScorer

    t0 = time.perf_counter()
    matches, contexts, sequences = synthetic_test_set(frames, sequence_length, methods, detections, classes, seed)
    t_match = time.perf_counter() - t0
    groups = {"all": list(range(frames))}
    for j, c in enumerate(contexts):
        groups.setdefault(c, []).append(j)

    def by_of(rows):
        by: dict = {}
        for j in rows:
            by.setdefault(contexts[j], {}).setdefault(sequences[j], []).append(j)
        return by

    t0 = time.perf_counter()
    scorers = {n: DrawScorer(m) for n, m in matches.items()}
    t_rank = time.perf_counter() - t0
    t_weighted = t_pooled = 0.0
    worst = 0.0
    for rows in groups.values():
        by = by_of(rows)
        t0 = time.perf_counter()
        new = map_draws(matches, by, resamples, seed, scorers=scorers)
        t_weighted += time.perf_counter() - t0
        k = min(pooled_resamples, resamples)
        if k:
            t0 = time.perf_counter()
            old = map_draws(matches, by, k, seed, scoring="pooled")
            t_pooled += time.perf_counter() - t0
            both = np.isfinite(old) & np.isfinite(new[:k])
            if not np.array_equal(np.isfinite(old), np.isfinite(new[:k])):
                worst = float("inf")
            elif both.any():
                worst = max(worst, float(np.max(np.abs(old[both] - new[:k][both]))))
    n_det = sum(len(r[c][0]) for m in matches.values() for r in m.per_image for c in m.classes)
    pooled_full = t_pooled * resamples / pooled_resamples if pooled_resamples else None
    return {
        "frames": frames, "sequences": len(set(sequences)), "contexts": len(set(contexts)), "methods": methods,
        "classes": classes, "detections_scored": int(n_det), "resamples": resamples, "groups": len(groups),
        "matching_s": round(t_match, 3), "ranking_s": round(t_rank, 3),
        "weighted_s": round(t_weighted, 3), "weighted_total_s": round(t_rank + t_weighted, 3),
        "pooled_draws_timed": min(pooled_resamples, resamples),
        "pooled_s_scaled": None if pooled_full is None else round(pooled_full, 3),
        "speedup": None if not pooled_full else round(pooled_full / (t_rank + t_weighted), 1),
        "max_abs_difference": worst,
        "fallback_classes": sum(len(s.fallback_classes) for s in scorers.values()),
    }
