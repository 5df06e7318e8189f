"""`hydrabench bench amp`: fp32 against bf16 autocast training on this CPU, side by side.

Two copies of one network (the same profile, branches and initial weights, `seed`) train on the same
frames with the same learning rate; step k of the fp32 copy and step k of the bf16 copy run back to
back (interleaved, so a machine that slows down slows both alike), each after
`torch.manual_seed(seed + k)` so the RPN / RoI samplers draw from the same stream. Reported: the
median step time of each (forward + backward + SGD, the first `warmup` steps untimed), the speed-up,
the loss of every step of both copies, and whether this CPU computes bf16 natively (AMX-BF16 or
AVX512-BF16, `study.engine.device.native_bf16`), which decides what `--amp auto` picks. Under bf16 autocast
only the backbones run in bf16: anchors, box coding, the RPN and RoI heads stay fp32
(`fusion.nets.layers.full_precision`).

A few steps say how fast and whether the losses stay together, not what either reaches: mAP parity
needs full training runs (`hydrabench train --amp` against `--no-amp`, then `evaluate`).
"""

from __future__ import annotations

import statistics
import time

import numpy as np

from study.bench.scale import cpu_model
from study.numbers import significant


def synthetic_batch(model, batch: int, seed: int) -> tuple[dict, list]:
    """Inputs in 0..1 for every sensor of `model` and 4 boxes (8..40 x 8..30 px, labels 1..8) per
    frame and target frame, drawn from `seed`."""
    import torch

    from fusion.nets import SENSORS

    g = torch.Generator().manual_seed(seed)
    inputs = {s: torch.rand(batch, SENSORS[s].channels, *model.transform.image_size(s), generator=g)
              for s in model.sensors}
    rng = np.random.default_rng(seed)
    targets = []
    for _ in range(batch):
        t = {}
        for frame, view in (("camera_left", "camera"), ("camera_right", "camera"), ("bev", "bev")):
            h, w = model.transform.sizes[view]
            wh = rng.uniform([8, 8], [min(40, w - 1), min(30, h - 1)], (4, 2))
            xy = rng.uniform(0, 1, (4, 2)) * (np.array([w, h]) - wh)
            t[frame] = {"boxes": torch.tensor(np.hstack([xy, xy + wh]), dtype=torch.float32),
                        "labels": torch.tensor(rng.integers(1, 9, 4), dtype=torch.int64)}
        targets.append(t)
    return inputs, targets


def dataset_batch(model, data: str, batch: int) -> tuple[dict, list]:
    """The first `batch` frames of a dataset, as training sees them (reference protocol)."""
    from fusion.data import FrameDataset, collate

    ds = FrameDataset(data, list(range(batch)), sensors=model.sensors, bev_size=model.transform.image_size("radar"),
                      protocol="reference")
    inputs, targets, _ = collate([ds[k] for k in range(min(batch, len(ds)))])
    return inputs, targets


def bench_setup(what: str, profile: str, branches, steps: int, warmup: int, batch: int, overrides=None):
    """The checks and the network specification the training benches share: (model profile, the
    branch specs of `branches` (empty: all)); UserError for bad counts or an unknown branch."""
    from fusion.nets import load_profile
    from sim.errors import UserError

    if steps < 1 or warmup < 0 or batch < 1:
        raise UserError(f"bench {what}: needs steps >= 1, warmup >= 0, batch >= 1 (got {steps}, {warmup}, {batch})")
    prof = load_profile(profile, **(overrides or {}))
    names = [b.name for b in prof.branches]
    bad = [b for b in branches if b not in names]
    if bad:
        raise UserError(f"--branches: unknown branch {bad[0]!r} (choose from: {', '.join(names)})")
    return prof, [b for b in prof.branches if not branches or b.name in branches]


def train_step(model, opt, inputs, targets, precision: str, seed: int) -> tuple[float, float]:
    """One SGD step on the CPU in `precision` ("fp32" or "bf16") -> (seconds, loss)."""
    import torch

    from study.engine.device import DeviceSetup

    torch.manual_seed(seed)
    setup = DeviceSetup("cpu", torch.get_num_threads(), precision == "bf16")
    t0 = time.perf_counter()
    with setup.autocast():
        losses = model(inputs, targets)
    total = losses["total"]
    opt.zero_grad(set_to_none=True)
    total.backward()
    opt.step()
    return time.perf_counter() - t0, float(total.detach())


