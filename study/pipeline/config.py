"""The config of `hydrabench study CONFIG`: `StudyConfig` and its sections, as a preset
(configs/study/<name>.yaml) or a YAML file, loaded strictly (unknown keys and bad values are
`UserError`s naming the key)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import get_type_hints

from sensors.generate import GenerateConfig
from sim.config import from_dict, load_yaml
from sim.errors import UserError
from study.engine.device import MAX_WORKERS
from study.engine.gate_training import GateTrainConfig
from study.engine.train import TrainConfig  # torch: loading a study config imports it, `--help` does not
from study.pipeline.presets import PRESETS_DIR as PRESETS_DIR  # (where the presets are, for its readers)
from study.pipeline.presets import study_config_file
from study.pipeline.sections import CrossoverSection, PemSection, TransitionsSection, check_whole_sequences
from study.pipeline.sections import check_fusion as _fusion
from study.pipeline.sections import check_positive as _positive


class Shared:
    """The annotation of a section field that is its experiment config's field of the same name
    (`section_of`)."""


def section_of(source: type):
    """Class decorator: a frozen config section whose fields annotated `Shared` are `source`'s fields
    of the same name, with their type and default (a value written beside one is the study's own
    default) and their meaning in `source`'s docstring; a section whose source checks its fields
    when built (`__post_init__`) runs those checks through `source_config`. So each field is defined
    once, and a field renamed or dropped in `source` fails here, at import. The section's docstring
    gets the list of its shared fields."""

    def wrap(cls):
        hints = get_type_hints(source)
        fields = {f.name: f for f in dataclasses.fields(source)}
        own_defaults, annotations, shared = {}, {}, []
        for name, annotation in cls.__dict__.get("__annotations__", {}).items():
            if annotation not in (Shared, "Shared"):  # a string under `from __future__ import annotations`
                annotations[name] = annotation
                continue
            if name not in fields:
                raise TypeError(f"{cls.__name__}.{name}: {source.__name__} has no field {name!r}")
            annotations[name] = hints[name]
            shared.append(name)
            if name in cls.__dict__:
                own_defaults[name] = cls.__dict__[name]
            elif fields[name].default is dataclasses.MISSING:
                raise TypeError(f"{cls.__name__}.{name}: {source.__name__}.{name} has no default; give the study's")
            else:
                setattr(cls, name, fields[name].default)
        cls.__annotations__ = annotations
        cls.SOURCE = source
        cls.SHARED = tuple(shared)
        listed = ", ".join(f"{n} (here {own_defaults[n]!r})" if n in own_defaults else n for n in shared)
        cls.__doc__ = (cls.__doc__ or "").rstrip() + (
            f"\n\n    Fields shared with `{source.__module__}.{source.__name__}` (type, default and meaning "
            f"there): {listed}.\n    ")
        return dataclass(frozen=True)(cls)

    return wrap


def source_config(section, where: str, **fields):
    """`section`'s experiment config built from its shared fields and `fields` (the experiment's own,
    or a shared one's value as the experiment takes it), so that the experiment's checks refuse a
    bad value; its UserError is prefixed with `where`, the section's YAML key."""
    try:
        return section.SOURCE(**{**{n: getattr(section, n) for n in section.SHARED}, **fields})
    except UserError as exc:
        raise UserError(f"{where}: {exc}") from None


@dataclass(frozen=True)
class SetSection:
    """A gate or a test set generated apart from the detectors' data (`data.gate`, `data.test`): the
    contexts, severities, twins and sensor profile of `data`, with its own size and seed. Its own
    stage (`gateset`, `testset`) generates it, so enlarging it regenerates only it and reruns only
    what reads it (a gate set: the gate datasets, the gates and the evaluation; a test set: the
    evaluation), and retrains no detector (issue 36).

    Fields:
        frames_per_context: [frames] per context.
        sequence_length: [frames] per sequence (whole sequences are what the bootstrap draws).
        seed: the set's seed; differs from `data.seed` and from the other set's (a sequence is
            identified by its scenario and seed, and one sequence in two sets is refused).
    """

    frames_per_context: int
    sequence_length: int = 4
    seed: int = 1

    def __post_init__(self) -> None:
        _positive("frames_per_context", self.frames_per_context)
        _positive("sequence_length", self.sequence_length)
        _positive("seed", self.seed, 0)
        check_whole_sequences("frames_per_context", self.frames_per_context, self.sequence_length)


