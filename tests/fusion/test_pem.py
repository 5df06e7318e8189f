"""fusion.pem: the fit recovers a known model from data drawn from it; draws are deterministic by
seed; strength 1 is the fitted model."""

import math

import numpy as np
import pytest

from fusion import pem

SENSORS = ("radar",)
TRUE_W = {"intercept": -0.5, "log_radar_cells": 1.2, "range_m": -0.04}
TRUE_MU = np.array([0.03, -0.02, -0.05, 0.04])
TRUE_SD = np.array([0.04, 0.03, 0.05, 0.04])
TRUE_RATE = {"city": 0.5, "fog": 3.0}
TRUE_NEAR = 0.3
IMAGE = (672, 376)


def _table(rng, n):
    table = {f: np.zeros(n) for f in pem.branch_features(SENSORS)}
    table["log_radar_cells"] = np.log1p(rng.integers(0, 60, n).astype(float))
    table["range_m"] = rng.uniform(2, 90, n)
    table["class_1"] = np.ones(n)
    return table


def _true_p(table):
    z = TRUE_W["intercept"] + TRUE_W["log_radar_cells"] * table["log_radar_cells"] + TRUE_W["range_m"] * table["range_m"]
    return 1 / (1 + np.exp(-z))


def _frames(count=500, seed=0):
    """Frames drawn from a known PEM: 8 objects on a grid in the upper half, false alarms in the lower."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(count):
        ctx = "city" if k % 2 else "fog"
        n = 8
        x0 = 20 + 80 * np.arange(n)
        gt = np.column_stack([x0, np.full(n, 40.0), x0 + 50, np.full(n, 120.0)])
        table = _table(rng, n)
        found = rng.random(n) < _true_p(table)
        e = TRUE_MU + TRUE_SD * rng.standard_normal((n, 4))
        boxes = pem.apply_error(gt, e)[found]
        scores = rng.beta(5, 2, found.sum())
        dup = found & (rng.random(n) < TRUE_NEAR)  # a found object's duplicate, shifted by 0.6 of its width
        boxes = np.vstack([boxes, pem.apply_error(gt[dup], np.tile([0.6, 0, 0, 0], (dup.sum(), 1)))])
        scores = np.r_[scores, np.full(dup.sum(), 0.4)]
        m = rng.poisson(TRUE_RATE[ctx])
        fa = np.column_stack([rng.uniform(0, 600, m), rng.uniform(220, 300, m)])
        fa = np.column_stack([fa, fa + rng.uniform(10, 60, (m, 2))])
        det = np.vstack([boxes, fa])
        out.append(pem.FitFrame(det, np.r_[scores, rng.beta(2, 5, m)], np.ones(len(det), int),
                                {"boxes": gt, "labels": np.ones(n, int)}, table, ctx, IMAGE))
    return out


@pytest.fixture(scope="module")
def fitted():
    return pem.fit_branch(_frames(), SENSORS)


def test_fit_recovers_the_known_model(fitted):
    # detection probability: the fitted curve against the true one on fresh objects
    table = _table(np.random.default_rng(5), 4000)
    assert np.abs(fitted.detection_probability(table) - _true_p(table)).mean() < 0.03
    # box error: every range bin with data has the true mean and sd
    assert np.allclose(np.asarray(fitted.loc_mean), TRUE_MU, atol=0.012)
    assert np.allclose(np.asarray(fitted.loc_sd), TRUE_SD, atol=0.012)
    # false alarms near an object: only found objects have them, at the true rate, 0.6 of a width off
    assert fitted.near_rate[0] == 0 and fitted.near_rate[1] == pytest.approx(TRUE_NEAR, rel=0.1)
    assert np.allclose(np.asarray(fitted.near)[:, :4], [0.6, 0, 0, 0], atol=1e-9)
    # other false alarms: the Poisson rate per context
    for ctx, rate in TRUE_RATE.items():
        assert fitted.fa_rate[ctx] == pytest.approx(rate, rel=0.15)
    # scores: found objects' Beta(5, 2) median, false alarms' Beta(2, 5) median
    assert np.median([q[len(pem.QUANTILES) // 2] for q in fitted.tp_score_q["0"]]) == pytest.approx(0.736, abs=0.04)
    assert fitted.fa_score_q[len(pem.QUANTILES) // 2] == pytest.approx(0.264, abs=0.04)
    # classes: every match was class 1
    conf = np.asarray(fitted.confusion)
    assert conf[1, 1] / conf[1].sum() > 0.95


def test_sampling_is_deterministic_by_seed_and_refits(fitted):
    frames = _frames(200, seed=3)

    def draw(seed, strength=1.0):
        return [fitted.sample(pem.frame_rng(seed, k, 0), f.truth, f.table, f.context, IMAGE, strength)
                for k, f in enumerate(frames)]

    a, b, c = draw(1), draw(1), draw(2)
    assert all(np.array_equal(x[i], y[i]) for x, y in zip(a, b) for i in range(3))
    assert any(len(x[1]) != len(y[1]) or not np.array_equal(x[1], y[1]) for x, y in zip(a, c))
    # strength 1 is exactly the fitted model
    d = draw(1, strength=1.0)
    assert all(np.array_equal(x[i], y[i]) for x, y in zip(a, d) for i in range(3))
    # a frame's draws do not depend on which other frames are drawn
    one = fitted.sample(pem.frame_rng(1, 7, 0), frames[7].truth, frames[7].table, frames[7].context, IMAGE)
    assert np.array_equal(one[0], a[7][0])
    # the draws refit to the model they came from (detection rate and false-alarm rate)
    refit = pem.fit_branch([pem.FitFrame(x[0], x[1], x[2], f.truth, f.table, f.context, IMAGE)
                            for x, f in zip(a, frames)], SENSORS)
    expected = np.mean([fitted.detection_probability(f.table).mean() for f in frames])
    assert refit.counts["found"] / refit.counts["objects"] == pytest.approx(expected, abs=0.04)
    assert refit.fa_rate["fog"] == pytest.approx(fitted.fa_rate["fog"], rel=0.25)


def test_strength_raises_detection_odds_and_shrinks_errors(fitted):
    table = _table(np.random.default_rng(9), 500)
    p1, p4 = fitted.detection_probability(table), fitted.detection_probability(table, 4.0)
    odds = (p4 / (1 - p4)) / (p1 / (1 - p1))
    assert np.allclose(odds, 4.0, rtol=1e-6)
    frames = _frames(100, seed=4)
    found = {}
    for s in (1.0, 4.0):
        n, err = 0, []
        for k, f in enumerate(frames):
            boxes, _, _ = fitted.sample(pem.frame_rng(0, k, 0), f.truth, f.table, "city", IMAGE, s)
            m = pem.match(boxes, np.ones(len(boxes)), f.truth["boxes"])
            n += (m >= 0).sum()
            err.append(pem.box_error(boxes[m >= 0], f.truth["boxes"][m[m >= 0]]))
        found[s] = (n, np.vstack(err).std(axis=0))
    assert found[4.0][0] > found[1.0][0]
    assert np.all(found[4.0][1] < found[1.0][1] / 2)
    with pytest.raises(ValueError, match="strength"):
        fitted.sample(pem.frame_rng(0, 0, 0), frames[0].truth, frames[0].table, "city", IMAGE, 0.0)


def test_round_trip_and_errors(fitted):
    again = pem.BranchPEM.from_dict(fitted.to_dict())
    table = _table(np.random.default_rng(1), 50)
    assert np.array_equal(again.detection_probability(table), fitted.detection_probability(table))
    with pytest.raises(ValueError, match="no true boxes"):
        pem.fit_branch([], SENSORS)
    assert pem.match(np.zeros((0, 4)), np.zeros(0), np.zeros((3, 4))).shape == (0,)
    assert math.isclose(pem.box_iou([[0, 0, 2, 2]], [[1, 0, 3, 2]])[0, 0], 1 / 3)


def test_shared_loadings_are_recovered_and_keep_each_branch_calibrated():
    from scipy.special import ndtr

    rng = np.random.default_rng(11)
    n, true = 1500, np.array([0.8, 0.6, 0.0])
    p = rng.uniform(0.1, 0.9, (n, 3))
    z = true * rng.standard_normal((n, 1)) + np.sqrt(1 - true ** 2) * rng.standard_normal((n, 3))
    found = ndtr(z) < p
    lam = np.asarray(pem.fit_loadings(found, p, sweeps=2))
    # three branches identify the loadings through their pair products (the latent correlations)
    assert lam[0] * lam[1] == pytest.approx(true[0] * true[1], abs=0.12)
    assert lam[0] * lam[2] < 0.15 and lam[1] * lam[2] < 0.15
    # the pair correlation makes two branches find the same objects; each branch's rate is unchanged
    joint = pem.joint_found(p, lam)
    assert joint[0, 1] == pytest.approx((found[:, 0] & found[:, 1]).mean(), abs=0.02)
    assert np.allclose(np.diag(joint), p.mean(axis=0), atol=0.02)


def test_sampling_with_a_shared_normal(fitted):
    frames = _frames(300, seed=8)
    hits = {}
    for lam in (0.0, 0.9):
        both, each = 0, np.zeros(2)
        for k, f in enumerate(frames):
            shared = pem.shared_normals(5, k, len(f.truth["boxes"]))
            found = []
            for b in range(2):
                boxes, _, _ = fitted.sample(pem.frame_rng(5, k, b), f.truth, f.table, f.context, IMAGE, 1.0, shared, lam)
                m = pem.match(boxes, np.ones(len(boxes)), f.truth["boxes"])
                hit = np.zeros(len(f.truth["boxes"]), bool)
                hit[m[m >= 0]] = True
                found.append(hit)
            both += (found[0] & found[1]).sum()
            each += [found[0].sum(), found[1].sum()]
        hits[lam] = (both, each)
    # a loading of 0 is the independent model; 0.9 finds the same objects more often at the same rate
    assert hits[0.9][0] > 1.08 * hits[0.0][0]
    assert np.allclose(hits[0.9][1], hits[0.0][1], rtol=0.1)
    f = frames[0]
    plain = fitted.sample(pem.frame_rng(5, 0, 0), f.truth, f.table, f.context, IMAGE)
    zero = fitted.sample(pem.frame_rng(5, 0, 0), f.truth, f.table, f.context, IMAGE, 1.0,
                         pem.shared_normals(5, 0, len(f.truth["boxes"])), 0.0)
    assert all(np.array_equal(a, b) for a, b in zip(plain, zero))
