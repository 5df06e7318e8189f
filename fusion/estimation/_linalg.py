"""Input checks and the few linear-algebra helpers every estimator here shares.

Every check raises a `ValueError` whose message starts with the name of the bad argument as the
caller wrote it (``R_list[2]``, ``P``), so a wrong shape is found without a debugger.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.linalg

# Relative eigenvalue floor below which an information matrix counts as singular: the smallest
# eigenvalue must exceed RCOND times the largest. 1e-12 leaves ~4 significant digits in P.
RCOND = 1e-12


class NotObservableError(ValueError):
    """The measurements do not determine every state component (singular information matrix)."""


def as_matrix(a, name: str, shape: tuple[int | None, int | None] = (None, None)) -> np.ndarray:
    """`a` as a finite float 2-D array of the given shape (None = any size), else ValueError."""
    m = np.asarray(a, dtype=float)
    if m.ndim != 2:
        raise ValueError(f"{name} must be a 2-D array of shape {_fmt_shape(shape)}, got shape {m.shape}")
    for axis, want in enumerate(shape):
        if want is not None and m.shape[axis] != want:
            raise ValueError(f"{name} must have shape {_fmt_shape(shape)}, got {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError(f"{name} contains NaN or inf")
    return m


def as_vector(v, name: str, length: int) -> np.ndarray:
    """`v` as a finite float vector of `length` entries; accepts (m,), (m, 1) or a scalar if m == 1."""
    a = np.asarray(v, dtype=float)
    if a.ndim == 0 and length == 1:
        a = a.reshape(1)
    elif a.ndim == 2 and a.shape[1] == 1:
        a = a[:, 0]
    if a.shape != (length,):
        raise ValueError(f"{name} must have shape ({length},), got {np.shape(v)}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or inf")
    return a


def as_covariance(C, name: str, dim: int) -> np.ndarray:
    """`C` as a symmetric positive-definite (dim, dim) float array; a scalar is allowed if dim == 1.

    Symmetry is checked to a relative 1e-8 and the result is exactly symmetrised; positive
    definiteness by a Cholesky factorisation.
    """
    a = np.asarray(C, dtype=float)
    if a.ndim == 0 and dim == 1:
        a = a.reshape(1, 1)
    m = as_matrix(a, name, (dim, dim))
    scale = max(float(np.max(np.abs(m))), np.finfo(float).tiny)
    if np.max(np.abs(m - m.T)) > 1e-8 * scale:
        raise ValueError(f"{name} must be symmetric")
    m = 0.5 * (m + m.T)
    try:
        np.linalg.cholesky(m)
    except np.linalg.LinAlgError:
        raise ValueError(
            f"{name} must be positive definite (smallest eigenvalue {np.linalg.eigvalsh(m)[0]:.3g})"
        ) from None
    return m


def check_lists(**lists: Sequence | None) -> int:
    """Check per-sensor lists passed by name: non-empty and as long as the first; return the length.

    Example: ``check_lists(H_list=H_list, R_true_list=R_true_list)``; None entries are skipped.
    """
    named = [(name, lst) for name, lst in lists.items() if lst is not None]
    for name, lst in named:
        if isinstance(lst, str | bytes) or not hasattr(lst, "__len__") or getattr(lst, "ndim", 1) == 0:
            raise ValueError(f"{name} must be a sequence with one entry per sensor")
        if len(lst) == 0:
            raise ValueError(f"{name} is empty: fusion needs at least one sensor")
    ref_name, ref = named[0]
    for name, lst in named[1:]:
        if len(lst) != len(ref):
            raise ValueError(f"{name} has {len(lst)} entries but {ref_name} has {len(ref)}: one per sensor")
    return len(ref)


def sensor_models(
    H_list: Sequence, R_list: Sequence, R_name: str = "R_list"
) -> tuple[list[np.ndarray], list[np.ndarray], int]:
    """Validate H_i (m_i, n) and R_i (m_i, m_i) SPD for every sensor; return them and n.

    R_name is the caller's name for the R list, used in error messages.
    """
    check_lists(H_list=H_list, **{R_name: R_list})
    Hs: list[np.ndarray] = []
    Rs: list[np.ndarray] = []
    n = None
    for i, (H, R) in enumerate(zip(H_list, R_list, strict=True)):
        H = as_matrix(H, f"H_list[{i}]", (None, n))
        n = H.shape[1]
        Hs.append(H)
        Rs.append(as_covariance(R, f"{R_name}[{i}]", H.shape[0]))
    assert n is not None
    return Hs, Rs, n


def measurements(z_list: Sequence, Hs: Sequence[np.ndarray]) -> tuple[list[np.ndarray], int | None]:
    """Validate z_i against H_i: each (m_i,) or, for K measurement sets at once, (K, m_i).

    Returns the arrays (each (m_i,) or (K, m_i)) and K (None for single vectors). All sensors must
    use the same form.
    """
    if len(z_list) != len(Hs):
        raise ValueError(f"z_list has {len(z_list)} entries but H_list has {len(Hs)}: one per sensor")
    zs: list[np.ndarray] = []
    batch: int | None = None
    for i, (z, H) in enumerate(zip(z_list, Hs, strict=True)):
        m = H.shape[0]
        a = np.asarray(z, dtype=float)
        if a.ndim == 2 and a.shape[1] == m and not (a.shape == (m, 1) and m > 1):
            this_batch: int | None = a.shape[0]
            if a.shape == (1, 1):
                this_batch = None
                a = a[0]
        else:
            a = as_vector(a, f"z_list[{i}]", m)
            this_batch = None
        if i == 0:
            batch = this_batch
        elif this_batch != batch:
            raise ValueError(
                f"z_list[{i}] has shape {np.shape(z)} but z_list[0] has shape {np.shape(z_list[0])}: "
                "give every sensor one vector (m_i,) or every sensor K rows (K, m_i)"
            )
        if not np.all(np.isfinite(a)):
            raise ValueError(f"z_list[{i}] contains NaN or inf")
        zs.append(a)
    return zs, batch


def spd_inverse(Y: np.ndarray, what: str) -> np.ndarray:
    """Inverse of a symmetric positive semi-definite information matrix Y.

    Raises NotObservableError if Y is singular to relative precision RCOND (the sensors leave some
    state direction unobserved).
    """
    w = np.linalg.eigvalsh(0.5 * (Y + Y.T))
    top = max(float(w[-1]), 0.0)
    if top == 0.0 or w[0] <= RCOND * top:
        rank = int(np.sum(w > RCOND * top)) if top > 0 else 0
        raise NotObservableError(
            f"{what} is singular (rank {rank} < {Y.shape[0]} state components): the sensors do not "
            "observe every state component; add a sensor or a prior"
        )
    c, low = scipy.linalg.cho_factor(Y)
    P = scipy.linalg.cho_solve((c, low), np.eye(Y.shape[0]))
    return 0.5 * (P + P.T)


def solve_spd(R: np.ndarray, B: np.ndarray) -> np.ndarray:
    """R^-1 B for symmetric positive-definite R, by Cholesky."""
    return scipy.linalg.cho_solve(scipy.linalg.cho_factor(R), B)


def symmetrize(P: np.ndarray) -> np.ndarray:
    """(P + P') / 2: removes the round-off asymmetry products like K R K' pick up."""
    return 0.5 * (P + np.swapaxes(P, -1, -2))


def check_prob(prob: float, name: str = "prob") -> float:
    """A probability strictly between 0 and 1."""
    p = float(prob)
    if not 0.0 < p < 1.0:
        raise ValueError(f"{name} must be strictly between 0 and 1, got {prob}")
    return p


def _fmt_shape(shape: tuple[int | None, ...]) -> str:
    return "(" + ", ".join("any" if s is None else str(s) for s in shape) + ")"
