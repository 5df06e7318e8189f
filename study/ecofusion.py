"""EcoFusion on a trained run (EcoFusion, DAC 2022): the configuration dataset, the configuration
gates, measured latency and energy, the joint optimisation, and Tables 1-3 / Figures 4-5.

**Configuration dataset** (`EcoData`, the gate dataset of `study.gates.GateData` with more per-frame
arrays): for every frame, the pooled stem features (what the learned gates read), each branch's
detections (every branch runs once per frame, in its own frame), and for every configuration phi
of the set Phi (`fusion.eco.configurations`) the parts of the fused loss L_f(phi)
(`fusion.eco.loss`) and the frame's VOC AP@0.5 of the fused detections. Subsets are fused
afterwards from the branches' detections: a branch's output depends only on its own sensors'
stem features, never on which other branches run, so this equals executing each configuration
(tested). Cached under `RUN/eco_data/<key>/` (key: checkpoint, dataset, configurations, fusion
method, loss definition), written in chunks atomically; interrupted, it continues.

**Latency and energy** (`measure_latency`, Eq. 6): each stem, branch and the fusion block are
timed on real frames at batch 1; a configuration's latency is the sum of its stems (each once),
its branches and the fusion block; that sum is checked against configurations timed end to end.
Energy is measured where a counter exists (RAPL on a CPU, NVML on an NVIDIA GPU), else modelled as
P x t with a stated P (the PX2's 45.4 W by default). Cached in `RUN/eco/latency.json` per machine,
thread count and checkpoint.

**Gates** (`train_eco_gate`): the deep and attention configuration gates regress L_f of every
configuration from the pooled stem features, with mean absolute error and Adam at lr 5e-5 on the
run's train split (`study.gates.fit_gate`), saved in `RUN/eco/gates/<gate>/`.

**Evaluation** (`evaluate_eco`, `sweep`): on the run's test split, each gate's predictions go
through the joint optimisation (Eq. 7-9, `fusion.eco.optimise`) at lambda_E and gamma; the chosen
configuration of each frame is fused and scored: mAP@0.5 (right camera, difficult boxes ignored),
mean actual L_f, mean energy and latency of the chosen configurations, sensor energy with clock
gating (Eq. 10-11) per scene.
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from sim.errors import UserError
from study.gates import (
    GateData,
    GateTrainConfig,
    _atomic_text,
    _atomic_torch_save,
    _bar,
    _predict,
    cached_sha256,
    checkpoint_path,
    fit_gate,
    mae,
    validation_split,
)

ECO_DATA_VERSION = 1
LATENCY_VERSION = 1
GATE_ORDER = ("knowledge", "deep", "attention", "loss_based")
FEATURE_GATES = ("deep", "attention")
"""Gates that read the stems' features, so every stem they read runs before they decide."""
TABLE1_LAMBDAS = (0.0, 0.01, 0.05)
TABLE2_LAMBDAS = (0.0, 0.01, 0.1)
SWEEP_LAMBDAS = (0.0, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 1.0)
FIG5_BASELINES = ("none_radar", "early", "late")
METRIC = "VOC all-point AP at IoU 0.5, right camera, difficult ground truth ignored"


# ----- the configuration dataset ---------------------------------------------------------------


def detections_array(per: dict, branches, max_det: int) -> np.ndarray:
    """{branch: Detections} -> (n_branches, max_det, 6) float64 [x1, y1, x2, y2, score, label];
    padding rows have label 0."""
    out = np.zeros((len(branches), max_det, 6))
    for j, b in enumerate(branches):
        d = per.get(b)
        if d is None or not len(d):
            continue
        n = min(len(d), max_det)
        out[j, :n, :4], out[j, :n, 4], out[j, :n, 5] = d.boxes[:n], d.scores[:n], d.labels[:n]
    return out


def detections_from_array(a: np.ndarray, branches) -> dict:
    """Inverse of `detections_array`."""
    from fusion.late import Detections

    out = {}
    for j, b in enumerate(branches):
        keep = a[j, :, 5] > 0
        out[b] = Detections(a[j, keep, :4].copy(), a[j, keep, 4].copy(), a[j, keep, 5].astype(np.int64))
    return out


def frame_ap(det, gt) -> float:
    """VOC AP@0.5 of one frame's detections (mean over the classes with non-difficult ground
    truth in the frame; NaN when it has none)."""
    from fusion.metrics import evaluate_detections
    from sim.actors import CLASSES

    res = evaluate_detections([{"boxes": det.boxes, "scores": det.scores, "labels": det.labels}], [gt],
                              classes=range(1, len(CLASSES) + 1))
    return float(res.mean_ap)


