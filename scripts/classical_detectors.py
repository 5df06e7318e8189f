"""Measure the classical detectors of examples/ on a dataset and record it (docs/nuscenes.md quotes it).

    hydrabench generate --out /tmp/cl/test --frames-per-context 24 --sequence-length 3 --seed 1 --workers 2
    python scripts/classical_detectors.py /tmp/cl/test --work /tmp/cl/work [--out results/classical_detectors_DATE.json]
    python scripts/classical_detectors.py --docs results/classical_detectors_DATE.json [--check]

Runs what a user runs, each as its own command, timed by wall clock: the nuScenes export, the lidar and
the radar detector, the weather rule gate in two forms (radar alone, or lidar and radar, in fog, rain and
snow; lidar alone otherwise), a first `hydrabench score` without intervals from which the context oracle
is picked (examples/context_oracle.py), then `hydrabench score` of both detectors, late fusion, the
gates and the oracle with 500 sequence draws. Also the devkit's own detection evaluation of each
detector (`DetectionEval`, detection_cvpr_2019, every scene), and with --networks a trained run's own
branches written out as results files and scored by the same command. The record holds the commands,
the wall and CPU times, the sizes, the CPU and its load, and each score result as `hydrabench score
--json` printed it. `--docs RECORD` writes the measured block of docs/nuscenes.md from a record
(`--check`: exit 1 when the page differs; the tests run it).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HYDRABENCH = [sys.executable, "-m", "study.cli"]
EXAMPLES = ROOT / "examples"


def timed(cmd: list[str], stdout=None) -> tuple[float, float]:
    """(wall seconds, CPU seconds: user + system) of `cmd` (its stderr passed through); raises on a
    non-zero exit. CPU time says what a step costs when other work shares the cores."""
    print("$ " + " ".join(cmd), file=sys.stderr, flush=True)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=stdout, cwd=ROOT)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return round(wall, 2), round(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime, 2)


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


def networks(run: str, data: Path, ns: Path, work: Path, resamples: int) -> dict:
    """`run`'s branches on `data` (study.predictions), written out as results files by
    study.external's writers and scored by `hydrabench score` like any detector from outside."""
    from sensors.dataset import DatasetReader
    from study import reference_model
    from study.external import ExportIndex, bev_results, coco_results
    from study.predictions import predict

    t0 = time.perf_counter()
    pred = predict(reference_model.resolve_run(run), data, work / "predictions", gates=("knowledge",), split="all")
    seconds = round(time.perf_counter() - t0, 1)
    reader = DatasetReader(data)
    index = ExportIndex(ns, reader)
    per_frame = [(dict(reader.meta(m["dataset_index"]), dataset_index=m["dataset_index"]), per)
                 for m, per in pred.per_frame]
    args = []
    for b in pred.branches:
        path = work / f"net_{b}.json"
        if pred.branch_frames[b] == "bev":
            path.write_text(json.dumps(bev_results(per_frame, b, index, pred.branch_sensors[b])))
            args += ["--nuscenes", f"{b}={path}"]
        else:
            path.write_text(json.dumps(coco_results(per_frame, b)))
            args += ["--coco", f"{b}={path}"]
    cmd = [*HYDRABENCH, "score", str(data), "--export", str(ns), *args, "--bootstrap", str(resamples), "--json"]
    print("$ " + " ".join(cmd), file=sys.stderr, flush=True)
    done = subprocess.run(cmd, check=True, stdout=subprocess.PIPE, cwd=ROOT, text=True)
    return {"run": run, "predict_seconds": seconds, "command": shown(cmd), "score": json.loads(done.stdout)}


BEGIN = "<!-- classical detectors: generated by scripts/classical_detectors.py --docs, do not edit -->"
END = "<!-- end of the classical detectors' measurement -->"
CLASSICAL = ("single:lidar", "single:radar", "late", "selection:weather_radar", "selection:weather_add_radar",
             "selection:context_oracle")


def _num(v, signed=False) -> str:
    return "-" if v is None else (f"{v:+.3f}" if signed else f"{v:.3f}")


def _iv(iv, signed=False) -> str:
    return f"[{_num(iv[0], signed)}, {_num(iv[1], signed)}]" if iv else "-"


def _short(text: str, record: dict) -> str:
    """A recorded command with the dataset's path as `data` and the work folder's as `work`."""
    work = str(Path(record["score"]["sources"]["lidar"]).parent)
    return text.replace(work, "work").replace(record["score"]["data"], "data")


