"""EcoFusion Eq. 6 measured: each stem, branch and the fusion block timed on real frames
(`measure_latency`), the additive latency model checked end to end, and each configuration's
latency and energy (`energy_table`, `hydrabench eco-energy`); each learned gate's own network timed
on the same frames (`gate_latency`, RUN/eco/gate_latency.json), so a gate pays for deciding. See
`study.eco`."""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from sim.errors import UserError
from sim.progress import progress as progress_bar
from study.eco.data import EcoSettings, eco_splits, open_eco_run
from study.engine.gate_data import cached_sha256, checkpoint_path
from study.outputs import write_json_atomic

LATENCY_VERSION = 1


def machine_description(threads: int) -> dict:
    cpu = platform.processor() or ""
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import torch

    return {"cpu": cpu, "cores": os.cpu_count(), "threads": threads, "torch": torch.__version__,
            "platform": platform.platform(), "device": "cpu"}


def measure_latency(model, data, indices, configs, method: str = "soft_nms", repeats: int = 3, threads: int = 1,
                    counter: str = "auto", check: int = 12, seed: int = 0, progress: bool = True):
    """Time every stem, branch and the fusion block on `indices` (batch 1) and check the additive
    model against configurations timed end to end (stems + branches + fusion in one call).

    Returns (LatencyModel, check dict). Each component's time is the median of `repeats` runs
    after one warm-up, averaged over the frames; fusion[n] is the mean over the configurations of
    n branches (each timed once per repeat). Checked end to end: the first `check` of late
    fusion, all branches, the other named baselines, then random others (seeded).
    """
    import torch

    from fusion.data import FrameDataset, collate
    from fusion.eco.energy import LatencyModel, open_counter
    from fusion.late import fuse
    from fusion.nets import SENSORS
    from sensors.rig import Calibration
    from study.engine.scoring import to_detections

    torch.set_num_threads(threads)
    ctr = open_counter(counter, "cpu")
    ds = FrameDataset(data, indices, sensors=model.sensors, bev_size=model.transform.image_size("radar"))
    frames = model.branch_frames
    stems_s, branch_s, fusion_s = defaultdict(list), defaultdict(list), defaultdict(list)
    energy = defaultdict(list) if ctr is not None else None
    direct_t, direct_e = defaultdict(list), defaultdict(list)
    checked = checked_configurations(configs, check, seed)
    shared = [s for s in model.sensors if SENSORS[s].stem in model.stems]
    by_n = defaultdict(list)
    for m in configs.members:
        by_n[len(m)].append(m)
    timed = _timer(ctr, repeats)
    load_before = os.getloadavg()

    def record(key, table, value):
        t, e = value
        table.append(t)
        if energy is not None:
            energy[key].append(e)

    bar = progress_bar(total=len(indices), desc="latency", enabled=progress)
    with torch.no_grad():
        for k in range(len(ds)):
            inputs, _t, metas = collate([ds[k]])
            calib = Calibration.from_dict(metas[0]["calibration"])
            for s in shared:
                record(f"stem:{s}", stems_s[s], timed(lambda s=s, x=inputs: model.extract_features(x, [s])))
            feats = model.extract_features(inputs)
            for b, branch in model.branches.items():
                if branch.fusion == "input":
                    xs = [model.transform(s, inputs[s]) for s in branch.sensors]
                else:
                    xs = [feats[s] for s in branch.sensors]
                record(f"branch:{b}", branch_s[b], timed(lambda br=branch, xs=xs: br(xs)))
            per = {n: to_detections(d) for n, d in model(inputs, selection=list(model.branches))[0].items()}
            for n, ms in by_n.items():
                def fuse_all(ms=ms, per=per, calib=calib):
                    for m in ms:
                        fuse({b: per[b] for b in m}, frames, calib, method=method)
                t, e = timed(fuse_all)  # every configuration of n branches once: the mean per configuration
                record(f"fusion:{n}", fusion_s[n], (t / len(ms), None if e is None else e / len(ms)))
            for m in checked:
                def run(m=m, inputs=inputs, calib=calib):
                    dets = model(inputs, selection=list(m))[0]
                    fuse({b: to_detections(d) for b, d in dets.items()}, frames, calib, method=method)
                t, e = timed(run)
                direct_t[m].append(t)
                if e is not None:
                    direct_e[m].append(e)
            bar.update(1)
    bar.close()
    lat = LatencyModel({s: float(np.mean(v)) for s, v in stems_s.items()},
                       {b: float(np.mean(v)) for b, v in branch_s.items()},
                       {n: float(np.mean(v)) for n, v in sorted(fusion_s.items())},
                       {b: (tuple(br.sensors) if br.fusion == "features" else ()) for b, br in model.branches.items()},
                       {k: float(np.mean(v)) for k, v in energy.items()} if energy is not None else None,
                       {"frames": len(ds), "repeats": repeats, "counter": ctr.name if ctr is not None else None,
                        "machine": machine_description(threads), "method": method,
                        "load_average_before": [round(x, 2) for x in load_before],
                        "load_average_after": [round(x, 2) for x in os.getloadavg()]})
    return lat, additive_check(lat, checked, direct_t, direct_e)


