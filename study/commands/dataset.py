"""Dataset commands: generate, verify, export-coco, show."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from sim.errors import UserError
from study.cli import (
    IMAGE_SUFFIXES,
    Formatter,
    dataset_dir,
    dataset_path,
    emit,
    in_file,
    int_list,
    name_arg,
    name_list,
    nonneg_int,
    out_dir,
    out_file,
    pos_float,
    pos_int,
    workers_int,
)

GEN_EPILOG = """\
Writes a sharded dataset (one sequence per shard) to --out: manifest.json plus shard directories of
.npy arrays and frames.json (format in the README). Shards are written under a temporary name and
renamed when complete; if the run is interrupted (even kill -9), run the same command again and it
completes the dataset, byte-identical to an uninterrupted run, whatever --workers or --backend is.

examples:
  hydrabench generate --out data/small --frames-per-context 20 --workers 2
  hydrabench generate --out data/fog --contexts fog,city+night+rain --severities 4,5 --twins
  hydrabench generate --out data/small --backend ray --workers 2                (a local Ray instance)
  ray start --head --port 6379 && hydrabench generate --out data/big --backend ray --address 127.0.0.1:6379
"""


def ray_address(text: str) -> str:
    """An argparse type: a Ray cluster address, HOST:PORT, ray://HOST:PORT or auto."""
    import argparse
    import re

    t = str(text).strip()
    if not re.fullmatch(r"auto|(ray://)?[A-Za-z0-9_.\-]+:\d{1,5}", t):
        raise argparse.ArgumentTypeError(f"expected HOST:PORT (as printed by `ray start --head`), ray://HOST:PORT "
                                         f"or auto, got {text!r}")
    return t


ray_address.kind = "name"


def add_generate(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=help_text, epilog=GEN_EPILOG, formatter_class=Formatter)
    p.add_argument("--out", required=True, type=out_dir,
                   help="dataset directory (created; an interrupted one is completed; a folder of other files is refused)")
    p.add_argument("--contexts", type=name_list, default=None,
                   help="'all' or comma-separated contexts/combinations, each once [all]")
    p.add_argument("--frames-per-context", type=pos_int, default=None,
                   help="frames per context, at most 1000000 in a dataset [20]")
    p.add_argument("--seed", type=nonneg_int, default=None, help="root seed [0]")
    p.add_argument("--workers", type=workers_int, default=1, help="parallel worker processes (--backend ray without "
                   "--address: the CPUs of the local Ray instance)")
    p.add_argument("--backend", default="local", choices=["local", "ray"],
                   help="local: this process or a local process pool; ray: one Ray task per shard (same bytes)")
    p.add_argument("--address", type=ray_address, default=None, help="with --backend ray: the cluster to join (HOST:PORT printed by "
                   "`ray start --head`, or auto); default: start a local Ray instance for this command")
    p.add_argument("--profile", type=name_arg, default=None, help="sensor profile: cpu or paper [cpu]")
    p.add_argument("--sequence-length", type=pos_int, default=None,
                   help="frames per sequence/shard, at most 1000 [10]")
    p.add_argument("--frame-rate", type=pos_float, default=None,
                   help="frames per second within a sequence; a sequence lasts at most 3600 s [2]")
    p.add_argument("--severities", type=int_list(0, 5, "severities"), default=None,
                   help="severity levels drawn per sequence for conditions [1,2,3,4,5]")
    p.add_argument("--transitions", type=name_list, default=None,
                   help="weather transitions drawn per sequence: none, onset, clearing, bank [none]")
    p.add_argument("--twins", action="store_true", default=None, help="also write clear-weather twins of every frame")
    p.add_argument("--no-degrade", dest="degrade", action="store_false", default=None,
                   help="skip the weather degradation models (clean sensors, weather only lights the scene)")
    p.add_argument("--lidar-fog", default=None, choices=["ours", "hahner"],
                   help="lidar fog model: ours, or hahner (Hahner et al. ICCV 2021 as published) [ours]")
    p.add_argument("--config", type=in_file, default=None, help="YAML file with GenerateConfig fields (flags override it)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(run=run_generate)


def build_config(args):
    from sensors.generate import GenerateConfig
    from sim.config import load_yaml, to_dict
    from sim.scenario import CONTEXT_NAMES

    base = to_dict(load_yaml(GenerateConfig, args.config)) if args.config else to_dict(GenerateConfig())
    if args.contexts is not None:
        base["contexts"] = list(CONTEXT_NAMES) if args.contexts == ("all",) else list(args.contexts)
    for flag, key in (("frames_per_context", "frames_per_context"), ("seed", "seed"), ("profile", "profile"),
                      ("sequence_length", "sequence_length"), ("frame_rate", "frame_rate_hz"),
                      ("twins", "twins"), ("degrade", "degrade"), ("lidar_fog", "lidar_fog")):
        value = getattr(args, flag)
        if value is not None:
            base[key] = value
    if args.severities is not None:
        base["severities"] = list(args.severities)
    if args.transitions is not None:
        base["transitions"] = list(args.transitions)
    return GenerateConfig.from_mapping(base)


def run_generate(args) -> int:
    from sensors.generate import generate

    config = build_config(args)
    out = Path(args.out)
    if args.address and args.backend != "ray":
        raise UserError("--address is the Ray cluster to join: it needs --backend ray")
    result = generate(config, out, workers=args.workers, progress=True, backend=args.backend, address=args.address)
    emit(result, args.json, lambda r: (
        f"{r['frames']} frames in {r['out']} ({r['frames_rendered']} rendered in {r['seconds']} s, "
        f"{r['frames_per_second']} frames/s, profile {r['profile']}, {r['workers']} workers"
        + (f" ({r['start_method']})" if r.get("start_method") else "") + f", {r['backend']} backend)"))
    return 0


# ---------------------------------------------------------------------------------------------


def add_verify(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=help_text + ". Exit code 2 names every missing, "
                       "unlisted or corrupted shard and every file another command would refuse.", formatter_class=Formatter)
    p.add_argument("dir", type=dataset_path, help="dataset directory")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout, also when the dataset "
                   "is damaged ({\"ok\": false, \"problems\": [...]}, exit code 2)")
    p.set_defaults(run=run_verify)


