"""The study's optional sections (`study.pipeline.config.StudyConfig`): each adds one stage of its own
(`crossover:`, `transitions:`, `pem:`), and none is required. Also the checks every section shares
(`check_fusion`, `check_positive`). Kept apart from `study.pipeline.config` so that each module stays a size a
newcomer can read; the config imports them from here."""

from __future__ import annotations

import math
from dataclasses import dataclass

from sim.errors import UserError


def check_fusion(where: str, value, *also: str) -> None:
    """A late-fusion method's label (`fusion.boxes.method_labels`), or one of `also`."""
    from fusion.boxes import method_labels

    if value not in (*also, *method_labels()):
        raise UserError(f"{where} must be {' or '.join((*also, *method_labels()))}, got {value!r}")


def check_positive(where: str, value, lo=1) -> None:
    if value < lo:
        raise UserError(f"{where} must be >= {lo}, got {value}")


def check_whole_sequences(where: str, frames: int, sequence_length: int) -> None:
    """UserError unless `frames` (the field `where`) is a whole number of sequences of `sequence_length`."""
    if frames % sequence_length:
        raise UserError(f"{where} {frames} is not a whole number of sequences of {sequence_length} frames")


@dataclass(frozen=True)
class CrossoverSection:
    """The crossover sweep (issue 37, `study.experiments.crossover`): at what physical severity fusing each
    sensor stops paying, on a sweep set of its own; its crossovers give the physical knowledge gate
    its rules (`study.experiments.physical_gate`), scored in the evaluation beside every other method.

    Fields:
        frames_per_step: [frames] per condition and severity level (whole sequences of
            `sequence_length`): each step's with-minus-without interval is drawn from its own
            sequences only.
        sequence_length: [frames] per sequence.
        frame_rate_hz: recording rate within a sequence [Hz] (as the detectors' data).
        seed: the sweep set's seed; level s is generated with seed + s, so seed + 1 .. seed + 5 must
            differ from every other set's seed.
        severities: the levels swept (1..5); each is a dataset of its own, as large as the others.
        conditions: the conditions swept (fog, rain, snow, night).
        fusion: the late fusion of every with and without set (nms | soft-nms | wbf), declared in
            advance; when evaluate.fusion is declared it must be the same.
        bootstrap: draws of whole sequences per step (95 % intervals and the crossing's interval).
        level: the intervals' coverage.
    """

    frames_per_step: int = 96
    sequence_length: int = 3
    frame_rate_hz: float = 2.0
    seed: int = 3000
    severities: tuple[int, ...] = (1, 2, 3, 4, 5)
    conditions: tuple[str, ...] = ("fog", "rain", "snow", "night")
    fusion: str = "soft-nms"
    bootstrap: int = 500
    level: float = 0.95

    def __post_init__(self) -> None:
        from fusion.physical_gate import CAR_QUANTITY

        check_positive("crossover.frames_per_step", self.frames_per_step)
        check_positive("crossover.sequence_length", self.sequence_length)
        check_positive("crossover.seed", self.seed, 0)
        check_positive("crossover.bootstrap", self.bootstrap)
        check_whole_sequences("crossover.frames_per_step", self.frames_per_step, self.sequence_length)
        if not self.severities or any(isinstance(s, bool) or s not in (1, 2, 3, 4, 5) for s in self.severities) \
                or list(self.severities) != sorted(set(self.severities)):
            raise UserError(f"crossover.severities must be distinct levels 1..5 in increasing order, got "
                            f"{list(self.severities)}")
        bad = [c for c in self.conditions if c not in CAR_QUANTITY]
        if bad or not self.conditions or len(set(self.conditions)) != len(self.conditions):
            raise UserError(f"crossover.conditions must be distinct names of {', '.join(CAR_QUANTITY)}, got "
                            f"{list(self.conditions)}")
        check_fusion("crossover.fusion", self.fusion)
        if not 0.5 <= self.level < 1:
            raise UserError(f"crossover.level must be in [0.5, 1), got {self.level}")

    def seeds(self) -> list[int]:
        from study.experiments.crossover import level_seed

        return [level_seed(self.seed, s) for s in self.severities]


