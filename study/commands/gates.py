"""`hydrabench train-gate`: the command line of `study.gates.train_gate` (the gate dataset and the
training are described in `study.gate_data` and `study.gates`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from study import gates
from study.cli import (
    Formatter,
    checkpoint_arg,
    dataset_dir,
    emit,
    name_arg,
    nonneg_int,
    pos_float,
    pos_int,
    training_run,
)
from study.commands.device import add_device_args
from study.device import resolve_device

TRAIN_EPILOG = """\
examples:
  hydrabench train-gate runs/all data/train1600 --gate deep
  hydrabench train-gate runs/all data/train1600 --gate attention --epochs 200 --json
  hydrabench evaluate runs/all data/train1600 --all-gates --json          (Tables 6 and 7)
DATA must be the run's training dataset: the gate trains on the run's train split (minus a
validation share of its sequences, which picks the epoch) and is tested on its test split.
"""


def _grid_arg(text: str) -> tuple[int, int]:
    try:
        rows, cols = (int(t) for t in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected ROWSxCOLS such as 8x16, got {text!r}") from None
    if rows < 4 or cols < 4:
        raise argparse.ArgumentTypeError(f"grid must be at least 4x4, got {text!r}")
    return rows, cols


def _fraction(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not 0.0 <= v < 1.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 1), got {v}")
    return v


def add_train_gate(sub, name, help_text):
    doc = gates.__doc__.split("**train-gate**", 1)[1].split("**Tables.**", 1)[0]
    p = sub.add_parser(name, help=help_text, description="hydrabench train-gate" + doc.rstrip(), epilog=TRAIN_EPILOG,
                       formatter_class=Formatter)
    p.add_argument("run_dir", metavar="RUN", type=training_run, help="training run directory (hydrabench train --out)")
    p.add_argument("data", type=dataset_dir, help="the run's training dataset")
    p.add_argument("--gate", type=name_arg, required=True, help="deep | attention (the gates that learn)")
    p.add_argument("--epochs", type=pos_int, default=100, help="passes over the training frames (more: continues)")
    p.add_argument("--batch-size", type=pos_int, default=32, help="frames per Adam step")
    p.add_argument("--lr", type=pos_float, default=5e-5, help="Adam learning rate (HydraFusion 5.3)")
    p.add_argument("--val-fraction", type=_fraction, default=0.15,
                   help="share of the train split's sequences held out to pick the epoch")
    p.add_argument("--grid", type=_grid_arg, default="8x16", help="ROWSxCOLS the stem features are pooled to")
    p.add_argument("--seed", type=nonneg_int, default=0, help="initialisation, data order, validation split")
    p.add_argument("--checkpoint", type=checkpoint_arg, default="latest", help="latest, or epoch-NNN")
    p.add_argument("--fresh", action="store_true", help="discard a previous training of this gate")
    add_device_args(p, purpose="eval")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(run=run_train_gate)


def run_train_gate(args) -> int:
    setup = resolve_device(args, purpose="eval")
    cfg = gates.GateTrainConfig(gate=args.gate, epochs=args.epochs, batch_size=args.batch_size, lr=args.lr,
                          val_fraction=args.val_fraction, seed=args.seed, grid=tuple(args.grid),
                          checkpoint=args.checkpoint, threads=setup.threads)
    result = gates.train_gate(Path(args.run_dir), Path(args.data), cfg, fresh=args.fresh, setup=setup)

    def text(r):
        lines = [f"{r['gate']} gate: held-out MAE {r['test_mae']} vs constant predictor {r['constant_mean_mae']} "
                 f"(per-branch training mean; median {r['constant_median_mae']}) on {r['test_frames']} test frames",
                 f"  trained on {r['train_frames']} frames with {r['optimizer']} lr {r['lr']}, best epoch "
                 f"{r['best_epoch']} of {r['epochs']} by validation MAE {r['val_mae']} ({r['val_frames']} frames)",
                 f"  top-1 agreement with optimal {r['top1_agreement_with_optimal']}, top-3 overlap "
                 f"{r['top3_overlap_with_optimal']}",
                 "  per branch (gate / constant): " + ", ".join(
                     f"{b} {v}/{r['constant_mean_mae_per_branch'][b]}" for b, v in r["test_mae_per_branch"].items()),
                 f"  saved {r['gate_path']}"]
        return "\n".join(lines)

    emit(result, args.json, text)
    return 0
