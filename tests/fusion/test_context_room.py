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
