"""`hydrabench train`: stems and branches jointly with the Faster R-CNN multi-task loss.

HydraFusion Section 5.3: SGD at lr 5e-3, a 70:30 train/test split (by sequence here, so no
sequence is in both), all branches trained together on every sample. Everything a resumed run needs
is in the run directory:

    RUN/config.json        the training config, the branch set, the dataset's generation config
    RUN/checkpoint.pt      latest state (model, optimiser, epoch, step in epoch, the epoch's running
                           loss sums (a resumed epoch's row averages all of it), RNG states),
                           written atomically every `checkpoint_steps` steps and at each epoch end
    RUN/epoch-XXX.pt       the model at the end of each epoch
    RUN/metrics.csv        one row per epoch: mean losses per branch, lr, test mAP@0.5 per branch (in its
                           own frame) and of their late fusion (right camera), seconds (train_seconds: steps)
    RUN/curves.png         metrics.csv plotted: losses and test mAP per branch against the epoch

Interrupted (even kill -9) and run again with the same arguments, training continues from the last
checkpoint; a larger --epochs extends a finished run.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from fusion.data import FrameDataset, collate, hold_out_sequences, split_by_sequence
from fusion.nets.profile import load_profile
from sensors.dataset import DatasetReader, lock_name, output_lock
from sensors.dataset import check as check_dataset
from sim.config import to_dict
from sim.errors import UserError
from study.engine.checkpoints import load_checkpoint, load_weights
from study.engine.device import rank_device, resolve_device, to_device
from study.engine.run_config import run_profile
from study.engine.warm_start import apply_warm_start, check_warm_start_profile
from study.outputs import atomic_path, torch_save_atomic


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
        gate_holdout: share of the train split's sequences, per context, the detectors do not train
            on (`fusion.data.hold_out_sequences`): the run's gate split, where the gates learn each
            branch's loss on frames its detector never saw (0 = none: the gates learn from the
            detectors' own training frames).
        seed: model initialisation and data order.
        checkpoint_steps: also checkpoint every this many steps within an epoch.
        checkpoint_seconds: also checkpoint when this many seconds passed since the last checkpoint
            (0 = off): on a loaded machine 100 steps can take hours, and a kill loses at most this.
            Where a run checkpoints does not change what it computes (resume is exact at any step).
        eval_frames: evaluate on at most this many test frames per epoch (0 = all).
        threads: torch CPU threads (0: the cores available).
        device: auto | cpu | cuda | cuda:N (`study.engine.device`); under torchrun each process takes the
            GPU of its LOCAL_RANK.
        amp: bf16 autocast of the backbones (`study.engine.device.resolve_amp`: None = bf16 on CUDA, fp32 on
            the CPU; "auto" = bf16 where the device has native bf16; True / "bf16"; False / "off").
            The resolved device type and precision are recorded in config.json ("compute").
        workers: DataLoader processes decoding frames (0: in the main process; None: 0 on the CPU,
            `study.engine.device.DEFAULT_CUDA_WORKERS` on CUDA).
        sampling: how the RPN and RoI heads draw the anchors and RoIs of their losses: "global"
            (torch's global generator, one image after the other, as torchvision does) or
            "per-frame" (`fusion.nets.sampling`: each frame's draw seeded by (seed, step, frame),
            so it does not depend on how a batch is split over processes; what torchrun runs use).
        init_from: trained runs (comma-separated, priority order) whose weights initialise this one
            (see `study.engine.warm_start.warm_start`); "" = scratch.
        hflip: probability that a training frame is mirrored left-right, world and rig together
            (`fusion.data.hflip_sample`; decided per frame and epoch from `seed`, so a resumed run
            sees the same frames). Refused for branches that fuse both cameras.
        protocol: the evaluation protocol whose ground truth the branches train on and are tested
            against (fusion.protocol: reference | visible | bev); runs made before it existed
            trained on `visible`.
        model: `KEY=VALUE` overrides of the model profile (`fusion.nets.profile.parse_model_overrides`:
            width=0.5, dilation=true, bev.output_stride=16, box_batch_size_per_image=64, ...); the
            resolved profile is recorded in config.json ("profile_fields").
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
    gate_holdout: float = 0.0
    seed: int = 0
    checkpoint_steps: int = 100
    checkpoint_seconds: float = 600.0
    eval_frames: int = 0
    threads: int = 0
    init_from: str = ""
    hflip: float = 0.0
    protocol: str = "reference"
    device: str = "auto"
    amp: bool | str | None = None
    workers: int | None = None
    sampling: str = "global"
    model: tuple[str, ...] = ()


def run_model_profile(cfg: TrainConfig):
    """The ModelProfile `cfg` trains: its named profile with its `model` overrides (UserError when an
    override is unknown or invalid)."""
    from fusion.nets.profile import parse_model_overrides

    return load_profile(cfg.model_profile, **parse_model_overrides(cfg.model))


# What a field added later means for a run made before it existed (config.json without the field).
LEGACY_DEFAULTS = {"protocol": "visible"}


def run_protocol(run_cfg: dict) -> str:
    """The evaluation protocol a run trained on (recorded in RUN/config.json)."""
    return run_cfg.get("protocol", LEGACY_DEFAULTS["protocol"])


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


def _lr_at(cfg: TrainConfig, epoch: int, step: int) -> float:
    drop = cfg.lr_drop_epoch or max(1, int(round(0.75 * cfg.epochs)))
    lr = cfg.lr * (0.1 if epoch >= drop else 1.0)
    if step < cfg.warmup_steps:
        lr *= 1e-3 + (1 - 1e-3) * step / cfg.warmup_steps
    return lr


def evaluate_epoch(model, cfg: TrainConfig, reader, test_idx, branches, setup=None) -> dict:
    from study.engine.scoring import bev_crop_of, fused, native, run_branches, score

    idx = test_idx if not cfg.eval_frames else test_idx[: cfg.eval_frames]
    if not idx:  # e.g. a one-sequence dataset: no test split, nothing to score
        return {**{f"map_{b}": None for b in branches}, "map_fused": None}
    model.eval()
    per_frame = run_branches(model, cfg.data, idx, branches, batch_size=cfg.batch_size, progress="evaluate",
                             workers=setup.workers if setup else 0)  # fp32: evaluation is not what --amp asks for
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
                  "amp", "workers", "compute")


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


TRAIN_LOCK = lock_name("train")
"""RUN/.train.lock: one train at a time per run (`sensors.dataset.output_lock`)."""


def check_run_dir(out: Path, main_rank: bool = True) -> None:
    """Refuse (UserError) an --out that is not empty and holds no training run. Only the main rank
    judges: it creates the directory and writes config.json (through a temporary file), so another
    rank looking at the same moment could see a half-made run and fail a good launch (it did under
    load: rank 1 exited with code 2 while rank 0 wrote)."""
    if main_rank and out.is_dir() and any(p.name != TRAIN_LOCK for p in out.iterdir()) and not (out / "config.json").exists():
        raise UserError(f"{out} is not empty and holds no training run (no config.json); use a new or empty --out")


LOG_EVERY_CUDA = 25
"""On CUDA the loss is read back (progress bar, non-finite check) every this many steps and before
each checkpoint: each read waits for the GPU. On the CPU it is read every step (it costs nothing)."""


def rng_state(cuda: bool) -> dict:
    """The random state a resumed run must continue from: torch's CPU generator and, when the run
    trains on CUDA (`cuda`), every GPU's generator (torchvision's anchor / RoI samplers draw from the
    generator of the device their tensors are on). "cuda_rng" is None on the CPU."""
    return {"torch_rng": torch.get_rng_state(),
            "cuda_rng": torch.cuda.get_rng_state_all() if cuda and torch.cuda.is_available() else None}


def restore_rng(state: dict) -> None:
    """Set the generators `rng_state` saved: the CPU's always, the GPUs' where the checkpoint holds
    them and this machine has GPUs (as many as both have)."""
    torch.set_rng_state(state["torch_rng"])
    cuda = state.get("cuda_rng")
    if cuda and torch.cuda.is_available():
        for index, s in enumerate(cuda[: torch.cuda.device_count()]):
            torch.cuda.set_rng_state(s, index)


def checkpoint_state(model, opt, epoch: int, step_in_epoch: int, global_step: int, cuda: bool,
                     epoch_sums: dict | None = None) -> dict:
    """What RUN/checkpoint.pt holds (RESUME_KEYS, the RNG states, and mid-epoch the running sums)."""
    state = {"model": model.state_dict(), "optimizer": opt.state_dict(), "epoch": epoch,
             "step_in_epoch": step_in_epoch, "global_step": global_step, **rng_state(cuda)}
    if epoch_sums is not None:
        state["epoch_sums"] = epoch_sums
    return state


def training_setup(cfg: TrainConfig, ddp):
    """The DeviceSetup of this process: under torchrun the GPU of its LOCAL_RANK (cuda:N refused),
    its share of the cores; the precision `cfg.amp` asks for (None: bf16 on CUDA, fp32 on the CPU)."""
    device = rank_device(cfg.device, ddp.world, ddp.local_rank)
    return resolve_device(device=device, threads=cfg.threads, amp=cfg.amp, workers=cfg.workers)


def check_config(cfg: TrainConfig, reader, ddp, out: Path) -> tuple[list, list[str]]:
    """Refuse (UserError) what cannot be trained; returns the BranchSpecs of the chosen branches (in
    the set's order) and their names as chosen (in --branches order)."""
    if cfg.sampling not in ("global", "per-frame"):
        raise UserError(f"--sampling {cfg.sampling!r}: choose from global, per-frame")
    if ddp.world > 1 and cfg.sampling != "per-frame":
        raise UserError(f"{out}: sampling {cfg.sampling!r} draws each process's anchors from its own global generator; "
                        "data-parallel training needs per-frame sampling (a run started with --sampling per-frame)")
    if ddp.world > 1 and cfg.batch_size < ddp.world:
        raise UserError(f"--batch-size {cfg.batch_size} is the global batch: it needs at least one frame per process "
                        f"({ddp.world} processes)")
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
    if not 0.0 <= cfg.gate_holdout < 1.0:
        raise UserError(f"--gate-holdout is a share of the train split's sequences in [0, 1), got {cfg.gate_holdout}")
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
    return specs, chosen


def run_config(cfg: TrainConfig, reader, specs, chosen: list[str], setup) -> dict:
    """RUN/config.json: the config, the branches, the dataset's generation config, the resolved
    model profile (a later edit of configs/model/<profile>.yaml must not change what `load_run`
    builds for these weights) and `compute`, the device type and precision this run trains in."""
    from study.engine.device import compute_identity

    run_cfg = {**dataclasses.asdict(cfg), "branches": chosen,
               "branch_specs": [dataclasses.asdict(s) for s in specs],
               "data_config": reader.manifest["config"], "profile_fields": to_dict(run_model_profile(cfg)),
               "compute": compute_identity(setup)}
    return json.loads(json.dumps(run_cfg))  # the form it has on disk (tuples become lists)


def check_same_run(out: Path, run_cfg: dict) -> None:
    """Refuse an --out whose config.json describes another run (FREE_ON_RESUME fields may differ)."""
    cfg_path = out / "config.json"
    if not cfg_path.exists():
        return
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


def build_model(cfg: TrainConfig, run_cfg: dict, specs, out: Path, initialise: bool = True):
    """The network of this run, initialised from `cfg.seed` (per-frame sampling installed if asked);
    without its initial draws for a run that resumes (its checkpoint loads every weight and the RNG)."""
    from fusion.nets import build_hydrafusion
    from fusion.nets.sampling import use_frame_seeded_sampling
    from fusion.nets.uninitialised import uninitialised

    torch.manual_seed(cfg.seed)
    with uninitialised() if not initialise else contextlib.nullcontext():
        model = build_hydrafusion(profile=run_profile(run_cfg, out), branches=specs)
    if cfg.sampling == "per-frame":
        use_frame_seeded_sampling(model)
    return model


def write_config(out: Path, run_cfg: dict) -> None:
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "config.json") as tmp:
        tmp.write_text(json.dumps(run_cfg, indent=1))


