"""EcoFusion evaluated on a run's test split: each gate's predictions through the joint optimisation
(Eq. 7-9) at one lambda_E and gamma against the fixed baselines and the oracle (`EcoEval`,
`evaluate_eco`, `hydrabench eco-evaluate`), and EcoFusion executed in the network
(`execute_ecofusion`). See `study.eco`."""

from __future__ import annotations

import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from fusion.metrics import MAX_BOOTSTRAP
from sim.errors import UserError
from sim.progress import progress as progress_bar
from study.eco.config_gate_study import load_eco_gate
from study.eco.data import (
    EcoSettings,
    detections_from_array,
    eco_gate_frames,
    eco_splits,
    open_eco_run,
)
from study.eco.latency_energy import energy_table
from study.engine.gate_training import predict_losses

GATE_ORDER = ("knowledge", "deep", "attention", "loss_based")
"""Gates that read the stems' features, so every stem they read runs before they decide."""
METRIC = "VOC all-point AP at IoU 0.5, right camera, difficult ground truth ignored"


class EcoEval:
    """Everything one evaluation needs, loaded once: the test frames' cached arrays, the energy
    of each configuration, and each gate's predicted losses."""

    def __init__(self, run_dir, data, s: EcoSettings = EcoSettings(), gates=None, threads: int = 2,
                 latency_threads: int = 1, progress: bool = True) -> None:
        from fusion.eco.config_gates import build_config_gate
        from fusion.eco.optimise import normalise_energy
        from sensors.dataset import DatasetReader

        self.run_dir, self.data, self.s = Path(run_dir), Path(data), s
        self.model, cfg, self.configs, self.ed = open_eco_run(self.run_dir, self.data, s, threads)
        self.run_cfg = cfg
        train, self.test = eco_splits(cfg, self.data, s.max_frames)
        # the frames the gates learn from: the gate split's when the run has one (L_f there is L_f on
        # unseen frames, as on the test frames), else the detectors' training frames
        frames = eco_gate_frames(cfg, self.data, s.max_frames, "auto", 0.0)
        self.train = train = frames.fit
        self.ed.ensure(train + self.test, batch_size=s.batch_size, progress=progress)
        self.reader = DatasetReader(self.data)
        self.metas = [self.reader.meta(i) for i in self.test]
        for i, m in zip(self.test, self.metas):
            m["dataset_index"] = int(i)
        arr = self.ed.arrays(self.test, ["features", "detections", "terms", "ap"])
        self.features = arr["features"]
        self.loss_unit = self._loss_unit(train)
        self.dets = [detections_from_array(a, self.ed.branches) for a in arr["detections"]]
        self.terms = arr["terms"]
        self.losses = self.ed.weights.combine(self.terms)
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
                gate = load_eco_gate(self.run_dir, g, self.model, self.configs, self.ed, s)
                self.predicted[g] = predict_losses(gate, self.features, metas=self.metas)

    def _loss_unit(self, train) -> float:
        """Late fusion's mean L_f over the frames the gates learn from ("late" loss scale; every configuration's
        where the set has no late fusion, as energy falls back to the largest), or 1 ("raw")."""
        from fusion.eco.optimise import LOSS_SCALES, loss_unit

        if self.s.loss_scale not in LOSS_SCALES:
            raise UserError(f"--loss-scale: expected one of {', '.join(LOSS_SCALES)}, got {self.s.loss_scale!r}")
        if self.s.loss_scale == "raw":
            return 1.0
        late = self.configs.baselines.get("late")
        losses = self.ed.losses(train)
        try:
            return loss_unit(losses[:, late] if late is not None else losses, "late")
        except ValueError as exc:
            raise UserError(f"--loss-scale: {exc}") from None

    def unit_of(self, gate: str) -> float:
        """What `gate`'s predictions are divided by before Eq. 7-9: the loss unit for the gates that
        predict L_f; 1 for the knowledge gate, whose scores count branches (static, as in the paper)."""
        return 1.0 if gate.startswith("knowledge") else self.loss_unit

    def choose(self, gate: str, lambda_e: float, gamma: float) -> np.ndarray:
        from fusion.eco.optimise import normalise_loss, select

        return select(normalise_loss(self.predicted[gate], self.unit_of(gate)), self.e, lambda_e, gamma, self.s.rule)

    def fixed(self, name: str) -> np.ndarray:
        return np.full(len(self.test), self.configs.index(name))

    def gate_overhead(self, choice: np.ndarray, gate: str | None, family: str = "ecofusion"):
        """(seconds, sensors) a gate adds to each frame's configuration: a gate reading stem features
        (deep, attention) runs every stem it reads before it decides, so the stems the chosen
        configuration does not need are extra time (and energy, at the configuration's own power),
        and every sensor it reads must measure (no clock gating for them). The knowledge gate
        decides from external context before any stem runs, and the loss-based oracle is
        a-posteriori: neither adds anything. The gate's own network (pooling and its convolutions)
        adds its measured time (`study.eco.latency_energy.gate_latency`, `family`:`gate`) where the
        gates stage measured it."""
        from fusion.eco.config_gates import CONFIG_GATES
        from fusion.nets.branch_gates import gate_sensors, trainable_gates

        if gate not in trainable_gates(CONFIG_GATES):
            return np.zeros(len(choice)), [set() for _ in choice]

        from study.eco.latency_energy import read_gate_latency

        read = set(gate_sensors(self.model))
        stems = self.latency_model.stems
        own = read_gate_latency(self.run_dir).get(f"{family}:{gate}", 0.0)
        extra = np.array([own + sum(stems.get(x, 0.0) for x in read - set(self.sensors[c])) for c in choice])
        return extra, [read for _ in choice]

    def metrics(self, choice: np.ndarray, per_scene: bool = False, gate: str | None = None) -> dict:
        """mAP, mean actual L_f, energy and latency of per-frame configuration choices; with `gate`,
        the energy and latency include what that gate costs to decide (`gate_overhead`)."""
        from fusion.eco.energy import total_energy
        from study.engine.scoring import score

        selection = [self.configs.members[i] for i in choice]
        sc = score(self.fused(choice), self.reader, "camera_right", protocol=self.ed.protocol)
        rows = np.arange(len(choice))
        lf = self.losses[rows, choice]
        extra, read = self.gate_overhead(choice, gate)
        t = self.t[choice] + extra
        scale = t / self.t[choice]  # E = P t at the configuration's own power
        e, e_raw = self.e[choice] * scale, self.e_raw[choice] * scale
        out = {"map": sc["map"], "map_vehicles": sc["map_vehicles"], "avg_loss": round(float(lf.mean()), 4),
               "energy": round(float(e.mean()), 4),
               # the configurations' own energy, what Eq. 9 trades against the predicted loss (`energy` adds
               # what the gate costs to decide, measured: with it, a larger lambda_E need not spend less)
               "energy_configuration": round(float(self.e[choice].mean()), 4),
               "energy_j": round(float(e_raw.mean()), 4),
               "latency_ms": round(1000 * float(t.mean()), 2),
               "gate_ms": round(1000 * float(extra.mean()), 2),
               "mean_branches": round(float(np.mean([len(m) for m in selection])), 3)}
        if per_scene:
            measuring = [sorted(set(self.sensors[c]) | r) for c, r in zip(choice, read)]
            sensor_e = np.array([total_energy(ek, ms, "clock") for ek, ms in zip(e, measuring)])
            sensor_off = np.array([total_energy(ek, ms, "off") for ek, ms in zip(e, measuring)])
            per_meas = np.array([total_energy(ek, ms, "clock", period="measurement") for ek, ms in zip(e, measuring)])
            per_meas_off = np.array([total_energy(ek, ms, "off", period="measurement") for ek, ms in zip(e, measuring)])
            scenes = {}
            for ctx in sorted(set(self.contexts)):
                k = np.array([c == ctx for c in self.contexts])
                scenes[ctx] = {"frames": int(k.sum()), "avg_loss": round(float(lf[k].mean()), 4),
                               "energy": round(float(e[k].mean()), 4),
                               "energy_clock_gated": round(float(sensor_e[k].mean()), 4),
                               "energy_all_sensors_on": round(float(sensor_off[k].mean()), 4),
                               "energy_clock_gated_per_measurement": round(float(per_meas[k].mean()), 4),
                               "energy_all_sensors_on_per_measurement": round(float(per_meas_off[k].mean()), 4),
                               "map": sc["map_per_context"].get(ctx)}
            out["per_scene"] = scenes
            out["energy_clock_gated"] = round(float(sensor_e.mean()), 4)
            out["energy_all_sensors_on"] = round(float(sensor_off.mean()), 4)
            out["energy_clock_gated_per_measurement"] = round(float(per_meas.mean()), 4)
            out["energy_all_sensors_on_per_measurement"] = round(float(per_meas_off.mean()), 4)
        return out

    def fused(self, choice: np.ndarray) -> list:
        """[(meta, Detections)]: each frame's chosen configuration fused in the right camera."""
        from study.engine.scoring import fuse_selection, fusion_method

        selection = [self.configs.members[i] for i in choice]
        return fuse_selection(list(zip(self.metas, self.dets)), selection, self.model.branch_frames,
                              fusion_method(self.s.fusion), memo=self.memo)

    def selection_counts(self, choice: np.ndarray, top: int = 5) -> dict:
        names, counts = np.unique(choice, return_counts=True)
        order = np.argsort(-counts)[:top]
        return {self.configs.names[names[i]]: round(100.0 * counts[i] / len(choice), 1) for i in order}

    def loss_label(self) -> str:
        if self.s.loss_scale == "raw":
            return "L_f as computed (raw)"
        return f"L_f / {self.loss_unit:.4f} (late fusion's mean training L_f)"

    def energy_label(self) -> str:
        scale = {"px2": "PX2-equivalent J: E / E(late) x 3.798 J (EcoFusion Table 1's late fusion)",
                 "late": "E / E(late), dimensionless", "joules": "J on this machine"}[self.s.energy_scale]
        return f"{scale}; E from {self.energy_info['energy_source']}"


