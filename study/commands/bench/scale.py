"""`hydrabench bench scale`: training images/s over threads and processes, generate local pool vs Ray (`study.bench.scale`)."""

from __future__ import annotations

import argparse

from study.cli import (
    Formatter,
    dataset_dir,
    emit,
    int_range,
    name_list,
    nonneg_int,
    out_file,
    workers_int,
)


def add_parser(what) -> None:
    c = what.add_parser("scale", help="training images/s at 1 and 2 threads, DDP 2 processes vs 1, generate local pool vs Ray",
                        description="In one run, back to back on a small dataset it generates (or --data): CPU "
                        "training images/s of `hydrabench train` at --threads 1 and 2; DDP with 2 gloo processes "
                        "(torchrun on 127.0.0.1, 1 thread each) against 1 process at 2 threads with the same global "
                        "batch (step time, images/s, and the largest difference of their final weights); and "
                        "`generate` frames/s with the local process pool against --backend ray (a local Ray started "
                        "and stopped by the command; skipped, with the reason, when Ray cannot start). Reports the "
                        "ratios, the machine and its load average before and after; training times are the steps "
                        "of the last epoch (metrics.csv train_seconds), each run a fresh process.",
                        formatter_class=Formatter)
    c.add_argument("--parts", type=parts_arg, default="train,ddp,generate",
                   help="comma-separated parts to measure: train (1 vs 2 threads), ddp (2 processes vs 1), "
                   "generate (local pool vs Ray)")
    c.add_argument("--data", type=dataset_dir, default=None, metavar="DATASET",
                   help="train on this cpu-profile dataset (default: the local-pool dataset of part generate, "
                   "or one generated for the run with --contexts etc.)")
    c.add_argument("--contexts", type=name_list, default=("all",),
                   help="'all' or comma-separated contexts of the generated dataset [all]")
    c.add_argument("--frames-per-context", type=int_range(1, 1000, "frames-per-context"), default=2,
                   help="frames per context of the generated dataset, at most 1000")
    c.add_argument("--sequence-length", type=int_range(1, 1000, "sequence-length"), default=2,
                   help="frames per sequence (one sequence per context: every frame trains, no evaluation between)")
    c.add_argument("--seed", type=nonneg_int, default=0, help="seed of the generated dataset and of the training runs")
    c.add_argument("--branches", type=name_list, default=("radar",),
                   help="comma-separated branches to train (cpu model profile) [radar]")
    c.add_argument("--batch-size", type=int_range(2, 1024, "batch-size"), default=4,
                   help="frames per SGD step, the global batch of the DDP run (2 to 1024)")
    c.add_argument("--epochs", type=int_range(1, 100, "epochs"), default=1,
                   help="epochs per training run, the last one timed (2: the first absorbs warm-up), at most 100")
    c.add_argument("--workers", type=workers_int, default=2,
                   help="local pool processes and Ray CPUs of part generate, at most 256")
    c.add_argument("--model", action="append", default=None, metavar="KEY=VALUE",
                   help="override a cpu model-profile field for every training run, repeatable, as `train --model`")
    c.add_argument("--plot", type=out_file(".png"), default=None, metavar="PNG", help="also draw the ratios into this PNG file")
    c.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    c.set_defaults(run=run_scale)


def parts_arg(text: str) -> tuple[str, ...]:
    """An argparse type: comma-separated parts of `bench scale` (train, ddp, generate), each once."""
    from study.bench.scale import PARTS

    items = name_list(text)
    bad = [p for p in items if p not in PARTS]
    if bad:
        raise argparse.ArgumentTypeError(f"unknown part {bad[0]!r} (choose from: {', '.join(PARTS)})")
    return items


parts_arg.kind = "names"


def run_scale(args) -> int:
    from study.bench.scale import ScaleConfig, bench_scale, check, plot_scale, text_table
    from study.outputs import check_writable_file

    cfg = ScaleConfig(parts=tuple(args.parts), data=args.data, contexts=tuple(args.contexts),
                      frames_per_context=args.frames_per_context, sequence_length=args.sequence_length, seed=args.seed,
                      branches=tuple(args.branches), batch_size=args.batch_size, epochs=args.epochs, workers=args.workers,
                      model=tuple(args.model or ()))
    check(cfg)  # everything refusable is refused before any work
    plot = check_writable_file(args.plot, (".png",)) if args.plot else None
    r = bench_scale(cfg)
    if plot is not None:
        plot_scale(r, plot)
    r["plot"] = str(plot) if plot is not None else None
    emit(r, args.json, text_table)
    return 0
