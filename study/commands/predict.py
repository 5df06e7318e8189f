"""`hydrabench predict`: the command line of `study.engine.predictions` (one pass of a model over a dataset,
kept on disk)."""

from __future__ import annotations

from pathlib import Path

from study.cli import Formatter, cache_dir, dataset_dir, emit, module_doc, name_list, pos_int, training_run
from study.commands.device import add_device_args

EPILOG = """\
examples:
  hydrabench predict cpu-frontier demo/test --out demo/predictions
  hydrabench compare cpu-frontier demo/test --predictions demo/predictions   (scores them, no network)
"""


def add_parser(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=module_doc("study.engine.predictions"), epilog=EPILOG,
                       formatter_class=Formatter)
    p.add_argument("run_dir", metavar="MODEL", type=training_run,
                   help="training run directory, or a reference model (models/: e.g. cpu-frontier)")
    p.add_argument("data", type=dataset_dir, help="dataset directory")
    p.add_argument("--out", type=cache_dir, default=None, metavar="PRED",
                   help="where to keep the predictions (reused when model, data and code are unchanged) "
                        "[MODEL's cache: RUN/predictions/<key>]")
    p.add_argument("--gates", type=name_list, default="knowledge,deep,attention,optimal",
                   help="gates whose outputs to keep (learned ones where trained)")
    p.add_argument("--split", default="auto", choices=["auto", "test", "all"],
                   help="auto: the run's test split on its own dataset, every frame on another")
    p.add_argument("--batch-size", type=pos_int, default=4, help="frames per forward pass")
    add_device_args(p, purpose="eval")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(run=run)


def run(args) -> int:
    from study.engine.device import resolve_device
    from study.engine.predictions import predict
    from study.experiments.compare import gate_names

    gates = gate_names(args.gates)
    pred = predict(Path(args.run_dir), Path(args.data), args.out, gates=gates, split=args.split,
                   batch_size=args.batch_size, setup=resolve_device(args, purpose="eval"))
    m = pred.manifest
    r = {"predictions": str(pred.root), "frames": m["frames"], "branches": m["branches"], "gates": m["gates"],
         "bytes": m["bytes"], "mb_per_1000_frames": m["mb_per_1000_frames"], "identity": m["identity"]}

    def text(r):
        return (f"{r['frames']} frames, branches {', '.join(r['branches'])}, gates {', '.join(r['gates']) or 'none'}: "
                f"{r['predictions']} ({r['bytes'] / 1e6:.1f} MB, {r['mb_per_1000_frames']} MB per 1,000 frames)")

    emit(r, args.json, text)
    return 0
