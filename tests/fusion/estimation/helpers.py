"""Shared test helpers: random sensor setups (hypothesis strategies) and matrix checks."""

import numpy as np
from hypothesis import HealthCheck, assume, settings
from hypothesis import strategies as st

# No example database (keeps the worktree clean), no deadline (shared CI cores), and a fixed
# derivation of examples so a failure reproduces on every machine.
PROPERTY = settings(
    max_examples=100,
    deadline=None,
    database=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.filter_too_much, HealthCheck.too_slow],
)


def random_spd(rng: np.random.Generator, m: int, scale: float = 1.0, max_cond: float = 30.0) -> np.ndarray:
    """A random SPD matrix with eigenvalues log-uniform in [scale / max_cond, scale], random axes."""
    Q, _ = np.linalg.qr(rng.standard_normal((m, m)))
    eig = scale * np.exp(rng.uniform(-np.log(max_cond), 0.0, size=m))
    return (Q * eig) @ Q.T


def sqrtm_psd(C: np.ndarray) -> np.ndarray:
    w, V = np.linalg.eigh(C)
    return (V * np.sqrt(np.clip(w, 0.0, None))) @ V.T


def min_eig(A: np.ndarray) -> float:
    return float(np.linalg.eigvalsh(0.5 * (A + A.T))[0])


def rel_err(a, b) -> float:
    """|a - b| / max(|b|, tiny) in the max norm."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


@st.composite
def sensor_setups(draw, max_n: int = 4, max_sensors: int = 4, max_m: int = 3, min_sensors: int = 1):
    """(H_list, R_list, z_list): random linear sensors that together observe an n-state.

    The stacked H has full column rank with a bounded condition number and every R_i is SPD with
    a bounded condition number, a common random scale (1e-3..1e3) and per-sensor factors (0.1..10),
    so that round-off stays far below the tolerances the tests state.
    """
    n = draw(st.integers(1, max_n), label="n")
    n_sensors = draw(st.integers(min_sensors, max_sensors), label="sensors")
    ms = [draw(st.integers(1, max_m), label=f"m_{i}") for i in range(n_sensors)]
    assume(sum(ms) >= n)
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1), label="seed"))
    common = 10.0 ** draw(st.floats(-3, 3), label="log10 R scale")
    scales = [common * 10.0 ** draw(st.floats(-1, 1), label=f"log10 R_{i} factor") for i in range(n_sensors)]
    H_list = [rng.standard_normal((m, n)) for m in ms]
    R_list = [random_spd(rng, m, s) for m, s in zip(ms, scales)]
    H = np.vstack(H_list)
    assume(np.linalg.cond(H) < 30.0)
    Y = sum(Hi.T @ np.linalg.solve(Ri, Hi) for Hi, Ri in zip(H_list, R_list))
    assume(np.linalg.cond(Y) < 1e6)
    x_true = rng.standard_normal(n) * 10.0
    z_list = [
        Hi @ x_true + np.linalg.cholesky(Ri) @ rng.standard_normal(Hi.shape[0])
        for Hi, Ri in zip(H_list, R_list)
    ]
    return H_list, R_list, z_list
