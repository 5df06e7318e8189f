"""EcoFusion's learned configuration gates: trained to regress L_f of every configuration from the
pooled stem features (`train_eco_gate`, `hydrabench eco-train-gate`) and loaded for evaluation
(`load_eco_gate`). See `study.eco`."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from fusion.eco.loss import FusedLossSpec
from sim.errors import UserError
from study.eco.data import EcoSettings, eco_gate_frames, open_eco_run
from study.engine.gate_training import (
    OBJECTIVE_LABEL,
    GateTrainConfig,
    choice_table,
    fit_objectives,
    mae,
    predict_losses,
    with_frame_context,
)
from study.outputs import torch_save_atomic, write_json_atomic


def train_eco_gate(run_dir, data, gate: str, cfg: GateTrainConfig, s: EcoSettings = EcoSettings(),
                   progress: bool = True, fresh: bool = False, out: Path | None = None) -> dict:
    """`hydrabench eco-train-gate`: the deep or attention configuration gate, trained on L_f of
    every configuration with `cfg.objective` (Adam; "auto": every objective, the lowest validation
    regret kept), on the run's gate split (`cfg.targets`, `study.experiments.selection.gate_frames`); saved in
    `out` (default RUN/eco/gates/<gate>/; resumable, like train-gate)."""
    from fusion.eco.config_gates import CONFIG_GATES, build_config_gate
    from sensors.dataset import DatasetReader

    cls = CONFIG_GATES.get(gate)
    if not cls.trainable:
        raise UserError(f"--gate {gate}: nothing to train (train deep or attention)")
    run_dir, data = Path(run_dir), Path(data)
    model, run_cfg, configs, ed = open_eco_run(run_dir, data, s, cfg.threads)
    frames = eco_gate_frames(run_cfg, data, s.max_frames, cfg.targets, cfg.val_fraction, cfg.seed, "eco-train-gate")
    fit_idx, val_idx, test = frames.fit, frames.val, frames.test
    reader = DatasetReader(data)
    ed.ensure(fit_idx + val_idx + test, batch_size=s.batch_size, progress=progress)
    out = Path(out) if out is not None else s.gate_dir(run_dir, gate)
    loss = dataclasses.asdict(ed.weights)
    requested = cfg.targets
    cfg = dataclasses.replace(cfg, targets=frames.targets)  # resolved: "auto" resumes a "holdout" gate and back
    settings = {**dataclasses.asdict(cfg), "gate": gate, "data_key": ed.key, "loss": loss}
    x_fit, x_val, x_test = (ed.arrays(i, ["features"])["features"] for i in (fit_idx, val_idx, test))
    y_fit, y_val, y_test = (ed.losses(i).astype(np.float32) for i in (fit_idx, val_idx, test))
    if cfg.context:  # the frames' context labels as constant planes after the pooled features
        x_fit, x_val, x_test = with_frame_context(reader, (x_fit, fit_idx), (x_val, val_idx), (x_test, test))
    out.mkdir(parents=True, exist_ok=True)
    meta = reader.manifest["frames"]
    contexts = [[meta[int(i)]["context"] for i in idx] for idx in (fit_idx, test)]
    g, fitted, objectives, objective = fit_objectives(
        lambda: build_config_gate(gate, model, configs, sensors=list(ed.sensors), **cfg.gate_options()),
        x_fit, y_fit, x_val, y_val, dataclasses.replace(cfg, gate=gate), out, settings, fresh,
        f"{gate} configuration gate", progress, extra={"data_key": ed.key, "loss": loss}, net=lambda c: c.net,
        contexts_fit=contexts[0])
    pred = predict_losses(g, x_test)
    mean_c = y_fit.mean(axis=0)
    from fusion.eco.optimise import select

    zero = np.zeros(len(configs))
    pick = select(pred, zero, 0.0, 0.0, "prose")
    result = {
        "gate": gate, "run": str(run_dir), "data": str(data), "configurations": len(configs), "optimizer": "Adam",
        "lr": cfg.lr, "loss": f"{OBJECTIVE_LABEL[objective]} of L_f per configuration", "loss_definition": loss,
        "objective": objective, "objective_requested": cfg.objective, "objectives": objectives,
        "targets": frames.targets, "targets_requested": requested, "gate_split": frames.holdout, "context": cfg.context,
        "pooling": cfg.pooling,
        "tau": fitted["tau"], "selected_on": f"validation {cfg.select_on}",
        "epochs": cfg.epochs, "choice": choice_table(pred, y_fit, y_test, *contexts, configs.names),
        "best_epoch": fitted["best_epoch"], "val_mae": fitted["best_val_mae"], "val_regret": fitted["best_val_regret"],
        "train_frames": len(fit_idx),
        "val_frames": len(val_idx), "test_frames": len(test), "test_mae": round(mae(pred, y_test), 6),
        "constant_mean_mae": round(mae(np.broadcast_to(mean_c, y_test.shape), y_test), 6),
        "test_loss_of_predicted_best": round(float(y_test[np.arange(len(test)), pick].mean()), 4),
        "test_loss_of_oracle_best": round(float(y_test.min(axis=1).mean()), 4),
        "test_loss_of_constant_best": round(float(y_test[:, int(np.argmin(mean_c))].mean()), 4),
        "gate_path": str(out / "gate.pt"), "eco_data": str(ed.dir),
    }
    torch_save_atomic({"name": gate, "options": {**cfg.gate_options(), "sensors": list(ed.sensors)},
                      "configurations": [list(m) for m in configs.members], "state": g.state_dict(),
                      "data_key": ed.key, "model_key": ed.model_key, "loss": loss, "result": result}, out / "gate.pt")
    write_json_atomic(out / "result.json", result)
    return result


def load_eco_gate(run_dir, name: str, model, configs, ed, s: EcoSettings = EcoSettings()):
    """A trained configuration gate from `s.gate_dir(run_dir, name)`/gate.pt, refused unless it was
    trained on a configuration dataset `ed` (an `EcoData`) of the same network, configurations,
    fusion and loss (on any frames: a gate fitted on a gate set runs on a test set) and this L_f."""

    from fusion.eco.config_gates import build_config_gate

    path = s.gate_dir(run_dir, name) / "gate.pt"
    fp = s.fp_flag()
    if not path.exists():
        raise UserError(f"no trained {name} configuration gate in {run_dir}{' for' + fp if fp else ''} "
                        f"(run: hydrabench eco-train-gate {run_dir} DATA --gate {name}{fp})")
    from study.engine.checkpoints import load_checkpoint, load_weights

    saved = load_checkpoint(path, ("options", "state"))
    if saved.get("data_key") != ed.key and saved.get("model_key") != ed.model_key:
        raise UserError(f"{path} was trained on another configuration dataset (checkpoint, configurations, fusion "
                        f"or loss differ); train it again with --fresh")
    if saved.get("loss", dataclasses.asdict(FusedLossSpec())) != dataclasses.asdict(s.loss_spec()):
        raise UserError(f"{path} was trained on another L_f (false-positive weight); train it again with --fresh")
    g = build_config_gate(name, model, configs, **saved["options"])
    load_weights(g, saved["state"], path)
    return g.eval()
