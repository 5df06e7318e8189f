"""`hydrabench score`: detections and selections made outside hydrabench, scored as `compare` scores the
own networks (`study.external`)."""

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
"""


def named_in_file(text: str) -> str:
    """An argparse type: `[NAME=]FILE` whose FILE exists and is readable (`in_file`'s check)."""
    from study.external import named_file

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
    p = sub.add_parser(name, help=help_text, description=module_doc("study.external"), epilog=EPILOG,
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
    from study.external import load_external, named_file, read_selection, score_external

    reader = DatasetReader(Path(args.data))
    ext, index = load_external(reader, args.split, nuscenes=args.nuscenes, coco=args.coco, export=args.export,
                               missing=args.missing)
    selections = {}
    for spec in args.selection:
        name, path = named_file(spec)
        selections[name or path.stem] = read_selection(path, ext, index)
    r = score_external(reader, ext, selections=selections, fusion=args.fusion, resamples=args.bootstrap,
                       protocol=args.protocol)
    r["data"], r["split"] = str(args.data), args.split

    def text(r):
        lines = [f"{r['frames']} frames, classes {r['classes']}, {r['protocol']} protocol, fusion {r['fusion']}"]
        for name, m in r["methods"].items():
            iv = m.get("ci95")
            ci = f" [{iv[0]:.3f}, {iv[1]:.3f}]" if iv else ""
            d = m.get("minus_late")
            dl = f"  minus late {d['value']:+.3f} ({d['verdict']})" if d and d["value"] is not None else ""
            lines.append(f"  {name:28s} mAP {m['map'] if m['map'] is not None else 'n/a'}{ci}{dl}")
        return "\n".join(lines)

    emit(r, args.json, text)
    return 0
