"""`hydrabench study`: the whole HydraFusion + EcoFusion comparison as cached, resumable stages.

    generate -> train -> gatedata -> gates -> evaluate -> report

Each stage is a function of its config section (`StudyConfig`) and of the digests of the stages it
reads. Its key is the SHA-256 of both; its output lives in `DIR/stages/<stage>-<key>/` with a
`manifest.json` (the key, what it was made of, its output digest, the seconds it took). A stage
works in `DIR/stages/<stage>-<key>.partial/` and is renamed to its final name when complete, so:

- a stage whose final directory exists (same key) is skipped: a second run does no work;
- killed anywhere (even kill -9), the next run continues in the partial directory: generation
  completes its missing shards, training resumes from its last checkpoint (`study.train`), the gate
  datasets from their last chunk, gate training from its last epoch; evaluation starts again;
- a changed field changes the key of its stage and of every stage below it (their inputs' digests
  change), and only those run again; the stages above keep theirs. Old keys stay in DIR/stages as
  a cache (delete them to reclaim the space).

Stages below `train` work on a *farm* of the run directory: the upstream run's directories are
recreated and its files symlinked (relative links), so what a stage writes (gate caches, gates,
latency tables) lands in its own directory and never changes a finished stage.

Beside its config section and its inputs, a stage's key holds everything else its output depends
on (`stage_identity`): the code it runs (`study.code_identity.code_digest` of its modules and of
its stage function), the sensor model version and the sensor profile (generate), the model
profile's contents (train), and the device type and precision the networks run in
(`study.device.compute_identity`; generation always runs on the CPU). Each key also holds the key of
every stage it reads, so a change reruns exactly its stage and the stages below it. Threads,
workers and backend are part of no key: they decide how fast a stage runs, not what it computes.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from sim.config import from_dict, load_yaml, to_dict
from sim.errors import UserError
from study.gate_data import file_sha256
from study.outputs import atomic_path, write_json_atomic

STUDY_VERSION = 2
PRESETS_DIR = Path(__file__).resolve().parents[1] / "configs" / "study"
STAGES = ("generate", "train", "gatedata", "gates", "evaluate", "report")
MARKER = "study.json"
"""The file that makes DIR a study directory (a folder of other files is refused)."""


def _positive(where: str, value, lo=1) -> None:
    if value < lo:
        raise UserError(f"{where} must be >= {lo}, got {value}")


@dataclass(frozen=True)
class DataSection:
    """The datasets (`sensors.generate.GenerateConfig`): one dataset, split by sequence into train
    and test by the training run; with `twins` every frame also has its clear-weather twin (only
    the condition differs), which the severity sweeps compare against.

    Fields:
        contexts: context names or combinations; "all" = the eight.
        frames_per_context: [frames] per context.
        sequence_length: [frames] per sequence (= per shard; the split is by sequence).
        frame_rate_hz: [Hz] within a sequence.
        severities: condition severities drawn per sequence (0-5).
        twins: also render every frame in clear weather.
        seed: root seed of the scenes.
    """

    contexts: tuple[str, ...] = ("all",)
    frames_per_context: int = 20
    sequence_length: int = 10
    frame_rate_hz: float = 2.0
    severities: tuple[int, ...] = (1, 2, 3, 4, 5)
    twins: bool = True
    seed: int = 0

    def generate_config(self, profile: str):
        from sensors.generate import GenerateConfig
        from sim.scenario import CONTEXT_NAMES

        contexts = tuple(CONTEXT_NAMES) if tuple(self.contexts) == ("all",) else tuple(self.contexts)
        return GenerateConfig(contexts=contexts, frames_per_context=self.frames_per_context, seed=self.seed,
                              profile=profile, sequence_length=self.sequence_length, frame_rate_hz=self.frame_rate_hz,
                              severities=tuple(self.severities), twins=self.twins)


@dataclass(frozen=True)
class TrainSection:
    """Training (`study.train.TrainConfig`, HydraFusion 5.3): one run of the paper's branches (the
    single-sensor branches among them give Table 2 (i) and late fusion (iii)) and, with
    `early_fusion`, one run of the input-level early-fusion models (Table 2 (ii)).

    Fields:
        branches: branches of the paper set to train (empty = all seven).
        early_fusion: also train the early-fusion set (cameras, cameras + lidar, radar + lidar).
        early_branches: which of the early-fusion models (empty = all three).
        epochs, batch_size, lr, warmup_steps, clip_grad, seed, checkpoint_steps: as TrainConfig.
        eval_frames: test frames scored after each epoch (0 = all).
        protocol: ground truth to train on and score against (reference | visible | bev-free).
        gate_holdout: share of the train split's sequences, per context, the detectors never train
            on: the gate split the gates learn from and every choice is made on (0 = none: the
            gates learn from the detectors' training frames, the choices are made on validation
            sequences carved from them).
        model: `KEY=VALUE` overrides of the model profile, as `train --model` (e.g. width=0.5).
        init_from: a reference model (a name in models/, `study.reference_model`) or a run directory
            whose weights initialise the paper run (`train --init-from`; "" = from scratch). Its
            checkpoint's digest is part of the train stage's key.
    """

    branches: tuple[str, ...] = ()
    early_fusion: bool = True
    early_branches: tuple[str, ...] = ()
    epochs: int = 10
    batch_size: int = 4
    lr: float = 5e-3
    warmup_steps: int = 100
    clip_grad: float = 10.0
    seed: int = 0
    checkpoint_steps: int = 100
    eval_frames: int = 0
    protocol: str = "reference"
    gate_holdout: float = 0.0
    model: tuple[str, ...] = ()
    init_from: str = ""

    def __post_init__(self) -> None:
        from fusion.nets.profile import parse_model_overrides

        parse_model_overrides(self.model)  # refuses a malformed or data-fixed key now, not after generation
        if not 0 <= self.gate_holdout < 1:
            raise UserError(f"train.gate_holdout must be in [0, 1), got {self.gate_holdout}")
        for name in ("epochs", "batch_size", "checkpoint_steps"):
            _positive(f"train.{name}", getattr(self, name))
        for name in ("warmup_steps", "eval_frames", "seed"):
            _positive(f"train.{name}", getattr(self, name), 0)
        if not self.lr > 0:
            raise UserError(f"train.lr must be > 0, got {self.lr}")
        if self.clip_grad < 0:
            raise UserError(f"train.clip_grad must be >= 0, got {self.clip_grad}")
        early = ("early_cameras", "early_camera_lidar", "early_radar_lidar")
        bad = [b for b in self.early_branches if b not in early]
        if bad:
            raise UserError(f"train.early_branches: unknown model {bad[0]!r} (choose from: {', '.join(early)})")
        if self.protocol not in ("reference", "visible"):
            raise UserError(f"train.protocol must be reference or visible (the study fuses in the right camera), "
                            f"got {self.protocol!r}")


@dataclass(frozen=True)
class GatesSection:
    """Gate datasets and gates: HydraFusion's per-branch gates (`study.branch_gate_study`, Section 5.2.2) and
    EcoFusion's per-configuration gates (`study.eco`), and the latency table (Eq. 6).

    Fields:
        gates: the learned gates to train (deep, attention); knowledge and the oracles need none.
        epochs, batch_size, lr, val_fraction, seed, targets: as GateTrainConfig (HydraFusion 5.3:
            lr 5e-5; targets "auto": the gate split when train.gate_holdout > 0).
        context, pooling: the learned gates' inputs besides the pooled stem features (GateTrainConfig:
            the frame's context label; "global" pooling: an MLP on each channel's mean).
        compare_targets: with a gate split, also train every gate on the detectors' own training
            frames (validated on the same gate-split frames), so the report measures what held-out
            targets change (under RUN/gates/<gate>/in_sample/ and RUN/eco/gates/<gate>/in_sample/).
        eco_max_frames: at most this many frames of each split for EcoFusion (0 = all).
        fusion: late fusion of an EcoFusion configuration (nms | soft-nms | wbf; EcoFusion 4.4: wbf).
        energy_frames, energy_repeats, energy_check: the latency measurement (eco-energy).
    """

    gates: tuple[str, ...] = ("deep", "attention")
    epochs: int = 100
    batch_size: int = 32
    lr: float = 5e-5
    val_fraction: float = 0.15
    seed: int = 0
    targets: str = "auto"
    compare_targets: bool = True
    context: bool = False
    pooling: str = "grid"
    eco_max_frames: int = 0
    fusion: str = "wbf"
    energy_frames: int = 3
    energy_repeats: int = 3
    energy_check: int = 12

    def __post_init__(self) -> None:
        from fusion.nets.branch_gates import trainable_gates  # the gate registry says which gates learn

        if bad := [g for g in self.gates if g not in trainable_gates()]:
            raise UserError(f"gates.gates: {bad[0]!r} is not a learned gate (choose from: {', '.join(trainable_gates())})")
        for name in ("epochs", "batch_size", "energy_frames", "energy_repeats"):
            _positive(f"gates.{name}", getattr(self, name))
        for name in ("eco_max_frames", "energy_check", "seed"):
            _positive(f"gates.{name}", getattr(self, name), 0)
        if not self.lr > 0:
            raise UserError(f"gates.lr must be > 0, got {self.lr}")
        if not 0 <= self.val_fraction < 1:
            raise UserError(f"gates.val_fraction must be in [0, 1), got {self.val_fraction}")
        if self.fusion not in ("nms", "soft-nms", "wbf"):
            raise UserError(f"gates.fusion must be nms, soft-nms or wbf, got {self.fusion!r}")
        from study.selection import TARGETS

        if self.targets not in TARGETS:
            raise UserError(f"gates.targets must be one of {', '.join(TARGETS)}, got {self.targets!r}")
        if self.pooling not in ("grid", "global"):
            raise UserError(f"gates.pooling must be grid or global, got {self.pooling!r}")
        if self.pooling == "global" and "attention" in self.gates:
            raise UserError("gates.pooling global: the attention gate attends over the pooled grid; train deep only")


@dataclass(frozen=True)
class EvaluateSection:
    """Evaluation on the run's test split.

    Fields:
        k: branches HydraFusion's gate keeps per frame (HydraFusion Table 2 (iv): top 3).
        hydra_gate: the gate of the HydraFusion rows (knowledge | deep | attention).
        eco_gate: the gate of the EcoFusion rows (knowledge | deep | attention).
        lambda_e: EcoFusion's energy weight (Eq. 8) of the EcoFusion rows.
        gamma: candidate margin of Eq. 7 (EcoFusion Section 5: 0.5).
        rule: Eq. 7 as "prose" (within gamma of the best) or "equation" (as printed).
        power: P of Eq. 6 where no counter exists: "px2" (45.4 W) or watts as a string.
        energy_scale: px2 | late | joules (`fusion.eco.optimise.normalise_energy`).
        loss_scale: late | raw: the L_f lambda_E and gamma weigh (`fusion.eco.optimise.normalise_loss`).
        twins: score the clear-weather twins of the test frames too (severity sweeps).
        bootstrap: draws of whole test sequences for 95 % intervals of every method's mAP, overall
            and per context, and of every paired difference (`study.scoring.context_bootstrap`;
            0 = none).
    """

    k: int = 3
    hydra_gate: str = "attention"
    eco_gate: str = "attention"
    lambda_e: float = 0.01
    gamma: float = 0.5
    rule: str = "prose"
    power: str = "px2"
    energy_scale: str = "px2"
    loss_scale: str = "late"
    twins: bool = True
    bootstrap: int = 0

    def __post_init__(self) -> None:
        _positive("evaluate.k", self.k)
        from fusion.metrics import MAX_BOOTSTRAP

        if isinstance(self.bootstrap, bool) or not isinstance(self.bootstrap, int) or not 0 <= self.bootstrap <= MAX_BOOTSTRAP:
            raise UserError(f"evaluate.bootstrap must be an integer in [0, {MAX_BOOTSTRAP}], got {self.bootstrap!r}")
        for name in ("hydra_gate", "eco_gate"):
            if getattr(self, name) not in ("knowledge", "deep", "attention"):
                raise UserError(f"evaluate.{name} must be knowledge, deep or attention, got {getattr(self, name)!r}")
        if not 0 <= self.lambda_e <= 1:
            raise UserError(f"evaluate.lambda_e must be in [0, 1], got {self.lambda_e}")
        if not self.gamma >= 0:
            raise UserError(f"evaluate.gamma must be >= 0, got {self.gamma}")
        if self.rule not in ("prose", "equation"):
            raise UserError(f"evaluate.rule must be prose or equation, got {self.rule!r}")
        if self.energy_scale not in ("px2", "late", "joules"):
            raise UserError(f"evaluate.energy_scale must be px2, late or joules, got {self.energy_scale!r}")
        if self.loss_scale not in ("late", "raw"):
            raise UserError(f"evaluate.loss_scale must be late or raw, got {self.loss_scale!r}")
        from fusion.eco.energy import power_model

        try:
            power_model(self.power)
        except ValueError as exc:
            raise UserError(f"evaluate.power: {exc}") from None


@dataclass(frozen=True)
class RunSection:
    """Where and how fast the stages run. The resolved device type and precision are part of the
    keys of the stages that run networks; threads, workers and backend of none.

    Fields:
        device: auto | cpu | cuda | cuda:N.
        threads: torch CPU threads (0: the cores available).
        workers: generation processes (and Ray CPUs with backend ray).
        backend: local | ray (generation: one Ray task per shard).
        amp: precision of the train stage (`study.device.resolve_amp`): "default" (bf16 autocast
            on CUDA, fp32 on the CPU), "auto" (bf16 where the device computes it natively: a GPU, or
            a CPU with AMX-BF16 or AVX512-BF16, `study.device.native_bf16`), "bf16" or "off". The
            backbones only: anchors, box coding and the heads stay fp32. The stages after train
            always run in fp32.
    """

    device: str = "auto"
    threads: int = 0
    workers: int = 1
    backend: str = "local"
    amp: str = "default"

    def __post_init__(self) -> None:
        if isinstance(self.amp, bool):  # YAML 1.1 reads a bare `off` / `on` as a boolean
            object.__setattr__(self, "amp", "bf16" if self.amp else "off")
        if self.amp not in ("default", "auto", "bf16", "off"):
            raise UserError(f"run.amp must be default, auto, bf16 or off, got {self.amp!r}")
        _positive("run.threads", self.threads, 0)
        _positive("run.workers", self.workers)
        if self.backend not in ("local", "ray"):
            raise UserError(f"run.backend must be local or ray, got {self.backend!r}")


@dataclass(frozen=True)
class StudyConfig:
    """One study (YAML: these keys, each section with its own; unknown keys are errors).

    Fields:
        scale: the name every table carries (smoke, cpu, paper, or your own).
        meaningless: the numbers are too small to mean anything (smoke, tests): the report says so
            in its first line.
        profile: sensor and model profile (cpu | paper).
        data, train, gates, evaluate, run: the sections above.
    """

    scale: str = "custom"
    meaningless: bool = False
    profile: str = "cpu"
    data: DataSection = field(default_factory=DataSection)
    train: TrainSection = field(default_factory=TrainSection)
    gates: GatesSection = field(default_factory=GatesSection)
    evaluate: EvaluateSection = field(default_factory=EvaluateSection)
    run: RunSection = field(default_factory=RunSection)

    def __post_init__(self) -> None:
        if not self.scale.strip():
            raise UserError("scale must name the study's scale")
        self.data.generate_config(self.profile)  # contexts, severities, profile: refused here
        from fusion.nets import load_profile

        try:
            paper = [b.name for b in load_profile(self.profile).branches]
        except (UserError, OSError, ValueError) as exc:
            raise UserError(f"profile: {exc}") from None
        bad = [b for b in self.train.branches if b not in paper]
        if bad:
            raise UserError(f"train.branches: unknown branch {bad[0]!r} (choose from: {', '.join(paper)})")
        if len(set(self.train.branches)) != len(self.train.branches):
            raise UserError("train.branches names a branch twice")


def load_study_config(spec: str) -> StudyConfig:
    """A preset name (configs/study/<name>.yaml) or a YAML file path -> StudyConfig (strict)."""
    path = Path(spec)
    if not spec.endswith((".yaml", ".yml")) and not path.exists():
        preset = PRESETS_DIR / f"{spec}.yaml"
        if not preset.is_file():
            names = sorted(p.stem for p in PRESETS_DIR.glob("*.yaml"))
            raise UserError(f"{spec!r} is neither a preset ({', '.join(names)}) nor a YAML file")
        path = preset
    if not path.is_file():
        raise UserError(f"{spec}: " + ("not a file" if path.exists() else "does not exist"))
    return load_yaml(StudyConfig, path)


def study_config_from_dict(data: dict) -> StudyConfig:
    return from_dict(StudyConfig, data, "study config")


# ----- stage machinery ------------------------------------------------------------------------


def _digest(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def link_farm(src: Path, dst: Path) -> None:
    """Recreate `src`'s directories under `dst` and symlink its files (relative links); entries
    already in `dst` are kept (a resumed stage keeps what it wrote)."""
    src, dst = Path(src).resolve(), Path(dst)
    for dirpath, _dirs, filenames in os.walk(src):
        rel = Path(dirpath).relative_to(src)
        target_dir = dst / rel
        target_dir.mkdir(parents=True, exist_ok=True)
        for f in filenames:
            if f.startswith(".") and ".tmp" in f:
                continue
            link = target_dir / f
            if not link.exists() and not link.is_symlink():
                os.symlink(os.path.relpath(Path(dirpath) / f, target_dir.resolve()), link)


@dataclass
class StageRecord:
    name: str
    key: str
    dir: Path
    status: str = "pending"
    seconds: float = 0.0
    digest: str = ""
    manifest: dict = field(default_factory=dict)


class Study:
    """One study directory: its config, its stages and their records."""

    def __init__(self, cfg: StudyConfig, out: str | Path, progress: bool = True) -> None:
        self.cfg, self.out, self.progress = cfg, Path(out), progress
        self.stages_dir = self.out / "stages"
        self.records: dict[str, StageRecord] = {}

    # -- bookkeeping --
    def say(self, text: str) -> None:
        if self.progress:
            sys.stderr.write(f"[study] {text}\n")
            sys.stderr.flush()

    def prepare(self) -> None:
        """Refuse a directory of other files; write the marker and the config."""
        if self.out.exists():
            if not self.out.is_dir():
                raise UserError(f"--out {self.out} exists and is not a directory")
            entries = [e.name for e in self.out.iterdir()]
            if entries and MARKER not in entries:
                raise UserError(f"--out {self.out} is not empty and holds no study (no {MARKER}); use a new or "
                                "empty directory")
        self.stages_dir.mkdir(parents=True, exist_ok=True)
        write_json_atomic(self.out / MARKER, {"version": STUDY_VERSION, "config": to_dict(self.cfg)}, default=str)

    def stage(self, name: str, inputs: dict, upstream: tuple[StageRecord, ...], func, **kwargs) -> StageRecord:
        """Run `func(work_dir, **kwargs) -> (outputs digest, extra manifest fields)` unless the stage
        with this key is done. The key is made of `inputs` (with what `stage_identity` adds) and the
        key and digest of each `upstream` stage; see the module docstring."""
        inputs = {**inputs, "upstream": {r.name: {"key": r.key, "digest": r.digest} for r in upstream}}
        key = _digest({"stage": name, "version": STUDY_VERSION, **inputs})[:16]
        final = self.stages_dir / f"{name}-{key}"
        partial = self.stages_dir / f"{name}-{key}.partial"
        rec = StageRecord(name, key, final)
        manifest_path = final / "manifest.json"
        if manifest_path.is_file():
            rec.manifest = json.loads(manifest_path.read_text())
            rec.status, rec.digest = "skipped", rec.manifest["digest"]
            self.say(f"{name}: skipped (done, key {key}, took {rec.manifest['seconds']} s when it ran)")
            self.records[name] = rec
            return rec
        resumed = partial.exists()
        partial.mkdir(parents=True, exist_ok=True)
        self.say(f"{name}: {'resuming' if resumed else 'running'} (key {key})")
        t0 = time.perf_counter()
        rec.dir = partial
        digest, extra = func(partial, **kwargs)
        rec.seconds = round(time.perf_counter() - t0, 2)
        rec.digest = digest
        rec.manifest = {"stage": name, "key": key, "compute": inputs.get("compute"), "inputs": inputs,
                        "digest": digest, "seconds": rec.seconds,
                        "finished": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), **extra}
        write_json_atomic(partial / "manifest.json", rec.manifest, default=str)
        if final.exists():  # a stale final directory without a manifest (cannot happen via rename) is replaced
            shutil.rmtree(final)
        os.replace(partial, final)
        rec.dir, rec.status = final, "ran"
        self.say(f"{name}: done in {rec.seconds} s")
        self.records[name] = rec
        return rec

    def summary(self) -> dict:
        return {n: {"key": r.key, "status": r.status, "seconds": r.seconds, "dir": str(r.dir),
                    "compute": r.manifest.get("compute")} for n, r in self.records.items()}


def _device_setup(cfg: StudyConfig):
    """The training stage's device choice (`run.amp`; by default bf16 autocast on CUDA, fp32 on the
    CPU); the stages after it run their networks in fp32 (`_eval_setup`)."""
    from study.device import resolve_device

    return resolve_device(device=cfg.run.device, threads=cfg.run.threads,
                          amp=None if cfg.run.amp == "default" else cfg.run.amp)


def _eval_setup(setup):
    """The same device without autocast: gate data, gates and evaluation are fp32 numbers."""
    import dataclasses

    return dataclasses.replace(setup, amp=False)


def eco_settings(cfg: StudyConfig):
    from study.eco.data import EcoSettings

    return EcoSettings(fusion=cfg.gates.fusion, power=cfg.evaluate.power, energy_scale=cfg.evaluate.energy_scale, loss_scale=cfg.evaluate.loss_scale,
                       rule=cfg.evaluate.rule, batch_size=cfg.train.batch_size, max_frames=cfg.gates.eco_max_frames)


# ----- the stages: each a function of its work directory and its inputs ----------------------


def generate_stage(work: Path, gcfg, workers: int, backend: str, progress: bool) -> tuple[str, dict]:
    """The dataset (`sensors.generate`) in work/data."""
    from sensors.generate import generate

    generate(gcfg, work / "data", workers=workers, progress=progress, backend=backend)
    manifest = work / "data" / "manifest.json"
    return file_sha256(manifest), {"frames": len(json.loads(manifest.read_text())["frames"])}


def train_stage(work: Path, data: Path, train_cfg: TrainSection, profile: str, setup, say,
                progress: bool) -> tuple[str, dict]:
    """The paper's branches in work/paper and, with early_fusion, the early-fusion models in work/early."""
    from study.train import TrainConfig, train

    t = train_cfg
    runs = {"paper": ("paper", t.branches)}
    if t.early_fusion:
        runs["early"] = ("early_fusion", t.early_branches)
    digests = {}
    for name, (bset, branches) in runs.items():
        say(f"train: {name} ({bset} branch set)")
        tc = TrainConfig(data=str(Path(data).resolve()), model_profile=profile, branch_set=bset,
                         branches=tuple(branches), epochs=t.epochs, batch_size=t.batch_size, lr=t.lr,
                         warmup_steps=t.warmup_steps, clip_grad=t.clip_grad, seed=t.seed,
                         checkpoint_steps=t.checkpoint_steps, eval_frames=t.eval_frames, threads=setup.threads,
                         protocol=t.protocol, device=setup.device, amp=setup.amp, workers=setup.workers,
                         gate_holdout=t.gate_holdout, model=tuple(t.model),
                         init_from=_init_from(t.init_from) if name == "paper" else "")
        train(tc, work / name, progress=progress)
        digests[name] = file_sha256(work / name / "checkpoint.pt")
    return _digest(digests), {"checkpoints_sha256": digests}