def epoch_plan(cfg: TrainConfig, n_frames: int, epoch: int, rank: int, world: int):
    """(shares, weights, flips) of an epoch: the frames of each step this process trains on (its share
    of the global batch under torchrun), the share's weight in the batch mean, and which frames are
    mirrored. A rank left without a frame (a last batch smaller than the world) runs one frame with
    weight 0 to join the all-reduce."""
    order = np.random.default_rng([cfg.seed, epoch]).permutation(n_frames)
    flips = np.random.default_rng([cfg.seed, epoch, 1]).random(n_frames) < cfg.hflip
    batches = [order[k:k + cfg.batch_size] for k in range(0, len(order), cfg.batch_size)]
    shares = [_rank_share(b, rank, world) for b in batches] if world > 1 else batches
    weights = [len(s) / len(b) for s, b in zip(shares, batches)]
    shares = [s if len(s) else b[:1] for s, b in zip(shares, batches)]
    return shares, weights, flips


def train_step(net, model, opt, params, cfg: TrainConfig, setup, inputs, targets, metas, lr: float,
               global_step: int, weight: float, world: int):
    """One SGD step on a batch already on the device -> the model's losses (tensors, not read back)."""
    for g in opt.param_groups:
        g["lr"] = lr
    if cfg.sampling == "per-frame":
        from fusion.nets.sampling import set_sample_keys

        set_sample_keys(model, [(cfg.seed, global_step, m["dataset_index"]) for m in metas])
    with setup.autocast():
        losses = net(inputs, targets)
    total = losses["total"]
    opt.zero_grad(set_to_none=True)
    if world > 1:
        # DDP averages gradients over the processes; weighting each process's mean loss by its share
        # of the batch makes that the mean over the batch's frames
        (total * (weight * world)).backward()
    else:
        total.backward()
    if cfg.clip_grad > 0:
        torch.nn.utils.clip_grad_norm_(params, cfg.clip_grad)
    opt.step()
    return losses


