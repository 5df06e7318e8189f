"""Batch WLS (HydraFusion Eq. 5) and its sequential Kalman form."""

import numpy as np
import pytest
import scipy.linalg
from filterpy.kalman import KalmanFilter
from hypothesis import given

from fusion.estimation import (
    NotObservableError,
    SequentialFusion,
    WLSFusion,
    information,
    sequential_fusion,
    wls,
)

from .helpers import PROPERTY, rel_err, sensor_setups


@PROPERTY
@given(sensor_setups())
def test_wls_is_eq5_written_out(setup):
    H_list, R_list, z_list = setup
    y_hat, P = wls(H_list, R_list, z_list)
    # Eq. 5 with explicit inverses
    info = sum(H.T @ np.linalg.inv(R) @ H for H, R in zip(H_list, R_list))
    P_ref = np.linalg.inv(info)
    y_ref = P_ref @ sum(H.T @ np.linalg.inv(R) @ z for H, R, z in zip(H_list, R_list, z_list))
    assert rel_err(P, P_ref) < 1e-9
    assert rel_err(y_hat, y_ref) < 1e-9
    assert np.array_equal(P, P.T)
    assert rel_err(information(H_list, R_list), info) < 1e-9
    # Eq. 5 is Eq. 4 on the stacked measurement with block-diagonal R
    H = np.vstack(H_list)
    R = scipy.linalg.block_diag(*R_list)
    z = np.concatenate(z_list)
    Ri = np.linalg.inv(R)
    y_eq4 = np.linalg.solve(H.T @ Ri @ H, H.T @ Ri @ z)
    assert rel_err(y_hat, y_eq4) < 1e-9


@PROPERTY
@given(sensor_setups())
def test_sequential_kalman_equals_batch_wls(setup):
    H_list, R_list, z_list = setup
    y_hat, P = wls(H_list, R_list, z_list)
    x, P_seq = sequential_fusion(H_list, R_list, z_list)
    assert rel_err(x, y_hat) < 1e-9
    assert rel_err(P_seq, P) < 1e-9
    # the order of the sensors does not matter
    order = list(reversed(range(len(H_list))))
    x_rev, P_rev = sequential_fusion(
        [H_list[i] for i in order], [R_list[i] for i in order], [z_list[i] for i in order]
    )
    assert rel_err(x_rev, y_hat) < 1e-9
    assert rel_err(P_rev, P) < 1e-9


@PROPERTY
@given(sensor_setups(min_sensors=2))
def test_classes_equal_their_function_twins(setup):
    H_list, R_list, z_list = setup
    y_hat, P = wls(H_list, R_list, z_list)
    acc = WLSFusion(H_list[0].shape[1])
    seq = SequentialFusion(H_list[0].shape[1])
    for H, R, z in zip(H_list, R_list, z_list):
        acc.update(z, R, H)
        seq.update(z, R, H)
    assert acc.count == seq.count == len(H_list)
    assert rel_err(acc.x, y_hat) < 1e-9 and rel_err(acc.P, P) < 1e-9
    assert rel_err(seq.x, y_hat) < 1e-9 and rel_err(seq.P, P) < 1e-9
    assert seq.kf is not None  # the Kalman filter took over once the state was observable


def test_two_scalar_sensors_are_inverse_variance_weighted_and_beat_the_better_one():
    r1, r2, z1, z2 = 4.0, 1.0, 10.0, 12.0
    y_hat, P = wls([[[1.0]], [[1.0]]], [r1, r2], [z1, z2])
    assert y_hat[0] == pytest.approx((z1 / r1 + z2 / r2) / (1 / r1 + 1 / r2), rel=1e-12)
    assert P[0, 0] == pytest.approx(1.0 / (1 / r1 + 1 / r2), rel=1e-12)
    assert P[0, 0] < min(r1, r2)


def test_exact_initialisation_matters_a_vague_prior_does_not_reach_1e_9():
    """Why the sequential form starts from the first sensor's information, not from a huge P0."""
    rng = np.random.default_rng(3)
    H_list = [rng.standard_normal((2, 2)) for _ in range(3)]
    R_list = [np.diag([0.01, 0.02]) * (i + 1) for i in range(3)]
    z_list = [H @ np.array([30.0, -20.0]) + rng.normal(0, 0.1, 2) for H in H_list]
    y_hat, P = wls(H_list, R_list, z_list)
    kf = KalmanFilter(dim_x=2, dim_z=2)
    kf.P *= 1e6  # "uninformative" prior at x = 0: its information 1e-6 I is not zero
    for H, R, z in zip(H_list, R_list, z_list):
        kf.update(z.reshape(2, 1), R=R, H=H)
    vague_error = rel_err(kf.x[:, 0], y_hat)
    assert vague_error > 1e-9
    x, _ = sequential_fusion(H_list, R_list, z_list)
    assert rel_err(x, y_hat) < 1e-12 < vague_error


