"""`hydrabench train`: stems and branches jointly with the Faster R-CNN multi-task loss.

HydraFusion Section 5.3: SGD at lr 5e-3, a 70:30 train/test split (by sequence here, so no
sequence is in both), all branches trained together on every sample. Everything a resumed run needs
is in the run directory:

    RUN/config.json        the training config, the branch set, the dataset's generation config
    RUN/checkpoint.pt      latest state (model, optimiser, epoch, step in epoch, the epoch's running
                           loss sums (a resumed epoch's row averages all of it), RNG states),
                           written atomically every `checkpoint_steps` steps and at each epoch end
    RUN/epoch-XXX.pt       the model at the end of each epoch
    RUN/metrics.csv        one row per epoch: mean losses per branch, lr, test mAP@0.5 per branch
                           (in its own frame) and of their late fusion (right camera), seconds
                           (train_seconds: the training steps alone)
    RUN/curves.png         metrics.csv plotted: losses and test mAP per branch against the epoch

Interrupted (even kill -9) and run again with the same arguments, training continues from the last
checkpoint; a larger --epochs extends a finished run.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from fusion.data import FrameDataset, collate, split_by_sequence
from fusion.nets.profile import load_profile
from sensors.dataset import DatasetReader
from sensors.dataset import check as check_dataset
from sim.config import to_dict
from sim.errors import UserError
from study.checkpoints import load_checkpoint, load_weights
from study.device import resolve_device, to_device
from study.run_config import run_profile


@dataclass(frozen=True)
class TrainConfig:
    """One training run.

    Fields:
        data: dataset directory (hydrabench generate).
        model_profile: configs/model/<profile>.yaml (cpu or paper).
        branch_set: paper | single | early_fusion | late_fusion (see `branch_set`).
        branches: names from the set to train (empty = the whole set).
        epochs: passes over the training split.
        batch_size: frames per step.
        lr: SGD learning rate (HydraFusion 5.3: 5e-3); momentum 0.9, weight decay 1e-4.
        warmup_steps: linear warm-up from lr / 1000 (detection from scratch diverges without it).
        lr_drop_epoch: lr x 0.1 from this epoch on (0 = 3/4 of `epochs`).
        clip_grad: gradient-norm clipping (0 = off).
        train_fraction, split_seed: the by-sequence split.
        seed: model initialisation and data order.
        checkpoint_steps: also checkpoint every this many steps within an epoch.
        checkpoint_seconds: also checkpoint when this many seconds passed since the last checkpoint
            (0 = off): on a loaded machine 100 steps can take hours, and a kill loses at most this.
            Where a run checkpoints does not change what it computes (resume is exact at any step).
        eval_frames: evaluate on at most this many test frames per epoch (0 = all).
        threads: torch CPU threads (0: the cores available).
        device: auto | cpu | cuda | cuda:N (`study.device`); under torchrun each process takes the
            GPU of its LOCAL_RANK.
        amp: bf16 autocast of the forward passes (None: on for CUDA, off on the CPU).
        workers: DataLoader processes decoding frames (0: in the main process).
        sampling: how the RPN and RoI heads draw the anchors and RoIs of their losses: "global"
            (torch's global generator, one image after the other, as torchvision does) or
            "per-frame" (`fusion.nets.sampling`: each frame's draw seeded by (seed, step, frame),
            so it does not depend on how a batch is split over processes; what torchrun runs use).
        init_from: trained runs (comma-separated, priority order) whose weights initialise this one
            (see `warm_start`); "" = scratch.
        hflip: probability that a training frame is mirrored left-right, world and rig together
            (`fusion.data.hflip_sample`; decided per frame and epoch from `seed`, so a resumed run
            sees the same frames). Refused for branches that fuse both cameras.
        protocol: the evaluation protocol whose ground truth the branches train on and are tested
            against (fusion.protocol: reference | visible | bev); runs made before it existed
            trained on `visible`.
    """

    data: str
    model_profile: str = "cpu"
    branch_set: str = "paper"
    branches: tuple[str, ...] = ()
    epochs: int = 10
    batch_size: int = 4
    lr: float = 5e-3
    warmup_steps: int = 100
    lr_drop_epoch: int = 0
    clip_grad: float = 10.0
    train_fraction: float = 0.7
    split_seed: int = 0
    seed: int = 0
    checkpoint_steps: int = 100
    checkpoint_seconds: float = 600.0
    eval_frames: int = 0
    threads: int = 0
    init_from: str = ""
    hflip: float = 0.0
    protocol: str = "reference"
    device: str = "auto"
    amp: bool | None = None
    workers: int = 0
    sampling: str = "global"


# What a field added later means for a run made before it existed (config.json without the field).
LEGACY_DEFAULTS = {"protocol": "visible"}


def run_protocol(run_cfg: dict) -> str:
    """The evaluation protocol a run trained on (recorded in RUN/config.json)."""
    return run_cfg.get("protocol", LEGACY_DEFAULTS["protocol"])


# Which trained module initialises which new one when warm-starting (`--init-from`): the paper's
# branches share one architecture (ResNet-18 layer2..4 + RPN + RoI heads), so a trained camera
# branch is a good start for the other camera-view branches, a trained radar branch for the BEV ones.
WARM_START_BRANCH = {
    "camera_left": "camera_right", "camera_both": "camera_right", "camera_lidar": "camera_right",
    "early_cameras": "camera_right", "early_camera_lidar": "camera_right",
    "lidar": "radar", "radar_lidar": "radar", "early_radar_lidar": "radar",
}
WARM_START_STEM = {"fwd_lidar": "camera", "lidar": "radar"}


def warm_start(model, source_states) -> dict:
    """Copy matching parameters from trained models' state dicts into `model`.

    `source_states`: one state dict, or several in priority order. Each module of `model` (a branch
    or a stem) comes from the first source that has it, either under its own name or under its
    warm-start origin (WARM_START_BRANCH / WARM_START_STEM); so with sources (a camera-only run, a
    seven-branch run) the camera-view branches start from the first run's trained camera branch and
    the radar / lidar ones from the second. Tensors whose shapes differ (the first conv of a stem
    with other input channels) keep their fresh initialisation; the merge conv of a fused branch
    started from a single-sensor branch passes that sensor's features through. Returns {"copied": n,
    "from": {target prefix: source prefix}, "source": {target prefix: index of the source},
    "merge_pass_through": {branch: sensor}, "kept": [...]}.
    """
    sources = [source_states] if isinstance(source_states, dict) else list(source_states)
    own = model.state_dict()
    mapping, origin_of = {}, {}
    for kind, names, table in (("branches", model.branches, WARM_START_BRANCH), ("stems", model.stems, WARM_START_STEM)):
        present_in = [{k.split(".")[1] for k in state if k.startswith(kind + ".")} for state in sources]
        for name in names:
            for s, present in enumerate(present_in):
                origin = name if name in present else table.get(name)
                if origin in present:
                    mapping[f"{kind}.{name}."] = f"{kind}.{origin}."
                    origin_of[f"{kind}.{name}."] = s
                    break
    new, kept = {}, []
    for key, value in own.items():
        dst = next((d for d in mapping if key.startswith(d)), None)
        state = sources[origin_of[dst]] if dst is not None else sources[0]
        src_key = mapping[dst] + key[len(dst):] if dst is not None else key
        if src_key in state and state[src_key].shape == value.shape:
            new[key] = state[src_key]
        else:
            kept.append(key)
    # A fused branch started from a single-sensor one: its fresh merge conv would scramble the
    # features the copied layer2.. expect, so it starts as a pass-through of that sensor's stem
    # channels (the other sensors' weights at zero; they still get gradients and learn).
    passed = {}
    for name, branch in model.branches.items():
        dst = f"branches.{name}."
        key = dst + "merge.weight"
        origin = mapping.get(dst, "")[len("branches."):-1]
        if key in kept and origin in branch.sensors and branch.merge is not None:
            w = torch.zeros_like(own[key])
            c = w.shape[0]
            at = branch.sensors.index(origin) * c
            w[torch.arange(c), at + torch.arange(c), w.shape[2] // 2, w.shape[3] // 2] = 1.0
            new[key], new[dst + "merge.bias"] = w, torch.zeros_like(own[dst + "merge.bias"])
            kept = [k for k in kept if k not in (key, dst + "merge.bias")]
            passed[name] = origin
    model.load_state_dict({**own, **new})
    return {"copied": len(new), "from": mapping, "source": origin_of, "merge_pass_through": passed, "kept": kept}


def branch_set(name: str, profile: str):
    """The BranchSpecs of a named set for a model profile."""
    from fusion.nets import load_profile as load_model_profile
    from fusion.nets.profile import BranchSpec

    paper = list(load_model_profile(profile).branches)
    single = [b for b in paper if len(b.sensors) == 1]
    if name == "paper":
        return paper
    if name in ("single", "late_fusion"):
        return single
    if name == "early_fusion":
        return [
            BranchSpec("early_cameras", ("camera_left", "camera_right"), "camera_right", fusion="input"),
            BranchSpec("early_camera_lidar", ("camera_left", "camera_right", "fwd_lidar"), "camera_right", fusion="input"),
            BranchSpec("early_radar_lidar", ("radar", "lidar"), "bev", fusion="input"),
        ]
    raise UserError(f"unknown branch set {name!r} (choose from: paper, single, early_fusion, late_fusion)")


def _atomic_save(obj, path: Path) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def _lr_at(cfg: TrainConfig, epoch: int, step: int) -> float:
    drop = cfg.lr_drop_epoch or max(1, int(round(0.75 * cfg.epochs)))
    lr = cfg.lr * (0.1 if epoch >= drop else 1.0)
    if step < cfg.warmup_steps:
        lr *= 1e-3 + (1 - 1e-3) * step / cfg.warmup_steps
    return lr


def evaluate_epoch(model, cfg: TrainConfig, reader, test_idx, branches, setup=None) -> dict:
    from study.detect import bev_crop_of, fused, native, run_branches, score

    idx = test_idx if not cfg.eval_frames else test_idx[: cfg.eval_frames]
    if not idx:  # e.g. a one-sequence dataset: no test split, nothing to score
        return {**{f"map_{b}": None for b in branches}, "map_fused": None}
    model.eval()
    per_frame = run_branches(model, cfg.data, idx, branches, batch_size=cfg.batch_size, progress="evaluate",
                             workers=setup.workers if setup else 0, amp=bool(setup and setup.amp))
    out = {}
    frames = model.branch_frames
    crop = bev_crop_of(model, reader)
    for b in branches:
        out[f"map_{b}"] = score(native(per_frame, b), reader, frames[b], crop, cfg.protocol)["map"]
    out["map_fused"] = score(fused(per_frame, branches, frames, "soft_nms"), reader, "camera_right",
                             protocol=cfg.protocol)["map"]
    model.train()
    return out


# settings a resumed run may change: they decide how long and where it runs, not what it learns
RESUME_KEYS = ("model", "optimizer", "epoch", "step_in_epoch", "global_step", "torch_rng")
"""What a run's checkpoint.pt must hold to be resumed."""
FREE_ON_RESUME = ("epochs", "lr_drop_epoch", "eval_frames", "threads", "checkpoint_steps", "checkpoint_seconds", "device",
                  "amp", "workers")


