"""`hydrabench bench amp`: training step time fp32 against bf16 autocast (`study.bench.amp.bench_amp`)."""

from __future__ import annotations

from study.bench.pipeline import machine
from study.cli import (
    Formatter,
    emit,
)
from study.commands.bench.common import add_training_bench_args, parse_model_args


def add_parser(what) -> None:
    a = what.add_parser("amp", help="training step time fp32 against bf16 autocast on this CPU, side by side",
                        description="Two copies of one network (same profile, branches, initial weights and frames) "
                        "train a few SGD steps, fp32 and bf16 autocast interleaved step by step; reports the median "
                        "step time of each, the speed-up, the losses after the same steps, and whether this CPU has "
                        "native bf16 (AMX-BF16 / AVX512-BF16), which is what --amp auto picks by.",
                        formatter_class=Formatter)
    add_training_bench_args(a, "timed steps of each precision", "train on this dataset's first frames (default: "
                         "synthetic frames)")
    a.set_defaults(run=run_amp)


def run_amp(args) -> int:
    from study.bench.amp import bench_amp

    r = bench_amp(args.profile, tuple(args.branches), batch=args.batch_size, steps=args.steps, warmup=args.warmup,
                  threads=args.threads, seed=args.seed, data=str(args.data) if args.data else None,
                  overrides=parse_model_args(args))
    r["parse_model_args"] = list(args.model or ())
    r.update(machine())
    emit(r, args.json, lambda r: "\n".join([
        f"{r['cpu'] or 'CPU'}, {r['threads']} threads; {r['profile']} profile, {', '.join(r['branches'])} "
        f"({r['parameters_m']} M parameters), batch {r['batch']}, {r['frames']} frames",
        f"native bf16: {r['native_bf16']} ({r['native_bf16_reason']}); --amp auto picks {r['amp_auto_picks']}",
        f"step time fp32 {r['step_s']['fp32']} s, bf16 {r['step_s']['bf16']} s: x{r['speedup_bf16']} "
        f"(median of {r['steps']} steps each, interleaved)",
        "loss per step fp32 " + ", ".join(map(str, r["loss_per_step"]["fp32"]))
        + "; bf16 " + ", ".join(map(str, r["loss_per_step"]["bf16"]))]))
    return 0