def add_losses(sums: dict, losses: dict, weight: float, world: int) -> None:
    """Running per-branch and total loss sums, as float64 tensors on the losses' device (no host
    sync); the same sums a Python float accumulation gives (float32 losses added in float64)."""
    terms = {b: sum(v.detach() for v in ld.values()) for b, ld in losses["branches"].items()}
    terms["total"] = losses["total"].detach()
    for b, v in terms.items():
        v = v.double() if world == 1 else weight * v.double()
        sums[b] = v if b not in sums else sums[b] + v


def sums_as_floats(sums: dict) -> dict[str, float]:
    return {k: float(v) for k, v in sums.items()}


def train_epoch(net, model, opt, params, cfg: TrainConfig, setup, ddp, dataset, epoch: int, step_in_epoch: int,
                global_step: int, resumed: dict, ckpt_path: Path, last_save: float, progress: bool):
    """Steps `step_in_epoch`.. of `epoch`, with mid-epoch checkpoints (rank 0). Returns
    (global_step, the epoch's loss sums as floats, steps counted, seconds of the steps, last_save)."""
    from sim.progress import progress as progress_bar

    shares, weights, flips = epoch_plan(cfg, len(dataset), epoch, ddp.rank, ddp.world)
    sums: dict = {k: torch.tensor(v, dtype=torch.float64, device=setup.device)
                  for k, v in resumed.get("sums", {}).items()}
    counts = resumed.get("steps", 0)
    t0 = time.perf_counter() - resumed.get("seconds", 0.0)
    log_every = LOG_EVERY_CUDA if setup.is_cuda else 1
    finite = torch.ones((), dtype=torch.bool, device=setup.device)
    steps_per_epoch = (len(dataset) + cfg.batch_size - 1) // cfg.batch_size
    # on a terminal a live bar; in a log file (nohup, CI) a line every few seconds (sim.progress)
    bar = progress_bar(total=steps_per_epoch, initial=step_in_epoch, desc=f"epoch {epoch + 1}/{cfg.epochs}",
                       unit="step", enabled=progress)
    for k, (inputs, targets, metas) in _batch_stream(dataset, shares, flips, step_in_epoch, setup.workers,
                                                      setup.is_cuda):
        if setup.is_cuda:  # checked here, on the CPU: inside the model each check would wait for the GPU
            model.check_targets(targets)
        inputs, targets = to_device(inputs, targets, setup.device)
        losses = train_step(net, model, opt, params, cfg, setup, inputs, targets, metas,
                            _lr_at(cfg, epoch, global_step), global_step, weights[k], ddp.world)
        finite &= torch.isfinite(losses["total"].detach())
        global_step += 1
        counts += 1
        add_losses(sums, losses, weights[k], ddp.world)
        bar.update(1)
        due = (k + 1) % cfg.checkpoint_steps == 0 or (
            cfg.checkpoint_seconds > 0 and time.perf_counter() - last_save >= cfg.checkpoint_seconds)
        save = due and k + 1 < len(shares) and ddp.rank == 0
        if counts % log_every == 0 or save or k + 1 == len(shares):
            if not bool(finite):
                raise RuntimeError(f"non-finite loss at epoch {epoch + 1} step {k} (lower --lr?)")
            bar.set_postfix(loss=f"{losses['total'].item():.3f}", lr=f"{opt.param_groups[0]['lr']:.2e}")
        if save:
            last_save = time.perf_counter()
            torch_save_atomic(checkpoint_state(model, opt, epoch, k + 1, global_step, setup.is_cuda,
                                          {"sums": sums_as_floats(sums), "steps": counts,
                                           "seconds": time.perf_counter() - t0}), ckpt_path)
    bar.close()
    return global_step, sums_as_floats(sums), counts, time.perf_counter() - t0, last_save