def _init_from(text: str) -> str:
    """train.init_from -> the run directory TrainConfig.init_from takes ("" stays "")."""
    if not text:
        return ""
    from study.reference_model import resolve_run

    run = resolve_run(text)
    if not (run / "checkpoint.pt").is_file():
        raise UserError(f"train.init_from {text!r}: neither a reference model (models/) nor a training run")
    return str(run.resolve())


def gatedata_stage(work: Path, run_paper: Path, data: Path, settings, batch_size: int, setup,
                   progress: bool, val_fraction: float = 0.15, seed: int = 0) -> tuple[str, dict]:
    """HydraFusion's gate dataset and EcoFusion's, cached under work/run (a farm of the paper run)."""
    from study.eco.data import build_eco_data
    from study.gate_data import GateData
    from study.scoring import frames_for, load_run

    run = work / "run"
    link_farm(run_paper, run)
    model, run_cfg = load_run(run, "latest", device=setup.device)
    train_idx, _ = frames_for(run_cfg, data, "train")
    gate_idx, _ = frames_for(run_cfg, data, "gate")
    test_idx, _ = frames_for(run_cfg, data, "test")
    gd = GateData(run, data, model)
    gd.ensure(sorted(train_idx + gate_idx + test_idx), batch_size=batch_size, progress=progress)
    eco = build_eco_data(run, data, settings, progress=progress, device=setup.device, val_fraction=val_fraction,
                         seed=seed)
    return _digest({"gate_data": gd.key, "eco_data": Path(eco["eco_data"]).name}), {
        "gate_data_key": gd.key, "eco_data": eco}


