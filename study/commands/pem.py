"""`hydrabench pem`: perception error models fitted on a model's predictions (`study.experiments.pem`):
fit, draw predictions, check against the network on held-out frames."""

from __future__ import annotations

from pathlib import Path

from sim.errors import UserError
from study.cli import (
    Formatter,
    bootstrap_int,
    cache_dir,
    count_int,
    dataset_dir,
    emit,
    in_file,
    module_doc,
    out_dir,
    out_file,
    pos_float,
    pos_int,
    predictions_dir,
    training_run,
)

EPILOG = """\
examples:
  hydrabench pem fit cpu-frontier data/fit7 --out pem.json          (fit on a dataset of its own seed)
  hydrabench pem predict pem.json demo/test --out pred_pem --seed 0
  hydrabench compare cpu-frontier demo/test --predictions pred_pem --gates knowledge
  hydrabench pem check cpu-frontier demo/test --network PRED_NET --pem pred_pem --plot pem_check.png
  hydrabench pem predict pem.json demo/test --out pred_pem_s4 --strength 4   (a stronger detector)
  hydrabench pem sweep cpu-frontier pem.json demo/test --gate-set data/gate6 --work sweep --plot sweep.png
  hydrabench pem known-answer pem.json demo/test --gate-set data/gate6 --work ka   (do the gates find a known rule?)
"""


def add_parser(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=module_doc("study.experiments.pem"), epilog=EPILOG,
                       formatter_class=Formatter)
    what = p.add_subparsers(dest="what", metavar="<what>", required=True)
    f = what.add_parser("fit", help="fit one PEM per branch on a model's predictions on a fitting dataset",
                        description=module_doc("fusion.pem"), formatter_class=Formatter)
    f.add_argument("run_dir", metavar="MODEL", type=training_run,
                   help="training run directory, or a reference model (models/: e.g. cpu-frontier)")
    f.add_argument("data", metavar="FITDATA", type=dataset_dir,
                   help="the dataset to fit on (not the one you test on: generate it with another --seed)")
    f.add_argument("--out", required=True, type=out_file(".json"), metavar="PEM.json", help="the PEM file to write")
    f.add_argument("--predictions", type=predictions_dir, default=None, metavar="PRED",
                   help="stored predictions of MODEL on FITDATA (hydrabench predict) [made, or read from MODEL's cache]")
    f.add_argument("--batch-size", type=pos_int, default=4, help="frames per forward pass (when predicting)")
    f.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    f.set_defaults(run=run_fit)
    d = what.add_parser("predict", help="draw every branch's detections from a PEM on a dataset, as predictions "
                        "`compare --predictions` scores (knowledge gate only)", formatter_class=Formatter)
    d.add_argument("pem", metavar="PEM.json", type=in_file, help="a PEM file (hydrabench pem fit)")
    d.add_argument("data", metavar="DATA", type=dataset_dir, help="dataset directory (not the one the PEM was fitted on)")
    d.add_argument("--out", required=True, type=out_dir, metavar="PRED", help="the predictions directory to write (new or empty, "
                   "or predictions to replace)")
    d.add_argument("--strength", type=pos_float, default=1.0,
                   help="1: the fitted detector; s: every object's odds of detection times s, box error / s, "
                        "false-alarm rate / s")
    d.add_argument("--seed", type=count_int, default=0, help="the draws' seed (same seed, same detections)")
    d.add_argument("--split", default="auto", choices=["auto", "test", "all"],
                   help="auto: the run's test split on its own dataset, every frame on another")
    d.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    d.set_defaults(run=run_predict)
    c = what.add_parser("check", help="PEM against network on held-out frames: mAP per branch, late fusion and "
                        "context inside the network's intervals; recall by range and score calibration",
                        formatter_class=Formatter)
    c.add_argument("run_dir", metavar="MODEL", type=training_run, help="the model the PEM was fitted on")
    c.add_argument("data", metavar="DATA", type=dataset_dir, help="the held-out dataset")
    c.add_argument("--network", required=True, type=predictions_dir, metavar="PRED",
                   help="the network's predictions on DATA (hydrabench predict)")
    c.add_argument("--pem", required=True, type=predictions_dir, action="append", metavar="PRED",
                   help="the PEM's predictions on DATA: one draw, or several (repeat --pem; other --seed), then also "
                        "their mean (pem_mean) is checked; the figure shows the first")
    c.add_argument("--bootstrap", type=bootstrap_int, default=500, metavar="N", help="sequence draws for the intervals")
    c.add_argument("--plot", type=out_file(".png", ".pdf", ".svg"), default=None, help="draw the curves here")
    c.add_argument("--out", type=out_file(".json"), default=None, help="also write the result as JSON here")
    c.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    c.set_defaults(run=run_check)
    w = what.add_parser("sweep", help="the verdict over detector strength: all_branches minus late, the knowledge "
                        "gate, the per-context constant and the physical gate minus all_branches, room for context and "
                        "the a-posteriori oracle, with intervals, per strength",
                        description=module_doc("study.experiments.pem_sweep"), formatter_class=Formatter)
    w.add_argument("run_dir", metavar="MODEL", type=training_run, help="the model the PEM was fitted on")
    w.add_argument("pem", metavar="PEM.json", type=in_file, help="a PEM file (hydrabench pem fit)")
    w.add_argument("data", metavar="DATA", type=dataset_dir, help="the held-out dataset to draw and score on")
    w.add_argument("--strengths", default="0.5,1,2,4", type=_strengths, metavar="S[,S...]",
                   help="the strengths, comma-separated (1: the fitted detector)")
    w.add_argument("--gate-set", type=dataset_dir, default=None, metavar="GATEDATA",
                   help="a gate set (another dataset, two sequences or more per context): the per-context constant "
                        "and the physical gate are chosen on it; without it they are not measured")
    w.add_argument("--work", required=True, type=cache_dir, metavar="DIR",
                   help="where each strength's predictions are written (DIR/strength-<s>; the gate set's "
                        "DIR/gate-strength-<s>)")
    w.add_argument("--seed", type=count_int, default=0, help="the test set's draws (the gate set's: seed + 1)")
    w.add_argument("--bootstrap", type=bootstrap_int, default=500, metavar="N", help="sequence draws for the intervals")
    w.add_argument("--plot", type=out_file(".png", ".pdf", ".svg"), default=None,
                   help="draw the curves over strength here (one panel per comparison, 95 %% interval bands)")
    w.add_argument("--out", type=out_file(".json"), default=None, help="also write the result as JSON here")
    w.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    w.set_defaults(run=run_sweep)
    k = what.add_parser("known-answer", help="a world where the best branch per context is known by construction: "
                        "do the gates that read context find it?", description=module_doc("study.experiments.known_answer"),
                        formatter_class=Formatter)
    k.add_argument("pem", metavar="PEM.json", type=in_file, help="a PEM file (hydrabench pem fit)")
    k.add_argument("data", metavar="TESTDATA", type=dataset_dir, help="the test set the gates are scored on")
    k.add_argument("--gate-set", required=True, type=dataset_dir, metavar="GATEDATA",
                   help="the gate set: the learners fit and choose on it (two sequences or more per context)")
    k.add_argument("--work", required=True, type=cache_dir, metavar="DIR",
                   help="where the world's predictions are written (DIR/gate, DIR/test)")
    k.add_argument("--strong", type=pos_float, default=8.0, help="the answer branch's strength in its context")
    k.add_argument("--weak", type=pos_float, default=0.125, help="every other branch's strength (below --strong)")
    k.add_argument("--seed", type=count_int, default=0, help="the gate set's draws (the test set's: seed + 1)")
    k.add_argument("--bootstrap", type=bootstrap_int, default=500, metavar="N", help="sequence draws for the intervals")
    k.add_argument("--out", type=out_file(".json"), default=None, help="also write the result as JSON here")
    k.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    k.set_defaults(run=run_known_answer)