def bench_amp(profile: str = "cpu", branches: tuple[str, ...] = (), batch: int = 4, steps: int = 3,
              warmup: int = 1, threads: int = 0, seed: int = 0, lr: float = 2e-3, data: str | None = None,
              overrides: dict | None = None) -> dict:
    """fp32 against bf16-autocast training steps (module docstring) -> a JSON-able dict.

    `branches`: names from the profile's branch set (empty: all of them); `data`: train on the
    first `batch` frames of this dataset instead of synthetic frames; `overrides`: ModelProfile
    fields (tests use a tiny network).
    """
    import torch

    from fusion.nets import build_hydrafusion
    from sim.errors import UserError
    from study.engine.device import default_threads, native_bf16

    prof, specs = bench_setup("amp", profile, branches, steps, warmup, batch, overrides)
    before = torch.get_num_threads()
    n_threads = threads or default_threads()
    torch.set_num_threads(n_threads)
    try:
        models, opts = {}, {}
        for precision in ("fp32", "bf16"):
            torch.manual_seed(seed)  # the same initial weights
            models[precision] = build_hydrafusion(profile=prof, branches=specs).train()
            opts[precision] = torch.optim.SGD(models[precision].parameters(), lr=lr, momentum=0.9, weight_decay=1e-4)
        model = models["fp32"]
        inputs, targets = dataset_batch(model, data, batch) if data else synthetic_batch(model, batch, seed)
        seconds = {"fp32": [], "bf16": []}
        loss = {"fp32": [], "bf16": []}
        for k in range(warmup + steps):
            for precision in ("fp32", "bf16"):  # interleaved: step k of each, back to back
                s, lo = train_step(models[precision], opts[precision], inputs, targets, precision, seed + k)
                if not np.isfinite(lo):
                    raise UserError(f"bench amp: non-finite {precision} loss at step {k} (lower --lr)")
                loss[precision].append(round(lo, 4))
                if k >= warmup:
                    seconds[precision].append(s)
    finally:
        torch.set_num_threads(before)
    native, why = native_bf16("cpu")
    median = {p: statistics.median(v) for p, v in seconds.items()}
    return {
        "cpu": cpu_model(), "threads": n_threads, "profile": profile, "branches": [b.name for b in specs],
        "parameters_m": round(sum(p.numel() for p in model.parameters()) / 1e6, 1), "batch": batch,
        "frames": "dataset " + str(data) if data else "synthetic", "steps": steps, "warmup_steps": warmup,
        "native_bf16": native, "native_bf16_reason": why, "amp_auto_picks": "bf16" if native else "fp32",
        "step_s": {p: significant(v, 4) for p, v in median.items()},
        "step_s_all": {p: [significant(x, 4) for x in v] for p, v in seconds.items()},
        "speedup_bf16": significant(median["fp32"] / median["bf16"], 3),
        "loss_per_step": loss,
        "final_loss": {p: v[-1] for p, v in loss.items()},
        "final_loss_relative_difference": round(abs(loss["bf16"][-1] - loss["fp32"][-1]) / max(abs(loss["fp32"][-1]), 1e-12), 4),
        "note": "median step time (forward + backward + SGD) after the warm-up steps, fp32 and bf16 interleaved; "
                "bf16 autocast covers the backbones, the heads run in fp32",
    }