def gates_stage(work: Path, gatedata_run: Path, data: Path, gates: GatesSection, settings, setup, say,
                progress: bool) -> tuple[str, dict]:
    """The learned HydraFusion and EcoFusion gates and the latency table, under work/run."""
    import dataclasses

    from study.branch_gate_study import GateTrainConfig, train_gate
    from study.eco.config_gate_study import train_eco_gate
    from study.eco.latency_energy import energy_table

    g = gates
    run = work / "run"
    link_farm(gatedata_run, run)
    from study.scoring import frames_for
    from study.study_eval import IN_SAMPLE

    run_cfg = json.loads((run / "config.json").read_text())
    compare = g.compare_targets and g.targets != "train" and bool(frames_for(run_cfg, data, "gate")[0])
    out, digests = {}, {}
    for gate in g.gates:
        gate_cfg = GateTrainConfig(gate=gate, epochs=g.epochs, batch_size=g.batch_size, lr=g.lr,
                                   val_fraction=g.val_fraction, seed=g.seed, threads=setup.threads, targets=g.targets,
                                   context=g.context, pooling=g.pooling)
        in_sample = dataclasses.replace(gate_cfg, targets="train")
        say(f"gates: HydraFusion {gate} gate")
        out[f"hydra_{gate}"] = train_gate(run, data, gate_cfg, progress=progress, setup=setup)
        digests[f"hydra_{gate}"] = file_sha256(run / "gates" / gate / "gate.pt")
        if compare:
            say(f"gates: HydraFusion {gate} gate on the detectors' training frames (the comparison)")
            d = run / "gates" / gate / IN_SAMPLE
            out[f"hydra_{gate}_{IN_SAMPLE}"] = train_gate(run, data, in_sample, progress=progress, setup=setup, out=d)
            digests[f"hydra_{gate}_{IN_SAMPLE}"] = file_sha256(d / "gate.pt")
        say(f"gates: EcoFusion {gate} gate")
        out[f"eco_{gate}"] = train_eco_gate(run, data, gate, gate_cfg, settings, progress=progress)
        digests[f"eco_{gate}"] = file_sha256(run / "eco" / "gates" / gate / "gate.pt")
        if compare:
            say(f"gates: EcoFusion {gate} gate on the detectors' training frames (the comparison)")
            d = settings.gate_dir(run, gate) / IN_SAMPLE
            out[f"eco_{gate}_{IN_SAMPLE}"] = train_eco_gate(run, data, gate, in_sample, settings, progress=progress,
                                                          out=d)
            digests[f"eco_{gate}_{IN_SAMPLE}"] = file_sha256(d / "gate.pt")
    say("gates: latency and energy of every configuration")
    energy = energy_table(run, data, settings, threads=1, repeats=g.energy_repeats, frames=g.energy_frames,
                          progress=progress, n_check=g.energy_check)
    energy = {k: v for k, v in energy.items() if not k.startswith("_")}
    digests["latency"] = file_sha256(run / "eco" / "latency.json")
    return _digest(digests), {"gates": out, "energy": energy}