@section_of(GenerateConfig)
class DataSection:
    """The datasets (`sensors.generate.GenerateConfig`): one dataset, split by sequence into train
    and test by the training run; with `twins` every frame also has its clear-weather twin (only
    the condition differs), which the severity sweeps compare against. "all" contexts are the
    eight.

    Fields:
        gate: a gate set (`SetSection`) in place of the detectors' held-out gate split: the gates fit
            on it and every choice is made on its validation sequences (`gates.val_fraction`).
        test: a test set (`SetSection`) in place of the detectors' test split: every method is scored
            on it.
    Without them the study splits the one dataset (train, gate holdout, test) as before."""

    contexts: Shared = ("all",)
    frames_per_context: Shared
    sequence_length: Shared
    frame_rate_hz: Shared
    severities: Shared
    twins: Shared = True
    seed: Shared
    gate: SetSection | None = None
    test: SetSection | None = None

    def __post_init__(self) -> None:
        seeds = {"data.seed": self.seed}
        for name in ("gate", "test"):
            part = getattr(self, name)
            if part is None:
                continue
            if part.seed in seeds.values():
                other = next(k for k, v in seeds.items() if v == part.seed)
                raise UserError(f"data.{name}.seed {part.seed} is {other}'s: each set needs its own seed (a sequence "
                                "is identified by its scenario and seed)")
            seeds[f"data.{name}.seed"] = part.seed

    def generate_config(self, profile: str, part: str = "detectors") -> GenerateConfig:
        """The GenerateConfig of this section for sensor `profile` (its checks refuse a bad value):
        the detectors' dataset, or (`part` "gate" / "test") the gate or test set, which differs from it
        only in its size and seed."""
        from sim.scenario import CONTEXT_NAMES

        contexts = tuple(CONTEXT_NAMES) if tuple(self.contexts) == ("all",) else tuple(self.contexts)
        own = {} if part == "detectors" else dataclasses.asdict(getattr(self, part))
        return source_config(self, "data" if part == "detectors" else f"data.{part}", contexts=contexts,
                             profile=profile, severities=tuple(self.severities), **own)

    def parts(self) -> tuple[str, ...]:
        """The datasets of the study, in the order a view lists them (`sensors.combine`)."""
        return ("detectors", *(p for p in ("gate", "test") if getattr(self, p) is not None))


@section_of(TrainConfig)
class TrainSection:
    """Training (`study.engine.train`, HydraFusion 5.3): one run of the paper's branches (the single-sensor
    branches among them give Table 2 (i) and late fusion (iii)) and, with `early_fusion`, one run of
    the input-level early-fusion models (Table 2 (ii)). The study trains on the `reference` or
    `visible` protocol (it fuses in the right camera); its gate split is `gate_holdout`, which the
    gates learn from and every choice is made on.

    Fields:
        branches: branches of the paper set to train (empty = all seven).
        early_fusion: also train the early-fusion set (cameras, cameras + lidar, radar + lidar).
        early_branches: which of the early-fusion models (empty = all three).
        init_from: a reference model (a name in models/, `study.engine.reference_model`) or a run directory
            whose weights initialise the paper run (`train --init-from`; "" = from scratch). Its
            checkpoint's digest is part of the train stage's key.
        detectors: adopt finished detectors instead of training the paper run: a reference model
            (a name in models/) or a training run, trained on this study's `data` (its generation
            config must be the generated dataset's). Its checkpoint's digest is the train stage's
            key, so the paper branches are never trained again (""= train them); the early-fusion
            models still train (unless `early_detectors`). The other train fields then apply to what
            still trains.
        early_detectors: the same for the early-fusion run (its `early_branches`).
    """

    branches: Shared
    early_fusion: bool = True
    early_branches: tuple[str, ...] = ()
    epochs: Shared
    batch_size: Shared
    lr: Shared
    warmup_steps: Shared
    clip_grad: Shared
    seed: Shared
    checkpoint_steps: Shared
    eval_frames: Shared
    protocol: Shared
    gate_holdout: Shared
    model: Shared
    init_from: str = ""
    detectors: str = ""
    early_detectors: str = ""

    def __post_init__(self) -> None:
        if self.detectors and self.init_from:
            raise UserError("train.detectors adopts finished detectors; train.init_from starts training from "
                            "weights: give one of them")
        # TrainConfig checks its fields in `study.engine.train.check_config`, against the dataset, at train
        # time; the study refuses them here, before it generates anything
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