def docs_block(record: dict, name: str) -> str:
    """The measured part of docs/nuscenes.md, every number from `record` (the file `name`); commands
    with the dataset as `data` and the work folder as `work`."""
    record = json.loads(_short(json.dumps(record), record))
    sc, ex, det = record["score"], record["export"], record["detectors"]
    frames = sc["frames"]
    out = [f"Measured {record['date'][:10]} on an {record['cpu']} ({record['cores']} cores, shared: load average "
           f"{record['load_average_before']} before it started), recorded in `{name}`: {frames} frames "
           f"(`{record['data']['generate_command']}`, {record['data']['bytes'] / 1e6:.0f} MB).", "",
           "| step | wall | CPU (user + system) | output |", "|---|---|---|---|",
           f"| `{record['commands']['export']}` | {ex['seconds']:.1f} s | {ex['cpu_seconds']:.1f} s | "
           f"{ex['bytes'] / 1e6:.1f} MB |"]
    for n in ("lidar", "radar"):
        out.append(f"| `{record['commands'][n]}` | {det[n]['seconds']:.1f} s | {det[n]['cpu_seconds']:.1f} s | "
                   f"{det[n]['boxes']} boxes |")
    per = ex["per_1000_frames"]
    out += ["", f"Per 1,000 frames the export takes {per['seconds'] / 60:.1f} minutes of wall time here "
                f"({per['cpu_seconds'] / 60:.1f} minutes of CPU) and {per['gb']:.2f} GB; each detector at most "
                f"{max(det[n]['cpu_seconds'] for n in det) / frames * 1000 / 60:.1f} minutes of CPU.", "",
            f"`{record['commands']['score']}` ({sc['bootstrap']['resamples']} draws of whole sequences; VOC mAP@0.5 "
            f"in the right camera, {sc['protocol']} protocol, classes {sc['classes']}):", "",
            "| method | mAP@0.5 | 95 % interval | minus late | its interval | verdict | vehicles mAP |",
            "|---|---|---|---|---|---|---|"]
    for m in CLASSICAL:
        v = sc["methods"][m]
        d = v.get("minus_late") or {}
        out.append(f"| {m} | {_num(v['map'])} | {_iv(v.get('ci95'))} | {_num(d.get('value'), True)} | "
                   f"{_iv(d.get('ci95'), True)} | {d.get('verdict', '-')} | {_num(v['map_vehicles'])} |")
    ctx = sc["contexts"]
    out += ["", "Per context (mAP@0.5):", "", f"| method | {' | '.join(ctx)} |", f"|---|{'---|' * len(ctx)}"]
    for m in CLASSICAL:
        out.append(f"| {m} | " + " | ".join(_num(sc["methods"][m]["map_per_context"][c]) for c in ctx) + " |")
    nets = record.get("networks")
    if nets:
        for m, v in nets["score"]["methods"].items():
            out.append(f"| {nets['run']} {m} | " + " | ".join(_num(v["map_per_context"][c]) for c in ctx) + " |")
    fixed = ("single:lidar", "single:radar", "late")
    best = {c: max(fixed, key=lambda m: sc["methods"][m]["map_per_context"][c] or -1) for c in ctx}
    out += ["", "Best fixed choice of the classical pair per context (what the context oracle takes): "
            + ", ".join(f"{c} {best[c]}" for c in ctx) + "."]
    if nets:
        nm = nets["score"]["methods"]
        out += ["", f"The own networks (`{nets['command']}`; the `{nets['run']}` run's branches written out by "
                "`study.external.bev_results` / `coco_results`, so scored by the same path in the same merged "
                f"classes): late {_num(nm['late']['map'])} {_iv(nm['late'].get('ci95'))}, all_branches "
                f"{_num(nm['all_branches']['map'])} {_iv(nm['all_branches'].get('ci95'))}; their lidar branch "
                f"{_num(nm['single:lidar']['map'])} against the classical lidar's "
                f"{_num(sc['methods']['single:lidar']['map'])}, their radar branch {_num(nm['single:radar']['map'])} "
                f"against the classical radar's {_num(sc['methods']['single:radar']['map'])}."]
        for sensor in ("lidar", "radar"):
            mine, theirs = sc["methods"][f"single:{sensor}"]["map_per_context"], nm[f"single:{sensor}"]["map_per_context"]
            above = [c for c in ctx if (mine[c] or 0) > (theirs[c] or 0)]
            out.append(f"The classical {sensor} scores above the own {sensor} branch in "
                       + (", ".join(f"{c} ({_num(mine[c])} against {_num(theirs[c])})" for c in above) or "no context")
                       + (", below it elsewhere." if above else "."))
    dk = record["devkit"]
    out += ["", "The devkit's own evaluation (`DetectionEval`, detection_cvpr_2019, every scene; AP averaged over "
            "the 0.5-4 m centre-distance thresholds): " + "; ".join(
                f"{n}: car {dk[n]['mean_dist_aps']['car']:.3f}, pedestrian {dk[n]['mean_dist_aps']['pedestrian']:.3f}, "
                f"truck {dk[n]['mean_dist_aps']['truck']:.3f}, mAP {dk[n]['mean_ap']:.3f} over its ten classes, NDS "
                f"{dk[n]['nd_score']:.3f}" for n in dk) + "."]
    return "\n".join(out)