def _strengths(text: str) -> list[float]:
    out = []
    for part in str(text).split(","):
        out.append(pos_float(part))
    return out


_strengths.kind = "strengths"


def _write_out(args, r: dict) -> None:
    """`--out`: the result as JSON, written atomically (its folder made)."""
    if args.out:
        from study.outputs import write_json_atomic

        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        write_json_atomic(args.out, r)


def run_fit(args) -> int:
    from study.engine.device import resolve_device
    from study.experiments.pem import fit

    r = fit(Path(args.run_dir), Path(args.data), Path(args.out), predictions=args.predictions,
            batch_size=args.batch_size, setup=None if args.predictions else resolve_device(purpose="eval"))
    emit(r, args.json, lambda r: "\n".join(
        [f"{r['pem']}: fitted on {r['frames']} frames of {r['fit_data']} in {r['seconds']} s"]
        + [f"  {b}: {c['found']}/{c['objects']} objects found, {c['false_alarms']} false alarms"
           for b, c in r["branches"].items()]))
    return 0


def run_predict(args) -> int:
    from study.experiments.pem import predict_pem

    out = Path(args.out)  # checked before the PEM file is read: what the user wrote last is often the slip
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not (out / "manifest.json").is_file())):
        raise UserError(f"--out {out}: exists and is not a predictions directory (choose a new or empty one)")
    r = predict_pem(Path(args.pem), Path(args.data), out, strength=args.strength, seed=args.seed,
                    split=args.split)
    emit(r, args.json, lambda r: (f"{r['predictions']}: {r['frames']} frames ({r['split']}) drawn at strength "
                                  f"{r['strength']:g}, seed {r['seed']}, in {r['seconds']} s"))
    return 0


def run_check(args) -> int:
    from study.experiments.pem import check, format_check, plot_check

    pems = {("pem" if i == 0 else f"pem{i + 1}"): Path(p) for i, p in enumerate(args.pem)}
    r = check(Path(args.run_dir), Path(args.data), Path(args.network), pems, resamples=args.bootstrap)
    if args.plot:
        plot_check(r, args.plot)
        r["plot"] = str(args.plot)
    _write_out(args, r)
    emit(r, args.json, format_check)
    return 0


def run_sweep(args) -> int:
    from study.experiments.pem_sweep import format_sweep, plot_sweep, sweep

    if args.plot and not args.bootstrap:
        raise UserError("--plot draws the intervals: give --bootstrap N > 0")
    r = sweep(Path(args.run_dir), Path(args.data), Path(args.pem), args.strengths, Path(args.work),
              gate_set=None if args.gate_set is None else Path(args.gate_set), seed=args.seed, resamples=args.bootstrap)
    if args.plot:
        plot_sweep(r, args.plot)
        r["plot"] = str(args.plot)
    _write_out(args, r)
    emit(r, args.json, format_sweep)
    return 0


def run_known_answer(args) -> int:
    from study.experiments.known_answer import format_result, run

    if not args.strong > args.weak:
        raise UserError(f"--strong ({args.strong:g}) must exceed --weak ({args.weak:g})")
    r = run(Path(args.pem), Path(args.gate_set), Path(args.data), Path(args.work), strong=args.strong,
            weak=args.weak, seed=args.seed, resamples=args.bootstrap)
    _write_out(args, r)
    emit(r, args.json, format_result)
    return 0