def run_verify(args) -> int:
    from sensors.dataset import read_manifest, verify

    problems = verify(args.dir)
    if problems:
        if args.json:
            emit({"ok": False, "dir": str(args.dir), "problems": problems}, True)
        raise UserError(f"{args.dir}: " + "; ".join(problems))
    m = read_manifest(args.dir)
    emit({"ok": True, "dir": str(args.dir), "shards": len(m["shards"]), "frames": len(m["frames"]), "problems": []},
         args.json, lambda r: f"{args.dir}: {r['shards']} shards, {r['frames']} frames, all checksums match")
    return 0


def add_export(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=help_text, formatter_class=Formatter)
    p.add_argument("dir", type=dataset_dir, help="dataset directory")
    p.add_argument("--out", required=True, type=out_file(".json"), help="COCO JSON file to write")
    p.add_argument("--camera", default="camera_right", choices=["camera_left", "camera_right"],
                   help="which camera's FWD labels")
    p.set_defaults(run=run_export)


def run_export(args) -> int:
    from sensors.dataset import DatasetReader, to_coco
    from study.outputs import atomic_path

    out = Path(args.out)
    coco = to_coco(DatasetReader(Path(args.dir)), args.camera)
    with atomic_path(out) as tmp:
        tmp.write_text(json.dumps(coco))
    sys.stderr.write(f"wrote {len(coco['images'])} images, {len(coco['annotations'])} boxes to {out}\n")
    return 0


def add_show(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=help_text + ": left/right cameras with FWD boxes, "
                       "lidar and radar BEV with BEV boxes, the forward-lidar projection, and a caption with the "
                       "context, weather and degradation parameters.", formatter_class=Formatter)
    p.add_argument("dir", type=dataset_dir, help="dataset directory")
    p.add_argument("--index", type=int, default=0,
                   help="frame index (negative counts from the end); with --context, the index among that context's frames")
    p.add_argument("--context", type=name_arg, default=None,
                   help="pick the frame among this context's frames; `all`: one picture per context the dataset "
                   "has (then --out must hold {context}, e.g. out/frame_{context}.png)")
    p.add_argument("--out", required=True, type=out_file(*IMAGE_SUFFIXES),
                   help="picture to write (.png, .pdf or .svg); {context} in it is replaced by the context's name")
    p.add_argument("--clear", action="store_true", help="show the clear-weather twin of the frame")
    p.set_defaults(run=run_show)


def run_show(args) -> int:
    from sensors.dataset import DatasetReader
    from study.report.plots import plot_frame

    reader = DatasetReader(Path(args.dir), clear=args.clear)
    frames = reader.manifest["frames"]
    present = sorted({f["context"] for f in frames})
    if args.context == "all":
        # one process for every context: the demo's eight pictures without eight interpreter starts
        if "{context}" not in str(args.out):
            raise UserError(f"--context all writes one picture per context: --out must hold {{context}}, got {args.out}")
        names = present
    elif args.context is not None:
        from sim.scenario import Context

        names = [Context.parse(args.context).name]
        if names[0] not in present:
            raise UserError(f"the dataset has no {names[0]!r} frames (it has: {', '.join(present)})")
    else:
        names = [None]
    picks = []
    for name in names:  # every index checked before the first picture is drawn
        candidates = [i for i, f in enumerate(frames) if name is None or f["context"] == name]
        if not -len(candidates) <= args.index < len(candidates):
            where = f" of context {name}" if name else ""
            raise UserError(f"--index {args.index} is out of range ({len(candidates)} frames{where} to choose from)")
        picks.append((name, candidates[args.index]))
    for name, index in picks:
        out = Path(str(args.out).replace("{context}", name or reader.manifest["frames"][index]["context"]))
        plot_frame(reader[index], str(out))
        sys.stderr.write(f"wrote {out}\n")
    return 0
