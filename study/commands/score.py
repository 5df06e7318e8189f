"""`hydrabench score`: detections, selections and gates made outside hydrabench, scored as `compare`
scores the own networks (`study.experiments.external`, `study.experiments.gate_protocol`), with the nuScenes devkit's own
metrics beside VOC mAP@0.5 on request (`study.experiments.nuscenes_metrics`)."""

from __future__ import annotations

from pathlib import Path

from study.cli import (
    FUSION_HELP,
    Formatter,
    bootstrap_int,
    dataset_dir,
    emit,
    fusion_arg,
    in_file,
    module_doc,
    name_arg,
)

EPILOG = """\
examples:
  hydrabench export nuscenes demo/test --out demo/nuscenes
  hydrabench score demo/test --export demo/nuscenes --nuscenes lidar=my_lidar.json --nuscenes radar=my_radar.json
  hydrabench score demo/test --coco camera=my_coco_results.json --selection my_gate.json --json
  hydrabench score demo/test --export demo/nuscenes --nuscenes lidar=l.json --nuscenes radar=r.json \
      --gate mygates.weather:pick --gate ranked=mygates.weather:Ranker --k 1 --nuscenes-metrics

gates (docs/nuscenes.md, "Score your own gate"): --gate [NAME=]package.module:attr imports attr
(from sys.path or the current directory; a class is built once without arguments); --gate [NAME=]ENTRY
loads the entry point ENTRY of the group hydrabench.gates. The gate is called once per frame with a
study.experiments.gate_protocol.GateFrame (road type, weather and light readings, clock, calibration, every
branch's detections in the right camera; never labels, context label or severity) and returns a list
of branch names, or a dict branch -> score (higher = better) of which the --k highest are fused. It is
scored as a selection file is, as method gate:NAME.
"""


def named_in_file(text: str) -> str:
    """An argparse type: `[NAME=]FILE` whose FILE exists and is readable (`in_file`'s check)."""
    from study.experiments.external import named_file

    name, path = named_file(text)
    in_file(str(path))
    return text


named_in_file.kind = "named_in_file"  # the fuzz suite tries every kind: this one as a command's own type


def export_dir(text: str) -> str:
    """An argparse type: a nuScenes export made by `hydrabench export nuscenes` (its v1.0 tables)."""
    import argparse

    from sensors.export.nuscenes import VERSION

    in_dir = Path(text)
    if not str(text).strip():
        raise argparse.ArgumentTypeError("expected a path, got an empty string")
    if not (in_dir / VERSION / "sample.json").is_file():
        raise argparse.ArgumentTypeError(f"{text} is not a nuScenes export ({VERSION}/sample.json missing; make one "
                                         "with hydrabench export nuscenes)")
    return str(in_dir)


export_dir.kind = "nuscenes_export"