@section_of(GateTrainConfig)
class GatesSection:
    """Gate datasets and gates: HydraFusion's per-branch gates (`study.engine.gate_training`, Section 5.2.2) and
    EcoFusion's per-configuration gates (`study.eco`), and the latency table (Eq. 6). Every learned
    gate trains with the shared fields (HydraFusion 5.3: lr 5e-5; targets "auto": the gate split
    when train.gate_holdout > 0).

    Fields:
        gates: the learned gates to train (deep, attention); knowledge and the oracles need none.
        compare_targets: with a gate split, also train every gate on the detectors' own training
            frames (validated on the same gate-split frames), so the report measures what held-out
            targets change (under RUN/gates/<gate>/in_sample/ and RUN/eco/gates/<gate>/in_sample/).
        eco_max_frames: at most this many frames of each split for EcoFusion (0 = all).
        fusion: late fusion of an EcoFusion configuration (nms | soft-nms | wbf; EcoFusion 4.4: wbf).
        curve: fitting-frame counts below the gate set's (e.g. [96, 384]) at which each learned
            HydraFusion gate is trained again on fewer whole sequences per context
            (`GateTrainConfig.fit_frames`), validated and tested on the same frames: the learning
            curve of its regret against the best constant and the per-context constant.
        energy_frames, energy_repeats, energy_check: the latency measurement (eco-energy).
    """

    gates: tuple[str, ...] = ("deep", "attention")
    epochs: Shared
    batch_size: Shared
    lr: Shared
    val_fraction: Shared
    seed: Shared
    targets: Shared
    compare_targets: bool = True
    context: Shared
    pooling: Shared
    eco_max_frames: int = 0
    fusion: str = "wbf"
    energy_frames: int = 3
    energy_repeats: int = 3
    energy_check: int = 12
    curve: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        from fusion.nets.branch_gates import trainable_gates  # the gate registry says which gates learn

        if any(n < 1 for n in self.curve) or len(set(self.curve)) != len(self.curve):
            raise UserError(f"gates.curve: distinct frame counts >= 1, got {list(self.curve)}")

        if bad := [g for g in self.gates if g not in trainable_gates()]:
            raise UserError(f"gates.gates: {bad[0]!r} is not a learned gate (choose from: {', '.join(trainable_gates())})")
        # GateTrainConfig checks targets and pooling when built (below); these, the trainer assumes
        for name in ("epochs", "batch_size", "energy_frames", "energy_repeats"):
            _positive(f"gates.{name}", getattr(self, name))
        for name in ("eco_max_frames", "energy_check", "seed"):
            _positive(f"gates.{name}", getattr(self, name), 0)
        if not self.lr > 0:
            raise UserError(f"gates.lr must be > 0, got {self.lr}")
        if not 0 <= self.val_fraction < 1:
            raise UserError(f"gates.val_fraction must be in [0, 1), got {self.val_fraction}")
        _fusion("gates.fusion", self.fusion)
        for gate in self.gates or ("deep",):  # the shared fields, as each gate's GateTrainConfig
            source_config(self, "gates", gate=gate)


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
        fusion: the late fusion of every fused method (issue 36's one declared rule): "validation"
            (the best late fusion on the validation frames, used for every method; Tables 2 and 3
            choose per row) or nms | soft-nms | wbf, declared in advance for every method and every
            table; then gates.fusion (EcoFusion's configurations) must be the same.
        bootstrap: draws of whole test sequences for 95 % intervals of every method's mAP, overall
            and per context, and of every paired difference (`study.engine.scoring.context_bootstrap`;
            0 = none).
        interval: how the bootstrap draws test sequences (`fusion.intervals.DESIGNS`): "sequence",
            from all of them (each context's count varies between draws, though a test set holds a
            fixed number of each); "stratified", each context's n of its n; "rescaled", n - 1 of its n
            (Rao and Wu 1988: the design's variance at any n). The coverage check checks the same.
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
    fusion: str = "validation"
    interval: str = "sequence"

    def __post_init__(self) -> None:
        _positive("evaluate.k", self.k)
        from fusion.metrics import MAX_BOOTSTRAP

        if isinstance(self.bootstrap, bool) or not isinstance(self.bootstrap, int) or not 0 <= self.bootstrap <= MAX_BOOTSTRAP:
            raise UserError(f"evaluate.bootstrap must be an integer in [0, {MAX_BOOTSTRAP}], got {self.bootstrap!r}")
        from fusion.nets.branch_gates import trainable_gates

        allowed = ("knowledge", *trainable_gates())
        for name in ("hydra_gate", "eco_gate"):
            if getattr(self, name) not in allowed:
                raise UserError(f"evaluate.{name} must be {', '.join(allowed)}, got {getattr(self, name)!r}")
        _fusion("evaluate.fusion", self.fusion, "validation")
        from fusion.intervals import DESIGNS

        if self.interval not in DESIGNS:
            raise UserError(f"evaluate.interval must be {', '.join(DESIGNS)}, got {self.interval!r}")
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
        amp: precision of the train stage (`study.engine.device.resolve_amp`): "default" (bf16 autocast
            on CUDA, fp32 on the CPU), "auto" (bf16 where the device computes it natively: a GPU, or
            a CPU with AMX-BF16 or AVX512-BF16, `study.engine.device.native_bf16`), "bf16" or "off". The
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
        if self.workers > MAX_WORKERS:
            raise UserError(f"run.workers must be <= {MAX_WORKERS}, got {self.workers}")
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
        crossover: the crossover sweep and the physical knowledge gate (`CrossoverSection`); none
            without it (no crossover stage runs).
        transitions: gates with memory on weather that changes (`TransitionsSection`); none without
            it (no transitions stage runs).
        pem: the verdict over detector strength, a perception error model fitted on the gate frames
            (`PemSection`); none without it (no pem stage runs).
    The optional sections are in `study.pipeline.sections`.
    """

    scale: str = "custom"
    meaningless: bool = False
    profile: str = "cpu"
    data: DataSection = field(default_factory=DataSection)
    train: TrainSection = field(default_factory=TrainSection)
    gates: GatesSection = field(default_factory=GatesSection)
    evaluate: EvaluateSection = field(default_factory=EvaluateSection)
    run: RunSection = field(default_factory=RunSection)
    crossover: CrossoverSection | None = None
    transitions: TransitionsSection | None = None
    pem: PemSection | None = None

    def __post_init__(self) -> None:
        if not self.scale.strip():
            raise UserError("scale must name the study's scale")
        for part in self.data.parts():  # contexts, severities, profile, each set's size: refused here
            self.data.generate_config(self.profile, part)
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
        seeds = {self.data.seed: "data.seed", **{getattr(self.data, p).seed: f"data.{p}.seed"
                                                   for p in ("gate", "test") if getattr(self.data, p)}}
        for name in ("crossover", "transitions"):
            sec = getattr(self, name)
            if sec is None:
                continue
            clash = sorted(set(seeds) & set(sec.seeds()))
            if clash:
                raise UserError(f"{name}.seed {sec.seed}: its sets' seeds include {clash[0]}, {seeds[clash[0]]}; "
                                "each set needs its own")
            seeds.update({v: f"{name}.seed" for v in sec.seeds()})
        if self.pem is not None and self.data.gate is None and not self.train.gate_holdout:
            raise UserError("pem: the PEM is fitted on gate frames the detectors never trained on: give a gate set "
                            "(data.gate) or train.gate_holdout > 0")
        e = self.evaluate.fusion
        for name in ("crossover", "pem"):
            sec = getattr(self, name)
            if sec is not None and e != "validation" and e != sec.fusion:
                raise UserError(f"{name}.fusion {sec.fusion!r} differs from evaluate.fusion {e!r}: one declared "
                                "fusion for every method")


def load_study_config(spec: str) -> StudyConfig:
    """A preset name (configs/study/<name>.yaml) or a YAML file path -> StudyConfig (strict)."""
    return load_yaml(StudyConfig, study_config_file(spec))


def study_config_from_dict(data: dict) -> StudyConfig:
    return from_dict(StudyConfig, data, "study config")