class EcoData(GateData):
    """Per frame: pooled stem features, every branch's detections, and L_f parts and AP of every
    configuration (module docstring). Arrays: "features" (n, C, rows, cols) float16,
    "detections" (n, n_branches, max_det, 6), "terms" (n, n_configurations, len(TERMS)),
    "ap" (n, n_configurations) (NaN for frames without non-difficult ground truth)."""

    subdir = "eco_data"

    def __init__(self, run_dir, data, model, configurations, fusion: str = "soft_nms", loss_spec=None,
                 checkpoint: str = "latest", grid=None) -> None:
        from fusion.eco.loss import FusedLossSpec
        from sensors.dataset import DatasetReader

        self.configurations = configurations
        self.fusion = fusion
        self.loss_spec = loss_spec or FusedLossSpec()
        prof = getattr(model, "profile", None)
        self.max_det = int(prof.box_detections_per_img) if prof is not None else 100
        self.reader = DatasetReader(data)
        super().__init__(run_dir, data, model, checkpoint, grid)

    def extra_identity(self) -> dict:
        return {"eco_version": ECO_DATA_VERSION, "configurations": [list(m) for m in self.configurations.members],
                "fusion": self.fusion, "loss": dataclasses.asdict(self.loss_spec), "max_detections": self.max_det,
                "ground_truth": "study.detect.ground_truth camera_right"}

    def compute(self, model, inputs, targets, metas, features) -> dict[str, np.ndarray]:
        from fusion.eco.loss import loss_terms
        from fusion.late import fuse, to_reference
        from sensors.rig import Calibration
        from study.detect import ground_truth, to_detections

        frames = model.branch_frames
        dets = model(inputs, selection=list(self.branches))
        det_arr, terms, aps = [], [], []
        for meta, per in zip(metas, dets):
            per = {n: to_detections(d) for n, d in per.items()}
            a = detections_array(per, self.branches, self.max_det)
            det_arr.append(a)
            per = detections_from_array(a, self.branches)  # exactly what the cache gives back
            calib = Calibration.from_dict(meta["calibration"])
            mapped = {n: to_reference(d, frames[n], calib) for n, d in per.items()}
            ref = dict.fromkeys(mapped, "camera_right")
            gt = ground_truth(self.reader.labels(meta["dataset_index"]), "camera_right", None, meta, self.protocol)
            t_row, ap_row = [], []
            for members in self.configurations.members:
                f = fuse({n: mapped[n] for n in members}, ref, calib, method=self.fusion)
                t_row.append(loss_terms(f.boxes, f.scores, f.labels, gt["boxes"], gt["labels"], gt["difficult"],
                                        self.loss_spec))
                ap_row.append(frame_ap(f, gt))
            terms.append(t_row)
            aps.append(ap_row)
        return {"detections": np.asarray(det_arr), "terms": np.asarray(terms), "ap": np.asarray(aps)}

    def losses(self, indices) -> np.ndarray:
        """(n, n_configurations) L_f of each frame and configuration."""
        return self.loss_spec.combine(self.arrays(indices, ["terms"])["terms"])


def fuse_choice(per_frame_dets, metas, branches, frames, chosen_members, method, memo=None) -> list:
    """[(meta, fused Detections)] for each frame's chosen configuration (branch tuple), memoised
    on (frame position, configuration)."""
    from fusion.late import fuse
    from sensors.rig import Calibration

    memo = {} if memo is None else memo
    out = []
    for k, (meta, per, members) in enumerate(zip(metas, per_frame_dets, chosen_members)):
        key = (k, members)
        if key not in memo:
            memo[key] = fuse({n: per[n] for n in members}, frames, Calibration.from_dict(meta["calibration"]),
                             method=method)
        out.append((meta, memo[key]))
    return out


# ----- loss vs AP ---------------------------------------------------------------------------


LOSS_VARIANTS = {
    "default": {},
    "no_false_positive_term": {"fp_weight": 0.0},
    "no_miss_term": {"miss_cost": 0.0},
    "no_box_term": {"box_weight": 0.0},
    "miss_cost_1": {"miss_cost": 1.0},
    "first_definition_miss_3.0": {"miss_cost": 2.995732},  # -ln 0.05: a found object could cost more than a miss
}
"""L_f variants whose ranking of configurations is compared with AP (eco-data's report)."""


def rank_correlation(losses: np.ndarray, ap: np.ndarray) -> dict:
    """Per-frame rank correlation across configurations between L_f and the frame's AP (lower
    loss should mean higher AP: a negative correlation). Frames without ground truth or with the
    same AP for every configuration are skipped. Returns mean / median Spearman rho and Kendall
    tau (scipy.stats, tau-b), and the share of frames where the lowest-loss configuration has the
    frame's best AP."""
    from scipy.stats import kendalltau, spearmanr

    rho, tau, top = [], [], []
    for lo, a in zip(losses, ap):
        if np.isnan(a).any() or np.ptp(a) == 0 or np.ptp(lo) == 0:
            continue
        rho.append(spearmanr(lo, a).statistic)
        tau.append(kendalltau(lo, a).statistic)
        top.append(a[np.argmin(lo)] >= a.max() - 1e-9)
    if not rho:
        return {"frames": 0, "spearman_mean": None, "spearman_median": None, "kendall_mean": None,
                "kendall_median": None, "lowest_loss_has_best_ap": None}
    return {"frames": len(rho), "spearman_mean": round(float(np.mean(rho)), 4),
            "spearman_median": round(float(np.median(rho)), 4), "kendall_mean": round(float(np.mean(tau)), 4),
            "kendall_median": round(float(np.median(tau)), 4),
            "lowest_loss_has_best_ap": round(float(np.mean(top)), 4)}


# ----- settings shared by the commands -------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class EcoSettings:
    """What identifies a configuration dataset and how energy is put on the lambda_E scale.

    Fields:
        configurations: YAML file of `fusion.eco.configurations.ConfigurationsConfig` ("" = every subset).
        fusion: late-fusion method of the configurations (nms, soft-nms, wbf).
        checkpoint: the run's checkpoint ("latest" or "epoch-NNN").
        power: "px2" (45.4 W) or watts: P of Eq. 6 where no energy counter exists.
        energy_scale: "px2" (E / E_late x 3.798 J), "late" (E / E_late) or "joules" (`fusion.eco.optimise`).
        rule: candidate rule of Eq. 7, "prose" or "equation".
        batch_size: frames per forward when building the dataset.
        max_frames: at most this many frames of each split (evenly spaced over the split, so every
            context keeps its share); 0 = every frame. For machines where a forward of every
            branch on every frame takes too long; results say how many frames they are on.
    """

    configurations: str = ""
    fusion: str = "soft-nms"
    checkpoint: str = "latest"
    power: str = "px2"
    energy_scale: str = "px2"
    rule: str = "prose"
    batch_size: int = 4
    max_frames: int = 0


