"""Bounds that a selective fusion is measured against, from per-image VOC matchings
(`fusion.metrics.ImageMatches`), and the bootstrap draws they are resampled with.

A gate that reads only the context (the weather, the kind of road) can do no better than the best
*constant* choice of branches per context: `best_constant_per_stratum` finds it among candidate
configurations, `best_constant_map` scores that composite (each image takes the detections of its
stratum's chosen configuration; AP pooled over all the images, not a mean of the strata's APs).
Chosen on the frames it is scored on, it is a bound, not a method, and optimistic: with few
sequences the best of many configurations wins partly by luck. `bootstrap_table` therefore takes
derived columns that are recomputed on each draw, so the choice is made again inside every draw
(the honest interval of a max over configurations chosen on the same frames).

`greedy_choice` is the a-posteriori oracle of a per-image choice: each image's configuration chosen,
with every image's ground truth read, to raise the pooled mAP (a bound of any gate choosing among
the candidates per image, not a method).
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Iterable, Mapping, Sequence

import numpy as np

from fusion.metrics import ImageMatches, sequence_draws

Derived = Callable[[Sequence[int]], float]
"""A statistic recomputed on each draw: the draw's rows (repeats allowed) -> a number."""


def composite(matches: Mapping[str, ImageMatches], choice_of_row: Sequence[str]) -> ImageMatches:
    """The ImageMatches of a per-image choice: row i takes `matches[choice_of_row[i]]`'s row i (all
    sources matched on the same images, in the same order, over the same classes)."""
    first = matches[choice_of_row[0]] if len(choice_of_row) else next(iter(matches.values()))
    return ImageMatches([matches[c].per_image[i] for i, c in enumerate(choice_of_row)], first.classes,
                        first.interpolation)


def _finite(v: float) -> float:
    return v if np.isfinite(v) else -np.inf


def best_constant_per_stratum(matches: Mapping[str, ImageMatches], candidates: Sequence[str], rows: Sequence[int],
                              strata: Sequence[Hashable]) -> dict:
    """Per stratum present in `rows`, the candidate with the highest mAP over that stratum's rows
    (`strata[r]`: row r's stratum; ties and NaN: the first candidate in order wins)."""
    if not candidates:
        raise ValueError("best_constant_per_stratum: no candidates")
    by: dict = {}
    for r in rows:
        by.setdefault(strata[r], []).append(r)
    out = {}
    for s, rs in by.items():
        values = [_finite(matches[c].mean_ap(rs)) for c in candidates]
        out[s] = candidates[int(np.argmax(values))]
    return out


def best_constant_map(matches: Mapping[str, ImageMatches], candidates: Sequence[str], rows: Sequence[int],
                      strata: Sequence[Hashable]) -> float:
    """The mAP over `rows` of the best constant per stratum, chosen on those same rows
    (`best_constant_per_stratum`), each row scored with its stratum's choice."""
    choice = best_constant_per_stratum(matches, candidates, rows, strata)
    per_image = {}
    for r in rows:
        per_image.setdefault(r, matches[choice[strata[r]]].per_image[r])
    first = matches[candidates[0]]
    pooled = ImageMatches([per_image[r] for r in rows], first.classes, first.interpolation)
    return pooled.mean_ap(range(len(rows)))


def bootstrap_table(matches: Mapping[str, ImageMatches], names: Sequence[str], rows_by_sequence: Mapping,
                    resamples: int, seed: int, derived: Mapping[str, Derived] | None = None,
                    draws: Iterable[Sequence[int]] | None = None) -> np.ndarray:
    """(resamples, len(names) + len(derived)): each draw of whole sequences with replacement
    (`fusion.metrics.sequence_draws` over `rows_by_sequence` {sequence: [rows]}, seeded; or the
    `draws` given, rows per draw, e.g. `fusion.intervals.design_draws`) scored by each source's mAP,
    then each derived statistic recomputed on the draw's rows."""
    derived = dict(derived or {})
    out = np.empty((resamples, len(names) + len(derived)))
    picks_of = sequence_draws(rows_by_sequence, resamples, seed) if draws is None else draws
    i = -1
    for i, picks in enumerate(picks_of):
        if i >= resamples:
            raise ValueError(f"bootstrap_table: more than {resamples} draws given")
        out[i] = [matches[n].mean_ap(picks) for n in names] + [f(picks) for f in derived.values()]
    if i + 1 != resamples:
        raise ValueError(f"bootstrap_table: {i + 1} draws given, {resamples} expected")
    return out


def greedy_choice(matches: Mapping[str, ImageMatches], candidates: Sequence[str], start: str,
                  passes: int = 3) -> list[str]:
    """Per image, the candidate that maximises the pooled mAP of all the images (every other image's
    choice held), by coordinate ascent from `start` on every image: images in order, a change only for
    a strict gain, `passes` sweeps or until none changes. Reads every image's ground truth (through its
    matching): an a-posteriori oracle, a local optimum whose mAP is at least `start`'s. All candidates
    matched on the same images over the same classes. Each image's K alternatives are scored together
    (`fusion.metrics.DrawScorer` over the K sources' images pooled, each alternative a multiplicity)."""
    from fusion.metrics import DrawScorer

    names = list(candidates)
    if start not in names:
        raise ValueError(f"greedy_choice: start {start!r} is not a candidate")
    k, first = len(names), matches[names[0]]
    n = len(first.per_image)
    if any(len(matches[c].per_image) != n for c in names):
        raise ValueError("greedy_choice: every candidate must hold the same images")
    pool = DrawScorer(ImageMatches([r for c in names for r in matches[c].per_image], first.classes,
                                   first.interpolation))
    choice = np.full(n, names.index(start))
    taken = np.zeros(k * n, np.int64)
    taken[choice * n + np.arange(n)] = 1
    current = _finite(float(pool.mean_ap_of_multiplicities(taken[None])[0]))
    for _ in range(max(1, passes)):
        changed = False
        for i in range(n):
            trial = np.repeat(taken[None], k, axis=0)
            trial[:, choice[i] * n + i] = 0
            trial[np.arange(k), np.arange(k) * n + i] = 1
            values = np.array([_finite(v) for v in pool.mean_ap_of_multiplicities(trial)])
            best = int(np.argmax(values))
            if values[best] > current + 1e-12:
                taken = trial[best]
                choice[i], current, changed = best, values[best], True
        if not changed:
            break
    return [names[j] for j in choice]
