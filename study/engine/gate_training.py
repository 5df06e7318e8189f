"""Training HydraFusion's branch gates on a trained run: `hydrabench train-gate` (HydraFusion
Section 5.2.2). The gate dataset they read (pooled stem features, per-branch losses) is
`study.engine.gate_data.GateData`.

**train-gate** trains the deep or attention gate on the run's train split (minus a validation
share of its sequences, which picks the epoch), Adam at lr 5e-5 (Section 5.3 gives the rate; the
optimiser is ours), on an objective of `fusion.gate_objectives`: the paper's regression of the per-branch loss with
mean absolute error, or one that targets the choice (the within-frame differences, a soft ranking,
the expected regret); by default ("auto") one gate per objective, keeping the lowest regret on the
validation sequences. The epoch is picked by the regret of the gate's
choice on the validation sequences (ties by MAE): of its top k where it runs k (`--k`). It reports the test split's MAE against constant
predictors (per-branch training mean and median) and the gate's choice against the best constant
branch, the per-context constant and the oracle.

    RUN/gates/<gate>/checkpoint.pt   latest state (gate, optimiser, epoch, RNG), every epoch
    RUN/gates/<gate>/gate.pt         the gate of the best validation epoch (what evaluate loads)
    RUN/gates/<gate>/metrics.csv     per epoch: the training objective, validation MAE and regret
    RUN/gates/<gate>/objectives/<objective>/   with --objective auto (the default): one gate per
                                     objective; the lowest validation regret is kept in gate.pt
    RUN/gates/<gate>/result.json     held-out MAE against the constant predictors, and the choice

The tables (Tables 3, 6, 7) that evaluate the trained gates are `study.engine.gate_tables`.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sim.errors import UserError
from sim.progress import progress as progress_bar
from study.engine.device import resolve_device
from study.engine.gate_data import GateData, cached_sha256, checkpoint_path
from study.outputs import atomic_path, torch_save_atomic, write_json_atomic

IN_SAMPLE = "in_sample"
"""Where (under a gate's directory) the study saves the same gate trained on the detectors' own
training frames, beside the one trained on the gate split. Here, not in `study.pipeline.evaluation`, so that
the gates stage's code (its key) holds no evaluation code."""

SELECT_ON = ("regret", "mae")
AUTO = "auto"
"""GateTrainConfig.objective: every objective, the best on validation regret kept."""
ROUTER = "context"
"""GateTrainConfig.objective: the context router, `mae` on `fusion.gate_objectives.context_targets`."""


# ----- training -------------------------------------------------------------------------------


@dataclass(frozen=True)
class GateTrainConfig:
    """One gate training run.

    Fields:
        gate: "deep" or "attention" (fusion.nets.branch_gates.GATES entries that learn).
        epochs: passes over the training frames.
        batch_size: frames per step.
        lr: Adam learning rate (HydraFusion 5.3 trains its gates at 5e-5).
        weight_decay: Adam L2 penalty.
        val_fraction: share of the gate split's sequences (per context; of the train split's when the
            run has no gate split) the epoch and objective are picked on (`study.experiments.selection.gate_frames`).
        targets: where the per-branch losses the gate learns come from (`study.experiments.selection.gate_frames`):
            "holdout" (the run's gate split: frames the detectors never saw), "train" (the detectors'
            own training frames) or "auto" (holdout when the run has a gate split).
        seed: initialisation, data order and validation split.
        grid: pooling grid (rows, columns) of the stem features.
        channels: widths of the three convs.
        hidden: MLP hidden width.
        dropout: before the MLP.
        checkpoint: which run checkpoint the gate serves ("latest" or "epoch-NNN").
        threads: torch CPU threads (0: the cores available).
        objective: what the gate is trained on (`fusion.gate_objectives.OBJECTIVES`): "mae" (the
            papers' regression of each choice's loss), "centred", "soft_ce" or "expected" (the
            decision: see that module), "best_label" (a classifier of the frame's best choice),
            or ROUTER "context" (a classifier of the frame's context, routing by the per-context
            table: `fit_objectives`); "auto" (the default) trains one gate per objective and keeps
            the one with the lowest validation regret (`fit_objectives`), so the objective is
            chosen on validation frames, never on test frames.
        tau: temperature of "soft_ce" and "expected", in loss units (0: `default_tau` of the
            fitting frames' losses, recorded in the result).
        select_on: what picks the epoch on the validation frames: "regret" (the mean loss of the
            chosen branch minus the per-frame best; ties by MAE) or "mae".
        k: the branches the gate runs per frame (its top k): the validation regret that picks the
            epoch and, with "auto", the objective is that of its top-k set (`top_k_regret`: the summed
            loss of the k it ranks first minus that of the frame's k best), so a gate that runs two
            is chosen for two (issue 50, item 5). 1: the top choice alone.
        context: the gate also reads the frame's context label (road layout and conditions, what
            a car can know: `fusion.nets.branch_gates.context_features`).
        pooling: "grid" (convs on the pooled grid) or "global" (an MLP on each stem channel's
            mean: compact features).
        fit_frames: fit on at most this many of the fitting frames, whole sequences taken evenly
            from each context in a seeded order (0 = all): the learning curve over the gate set's
            size (`study.experiments.selection.fewer_frames`); validation and test frames stay the same.
    """

    gate: str = "deep"
    epochs: int = 100
    batch_size: int = 32
    lr: float = 5e-5
    weight_decay: float = 0.0
    val_fraction: float = 0.15
    targets: str = "auto"
    seed: int = 0
    grid: tuple[int, int] = (8, 16)
    channels: tuple[int, int, int] = (64, 32, 16)
    hidden: int = 64
    dropout: float = 0.2
    checkpoint: str = "latest"
    threads: int = 0
    objective: str = "auto"
    tau: float = 0.0
    select_on: str = "regret"
    context: bool = False
    pooling: str = "grid"
    fit_frames: int = 0
    k: int = 1

    def __post_init__(self) -> None:
        from fusion.gate_objectives import OBJECTIVES

        if self.fit_frames < 0:
            raise UserError(f"fit_frames: must be >= 0 (0: every fitting frame), got {self.fit_frames}")
        if not isinstance(self.k, int) or self.k < 1:
            raise UserError(f"k: must be an integer >= 1 (the branches the gate runs), got {self.k!r}")

        if self.objective not in (AUTO, ROUTER):
            OBJECTIVES.get(self.objective)  # UserError naming the choices
        from study.experiments.selection import TARGETS

        if self.targets not in TARGETS:
            raise UserError(f"targets: expected one of {', '.join(TARGETS)}, got {self.targets!r}")
        if not self.tau >= 0:
            raise UserError(f"tau: must be >= 0 (0: the default temperature), got {self.tau}")
        if self.select_on not in SELECT_ON:
            raise UserError(f"select_on: expected one of {', '.join(SELECT_ON)}, got {self.select_on!r}")
        if self.pooling not in ("grid", "global"):
            raise UserError(f"pooling: expected grid or global, got {self.pooling!r}")
        if self.pooling == "global" and self.gate == "attention":
            raise UserError("pooling global: the attention gate attends over the pooled grid; use the deep gate")

    def gate_options(self) -> dict:
        extra = {"context": self.context, "pooling": self.pooling} if self.context or self.pooling != "grid" else {}
        return {"grid": list(self.grid), "channels": list(self.channels), "hidden": self.hidden,
                "dropout": self.dropout, **extra}


def mae(pred: np.ndarray, target: np.ndarray) -> float:
    return float(np.abs(np.asarray(pred, np.float64) - np.asarray(target, np.float64)).mean()) if len(target) else float("nan")


def reads_context(gate) -> bool:
    """Whether a learned gate (a ConvGate, or EcoFusion's configuration gate around one) reads the
    frame's context label besides the stem features."""
    return bool(getattr(getattr(gate, "net", gate), "context", False))


def gate_input(gate, feats: np.ndarray, metas) -> np.ndarray:
    """What `gate` consumes from cached pooled features: `feats` itself, or with the frames'
    context planes appended (`fusion.nets.branch_gates.with_context`) when the gate reads them."""
    if not reads_context(gate):
        return feats
    from fusion.nets.branch_gates import with_context

    return with_context(feats, metas)


def with_frame_context(reader, *pairs) -> tuple[np.ndarray, ...]:
    """Each (pooled features, dataset indices) pair with those frames' context planes appended
    (`fusion.nets.branch_gates.with_context`): the inputs of a gate trained with `context`."""
    from fusion.nets.branch_gates import with_context

    frames = reader.manifest["frames"]
    return tuple(with_context(x, [frames[int(i)] for i in idx]) for x, idx in pairs)


def predict_losses(gate, feats: np.ndarray, batch: int = 256, metas=None) -> np.ndarray:
    """A learned gate's predicted losses on prepared pooled features, in batches, without gradients.

    feats: (n, channels, rows, cols) pooled stem features as `GateData` stores them; with `metas`
    (the frames' meta dicts) the context planes of a gate that reads them are appended here,
    without them `feats` must already hold them (`gate_input`).
    Returns (n, n_branches) float32, or (n, n_configurations) for EcoFusion's configuration gates."""
    import torch

    if metas is not None:
        feats = gate_input(gate, feats, metas)
    gate.eval()
    out = []
    with torch.no_grad():
        for k in range(0, len(feats), batch):
            out.append(gate.predict_prepared(torch.from_numpy(feats[k:k + batch])).numpy())
    width = len(getattr(gate, "configurations", None) or gate.branches)
    return np.concatenate(out) if out else np.zeros((0, width), np.float32)


def ranking_agreement(pred: np.ndarray, truth: np.ndarray, k: int) -> float:
    """Mean share of the true k lowest-loss branches that the prediction also puts in its top k."""
    if not len(truth):
        return float("nan")
    p = np.argsort(pred, axis=1, kind="stable")[:, :k]
    t = np.argsort(truth, axis=1, kind="stable")[:, :k]
    return float(np.mean([len(set(a) & set(b)) / k for a, b in zip(p, t)]))


def fit_gate(gate, x_fit: np.ndarray, y_fit: np.ndarray, x_val: np.ndarray, y_val: np.ndarray, cfg: GateTrainConfig,
             out: Path | None = None, progress: bool = True, state: dict | None = None,
             extra: dict | None = None) -> dict:
    """Train `gate` (a ConvGate) on `cfg.objective` with Adam; checkpoint to `out` every epoch
    (resumable from the checkpoint dict `state`; `extra` is stored in every checkpoint).

    y are the per-frame costs of the gate's choices (branch losses, or L_f per configuration). The
    epoch is picked on the validation frames by `cfg.select_on`: the regret of the gate's top
    `cfg.k` (`top_k_regret`; at k = 1 its choice's cost minus the frame's best), ties broken by MAE;
    or MAE alone.

    Returns {"best_epoch", "best_val_mae", "best_val_regret", "tau", "history"}; the gate holds the
    weights of the best validation epoch (the last epoch when there is no validation set).
    """
    import torch

    from fusion.gate_objectives import OBJECTIVES, default_tau, top_k_regret

    if cfg.objective == AUTO:
        raise ValueError("fit_gate trains one objective; fit_objectives chooses among them (objective 'auto')")
    torch.manual_seed(cfg.seed)
    objective = OBJECTIVES.get(cfg.objective)
    tau = float(cfg.tau) if cfg.tau > 0 else default_tau(y_fit)
    if state is None:
        gate.fit_normalization(torch.from_numpy(x_fit), torch.from_numpy(y_fit))
    opt = torch.optim.Adam(gate.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    epoch, best_val, best_epoch, best_state, history = 0, None, 0, None, []
    if state is not None:
        gate.load_state_dict(state["gate"])
        opt.load_state_dict(state["optimizer"])
        epoch, best_val, best_epoch = state["epoch"], state["best_val"], state["best_epoch"]
        best_state, history = state["best_state"], state["history"]
        torch.set_rng_state(state["torch_rng"])
    y_fit_t = torch.from_numpy(y_fit)
    while epoch < cfg.epochs:
        gate.train()
        order = np.random.default_rng([cfg.seed, epoch]).permutation(len(x_fit))
        total, n = 0.0, 0
        # a live bar on a terminal; in a log file only the per-epoch JSON line below
        bar = progress_bar(total=len(order), desc=f"train-gate {gate.name} epoch {epoch + 1}/{cfg.epochs}",
                           enabled=progress and sys.stderr.isatty())
        for k in range(0, len(order), cfg.batch_size):
            b = order[k:k + cfg.batch_size]
            pred = gate.predict_prepared(torch.from_numpy(x_fit[b]))
            loss = objective(pred, y_fit_t[b], tau)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(b)
            n += len(b)
            bar.update(len(b))
            bar.set_postfix(**{cfg.objective: f"{total / max(n, 1):.4f}"})
        bar.close()
        epoch += 1
        row = {"epoch": epoch, f"train_{cfg.objective}": round(total / max(n, 1), 6), "val_mae": "", "val_regret": ""}
        if len(x_val):
            p_val = predict_losses(gate, x_val)
            row["val_mae"], row["val_regret"] = round(mae(p_val, y_val), 6), round(top_k_regret(y_val, p_val, cfg.k), 6)
            score = [row["val_regret"], row["val_mae"]] if cfg.select_on == "regret" else [row["val_mae"]]
        history.append(row)
        if not len(x_val) or best_val is None or score < best_val:
            best_val, best_epoch = (score if len(x_val) else None), epoch
            best_state = {k: v.detach().clone() for k, v in gate.state_dict().items()}
        if out is not None:
            torch_save_atomic({"gate": gate.state_dict(), "optimizer": opt.state_dict(), "epoch": epoch,
                               "best_val": best_val, "best_epoch": best_epoch, "best_state": best_state,
                               "history": history, "torch_rng": torch.get_rng_state(),
                               "config": dataclasses.asdict(cfg), **(extra or {})}, out / "checkpoint.pt")
            _write_csv(out / "metrics.csv", history)
        if progress:
            sys.stderr.write(json.dumps(row) + "\n")
    if best_state is not None:
        gate.load_state_dict(best_state)
    gate.eval()
    best = history[best_epoch - 1] if best_epoch else {}
    return {"best_epoch": best_epoch, "best_val_mae": best.get("val_mae") if best.get("val_mae") != "" else None,
            "best_val_regret": best.get("val_regret") if best.get("val_regret") != "" else None,
            "tau": round(tau, 6), "history": history}


def resume_state(ckpt: Path, settings: dict, fresh: bool, what: str, progress: bool) -> dict | None:
    """The checkpoint dict at `ckpt` to resume from, None to start afresh (no checkpoint, or
    `fresh`); UserError when it was trained with other `settings` (epochs and threads may differ)."""
    if not ckpt.exists() or fresh:
        return None
    from study.engine.checkpoints import load_checkpoint

    state = load_checkpoint(ckpt, ("config", "epoch", "gate", "optimizer", "best_state", "history", "torch_rng"))
    skip = ("epochs", "threads")
    settings = {k: v for k, v in settings.items() if k not in skip}
    config = {"k": 1, **state["config"]}  # a checkpoint from before `k` was chosen at 1
    old = {k: v for k, v in {**config, **{k: state.get(k) for k in settings if k not in config}}.items()
           if k not in skip}
    if json.loads(json.dumps(old)) != json.loads(json.dumps(settings)):
        diff = sorted(k for k in settings if json.loads(json.dumps(old.get(k))) != json.loads(json.dumps(settings[k])))
        raise UserError(f"{ckpt.parent} holds a {what} trained with other settings or on another checkpoint or "
                        f"dataset ({', '.join(diff)}); pass --fresh to train it again")
    if progress:
        sys.stderr.write(f"resuming {ckpt.parent} at epoch {state['epoch'] + 1}\n")
    return state


def fit_objectives(build, x_fit, y_fit, x_val, y_val, cfg: GateTrainConfig, out: Path, settings: dict, fresh: bool,
                   what: str, progress: bool = True, extra: dict | None = None, net=lambda g: g,
                   contexts_fit=None):
    """Fit a gate from `build()` on `cfg.objective`, or with "auto" one per objective (each in
    out/objectives/<name>/, resumable; the kept one's metrics.csv copied to out/), keeping the lowest
    validation regret (ties: the first in `OBJECTIVES` order). With "auto" and the fitting frames'
    `contexts_fit`, one more candidate, ROUTER ("context"): the context classifier of weather-
    conditioned routing, `mae` on each fitting frame's context row of the per-context table
    (`fusion.gate_objectives.context_targets`), judged like the others by its validation regret on
    the frames' own costs. Without validation frames "auto" has nothing to choose on and trains
    "mae", the papers', in out/. `net(gate)` is the module `fit_gate` trains. Returns (gate,
    fit_gate's result of the kept one, {objective: its validation regret, MAE, epoch and tau}, the
    kept objective)."""
    import torch

    from fusion.gate_objectives import OBJECTIVES, context_targets

    several = cfg.objective == AUTO and len(x_val) > 0
    names = list(OBJECTIVES.names()) if several else ["mae" if cfg.objective == AUTO else cfg.objective]
    if several and contexts_fit is not None:
        names.append(ROUTER)
    if ROUTER in names and contexts_fit is None:
        raise ValueError(f"objective {ROUTER!r}: needs the fitting frames' contexts (contexts_fit)")
    fits, gates = {}, {}
    for name in names:
        sub = out / "objectives" / name if several else out
        sub.mkdir(parents=True, exist_ok=True)
        router = name == ROUTER
        c = dataclasses.replace(cfg, objective="mae" if router else name)
        targets = context_targets(y_fit, contexts_fit).astype(y_fit.dtype) if router else y_fit
        tag = {"router": ROUTER} if router else {}  # in the checkpoint: a router resumes only as one
        state = resume_state(sub / "checkpoint.pt", {**settings, "objective": c.objective, **tag}, fresh, what,
                             progress)
        torch.manual_seed(cfg.seed)
        gate = build()
        if progress and len(names) > 1:
            sys.stderr.write(f"{what}: objective {name}\n")
        fits[name] = fit_gate(net(gate), x_fit, targets, x_val, y_val, c, out=sub, progress=progress, state=state,
                              extra={**(extra or {}), **tag})
        gates[name] = gate
    scored = {n: f["best_val_regret"] for n, f in fits.items() if f["best_val_regret"] is not None}
    kept = min(scored, key=scored.get) if scored else names[0]
    if several:
        import shutil

        shutil.copyfile(out / "objectives" / kept / "metrics.csv", out / "metrics.csv")
    table = {n: {"val_regret": f["best_val_regret"], "val_mae": f["best_val_mae"], "best_epoch": f["best_epoch"],
                 "tau": f["tau"]} for n, f in fits.items()}
    return gates[kept], fits[kept], table, kept


OBJECTIVE_LABEL = {"mae": "mean absolute error", "centred": "mean absolute error of the within-frame differences",
                   "soft_ce": "cross entropy against softmax(-L / tau)", "expected": "expected regret under softmax(-s / tau)",
                   "best_label": "cross entropy against the best choice's label",
                   ROUTER: "mean absolute error against the frame's context row of the per-context table"}


def choice_table(pred: np.ndarray, y_fit: np.ndarray, y_test: np.ndarray, contexts_fit, contexts_test,
                 names: list[str], sequences_test=None, resamples: int = 1000) -> dict:
    """The gate's one choice per test frame (argmin of its predictions) beside the best constant and
    the per-context constant (both fitted on the fitting frames) and the oracle: mean test loss of
    what each chooses, regret, and how often the gate differs from the constant; with the test frames'
    `sequences_test`, the 95 % intervals of gate minus constant and gate minus per-context constant
    regret over test sequences (`fusion.gate_objectives.regret_gap`)."""
    from fusion.gate_objectives import (
        apply_context_choice,
        choose,
        constant_choice,
        context_choice,
        judge,
        regret_gap,
    )

    const = constant_choice(y_fit)
    table = context_choice(y_fit, contexts_fit)
    chosen, by_context = choose(pred), apply_context_choice(table, contexts_test, const)
    j = judge(y_test, chosen, const, by_context)
    out = {**{k: (round(v, 6) if isinstance(v, float) else v) for k, v in j.items()},
           "constant": names[const], "per_context_constant": {c: names[i] for c, i in table.items()}}
    if sequences_test is not None and len(y_test):
        out["minus_constant"] = regret_gap(y_test, chosen, np.full(len(y_test), const), sequences_test, resamples)
        out["minus_context"] = regret_gap(y_test, chosen, by_context, sequences_test, resamples)
    return out


def _write_csv(path: Path, rows: list[dict]) -> None:
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def train_gate(run_dir, data, cfg: GateTrainConfig, progress: bool = True, fresh: bool = False, setup=None,
               out: Path | None = None) -> dict:
    """Build the gate dataset when missing, train the gate, report held-out MAE (see module doc).

    `setup` (`study.engine.device.DeviceSetup`; default: --device auto with `cfg.threads`): where the run's
    network computes the gate dataset (stem features and per-sample losses, the expensive part, in
    float32). The gate itself, a few small convs on pooled features, trains on the CPU. `out`: where
    it is saved (default RUN/gates/<gate>; the study puts the in-sample comparison elsewhere)."""

    from fusion.nets.branch_gates import GATES, build_gate
    from sensors.dataset import DatasetReader
    from study.engine.scoring import load_run
    from study.experiments.selection import gate_frames

    cls = GATES.get(cfg.gate)
    if not cls.trainable:
        what = ("ranks by the a-posteriori losses, which need ground truth" if cfg.gate == "optimal"
                else "ranks from its knowledge table")
        raise UserError(f"--gate {cfg.gate}: nothing to train, the {cfg.gate} gate {what} (train deep or attention)")
    setup = setup or resolve_device(threads=cfg.threads, purpose="eval")
    run_dir, data = Path(run_dir), Path(data)
    model, run_cfg = load_run(run_dir, cfg.checkpoint, device=setup.device)
    reader = DatasetReader(data)
    frames = gate_frames(run_cfg, data, cfg.targets, cfg.val_fraction, cfg.seed, "train-gate")
    fit_idx, val_idx, test_idx = frames.fit, frames.val, frames.test
    if cfg.fit_frames:
        from study.experiments.selection import fewer_frames

        fit_idx = fewer_frames(reader, fit_idx, cfg.fit_frames, cfg.seed)
    gd = GateData(run_dir, data, model, cfg.checkpoint, cfg.grid)
    out = Path(out) if out is not None else run_dir / "gates" / cfg.gate
    requested = cfg.targets
    cfg = dataclasses.replace(cfg, targets=frames.targets)  # resolved: "auto" resumes a "holdout" gate and back
    settings = {**dataclasses.asdict(cfg), "data_key": gd.key}
    gd.ensure(fit_idx + val_idx + test_idx, progress=progress)
    x_fit, y_fit = gd.load(fit_idx)
    x_val, y_val = gd.load(val_idx)
    x_test, y_test = gd.load(test_idx)
    if cfg.context:  # the frames' context labels as constant planes after the pooled features
        x_fit, x_val, x_test = with_frame_context(reader, (x_fit, fit_idx), (x_val, val_idx), (x_test, test_idx))
    out.mkdir(parents=True, exist_ok=True)
    if setup.is_cuda:
        model.cpu()  # build_gate reads the model's layout; the gate trains on the CPU
    contexts = [[reader.manifest["frames"][int(i)]["context"] for i in idx] for idx in (fit_idx, test_idx)]
    gate, fitted, objectives, objective = fit_objectives(
        lambda: build_gate(cfg.gate, model, sensors=list(gd.sensors), **cfg.gate_options()),
        x_fit, y_fit, x_val, y_val, cfg, out, settings, fresh, f"{cfg.gate} gate", progress,
        extra={"data_key": gd.key}, contexts_fit=contexts[0])

    pred = predict_losses(gate, x_test)
    mean_c, median_c = y_fit.mean(axis=0), np.median(y_fit, axis=0)
    branches = list(model.branches)
    result = {
        "gate": cfg.gate, "run": str(run_dir), "data": str(data), "checkpoint": cfg.checkpoint,
        "optimizer": "Adam", "lr": cfg.lr, "loss": OBJECTIVE_LABEL[objective], "objective": objective,
        "targets": frames.targets, "targets_requested": requested, "gate_split": frames.holdout, "context": cfg.context,
        "pooling": cfg.pooling,
        "objective_requested": cfg.objective, "objectives": objectives,
        "tau": fitted["tau"], "epochs": cfg.epochs, "k": cfg.k,
        "selected_on": f"validation {cfg.select_on}" + (f" of the top {cfg.k}" if cfg.k > 1 and cfg.select_on == "regret" else ""),
        "best_epoch": fitted["best_epoch"], "val_mae": fitted["best_val_mae"], "val_regret": fitted["best_val_regret"],
        "choice": choice_table(pred, y_fit, y_test, contexts[0], contexts[1], branches,
                               [reader.manifest["frames"][int(i)]["shard"] for i in test_idx]),
        "train_frames": len(fit_idx), "val_frames": len(val_idx), "test_frames": len(test_idx),
        "test_mae": round(mae(pred, y_test), 6),
        "constant_mean_mae": round(mae(np.broadcast_to(mean_c, y_test.shape), y_test), 6),
        "constant_median_mae": round(mae(np.broadcast_to(median_c, y_test.shape), y_test), 6),
        "test_mae_per_branch": {b: round(mae(pred[:, j], y_test[:, j]), 6) for j, b in enumerate(branches)},
        "constant_mean_mae_per_branch": {b: round(mae(np.full(len(y_test), mean_c[j]), y_test[:, j]), 6)
                                         for j, b in enumerate(branches)},
        "top1_agreement_with_optimal": round(ranking_agreement(pred, y_test, 1), 4),
        "top3_overlap_with_optimal": round(ranking_agreement(pred, y_test, min(3, len(branches))), 4),
        "mean_test_loss_per_branch": {b: round(float(y_test[:, j].mean()), 6) for j, b in enumerate(branches)},
        "gate_data": str(gd.dir), "gate_path": str(out / "gate.pt"),
        # where and in which precision the gate data was computed (the gate itself trains in fp32)
        "compute": {k: gd.identity[k] for k in ("device", "precision")},
    }
    result["beats_constant"] = result["test_mae"] < result["constant_mean_mae"]
    torch_save_atomic({"name": cfg.gate, "options": {**cfg.gate_options(), "sensors": list(gd.sensors)},
                      "branches": branches, "state": gate.state_dict(), "data_key": gd.key,
                      "checkpoint": cfg.checkpoint, "checkpoint_sha256": gd.identity["checkpoint_sha256"],
                      "result": result}, out / "gate.pt")
    write_json_atomic(out / "result.json", result)
    return result


# ----- gates for evaluation -------------------------------------------------------------------

def load_trained_gate(run_dir, name: str, model, checkpoint: str = "latest"):
    """The gate `train_gate` saved in RUN/gates/<name>/gate.pt, for this checkpoint of the run."""

    from fusion.nets.branch_gates import build_gate

    run_dir = Path(run_dir)
    path = run_dir / "gates" / name / "gate.pt"
    if not path.exists():
        raise UserError(f"no trained {name} gate in {run_dir} (run: hydrabench train-gate {run_dir} DATA --gate {name})")
    from study.engine.checkpoints import load_checkpoint, load_weights

    saved = load_checkpoint(path, ("branches", "options", "state"))
    if saved.get("checkpoint_sha256") != cached_sha256(checkpoint_path(run_dir, checkpoint)):
        raise UserError(f"{path} was trained for another checkpoint of this run than {checkpoint!r}; "
                        f"train it again (hydrabench train-gate {run_dir} DATA --gate {name} --fresh)")
    if list(saved["branches"]) != list(model.branches):
        raise UserError(f"{path} ranks branches {saved['branches']}, the run has {list(model.branches)}")
    gate = build_gate(name, model, **saved["options"])
    load_weights(gate, saved["state"], path)
    return gate.eval()
