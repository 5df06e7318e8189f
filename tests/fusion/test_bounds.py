"""fusion.bounds: the best constant per stratum is the one of best mAP in each stratum, its composite
takes each image from its stratum's choice, and re-choosing it inside every bootstrap draw gives an
interval of "room" (best constant per stratum minus a fixed source) that holds the truth; the
a-posteriori per-image oracle finds the known best choice and never scores below where it starts."""

import numpy as np

from fusion.bounds import (
    best_constant_map,
    best_constant_per_stratum,
    bootstrap_table,
    composite,
    greedy_choice,
)
from fusion.intervals import percentile_interval
from fusion.metrics import ImageMatches


def _image(rng, q: float) -> dict:
    """One image with one ground-truth box of class 1: found with probability q (a true positive
    scored in [0.5, 1)), and a false positive scored in [0, 1) with probability 0.5."""
    scores, tp = [], []
    if rng.random() < q:
        scores.append(0.5 + 0.5 * rng.random())
        tp.append(True)
    if rng.random() < 0.5:
        scores.append(rng.random())
        tp.append(False)
    order = np.argsort(-np.array(scores, float), kind="stable")
    return {1: (np.array(scores, float)[order], np.array(tp, bool)[order], 1)}


def _matches(quality: dict, contexts: list[str], seed: int) -> dict[str, ImageMatches]:
    """{source: ImageMatches} with each source's detection rate per context `quality[source][ctx]`."""
    rng = np.random.default_rng(seed)
    return {s: ImageMatches([_image(rng, q[c]) for c in contexts], (1,), "all") for s, q in quality.items()}


QUALITY = {"a": {"x": 0.9, "y": 0.3}, "b": {"x": 0.3, "y": 0.9}, "every": {"x": 0.6, "y": 0.6}}


def test_the_best_constant_per_stratum_is_the_best_in_each_and_the_composite_takes_its_rows():
    contexts = ["x"] * 60 + ["y"] * 60
    m = _matches(QUALITY, contexts, 0)
    rows = list(range(len(contexts)))
    assert best_constant_per_stratum(m, ["a", "b", "every"], rows, contexts) == {"x": "a", "y": "b"}
    # the order of the candidates does not change a clear choice; a tie goes to the first
    assert best_constant_per_stratum(m, ["every", "b", "a"], rows, contexts) == {"x": "a", "y": "b"}
    assert best_constant_per_stratum({"p": m["a"], "q": m["a"]}, ["q", "p"], rows, contexts) == {"x": "q", "y": "q"}
    both = composite(m, ["a"] * 60 + ["b"] * 60)
    assert both.per_image[0] is m["a"].per_image[0] and both.per_image[100] is m["b"].per_image[100]
    assert best_constant_map(m, ["a", "b", "every"], rows, contexts) == both.mean_ap(rows)
    assert best_constant_map(m, ["a", "b", "every"], rows, contexts) > max(m[s].mean_ap(rows) for s in m)


def test_room_interval_with_the_choice_made_in_every_draw_holds_the_truth():
    cands = ["a", "b", "every"]
    # the truth: the room of the population, approximated by 4000 images per context
    big = ["x"] * 4000 + ["y"] * 4000
    mb = _matches(QUALITY, big, 1)
    rows = list(range(len(big)))
    truth = best_constant_map(mb, cands, rows, big) - mb["every"].mean_ap(rows)
    # a study: 12 sequences of 5 frames per context
    contexts = ["x"] * 60 + ["y"] * 60
    m = _matches(QUALITY, contexts, 2)
    by_seq = {f"{c}{i // 5}": [] for i, c in enumerate(contexts)}
    for i, c in enumerate(contexts):
        by_seq[f"{c}{i // 5}"].append(i)
    draws = bootstrap_table(m, ["every"], by_seq, 300, 0,
                            {"oracle": lambda r: best_constant_map(m, cands, r, contexts)})
    assert draws.shape == (300, 2)
    lo, hi = percentile_interval(draws[:, 1] - draws[:, 0])
    assert lo <= truth <= hi and lo > 0, (lo, truth, hi)
    # the same draws as fusion.metrics.sequence_draws: a source's column is its mAP on each draw
    from fusion.metrics import sequence_draws

    first = next(iter(sequence_draws(by_seq, 1, 0)))
    assert draws[0, 0] == m["every"].mean_ap(first)


def test_the_greedy_oracle_takes_each_image_from_the_source_that_finds_it_and_never_loses_its_start():
    hit = {1: (np.array([0.9]), np.array([True]), 1)}
    miss = {1: (np.array([0.9]), np.array([False]), 1)}  # the box missed, a false alarm instead
    both = {1: (np.array([0.6, 0.5]), np.array([False, True]), 1)}  # a false alarm above the hit
    m = {"a": ImageMatches([hit] * 5 + [miss] * 5, (1,), "all"), "b": ImageMatches([miss] * 5 + [hit] * 5, (1,), "all"),
         "every": ImageMatches([both] * 10, (1,), "all")}
    choice = greedy_choice(m, ["a", "b", "every"], "every")
    assert choice == ["a"] * 5 + ["b"] * 5 and composite(m, choice).mean_ap(range(10)) == 1.0
    contexts = ["x"] * 40 + ["y"] * 40
    rnd = _matches(QUALITY, contexts, 3)
    rows = range(len(contexts))
    greedy = composite(rnd, greedy_choice(rnd, ["a", "b", "every"], "every"))
    assert greedy.mean_ap(rows) >= best_constant_map(rnd, ["a", "b", "every"], list(rows), contexts)
    assert greedy.mean_ap(rows) > rnd["every"].mean_ap(rows)
    assert greedy_choice({"a": m["a"]}, ["a"], "a") == ["a"] * 10