def _setup(run_dir, data, s: EcoSettings, threads: int = 2):
    import torch

    from fusion.eco.configurations import build_configurations, load_configurations_config
    from fusion.nets.gates import gate_sensors
    from study.detect import fusion_method, load_run

    torch.set_num_threads(threads)
    method = fusion_method(s.fusion)
    model, cfg = load_run(run_dir, s.checkpoint)
    if not gate_sensors(model):
        raise UserError("EcoFusion's learned gates read the shared stems; this run's branches have none")
    ccfg = load_configurations_config(s.configurations or None)
    configs = build_configurations(model.branch_sensors, ccfg)
    ed = EcoData(run_dir, data, model, configs, method, checkpoint=s.checkpoint)
    return model, cfg, configs, ed


def _subsample(indices: list[int], n: int) -> list[int]:
    """At most n of `indices`, evenly spaced (indices are in dataset order, grouped by sequence)."""
    if not n or len(indices) <= n:
        return list(indices)
    return [indices[int(k)] for k in np.linspace(0, len(indices) - 1, n).round().astype(int)]


def _splits(cfg, data, max_frames: int = 0) -> tuple[list[int], list[int]]:
    from study.detect import run_train_test

    train, test = run_train_test(cfg, data, "EcoFusion")
    return _subsample(train, max_frames), _subsample(test, max_frames)


def build_eco_data(run_dir, data, s: EcoSettings = EcoSettings(), progress: bool = True) -> dict:
    """`hydrabench eco-data`: build (or complete) the configuration dataset and report how well
    L_f ranks configurations by per-frame AP (rank correlation, per definition variant)."""
    from fusion.eco.loss import FusedLossSpec

    run_dir, data = Path(run_dir), Path(data)
    model, cfg, configs, ed = _setup(run_dir, data, s)
    train, test = _splits(cfg, data, s.max_frames)
    t0 = time.perf_counter()
    computed = ed.ensure(train + test, batch_size=s.batch_size, progress=progress)
    seconds = time.perf_counter() - t0
    arr = ed.arrays(test, ["terms", "ap"])
    corr = {}
    for name, kw in LOSS_VARIANTS.items():
        spec = dataclasses.replace(FusedLossSpec(), **kw)
        corr[name] = rank_correlation(spec.combine(arr["terms"]), arr["ap"])
    lf = ed.loss_spec.combine(arr["terms"])
    return {
        "run": str(run_dir), "data": str(data), "eco_data": str(ed.dir), "configurations": len(configs),
        "baselines": {k: configs.names[v] for k, v in configs.baselines.items()},
        "frames": {"train": len(train), "test": len(test)}, "computed_frames": computed,
        "seconds": round(seconds, 1), "fusion": ed.fusion, "loss_definition": dataclasses.asdict(ed.loss_spec),
        "loss_vs_ap_test": corr,
        "mean_loss_test": {configs.names[i]: round(float(lf[:, i].mean()), 4) for i in configs.baselines.values()},
        "note": "rank correlation per frame across configurations between L_f and the frame's AP@0.5 "
                "(negative = lower loss ranks higher AP), then averaged over frames",
    }


# ----- latency and energy ---------------------------------------------------------------------


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
    from study.detect import to_detections

    torch.set_num_threads(threads)
    ctr = open_counter(counter, "cpu")
    ds = FrameDataset(data, indices, sensors=model.sensors, bev_size=model.transform.image_size("radar"))
    frames = model.branch_frames
    stems_s, branch_s, fusion_s = defaultdict(list), defaultdict(list), defaultdict(list)
    energy = defaultdict(list) if ctr is not None else None
    direct_t, direct_e = defaultdict(list), defaultdict(list)
    rng = np.random.default_rng(seed)
    members = list(configs.members)
    first = [configs.members[configs.baselines["late"]]] if "late" in configs.baselines else []
    if tuple(configs.branches) in members:
        first.append(tuple(configs.branches))
    first += [configs.members[i] for i in configs.baselines.values()]
    first = list(dict.fromkeys(first))
    others = [m for m in members if m not in first]
    extra = [others[i] for i in rng.permutation(len(others))] if others else []
    checked = (first + extra)[:max(check, 1)]
    shared = [s for s in model.sensors if SENSORS[s].stem in model.stems]
    by_n = defaultdict(list)
    for m in members:
        by_n[len(m)].append(m)

    def timed(fn):
        """(median seconds, mean joules or None) of `repeats` calls after one warm-up."""
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

    def record(key, table, value):
        t, e = value
        table.append(t)
        if energy is not None:
            energy[key].append(e)

    bar = _bar(len(indices), "latency", progress)
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
                        "machine": machine_description(threads), "method": method})
    rows = {}
    for m in checked:
        pred, meas = lat.latency(m), float(np.mean(direct_t[m]))
        rows["+".join(m)] = {"measured_ms": round(1000 * meas, 2), "additive_ms": round(1000 * pred, 2),
                             "relative_error": round((pred - meas) / meas, 4)}
        if direct_e.get(m):
            rows["+".join(m)].update(measured_j=round(float(np.mean(direct_e[m])), 4),
                                     additive_j=round(lat.measured_energy(m), 4))
    errs = [abs(r["relative_error"]) for r in rows.values()]
    check_out = {"configurations": rows, "mean_abs_relative_error": round(float(np.mean(errs)), 4),
                 "max_abs_relative_error": round(float(np.max(errs)), 4)}
    return lat, check_out


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
    from study.detect import fusion_method

    run_dir, data = Path(run_dir), Path(data)
    if model is None:
        model, cfg, configs, _ed = _setup(run_dir, data, s, threads)
        _train, test = _splits(cfg, data, s.max_frames)
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
        _atomic_text(path, json.dumps({"identity": ident, "model": lat.to_dict(), "check": check}, indent=1))
    t, e, source = configuration_energy(lat, configs.members, power)
    base = {k: {"configuration": configs.names[i], "latency_ms": round(1000 * t[i], 2), "energy_j": round(e[i], 4)}
            for k, i in configs.baselines.items()}
    return {"latency_model": {"stems_ms": {k: round(1000 * v, 2) for k, v in lat.stems.items()},
                              "branches_ms": {k: round(1000 * v, 2) for k, v in lat.branches.items()},
                              "fusion_ms": {str(k): round(1000 * v, 3) for k, v in lat.fusion.items()}},
            "additive_check": check, "baselines": base, "energy_source": source, "machine": lat.meta.get("machine"),
            "latency_cache": str(path), "_model": lat, "_t": t, "_e": e}


