"""Chi-square innovation gating: drop what the estimate and R cannot explain, keep the rest."""

import numpy as np
import pytest
from scipy import stats

from fusion.estimation import NotObservableError, gate_threshold, gated_update, gated_wls, wls

H2 = np.eye(2)
X_TRUE = np.array([20.0, 5.0])  # [m]
R_GOOD = [
    np.diag([0.3, 0.3]) ** 2,
    np.diag([0.2, 0.5]) ** 2,
    np.diag([0.4, 0.2]) ** 2,
    np.diag([0.25, 0.25]) ** 2,
]


def draw(rng, R):
    return X_TRUE + np.linalg.cholesky(R) @ rng.standard_normal(2)


def test_threshold_is_the_chi_square_quantile():
    assert gate_threshold(2, 0.99) == pytest.approx(9.2103, abs=1e-4)
    assert gate_threshold(1, 0.95) == pytest.approx(1.96**2, rel=1e-3)
    with pytest.raises(ValueError, match="prob must be strictly between 0 and 1"):
        gate_threshold(2, 1.5)
    with pytest.raises(ValueError, match="dim_z must be a positive integer"):
        gate_threshold(0)


@pytest.mark.parametrize("reference", ["prior", "running"])
def test_gate_against_a_prior_rejects_an_injected_outlier(reference):
    rng = np.random.default_rng(0)
    x0, P0 = X_TRUE + np.array([0.3, -0.2]), np.diag([0.5, 0.5]) ** 2
    z_list = [draw(rng, R) for R in R_GOOD]
    z_list[2] = X_TRUE + np.array([0.0, 6.0])  # 30 sigma off laterally: a ghost detection
    out = gated_update(x0, P0, [H2] * 4, R_GOOD, z_list, prob=0.99, reference=reference)
    assert out.kept.tolist() == [True, True, False, True]
    assert out.nis[2] > out.threshold[2] and np.all(out.nis[[0, 1, 3]] <= out.threshold[[0, 1, 3]])
    # the result is the ungated fusion of prior + the kept sensors (a prior is one more sensor)
    keep = [0, 1, 3]
    x_ref, P_ref = wls([H2] + [H2] * 3, [P0] + [R_GOOD[i] for i in keep], [x0] + [z_list[i] for i in keep])
    assert np.allclose(out.x, x_ref, rtol=0, atol=1e-12) and np.allclose(out.P, P_ref, rtol=0, atol=1e-14)
    # and much closer to the truth than the ungated fusion
    x_all, _ = wls([H2] * 5, [P0] + R_GOOD, [x0] + z_list)
    assert np.linalg.norm(out.x - X_TRUE) < 0.3 < np.linalg.norm(x_all - X_TRUE)


def test_false_rejections_happen_at_rate_one_minus_prob():
    rng = np.random.default_rng(1)
    n, prob = 2000, 0.95
    P0 = np.diag([0.4, 0.8]) ** 2
    R = np.array([[0.1, 0.05], [0.05, 0.2]])
    rejected = 0
    for _ in range(n):
        x0 = X_TRUE + np.linalg.cholesky(P0) @ rng.standard_normal(2)  # an honest prior
        out = gated_update(x0, P0, [H2], [R], [draw(rng, R)], prob=prob)
        rejected += not out.kept[0]
    rate = rejected / n
    assert abs(rate - (1 - prob)) < 4 * np.sqrt(prob * (1 - prob) / n)


def test_wls_without_prior_finds_the_outlier_by_leave_one_out():
    rng = np.random.default_rng(2)
    z_list = [draw(rng, R) for R in R_GOOD]
    z_list[1] = z_list[1] + np.array([4.0, 0.0])  # 20 sigma in x
    out = gated_wls([H2] * 4, R_GOOD, z_list)
    assert out.kept.tolist() == [True, False, True, True]
    x_ref, P_ref = wls([H2] * 3, [R_GOOD[i] for i in (0, 2, 3)], [z_list[i] for i in (0, 2, 3)])
    assert np.allclose(out.x, x_ref, atol=1e-12) and np.allclose(out.P, P_ref, atol=1e-14)
    assert out.nis[1] > 10 * out.threshold[1]
    assert np.all(out.nis[out.kept] <= out.threshold[out.kept])