def write_docs(record_path: Path, page: Path, check: bool) -> int:
    """docs/nuscenes.md's measured block from the record at `record_path`."""
    sys.path.insert(0, str(ROOT))
    from study.outputs import replace_marked_block, update_page

    record = json.loads(record_path.read_text())
    try:
        shown_name = record_path.resolve().relative_to(ROOT).as_posix()
    except ValueError:
        shown_name = str(record_path)
    old = page.read_text()
    return update_page(page, old, replace_marked_block(old, BEGIN, END, docs_block(record, shown_name)), check)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n")[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", type=Path, nargs="?", help="a generated dataset")
    p.add_argument("--work", type=Path, help="a new folder for the export and the files")
    p.add_argument("--docs", type=Path, metavar="RECORD", help="write docs/nuscenes.md's block from RECORD instead")
    p.add_argument("--page", type=Path, default=ROOT / "docs" / "nuscenes.md", help="the page --docs writes")
    p.add_argument("--check", action="store_true", help="with --docs: exit 1 when the page differs, write nothing")
    p.add_argument("--out", type=Path, default=None, help="the record (default: results/classical_detectors_DATE.json)")
    p.add_argument("--bootstrap", type=int, default=500, help="sequence draws of the final score [500]")
    p.add_argument("--generate-command", default="", help="how DATA was made, recorded as given")
    p.add_argument("--networks", default=None, metavar="RUN",
                   help="also score this run's own networks (e.g. cpu-frontier) through the same path: each branch's "
                        "detections written as nuScenes (BEV branches) or COCO (the camera) results")
    args = p.parse_args(argv)
    if args.docs:
        return write_docs(args.docs, args.page, args.check)
    if args.data is None or args.work is None:
        p.error("give DATA and --work (or --docs RECORD)")
    os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
    date = datetime.datetime.now(datetime.UTC)
    out = args.out or ROOT / "results" / f"classical_detectors_{date:%Y-%m-%d}.json"
    work, data = args.work.resolve(), args.data.resolve()
    work.mkdir(parents=True, exist_ok=False)
    ns = work / "nuscenes"
    load = " ".join(Path("/proc/loadavg").read_text().split()[:3]) if Path("/proc/loadavg").exists() else None
    frames = json.loads((data / "manifest.json").read_text())
    frames = len(frames["frames"]) if "frames" in frames else None

    commands, seconds, cpu_seconds = {}, {}, {}

    def step(name, cmd, stdout=None):
        commands[name] = shown(cmd)
        seconds[name], cpu_seconds[name] = timed(cmd, stdout)

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
        "commands": commands, "seconds": seconds, "cpu_seconds": cpu_seconds,
        "export": {"bytes": export_bytes, "seconds": seconds["export"], "cpu_seconds": cpu_seconds["export"],
                   "per_1000_frames": {"seconds": round(seconds["export"] / frames * 1000, 1),
                                       "cpu_seconds": round(cpu_seconds["export"] / frames * 1000, 1),
                                       "gb": round(export_bytes / frames * 1000 / 1e9, 3)}},
        "detectors": {n: {"seconds": seconds[n], "cpu_seconds": cpu_seconds[n], "boxes": boxes[n]} for n in files},
        "devkit": {n: devkit_metrics(ns, f) for n, f in files.items()},
        "score": result,
    }
    if args.networks:
        record["networks"] = networks(args.networks, data, ns, work, args.bootstrap)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=1) + "\n")
    print(f"wrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
