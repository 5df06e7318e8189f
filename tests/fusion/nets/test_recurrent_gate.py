"""fusion.nets.recurrent_gate: the GRU gate's windows, its untrained prediction, and that it learns
to carry what a single frame does not show (a task no per-frame gate can solve)."""

import numpy as np
import pytest
import torch

from fusion.nets.recurrent_gate import RecurrentGate, channel_means, evaluate, fit_recurrent


def _gate(inputs=6, branches=3, hidden=8, seed=0):
    torch.manual_seed(seed)
    g = RecurrentGate(inputs, branches, hidden=hidden, dropout=0.0)
    with torch.no_grad():  # a head that is not zero, so that windows can differ
        g.head.weight.normal_()
        g.head.bias.normal_()
    return g.eval()


def test_channel_means_average_each_channel_over_the_grid():
    x = np.arange(2 * 3 * 4 * 5, dtype=np.float16).reshape(2, 3, 4, 5)
    assert np.allclose(channel_means(x), x.astype(np.float32).mean(axis=(2, 3)))
    with pytest.raises(ValueError, match="rows, cols"):
        channel_means(x[0])


def test_an_untrained_gate_predicts_the_median_loss_of_its_fitting_frames():
    rng = np.random.default_rng(0)
    x, y = rng.normal(size=(50, 6)), rng.exponential(size=(50, 3))
    g = RecurrentGate(6, 3, hidden=8)
    g.fit_normalization(x, y)
    pred = g.predict_sequence(rng.normal(size=(7, 6)))
    assert np.allclose(pred, np.median(y, axis=0), atol=1e-6)


def test_a_window_as_long_as_the_sequence_is_the_whole_sequence_and_window_1_is_each_frame_alone():
    rng = np.random.default_rng(1)
    g = _gate()
    x = rng.normal(size=(9, 6)).astype(np.float32)
    whole = g.predict_sequence(x)
    assert np.allclose(g.predict_sequence(x, window=9), whole, atol=1e-5)
    assert np.allclose(g.predict_sequence(x, window=50), whole, atol=1e-5)
    alone = np.stack([g.predict_sequence(x[t:t + 1])[0] for t in range(9)])
    assert np.allclose(g.predict_sequence(x, window=1), alone, atol=1e-5)
    w3 = g.predict_sequence(x, window=3)
    for t in range(9):  # frame t from frames t-2..t only, from a zero state
        assert np.allclose(w3[t], g.predict_sequence(x[max(0, t - 2):t + 1])[-1], atol=1e-5)
    assert not np.allclose(w3, whole, atol=1e-3)  # memory beyond the window changes the prediction
    with pytest.raises(ValueError, match="window"):
        g.predict_sequence(x, window=0)


def _memory_task(n, T=5, seed=0):
    """The best of two branches is told by a cue on the first frame only; the later frames are noise."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        cue = rng.integers(0, 2)
        x = rng.normal(scale=1.0, size=(T, 4)).astype(np.float32)
        x[0, 0] = 3.0 if cue else -3.0
        x[1:, 0] = rng.normal(scale=1.0, size=T - 1)
        y = np.empty((T, 2), np.float32)
        y[:, cue], y[:, 1 - cue] = 0.2, 1.0
        out.append((x, y + rng.normal(scale=0.02, size=y.shape).astype(np.float32)))
    return out


def test_the_gate_learns_to_carry_a_cue_that_only_the_first_frame_shows():
    """A per-frame gate can only guess on frames 1..T-1 (regret 0.4 on them); the GRU carries the cue."""
    fit, val, test = _memory_task(128, seed=0), _memory_task(32, seed=1), _memory_task(64, seed=2)
    torch.manual_seed(0)
    g = RecurrentGate(4, 2, hidden=16, dropout=0.0)
    info = fit_recurrent(g, fit, val, epochs=20, lr=2e-2, batch_size=16, seed=0)
    assert info["best_epoch"] > 0 and info["history"][0]["epoch"] == 0
    assert evaluate(g, test)["regret"] < 0.05
    later = np.mean([(y[1:][np.arange(len(y) - 1), g.predict_sequence(x)[1:].argmin(axis=1)]
                      - y[1:].min(axis=1)).mean() for x, y in test])
    alone = np.mean([(y[1:][np.arange(len(y) - 1), g.predict_sequence(x, window=1)[1:].argmin(axis=1)]
                      - y[1:].min(axis=1)).mean() for x, y in test])
    assert later < 0.05 < 0.2 < alone  # without its memory the same net guesses


def test_the_epoch_kept_is_the_one_of_lowest_validation_regret():
    fit, val = _memory_task(64, seed=3), _memory_task(32, seed=4)
    torch.manual_seed(0)
    g = RecurrentGate(4, 2, hidden=8, dropout=0.0)
    info = fit_recurrent(g, fit, val, epochs=6, lr=1e-2, seed=0)
    best = min(info["history"], key=lambda r: (r["val_regret"], r["val_mae"], r["epoch"]))
    assert info["best_epoch"] == best["epoch"]
    assert evaluate(g, val)["regret"] == pytest.approx(best["val_regret"], abs=1e-6)
    assert info["kept_by"] == "validation regret"
    last = fit_recurrent(RecurrentGate(4, 2, hidden=8), fit, [], epochs=3, seed=0)  # nothing to choose on
    assert last["best_epoch"] == 3 and last["kept_by"].startswith("last epoch") and last["val_regret"] is None
    with pytest.raises(ValueError, match="fitting sequences"):
        fit_recurrent(g, [], val, epochs=1)
