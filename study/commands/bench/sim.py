"""`hydrabench bench sim`: scene steps per second per context (`study.bench.pipeline.bench_sim`)."""

from __future__ import annotations

from study.cli import (
    Formatter,
    emit,
    nonneg_int,
    pos_int,
)


def add_parser(what) -> None:
    s = what.add_parser("sim", help="scene steps per second per context (one core)",
                        description="Simulate each context for --frames frames after its setup and "
                        "report steady-state scene steps per second (one process, one core).",
                        formatter_class=Formatter)
    s.add_argument("--frames", type=pos_int, default=200, help="recorded frames per context")
    s.add_argument("--seed", type=nonneg_int, default=0, help="root random seed")
    s.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    s.set_defaults(run=run_sim)


def run_sim(args) -> int:
    from study.bench.pipeline import bench_sim

    result = bench_sim(frames=args.frames, seed=args.seed)
    emit(result, args.json, lambda r: "\n".join(
        [f"{c:9s} {v:8.1f} scenes/s  (setup {r['setup_seconds'][c]:.2f} s incl. warm-up)"
         for c, v in r["scenes_per_second"].items()]))
    return 0