def evaluate_stage(work: Path, gates_run: Path, run_early: Path | None, data: Path, cfg: StudyConfig, settings,
                   setup, progress: bool) -> tuple[str, dict]:
    """Every method on the test split (`study.study_eval`) -> work/results.json (with the device
    type and precision it ran in)."""
    from study.device import compute_identity
    from study.study_eval import evaluate_study

    run = work / "run"
    link_farm(gates_run, run)
    res = evaluate_study(run, run_early, data, cfg, settings, work, setup=setup, progress=progress)
    res["compute"] = compute_identity(setup)
    write_json_atomic(work / "results.json", res, default=str)
    return file_sha256(work / "results.json"), {}


def report_stage(work: Path, results_dir: Path, context: dict, rel_to: Path) -> tuple[str, dict]:
    """report.md, report.html and report.json of the evaluation's results."""
    from study.report import write_report

    results = json.loads((Path(results_dir) / "results.json").read_text())
    write_report(results, context, work, results_dir, rel_to=rel_to)
    return file_sha256(work / "report.json"), {"files": sorted(p.name for p in work.iterdir())}


STAGE_CODE = {
    "generate": (("sensors.generate",), generate_stage),
    "train": (("study.train",), train_stage),
    "gatedata": (("study.scoring", "study.eco.data", "study.gate_data"), gatedata_stage),
    "gates": (("study.eco.latency_energy", "study.eco.config_gate_study", "study.branch_gate_study"), gates_stage),
    "evaluate": (("study.study_eval",), evaluate_stage),
    "report": (("study.report",), report_stage),
}
"""Per stage: the modules it runs and its stage function; their code is part of its key."""


