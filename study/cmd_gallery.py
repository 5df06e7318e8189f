"""`hydrabench gallery`: one scene of a dataset re-rendered under every condition and severity."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sim.errors import UserError
from study.cli import IMAGE_SUFFIXES, Formatter, dataset_dir, emit, name_arg, name_list, out_file

EPILOG = """\
Takes frame --index of the dataset, rebuilds that exact moment from its shard's seed, and renders it
again under a representative weather state of each condition and severity (the centre of the
severity table's interval; sim.weather.representative_weather), with the weather degradation models
(no random obstructions), so one row differs from the next only by the weather. Columns: right
camera, forward lidar, lidar BEV, radar BEV. Fog must look like fog; the radar must barely change
in fog.
"""


def add_parser(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=help_text, epilog=EPILOG, formatter_class=Formatter)
    p.add_argument("dir", type=dataset_dir, help="dataset directory (its manifest gives the scene's seed and profile)")
    p.add_argument("--out", required=True, type=out_file(*IMAGE_SUFFIXES), help="picture to write (.png, .pdf or .svg)")
    p.add_argument("--index", type=int, default=0, help="frame of the dataset to use as the scene")
    p.add_argument("--context", type=name_arg, default=None, help="take the --index-th frame of this context instead")
    p.add_argument("--conditions", type=name_list, default="rain,fog,snow,night",
                   help="comma-separated conditions (rows), each once")
    p.add_argument("--json", action="store_true", help="print one JSON object (what was rendered) on stdout")
    p.set_defaults(run=run)


def scene_of(manifest: dict, index: int):
    """Re-simulate the moment of dataset frame `index` (deterministic from its shard spec)."""
    from sim.scenario import ScenarioSpec, Simulator

    frames = manifest["frames"]
    if not -len(frames) <= index < len(frames):
        raise UserError(f"--index {index} is out of range (dataset has {len(frames)} frames)")
    f = frames[index]
    shard = next(s for s in manifest["shards"] if s["name"] == f["shard"])
    cfg = manifest["config"]
    spec = ScenarioSpec(context=shard["context"], severity=shard["severity"], seed=shard["seed"],
                        frames=f["index"] + 1, frame_rate_hz=cfg["frame_rate_hz"], profile=cfg["profile"],
                        transition=shard["transition"])
    scenes = list(Simulator(spec).scenes())
    return scenes[0], scenes[-1], shard


def run(args) -> int:
    from sensors.dataset import read_manifest
    from sensors.degrade import Degrader
    from sensors.frame import SequenceRenderer
    from sensors.rig import load_profile
    from sim.progress import progress
    from sim.scenario import Context
    from sim.weather import CONDITIONS, representative_weather
    from study.plots import plot_gallery

    out = Path(args.out)
    conditions = list(args.conditions)
    bad = [c for c in conditions if c not in CONDITIONS]
    if bad:
        raise UserError(f"unknown condition {bad[0]!r} (choose from: {', '.join(CONDITIONS)})")
    manifest = read_manifest(Path(args.dir))
    index = args.index
    if args.context is not None:
        from sim.scenario import Context

        name = Context.parse(args.context).name
        picks = [i for i, f in enumerate(manifest["frames"]) if f["context"] == name]
        if not -len(picks) <= args.index < len(picks):
            raise UserError(f"the dataset has {len(picks)} {name!r} frames; --index {args.index} is out of range")
        index = picks[args.index]
    first, scene, shard = scene_of(manifest, index)
    renderer = SequenceRenderer(first, load_profile(manifest["profile"]), seed=shard["seed"])
    layout = Context.parse(shard["context"]).layout
    rows = [("clear", 0)] + [(c, s) for c in conditions for s in range(1, 6)]
    panels = []
    for cond, sev in progress(iterable=rows, desc="gallery", unit="row"):
        weather = representative_weather(cond if cond != "clear" else "fog", sev)
        context = layout if cond == "clear" else f"{layout}+{cond}"
        degrader = Degrader(renderer.calib, context, shard["seed"], obstructions=False,
                            lidar_fog=manifest["config"].get("lidar_fog", "ours"))
        obs, params = degrader.apply(scene, renderer.observe(scene, weather), scene.frame_index)
        frame = renderer.finalize(scene, obs, params)
        panels.append({"condition": cond, "severity": sev, "weather": weather, "frame": frame})
    plot_gallery(panels, str(out), title=f"{shard['context']} scene (dataset frame {args.index}), "
                 f"profile {manifest['profile']}: the same moment under each condition and severity")
    result = {"out": str(out), "rows": len(rows), "scene": {"context": shard["context"], "seed": shard["seed"],
              "frame_index": int(scene.frame_index)},
              "lidar_points": {f"{p['condition']}{p['severity']}": int(len(p["frame"].lidar_points)) for p in panels},
              "camera_mean": {f"{p['condition']}{p['severity']}": round(float(np.mean(p["frame"].camera_right)), 1)
                              for p in panels}}
    emit(result, args.json, lambda r: f"wrote {r['out']} ({r['rows']} rows)")
    return 0
