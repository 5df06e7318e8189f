"""Scenes of a context, simulated, summarised and drawn top-down (`hydrabench scenes`): actors per
class, structures, the weather at the first and last frame, the simulation speed, and a digest of
every scene (the same spec gives the same digest)."""

from __future__ import annotations

import hashlib
import time
from collections import Counter
from pathlib import Path


def summarise(scenes, seconds: float) -> dict:
    last = scenes[-1]
    counts = Counter()
    for s in scenes:
        counts.update(s.actors.class_names())
    from sim.world import STRUCTURE_KINDS

    digest = hashlib.sha256("".join(s.digest() for s in scenes).encode()).hexdigest()
    return {
        "context": last.context.name,
        "layout": last.context.layout,
        "conditions": list(last.context.conditions),
        "severity": last.severity,
        "frames": len(scenes),
        "seconds": round(seconds, 3),
        "scenes_per_second": round(len(scenes) / seconds, 1) if seconds > 0 else None,
        "actors_per_class": {k: round(v / len(scenes), 2) for k, v in sorted(counts.items())},
        "structures": {k: last.structures.count(k) for k in STRUCTURE_KINDS},
        "weather_first": scenes[0].weather.summary(),
        "weather_last": last.weather.summary(),
        "sequence_id": last.sequence_id,
        "digest": digest,
    }


def simulate_scenes(spec, plot: str | Path | None = None) -> dict:
    """Simulate `spec` (a `sim.scenario.ScenarioSpec`) with a progress bar, summarise its scenes
    (`summarise`) and, with `plot` (a checked image path), draw the last frame top-down there."""
    from sim.progress import progress
    from sim.scenario import Simulator
    from study.report.plots import plot_scene

    t0 = time.perf_counter()
    bar = progress(total=spec.frames, desc=f"scenes {spec.context}", unit="frame")
    scenes = []
    for scene in Simulator(spec).scenes():
        scenes.append(scene)
        bar.update(1)
    bar.close()
    r = summarise(scenes, time.perf_counter() - t0)
    if plot is not None:
        plot_scene(scenes[-1], str(plot))
        r["plot"] = str(Path(plot))
    return r
