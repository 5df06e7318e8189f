"""The context oracle's room, naive and split-sample, on synthetic problems whose true room is known."""

import numpy as np
import pytest

from fusion.context_room import covers_zero, mean_scorer, naive_room, null_rooms, room_for_context, split_room

CONTEXTS = np.repeat(np.arange(4), 12)  # 4 contexts x 12 sequences
K = 5  # constants; the reference (all branches) is constant 0


def _problem(rng, lift=0.0):
    """Per-sequence scores: a shared sequence difficulty plus independent noise per constant; constant 2
    is better by `lift` in contexts 0 and 1 (true room: lift / 2, every context the same weight)."""
    v = rng.normal(0.4, 0.1, (len(CONTEXTS), 1)) + rng.normal(0.0, 0.05, (len(CONTEXTS), K))
    v[CONTEXTS < 2, 2] += lift
    return v


def test_with_equal_constants_the_split_interval_holds_zero_and_the_naive_one_does_not():
    rng = np.random.default_rng(0)
    split_cover = naive_cover = 0
    draws = 12
    for i in range(draws):
        rec = room_for_context(mean_scorer(_problem(rng)), CONTEXTS, 0, K, resamples=60, seed=i, splits=10,
                               permutations=20)
        split_cover += covers_zero(rec["split"]["interval"])
        naive_cover += covers_zero(rec["naive"]["interval"])
        assert rec["naive"]["estimate"] > 0  # the best of 5 noisy constants chosen on the scored frames
        # noise alone makes the naive room; the split one's null is centred near 0
        assert rec["naive"]["null_mean"] > 0.01 and abs(rec["split"]["null_mean"]) < 0.01
    assert split_cover >= 10 and naive_cover == 0, (split_cover, naive_cover)


def test_a_real_room_is_resolved_by_the_split_estimate_and_stands_above_its_null():
    rng = np.random.default_rng(1)
    rec = room_for_context(mean_scorer(_problem(rng, lift=0.1)), CONTEXTS, 0, K, resamples=100, seed=0,
                           splits=20, permutations=30)
    s = rec["split"]
    assert s["interval"][0] > 0 and s["estimate"] > s["null_upper"]
    assert s["estimate"] == pytest.approx(0.05, abs=0.02)  # lift / 2


def test_the_naive_room_is_never_negative_and_the_split_room_chooses_only_on_what_it_does_not_score():
    rng = np.random.default_rng(2)
    v = _problem(rng)
    score = mean_scorer(v)
    assert naive_room(score, CONTEXTS, 0) >= 0
    # constant 1 is best on every even sequence and worst on every odd one: chosen on one half it is
    # scored on the other, where it loses against what the other half chose
    w = np.zeros((len(CONTEXTS), K))
    w[::2, 1], w[1::2, 1] = 1.0, -1.0
    assert naive_room(mean_scorer(w), CONTEXTS, 0) == pytest.approx(0.0)  # even and odd cancel in the pool
    # a half with more even sequences picks constant 1, and its other half then holds more odd ones
    assert split_room(mean_scorer(w), CONTEXTS, 0, np.random.default_rng(0), splits=20) < 0
    null = null_rooms(score, CONTEXTS, 0, K, permutations=10, seed=0, splits=2)
    assert null["naive"].shape == (10,) and np.all(null["naive"] >= 0)
    assert split_room(score, CONTEXTS, 0, np.random.default_rng(0), splits=5) == \
        split_room(score, CONTEXTS, 0, np.random.default_rng(0), splits=5)  # seeded


def test_bad_arguments_are_named():
    score = mean_scorer(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="values must be"):
        mean_scorer(np.zeros(3))
    with pytest.raises(ValueError, match="reference must be"):
        room_for_context(score, [0, 0, 1, 1], 2, 2)
    with pytest.raises(ValueError, match="splits must be"):
        split_room(score, [0, 0, 1, 1], 0, np.random.default_rng(0), splits=0)


def _matches(rng, n_images, classes=(1, 2), skill=0.6):
    """One source's VOC matching of `n_images` synthetic images: a few boxes per image, each detected
    with probability `skill` (a true positive at a high score), plus false alarms at lower scores."""
    from fusion.metrics import ImageMatches

    dets, gts = [], []
    for _ in range(n_images):
        n = int(rng.integers(1, 4))
        lab = rng.choice(classes, n)
        xy = rng.uniform(0, 400, (n, 2))
        boxes = np.c_[xy, xy + 40]
        hit = rng.random(n) < skill
        fa = int(rng.integers(0, 3))
        fxy = rng.uniform(500, 900, (fa, 2))
        dets.append({"boxes": np.r_[boxes[hit], np.c_[fxy, fxy + 40]],
                     "scores": np.r_[rng.uniform(0.5, 1.0, hit.sum()), rng.uniform(0.0, 0.7, fa)],
                     "labels": np.r_[lab[hit], rng.choice(classes, fa)]})
        gts.append({"boxes": boxes, "labels": lab})
    return ImageMatches.of(dets, gts, classes=list(classes))


def test_the_matches_scorer_is_pooled_map_and_reads_a_permuted_source_per_sequence():
    from fusion.bounds import composite
    from fusion.context_room import matches_scorer

    rng = np.random.default_rng(3)
    seq = np.repeat(np.arange(6), 3)  # 6 sequences of 3 images
    sources = [_matches(rng, len(seq), skill=s) for s in (0.4, 0.7, 0.9)]
    score = matches_scorer(sources, seq)
    draw = np.array([0, 0, 2, 5])  # sequence 0 twice
    rows = np.concatenate([np.flatnonzero(seq == i) for i in draw])
    assert np.allclose(score(draw), [m.mean_ap(rows) for m in sources])
    identity = np.tile(np.arange(3), (6, 1))
    assert np.allclose(score(draw, identity), score(draw))
    perm = np.tile(np.arange(3), (6, 1))
    perm[2] = [2, 0, 1]  # sequence 2 reads source 2 for constant 0, source 0 for 1, source 1 for 2
    for k in range(3):
        mixed = composite({str(i): m for i, m in enumerate(sources)}, [str(perm[s, k]) for s in seq])
        assert np.isclose(score(draw, perm)[k], mixed.mean_ap(rows))
    with pytest.raises(ValueError, match="same images"):
        matches_scorer([sources[0], _matches(rng, 5)], seq)
    # identical constants: no room, naive or split, and none under the null
    twin = matches_scorer([sources[1], sources[1]], seq)
    rec = room_for_context(twin, np.array([0, 0, 0, 1, 1, 1]), 0, 2, resamples=10, splits=4, permutations=5)
    assert all(rec[k]["estimate"] == 0 and rec[k]["null_upper"] == 0 for k in ("naive", "split"))