@dataclass(frozen=True)
class TransitionsSection:
    """Gates with memory on weather that changes (issue 37 item 3, `study.experiments.transitions`): a set of
    long sequences whose weather ramps, one dataset per (part, kind), validation and test parts with
    their own seeds; each learned HydraFusion gate per frame, with hysteresis and with an EMA of its
    scores (each parameter chosen on the validation part), the best constant and the a-posteriori
    oracle, scored per test sequence.

    Fields:
        duration_s: [s] per sequence (issue 37: at least 30 s).
        frame_rate_hz: [Hz] within a sequence.
        sequences: per condition and kind, in the test part.
        validation_sequences: per condition and kind, in the validation part.
        conditions: those with a ramp (fog, rain, snow; night has none).
        kinds: onset | clearing | bank.
        severities: the levels the ramps reach (drawn per sequence).
        seed: the part and kind datasets get seed + 10 * kind index (+ 5 for validation).
        radius: [frames] either side of a change of the best branch: the transition window.
        margins: hysteresis margins (in predicted-loss units) chosen among on validation.
        alphas: EMA weights of the newest frame chosen among on validation (1 = no memory).
        bootstrap: draws of test sequences for the intervals.
        recurrent_epochs: epochs of the recurrent gate (`fusion.nets.recurrent_gate`) on the gate set's
            fitting sequences (the epoch kept: lowest regret on its validation sequences); 0: none.
        recurrent_hidden: its GRU state width.
        windows: [frames] how much of the past the recurrent gate runs over on a transition sequence,
            chosen among on the validation part (0: the whole sequence from its first frame).
    """

    duration_s: float = 30.0
    frame_rate_hz: float = 2.0
    sequences: int = 2
    validation_sequences: int = 1
    conditions: tuple[str, ...] = ("fog", "rain", "snow")
    kinds: tuple[str, ...] = ("onset", "clearing", "bank")
    severities: tuple[int, ...] = (4, 5)
    seed: int = 4000
    radius: int = 3
    margins: tuple[float, ...] = (0.0, 0.02, 0.05, 0.1, 0.2)
    alphas: tuple[float, ...] = (1.0, 0.7, 0.5, 0.3, 0.2)
    bootstrap: int = 500
    recurrent_epochs: int = 60
    recurrent_hidden: int = 32
    windows: tuple[int, ...] = (2, 4, 8, 0)

    def __post_init__(self) -> None:
        from study.experiments.transitions import check_section

        check_section(self)

    def seeds(self) -> list[int]:
        from study.experiments.transitions import PARTS, part_seed

        return [part_seed(self.seed, p, k) for p in PARTS for k in self.kinds]


@dataclass(frozen=True)
class PemSection:
    """The verdict over detector strength (issue 49 item 3, `study.experiments.pem_section`): a perception
    error model (`fusion.pem`, docs/pem.md) fitted on the study's detectors' predictions on the gate
    split's (or gate set's) fitting frames, never a test frame, then drawn at each strength on the test
    frames and on the gate frames the study chooses on (`gates.val_fraction`, `gates.seed`; the fitting
    frames where those carve none), and the sweep (`study.experiments.pem_sweep.sweep`): all_branches
    minus late, the knowledge gate, the per-context constant and the physical gate minus all_branches
    (both chosen on the gate frames), room for context and the a-posteriori oracles, each with its 95 %
    interval, per strength.

    Fields:
        strengths: [1] the strengths swept, distinct and > 0: the odds of detection times s, box error
            and false-alarm rates divided by s (`fusion.pem`); 1 is the fitted model.
        seed: the draws' seed on the test frames; the gate frames are drawn with seed + 1.
        bootstrap: [draws] of whole test sequences for each comparison's 95 % interval (>= 1).
        fusion: the late fusion of every fused method (nms | soft-nms | wbf), declared in advance; when
            evaluate.fusion is declared it must be the same.
    """

    strengths: tuple[float, ...] = (0.5, 1.0, 2.0, 4.0)
    seed: int = 0
    bootstrap: int = 500
    fusion: str = "soft-nms"

    def __post_init__(self) -> None:
        from fusion.metrics import MAX_BOOTSTRAP

        s = self.strengths
        if not s or any(isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) or x <= 0
                        for x in s) or len(set(s)) != len(s):
            raise UserError(f"pem.strengths must be distinct finite numbers > 0, got {list(s)}")
        object.__setattr__(self, "strengths", tuple(float(x) for x in s))
        if isinstance(self.seed, bool) or not isinstance(self.seed, int):
            raise UserError(f"pem.seed must be an integer, got {self.seed!r}")
        check_positive("pem.seed", self.seed, 0)
        if isinstance(self.bootstrap, bool) or not isinstance(self.bootstrap, int) or \
                not 1 <= self.bootstrap <= MAX_BOOTSTRAP:
            raise UserError(f"pem.bootstrap must be an integer in [1, {MAX_BOOTSTRAP}], got {self.bootstrap!r}")
        check_fusion("pem.fusion", self.fusion)