def stage_identity(name: str, cfg: StudyConfig, setup) -> dict:
    """What stage `name`'s output depends on beyond its config section and its upstream stages:
    its code, its device type and precision, and (generate) the sensor model version and sensor
    profile, (train) the model profile's contents, (report) REPORT_VERSION."""
    from study.code_identity import code_digest
    from study.device import compute_identity

    modules, func = STAGE_CODE[name]
    out = {"code": code_digest(modules, (func,))[:16],
           "compute": compute_identity(device="cpu") if name in ("generate", "report") else compute_identity(setup)}
    if name == "generate":
        import sensors
        from sensors.rig import load_profile as sensor_profile

        out["sensor_model_version"] = sensors.SENSOR_MODEL_VERSION
        out["sensor_profile"] = _digest(to_dict(sensor_profile(cfg.profile)))[:16]
    elif name == "train":
        from fusion.nets import load_profile as model_profile

        out["model_profile"] = _digest(to_dict(model_profile(cfg.profile)))[:16]
        if cfg.train.init_from:  # the weights it starts from, not their name
            out["init_from_sha256"] = file_sha256(Path(_init_from(cfg.train.init_from)) / "checkpoint.pt")[:16]
    elif name == "report":
        import study.report

        out["report_version"] = study.report.REPORT_VERSION
    return out