# ----- gates ----------------------------------------------------------------------------------


def train_eco_gate(run_dir, data, gate: str, cfg: GateTrainConfig, s: EcoSettings = EcoSettings(),
                   progress: bool = True, fresh: bool = False) -> dict:
    """`hydrabench eco-train-gate`: the deep or attention configuration gate, regressing L_f of
    every configuration (mean absolute error, Adam), on the run's train split; saved in
    RUN/eco/gates/<gate>/ (resumable, like train-gate)."""
    import torch

    from fusion.eco.gates import CONFIG_GATES, build_config_gate
    from sensors.dataset import DatasetReader

    cls = CONFIG_GATES.get(gate)
    if not cls.trainable:
        raise UserError(f"--gate {gate}: nothing to train (train deep or attention)")
    run_dir, data = Path(run_dir), Path(data)
    model, run_cfg, configs, ed = _setup(run_dir, data, s, cfg.threads)
    train, test = _splits(run_cfg, data, s.max_frames)
    ed.ensure(train + test, batch_size=s.batch_size, progress=progress)
    out = run_dir / "eco" / "gates" / gate
    settings = {**dataclasses.asdict(cfg), "gate": gate, "data_key": ed.key}
    for k in ("epochs", "threads"):
        settings.pop(k)
    state = None
    if (out / "checkpoint.pt").exists() and not fresh:
        state = torch.load(out / "checkpoint.pt", map_location="cpu", weights_only=False)
        old = {**state["config"], "gate": gate, "data_key": state.get("data_key")}
        for k in ("epochs", "threads"):
            old.pop(k, None)
        if json.loads(json.dumps(old)) != json.loads(json.dumps(settings)):
            diff = sorted(k for k in settings if json.loads(json.dumps(old.get(k))) != json.loads(json.dumps(settings[k])))
            raise UserError(f"{out} holds a {gate} gate trained with other settings or data ({', '.join(diff)}); "
                            "pass --fresh to train it again")
        if progress:
            sys.stderr.write(f"resuming {out} at epoch {state['epoch'] + 1}\n")
    fit_idx, val_idx = validation_split(DatasetReader(data), train, cfg.val_fraction, cfg.seed)
    x_fit, x_val, x_test = (ed.arrays(i, ["features"])["features"] for i in (fit_idx, val_idx, test))
    y_fit, y_val, y_test = (ed.losses(i).astype(np.float32) for i in (fit_idx, val_idx, test))
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    g = build_config_gate(gate, model, configs, sensors=list(ed.sensors), **cfg.gate_options())
    cfg_named = dataclasses.replace(cfg, gate=gate)
    fitted = fit_gate(g.net, x_fit, y_fit, x_val, y_val, cfg_named, out=out, progress=progress, state=state,
                      extra={"data_key": ed.key})
    pred = _predict(g, x_test)
    mean_c = y_fit.mean(axis=0)
    from fusion.eco.optimise import select

    zero = np.zeros(len(configs))
    pick = select(pred, zero, 0.0, 0.0, "prose")
    result = {
        "gate": gate, "run": str(run_dir), "data": str(data), "configurations": len(configs), "optimizer": "Adam",
        "lr": cfg.lr, "loss": "mean absolute error of L_f per configuration", "epochs": cfg.epochs,
        "best_epoch": fitted["best_epoch"], "val_mae": fitted["best_val_mae"], "train_frames": len(fit_idx),
        "val_frames": len(val_idx), "test_frames": len(test), "test_mae": round(mae(pred, y_test), 6),
        "constant_mean_mae": round(mae(np.broadcast_to(mean_c, y_test.shape), y_test), 6),
        "test_loss_of_predicted_best": round(float(y_test[np.arange(len(test)), pick].mean()), 4),
        "test_loss_of_oracle_best": round(float(y_test.min(axis=1).mean()), 4),
        "test_loss_of_constant_best": round(float(y_test[:, int(np.argmin(mean_c))].mean()), 4),
        "gate_path": str(out / "gate.pt"), "eco_data": str(ed.dir),
    }
    _atomic_torch_save({"name": gate, "options": {**cfg.gate_options(), "sensors": list(ed.sensors)},
                        "configurations": [list(m) for m in configs.members], "state": g.state_dict(),
                        "data_key": ed.key, "result": result}, out / "gate.pt")
    _atomic_text(out / "result.json", json.dumps(result, indent=1))
    return result


