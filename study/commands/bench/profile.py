"""`hydrabench bench profile`: where one training step's time goes (`study.bench.step_profile`)."""

from __future__ import annotations

from study.bench.pipeline import machine
from study.cli import (
    Formatter,
    emit,
)
from study.commands.bench.common import add_training_bench_args, format_bench_doc, parse_model_args


def add_parser(what) -> None:
    pr = what.add_parser("profile", help="where one training step's time goes: stems, layer2-4, RPN, RoIAlign, box head, "
                         "backward, optimiser", description=format_bench_doc("study.bench.step_profile"), formatter_class=Formatter)
    add_training_bench_args(pr, "timed steps", "train on this dataset's first frames and time reading them (default: "
                         "synthetic frames)")
    pr.add_argument("--precision", choices=("fp32", "bf16"), default="fp32",
                    help="fp32, or bf16 autocast of the backbones (as train --amp)")
    pr.set_defaults(run=run_profile)


def run_profile(args) -> int:
    from study.bench.step_profile import bench_profile

    r = bench_profile(args.profile, tuple(args.branches), batch=args.batch_size, steps=args.steps, warmup=args.warmup,
                      threads=args.threads, seed=args.seed, precision=args.precision,
                      data=str(args.data) if args.data else None, overrides=parse_model_args(args))
    r["parse_model_args"] = list(args.model or ())
    r.update(machine())

    def text(r):
        lines = [f"{r['cpu'] or 'CPU'}, {r['threads']} threads; {r['profile']} profile, {', '.join(r['branches'])}, "
                 f"batch {r['batch']}, {r['precision']}, {r['frames']} frames: step {r['step_ms']} ms "
                 f"(median of {r['steps']})"]
        for p, ms in r["parts_ms"].items():
            lines.append(f"  {p:16s} {ms:9.1f} ms  {r['parts_pct'][p]:5.1f} %")
        lines.append("  backward by kind: " + ", ".join(f"{k} {v} %" for k, v in r["backward_by_kind_pct"].items()))
        if r["data_ms"] is not None:
            lines.append(f"  data (read + collate, outside the step) {r['data_ms']} ms")
        lines.append("  layer2/3/4 feature maps (H, W): " + "; ".join(
            f"{b} " + " ".join(f"{k} {v[0]}x{v[1]}" for k, v in s.items()) for b, s in r["feature_map_hw"].items()))
        return "\n".join(lines)

    emit(r, args.json, text)
    return 0
