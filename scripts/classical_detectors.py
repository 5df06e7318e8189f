"""Measure the classical detectors of examples/ on a dataset and record it (docs/examples.md quotes it).

    hydrabench generate --out /tmp/cl/test --frames-per-context 24 --sequence-length 3 --seed 1 --workers 2
    python scripts/classical_detectors.py /tmp/cl/test --work /tmp/cl/work [--out results/classical_detectors_DATE.json]

Runs what a user runs, each as its own command, timed by wall clock: the nuScenes export, the lidar and
the radar detector, the weather rule gate in two forms (radar alone, or lidar and radar, in fog, rain and
snow; lidar alone otherwise), a first `hydrabench score` without intervals from which the context oracle
is picked (examples/context_oracle.py), then `hydrabench score` of both detectors, late fusion, the
gates and the oracle with 500 sequence draws. Also the devkit's own detection evaluation of each
detector (`DetectionEval`, detection_cvpr_2019, every scene). The record holds the commands, the
times, the sizes, the CPU and its load, and the score result as `hydrabench score --json` printed it.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HYDRABENCH = [sys.executable, "-m", "study.cli"]
EXAMPLES = ROOT / "examples"


def timed(cmd: list[str], stdout=None) -> float:
    """Wall seconds of `cmd` (its stderr passed through); raises on a non-zero exit."""
    print("$ " + " ".join(cmd), file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=stdout, cwd=ROOT)
    return round(time.perf_counter() - t0, 2)


def size(path: Path) -> int:
    return sum(f.stat().st_size for f in Path(path).rglob("*") if f.is_file())


def shown(cmd: list[str]) -> str:
    """`cmd` as a user types it (the interpreter as python, the CLI as hydrabench)."""
    words = list(cmd)
    if words[:3] == HYDRABENCH:
        words = ["hydrabench", *words[3:]]
    elif words[0] == sys.executable:
        words[0] = "python"
    return " ".join(str(w).replace(str(ROOT) + "/", "") for w in words)


def devkit_metrics(export: Path, results: Path) -> dict:
    """The nuScenes devkit's detection evaluation of `results` on every scene of `export`."""
    import tempfile

    from nuscenes import NuScenes
    from nuscenes.eval.common.config import config_factory
    from nuscenes.eval.detection.evaluate import DetectionEval

    nusc = NuScenes(version="v1.0-hydrabench", dataroot=str(export), verbose=False)
    with tempfile.TemporaryDirectory() as tmp:
        ev = DetectionEval(nusc, config_factory("detection_cvpr_2019"), str(results), "hydrabench-all", tmp,
                           verbose=False)
        metrics, _ = ev.evaluate()
    s = metrics.serialize()
    return {"mean_ap": s["mean_ap"], "nd_score": s["nd_score"],
            "mean_dist_aps": {k: round(v, 4) for k, v in s["mean_dist_aps"].items()},
            "note": "devkit 1.2.0, detection_cvpr_2019: mean_ap averages nuScenes' ten classes (hydrabench makes six)"}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n")[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", type=Path, help="a generated dataset")
    p.add_argument("--work", type=Path, required=True, help="a new folder for the export and the files")
    p.add_argument("--out", type=Path, default=None, help="the record (default: results/classical_detectors_DATE.json)")
    p.add_argument("--bootstrap", type=int, default=500, help="sequence draws of the final score [500]")
    p.add_argument("--generate-command", default="", help="how DATA was made, recorded as given")
    args = p.parse_args(argv)
    os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
    date = datetime.datetime.now(datetime.UTC)
    out = args.out or ROOT / "results" / f"classical_detectors_{date:%Y-%m-%d}.json"
    work, data = args.work.resolve(), args.data.resolve()
    work.mkdir(parents=True, exist_ok=False)
    ns = work / "nuscenes"
    load = " ".join(Path("/proc/loadavg").read_text().split()[:3]) if Path("/proc/loadavg").exists() else None
    frames = json.loads((data / "manifest.json").read_text())
    frames = len(frames["frames"]) if "frames" in frames else None

    commands, seconds = {}, {}

    def step(name, cmd, stdout=None):
        commands[name], seconds[name] = shown(cmd), timed(cmd, stdout)

    step("export", [*HYDRABENCH, "export", "nuscenes", str(data), "--out", str(ns)])
    files = {"lidar": work / "lidar.json", "radar": work / "radar.json"}
    for name, f in files.items():
        step(name, [sys.executable, str(EXAMPLES / f"{name}_detector.py"), "--export", str(ns), "--out", str(f)])
    gates = {"weather_radar": work / "weather_radar.json", "weather_add_radar": work / "weather_add_radar.json"}
    step("weather_radar", [sys.executable, str(EXAMPLES / "weather_gate.py"), "--export", str(ns), "--out",
                           str(gates["weather_radar"]), "--adverse", "radar"])
    step("weather_add_radar", [sys.executable, str(EXAMPLES / "weather_gate.py"), "--export", str(ns), "--out",
                               str(gates["weather_add_radar"]), "--adverse", "lidar,radar"])
    score = [*HYDRABENCH, "score", str(data), "--export", str(ns),
             *[a for n, f in files.items() for a in ("--nuscenes", f"{n}={f}")]]
    with open(work / "score_constants.json", "w") as fh:
        step("score_constants", [*score, "--bootstrap", "0", "--json"], fh)
    gates["context_oracle"] = work / "context_oracle.json"
    step("context_oracle", [sys.executable, str(EXAMPLES / "context_oracle.py"), "--score",
                            str(work / "score_constants.json"), "--export", str(ns), "--out", str(gates["context_oracle"])])
    with open(work / "score.json", "w") as fh:
        step("score", [*score, *[a for n, f in gates.items() for a in ("--selection", f"{n}={f}")],
                       "--bootstrap", str(args.bootstrap), "--json"], fh)
    result = json.loads((work / "score.json").read_text())
    boxes = {n: sum(len(v) for v in json.loads(f.read_text())["results"].values()) for n, f in files.items()}
    export_bytes = size(ns)
    cpu = next((ln.split(":", 1)[1].strip() for ln in subprocess.run(["lscpu"], capture_output=True, text=True)
                .stdout.splitlines() if ln.startswith("Model name")), None)
    record = {
        "date": f"{date:%Y-%m-%d %H:%M} UTC", "cpu": cpu, "cores": os.cpu_count(), "load_average_before": load,
        "data": {"frames": frames, "bytes": size(data), "generate_command": args.generate_command},
        "commands": commands, "seconds": seconds,
        "export": {"bytes": export_bytes, "seconds": seconds["export"],
                   "per_1000_frames": {"seconds": round(seconds["export"] / frames * 1000, 1),
                                       "gb": round(export_bytes / frames * 1000 / 1e9, 3)}},
        "detectors": {n: {"seconds": seconds[n], "boxes": boxes[n]} for n in files},
        "devkit": {n: devkit_metrics(ns, f) for n, f in files.items()},
        "score": result,
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=1) + "\n")
    print(f"wrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