def load_eco_gate(run_dir, name: str, model, configs, data_key: str):
    """A trained configuration gate from RUN/eco/gates/<name>/gate.pt (for this configuration dataset)."""
    import torch

    from fusion.eco.gates import build_config_gate

    path = Path(run_dir) / "eco" / "gates" / name / "gate.pt"
    if not path.exists():
        raise UserError(f"no trained {name} configuration gate in {run_dir} "
                        f"(run: hydrabench eco-train-gate {run_dir} DATA --gate {name})")
    saved = torch.load(path, map_location="cpu", weights_only=False)
    if saved.get("data_key") != data_key:
        raise UserError(f"{path} was trained on another configuration dataset (checkpoint, configurations, fusion "
                        f"or loss differ); train it again with --fresh")
    g = build_config_gate(name, model, configs, **saved["options"])
    g.load_state_dict(saved["state"])
    return g.eval()


# ----- evaluation -----------------------------------------------------------------------------


class EcoEval:
    """Everything one evaluation needs, loaded once: the test frames' cached arrays, the energy
    of each configuration, and each gate's predicted losses."""

    def __init__(self, run_dir, data, s: EcoSettings = EcoSettings(), gates=None, threads: int = 2,
                 latency_threads: int = 1, progress: bool = True) -> None:
        from fusion.eco.gates import build_config_gate
        from fusion.eco.optimise import normalise_energy
        from sensors.dataset import DatasetReader

        self.run_dir, self.data, self.s = Path(run_dir), Path(data), s
        self.model, cfg, self.configs, self.ed = _setup(self.run_dir, self.data, s, threads)
        train, self.test = _splits(cfg, self.data, s.max_frames)
        self.ed.ensure(train + self.test, batch_size=s.batch_size, progress=progress)
        self.reader = DatasetReader(self.data)
        self.metas = [self.reader.meta(i) for i in self.test]
        for i, m in zip(self.test, self.metas):
            m["dataset_index"] = int(i)
        arr = self.ed.arrays(self.test, ["features", "detections", "terms", "ap"])
        self.features = arr["features"]
        self.dets = [detections_from_array(a, self.ed.branches) for a in arr["detections"]]
        self.terms = arr["terms"]
        self.losses = self.ed.loss_spec.combine(self.terms)
        self.ap = arr["ap"]
        self.energy_info = energy_table(self.run_dir, self.data, s, threads=latency_threads, progress=progress,
                                        model=self.model, configs=self.configs, test=self.test, reuse=True)
        self.t, self.e_raw = self.energy_info.pop("_t"), self.energy_info.pop("_e")
        self.latency_model = self.energy_info.pop("_model")
        late = self.configs.baselines.get("late")
        ref = self.e_raw[late] if late is not None else self.e_raw.max()
        try:
            self.e = normalise_energy(self.e_raw, ref, s.energy_scale)
        except ValueError as exc:
            raise UserError(f"--energy-scale: {exc}") from None
        self.sensors = self.configs.sensors(self.model.branch_sensors)
        self.contexts = [m["context"] for m in self.metas]
        self.memo: dict = {}
        self.predicted: dict[str, np.ndarray] = {}
        for g in gates or GATE_ORDER:
            if g == "loss_based":
                self.predicted[g] = self.losses
            elif g == "knowledge":
                self.predicted[g] = build_config_gate(g, self.model, self.configs).predict(None, self.metas).numpy()
            else:
                gate = load_eco_gate(self.run_dir, g, self.model, self.configs, self.ed.key)
                self.predicted[g] = _predict(gate, self.features)

    def choose(self, gate: str, lambda_e: float, gamma: float) -> np.ndarray:
        from fusion.eco.optimise import select

        return select(self.predicted[gate], self.e, lambda_e, gamma, self.s.rule)

    def fixed(self, name: str) -> np.ndarray:
        return np.full(len(self.test), self.configs.index(name))

    def gate_overhead(self, choice: np.ndarray, gate: str | None):
        """(seconds, sensors) a gate adds to each frame's configuration: a gate reading stem features
        (deep, attention) runs every stem it reads before it decides, so the stems the chosen
        configuration does not need are extra time (and energy, at the configuration's own power),
        and every sensor it reads must measure (no clock gating for them). The knowledge gate
        decides from external context before any stem runs, and the loss-based oracle is
        a-posteriori: neither adds anything. The gate network's own few small convolutions are not
        counted."""
        if gate not in FEATURE_GATES:
            return np.zeros(len(choice)), [set() for _ in choice]
        from fusion.nets.gates import gate_sensors

        read = set(gate_sensors(self.model))
        stems = self.latency_model.stems
        extra = np.array([sum(stems.get(x, 0.0) for x in read - set(self.sensors[c])) for c in choice])
        return extra, [read for _ in choice]

    def metrics(self, choice: np.ndarray, per_scene: bool = False, gate: str | None = None) -> dict:
        """mAP, mean actual L_f, energy and latency of per-frame configuration choices; with `gate`,
        the energy and latency include what that gate costs to decide (`gate_overhead`)."""
        from fusion.eco.energy import total_energy
        from study.detect import fusion_method, score

        members = [self.configs.members[i] for i in choice]
        fused = fuse_choice(self.dets, self.metas, self.ed.branches, self.model.branch_frames, members,
                            fusion_method(self.s.fusion), self.memo)
        sc = score(fused, self.reader, "camera_right", protocol=self.ed.protocol)
        rows = np.arange(len(choice))
        lf = self.losses[rows, choice]
        extra, read = self.gate_overhead(choice, gate)
        t = self.t[choice] + extra
        scale = t / self.t[choice]  # E = P t at the configuration's own power
        e, e_raw = self.e[choice] * scale, self.e_raw[choice] * scale
        out = {"map": sc["map"], "map_vehicles": sc["map_vehicles"], "avg_loss": round(float(lf.mean()), 4),
               "energy": round(float(e.mean()), 4),
               "energy_j": round(float(e_raw.mean()), 4),
               "latency_ms": round(1000 * float(t.mean()), 2),
               "gate_stems_ms": round(1000 * float(extra.mean()), 2),
               "mean_branches": round(float(np.mean([len(m) for m in members])), 3)}
        if per_scene:
            measuring = [sorted(set(self.sensors[c]) | r) for c, r in zip(choice, read)]
            sensor_e = np.array([total_energy(ek, ms, "clock") for ek, ms in zip(e, measuring)])
            sensor_off = np.array([total_energy(ek, ms, "off") for ek, ms in zip(e, measuring)])
            scenes = {}
            for ctx in sorted(set(self.contexts)):
                k = np.array([c == ctx for c in self.contexts])
                scenes[ctx] = {"frames": int(k.sum()), "avg_loss": round(float(lf[k].mean()), 4),
                               "energy": round(float(e[k].mean()), 4),
                               "energy_clock_gated": round(float(sensor_e[k].mean()), 4),
                               "energy_all_sensors_on": round(float(sensor_off[k].mean()), 4),
                               "map": sc["map_per_context"].get(ctx)}
            out["per_scene"] = scenes
            out["energy_clock_gated"] = round(float(sensor_e.mean()), 4)
            out["energy_all_sensors_on"] = round(float(sensor_off.mean()), 4)
        return out

    def selection_counts(self, choice: np.ndarray, top: int = 5) -> dict:
        names, counts = np.unique(choice, return_counts=True)
        order = np.argsort(-counts)[:top]
        return {self.configs.names[names[i]]: round(100.0 * counts[i] / len(choice), 1) for i in order}

    def energy_label(self) -> str:
        scale = {"px2": "PX2-equivalent J: E / E(late) x 3.798 J (EcoFusion Table 1's late fusion)",
                 "late": "E / E(late), dimensionless", "joules": "J on this machine"}[self.s.energy_scale]
        return f"{scale}; E from {self.energy_info['energy_source']}"