def amp_parity(data: str, out, profile: str = "cpu", branches: tuple[str, ...] = ("radar",), epochs: int = 2,
               batch: int = 4, lr: float = 0.02, warmup: int = 60, threads: int = 0, seed: int = 0,
               bootstrap: int = 200, progress: bool = True, model_overrides: tuple[str, ...] = ()) -> dict:
    """`hydrabench bench amp-parity`: the same training run twice on `data`, in fp32 and in bf16
    autocast (`train --amp off` / `--amp bf16`: the same initial weights, frames, order and learning
    rate), each in `out/<precision>/` (resumable), then both scored on the run's test split: each
    branch alone in the right camera, vehicle and all-class mAP, and the paired difference bf16 -
    fp32 with a 95 % interval from `bootstrap` draws of whole test sequences
    (`study.engine.scoring.context_bootstrap`). Parity: an interval that holds 0 and is narrow. The two runs
    do not follow the same trajectory (bf16 rounding changes every step after the first), so the
    difference also holds run-to-run variation, which is what a user of either precision gets.
    Also: each run's training seconds (process wall time) and final epoch loss. `model_overrides`: `KEY=VALUE`
    overrides of the model profile for both runs (`TrainConfig.model`)."""
    import csv
    import json
    import time
    from pathlib import Path

    import torch

    from sensors.dataset import DatasetReader
    from sensors.dataset import check as check_dataset
    from sim.errors import UserError
    from study.engine.device import default_threads, native_bf16
    from study.engine.scoring import (
        context_bootstrap,
        difference_interval,
        frames_for,
        fused,
        fusion_method,
        load_run,
        run_branches,
        score,
    )
    from study.engine.train import TrainConfig, train

    out = Path(out)
    data = str(Path(data).resolve())
    if not 0 <= bootstrap <= 10000:
        raise UserError(f"--bootstrap must be 0..10000 draws, got {bootstrap}")
    marker = out / "amp_parity.json"
    ours = {"fp32", "bf16", marker.name}
    if out.exists() and (not out.is_dir() or any(p.name not in ours for p in out.iterdir())):
        raise UserError(f"--out {out} holds other files than amp-parity's fp32/, bf16/ and {marker.name}; use a new or "
                        "empty directory")
    check_dataset(data)  # every shard readable before anything is written (train checks the rest first too)
    n_threads = threads or default_threads()
    runs, dets, reader = {}, {}, DatasetReader(data)
    for precision, amp in (("fp32", "off"), ("bf16", "bf16")):
        cfg = TrainConfig(data=data, model_profile=profile, branch_set="paper", branches=tuple(branches), epochs=epochs,
                          batch_size=batch, lr=lr, warmup_steps=warmup, seed=seed, threads=n_threads, device="cpu",
                          amp=amp, eval_frames=4, checkpoint_seconds=300.0, model=tuple(model_overrides))
        t0 = time.perf_counter()
        train(cfg, out / precision, progress=progress)
        seconds = time.perf_counter() - t0
        model, run_cfg = load_run(out / precision, "latest", device="cpu")
        test, _ = frames_for(run_cfg, data, "test")
        if not test:
            raise UserError(f"{data}: the run's split has no test frames to score (generate more sequences)")
        torch.set_num_threads(n_threads)
        per = run_branches(model, data, test, list(branches), progress=f"detect {precision}")
        frames = model.branch_frames
        with open(out / precision / "metrics.csv") as fh:
            rows = list(csv.DictReader(fh))
        runs[precision] = {"train_seconds": round(sum(float(r["train_seconds"]) for r in rows), 1),
                           "seconds_this_call": round(seconds, 1), "compute": run_cfg.get("compute"),
                           "loss_total_per_epoch": [float(r["loss_total"]) for r in rows], "branches": {}}
        for b in branches:
            alone = fused(per, [b], frames, fusion_method("soft-nms"))
            s = score(alone, reader, "camera_right", protocol=run_cfg.get("protocol", "reference"))
            runs[precision]["branches"][b] = {"map": s["map"], "map_vehicles": s["map_vehicles"]}
            dets[f"{precision}:{b}"] = alone
    intervals = {}
    if bootstrap:
        ci = context_bootstrap(dets, reader, "camera_right", resamples=bootstrap, desc="bootstrap bf16 - fp32")
        all_ = ci["per_context"]["all"]
        intervals = {b: {"fp32": all_["map_vehicles"][f"fp32:{b}"], "bf16": all_["map_vehicles"][f"bf16:{b}"],
                         "bf16_minus_fp32": difference_interval(all_, f"bf16:{b}", f"fp32:{b}")}
                     for b in branches}
        intervals["sequences"] = all_["sequences"]
    native, why = native_bf16("cpu")
    result = {"cpu": cpu_model(), "threads": n_threads, "profile": profile, "branches": list(branches), "epochs": epochs,
              "batch": batch, "lr": lr, "warmup_steps": warmup, "data": data, "test_frames": len(test),
              "native_bf16": native, "native_bf16_reason": why, "runs": runs, "ci95_vehicle_map": intervals,
              "bootstrap": bootstrap, "out": str(out)}
    marker.write_text(json.dumps(result, indent=1) + "\n")  # the last result beside the two runs
    return result