def finish_epoch(model, opt, cfg: TrainConfig, setup, reader, test_idx, chosen, out: Path, epoch: int,
                 global_step: int, sums: dict, counts: int, t0: float, train_seconds: float) -> dict:
    """Rank 0 at an epoch's end: RUN/epoch-XXX.pt, the test evaluation, the metrics row and plot, the
    checkpoint. Returns the row."""
    from study.report.plots import plot_training_curves

    torch_save_atomic({"model": model.state_dict()}, out / f"epoch-{epoch:03d}.pt")
    evals = evaluate_epoch(model, cfg, reader, test_idx, chosen, setup)
    row = {"epoch": epoch, "steps": global_step, "lr": opt.param_groups[0]["lr"],
           **{f"loss_{b}": round(v / max(counts, 1), 4) for b, v in sums.items()}, **evals,
           "seconds": round(time.perf_counter() - t0, 1), "train_seconds": round(train_seconds, 2)}
    _append_row(out / "metrics.csv", row)
    plot_training_curves(out / "metrics.csv", out / "curves.png")
    torch_save_atomic(checkpoint_state(model, opt, epoch, 0, global_step, setup.is_cuda), out / "checkpoint.pt")
    return row


def train(cfg: TrainConfig, out: Path, progress: bool = True) -> dict:
    """Train (or resume) the run in `out`. Launched by torchrun (WORLD_SIZE > 1), each process
    trains on its share of every batch (`DistributedDataParallel`, gloo on the CPU, NCCL on GPUs)
    and rank 0 alone writes the run directory; `batch_size` stays the global batch."""
    from study.engine import distributed as dist

    ddp = dist.from_env()
    setup = training_setup(cfg, ddp)
    ddp.init(setup.device)
    main_rank = ddp.rank == 0
    progress = progress and main_rank
    check_dataset(cfg.data)  # every shard readable before RUN/ exists
    reader = DatasetReader(cfg.data)
    specs, chosen = check_config(cfg, reader, ddp, out)
    run_cfg = run_config(cfg, reader, specs, chosen, setup)
    srcs = [Path(r) / "checkpoint.pt" for r in cfg.init_from.split(",")] if cfg.init_from else []
    missing = [str(s.parent) for s in srcs if not s.exists()]
    if missing:
        raise UserError(f"--init-from {missing[0]}: no checkpoint.pt there")
    for s in srcs:
        check_warm_start_profile(s.parent, run_cfg)
    check_run_dir(out, main_rank)
    if main_rank:
        check_same_run(out, run_cfg)

    train_idx, test_idx = split_by_sequence(reader, cfg.train_fraction, cfg.split_seed)
    train_idx, _gate_idx = hold_out_sequences(reader, train_idx, cfg.gate_holdout, cfg.split_seed)
    # Every checkpoint the run reads is read (and its weights loaded) before RUN/ is created or its
    # config.json rewritten: a truncated or foreign checkpoint is refused with nothing changed.
    ckpt_path = out / "checkpoint.pt"
    resuming = ckpt_path.exists()  # (no rank writes a checkpoint before the barrier below)
    state = load_checkpoint(ckpt_path, RESUME_KEYS) if resuming else None
    model = build_model(cfg, run_cfg, specs, out, initialise=state is None)
    if state is not None:
        load_weights(model, state["model"], ckpt_path)
    sources = [load_checkpoint(s)["model"] for s in srcs] if cfg.init_from and not resuming else []
    # One train at a time per RUN (the second is refused naming the first's PID, as generate does),
    # taken once everything is checked and read; rank 0 holds it for the whole launch.
    hold = contextlib.ExitStack()
    if main_rank:
        out.mkdir(parents=True, exist_ok=True)
        hold.enter_context(output_lock(out, "train"))
    with hold:
        if main_rank:
            write_config(out, run_cfg)
        ddp.barrier()  # rank 0 has checked and written config.json; no checkpoint is written before this
        if sources:
            apply_warm_start(model, sources, srcs, out, main_rank, progress)
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
            restore_rng(state)
            resumed = state.get("epoch_sums", {}) if step_in_epoch else {}
            if progress:
                sys.stderr.write(f"resuming {out} at epoch {epoch + 1}, step {step_in_epoch}\n")
        net = ddp.wrap(model, setup)  # DistributedDataParallel under torchrun, the model itself otherwise
        if progress and ddp.world > 1:
            sys.stderr.write(f"data-parallel: {ddp.world} processes ({ddp.backend}), global batch {cfg.batch_size}\n")
        # frames travel to a GPU as the uint8 they are on disk and become float there (4x fewer bytes)
        dataset = FrameDataset(cfg.data, train_idx, sensors=model.sensors_for(None),
                               bev_size=model.transform.image_size("radar"), protocol=cfg.protocol, uint8=setup.is_cuda)
        result = {}
        last_save = time.perf_counter()  # the time-based checkpoints count from here (and each save)
        while epoch < cfg.epochs:
            t_epoch = time.perf_counter() - resumed.get("seconds", 0.0)
            global_step, sums, counts, train_seconds, last_save = train_epoch(
                net, model, opt, params, cfg, setup, ddp, dataset, epoch, step_in_epoch, global_step, resumed,
                ckpt_path, last_save, progress)
            resumed = {}
            sums = ddp.sum_dict(sums)  # the batch-mean losses of every process added up (one process: as is)
            epoch += 1
            step_in_epoch = 0
            if main_rank:
                result = finish_epoch(model, opt, cfg, setup, reader, test_idx, chosen, out, epoch, global_step, sums,
                                      counts, t_epoch, train_seconds)
                last_save = time.perf_counter()
                if progress:
                    sys.stderr.write(json.dumps(result) + "\n")
            ddp.barrier()  # the others wait for rank 0's evaluation and checkpoint
        metrics_path = out / "metrics.csv"
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
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
