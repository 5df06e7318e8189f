"""EcoFusion's joint energy-performance optimisation (Section 3.3, Eq. 7-9; Algorithm 1 lines 4-8).

Given predicted fused losses L_f(phi) for every configuration and their energies E(phi):

- phi' = argmin L_f (the minimum-loss configuration);
- candidates Phi* = rho(L_f(Phi), gamma), Eq. 7. The paper writes two different rules:
    "equation": L_f(phi) - L_f(phi') <= L_f(phi') + gamma   (Eq. 7 as printed: L_f(phi) <= 2 L_f(phi') + gamma)
    "prose":    L_f(phi) - L_f(phi') <= gamma               ("a fusion loss within gamma of phi*")
  The text also says gamma = 0 keeps only phi', which holds for the prose rule and not for the
  equation (which then still keeps every configuration up to twice the best loss). The default is
  the prose rule: it is the one whose gamma means what Sections 3.3 and 5.3 say it means
  ("the maximum deviation in performance from the best performing configuration"), and its
  candidate set does not grow with the loss scale. Both are available (`rule=`).
- L_joint(phi, lambda_E) = (1 - lambda_E) L_f(phi) + lambda_E E(phi), Eq. 8;
- phi* = argmin over Phi* of L_joint, Eq. 9 (ties: the lower energy, then the first in Phi order).

Energy units. The paper's E is joules on a Drive PX2 (0.9-3.8 J, Table 1) against losses of about
1, so its lambda_E values (0.01, 0.05, 0.1) weigh joules of that machine. To make lambda_E mean the
same on every machine, `normalise_energy` expresses E relative to the late-fusion configuration
measured on the same machine and scales it to the paper's late-fusion energy:
E_hat(phi) = E(phi) / E(late) * 3.798 J ("px2": PX2-equivalent joules, Table 1), or leaves the
ratio E(phi) / E(late) ("late"). Either way the machine's power and speed cancel.

Loss units. L_f is the sum of detection loss terms, whose size depends on the dataset, the
detectors and how hard the frames are (the paper's is about 1, Table 2 and Figure 4; ours 0.8-4.5
per context). Left raw, the same lambda_E and gamma mean different trade-offs on every dataset.
`normalise_loss` divides L_f by late fusion's mean L_f over the training frames ("late", the
default): late fusion sits at 1 on the loss axis as on the paper's (0.9 for its attention gate at
lambda_E 0), and gamma is a share of late fusion's loss: gamma 0.5 admits every configuration whose
predicted loss is within half of late fusion's mean loss of the best one, the paper's gamma 0.5 on
its losses of about 1. "raw" keeps L_f as it is. With E on the "px2" scale (late fusion at 3.798)
and L on the "late" scale (late fusion at 1), lambda_E weighs the two in the paper's proportions.
"""

from __future__ import annotations

import numpy as np

CANDIDATE_RULES = ("prose", "equation")
DEFAULT_RULE = "prose"
DEFAULT_GAMMA = 0.5
"""Section 5: "In all of our experiments, we set gamma = 0.5"."""
PAPER_LATE_ENERGY_J = 3.798
"""EcoFusion Table 1: late fusion (C_L + C_R + L + R) on the Drive PX2, 3.798 J."""
ENERGY_SCALES = ("px2", "late", "joules")
LOSS_SCALES = ("late", "raw")


def candidates(losses, gamma: float = DEFAULT_GAMMA, rule: str = DEFAULT_RULE) -> np.ndarray:
    """Eq. 7: the candidate mask Phi* of predicted losses (B, n) or (n,) -> bool of the same shape."""
    if rule not in CANDIDATE_RULES:
        raise ValueError(f"rule: expected one of {CANDIDATE_RULES}, got {rule!r}")
    if gamma < 0:
        raise ValueError(f"gamma: must be >= 0, got {gamma}")
    losses = np.asarray(losses, np.float64)
    if not np.isfinite(losses).all():
        raise ValueError("losses: predicted losses must be finite")
    best = losses.min(axis=-1, keepdims=True)  # L_f(phi')
    if rule == "equation":
        return losses - best <= best + gamma  # Eq. 7 as printed
    return losses - best <= gamma  # "within gamma of the best"


