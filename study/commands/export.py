"""`hydrabench export <format>`: a dataset written in another tool's format (nuscenes, coco)."""

from __future__ import annotations

from study.cli import (
    Formatter,
    dataset_dir,
    emit,
    holdout_fraction,
    nonneg_int,
    open_fraction,
    out_dir,
    out_file,
)

NUSCENES_EPILOG = """\
Writes DIR/v1.0-hydrabench/ (the thirteen nuScenes tables and splits.json), DIR/samples/ (CAM_FRONT =
the right camera, CAM_FRONT_STEREO_LEFT, LIDAR_TOP .pcd.bin, RADAR_TOP .pcd of CFAR peaks), DIR/maps/
and DIR/hydrabench_export.json. Load it with the devkit:
  NuScenes(version="v1.0-hydrabench", dataroot="DIR")
and evaluate on a hydrabench split with DetectionEval(..., eval_set="hydrabench-test"). The split
options are those of `hydrabench train` and `train-gate` (docs/nuscenes.md).

examples:
  hydrabench export nuscenes data/small --out data/small-nuscenes
  hydrabench export nuscenes data/small --out data/small-nuscenes --gate-holdout 0.3 --json
"""


def add_parser(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=help_text, formatter_class=Formatter)
    formats = p.add_subparsers(dest="format", metavar="<format>", parser_class=type(p))
    formats.required = True
    add_nuscenes(formats)
    add_coco(formats)


def add_nuscenes(formats):
    text = "a dataset in nuScenes v1.0 format: all four sensors, 3D boxes, calibration, sequences, splits"
    p = formats.add_parser("nuscenes", help=text, description=text, epilog=NUSCENES_EPILOG, formatter_class=Formatter)
    p.add_argument("dir", type=dataset_dir, help="dataset directory")
    p.add_argument("--out", required=True, type=out_dir, help="folder to write (new or empty)")
    p.add_argument("--clear", action="store_true", help="export the clear-weather twins instead of the frames")
    p.add_argument("--train-fraction", type=open_fraction, default=0.7, help="share of each context's sequences the "
                   "detectors train on (a training run's train_fraction)")
    p.add_argument("--split-seed", type=nonneg_int, default=0, help="seed of the train/test split (a training run's split_seed)")
    p.add_argument("--gate-holdout", type=holdout_fraction, default=0.0, help="share of the train split's sequences "
                   "held out for the gates (train --gate-holdout)")
    p.add_argument("--val-fraction", type=holdout_fraction, default=0.15, help="share of the gate split's sequences "
                   "kept for validation (train-gate --val-fraction)")
    p.add_argument("--gate-seed", type=nonneg_int, default=0, help="seed of the validation carve (train-gate --seed)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(run=run_nuscenes)


def run_nuscenes(args) -> int:
    from study.experiments.nuscenes_export import export_nuscenes

    result = export_nuscenes(args.dir, args.out, clear=args.clear, train_fraction=args.train_fraction,
                             split_seed=args.split_seed, gate_holdout=args.gate_holdout,
                             val_fraction=args.val_fraction, gate_seed=args.gate_seed)
    c = result["counts"]
    emit(result, args.json, lambda r: (
        f"{r['frames']} frames -> {c['scene']} scenes, {c['sample']} samples, {c['sample_data']} sample_data, "
        f"{c['sample_annotation']} annotations of {c['instance']} instances in {r['out']} "
        f"({r['bytes'] / 1e6:.1f} MB in {r['seconds']} s); splits: "
        + ", ".join(f"{k} {v}" for k, v in r["split_scenes"].items())))
    return 0


def add_coco(formats):
    text = "one camera's FWD labels as COCO JSON (the same as `hydrabench export-coco`)"
    p = formats.add_parser("coco", help=text, description=text, formatter_class=Formatter)
    p.add_argument("dir", type=dataset_dir, help="dataset directory")
    p.add_argument("--out", required=True, type=out_file(".json"), help="COCO JSON file to write")
    p.add_argument("--camera", default="camera_right", choices=["camera_left", "camera_right"],
                   help="which camera's FWD labels")
    from study.commands.dataset import run_export

    p.set_defaults(run=run_export)
