"""EcoFusion's configuration dataset (`EcoData`: per frame, every branch's detections and the fused
loss L_f and AP of every configuration), the settings that identify it (`EcoSettings`), and how well
L_f ranks configurations by AP (`rank_correlation`, `hydrabench eco-data`). See `study.eco`."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from sim.errors import UserError
from study.engine.gate_data import GateData

ECO_DATA_VERSION = 1
LOSS_VARIANTS = {
    "default": {},
    "no_false_positive_term": {"fp_weight": 0.0},
    "no_miss_term": {"miss_cost": 0.0},
    "no_box_term": {"box_weight": 0.0},
    "miss_cost_1": {"miss_cost": 1.0},
    "first_definition_miss_3.0": {"miss_cost": 2.995732},  # -ln 0.05: a found object could cost more than a miss
}
"""L_f variants whose ranking of configurations is compared with AP (eco-data's report)."""


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
                 checkpoint: str = "latest", grid=None, weights=None) -> None:
        from fusion.eco.loss import FusedLossSpec
        from sensors.dataset import DatasetReader

        self.configurations = configurations
        self.fusion = fusion
        self.loss_spec = loss_spec or FusedLossSpec()  # computes the cached terms (part of the key)
        # combines them into L_f (`losses`): only the weights may differ from `loss_spec`, since
        # the terms depend on the matching (iou_thr) and the box term's beta alone
        self.weights = weights or self.loss_spec
        if (self.weights.iou_thr, self.weights.beta) != (self.loss_spec.iou_thr, self.loss_spec.beta):
            raise ValueError("weights may change the weights of L_f, not its matching or box term")
        prof = getattr(model, "profile", None)
        self.max_det = int(prof.box_detections_per_img) if prof is not None else 100
        self.reader = DatasetReader(data)
        super().__init__(run_dir, data, model, checkpoint, grid)

    def extra_identity(self) -> dict:
        return {"eco_version": ECO_DATA_VERSION, "configurations": [list(m) for m in self.configurations.members],
                "fusion": self.fusion, "loss": dataclasses.asdict(self.loss_spec), "max_detections": self.max_det,
                "ground_truth": "study.engine.scoring.ground_truth camera_right"}

    def compute(self, model, inputs, targets, metas, features) -> dict[str, np.ndarray]:
        from fusion.eco.loss import loss_terms
        from fusion.late import fuse, to_reference
        from sensors.rig import Calibration
        from study.engine.scoring import ground_truth, to_detections

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
        """(n, n_configurations) L_f of each frame and configuration (with `weights`)."""
        return self.weights.combine(self.arrays(indices, ["terms"])["terms"])



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


@dataclasses.dataclass(frozen=True)
class EcoSettings:
    """What identifies a configuration dataset and how energy is put on the lambda_E scale.

    Fields:
        configurations: YAML file of `fusion.eco.configurations.ConfigurationsConfig` ("" = every subset).
        fusion: late-fusion method of the configurations (nms, soft-nms, wbf): WBF by default, as
            EcoFusion's Section 4.4 fuses. (On the `cpu` study's validation frames Soft-NMS scores late
            fusion higher, 0.323 against 0.278; the study fuses its fixed methods with the method its
            validation frames choose, `study.pipeline.evaluation`, and EcoFusion's L_f with this one.)
        checkpoint: the run's checkpoint ("latest" or "epoch-NNN").
        power: "px2" (45.4 W) or watts: P of Eq. 6 where no energy counter exists.
        energy_scale: "px2" (E / E_late x 3.798 J), "late" (E / E_late) or "joules" (`fusion.eco.optimise`).
        loss_scale: "late" (L_f / late fusion's mean training L_f) or "raw": the L_f that lambda_E and
            gamma weigh (`fusion.eco.optimise.normalise_loss`).
        rule: candidate rule of Eq. 7, "prose" or "equation".
        batch_size: frames per forward when building the dataset.
        max_frames: at most this many frames of each split (evenly spaced over the split, so every
            context keeps its share); 0 = every frame. For machines where a forward of every
            branch on every frame takes too long; results say how many frames they are on.
        fp_weight: [1] weight of L_f's false-positive term (`fusion.eco.loss.FusedLossSpec`): what
            the learned gates regress, what the Loss-based oracle minimises and what "avg L_f"
            reports. The cached terms do not depend on it (only on matching), so changing it
            reuses the configuration dataset; a gate trained at one weight is kept apart from
            the others (`gate_dir`).
    """

    configurations: str = ""
    fusion: str = "wbf"
    checkpoint: str = "latest"
    power: str = "px2"
    energy_scale: str = "px2"
    loss_scale: str = "late"
    rule: str = "prose"
    batch_size: int = 4
    max_frames: int = 0
    fp_weight: float = 1.0

    def loss_spec(self):
        """The L_f definition these settings combine the cached terms with."""
        from fusion.eco.loss import FusedLossSpec

        return dataclasses.replace(FusedLossSpec(), fp_weight=float(self.fp_weight))

    def fp_flag(self) -> str:
        """" --fp-weight W" for a non-default weight (to name in messages), else ""."""
        return "" if self.fp_weight == 1.0 else f" --fp-weight {self.fp_weight:g}"

    def gate_dir(self, run_dir, gate: str) -> Path:
        """RUN/eco/gates/<gate>/ for the default L_f; RUN/eco/gates/<gate>-fp<w>/ for another
        false-positive weight, so gates trained on different targets never overwrite each other."""
        name = gate if self.fp_weight == 1.0 else f"{gate}-fp{self.fp_weight:g}"
        return Path(run_dir) / "eco" / "gates" / name


