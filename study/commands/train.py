"""`hydrabench train`: the command line of `study.engine.train` (what a run holds is described there)."""

from __future__ import annotations

import json
from pathlib import Path

from study.cli import (
    Formatter,
    count_int,
    dataset_dir,
    emit,
    holdout_fraction,
    module_doc,
    name_arg,
    name_list,
    nonneg_float,
    nonneg_int,
    out_dir,
    pos_float,
    pos_int,
    probability,
)
from study.commands.device import add_device_args
from study.engine.device import rank_device, resolve_device

EPILOG = """\
examples:
  hydrabench train data/train1k --out runs/cam_radar --branches camera_right,radar --epochs 12
  hydrabench train data/train1k --out runs/all --epochs 10          (all seven branches)
  hydrabench train data/train1k --out runs/early --branch-set early_fusion
Branch sets (--branch-set): paper (the seven), single (one branch per sensor), early_fusion
(input-level: cameras, cameras + forward lidar, radar + lidar), late_fusion (= single, fused at
evaluation). --branches picks a subset of the set by name.
"""


def add_parser(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=module_doc("study.engine.train").split("\n\n", 1)[1], epilog=EPILOG,
                       formatter_class=Formatter)
    p.add_argument("data", type=dataset_dir, help="dataset directory")
    p.add_argument("--out", required=True, type=out_dir, help="run directory (created; an existing run is resumed)")
    p.add_argument("--profile", type=name_arg, default="cpu", help="model profile (configs/model)")
    p.add_argument("--branch-set", type=name_arg, default="paper", help="paper | single | early_fusion | late_fusion")
    p.add_argument("--branches", type=name_list, default=None,
                   help="comma-separated branch names from the set, each once (default: the whole set)")
    p.add_argument("--epochs", type=pos_int, default=10, help="passes over the training split (more: extends a run)")
    p.add_argument("--batch-size", type=pos_int, default=4, help="frames per SGD step")
    p.add_argument("--lr", type=pos_float, default=5e-3, help="SGD learning rate (HydraFusion 5.3)")
    p.add_argument("--warmup-steps", type=count_int, default=100, help="steps of linear lr warm-up from lr/1000")
    p.add_argument("--lr-drop-epoch", type=count_int, default=0, help="lr x 0.1 from this epoch (0: 3/4 of --epochs)")
    p.add_argument("--clip-grad", type=nonneg_float, default=10.0, help="max gradient norm (0: no clipping)")
    p.add_argument("--seed", type=nonneg_int, default=0, help="initialisation and data order")
    p.add_argument("--eval-frames", type=count_int, default=0, help="test frames evaluated per epoch (0 = all)")
    p.add_argument("--checkpoint-steps", type=pos_int, default=100, help="also checkpoint every N steps within an epoch")
    p.add_argument("--checkpoint-seconds", type=nonneg_float, default=600.0,
                   help="also checkpoint when this many seconds passed since the last one (0: off); a kill loses at "
                   "most this much work")
    p.add_argument("--init-from", type=name_list, default=None, help="initialise from trained runs or reference models (models/: e.g. cpu-ref), comma-separated in priority "
                   "order: each branch / stem from the first run that has it or its origin (other camera-view "
                   "branches from camera_right, BEV ones from radar)")
    p.add_argument("--hflip", type=probability, default=0.0, help="probability of mirroring a training frame left-right "
                   "(all sensors and labels together; not with branches that fuse both cameras)")
    p.add_argument("--gate-holdout", type=holdout_fraction, default=0.0,
                   help="share of the train split's sequences, per context, the detectors do not train on: the run's "
                   "gate split, where train-gate and eco-train-gate learn each branch's loss on unseen frames "
                   "(default 0: none)")
    p.add_argument("--protocol", default="reference", choices=("reference", "visible", "bev"),
                   help="ground truth to train on and test against (README, 'Evaluation protocols'): reference = "
                   "the projected 3D box of every actor within range that some sensor observes (world truth); "
                   "visible = the camera's visible-pixel boxes, small ones ignored; bev = as reference, BEV "
                   "branches scored on their own grid")
    p.add_argument("--sampling", default="auto", choices=["auto", "global", "per-frame"],
                   help="anchor / RoI sampling of the detection losses: global (torch's generator, one image after "
                   "the other), per-frame (seeded per frame and step: the same whatever the number of processes); "
                   "auto: the run's own, else per-frame under torchrun and global in one process")
    p.add_argument("--model", action="append", default=None, metavar="KEY=VALUE",
                   help="override a model-profile field, repeatable: width=0.5 (layer2-4 channels x 0.5), "
                   "dilation=true (stride-1 stages dilated), channels_last=true, bev.output_stride=16, "
                   "box_batch_size_per_image=64, ... (configs/model/<profile>.yaml names them; sizes, classes and "
                   "branches are fixed by the dataset). Recorded in RUN/config.json")
    add_device_args(p)
    p.add_argument("--json", action="store_true", help="print one JSON object (final metrics) on stdout")
    p.set_defaults(run=run)


def run(args) -> int:
    from study.engine import train as training
    from study.engine.distributed import from_env
    from study.engine.reference_model import resolve_run

    job = from_env()
    # cuda:N under torchrun, or a device this machine does not have: refused before anything is written
    resolve_device(args, device=rank_device(args.device, job.world, job.local_rank), apply=False)
    cfg = training.TrainConfig(
        data=str(Path(args.data).resolve()), model_profile=args.profile, branch_set=args.branch_set,
        branches=tuple(args.branches or ()), epochs=args.epochs,
        batch_size=args.batch_size, lr=args.lr, warmup_steps=args.warmup_steps, lr_drop_epoch=args.lr_drop_epoch,
        clip_grad=args.clip_grad, seed=args.seed, eval_frames=args.eval_frames, threads=args.threads,
        checkpoint_steps=args.checkpoint_steps,
        checkpoint_seconds=args.checkpoint_seconds, init_from=",".join(str(resolve_run(r).resolve()) for r in args.init_from or ()),
        hflip=args.hflip, gate_holdout=args.gate_holdout, protocol=args.protocol, device=args.device, amp=args.amp, workers=args.workers,
        sampling=_resolve_sampling(args.sampling, Path(args.out)), model=tuple(args.model or ()),
    )
    result = training.train(cfg, Path(args.out))
    if job.rank == 0:  # one JSON object, from one process
        emit(result, args.json, lambda r: f"run {r['run']}: {r['epochs']} epochs, last epoch {r['last']}")
    return 0


def _resolve_sampling(choice: str, out: Path) -> str:
    """--sampling auto: the run's own (runs from before the option: global); a new run per-frame under
    torchrun, global in one process (torchvision's behaviour, so one-process results stay as they were)."""
    if choice != "auto":
        return choice
    cfg_path = out / "config.json"
    if cfg_path.exists():
        return json.loads(cfg_path.read_text()).get("sampling", "global")
    from study.engine.distributed import from_env

    return "per-frame" if from_env().world > 1 else "global"