class _Batches(torch.utils.data.Dataset):
    """Batch k of an epoch as collate() gives it, so DataLoader workers can decode frames ahead."""

    def __init__(self, dataset, batches, flips):
        self.dataset, self.batches, self.flips = dataset, batches, flips

    def __len__(self) -> int:
        return len(self.batches)

    def __getitem__(self, k: int):
        return collate([self.dataset.item(int(i), flip=bool(self.flips[i])) for i in self.batches[k]])


def _as_is(x):
    return x


def _batch_stream(dataset, batches, flips, start: int, workers: int, pin: bool):
    """(step, batch) for steps start.. of an epoch; decoded in `workers` processes when > 0."""
    items = _Batches(dataset, batches, flips)
    if workers <= 0:
        for k in range(start, len(batches)):
            yield k, items[k]
        return
    from torch.utils.data import DataLoader

    loader = DataLoader(items, batch_size=None, sampler=range(start, len(batches)), num_workers=workers,
                        collate_fn=_as_is, pin_memory=pin, persistent_workers=False)
    yield from zip(range(start, len(batches)), loader)


def _rank_share(batch, rank: int, world: int):
    """This process's frames of a global batch (np.array_split: sizes differ by at most one)."""
    return np.array_split(np.asarray(batch), world)[rank]


