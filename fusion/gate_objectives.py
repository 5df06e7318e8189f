"""What a learned gate is trained on, and how its choice is judged.

A learned gate outputs, per frame, one score s_c per choice c (a branch for HydraFusion, a
configuration for EcoFusion); lower is better and the gate picks argmin_c s_c. Each choice has a
cost L_c on that frame (a branch's loss, a configuration's L_f, or L_joint = L_f + lambda_E E).

The papers train the gate to regress L_c with mean absolute error (HydraFusion Section 5.2.2,
EcoFusion Section 4.3): `mae`. The choice only depends on the differences between choices within a
frame, while L_c itself is dominated by how hard the frame is, which every choice shares (on the
`cpu` study: per-context mean L_f 0.8-4.5, choices within a context 0.1-0.9 apart). A regressor can
spend its capacity on the frame's difficulty and still rank the choices no better than a constant.
The objectives below target the decision instead; each is minimised by s = L + (a per-frame
constant), so a gate trained with any of them is read the same way (argmin of its scores):

    "mae"       mean_c |s_c - L_c|                                          (the papers')
    "centred"   mean_c |(s_c - mean_c' s_c') - (L_c - mean_c' L_c')|         (within-frame differences)
    "soft_ce"   -sum_c q_c log p_c,  q = softmax(-L / tau), p = softmax(-s / tau)
    "expected"  sum_c p_c (L_c - min_c' L_c'),  p = softmax(-s / tau)       (expected regret)
    "best_label" -log p_{c*},  c* = argmin_c L_c,  p = softmax(-s)           (the best choice's label)

"best_label" is the router target of the mixture-of-experts literature: a classifier of which
choice is best on the frame (the best-configuration label), blind to by how much; its scores are
logits (argmin of -log p is argmax p), not costs, so it is not minimised by s = L + c. A gate that
routes by the context label instead is the per-context constant below (`context_choice`): with
the context known exactly (the simulator's, or a perfect classifier), a lookup per context.

The other router target of the literature, weather-conditioned routing, classifies the frame's
context (weather, light, road) from the sensors and routes by it. `context_targets` gives it as a
cost target: each fitting frame's target is its context's row of the per-context table M (mean
cost of every choice over that context's fitting frames), so a gate regressing it (`mae`) learns
which of the 8 table rows its frame's features look like: a classifier over the contexts with the
lookup folded into its output (the minimiser of the expected error is the posterior-weighted
median row), whose argmin and ranking are those of the context it recognises. Its targets hold
the context label and nothing of the frame's own costs, unlike the objectives above; a context the
fitting frames lack gets the mean row.

`tau` is in units of L: `default_tau` takes the median over frames of the within-frame standard
deviation of L, so that q is neither one-hot nor uniform on a typical frame.

Judging a choice (`regret`, `judge`): the mean cost of what was chosen minus the mean cost of the
per-frame best (the a-posteriori oracle). A gate is worth its compute when its regret is below the
best constant choice's (`constant_choice`, fitted on training frames) and, to show it reads more than
the context, below the per-context constant's (`context_choice`: one fixed choice per context, what a
perfect context classifier with a lookup table gets).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np

from sim.registry import Registry

OBJECTIVES: Registry[Callable] = Registry(
    "gate objective",
    "objective(scores (B, n) tensor, costs (B, n) tensor, tau float) -> scalar tensor to minimise; "
    "minimised by scores = costs + a per-frame constant")


def _check(scores, costs) -> None:
    if scores.shape != costs.shape or scores.dim() != 2:
        raise ValueError(f"scores and costs: expected the same (B, n) shape, got {tuple(scores.shape)} and "
                         f"{tuple(costs.shape)}")


@OBJECTIVES.register("mae")
def mae_objective(scores, costs, tau: float = 1.0):
    """Mean absolute error of the scores against the costs (the papers' regression)."""
    _check(scores, costs)
    return (scores - costs).abs().mean()


@OBJECTIVES.register("centred")
def centred_objective(scores, costs, tau: float = 1.0):
    """Mean absolute error of the within-frame differences: both sides minus their frame mean."""
    _check(scores, costs)
    return ((scores - scores.mean(dim=1, keepdim=True)) - (costs - costs.mean(dim=1, keepdim=True))).abs().mean()


@OBJECTIVES.register("soft_ce")
def soft_ce_objective(scores, costs, tau: float = 1.0):
    """Cross entropy of softmax(-s / tau) against the soft target softmax(-L / tau), mean over frames."""
    import torch

    _check(scores, costs)
    target = torch.softmax(-costs / tau, dim=1)
    return -(target * torch.log_softmax(-scores / tau, dim=1)).sum(dim=1).mean()


@OBJECTIVES.register("expected")
def expected_regret_objective(scores, costs, tau: float = 1.0):
    """Expected regret of a choice drawn from softmax(-s / tau): sum_c p_c (L_c - min L), mean over
    frames. Its gradient moves probability towards the cheaper choices in proportion to what they
    save; as tau -> 0 it is the regret of argmin s."""
    import torch

    _check(scores, costs)
    p = torch.softmax(-scores / tau, dim=1)
    return (p * (costs - costs.min(dim=1, keepdim=True).values)).sum(dim=1).mean()


@OBJECTIVES.register("best_label")
def best_label_objective(scores, costs, tau: float = 1.0):
    """Cross entropy of softmax(-s) against the one-hot label of each frame's cheapest choice (ties:
    the first), mean over frames; `tau` is not used (a hard label has no temperature)."""
    import torch

    _check(scores, costs)
    return torch.nn.functional.cross_entropy(-scores, costs.argmin(dim=1))


def default_tau(costs) -> float:
    """The median over frames of the within-frame standard deviation of the costs (B, n), at least
    1e-3: the temperature at which a typical frame's soft target is neither one-hot nor uniform."""
    costs = np.asarray(costs, np.float64)
    if costs.ndim != 2 or not len(costs):
        raise ValueError(f"costs: expected a non-empty (B, n) array, got shape {costs.shape}")
    return float(max(np.median(costs.std(axis=1)), 1e-3))


# ----- judging a choice -------------------------------------------------------------------------


def choose(scores) -> np.ndarray:
    """argmin per row of (B, n) scores; ties go to the first choice."""
    return np.argmin(np.atleast_2d(np.asarray(scores, np.float64)), axis=1)


def chosen_cost(costs, choice) -> np.ndarray:
    """(B,) cost of each frame's chosen index."""
    costs = np.asarray(costs, np.float64)
    return costs[np.arange(len(costs)), np.asarray(choice, int)]


def regret(costs, choice) -> float:
    """Mean over frames of cost(chosen) - min cost: 0 for the oracle, nan for no frames."""
    costs = np.asarray(costs, np.float64)
    if not len(costs):
        return float("nan")
    return float((chosen_cost(costs, choice) - costs.min(axis=1)).mean())


def top_k_regret(costs, scores, k: int = 1) -> float:
    """Mean over frames of the summed cost of the k choices of lowest score minus the summed cost of
    the frame's k cheapest choices (issue 50, item 5): the regret of a gate that runs its top k. 0 for
    a gate that ranks the k cheapest first in any order; `regret` of the top choice at k = 1; 0 at
    k >= the number of choices. Ties in the scores go to the first choice, as `choose`; nan for no
    frames."""
    costs = np.atleast_2d(np.asarray(costs, np.float64))
    scores = np.atleast_2d(np.asarray(scores, np.float64))
    if costs.shape != scores.shape:
        raise ValueError(f"costs and scores: expected the same shape, got {costs.shape} and {scores.shape}")
    if k < 1:
        raise ValueError(f"k: must be >= 1, got {k}")
    if not len(costs):
        return float("nan")
    k = min(int(k), costs.shape[1])
    chosen = np.argsort(scores, axis=1, kind="stable")[:, :k]
    picked = np.take_along_axis(costs, chosen, axis=1).sum(axis=1)
    return float((picked - np.sort(costs, axis=1)[:, :k].sum(axis=1)).mean())


def constant_choice(costs_fit) -> int:
    """The one choice with the lowest mean cost over the fitting frames."""
    costs_fit = np.asarray(costs_fit, np.float64)
    if costs_fit.ndim != 2 or not len(costs_fit):
        raise ValueError(f"costs_fit: expected a non-empty (B, n) array, got shape {costs_fit.shape}")
    return int(np.argmin(costs_fit.mean(axis=0)))


def context_choice(costs_fit, contexts_fit: Sequence[str]) -> dict[str, int]:
    """One choice per context, the lowest mean cost over that context's fitting frames."""
    costs_fit = np.asarray(costs_fit, np.float64)
    contexts_fit = np.asarray(contexts_fit)
    if len(contexts_fit) != len(costs_fit):
        raise ValueError(f"contexts_fit: expected {len(costs_fit)} entries, got {len(contexts_fit)}")
    return {str(c): constant_choice(costs_fit[contexts_fit == c]) for c in sorted(set(contexts_fit.tolist()))}


def context_targets(costs_fit, contexts_fit: Sequence[str], contexts: Sequence[str] | None = None) -> np.ndarray:
    """(B, n) the per-context table's row of each frame of `contexts` (default: `contexts_fit`):
    the mean cost of every choice over the fitting frames of that frame's context; the mean over
    all fitting frames for a context they lack. The router target of a context classifier (module doc)."""
    costs_fit = np.asarray(costs_fit, np.float64)
    contexts_fit = np.asarray(contexts_fit).astype(str)
    if costs_fit.ndim != 2 or not len(costs_fit):
        raise ValueError(f"costs_fit: expected a non-empty (B, n) array, got shape {costs_fit.shape}")
    if len(contexts_fit) != len(costs_fit):
        raise ValueError(f"contexts_fit: expected {len(costs_fit)} entries, got {len(contexts_fit)}")
    rows = {c: costs_fit[contexts_fit == c].mean(axis=0) for c in set(contexts_fit.tolist())}
    fallback = costs_fit.mean(axis=0)
    wanted = contexts_fit if contexts is None else np.asarray(contexts).astype(str)
    return np.stack([rows.get(c, fallback) for c in wanted.tolist()]) if len(wanted) else \
        np.zeros((0, costs_fit.shape[1]))


def apply_context_choice(table: Mapping[str, int], contexts: Sequence[str], fallback: int) -> np.ndarray:
    """Each frame's choice from its context's entry (`fallback` for a context the table lacks)."""
    return np.array([table.get(str(c), fallback) for c in contexts], int)


def regret_gap(costs, choice_a, choice_b, groups: Sequence, resamples: int = 1000, seed: int = 0,
               level: float = 0.95) -> dict:
    """Regret of `choice_a` minus regret of `choice_b` (the same frames' costs, (B, n)): the estimate
    and its percentile interval over `resamples` draws of whole groups (a frame's sequence: frames of
    one sequence share their traffic and weather), with replacement. Below 0: `a` regrets less."""
    costs = np.asarray(costs, np.float64)
    d = chosen_cost(costs, choice_a) - chosen_cost(costs, choice_b)
    keys = sorted({str(g) for g in groups})
    index = {k: i for i, k in enumerate(keys)}
    g = np.array([index[str(x)] for x in groups])
    sums, counts = np.bincount(g, d, len(keys)), np.bincount(g, minlength=len(keys)).astype(np.float64)
    rng = np.random.default_rng(seed)
    draws = rng.integers(0, len(keys), (resamples, len(keys)))
    means = sums[draws].sum(axis=1) / counts[draws].sum(axis=1)
    lo, hi = np.percentile(means, [100 * (1 - level) / 2, 100 * (1 + level) / 2])
    return {"estimate": round(float(d.mean()), 6), "interval": [round(float(lo), 6), round(float(hi), 6)],
            "groups": len(keys), "resamples": resamples}


def judge(costs, choice, constant: int, context: np.ndarray | None = None) -> dict:
    """The choice beside the best constant, the per-context constant (when given) and the oracle:
    mean cost, regret, share of frames where the choice differs from the constant."""
    costs = np.asarray(costs, np.float64)
    choice = np.asarray(choice, int)
    const = np.full(len(costs), constant, int)
    out = {
        "frames": len(costs),
        "mean_cost": float(chosen_cost(costs, choice).mean()) if len(costs) else float("nan"),
        "regret": regret(costs, choice),
        "constant_mean_cost": float(chosen_cost(costs, const).mean()) if len(costs) else float("nan"),
        "constant_regret": regret(costs, const),
        "oracle_mean_cost": float(costs.min(axis=1).mean()) if len(costs) else float("nan"),
        "differs_from_constant": float((choice != constant).mean()) if len(costs) else float("nan"),
    }
    if context is not None:
        out["context_mean_cost"] = float(chosen_cost(costs, context).mean()) if len(costs) else float("nan")
        out["context_regret"] = regret(costs, context)
    return out
