"""`hydrabench compare`: the command line of `study.experiments.compare` (selective against fixed fusion) and its
figure."""

from __future__ import annotations

from pathlib import Path

from study.cli import (
    FUSION_HELP,
    Formatter,
    bootstrap_int,
    count_int,
    dataset_dir,
    emit,
    fusion_arg,
    module_doc,
    name_list,
    out_file,
    pos_int,
    predictions_dir,
    training_run,
)
from study.commands.device import add_device_args

EPILOG = """\
examples:
  hydrabench compare cpu-ref demo/test                  (the committed reference model on a fresh dataset)
  hydrabench compare runs/all data/train1600 --k 3 --fusion wbf --bootstrap 1000 --json
  hydrabench compare cpu-ref demo/test --plot demo/compare.png
"""


def add_parser(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=module_doc("study.experiments.compare"), epilog=EPILOG,
                       formatter_class=Formatter)
    p.add_argument("run_dir", metavar="RUN", type=training_run,
                   help="training run directory, or a reference model (models/: e.g. cpu-ref)")
    p.add_argument("data", type=dataset_dir, help="dataset directory")
    p.add_argument("--k", type=pos_int, default=2, help="branches each gate keeps per frame")
    p.add_argument("--fusion", type=fusion_arg, default="soft-nms", help=f"how chosen branches are fused: {FUSION_HELP}")
    p.add_argument("--gates", type=name_list, default="knowledge,deep,attention,optimal",
                   help="HydraFusion gates to compare (deep and attention only where trained)")
    p.add_argument("--split", default="auto", choices=["auto", "test", "all"],
                   help="auto: the run's test split on its own dataset, every frame on another")
    p.add_argument("--bootstrap", type=bootstrap_int, default=500, metavar="N",
                   help="draws of whole sequences for the 95%% intervals (0: none)")
    p.add_argument("--twins", action="store_true",
                   help="also run every method on the clear-weather twins (a dataset generated with --twins): per "
                   "condition and severity the vehicle mAP kept, RA = degraded / clear with its interval, the "
                   "severity's physical value, and per method mRA, mRR and mCE against late fusion")
    p.add_argument("--coverage-deals", type=count_int, default=0, metavar="N",
                   help="also check the intervals on this test set: deal it N times into disjoint sets of at least "
                        "6 sequences per context (up to 8 sets) and count how often each set's 95 %% interval of "
                        "minus late fusion holds the other sets' estimate (about 0.93 for exact intervals); "
                        "0 (default): no check")
    p.add_argument("--interval", default="sequence", choices=["sequence", "stratified", "rescaled"],
                   help="how the bootstrap draws test sequences: sequence (from all of them), stratified (each "
                        "context's n of its n, as a test set is built), rescaled (n - 1 of its n, Rao and Wu 1988: "
                        "the design's variance even at few sequences per context)")
    p.add_argument("--coverage-design", default=None, metavar="D[,D...]",
                   help="which bootstraps the coverage check runs on each set, on the same deals (sequence, "
                        "stratified, rescaled; comma-separated for several) [--interval's]")
    p.add_argument("--predictions", type=predictions_dir, default=None, metavar="PRED",
                   help="score these stored predictions of RUN on DATA (hydrabench predict) and run no network")
    p.add_argument("--batch-size", type=pos_int, default=4, help="frames per forward pass")
    p.add_argument("--plot", type=out_file(".png", ".pdf", ".svg"), default=None,
                   help="also draw each method's mAP minus late fusion with its interval")
    add_device_args(p, purpose="eval")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(run=run)


def run(args) -> int:
    from sim.errors import UserError
    from study.engine.device import resolve_device
    from study.experiments.compare import compare, format_table, gate_names

    gates = gate_names(args.gates)
    from fusion.intervals import DESIGNS

    designs = (args.interval if args.coverage_design is None else args.coverage_design).split(",")
    bad = [d for d in designs if d not in DESIGNS]
    if bad:
        raise UserError(f"--coverage-design: unknown design {bad[0]!r} (choose from: {', '.join(DESIGNS)}, "
                        "comma-separated)")
    r = compare(Path(args.run_dir), Path(args.data), gates=gates, k=args.k, fusion=args.fusion, split=args.split,
                resamples=args.bootstrap, batch_size=args.batch_size, setup=resolve_device(args, purpose="eval"),
                twins=args.twins, coverage_deals=args.coverage_deals,
                coverage_designs=designs, interval=args.interval, need_intervals="--plot" if args.plot else None,
                predictions=args.predictions)
    if args.plot:
        from study.experiments.compare import plot_compare

        plot_compare(r, args.plot)
        r["plot"] = str(args.plot)
        if args.twins:
            from study.experiments.compare import plot_robustness

            ra = Path(args.plot).with_name(Path(args.plot).stem + "_ra" + Path(args.plot).suffix)
            plot_robustness(r, ra)
            r["plot_ra"] = str(ra)
    emit(r, args.json, format_table)
    return 0
