"""`hydrabench train-gate`: the command line of `study.engine.gate_training.train_gate` (the gate dataset
and the training are described in `study.engine.gate_data` and `study.engine.gate_training`)."""

from __future__ import annotations

from pathlib import Path

from study.cli import (
    Formatter,
    checkpoint_arg,
    dataset_dir,
    emit,
    holdout_fraction,
    name_arg,
    nonneg_float,
    nonneg_int,
    pool_grid,
    pos_float,
    pos_int,
    training_run,
)
from study.commands.device import add_device_args
from study.engine import gate_training as branch_gate_study
from study.engine.device import resolve_device

TRAIN_EPILOG = """\
examples:
  hydrabench train-gate runs/all data/train1600 --gate deep
  hydrabench train-gate runs/all data/train1600 --gate attention --epochs 200 --json
  hydrabench evaluate runs/all data/train1600 --all-gates --json          (Tables 6 and 7)
DATA must be the run's training dataset: the gate trains on the run's train split (minus a
validation share of its sequences, which picks the epoch) and is tested on its test split.
"""


def add_objective_args(p) -> None:
    """--objective, --tau and --select-on (train-gate and eco-train-gate; fusion.gate_objectives)."""
    from fusion.gate_objectives import OBJECTIVES

    p.add_argument("--objective", default=branch_gate_study.AUTO,
                   choices=[branch_gate_study.AUTO, *OBJECTIVES.names(), branch_gate_study.ROUTER],
                   help="what the gate learns: mae regresses each choice's loss (the papers'); centred its "
                        "difference from the frame's mean; soft_ce the soft ranking softmax(-L/tau); expected the "
                        "expected regret of its choice; best_label classifies the frame's best choice; context "
                        "classifies the frame's context and routes by the per-context table (weather-conditioned "
                        "routing); auto (default) trains one gate per objective and keeps the lowest regret on the "
                        "validation sequences")
    p.add_argument("--tau", type=nonneg_float, default=0.0,
                   help="temperature of soft_ce and expected, in loss units (0: the median within-frame spread)")
    p.add_argument("--targets", default="auto", choices=["auto", "holdout", "train"],
                   help="which frames' per-branch losses the gate learns: holdout, the run's gate split (trained with "
                        "train --gate-holdout: frames the detectors never saw); train, the detectors' own training "
                        "frames (where overfitting branches look better than they are); auto (default): holdout when "
                        "the run has a gate split. Both are validated on the same gate-split sequences")
    p.add_argument("--context-inputs", action="store_true",
                   help="the gate also reads the frame's context label: road layout (one-hot) and conditions "
                        "(multi-hot), what a map, a rain sensor, a light sensor and a clock tell a car; never the "
                        "severity or lens cover, which only the simulator knows")
    p.add_argument("--pooling", default="grid", choices=["grid", "global"],
                   help="grid (default): the gate's convs read the stem features pooled to --grid; global: an MLP "
                        "on each stem channel's mean (compact features; deep gate only)")
    p.add_argument("--select-on", default="regret", choices=list(branch_gate_study.SELECT_ON),
                   help="what picks the epoch on the validation sequences: the regret of the gate's choice "
                        "(ties by MAE) or MAE")


def parse_objective_fields(args) -> dict:
    return {"objective": args.objective, "tau": args.tau, "select_on": args.select_on, "targets": args.targets,
            "context": args.context_inputs, "pooling": args.pooling}


def format_choice_lines(r: dict, what: str) -> list[str]:
    """The gate's choice on the test frames beside the best constant, the per-context constant and the oracle."""
    c = r.get("choice")
    if not c:
        return []
    lines = []
    if r.get("context") or r.get("pooling", "grid") != "grid":
        lines.append(f"  inputs: stem features pooled {'per channel' if r.get('pooling') == 'global' else 'to the grid'}"
                     + (", and the context label (layout, conditions)" if r.get("context") else ""))
    if r.get("targets"):
        lines.append(f"  targets: {r['targets']} ({r.get('train_frames')} frames: "
                     + ("the gate split, never seen by the detectors" if r["targets"] == "holdout"
                        else "the detectors' own training frames") + f"); validation {r.get('val_frames')} frames")
    if len(r.get("objectives") or {}) > 1:
        lines.append("  objectives (validation regret, the lowest kept): " + ", ".join(
            f"{n} {v['val_regret']}" for n, v in r["objectives"].items()) + f" -> {r['objective']}")
    return lines + [f"  choice ({r['objective']}, epoch picked on {r['selected_on']}): mean test {what} {c['mean_cost']:.4f}, "
            f"regret {c['regret']:.4f}; best constant ({c['constant']}) {c['constant_mean_cost']:.4f}, regret "
            f"{c['constant_regret']:.4f}; per-context constant regret {c.get('context_regret', float('nan')):.4f}; "
            f"oracle {c['oracle_mean_cost']:.4f}; differs from the constant on {100 * c['differs_from_constant']:.1f} % "
            "of the frames"]