def test_clean_sensors_are_all_kept():
    rng = np.random.default_rng(3)
    kept_all = 0
    for _ in range(50):
        out = gated_wls([H2] * 4, R_GOOD, [draw(rng, R) for R in R_GOOD], prob=0.999)
        kept_all += out.kept.all()
    assert kept_all >= 45  # a 0.1 % gate per sensor and test: almost never a false drop


def test_two_sensors_that_disagree_are_both_kept_and_flagged():
    z_list = [X_TRUE, X_TRUE + np.array([10.0, 0.0])]
    out = gated_wls([H2] * 2, R_GOOD[:2], z_list)
    # each was tested against the other and both fail, but without a third sensor nobody can say
    # which is wrong: both are kept and the conflict shows as kept & nis > threshold
    assert out.kept.all()
    assert np.all(out.nis > out.threshold)
    single = gated_wls([H2], R_GOOD[:1], [X_TRUE])
    assert single.kept.all() and np.isnan(single.nis).all()


def test_no_guess_when_two_exclusions_explain_the_data_equally_well():
    # -3, 0, +3 with unit variance: dropping either end leaves a consistent pair (NIS 4.5 < 6.63)
    out = gated_wls([np.eye(1)] * 3, [1.0] * 3, [[-3.0], [0.0], [3.0]])
    assert out.kept.all()
    assert out.nis[0] > out.threshold[0] and out.nis[2] > out.threshold[2]  # the conflict is reported
    # move one end further out and the data decide: only dropping it clears the others
    out = gated_wls([np.eye(1)] * 3, [1.0] * 3, [[-6.0], [0.0], [1.0]])
    assert out.kept.tolist() == [False, True, True]


def test_partial_sensors_exclusion_needs_redundancy_in_the_conflicting_axis():
    H_x, H_y = np.array([[1.0, 0.0]]), np.array([[0.0, 1.0]])
    R_list = [0.01, 0.01, np.eye(2) * 0.01]
    z_list = [[20.0], [5.0], X_TRUE + np.array([0.0, 3.0])]  # the 2-D sensor is 30 sigma off in y
    # only one other sensor sees y: the y-only sensor and the 2-D sensor accuse each other
    out = gated_wls([H_x, H_y, H2], R_list, z_list)
    assert out.kept.all()
    assert out.nis[0] <= out.threshold[0] and np.all(out.nis[1:] > out.threshold[1:])
    # a second y-only sensor agreeing with the first arbitrates: the 2-D sensor goes
    out = gated_wls([H_x, H_y, H2, H_y], R_list + [0.01], z_list + [[5.05]])
    assert out.kept.tolist() == [True, True, False, True]
    with pytest.raises(NotObservableError):
        gated_wls([H_x], [0.01], [[20.0]])


def test_two_outliers_among_six_are_both_excluded():
    rng = np.random.default_rng(7)
    R_list = R_GOOD + [np.eye(2) * 0.09, np.eye(2) * 0.04]
    z_list = [draw(rng, R) for R in R_list]
    z_list[0] = z_list[0] + np.array([5.0, 0.0])
    z_list[4] = z_list[4] + np.array([-4.0, 3.0])
    out = gated_wls([H2] * 6, R_list, z_list)
    assert out.kept.tolist() == [False, True, True, True, False, True]


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match=r"P must have shape \(2, 2\)"):
        gated_update(X_TRUE, np.eye(3), [H2], [np.eye(2)], [X_TRUE])
    with pytest.raises(ValueError, match="reference must be 'prior' or 'running'"):
        gated_update(X_TRUE, np.eye(2), [H2], [np.eye(2)], [X_TRUE], reference="posterior")
    with pytest.raises(ValueError, match=r"R_list\[0\] must be positive definite"):
        gated_wls([H2, H2], [np.zeros((2, 2)), np.eye(2)], [X_TRUE, X_TRUE])


def test_gated_nis_is_chi_square_distributed_for_clean_leave_one_out():
    """Leave-one-out NIS uses S = H P_-i H' + R with independent terms, so it is exactly chi2(m)."""
    rng = np.random.default_rng(5)
    values = []
    for _ in range(300):
        out = gated_wls([H2] * 4, R_GOOD, [draw(rng, R) for R in R_GOOD], prob=1 - 1e-9)
        values.append(out.nis[0])
    assert stats.kstest(values, stats.chi2(2).cdf).pvalue > 1e-3
