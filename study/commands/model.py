"""`hydrabench model`: reference models (`study.engine.reference_model`): export a run, list, check."""

from __future__ import annotations

import json
from pathlib import Path

from study.cli import Formatter, emit, in_file, module_doc, name_arg, out_dir, training_run


def add_parser(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=module_doc("study.engine.reference_model"), formatter_class=Formatter)
    what = p.add_subparsers(dest="what", metavar="<what>", required=True)
    ex = what.add_parser("export", help="write a run's float16 weights, gates and manifest to a directory",
                         formatter_class=Formatter)
    ex.add_argument("run_dir", metavar="RUN", type=training_run, help="training run directory (hydrabench train --out)")
    ex.add_argument("--out", required=True, type=out_dir, help="the model directory to write (e.g. models/cpu-ref)")
    ex.add_argument("--name", type=name_arg, required=True, help="the model's name (its directory name in models/)")
    ex.add_argument("--measured", type=in_file, default=None,
                    help="JSON of what the model scored (hydrabench evaluate --json), kept in the manifest")
    ex.add_argument("--training-commit", type=name_arg, default=None, metavar="SHA",
                    help="the commit the run trained at, 7-40 hex digits (default: this checkout's HEAD); the "
                    "training command is written from the run's config.json")
    ex.add_argument("--json", action="store_true", help="print the manifest as one JSON object")
    ex.set_defaults(run=run_export)
    ls = what.add_parser("list", help="the reference models in models/, each checked against its manifest",
                         formatter_class=Formatter)
    ls.add_argument("--json", action="store_true", help="print one JSON object")
    ls.set_defaults(run=run_list)


def run_export(args) -> int:
    from sim.errors import UserError
    from study.engine.reference_model import compact_measured, export_model

    measured = None
    if args.measured:
        try:
            measured = json.loads(Path(args.measured).read_text())
        except ValueError:
            raise UserError(f"--measured {args.measured}: not JSON") from None
    man = export_model(Path(args.run_dir), Path(args.out), name=args.name,
                       measured=compact_measured(measured) if measured is not None else None,
                       training_commit=args.training_commit)
    emit(man, args.json, lambda m: (f"{args.out}: {m['name']}, {m['weights']['parameters'] / 1e6:.1f} M parameters, "
                                    f"{m['weights']['bytes'] / 2**20:.1f} MiB float16; gates: "
                                    f"{', '.join(m['gates']) or 'none'}"
                                    + (f" (left out, trained on another checkpoint: {', '.join(m['skipped_gates'])})"
                                       if m["skipped_gates"] else "")))
    return 0


def run_list(args) -> int:
    from sim.errors import UserError
    from study.engine.reference_model import MODEL_DIR, available_models, verify

    rows = []
    for n in available_models():
        try:
            m = verify(MODEL_DIR / n)
            rows.append({"name": n, "ok": True, "profile": m["profile"], "branches": m["branches"],
                         "gates": m["gates"], "bytes": m["weights"]["bytes"], "measured": m.get("measured", {})})
        except UserError as err:
            rows.append({"name": n, "ok": False, "problem": str(err)})
    emit({"models": rows, "dir": str(MODEL_DIR)}, args.json, lambda r: "\n".join(
        [f"{x['name']}: " + (f"{x['profile']} profile, branches {', '.join(x['branches'])}, gates "
                             f"{', '.join(x['gates']) or 'none'}, {x['bytes'] / 2**20:.1f} MiB" if x["ok"] else x["problem"])
         for x in r["models"]] or [f"no reference model in {r['dir']}"]))
    return 0