def evaluate_eco(run_dir, data, lambda_e: float = 0.01, gamma: float = 0.5, s: EcoSettings = EcoSettings(),
                 gates=None, progress: bool = True, ev: EcoEval | None = None, bootstrap: int = 0) -> dict:
    """`hydrabench eco-evaluate`: every gate at one lambda_E and gamma against the fixed baselines
    and the oracle (regret = gate minus loss-based, in mean joint loss and mean L_f). `bootstrap`:
    95 % intervals of every mAP and every paired mAP difference (gate minus late fusion above all)
    from that many draws of whole sequences (`study.engine.scoring.context_bootstrap`), as "ci95"."""
    if not 0 <= bootstrap <= MAX_BOOTSTRAP:
        raise UserError(f"--bootstrap must be 0..{MAX_BOOTSTRAP} draws, got {bootstrap}")
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
    ci = None
    if bootstrap:
        from study.engine.scoring import context_bootstrap

        sources = {g: ev.fused(ev.choose(g, lambda_e, gamma)) for g in ev.predicted}
        sources.update({name: ev.fused(ev.fixed(name)) for name in ev.configs.baselines if name not in sources})
        ci = context_bootstrap(sources, ev.reader, "camera_right", ev.ed.protocol, bootstrap, classes="all",
                               desc="bootstrap gates")
        for g in ratios:
            ratios[g]["map_minus_late_ci95"] = ci["per_context"]["all"]["difference"].get(f"{g} - late")
    return {"lambda_e": lambda_e, "gamma": gamma, "rule": s.rule, "fp_weight": s.fp_weight, "gates": rows, "baselines": base,
            "against_late": ratios, **({"ci95": ci} if ci else {}), "frames": len(ev.test), "configurations": len(ev.configs),
            "energy_unit": ev.energy_label(), "loss_unit": ev.loss_label(), "latency": "additive model of measured component latencies, "
            "this machine", "metric": METRIC, "run": str(run_dir), "data": str(data)}