def evaluate_eco(run_dir, data, lambda_e: float = 0.01, gamma: float = 0.5, s: EcoSettings = EcoSettings(),
                 gates=None, progress: bool = True, ev: EcoEval | None = None) -> dict:
    """`hydrabench eco-evaluate`: every gate at one lambda_E and gamma against the fixed baselines
    and the oracle (regret = gate minus loss-based, in mean joint loss and mean L_f)."""
    from fusion.eco.optimise import joint_loss

    ev = ev or EcoEval(run_dir, data, s, gates, progress=progress)
    rows, base = {}, {}
    joint = {}
    for g in ev.predicted:
        ch = ev.choose(g, lambda_e, gamma)
        rows[g] = {**ev.metrics(ch, per_scene=True, gate=g), "selected": ev.selection_counts(ch)}
        joint[g] = float(joint_loss(ev.losses[np.arange(len(ch)), ch], ev.e[ch], lambda_e).mean())
        rows[g]["avg_joint_loss"] = round(joint[g], 4)
    for name in ev.configs.baselines:
        ch = ev.fixed(name)
        base[name] = {**ev.metrics(ch, per_scene=True), "configuration": ev.configs.names[ch[0]]}
        base[name]["avg_joint_loss"] = round(float(joint_loss(ev.losses[:, ch[0]], ev.e[ch[0]], lambda_e).mean()), 4)
    if "loss_based" in rows:
        for g in rows:
            rows[g]["regret_joint_loss"] = round(joint[g] - joint["loss_based"], 4)
            rows[g]["regret_avg_loss"] = round(rows[g]["avg_loss"] - rows["loss_based"]["avg_loss"], 4)
    late = base.get("late")
    ratios = {}
    if late:
        for g, r in rows.items():
            ratios[g] = {"map_minus_late": None if r["map"] is None or late["map"] is None
                         else round(r["map"] - late["map"], 4),
                         "energy_ratio": round(r["energy"] / late["energy"], 4),
                         "latency_ratio": round(r["latency_ms"] / late["latency_ms"], 4)}
    return {"lambda_e": lambda_e, "gamma": gamma, "rule": s.rule, "gates": rows, "baselines": base,
            "against_late": ratios, "frames": len(ev.test), "configurations": len(ev.configs),
            "energy_unit": ev.energy_label(), "latency": "additive model of measured component latencies, "
            "this machine", "metric": METRIC, "run": str(run_dir), "data": str(data)}