def checked_configurations(configs, check: int, seed: int) -> list[tuple[str, ...]]:
    """The configurations timed end to end: late fusion, all branches, the other named baselines,
    then random others (seeded), the first `check` (at least one)."""
    rng = np.random.default_rng(seed)
    members = list(configs.members)
    first = [configs.members[configs.baselines["late"]]] if "late" in configs.baselines else []
    if tuple(configs.branches) in members:
        first.append(tuple(configs.branches))
    first += [configs.members[i] for i in configs.baselines.values()]
    first = list(dict.fromkeys(first))
    others = [m for m in members if m not in first]
    extra = [others[i] for i in rng.permutation(len(others))] if others else []
    return (first + extra)[:max(check, 1)]


def _timer(ctr, repeats: int):
    """timed(fn) -> (median seconds, mean joules or None) of `repeats` calls of fn after one warm-up,
    joules from the energy counter `ctr` (None: no counter)."""

    def timed(fn):
        fn()
        ts, es = [], []
        for _ in range(repeats):
            before = ctr.read() if ctr is not None else None
            t = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t)
            if ctr is not None:
                es.append(ctr.joules(before, ctr.read()))
        return float(np.median(ts)), (float(np.mean(es)) if es else None)

    return timed


def additive_check(lat, checked, direct_t: dict, direct_e: dict) -> dict:
    """The additive latency model `lat` against the configurations timed end to end: per
    configuration measured and additive ms (and J where a counter measured), relative errors."""
    rows = {}
    for m in checked:
        pred, meas = lat.latency(m), float(np.mean(direct_t[m]))
        rows["+".join(m)] = {"measured_ms": round(1000 * meas, 2), "additive_ms": round(1000 * pred, 2),
                             "relative_error": round((pred - meas) / meas, 4)}
        if direct_e.get(m):
            rows["+".join(m)].update(measured_j=round(float(np.mean(direct_e[m])), 4),
                                     additive_j=round(lat.measured_energy(m), 4))
    errs = [abs(r["relative_error"]) for r in rows.values()]
    return {"configurations": rows, "mean_abs_relative_error": round(float(np.mean(errs)), 4),
            "max_abs_relative_error": round(float(np.max(errs)), 4)}


def latency_identity(run_dir, s: EcoSettings, threads: int, counter: str) -> dict:
    return {"version": LATENCY_VERSION, "checkpoint_sha256": cached_sha256(checkpoint_path(run_dir, s.checkpoint)),
            "machine": machine_description(threads), "counter": counter, "fusion": s.fusion}