def check_run_dir(out: Path, main_rank: bool = True) -> None:
    """Refuse (UserError) an --out that is not empty and holds no training run. Only the main rank
    judges: it creates the directory and writes config.json (through a temporary file), so another
    rank looking at the same moment could see a half-made run and fail a good launch (it did under
    load: rank 1 exited with code 2 while rank 0 wrote)."""
    if main_rank and out.is_dir() and any(out.iterdir()) and not (out / "config.json").exists():
        raise UserError(f"{out} is not empty and holds no training run (no config.json); use a new or empty --out")


def train(cfg: TrainConfig, out: Path, progress: bool = True) -> dict:
    """Train (or resume) the run in `out`. Launched by torchrun (WORLD_SIZE > 1), each process
    trains on its share of every batch (`DistributedDataParallel`, gloo on the CPU, NCCL on GPUs)
    and rank 0 alone writes the run directory; `batch_size` stays the global batch."""

    from fusion.nets import build_hydrafusion
    from sim.progress import progress as progress_bar
    from study import distributed as dist
    from study.plots import plot_training_curves

    ddp = dist.from_env()
    device = cfg.device
    if ddp.world > 1 and device in ("auto", "cuda"):
        device = f"cuda:{ddp.local_rank}" if torch.cuda.is_available() else ("cpu" if device == "auto" else device)
    setup = resolve_device(device=device, threads=cfg.threads, amp=cfg.amp, workers=cfg.workers)
    ddp.init(setup.device)
    if cfg.sampling not in ("global", "per-frame"):
        raise UserError(f"--sampling {cfg.sampling!r}: choose from global, per-frame")
    if ddp.world > 1 and cfg.sampling != "per-frame":
        raise UserError(f"{out}: sampling {cfg.sampling!r} draws each process's anchors from its own global generator; "
                        "data-parallel training needs per-frame sampling (a run started with --sampling per-frame)")
    if ddp.world > 1 and cfg.batch_size < ddp.world:
        raise UserError(f"--batch-size {cfg.batch_size} is the global batch: it needs at least one frame per process "
                        f"({ddp.world} processes)")
    main_rank = ddp.rank == 0
    progress = progress and main_rank
    check_dataset(cfg.data)  # every shard readable before RUN/ exists
    reader = DatasetReader(cfg.data)
    specs = branch_set(cfg.branch_set, cfg.model_profile)
    names = [s.name for s in specs]
    chosen = list(cfg.branches) or names
    twice = [b for k, b in enumerate(chosen) if b in chosen[:k]]
    if twice:
        raise UserError(f"branch {twice[0]!r} is named twice")
    bad = [b for b in chosen if b not in names]
    if bad:
        raise UserError(f"unknown branch {bad[0]!r} in set {cfg.branch_set!r} (choose from: {', '.join(names)})")
    specs = [s for s in specs if s.name in chosen]
    if not 0.0 <= cfg.hflip <= 1.0:
        raise UserError(f"--hflip is a probability in [0, 1], got {cfg.hflip}")
    if not (cfg.checkpoint_seconds >= 0 and math.isfinite(cfg.checkpoint_seconds)):
        raise UserError(f"--checkpoint-seconds must be a finite number >= 0, got {cfg.checkpoint_seconds}")
    stereo = [s.name for s in specs if {"camera_left", "camera_right"} <= set(s.sensors)]
    if cfg.hflip > 0 and stereo:
        raise UserError(f"--hflip mirrors the rig, which swaps the stereo cameras' sides: branch {stereo[0]!r} "
                        "fuses both cameras and would see its geometry reversed; leave it out or use --hflip 0")
    from fusion.protocol import PROTOCOLS

    if cfg.protocol not in PROTOCOLS:
        raise UserError(f"--protocol: unknown protocol {cfg.protocol!r} (choose from: {', '.join(PROTOCOLS)})")
    if reader.manifest["profile"] != cfg.model_profile:
        raise UserError(f"dataset profile {reader.manifest['profile']!r} does not match model profile {cfg.model_profile!r}")
    # The resolved model profile is part of the run: a later edit of configs/model/<profile>.yaml
    # (strides, anchors, head sizes) must not change what `load_run` builds for these weights.
    run_cfg = {**dataclasses.asdict(cfg), "branches": chosen, "branch_specs": [dataclasses.asdict(s) for s in specs],
               "data_config": reader.manifest["config"], "profile_fields": to_dict(load_profile(cfg.model_profile))}
    run_cfg = json.loads(json.dumps(run_cfg))  # the form it has on disk (tuples become lists)
    srcs = [Path(r) / "checkpoint.pt" for r in cfg.init_from.split(",")] if cfg.init_from else []
    missing = [str(s.parent) for s in srcs if not s.exists()]
    if missing:
        raise UserError(f"--init-from {missing[0]}: no checkpoint.pt there")
    check_run_dir(out, main_rank)
    cfg_path = out / "config.json"
    if main_rank and cfg_path.exists():
        old = json.loads(cfg_path.read_text())
        # fields added after a run was made hold their default in it (LEGACY_DEFAULTS: what it meant then)
        old = {**{f.name: LEGACY_DEFAULTS.get(f.name, f.default) for f in dataclasses.fields(TrainConfig)
                  if f.name not in old}, **old}
        old = json.loads(json.dumps(old))
        comparable = {k: v for k, v in old.items() if k not in FREE_ON_RESUME}
        now = {k: v for k, v in run_cfg.items() if k not in FREE_ON_RESUME}
        if comparable != now:
            diff = sorted(k for k in now if comparable.get(k) != now.get(k))
            raise UserError(f"{out} holds a run with a different config ({', '.join(diff)}); use another --out")

    train_idx, test_idx = split_by_sequence(reader, cfg.train_fraction, cfg.split_seed)
    torch.manual_seed(cfg.seed)
    model = build_hydrafusion(profile=run_profile(run_cfg, out), branches=specs)
    if cfg.sampling == "per-frame":
        from fusion.nets.sampling import use_frame_seeded_sampling

        use_frame_seeded_sampling(model)
    # Every checkpoint the run reads is read (and its weights loaded) before RUN/ is created or its
    # config.json rewritten: a truncated or foreign checkpoint is refused with nothing changed.
    ckpt_path = out / "checkpoint.pt"
    resuming = ckpt_path.exists()  # (no rank writes a checkpoint before the barrier below)
    state = load_checkpoint(ckpt_path, RESUME_KEYS) if resuming else None
    if state is not None:
        load_weights(model, state["model"], ckpt_path)
    sources = [load_checkpoint(s)["model"] for s in srcs] if cfg.init_from and not resuming else []
    if main_rank:
        out.mkdir(parents=True, exist_ok=True)
        tmp = cfg_path.with_name(".config.json.tmp")
        tmp.write_text(json.dumps(run_cfg, indent=1))
        os.replace(tmp, cfg_path)
    ddp.barrier()  # rank 0 has checked and written config.json; no checkpoint is written before this
    if sources:
        report = warm_start(model, sources)
        if main_rank:
            (out / "warm_start.json").write_text(json.dumps({"sources": [str(s) for s in srcs], **report}, indent=1))
        if progress:
            sys.stderr.write(f"warm start from {', '.join(map(str, srcs))}: {report['copied']} tensors copied, "
                             f"{len(report['kept'])} fresh\n")
    model.train()
    if setup.is_cuda:
        model.to(setup.torch_device())
    params = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.SGD(params, lr=cfg.lr, momentum=0.9, weight_decay=1e-4)
    epoch, step_in_epoch, global_step = 0, 0, 0
    resumed: dict = {}  # the interrupted epoch's running loss sums, so its row averages the whole epoch
    if state is not None:
        opt.load_state_dict(state["optimizer"])
        epoch, step_in_epoch, global_step = state["epoch"], state["step_in_epoch"], state["global_step"]
        torch.set_rng_state(state["torch_rng"])
        resumed = state.get("epoch_sums", {}) if step_in_epoch else {}
        if progress:
            sys.stderr.write(f"resuming {out} at epoch {epoch + 1}, step {step_in_epoch}\n")
    net = ddp.wrap(model, setup)  # DistributedDataParallel under torchrun, the model itself otherwise
    if progress and ddp.world > 1:
        sys.stderr.write(f"data-parallel: {ddp.world} processes ({ddp.backend}), global batch {cfg.batch_size}\n")
    sensors = model.sensors_for(None)
    dataset = FrameDataset(cfg.data, train_idx, sensors=sensors, bev_size=model.transform.image_size("radar"),
                           protocol=cfg.protocol)
    steps_per_epoch = (len(dataset) + cfg.batch_size - 1) // cfg.batch_size
    metrics_path = out / "metrics.csv"
    result = {}
    last_save = time.perf_counter()  # the time-based checkpoints count from here (and each save)
    while epoch < cfg.epochs:
        order = np.random.default_rng([cfg.seed, epoch]).permutation(len(dataset))
        flips = np.random.default_rng([cfg.seed, epoch, 1]).random(len(dataset)) < cfg.hflip
        batches = [order[k:k + cfg.batch_size] for k in range(0, len(order), cfg.batch_size)]
        # under torchrun: this rank's share of each global batch; a rank left without a frame (a
        # last batch smaller than the world) runs one frame with weight 0 to join the all-reduce
        shares = [_rank_share(b, ddp.rank, ddp.world) for b in batches] if ddp.world > 1 else batches
        weights = [len(s) / len(b) for s, b in zip(shares, batches)]
        shares = [s if len(s) else b[:1] for s, b in zip(shares, batches)]
        sums: dict[str, float] = dict(resumed.get("sums", {}))
        counts = resumed.get("steps", 0)
        t0 = time.perf_counter() - resumed.get("seconds", 0.0)
        resumed = {}
        # on a terminal a live bar; in a log file (nohup, CI) a line every few seconds (sim.progress)
        bar = progress_bar(total=steps_per_epoch, initial=step_in_epoch, desc=f"epoch {epoch + 1}/{cfg.epochs}",
                           unit="step", enabled=progress)
        for k, (inputs, targets, metas) in _batch_stream(dataset, shares, flips, step_in_epoch, setup.workers,
                                                          setup.is_cuda):
            inputs, targets = to_device(inputs, targets, setup.device)
            for g in opt.param_groups:
                g["lr"] = _lr_at(cfg, epoch, global_step)
            if cfg.sampling == "per-frame":
                from fusion.nets.sampling import set_sample_keys

                set_sample_keys(model, [(cfg.seed, global_step, m["dataset_index"]) for m in metas])
            with setup.autocast():
                losses = net(inputs, targets)
            total = losses["total"]
            if not torch.isfinite(total):
                raise RuntimeError(f"non-finite loss at epoch {epoch + 1} step {k} (lower --lr?)")
            opt.zero_grad(set_to_none=True)
            if ddp.world > 1:
                # DDP averages gradients over the processes; weighting each process's mean loss by
                # its share of the batch makes that the mean over the batch's frames
                (total * (weights[k] * ddp.world)).backward()
            else:
                total.backward()
            if cfg.clip_grad > 0:
                torch.nn.utils.clip_grad_norm_(params, cfg.clip_grad)
            opt.step()
            global_step += 1
            counts += 1
            w = weights[k]
            for b, ld in losses["branches"].items():
                v = float(sum(v.detach() for v in ld.values()))
                sums[b] = sums.get(b, 0.0) + (v if ddp.world == 1 else w * v)
            sums["total"] = sums.get("total", 0.0) + (float(total.detach()) if ddp.world == 1 else w * float(total.detach()))
            bar.set_postfix(loss=f"{total.item():.3f}", lr=f"{opt.param_groups[0]['lr']:.2e}")
            bar.update(1)
            due = (k + 1) % cfg.checkpoint_steps == 0 or (
                cfg.checkpoint_seconds > 0 and time.perf_counter() - last_save >= cfg.checkpoint_seconds)
            if due and k + 1 < len(batches) and main_rank:
                last_save = time.perf_counter()
                _atomic_save({"model": model.state_dict(), "optimizer": opt.state_dict(), "epoch": epoch,
                              "step_in_epoch": k + 1, "global_step": global_step,
                              "torch_rng": torch.get_rng_state(),
                              "epoch_sums": {"sums": sums, "steps": counts, "seconds": time.perf_counter() - t0}},
                             ckpt_path)
        bar.close()
        train_seconds = time.perf_counter() - t0  # the steps alone, before the epoch's evaluation
        sums = ddp.sum_dict(sums)  # the batch-mean losses of every process added up (one process: as is)
        epoch += 1
        step_in_epoch = 0
        if main_rank:
            _atomic_save({"model": model.state_dict()}, out / f"epoch-{epoch:03d}.pt")
            evals = evaluate_epoch(model, cfg, reader, test_idx, chosen, setup)
            row = {"epoch": epoch, "steps": global_step, "lr": opt.param_groups[0]["lr"],
                   **{f"loss_{b}": round(v / max(counts, 1), 4) for b, v in sums.items()}, **evals,
                   "seconds": round(time.perf_counter() - t0, 1), "train_seconds": round(train_seconds, 2)}
            _append_row(metrics_path, row)
            plot_training_curves(metrics_path, out / "curves.png")
            _atomic_save({"model": model.state_dict(), "optimizer": opt.state_dict(), "epoch": epoch,
                          "step_in_epoch": 0, "global_step": global_step, "torch_rng": torch.get_rng_state()},
                         ckpt_path)
            last_save = time.perf_counter()
            if progress:
                sys.stderr.write(json.dumps(row) + "\n")
            result = row
        ddp.barrier()  # the others wait for rank 0's evaluation and checkpoint
    if not result and metrics_path.exists():
        with open(metrics_path) as fh:
            rows = list(csv.DictReader(fh))
        result = rows[-1] if rows else {}
    ddp.close()
    return {"run": str(out), "epochs": cfg.epochs, "train_frames": len(train_idx), "test_frames": len(test_idx),
            "branches": chosen, "last": result, "device": setup.describe(), "processes": ddp.world}


def _append_row(path: Path, row: dict) -> None:
    rows = []
    if path.exists():
        with open(path) as fh:
            rows = list(csv.DictReader(fh))
    rows = [r for r in rows if int(r["epoch"]) < row["epoch"]] + [{k: str(v) for k, v in row.items()}]
    keys = list(dict.fromkeys(k for r in rows for k in r))
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    os.replace(tmp, path)
