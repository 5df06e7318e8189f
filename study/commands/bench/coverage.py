"""`hydrabench bench coverage`: how often per-context bootstrap intervals of mAP hold the population value,
on a synthetic detection problem with known AP (`study.bench.coverage`)."""

from __future__ import annotations

from study.bench.pipeline import machine
from study.cli import Formatter, emit, int_list, int_range, nonneg_int, out_file
from study.commands.bench.common import format_bench_doc


def add_parser(what) -> None:
    c = what.add_parser("coverage", help="coverage of per-context mAP intervals (percentile, basic, BCa, studentized, "
                        "jackknife, rescaled) on a synthetic problem with known AP", description=format_bench_doc("study.bench.coverage"),
                        formatter_class=Formatter)
    c.add_argument("--sequences", type=int_list(2, 400, "sequences"), default="6,12,24",
                   help="comma-separated numbers of sequences per context (the study's test sets hold 48, "
                   "the coverage check's 8 disjoint sets 6)")
    c.add_argument("--trials", type=int_range(2, 100_000, "trials"), default=200,
                   help="independent samples per number of sequences (coverage's standard error ~0.015 at 200)")
    c.add_argument("--resamples", type=int_range(10, 100_000, "resamples"), default=400,
                   help="bootstrap draws of whole sequences per sample")
    c.add_argument("--frames-per-sequence", type=int_range(1, 100, "frames per sequence"), default=3,
                   help="frames of a sequence (the study's test sets: 3)")
    c.add_argument("--classes", choices=("vehicles", "all"), default="vehicles",
                   help="the synthetic classes: the four vehicles (car, van, truck, bus: the study's vehicle mAP) or "
                   "all eight, with rare, hard two-wheelers and groups (the classes of the study's per-context intervals)")
    c.add_argument("--no-studentized", action="store_true",
                   help="skip the studentized interval (its jackknife inside every draw costs most of the time)")
    c.add_argument("--seed", type=nonneg_int, default=0, help="seed of the samples and the draws")
    c.add_argument("--out", type=out_file(".json"), default=None, metavar="FILE",
                   help="also write the result there (e.g. results/bench_coverage_<date>.json)")
    c.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    c.set_defaults(run=run_coverage)


def run_coverage(args) -> int:
    from study.bench.coverage import bench_coverage
    from study.bench.scale import cpu_model

    r = bench_coverage(args.sequences, args.trials, args.resamples, args.seed,
                       frames_per_sequence=args.frames_per_sequence, studentized=not args.no_studentized,
                       classes=args.classes,
                       progress=not args.json)
    r = {**r, "cpu": cpu_model(), **machine()}
    if args.out:
        from study.outputs import write_json_atomic

        write_json_atomic(args.out, r)

    def text(r):
        lines = [f"classes: {r['model']['class_set']}; {r['trials']} samples per row, {r['resamples']} draws each, {r['frames_per_sequence']} frames per "
                 f"sequence; {r['seconds']} s ({r['cpu']})"]
        for q, truth in r["truth"].items():
            lines.append(f"{q}: population value {truth:.4f}")
            methods = list(next(iter(r["by_sequences"].values()))["quantities"][q]["coverage"])
            lines.append(f"  {'n':>3s} {'bias':>7s} {'boot.bias':>9s}  " + " ".join(f"{m:>19s}" for m in methods))
            for n, rec in r["by_sequences"].items():
                qq = rec["quantities"][q]
                cells = " ".join(f"{c['coverage']:.3f}±{c['se']:.3f} @{c.get('median_position') or 0:.2f}"
                                 .rjust(19) for c in qq["coverage"].values())
                dg = qq["diagnostics"]
                lines.append(f"  {n:>3s} {dg['estimator_bias']:+7.4f} {dg['bootstrap_bias']:+9.4f}  {cells}")
        lines.append("cells: coverage ± binomial s.e. @ median position of the estimate in its interval")
        lines.append("best at the fewest sequences: " + ", ".join(f"{q}: {m}" for q, m in r["best_at_fewest"].items()))
        if args.out:
            lines.append(f"wrote {args.out}")
        return "\n".join(lines)

    emit(r, args.json, text)
    return 0