def add_parser(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=module_doc("study.experiments.external"), epilog=EPILOG,
                       formatter_class=Formatter)
    p.add_argument("data", type=dataset_dir, help="dataset directory")
    p.add_argument("--export", type=export_dir, default=None, metavar="DIR",
                   help="the nuScenes export of DATA (hydrabench export nuscenes) the sample tokens refer to")
    p.add_argument("--nuscenes", action="append", type=named_in_file, default=[], metavar="[NAME=]FILE",
                   help="nuScenes detection-results JSON of one branch (repeat for each; NAME: the branch, else "
                        "named by its meta's sensors)")
    p.add_argument("--coco", action="append", type=named_in_file, default=[], metavar="[NAME=]FILE",
                   help="COCO results JSON of a camera-only 2D detector on the right camera (NAME default: camera)")
    p.add_argument("--selection", action="append", type=named_in_file, default=[], metavar="[NAME=]FILE",
                   help="per-frame selection (JSON: frame index or sample token -> [branch, ...]), scored as a gate")
    p.add_argument("--gate", action="append", default=[], metavar="[NAME=]MODULE:ATTR|ENTRY",
                   help="a gate from outside (docs/nuscenes.md): package.module:attr, or an entry point of the group "
                        "hydrabench.gates; scored as a selection file is (repeat for each)")
    p.add_argument("--k", default=None, metavar="K",
                   help="branches a score-returning gate keeps per frame: 1..number of branches, or all (default: 2, "
                        "as compare's built-in gates, at most the number of branches)")
    p.add_argument("--nuscenes-metrics", action="store_true",
                   help="also the nuScenes devkit's own detection metrics (mAP by centre distance, mATE, mASE, mAOE, "
                        "mAVE, mAAE, NDS; means over the classes present) of each --nuscenes file, overall, per "
                        "context and per severity")
    p.add_argument("--split", type=name_arg, default="all", help="all, or a split of the export's splits.json")
    p.add_argument("--missing", default="refuse", choices=["refuse", "empty"],
                   help="a frame a nuScenes file leaves out: refuse the file, or score it as a frame without "
                        "detections (counted in the result)")
    p.add_argument("--fusion", default="soft-nms", type=fusion_arg, help=f"how branches are fused: {FUSION_HELP}")
    p.add_argument("--protocol", default="reference", choices=["reference", "visible"],
                   help="what counts as an object to find (fusion.protocol)")
    p.add_argument("--bootstrap", type=bootstrap_int, default=500, metavar="N",
                   help="draws of whole sequences for the 95%% intervals (0: none)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(run=run)


def run(args) -> int:
    from sensors.dataset import DatasetReader
    from sim.errors import UserError
    from study.experiments.external import load_external, named_file, read_selection, score_external
    from study.experiments.gate_protocol import gate_k, gate_selection, load_gate

    if args.k is not None and not args.gate:
        raise UserError("--k is for --gate (the branches a score-returning gate keeps)")
    if args.nuscenes_metrics and not args.nuscenes:
        raise UserError("--nuscenes-metrics: the devkit scores 3D boxes: give nuScenes results (--nuscenes); COCO "
                        "results are 2D")
    loaded = [load_gate(spec) for spec in args.gate]  # a gate that does not load fails before any file is read
    names = [name for name, _ in loaded]
    if len(set(names)) < len(names):
        twice = next(n for n in names if names.count(n) > 1)
        raise UserError(f"--gate: two gates named {twice!r} (name them: --gate NAME=...)")
    reader = DatasetReader(Path(args.data))
    ext, index = load_external(reader, args.split, nuscenes=args.nuscenes, coco=args.coco, export=args.export,
                               missing=args.missing)
    k = gate_k(_parse_k(args.k, len(ext.branches)), len(ext.branches), args.k is not None)
    selections = {}
    for spec in args.selection:
        name, path = named_file(spec)
        selections[name or path.stem] = read_selection(path, ext, index)
    gates, gate_info = {}, {}
    for spec, (name, gate) in zip(args.gate, loaded, strict=True):
        gates[name] = gate_selection(name, gate, ext, index, k)
        gate_info[name] = {"spec": spec, "k_if_scores": k}
    r = score_external(reader, ext, selections=selections, gates=gates, fusion=args.fusion,
                       resamples=args.bootstrap, protocol=args.protocol)
    r["data"], r["split"] = str(args.data), args.split
    if gate_info:
        r["gates"] = gate_info
    if args.nuscenes_metrics:
        from study.experiments.nuscenes_metrics import describe, score_nuscenes

        for branch, metrics in score_nuscenes(ext, index, args.export, args.split).items():
            r["methods"][f"single:{branch}"]["nuscenes"] = metrics
        r["nuscenes_metrics"] = describe()

    def text(r):
        lines = [f"{r['frames']} frames, classes {r['classes']}, {r['protocol']} protocol, fusion {r['fusion']}"]
        for name, m in r["methods"].items():
            iv = m.get("ci95")
            ci = f" [{iv[0]:.3f}, {iv[1]:.3f}]" if iv else ""
            d = m.get("minus_late")
            dl = f"  minus late {d['value']:+.3f} ({d['verdict']})" if d and d["value"] is not None else ""
            energy = f"  sensors {m['sensor_energy_j']:.2f} J/frame" if m.get("sensor_energy_j") is not None else ""
            lines.append(f"  {name:28s} mAP {m['map'] if m['map'] is not None else 'n/a'}{ci}{dl}{energy}")
        ns = {name: m["nuscenes"] for name, m in r["methods"].items() if "nuscenes" in m}
        if ns:
            lines.append(f"nuScenes devkit ({r['nuscenes_metrics']['config']}), means over the classes present in "
                         "its ground truth; devkit: its own mAP and NDS over ten classes")
            lines.extend(_nuscenes_lines(ns))
        return "\n".join(lines)

    emit(r, args.json, text)
    return 0


def _parse_k(text, n_branches: int):
    from study.engine.gate_tables import parse_k

    return None if text is None else parse_k(text, n_branches)


def _nuscenes_lines(ns: dict) -> list[str]:
    from study.numbers import number_text

    def row(label: str, s: dict) -> str:
        e = s["tp_errors"]
        errs = " ".join(f"{k} {number_text(v)}" for k, v in e.items())
        return (f"  {label:28s} mAP {number_text(s['map'])}  {errs}  NDS {number_text(s['nds'])}  "
                f"(devkit mAP {number_text(s['devkit']['mean_ap'])}, NDS {number_text(s['devkit']['nd_score'])}; "
                f"classes {', '.join(s['classes']) or 'none'})")

    lines = []
    for name, m in ns.items():
        lines.append(row(name, m["overall"]))
        for group in ("per_context", "per_severity"):
            for key, s in m[group].items():
                label = f"{key}" if group == "per_context" else f"severity {key}"
                lines.append(row(f"  {label}", s))
    return lines