def sweep(run_dir, data, out: Path, gamma: float = 0.5, lambdas=SWEEP_LAMBDAS, s: EcoSettings = EcoSettings(),
          gates=None, fig_gate: str = "attention", progress: bool = True, ev: EcoEval | None = None) -> dict:
    """`hydrabench eco-sweep`: Tables 1-3 and Figures 4-5 (see README). `ev`: an `EcoEval` of the
    same run, data and settings already loaded (the study's evaluation reuses it)."""
    from fusion.eco.energy import SENSOR_DEVICES, sensor_energy
    from fusion.eco.optimise import pareto_front

    ev = ev or EcoEval(run_dir, data, s, gates, progress=progress)
    gates = list(ev.predicted)
    eco_gate = fig_gate if fig_gate in gates else gates[0]
    lambdas = sorted(set(lambdas) | set(TABLE1_LAMBDAS) | set(TABLE2_LAMBDAS))
    curve = {g: {} for g in gates}
    bar = _bar(len(gates) * len(lambdas), "sweep", progress)
    for g in gates:
        for lam in lambdas:
            ch = ev.choose(g, lam, gamma)
            curve[g][lam] = {**ev.metrics(ch, per_scene=(lam == 0.01), gate=g), "selected": ev.selection_counts(ch, 3)}
            bar.update(1)
    bar.close()
    base = {name: {**ev.metrics(ev.fixed(name), per_scene=True), "configuration": ev.configs.names[i]}
            for name, i in ev.configs.baselines.items()}
    table1 = {name: {k: base[name][k] for k in ("configuration", "map", "energy", "energy_j", "latency_ms")}
              for name in base}
    for lam in TABLE1_LAMBDAS:
        table1[f"ecofusion_{eco_gate}_lambda_{lam:g}"] = {k: curve[eco_gate][lam][k]
                                                         for k in ("map", "energy", "energy_j", "latency_ms")}
    table2 = {f"{lam:g}": {g: {k: curve[g][lam][k] for k in ("map", "avg_loss", "energy")} for g in gates}
              for lam in TABLE2_LAMBDAS}
    # Table 3: sensors clock-gated per scene, knowledge gate (the paper's choice: external context) and
    # the figure's gate at lambda_E 0.01, against late fusion with every sensor measuring
    late = base.get("late")
    table3 = {}
    if late:
        for label, src in (("late_fusion", late), *((f"ecofusion_{g}", curve[g][0.01]) for g in
                                                    dict.fromkeys(("knowledge", eco_gate)) if g in curve)):
            key = "energy_all_sensors_on" if label == "late_fusion" else "energy_clock_gated"
            table3[label] = {ctx: v[key] for ctx, v in src["per_scene"].items()}
            table3[label]["overall"] = src[key]
        for label in [k for k in table3 if k != "late_fusion"]:
            table3[f"{label}_savings_pct"] = {ctx: round(100 * (1 - table3[label][ctx] / table3["late_fusion"][ctx]), 2)
                                             for ctx in table3[label]}
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    fig4 = out / "figure4_loss_energy.png"
    fig5 = out / "figure5_scenes.png"
    fronts = {g: [lambdas[i] for i in pareto_front([curve[g][lam]["avg_loss"] for lam in lambdas],
                                                  [curve[g][lam]["energy"] for lam in lambdas])] for g in gates}
    plot_figure4(curve, lambdas, fronts, base, fig4, ev.energy_label())
    scenes = {name: base[name]["per_scene"] for name in FIG5_BASELINES if name in base}
    scenes[f"ecofusion_{eco_gate}"] = curve[eco_gate][0.01]["per_scene"]
    plot_figure5(scenes, fig5, ev.energy_label())
    result = {
        "table1": table1, "table2": table2, "table3": table3,
        "table3_sensor_model": {k: {"power_w": d.power_w, "motor_w": d.motor_w, "rate_hz": d.rate_hz,
                                    "energy_measuring_j": round(sensor_energy(d, True), 4),
                                    "energy_clock_gated_j": round(sensor_energy(d, False), 4), "source": d.source}
                                for k, d in SENSOR_DEVICES.items()},
        "figure4": {g: {f"{lam:g}": {k: curve[g][lam][k] for k in ("avg_loss", "energy", "map")} for lam in lambdas}
                    for g in gates},
        "pareto_lambdas": {g: [f"{x:g}" for x in v] for g, v in fronts.items()},
        "curve": {g: {f"{lam:g}": {k: v for k, v in curve[g][lam].items() if k != "per_scene"} for lam in lambdas}
                  for g in gates},
        "figures": [str(fig4), str(fig5)], "gamma": gamma, "rule": s.rule, "figure_gate": eco_gate,
        "energy_unit": ev.energy_label(), "additive_check": ev.energy_info["additive_check"],
        "frames": len(ev.test), "configurations": len(ev.configs), "metric": METRIC,
        "run": str(run_dir), "data": str(data),
    }
    _atomic_text(out / "result.json", json.dumps(result, indent=1))
    return result