def run_study(cfg: StudyConfig, out: str | Path, until: str = "report", progress: bool = True) -> dict:
    """Run (or continue) the study in `out` up to stage `until`; returns the stage summary and,
    when the report stage ran or was skipped, the report's JSON (every number of the report)."""
    if until not in STAGES:
        raise UserError(f"--until: unknown stage {until!r} (choose from: {', '.join(STAGES)})")
    study = Study(cfg, out, progress)
    study.prepare()
    setup = _device_setup(cfg)
    t_start = time.perf_counter()
    last = STAGES.index(until)
    result: dict = {"out": str(study.out)}

    eval_setup = _eval_setup(setup)

    def ident(name: str) -> dict:
        return stage_identity(name, cfg, setup if name == "train" else eval_setup)

    gcfg = cfg.data.generate_config(cfg.profile)
    gen = study.stage("generate", {"data": gcfg.to_dict(), **ident("generate")}, (), generate_stage,
                      gcfg=gcfg, workers=cfg.run.workers, backend=cfg.run.backend, progress=progress)
    data = gen.dir / "data"
    if last < 1:
        return _finish(study, result, t_start)

    tr = study.stage("train", {"profile": cfg.profile, "train": to_dict(cfg.train), **ident("train")}, (gen,),
                     train_stage, data=data, train_cfg=cfg.train, profile=cfg.profile, setup=setup, say=study.say,
                     progress=progress)
    run_early = tr.dir / "early" if cfg.train.early_fusion else None
    if last < 2:
        return _finish(study, result, t_start)

    settings = eco_settings(cfg)
    gdr = study.stage("gatedata", {"eco_max_frames": cfg.gates.eco_max_frames, "fusion": cfg.gates.fusion,
                                   "batch_size": cfg.train.batch_size, "val_fraction": cfg.gates.val_fraction,
                                   "seed": cfg.gates.seed, **ident("gatedata")}, (tr,),
                      gatedata_stage, run_paper=tr.dir / "paper", data=data, settings=settings,
                      batch_size=cfg.train.batch_size, setup=eval_setup, progress=progress,
                      val_fraction=cfg.gates.val_fraction, seed=cfg.gates.seed)
    if last < 3:
        return _finish(study, result, t_start)

    gt = study.stage("gates", {"gates": to_dict(cfg.gates), **ident("gates")}, (gdr,), gates_stage,
                     gatedata_run=gdr.dir / "run", data=data, gates=cfg.gates, settings=settings, setup=eval_setup,
                     say=study.say, progress=progress)
    if last < 4:
        return _finish(study, result, t_start)

    ev = study.stage("evaluate", {"evaluate": to_dict(cfg.evaluate), **ident("evaluate")}, (gt, tr),
                     evaluate_stage, gates_run=gt.dir / "run", run_early=run_early, data=data, cfg=cfg,
                     settings=settings, setup=eval_setup, progress=progress)
    if last < 5:
        return _finish(study, result, t_start)

    context = {"scale": cfg.scale, "meaningless": cfg.meaningless, "config": to_dict(cfg),
               "stages": {n: r.manifest for n, r in study.records.items()},
               "stage_dirs": {n: str(r.dir) for n, r in study.records.items()}}
    rp = study.stage("report", {"scale": cfg.scale, "meaningless": cfg.meaningless, **ident("report")}, (ev,),
                     report_stage, results_dir=ev.dir, context=context, rel_to=study.out)
    for name in ("report.md", "report.html", "report.json"):
        with atomic_path(study.out / name) as tmp:
            shutil.copyfile(rp.dir / name, tmp)
    result["report"] = {n: str(study.out / n) for n in ("report.md", "report.html", "report.json")}
    result["report_json"] = json.loads((study.out / "report.json").read_text())
    return _finish(study, result, t_start)


def _finish(study: Study, result: dict, t_start: float) -> dict:
    result["stages"] = study.summary()
    result["seconds"] = round(time.perf_counter() - t_start, 2)
    ran = [n for n, r in study.records.items() if r.status == "ran"]
    study.say(f"finished in {result['seconds']} s; ran: {', '.join(ran) or 'nothing (every stage was done)'}")
    return result