def open_eco_run(run_dir, data, s: EcoSettings, threads: int = 2, device: str = "cpu"):
    """A trained run ready for EcoFusion: (model, run config, configurations, EcoData).

    Loads the run's network at `s.checkpoint`, builds the configuration set of `s.configurations`
    over its branches, and the configuration dataset (`EcoData`) of `data` under `s`'s loss and
    fusion method, the model on `device` (the configuration dataset is computed where the model is;
    its cache key names the device type, `study.engine.gate_data`). UserError if the run's branches share no
    stems (the learned gates read them)."""
    import torch

    from fusion.eco.configurations import build_configurations, load_configurations_config
    from fusion.nets.branch_gates import gate_sensors
    from study.engine.scoring import fusion_method, load_run

    torch.set_num_threads(threads)
    method = fusion_method(s.fusion)
    model, cfg = load_run(run_dir, s.checkpoint, device=device)
    if not gate_sensors(model):
        raise UserError("EcoFusion's learned gates read the shared stems; this run's branches have none")
    ccfg = load_configurations_config(s.configurations or None)
    configs = build_configurations(model.branch_sensors, ccfg)
    ed = EcoData(run_dir, data, model, configs, method, checkpoint=s.checkpoint, weights=s.loss_spec())
    return model, cfg, configs, ed


def _subsample(indices: list[int], n: int) -> list[int]:
    """At most n of `indices`, evenly spaced (indices are in dataset order, grouped by sequence)."""
    if not n or len(indices) <= n:
        return list(indices)
    return [indices[int(k)] for k in np.linspace(0, len(indices) - 1, n).round().astype(int)]


def eco_splits(cfg, data, max_frames: int = 0) -> tuple[list[int], list[int]]:
    """The run's (train, test) dataset indices of `data` (`study.engine.scoring.run_train_test`), each cut
    to at most `max_frames` evenly spaced frames (0 = all)."""
    from study.engine.scoring import run_train_test

    train, test = run_train_test(cfg, data, "EcoFusion")
    return _subsample(train, max_frames), _subsample(test, max_frames)


def eco_gate_frames(cfg, data, max_frames: int = 0, targets: str = "auto", val_fraction: float = 0.15,
                    seed: int = 0, who: str = "EcoFusion"):
    """`study.experiments.selection.gate_frames` of an EcoFusion run, its fitting and test frames cut to at most
    `max_frames` evenly spaced ones (0 = all)."""
    import dataclasses as dc

    from study.experiments.selection import gate_frames

    f = gate_frames(cfg, data, targets, val_fraction, seed, who)
    return dc.replace(f, fit=_subsample(f.fit, max_frames), test=_subsample(f.test, max_frames))


def build_eco_data(run_dir, data, s: EcoSettings = EcoSettings(), progress: bool = True, device: str = "cpu",
                   val_fraction: float = 0.15, seed: int = 0) -> dict:
    """`hydrabench eco-data`: build (or complete) the configuration dataset (the run's training,
    gate-split and test frames) and report how well L_f ranks configurations by per-frame AP (rank
    correlation, per definition variant) on the gates' validation frames (`val_fraction`, `seed`:
    `study.experiments.selection.gate_frames`, from the gate split when the run has one), so a choice of L_f's
    weights made from it reads no test frame; on every fitting frame when there are too few
    sequences to carve any. The network runs on `device` (a torch device string, `study.engine.device`),
    in fp32."""
    from fusion.eco.loss import FusedLossSpec
    from study.engine.scoring import frames_for

    run_dir, data = Path(run_dir), Path(data)
    model, cfg, configs, ed = open_eco_run(run_dir, data, s, device=device)
    train, test = eco_splits(cfg, data, s.max_frames)
    frames = eco_gate_frames(cfg, data, s.max_frames, "auto", val_fraction, seed)
    gate, _ = frames_for(cfg, data, "gate")
    t0 = time.perf_counter()
    computed = ed.ensure(sorted(set(train) | set(gate) | set(test)), batch_size=s.batch_size, progress=progress)
    seconds = time.perf_counter() - t0
    val = frames.val
    on = val or frames.fit
    arr = ed.arrays(on, ["terms", "ap"])
    corr = {}
    for name, kw in LOSS_VARIANTS.items():
        spec = dataclasses.replace(FusedLossSpec(), **kw)
        corr[name] = rank_correlation(spec.combine(arr["terms"]), arr["ap"])
    if ed.weights != FusedLossSpec():
        corr[f"fp_weight_{ed.weights.fp_weight:g}"] = rank_correlation(ed.weights.combine(arr["terms"]), arr["ap"])
    lf = ed.weights.combine(ed.arrays(test, ["terms"])["terms"])
    return {
        "run": str(run_dir), "data": str(data), "eco_data": str(ed.dir), "configurations": len(configs),
        "baselines": {k: configs.names[v] for k, v in configs.baselines.items()},
        "frames": {"train": len(train), "gate": len(gate), "test": len(test)}, "computed_frames": computed,
        "seconds": round(seconds, 1), "fusion": ed.fusion, "loss_definition": dataclasses.asdict(ed.weights),
        "loss_vs_ap_validation": corr,
        "loss_vs_ap_on": f"{'validation' if val else 'fitting'} frames of the "
                         f"{'gate' if frames.holdout else 'train'} split ({len(on)}), never test frames",
        "mean_loss_test": {configs.names[i]: round(float(lf[:, i].mean()), 4) for i in range(len(configs))},
        "lowest_mean_loss_test": configs.names[int(np.argmin(lf.mean(axis=0)))] if len(lf) else None,
        "note": "rank correlation per frame across configurations between L_f and the frame's AP@0.5 "
                "(negative = lower loss ranks higher AP), then averaged over frames",
    }