def execute_ecofusion(run_dir, data, gate: str, lambda_e: float, gamma: float, s: EcoSettings = EcoSettings(),
                      frames: int = 0, progress: bool = True, ev: EcoEval | None = None) -> dict:
    """EcoFusion executed: the gate and the joint optimisation wired into the network
    (`EcoFusionSelector` as `model.gate`), so per frame only the chosen configuration's branches
    and the stems they need run (the knowledge gate reads no stem before deciding). Counts stem and
    branch calls, times each frame end to end (fusion included) and checks the fused detections
    against the offline selection from the configuration dataset."""
    import torch

    from fusion.data import FrameDataset, collate
    from fusion.eco.config_gates import EcoFusionSelector, build_config_gate
    from fusion.late import fuse
    from sensors.rig import Calibration
    from study.engine.scoring import fuse_selection, fusion_method, to_detections

    ev = ev or EcoEval(run_dir, data, s, [gate], progress=progress)
    model = ev.model
    if gate == "knowledge":
        g = build_config_gate(gate, model, ev.configs)
    elif gate == "loss_based":
        g = build_config_gate(gate, model, ev.configs)
    else:
        g = load_eco_gate(run_dir, gate, model, ev.configs, ev.ed)
    selector = EcoFusionSelector(g, ev.e, lambda_e, gamma, s.rule, loss_unit=ev.unit_of(gate))
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
            bar = progress_bar(total=len(idx), desc=f"execute {gate}", enabled=progress)
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
                ref = fuse_selection([(ev.metas[pos], ev.dets[pos])], [ev.configs.members[choice]],
                                     model.branch_frames, method)[0][1]
                same += bool(len(ref) == len(fused) and np.allclose(ref.boxes, fused.boxes, atol=1e-3)
                             and np.allclose(ref.scores, fused.scores, atol=1e-4))
                bar.update(1)
            bar.close()
    finally:
        model.gate = None
        for h in hooks:
            h.remove()
    n = len(idx)
    config_index = offline[idx]  # per frame, the configuration the gate chose
    return {"gate": gate, "lambda_e": lambda_e, "gamma": gamma, "frames": n,
            "stem_runs_per_frame": {k.split(":", 1)[1]: round(v / n, 3) for k, v in calls.items() if k.startswith("stem:")},
            "branch_runs_per_frame": round(sum(v for k, v in calls.items() if k.startswith("branch:")) / n, 3),
            "mean_branches_chosen": round(float(np.mean([len(ev.configs.members[c]) for c in config_index])), 3),
            "measured_latency_ms": round(1000 * float(np.mean(times)), 2),
            "additive_latency_ms": round(1000 * float(ev.t[config_index].mean()), 2),
            "choice_equals_offline": round(agree / n, 4), "detections_equal_offline": round(same / n, 4)}
