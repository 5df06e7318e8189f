"""Room for context without its selection optimism: a split-sample estimate, its interval, and its null.

The *context oracle* runs, in each context, the best of K constant choices (fixed branch sets); the
*room for context* is what it adds over one reference constant (all branches). Chosen and scored on
the same sequences, that room is >= 0 by construction whenever the reference is one of the K: the
maximum of K noisy scores is biased upwards, and a bootstrap that chooses again inside each draw
carries the same optimism into its interval. Two corrections, both here:

- `split_room`: choose per context on one half of the sequences (halves drawn within each context),
  score on the other half, and the same with the halves swapped (cross-fitting); averaged over many
  random splits. The choice never sees the sequences it is scored on, so a room of 0 is estimated
  without bias towards positive values (the choice is made on half the data, so a real room is
  slightly under-estimated: the estimate is conservative).
- `null_rooms`: the same statistic under a null of equal constants, made by permuting the K constants'
  labels independently within each sequence (exchangeable under the null; a sequence keeps its own
  difficulty). Its distribution says how much room noise alone makes, for the naive and the split
  estimates alike.

The room is sum_c w_c (score_c(chosen_c) - score_c(reference)), w_c each context's share of the
scored sequences' weight. For a score that is a weighted mean over sequences (`mean_scorer`) it is the
pooled room exactly; for a pooled AP it is the context-weighted mean of per-context rooms.

A scorer is a callable `score(seqs, perm) -> ndarray[K]`: each constant's score over the sequence
indices `seqs` (int array, repeats allowed: a bootstrap draw), where constant k in sequence i is read
from constant `perm[i, k]` (`perm` None: the identity). A scorer over stored detections pools, for
constant k, sequence i's detections of constant perm[i, k]; `mean_scorer` is the additive case.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from fusion.intervals import percentile_interval

Scorer = Callable[[np.ndarray, "np.ndarray | None"], np.ndarray]


def mean_scorer(values, weights=None) -> Scorer:
    """A scorer of per-sequence scores `values` [n_seq, K] (one score per sequence and constant): the
    weighted mean over the given sequences (`weights` [n_seq], frames per sequence say; default 1)."""
    v = np.asarray(values, dtype=float)
    if v.ndim != 2 or not v.size:
        raise ValueError(f"mean_scorer: values must be [n_seq, K] and non-empty, got shape {v.shape}")
    w = np.ones(len(v)) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (len(v),) or np.any(w < 0):
        raise ValueError("mean_scorer: weights must be one non-negative number per sequence")
    rows = np.arange(len(v))

    def score(seqs: np.ndarray, perm: np.ndarray | None = None) -> np.ndarray:
        seqs = np.asarray(seqs, dtype=int)
        x = v[seqs] if perm is None else v[rows[seqs, None], perm[seqs]]
        return (w[seqs, None] * x).sum(axis=0) / w[seqs].sum()

    return score


def matches_scorer(matches: Sequence, sequence_of_image: Sequence[int]) -> Scorer:
    """A scorer of pooled VOC mAP over K sources' per-image matching (`fusion.metrics.ImageMatches`, all
    on the same images, same classes): constant k's score over the sequences `seqs` is the mAP of the
    images of those sequences pooled (a sequence drawn twice counts twice), sequence i's images read
    from source `perm[i, k]`. `sequence_of_image`: each image's sequence, 0..n_seq-1.

    Exact and fast: the K sources' images are one ranked pool (`fusion.metrics.DrawScorer`), and a
    constant's score is that pool's AP under multiplicities that take, for each sequence, its images
    from the source the constant reads there (the others weigh 0)."""
    from fusion.metrics import DrawScorer, ImageMatches

    seq = np.asarray(sequence_of_image, dtype=int)
    if not len(matches) or seq.ndim != 1 or len(seq) != len(matches[0].per_image) or (len(seq) and seq.min() < 0):
        raise ValueError("matches_scorer: one sequence index >= 0 per image of the (non-empty) sources")
    if any(len(m.per_image) != len(seq) for m in matches):
        raise ValueError("matches_scorer: every source must hold the same images")
    k_sources, n = len(matches), len(seq)
    first = matches[0]
    pool = DrawScorer(ImageMatches([r for m in matches for r in m.per_image], first.classes, first.interpolation))
    n_seq = int(seq.max()) + 1
    columns = np.arange(n)

    def score(seqs: np.ndarray, perm: np.ndarray | None = None) -> np.ndarray:
        taken = np.bincount(np.asarray(seqs, dtype=int), minlength=n_seq)[seq]  # each image's multiplicity
        mult = np.zeros((k_sources, k_sources * n), np.int64)
        for k in range(k_sources):
            source = np.full(n, k) if perm is None else np.asarray(perm)[seq, k]
            mult[k, source * n + columns] = taken
        return pool.mean_ap_of_multiplicities(mult)

    return score


def _check(contexts, reference: int, k: int | None = None):
    c = np.asarray(contexts)
    if c.ndim != 1 or not len(c):
        raise ValueError("contexts must be one label per sequence, at least one sequence")
    if not isinstance(reference, (int, np.integer)) or reference < 0 or (k is not None and reference >= k):
        raise ValueError(f"reference must be the index of one of the constants, got {reference!r}")
    return c


def _room(score: Scorer, choose: np.ndarray, judge: np.ndarray, contexts: np.ndarray, reference: int,
          perm, weight: np.ndarray) -> float:
    """Room over the sequences `judge` of the per-context choice made on `choose` (the same array:
    the naive, in-sample room)."""
    total, room = 0.0, 0.0
    for c in np.unique(contexts[judge]):
        on_c = judge[contexts[judge] == c]
        pick = choose[contexts[choose] == c]
        w = weight[on_c].sum()
        total += w
        if not len(pick):
            continue  # nothing to choose on: the reference is kept, room 0
        best = int(np.argmax(score(pick, perm)))
        s = score(on_c, perm)
        room += w * (s[best] - s[reference])
    return room / total if total else float("nan")


def naive_room(score: Scorer, contexts, reference: int, seqs=None, perm=None, weights=None) -> float:
    """The context oracle's room chosen and scored on the same sequences `seqs` (default: all): what a
    study reports when it chooses on test. Optimistic (>= 0 when `reference` is among the constants)."""
    c = _check(contexts, reference)
    seqs = np.arange(len(c)) if seqs is None else np.asarray(seqs, dtype=int)
    w = np.ones(len(c)) if weights is None else np.asarray(weights, dtype=float)
    return _room(score, seqs, seqs, c, reference, perm, w)


def split_room(score: Scorer, contexts, reference: int, rng: np.random.Generator, splits: int = 20,
               seqs=None, perm=None, weights=None) -> float:
    """The room chosen on one half and scored on the other, both ways (cross-fitted), averaged over
    `splits` random halvings. Halves are drawn within each context over the distinct sequences of
    `seqs` (copies of a sequence in a bootstrap draw stay on one side, so nothing chosen on is scored);
    a context with one distinct sequence cannot be split and adds room 0."""
    if splits < 1:
        raise ValueError(f"splits must be >= 1, got {splits!r}")
    c = _check(contexts, reference)
    seqs = np.arange(len(c)) if seqs is None else np.asarray(seqs, dtype=int)
    w = np.ones(len(c)) if weights is None else np.asarray(weights, dtype=float)
    ids = np.unique(seqs)
    out = []
    for _ in range(splits):
        half = np.zeros(len(c), dtype=bool)
        for ctx in np.unique(c[ids]):
            members = rng.permutation(ids[c[ids] == ctx])
            half[members[: len(members) // 2]] = True
        a, b = seqs[half[seqs]], seqs[~half[seqs]]
        # a context whose distinct sequences all fell in one half is chosen on nothing: room 0 there
        out.append(0.5 * (_room(score, a, b, c, reference, perm, w) + _room(score, b, a, c, reference, perm, w)))
    return float(np.nanmean(out))


def _stratified_draw(rng: np.random.Generator, by_context: list[np.ndarray]) -> np.ndarray:
    return np.concatenate([m[rng.integers(0, len(m), len(m))] for m in by_context])


def null_rooms(score: Scorer, contexts, reference: int, k: int, permutations: int = 200, seed: int = 0,
               splits: int = 4, weights=None) -> dict:
    """The naive and the split room under a null of equal constants: in each of `permutations` draws the
    K constants' labels are permuted independently within every sequence. Returns {"naive": [...],
    "split": [...]} (one value per permutation)."""
    c = _check(contexts, reference, k)
    if permutations < 1:
        raise ValueError(f"permutations must be >= 1, got {permutations!r}")
    rng = np.random.default_rng(seed)
    naive, split = [], []
    for _ in range(permutations):
        perm = np.argsort(rng.random((len(c), k)), axis=1)
        naive.append(naive_room(score, c, reference, perm=perm, weights=weights))
        split.append(split_room(score, c, reference, rng, splits, perm=perm, weights=weights))
    return {"naive": np.asarray(naive), "split": np.asarray(split)}


def room_for_context(score: Scorer, contexts, reference: int, k: int, resamples: int = 200, seed: int = 0,
                     splits: int = 20, splits_per_draw: int = 2, permutations: int = 100, level: float = 0.95,
                     weights=None) -> dict:
    """The context oracle's room over `reference`, naive and split-sample, each with a `level` percentile
    interval over `resamples` draws of whole sequences within contexts (the naive one chosen again in
    every draw, as the study's; the split one split again in every draw, `splits_per_draw` times), and
    both under the null of equal constants (`null_rooms`: its mean and its upper `level` quantile).

    contexts: one label per sequence (the scorer's sequence order); k: the number of constants.
    Returns {"naive": {...}, "split": {...}}, each with "estimate", "interval", "null_mean",
    "null_upper"."""
    c = _check(contexts, reference, k)
    if resamples < 1:
        raise ValueError(f"resamples must be >= 1, got {resamples!r}")
    rng = np.random.default_rng(seed)
    by_context = [np.flatnonzero(c == ctx) for ctx in np.unique(c)]
    draws_naive, draws_split = [], []
    for _ in range(resamples):
        d = _stratified_draw(rng, by_context)
        draws_naive.append(naive_room(score, c, reference, seqs=d, weights=weights))
        draws_split.append(split_room(score, c, reference, rng, splits_per_draw, seqs=d, weights=weights))
    null = null_rooms(score, c, reference, k, permutations, seed + 1, weights=weights)
    est = {"naive": naive_room(score, c, reference, weights=weights),
           "split": split_room(score, c, reference, rng, splits, weights=weights)}
    draws = {"naive": draws_naive, "split": draws_split}
    return {name: {"estimate": est[name], "interval": percentile_interval(draws[name], level),
                   "null_mean": float(np.mean(null[name])),
                   "null_upper": float(np.quantile(null[name], level))} for name in est}


def covers_zero(interval: Sequence[float] | None) -> bool:
    """The interval holds 0 (its bounds included)."""
    return interval is not None and interval[0] <= 0.0 <= interval[1]