def plot_figure4(curve, lambdas, fronts, base, path: Path, energy_label: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    from study.outputs import savefig_atomic

    gates = list(curve)
    fig, axes = plt.subplots(1, len(gates), figsize=(4.2 * len(gates), 4.0), sharex=True, sharey=True, squeeze=False)
    norm = LogNorm(vmin=min(x for x in lambdas if x > 0), vmax=max(lambdas))
    sc = None
    for ax, g in zip(axes[0], gates):
        e = [curve[g][lam]["energy"] for lam in lambdas]
        lo = [curve[g][lam]["avg_loss"] for lam in lambdas]
        col = [max(lam, norm.vmin) for lam in lambdas]
        sc = ax.scatter(e, lo, c=col, cmap="viridis", norm=norm, s=40, zorder=3, edgecolors="k", linewidths=0.4)
        fe = [curve[g][lam]["energy"] for lam in fronts[g]]
        fl = [curve[g][lam]["avg_loss"] for lam in fronts[g]]
        ax.step(fe, fl, where="post", color="crimson", lw=1.2, zorder=2, label="Pareto front")
        for name, marker in (("late", "s"), ("early", "^"), ("none_radar", "v"), ("none_camera_right", "o")):
            if name in base:
                ax.scatter(base[name]["energy"], base[name]["avg_loss"], marker=marker, facecolors="none",
                           edgecolors="gray", s=50, label=name, zorder=1)
        ax.set_title(g)
        ax.set_xlabel(f"mean energy [{energy_label.split(';')[0].split(':')[0]}]")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("mean fused loss L_f (test frames)")
    axes[0][0].legend(fontsize=7, loc="best")
    cb = fig.colorbar(sc, ax=axes[0].tolist(), shrink=0.9)
    cb.set_label("lambda_E (0 drawn at the lowest value)")
    fig.suptitle("EcoFusion Figure 4 analogue: loss against energy per gate, lambda_E colour-coded", fontsize=10)
    savefig_atomic(fig, path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def plot_figure5(scenes: dict, path: Path, energy_label: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from study.outputs import savefig_atomic

    methods = list(scenes)
    ctxs = sorted({c for v in scenes.values() for c in v})
    fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    w = 0.8 / len(methods)
    x = np.arange(len(ctxs))
    for k, m in enumerate(methods):
        axes[0].bar(x + k * w, [scenes[m].get(c, {}).get("avg_loss", np.nan) for c in ctxs], w, label=m)
        axes[1].bar(x + k * w, [scenes[m].get(c, {}).get("energy", np.nan) for c in ctxs], w, label=m)
    axes[0].set_ylabel("mean fused loss L_f")
    axes[1].set_ylabel(f"mean energy\n[{energy_label.split(';')[0].split(':')[0]}]")
    axes[1].set_xticks(x + w * (len(methods) - 1) / 2, ctxs)
    axes[0].legend(fontsize=8, ncol=len(methods))
    for ax in axes:
        ax.grid(alpha=0.3, axis="y")
    fig.suptitle("EcoFusion Figure 5 analogue: loss and energy per scene (test frames)", fontsize=10)
    savefig_atomic(fig, path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def execute_ecofusion(run_dir, data, gate: str, lambda_e: float, gamma: float, s: EcoSettings = EcoSettings(),
                      frames: int = 0, progress: bool = True, ev: EcoEval | None = None) -> dict:
    """EcoFusion executed: the gate and the joint optimisation wired into the network
    (`EcoFusionSelector` as `model.gate`), so per frame only the chosen configuration's branches
    and the stems they need run (the knowledge gate reads no stem before deciding). Counts stem and
    branch calls, times each frame end to end (fusion included) and checks the fused detections
    against the offline selection from the configuration dataset."""
    import torch

    from fusion.data import FrameDataset, collate
    from fusion.eco.gates import EcoFusionSelector, build_config_gate
    from fusion.late import fuse
    from sensors.rig import Calibration
    from study.detect import fusion_method, to_detections

    ev = ev or EcoEval(run_dir, data, s, [gate], progress=progress)
    model = ev.model
    if gate == "knowledge":
        g = build_config_gate(gate, model, ev.configs)
    elif gate == "loss_based":
        g = build_config_gate(gate, model, ev.configs)
    else:
        g = load_eco_gate(run_dir, gate, model, ev.configs, ev.ed.key)
    selector = EcoFusionSelector(g, ev.e, lambda_e, gamma, s.rule)
    idx = list(range(len(ev.test)))[: frames or None]
    ds = FrameDataset(data, [ev.test[i] for i in idx], sensors=model.sensors,
                      bev_size=model.transform.image_size("radar"))
    calls = defaultdict(int)
    hooks = [m.register_forward_hook(lambda mod, a, o, n=f"stem:{n}": calls.__setitem__(n, calls[n] + 1))
             for n, m in model.stems.items()]
    hooks += [m.register_forward_hook(lambda mod, a, o, n=f"branch:{n}": calls.__setitem__(n, calls[n] + 1))
              for n, m in model.branches.items()]
    method = fusion_method(s.fusion)
    offline = ev.choose(gate, lambda_e, gamma)
    times, agree, same = [], 0, 0
    model.gate = selector
    try:
        with torch.no_grad():
            bar = _bar(len(idx), f"execute {gate}", progress)
            for k, pos in enumerate(idx):
                inputs, _t, metas = collate([ds[k]])
                if gate == "loss_based":
                    metas = [dict(metas[0], config_losses=ev.losses[pos])]
                t0 = time.perf_counter()
                dets = model(inputs, meta=metas)[0]
                fused = fuse({b: to_detections(d) for b, d in dets.items()}, model.branch_frames,
                             Calibration.from_dict(metas[0]["calibration"]), method=method)
                times.append(time.perf_counter() - t0)
                choice = int(selector.last_choice[0])
                agree += choice == int(offline[pos])
                ref = fuse_choice([ev.dets[pos]], [ev.metas[pos]], ev.ed.branches, model.branch_frames,
                                  [ev.configs.members[choice]], method)[0][1]
                same += bool(len(ref) == len(fused) and np.allclose(ref.boxes, fused.boxes, atol=1e-3)
                             and np.allclose(ref.scores, fused.scores, atol=1e-4))
                bar.update(1)
            bar.close()
    finally:
        model.gate = None
        for h in hooks:
            h.remove()
    n = len(idx)
    chosen = offline[idx]
    return {"gate": gate, "lambda_e": lambda_e, "gamma": gamma, "frames": n,
            "stem_runs_per_frame": {k.split(":", 1)[1]: round(v / n, 3) for k, v in calls.items() if k.startswith("stem:")},
            "branch_runs_per_frame": round(sum(v for k, v in calls.items() if k.startswith("branch:")) / n, 3),
            "mean_branches_chosen": round(float(np.mean([len(ev.configs.members[c]) for c in chosen])), 3),
            "measured_latency_ms": round(1000 * float(np.mean(times)), 2),
            "additive_latency_ms": round(1000 * float(ev.t[chosen].mean()), 2),
            "choice_equals_offline": round(agree / n, 4), "detections_equal_offline": round(same / n, 4)}