def joint_loss(losses, energy, lambda_e: float):
    """Eq. 8: L_joint = (1 - lambda_E) L_f + lambda_E E (broadcasting)."""
    if not 0.0 <= lambda_e <= 1.0:
        raise ValueError(f"lambda_e: must be in [0, 1], got {lambda_e}")
    return (1.0 - lambda_e) * np.asarray(losses, np.float64) + lambda_e * np.asarray(energy, np.float64)


def select(losses, energy, lambda_e: float, gamma: float = DEFAULT_GAMMA, rule: str = DEFAULT_RULE) -> np.ndarray:
    """Eq. 9: index of phi* per row of predicted losses (B, n) with energies (n,) -> (B,) int.

    Ties in L_joint go to the lower energy, then to the first configuration."""
    losses = np.atleast_2d(np.asarray(losses, np.float64))
    energy = np.asarray(energy, np.float64)
    if energy.shape != (losses.shape[1],):
        raise ValueError(f"energy: expected shape ({losses.shape[1]},), got {energy.shape}")
    mask = candidates(losses, gamma, rule)
    joint = np.where(mask, joint_loss(losses, energy, lambda_e), np.inf)
    best = joint.min(axis=1, keepdims=True)
    tied = joint <= best + 1e-12 * np.maximum(1.0, np.abs(best))
    e = np.where(tied, energy[None, :], np.inf)
    return np.argmin(e, axis=1)  # lowest energy among the tied; argmin keeps the first on equal energy


def normalise_energy(energy, late_energy: float, scale: str = "px2") -> np.ndarray:
    """E on a machine-independent scale (module docstring): "px2" E / E_late * 3.798 J,
    "late" E / E_late, "joules" E unchanged (machine-dependent lambda_E)."""
    if scale not in ENERGY_SCALES:
        raise ValueError(f"scale: expected one of {ENERGY_SCALES}, got {scale!r}")
    energy = np.asarray(energy, np.float64)
    if scale == "joules":
        return energy
    if not late_energy > 0:
        raise ValueError(f"late_energy: must be > 0, got {late_energy}")
    ratio = energy / late_energy
    return ratio * PAPER_LATE_ENERGY_J if scale == "px2" else ratio


def loss_unit(train_late_losses, scale: str = "late") -> float:
    """What `normalise_loss` divides by: the mean L_f of late fusion over the training frames
    ("late"), or 1 ("raw")."""
    if scale not in LOSS_SCALES:
        raise ValueError(f"scale: expected one of {LOSS_SCALES}, got {scale!r}")
    if scale == "raw":
        return 1.0
    late = np.asarray(train_late_losses, np.float64)
    unit = float(late.mean()) if late.size else float("nan")
    if not unit > 0:
        raise ValueError(f"late fusion's mean training L_f must be > 0, got {unit}")
    return unit


def normalise_loss(losses, unit: float) -> np.ndarray:
    """L_f on the scale lambda_E and gamma weigh (module docstring): L_f / unit (`loss_unit`)."""
    if not unit > 0:
        raise ValueError(f"unit: must be > 0, got {unit}")
    return np.asarray(losses, np.float64) / unit


def pareto_front(loss, energy) -> np.ndarray:
    """Indices of the points no other point beats in both loss and energy (minimising both),
    sorted by energy."""
    loss, energy = np.asarray(loss, float), np.asarray(energy, float)
    order = np.lexsort((loss, energy))
    front, best = [], np.inf
    for i in order:
        if loss[i] < best:
            front.append(int(i))
            best = loss[i]
    return np.array(front, int)
