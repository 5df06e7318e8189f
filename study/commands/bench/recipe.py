"""`hydrabench bench recipe`: training recipes judged by held-out vehicle mAP per CPU-hour (`study.bench.recipe`)."""

from __future__ import annotations

from study.bench.pipeline import machine
from study.cli import (
    Formatter,
    dataset_dir,
    emit,
    float_range,
    int_range,
    name_arg,
    nonneg_int,
    out_dir,
    out_file,
)
from study.commands.bench.common import format_bench_doc


def add_parser(what) -> None:
    rc = what.add_parser("recipe", help="training recipes and cost options judged by held-out vehicle mAP per "
                         "CPU-hour, with their curves", description=format_bench_doc("study.bench.recipe"), formatter_class=Formatter)
    rc.add_argument("data", type=dataset_dir, help="dataset to train on (the runs' gate split is the held-out set)")
    rc.add_argument("--out", required=True, type=out_dir, help="directory of the candidate runs (a second call resumes)")
    rc.add_argument("--branch", type=name_arg, default="lidar", help="the branch every candidate trains")
    rc.add_argument("--epochs", type=int_range(1, 100, "epochs"), default=3, help="epochs of every candidate")
    rc.add_argument("--candidate", action="append", default=None, metavar="NAME:FIELD=VALUE[+FIELD=VALUE]",
                    help="a candidate (repeatable): what differs from the base recipe (lr, warmup_steps, clip_grad, "
                    "hflip, lr_drop_epoch, epochs, model=KEY=VALUE); default: base, lr 0.04, hflip 0.5, bev stride 16, 64 RoIs")
    rc.add_argument("--bootstrap", type=int_range(0, 10000, "bootstrap"), default=200,
                    help="draws of whole held-out sequences for the last epoch's intervals (0: none)")
    rc.add_argument("--aim", type=float_range(0.0, 1.0, "aim", lo_open=True), default=None, metavar="MAP",
                    help="a held-out vehicle mAP to reach: where each curve reaches it, and if none does, the "
                    "budget frontier's log-linear extrapolation (candidates differing in epochs=N trace the frontier)")
    rc.add_argument("--threads", type=nonneg_int, default=0, help="torch CPU threads (0: the cores available)")
    rc.add_argument("--plot", type=out_file(".png", ".pdf", ".svg"), default=None, help="draw the curves")
    rc.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    rc.set_defaults(run=run_recipe)


def run_recipe(args) -> int:
    from sim.errors import UserError
    from study.bench.recipe import bench_recipe, parse_candidate, plot_recipe

    cands = dict(parse_candidate(c) for c in args.candidate) if args.candidate else None
    if args.candidate and len(cands) != len(args.candidate):
        raise UserError("--candidate: each name once")
    r = bench_recipe(str(args.data), args.out, args.branch, cands, epochs=args.epochs, threads=args.threads,
                     bootstrap=args.bootstrap, aim=args.aim)
    r.update(machine())
    if args.plot:
        plot_recipe(r, args.plot)
        r["plot"] = str(args.plot)

    def text(r):
        lines = [f"{r['cpu'] or 'CPU'}, {r['threads']} threads; {r['branch']} branch, {r['epochs']} epochs each; "
                 f"held out: {r['held_out']['frames']} gate-split frames; budget {r['budget_core_hours']} core-hours",
                 f"{'candidate':16s} {'core-h':>7s} {'veh. mAP':>8s} {'at budget':>9s}  per epoch"]
        for name, c in r["candidates"].items():
            last = c["curve"][-1]
            lines.append(f"{name:16s} {last['core_hours']:7.3f} {last['map_vehicles'] or 0:8.3f} "
                         f"{c['map_vehicles_at_budget']:9.3f}  " + " ".join(f"{p['map_vehicles'] or 0:.3f}" for p in c["curve"]))
        lines.append(f"chosen: {r['chosen']} ({r['rule']})")
        a = r.get("aim")
        if a and a["reached"]:
            stays = a["per_candidate_stays_from_core_hours"][a["by"]]
            lines.append(f"aim {a['map_vehicles']:g}: reached at {a['core_hours']} core-hours ({a['by']})"
                         + (f", stays reached from {stays}" if stays is not None else ", falls back below it"))
        elif a:
            guess = (f"; at the frontier's last gain of {a['gain_per_doubling']:+.3f} per doubling it would be reached "
                     f"near {a['extrapolated_core_hours']} core-hours (extrapolated)") if "extrapolated_core_hours" in a else ""
            lines.append(f"aim {a['map_vehicles']:g}: not reached (best {a['best_map_vehicles']:.3f} at "
                         f"{a['best_core_hours']} core-hours){guess}")
        return "\n".join(lines)

    emit(r, args.json, text)
    return 0