def energy_table(run_dir, data, s: EcoSettings = EcoSettings(), threads: int = 1, repeats: int = 3, frames: int = 3,
                 counter: str = "auto", fresh: bool = False, progress: bool = True, model=None, configs=None,
                 test=None, reuse: bool = False, n_check: int = 12) -> dict:
    """`hydrabench eco-energy`: the latency model of this run on this machine (cached in
    RUN/eco/latency.json; `fresh` measures again) with its additive check, and each baseline's
    latency and energy. `reuse`: take a cached table of this checkpoint measured with other
    thread / counter settings (what evaluation does) instead of measuring again."""
    from fusion.eco.energy import LatencyModel, configuration_energy, power_model
    from study.engine.scoring import fusion_method

    run_dir, data = Path(run_dir), Path(data)
    if model is None:
        model, cfg, configs, _ed = open_eco_run(run_dir, data, s, threads)
        _train, test = eco_splits(cfg, data, s.max_frames)
    try:
        power = power_model(s.power)
    except ValueError as exc:
        raise UserError(f"--power: {exc}") from None
    path = run_dir / "eco" / "latency.json"
    ident = latency_identity(run_dir, s, threads, counter)
    cached = json.loads(path.read_text()) if path.exists() else None
    usable = cached is not None and not fresh and (
        cached.get("identity") == ident
        or (reuse and all(cached["identity"].get(k) == ident[k] for k in ("version", "checkpoint_sha256", "fusion"))))
    if usable:
        lat, check = LatencyModel.from_dict(cached["model"]), cached["check"]
    else:
        if progress:
            sys.stderr.write(f"measuring latency on {frames} test frames ({threads} thread(s), {repeats} repeats)\n")
        lat, check = measure_latency(model, data, test[:frames], configs, fusion_method(s.fusion), repeats, threads,
                                     counter, check=n_check, progress=progress)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_json_atomic(path, {"identity": ident, "model": lat.to_dict(), "check": check})
    t, e, source = configuration_energy(lat, configs.members, power)
    base = {k: {"configuration": configs.names[i], "latency_ms": round(1000 * t[i], 2), "energy_j": round(e[i], 4)}
            for k, i in configs.baselines.items()}
    return {"latency_model": {"stems_ms": {k: round(1000 * v, 2) for k, v in lat.stems.items()},
                              "branches_ms": {k: round(1000 * v, 2) for k, v in lat.branches.items()},
                              "fusion_ms": {str(k): round(1000 * v, 3) for k, v in lat.fusion.items()}},
            "additive_check": check, "baselines": base, "energy_source": source, "machine": lat.meta.get("machine"),
            "latency_cache": str(path), "_model": lat, "_t": t, "_e": e}


GATE_LATENCY = "gate_latency.json"
"""Under RUN/eco/: each learned gate's own decision time (`gate_latency`)."""


def gate_latency(run_dir, data, gates: dict, indices, repeats: int = 3, threads: int = 1, progress: bool = True) -> dict:
    """Time each gate's own decision on `indices` (batch 1): `gates` {name: gate} with `predict(features,
    metas)` (a learned HydraFusion gate or EcoFusion configuration gate: pooling of the stem features
    and its network; the stems themselves are the stems' time, `EcoEval.gate_overhead`). Per gate: the
    median over frames of each frame's median of `repeats` runs after one warm-up, the 25th and 75th
    percentiles over frames, with the load average before and after (the machine's other work).
    Written to RUN/eco/gate_latency.json and returned."""
    import torch

    from fusion.data import FrameDataset, collate
    from study.engine.scoring import load_run

    torch.set_num_threads(threads)
    model, _cfg = load_run(run_dir)
    ds = FrameDataset(data, list(indices), sensors=model.sensors, bev_size=model.transform.image_size("radar"))
    timed = _timer(None, repeats)
    load_before = os.getloadavg()
    per: dict = defaultdict(list)
    bar = progress_bar(total=len(ds), desc="gate latency", enabled=progress)
    with torch.no_grad():
        for k in range(len(ds)):
            inputs, _t, metas = collate([ds[k]])
            feats = model.extract_features(inputs)
            for name, gate in gates.items():
                gate.eval()
                per[name].append(timed(lambda g=gate, f=feats, m=metas: g.predict(f, m))[0])
            bar.update(1)
    bar.close()
    out = {"frames": len(ds), "repeats": repeats, "threads": threads, "machine": machine_description(threads),
           "load_average_before": [round(x, 2) for x in load_before],
           "load_average_after": [round(x, 2) for x in os.getloadavg()],
           "gates": {n: {"median_ms": round(1000 * float(np.median(v)), 3),
                         "p25_ms": round(1000 * float(np.percentile(v, 25)), 3),
                         "p75_ms": round(1000 * float(np.percentile(v, 75)), 3)} for n, v in per.items()}}
    write_json_atomic(Path(run_dir) / "eco" / GATE_LATENCY, out)
    return out


def read_gate_latency(run_dir) -> dict:
    """{gate name ("hydrafusion:deep", "ecofusion:attention"): seconds} of RUN/eco/gate_latency.json
    ({} when the gates' own time was not measured)."""
    path = Path(run_dir) / "eco" / GATE_LATENCY
    if not path.is_file():
        return {}
    return {n: v["median_ms"] / 1000 for n, v in json.loads(path.read_text())["gates"].items()}
