"""One scene of a dataset re-rendered under every condition and severity (`hydrabench gallery`).

Takes a frame of the dataset, rebuilds that exact moment from its shard's seed, and renders it
again under a representative weather state of each condition and severity (the centre of the
severity table's interval; sim.weather.representative_weather), with the weather degradation models
(no random obstructions), so one row differs from the next only by the weather. Columns: right
camera, forward lidar, lidar BEV, radar BEV.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sim.errors import UserError


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


def render_gallery(data, out, index: int = 0, context: str | None = None,
                   conditions=("rain", "fog", "snow", "night")) -> dict:
    """Draw the gallery of dataset frame `index` (with `context`: the index-th frame of that context)
    into the picture `out` (.png, .pdf or .svg), one row per condition and severity 1-5 below the
    clear row; returns what was rendered (rows, the scene, lidar points and camera mean per row)."""
    from sensors.dataset import read_manifest
    from sensors.degrade import Degrader
    from sensors.frame import SequenceRenderer
    from sensors.rig import load_profile
    from sim.progress import progress
    from sim.scenario import Context
    from sim.weather import CONDITIONS, representative_weather
    from study.report.plots import plot_gallery

    out = Path(out)
    conditions = list(conditions)
    bad = [c for c in conditions if c not in CONDITIONS]
    if bad:
        raise UserError(f"unknown condition {bad[0]!r} (choose from: {', '.join(CONDITIONS)})")
    manifest = read_manifest(Path(data))
    pick = index
    if context is not None:
        name = Context.parse(context).name
        picks = [i for i, f in enumerate(manifest["frames"]) if f["context"] == name]
        if not -len(picks) <= pick < len(picks):
            raise UserError(f"the dataset has {len(picks)} {name!r} frames; --index {pick} is out of range")
        index = picks[pick]
    first, scene, shard = scene_of(manifest, index)
    renderer = SequenceRenderer(first, load_profile(manifest["profile"]), seed=shard["seed"])
    layout = Context.parse(shard["context"]).layout
    rows = [("clear", 0)] + [(c, s) for c in conditions for s in range(1, 6)]
    panels = []
    for cond, sev in progress(iterable=rows, desc="gallery", unit="row"):
        weather = representative_weather(cond if cond != "clear" else "fog", sev)
        row_context = layout if cond == "clear" else f"{layout}+{cond}"
        degrader = Degrader(renderer.calib, row_context, shard["seed"], obstructions=False,
                            lidar_fog=manifest["config"].get("lidar_fog", "ours"))
        obs, params = degrader.apply(renderer.observe(scene, weather), scene.frame_index)
        frame = renderer.finalize(scene, obs, params)
        panels.append({"condition": cond, "severity": sev, "weather": weather, "frame": frame})
    plot_gallery(panels, str(out), title=f"{shard['context']} scene (dataset frame {pick}), "
                 f"profile {manifest['profile']}: the same moment under each condition and severity")
    result = {"out": str(out), "rows": len(rows), "scene": {"context": shard["context"], "seed": shard["seed"],
              "frame_index": int(scene.frame_index)},
              "lidar_points": {f"{p['condition']}{p['severity']}": int(len(p["frame"].lidar_points)) for p in panels},
              "camera_mean": {f"{p['condition']}{p['severity']}": round(float(np.mean(p["frame"].camera_right)), 1)
                              for p in panels}}
    return result
