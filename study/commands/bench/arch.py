"""`hydrabench bench arch`: training-step time of the model's cost options (`study.bench.arch`)."""

from __future__ import annotations

from study.bench.pipeline import machine
from study.cli import (
    Formatter,
    dataset_dir,
    emit,
    int_range,
    name_arg,
    name_list,
    nonneg_int,
)
from study.commands.bench.common import format_bench_doc


def add_parser(what) -> None:
    ar = what.add_parser("arch", help="training-step time of the model's cost options (width, dilation, channels_last, "
                         "stride, RoIs), fp32 and bf16, side by side", description=format_bench_doc("study.bench.arch"),
                         formatter_class=Formatter)
    ar.add_argument("--profile", type=name_arg, default="cpu", help="model profile")
    ar.add_argument("--branches", type=name_list, default=(), help="comma-separated branches (default: the profile's)")
    ar.add_argument("--variant", action="append", default=None, metavar="NAME:KEY=VALUE[+KEY=VALUE]",
                    help="a variant (repeatable; the first is the base, 'base:' for none); default: base, width 0.5, "
                    "width 0.25, channels_last, dilation, bev stride 16, 64 RoIs, width 0.5 + channels_last")
    ar.add_argument("--precisions", type=name_list, default="fp32,bf16", help="fp32 and/or bf16")
    ar.add_argument("--batch-size", type=int_range(1, 64, "batch-size"), default=4, help="frames per step")
    ar.add_argument("--steps", type=int_range(1, 1000, "steps"), default=3, help="timed steps per variant and precision")
    ar.add_argument("--warmup", type=int_range(0, 100, "warmup"), default=1, help="untimed steps first")
    ar.add_argument("--threads", type=nonneg_int, default=0, help="torch CPU threads (0: the cores available)")
    ar.add_argument("--seed", type=nonneg_int, default=0, help="initial weights, frames and sampling")
    ar.add_argument("--data", type=dataset_dir, default=None, metavar="DATASET",
                    help="train on this dataset's first frames (default: synthetic frames)")
    ar.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    ar.set_defaults(run=run_arch)


def run_arch(args) -> int:
    from sim.errors import UserError
    from study.bench.arch import bench_arch, parse_variant

    variants = dict(parse_variant(v) for v in args.variant) if args.variant else None
    if args.variant and len(variants) != len(args.variant):
        raise UserError("--variant: each name once")
    precisions = tuple(args.precisions if not isinstance(args.precisions, str) else args.precisions.split(","))
    r = bench_arch(args.profile, tuple(args.branches), variants, precisions, batch=args.batch_size, steps=args.steps,
                   warmup=args.warmup, threads=args.threads, seed=args.seed,
                   data=str(args.data) if args.data else None)
    r.update(machine())

    def text(r):
        ps = r["precisions"]
        lines = [f"{r['cpu'] or 'CPU'}, {r['threads']} threads; {r['profile']} profile, {', '.join(r['branches'])}, "
                 f"batch {r['batch']}, {r['frames']} frames, median of {r['steps']} steps; ratios against "
                 f"{r['base']!r} in the same run",
                 f"{'variant':28s} {'M params':>8s} {'fp16 MiB':>8s} " + " ".join(f"{p + ' s':>8s} {'x':>5s}" for p in ps)]
        for name, v in r["variants"].items():
            lines.append(f"{name:28s} {v['parameters_m']:8.1f} {v['float16_mib']:8.1f} " + " ".join(
                f"{v['step_s'][p]:8.3f} {v['speedup_vs_base'][p]:5.2f}" for p in ps))
        return "\n".join(lines)

    emit(r, args.json, text)
    return 0
