"""`hydrabench bench bootstrap`: the sequence bootstrap scored per draw against ranked once
(`study.bench.bootstrap`)."""

from __future__ import annotations

from study.bench.pipeline import machine
from study.cli import Formatter, emit, int_range, nonneg_int


def add_parser(what) -> None:
    b = what.add_parser("bootstrap", help="the sequence bootstrap: each draw pooled and ranked again against ranked "
                        "once and weighted (seconds, equal intervals)",
                        description="Time the paired sequence bootstrap of `compare` and the study (every method's mAP "
                        "on every draw, overall and per context) on a synthetic test set of the verdict's shape, "
                        "scored per draw (the old way) and by weighting detections ranked once; checks that both "
                        "give the same mAP on every draw (to 1e-9).",
                        formatter_class=Formatter)
    b.add_argument("--frames", type=int_range(8, 100_000, "frames"), default=1152, help="test frames")
    b.add_argument("--sequence-length", type=int_range(1, 100, "sequence length"), default=3,
                   help="frames per sequence")
    b.add_argument("--methods", type=int_range(1, 100, "methods"), default=11, help="methods scored on each draw")
    b.add_argument("--detections", type=int_range(1, 1000, "detections"), default=60,
                   help="detections per frame and method (mean)")
    b.add_argument("--resamples", type=int_range(1, 100_000, "resamples"), default=500, help="bootstrap draws per group")
    b.add_argument("--pooled-resamples", type=nonneg_int, default=20,
                   help="draws per group timed the old way (its time is scaled to --resamples); 0: skip it")
    b.add_argument("--seed", type=nonneg_int, default=0, help="random seed of the synthetic set and the draws")
    b.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    b.set_defaults(run=run_bootstrap)


def run_bootstrap(args) -> int:
    from study.bench.bootstrap import bench_bootstrap
    from study.bench.scale import cpu_model

    r = bench_bootstrap(frames=args.frames, sequence_length=args.sequence_length, methods=args.methods,
                        detections=args.detections, resamples=args.resamples,
                        pooled_resamples=args.pooled_resamples, seed=args.seed)
    r = {**r, "cpu": cpu_model(), **machine()}

    def text(r):
        pooled = ("not timed" if r["pooled_s_scaled"] is None else
                  f"{r['pooled_s_scaled']:.1f} s (timed on {r['pooled_draws_timed']} draws per group, scaled)")
        return "\n".join([
            f"{r['frames']} frames, {r['sequences']} sequences, {r['contexts']} contexts, {r['methods']} methods, "
            f"{r['detections_scored']} detections; {r['resamples']} draws x {r['groups']} groups ({r['cpu']})",
            f"  ranked once, weighted: {r['weighted_total_s']:.2f} s (ranking {r['ranking_s']:.2f} s)",
            f"  pooled per draw:       {pooled}" + (f"; x{r['speedup']}" if r["speedup"] else ""),
            f"  largest difference of a draw's mAP: {r['max_abs_difference']:.2e}",
        ])

    emit(r, args.json, text)
    return 0
