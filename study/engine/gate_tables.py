"""The gate tables on a trained run (HydraFusion Section 5.2.2, Tables 3, 6 and 7): each gate's
selection (per frame, the tuple of branch names it keeps) fused and scored. The gates are trained
by `study.engine.gate_training` (`hydrabench train-gate`).

`evaluate_gate` wires one gate into the network (`model.gate`), so only the branches
it selects run, and fuses them. `evaluate_all_gates` runs every branch once per frame and selects
and fuses subsets afterwards: the same numbers, because a branch's detections depend only on the
stem features of its own sensors (stems run on every frame either way, the gate reads all of
them), never on which other branches run; the tests check this equality.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from typing import Any

import numpy as np

from fusion.boxes import FUSION_METHODS, method_label
from sim.errors import UserError
from sim.progress import progress as progress_bar
from study.engine.device import resolve_device
from study.engine.gate_data import GateData
from study.engine.gate_training import load_trained_gate, mae
from study.numbers import rounded

TABLE_KS = (1, 3, 5, "all")
TABLE_FUSIONS = tuple(FUSION_METHODS.names())


def parse_k(text: Any, n_branches: int, field: str = "--k") -> int | str:
    """An int 1..n_branches or "all" (the table's column name); UserError naming `field` otherwise."""
    from fusion.nets.branch_gates import check_k

    if isinstance(text, str) and text.strip().lower() == "all":
        return "all"
    try:
        k = int(text)
    except (TypeError, ValueError):
        raise UserError(f"{field}: expected an integer 1..{n_branches} or 'all', got {text!r}") from None
    try:
        check_k(k, n_branches, field)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    return k


def table_ks(n_branches: int) -> list[int | str]:
    """The table's k columns that exist for this many branches: 1, 3, 5 below n, then all."""
    return [k for k in TABLE_KS if k == "all" or k < n_branches]


def make_gate(name: str, model, run_dir, checkpoint: str = "latest", k: int | str | None = None):
    """A ready gate: trained ones loaded from the run, the others built from the model."""
    from fusion.nets.branch_gates import GATES, build_gate

    cls = GATES.get(name)
    gate = load_trained_gate(run_dir, name, model, checkpoint) if cls.trainable else build_gate(name, model).eval()
    gate.k = None if k in (None, "all") else int(k)
    return gate


def selection_rates(selections: list[tuple[str, ...]], branches) -> dict[str, float]:
    """Branch -> percent of frames whose selection contains it, to 0.1 % (HydraFusion Table 7; the
    one rate of `compare`, `evaluate --all-gates` and the study)."""
    n = max(len(selections), 1)
    return {b: rounded(100.0 * sum(b in s for s in selections) / n, 1) for b in branches}


def _rates_per_context(selections, contexts, branches) -> dict[str, dict[str, float]]:
    by: dict[str, list] = defaultdict(list)
    for s, c in zip(selections, contexts):
        by[c].append(s)
    return {c: selection_rates(v, branches) for c, v in sorted(by.items())}


def setup_run(run_dir, data, split, weights, checkpoint, setup=None):
    from fusion.nets.branch_gates import gate_sensors
    from sensors.dataset import DatasetReader
    from study.engine.scoring import frames_for, load_run

    setup = setup or resolve_device(purpose="eval")
    model, cfg = load_run(run_dir, checkpoint, device=setup.device)
    model.device_setup = setup  # read by _loader, gate_on_device and the autocast of the gated forwards
    if not gate_sensors(model):
        raise UserError("gates need HydraFusion's shared stems (a gate reads every stem before choosing branches); "
                        f"this run's branches ({', '.join(model.branches)}) fuse their inputs and have none")
    indices, used_split = frames_for(cfg, data, split)
    if not indices:
        raise UserError(f"no frames to evaluate in the {used_split!r} split of {data}")
    bad = [b for b in (weights or {}) if b not in model.branches]
    if bad:
        raise UserError(f"--weights names {bad[0]!r}, which is not a branch of this run")
    return model, cfg, indices, used_split, DatasetReader(data)


def _loader(model, data, indices, batch_size, clear: bool = False):
    """Batches (inputs on the model's device, targets, metas), decoded by the setup's workers;
    `clear`: the frames' clear-weather twins."""
    from torch.utils.data import DataLoader

    from fusion.data import FrameDataset, collate
    from study.engine.device import to_device

    setup = model.device_setup
    ds = FrameDataset(data, indices, sensors=model.sensors, bev_size=model.transform.image_size("radar"),
                      uint8=setup.is_cuda, clear=clear)  # uint8 to a GPU, float32 there (`to_device`)
    for inputs, targets, metas in DataLoader(ds, batch_size=batch_size, shuffle=False, collate_fn=collate,
                                             num_workers=setup.workers, pin_memory=setup.is_cuda):
        yield to_device(inputs, None, setup.device)[0], targets, metas


def gate_on_device(gate, model):
    return gate.to(model.device_setup.device) if model.device_setup.is_cuda else gate


def _optimal_losses(run_dir, data, model, checkpoint, indices, progress) -> dict[int, dict[str, float]]:
    gd = GateData(run_dir, data, model, checkpoint)
    gd.ensure(indices, progress=progress)
    return dict(zip((int(i) for i in indices), gd.branch_losses(indices)))


def evaluate_gate(run_dir, data, gate: str, k=None, fusion: str = "soft-nms", split: str = "auto", weights=None,
                  checkpoint: str = "latest", batch_size: int = 4, progress: bool = True, setup=None) -> dict:
    """mAP of one gate at one k (None: 3, or every branch when there are fewer) with one fusion
    method, the gate wired into the network (`model.gate`): per frame only the k branches it
    selects run, then they are fused."""
    import torch

    from study.engine.scoring import fused, fusion_method, score, to_detections
    from study.engine.train import run_protocol

    method = fusion_method(fusion)
    model, _cfg, indices, used_split, reader = setup_run(run_dir, data, split, weights, checkpoint, setup)
    k = parse_k(min(3, len(model.branches)) if k is None else k, len(model.branches))
    g = gate_on_device(make_gate(gate, model, run_dir, checkpoint, k), model)
    losses = _optimal_losses(run_dir, data, model, checkpoint, indices, progress) if g.reads == "losses" else None
    calls: dict[str, int] = defaultdict(int)

    def count(module, args, _out):
        calls[module.name] += int(args[0][0].shape[0])

    hooks = [b.register_forward_hook(count) for b in model.branches.values()]
    model.gate = g
    per_frame = []
    try:
        with torch.no_grad():
            bar = progress_bar(total=len(indices), desc=f"evaluate {gate} k={k}", enabled=progress)
            for inputs, _targets, metas in _loader(model, data, indices, batch_size):
                if losses is not None:
                    metas = [dict(m, branch_losses=losses[int(m["dataset_index"])]) for m in metas]
                with model.device_setup.autocast():
                    dets = model(inputs, meta=metas)
                for meta, per in zip(metas, dets):
                    per_frame.append((meta, {n: to_detections(d) for n, d in per.items()}))
                bar.update(len(metas))
            bar.close()
    finally:
        model.gate = None
        for h in hooks:
            h.remove()
    branches = list(model.branches)
    result = score(fused(per_frame, branches, model.branch_frames, method, weights), reader, "camera_right",
                   protocol=run_protocol(_cfg))
    selections = [tuple(per) for _, per in per_frame]
    kk = str(k)
    result.update({
        "gate": gate, "k": k, "fusion": method, "split": used_split, "run": str(run_dir), "data": str(data),
        "map_table": {gate: {method_label(method): {kk: result["map"]}}},
        "selection_rate": {gate: {kk: selection_rates(selections, branches)}},
        "selection_rate_per_context": {gate: {kk: _rates_per_context(selections, [m["context"] for m, _ in per_frame],
                                                                      branches)}},
        "branch_runs_per_frame": round(sum(calls.values()) / max(len(per_frame), 1), 4),
        "branch_runs": dict(calls),
        "metric": "VOC all-point AP at IoU 0.5, right camera, difficult ground truth ignored",
    })
    return result


def top_k_selection(predicted, branches, k) -> list[tuple[str, ...]]:
    """A gate's selection: per frame, the tuple (in branch order) of the `k` branches (an int, or
    "all") with the lowest predicted loss. `predicted`: (frames, n_branches), columns in `branches`
    order."""
    import torch

    from fusion.nets.branch_gates import top_k

    k = len(branches) if k == "all" else min(int(k), len(branches))
    return top_k(torch.as_tensor(np.asarray(predicted), dtype=torch.float32).reshape(-1, len(branches)), branches, k)


@dataclass
class GatePass:
    """One pass over frames: every branch's detections and every gate's prediction per frame."""

    per_frame: list  # (meta, {branch: Detections in its own frame})
    predicted: dict  # gate -> per frame, the predicted loss of each branch
    losses: dict | None  # dataset index -> {branch: a-posteriori loss} when a gate reads losses
    gates: dict  # gate name -> the gate module
    branches: list  # the network's branch names, the columns of `predicted`

    def selection(self, gate: str, k) -> list[tuple[str, ...]]:
        """Per frame, the tuple of branch names `gate` keeps at `k` (`top_k_selection`)."""
        return top_k_selection(self.predicted[gate], self.branches, k)


def gate_pass(run_dir, data, model, names, indices, checkpoint: str = "latest", batch_size: int = 4,
              progress: bool = True, clear: bool = False) -> GatePass:
    """Run every branch of `model` once per frame of `indices` and every gate of `names` beside it
    (the optimal gate reads the run's a-posteriori branch losses, computed when missing; not on the
    `clear` twins, whose losses are not cached)."""
    import torch

    from study.engine.scoring import to_detections

    gate_objs = {g: gate_on_device(make_gate(g, model, run_dir, checkpoint), model) for g in names}
    branches = list(model.branches)
    need_losses = any(g.reads == "losses" for g in gate_objs.values())
    if need_losses and clear:
        raise UserError("the optimal gate reads the cached losses of the degraded frames, not of their twins")
    losses = _optimal_losses(run_dir, data, model, checkpoint, indices, progress) if need_losses else None
    predicted: dict[str, list] = {g: [] for g in names}
    per_frame = []
    with torch.no_grad():
        bar = progress_bar(total=len(indices), desc="branches and gates" + (" (clear twins)" if clear else ""),
                           enabled=progress)
        for inputs, _targets, metas in _loader(model, data, indices, batch_size, clear):
            if losses is not None:
                metas = [dict(m, branch_losses=losses[int(m["dataset_index"])]) for m in metas]
            with model.device_setup.autocast():
                feats = model.extract_features(inputs)
                preds = {g: gate.predict(feats, metas).float().cpu() for g, gate in gate_objs.items()}
                dets = model(inputs, selection=branches)
            for g, pred in preds.items():
                predicted[g].extend(pred.tolist())
            for meta, per in zip(metas, dets):
                per_frame.append((meta, {n: to_detections(d) for n, d in per.items()}))
            bar.update(len(metas))
        bar.close()
    return GatePass(per_frame, predicted, losses, gate_objs, branches)


def evaluate_all_gates(run_dir, data, gates=None, fusions=TABLE_FUSIONS, ks=None, split: str = "auto", weights=None,
                       checkpoint: str = "latest", batch_size: int = 4, progress: bool = True, setup=None) -> dict:
    """HydraFusion Tables 6 and 7 on this benchmark: mAP per gate x fusion x k, and how often each
    gate selects each branch per k. Every branch runs once per frame; each gate's top-k subsets are
    fused afterwards (equal to running only the selected branches: see the module docstring)."""
    from fusion.nets.branch_gates import GATES
    from study.engine.scoring import fuse_selection, score
    from study.engine.train import run_protocol

    model, _cfg, indices, used_split, reader = setup_run(run_dir, data, split, weights, checkpoint, setup)
    protocol = run_protocol(_cfg)
    names = list(gates or GATES.names())
    branches = list(model.branches)
    ks = list(ks or table_ks(len(branches)))
    ks = [parse_k(k, len(branches), "k") for k in ks]
    gp = gate_pass(run_dir, data, model, names, indices, checkpoint, batch_size, progress)
    per_frame, predicted, losses, gate_objs = gp.per_frame, gp.predicted, gp.losses, gp.gates

    frames = model.branch_frames
    contexts = [m["context"] for m, _ in per_frame]
    memo: dict[str, dict] = {}  # fusion method -> fused frames, shared by the gates' selections

    map_table: dict = {}
    ctx_table: dict = {}
    rates: dict = {}
    rates_ctx: dict = {}
    bar = progress_bar(total=len(names) * len(ks) * len(fusions), desc="fuse and score", enabled=progress)
    for g in names:
        map_table[g], ctx_table[g], rates[g], rates_ctx[g] = {}, {}, {}, {}
        for k in ks:
            selection = gp.selection(g, k)
            rates[g][str(k)] = selection_rates(selection, branches)
            rates_ctx[g][str(k)] = _rates_per_context(selection, contexts, branches)
            for method in fusions:
                label = method_label(method)
                out = fuse_selection(per_frame, selection, frames, method, weights, memo.setdefault(method, {}))
                sc = score(out, reader, "camera_right", protocol=protocol)
                map_table[g].setdefault(label, {})[str(k)] = sc["map"]
                ctx_table[g].setdefault(label, {})[str(k)] = sc["map_per_context"]
                bar.update(1)
    bar.close()
    best = {}
    for g in names:
        label, row = max(map_table[g].items(), key=lambda kv: max((v for v in kv[1].values() if v is not None),
                                                                  default=-1.0))
        best[g] = {"fusion": label, "map": row}
    result = {
        "map_table": map_table,
        "selection_rate": rates,
        "table3": best,
        "map_per_context_table": ctx_table,
        "selection_rate_per_context": rates_ctx,
        "gates": names, "fusions": [method_label(m) for m in fusions], "ks": [str(k) for k in ks],
        "branches": branches, "frames": len(per_frame), "split": used_split, "run": str(run_dir), "data": str(data),
        "metric": "VOC all-point AP at IoU 0.5, right camera, difficult ground truth ignored",
        "method": "every branch ran once per frame; each gate's top-k subset was fused afterwards (equal to running "
                  "only the selected branches: a branch depends only on its sensors' stem features)",
    }
    if losses is not None:
        actual = np.array([[losses[int(m["dataset_index"])][b] for b in branches] for m, _ in per_frame])
        result["loss_mae"] = {g: round(mae(np.array(predicted[g]), actual), 6)
                              for g, gate in gate_objs.items() if gate.trainable}
    return result