def add_train_gate(sub, name, help_text):
    doc = branch_gate_study.__doc__.split("**train-gate**", 1)[1].split("**Tables.**", 1)[0]
    p = sub.add_parser(name, help=help_text, description="hydrabench train-gate" + doc.rstrip(), epilog=TRAIN_EPILOG,
                       formatter_class=Formatter)
    p.add_argument("run_dir", metavar="RUN", type=training_run, help="training run directory (hydrabench train --out)")
    p.add_argument("data", type=dataset_dir, help="the run's training dataset")
    p.add_argument("--gate", type=name_arg, required=True, help="deep | attention (the gates that learn)")
    p.add_argument("--epochs", type=pos_int, default=100, help="passes over the training frames (more: continues)")
    p.add_argument("--batch-size", type=pos_int, default=32, help="frames per Adam step")
    p.add_argument("--lr", type=pos_float, default=5e-5, help="Adam learning rate (HydraFusion 5.3)")
    p.add_argument("--val-fraction", type=holdout_fraction, default=0.15,
                   help="share of the gate split's sequences (the train split's when the run has none), per "
                        "context, held out to pick the epoch and objective")
    p.add_argument("--grid", type=pool_grid, default="8x16", help="ROWSxCOLS the stem features are pooled to")
    p.add_argument("--seed", type=nonneg_int, default=0, help="initialisation, data order, validation split")
    p.add_argument("--checkpoint", type=checkpoint_arg, default="latest", help="latest, or epoch-NNN")
    add_objective_args(p)
    p.add_argument("--k", type=pos_int, default=1,
                   help="the branches the gate will run per frame (compare --k): the epoch and objective are chosen "
                        "by the validation regret of its top k (the summed loss of the k it ranks first minus the "
                        "frame's k best), so a gate that runs two is chosen for two")
    p.add_argument("--fresh", action="store_true", help="discard a previous training of this gate")
    add_device_args(p, purpose="eval")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(run=run_train_gate)


def run_train_gate(args) -> int:
    setup = resolve_device(args, purpose="eval")
    cfg = branch_gate_study.GateTrainConfig(gate=args.gate, epochs=args.epochs, batch_size=args.batch_size,
                                            lr=args.lr, val_fraction=args.val_fraction, seed=args.seed,
                                            grid=tuple(args.grid), checkpoint=args.checkpoint, threads=setup.threads,
                                            k=args.k, **parse_objective_fields(args))
    result = branch_gate_study.train_gate(Path(args.run_dir), Path(args.data), cfg, fresh=args.fresh, setup=setup)

    def text(r):
        lines = [f"{r['gate']} gate: held-out MAE {r['test_mae']} vs constant predictor {r['constant_mean_mae']} "
                 f"(per-branch training mean; median {r['constant_median_mae']}) on {r['test_frames']} test frames",
                 f"  trained on {r['train_frames']} frames with {r['optimizer']} lr {r['lr']}, best epoch "
                 f"{r['best_epoch']} of {r['epochs']} by validation MAE {r['val_mae']} ({r['val_frames']} frames)",
                 f"  top-1 agreement with optimal {r['top1_agreement_with_optimal']}, top-3 overlap "
                 f"{r['top3_overlap_with_optimal']}",
                 "  per branch (gate / constant): " + ", ".join(
                     f"{b} {v}/{r['constant_mean_mae_per_branch'][b]}" for b, v in r["test_mae_per_branch"].items()),
                 *format_choice_lines(r, "loss of the chosen branch"),
                 f"  saved {r['gate_path']}"]
        return "\n".join(lines)

    emit(result, args.json, text)
    return 0