def test_batched_measurements_fuse_row_by_row():
    rng = np.random.default_rng(0)
    H_list = [rng.standard_normal((2, 3)), rng.standard_normal((1, 3)), rng.standard_normal((3, 3))]
    R_list = [np.eye(2), 2.0, np.diag([1.0, 2.0, 3.0])]
    Z = [rng.standard_normal((5, H.shape[0])) for H in H_list]
    y_batch, P = wls(H_list, R_list, Z)
    assert y_batch.shape == (5, 3)
    for k in range(5):
        y_k, P_k = wls(H_list, R_list, [z[k] for z in Z])
        assert rel_err(y_batch[k], y_k) < 1e-12
        assert np.array_equal(P, P_k)


def test_column_vectors_and_scalars_are_accepted():
    y1, P1 = wls([np.eye(2), [[1.0, 1.0]]], [np.eye(2), 0.5], [np.array([[1.0], [2.0]]), 3.0])
    y2, P2 = wls([np.eye(2), [[1.0, 1.0]]], [np.eye(2), [[0.5]]], [np.array([1.0, 2.0]), [3.0]])
    assert np.array_equal(y1, y2) and np.array_equal(P1, P2)


@pytest.mark.parametrize(
    ("H_list", "R_list", "z_list", "message"),
    [
        ([np.eye(2)], [np.eye(2), np.eye(2)], [np.zeros(2)], r"R_list has 2 entries but H_list has 1"),
        ([np.eye(2), np.eye(2)], [np.eye(2), np.eye(2)], [np.zeros(2)], r"z_list has 1 entries"),
        ([], [], [], r"H_list is empty"),
        (
            [np.eye(2), np.ones((2, 3))],
            [np.eye(2), np.eye(2)],
            [np.zeros(2)] * 2,
            r"H_list\[1\] must have shape \(any, 2\)",
        ),
        (
            [np.eye(2), np.ones(2)],
            [np.eye(2), np.eye(2)],
            [np.zeros(2)] * 2,
            r"H_list\[1\] must be a 2-D array",
        ),
        (
            [np.eye(2), np.eye(2)],
            [np.eye(2), np.eye(3)],
            [np.zeros(2)] * 2,
            r"R_list\[1\] must have shape \(2, 2\)",
        ),
        (
            [np.eye(2), np.eye(2)],
            [np.eye(2), np.diag([1.0, -1.0])],
            [np.zeros(2)] * 2,
            r"R_list\[1\] must be positive definite",
        ),
        (
            [np.eye(2), np.eye(2)],
            [[[1.0, 0.5], [0.0, 1.0]], np.eye(2)],
            [np.zeros(2)] * 2,
            r"R_list\[0\] must be symmetric",
        ),
        (
            [np.eye(2), np.eye(2)],
            [np.eye(2), np.eye(2)],
            [np.zeros(2), np.zeros(3)],
            r"z_list\[1\] must have shape \(2,\)",
        ),
        (
            [np.eye(2), np.eye(2)],
            [np.eye(2), np.eye(2)],
            [np.zeros(2), [np.nan, 0.0]],
            r"z_list\[1\] contains NaN",
        ),
    ],
)
def test_bad_input_names_the_list_and_index(H_list, R_list, z_list, message):
    with pytest.raises(ValueError, match=message):
        wls(H_list, R_list, z_list)
    with pytest.raises(ValueError, match=message):
        sequential_fusion(H_list, R_list, z_list)


def test_unobservable_state_is_a_clear_error():
    # two sensors that both see only x1 + x2: x1 - x2 is never observed
    H_list = [np.array([[1.0, 1.0]]), np.array([[2.0, 2.0]])]
    with pytest.raises(NotObservableError, match=r"singular \(rank 1 < 2 state components\).*do not observe"):
        wls(H_list, [1.0, 1.0], [1.0, 2.0])
    with pytest.raises(NotObservableError):
        sequential_fusion(H_list, [1.0, 1.0], [1.0, 2.0])
    acc = WLSFusion(2)
    acc.update([1.0], 1.0, H_list[0])
    with pytest.raises(NotObservableError, match="1 sensors fused so far"):
        _ = acc.x
    assert issubclass(NotObservableError, ValueError)
