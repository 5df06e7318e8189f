"""Choices made on validation frames only, and the guard that refuses a choice reading test frames.

Every choice the study makes from data (a gate's training epoch and objective, the late-fusion
method of the fixed methods, HydraFusion Table 3's fusion per gate, L_f's weights) is made on the
validation frames (`gate_frames`): whole sequences, per context, carved (`validation_split`) from
the run's gate split when it has one (`study.engine.train.TrainConfig.gate_holdout`: training sequences the
detectors never saw), else from the frames the detectors trained on, which flatter the branches a
little. They are never test frames.

What a gate learns from (`gate_frames`' `targets`): "holdout", the gate split's other sequences, so
each branch's loss is the loss it has on frames it never saw, as on test frames; or "train", the
detectors' own training frames, where a branch that overfits looks better than it will be ("auto":
holdout when the run has a gate split). Either way the validation frames are the same, so the two
are compared on the same frames.

`SelectionLog` is the guard: it is built from the run's test indices, and every choice goes through
`choose(what, candidates, indices, ...)`, which raises `TestSplitLeak` when any index it is handed is
a test frame, and records what was chosen, among what, on how many frames and sequences. The
study's report prints that record ("What was chosen where").
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

TARGETS = ("auto", "holdout", "train")
"""Where a gate's per-branch targets come from (`gate_frames`)."""


class TestSplitLeak(RuntimeError):
    """A choice was about to read test frames."""

    __test__ = False  # not a pytest test class


@dataclass
class SelectionLog:
    """The run's test frames and every choice made so far (see the module docstring)."""

    test: frozenset[int]
    choices: list[dict] = field(default_factory=list)

    @classmethod
    def of(cls, test_indices: Iterable[int]) -> SelectionLog:
        return cls(frozenset(int(i) for i in test_indices))

    def check(self, indices: Iterable[int], what: str) -> list[int]:
        """`indices` as a list; TestSplitLeak when one of them is a test frame."""
        out = [int(i) for i in indices]
        leaked = sorted(self.test.intersection(out))
        if leaked:
            raise TestSplitLeak(f"{what}: {len(leaked)} of the {len(out)} frames it would be chosen on are test "
                                f"frames (first: dataset index {leaked[0]}); choices are made on validation frames")
        if not out:
            raise TestSplitLeak(f"{what}: no validation frames to choose on")
        return out

    def choose(self, what: str, candidates: Mapping[str, float], indices: Sequence[int], *, lower_is_better: bool,
               measure: str, sequences: int | None = None) -> str:
        """The best of `candidates` ({name: value measured on `indices`}), recorded. Ties go to the
        first candidate in order; a candidate whose value is None never wins."""
        idx = self.check(indices, what)
        valid = {k: v for k, v in candidates.items() if v is not None}
        if not valid:
            raise ValueError(f"{what}: no candidate has a value")
        pick = (min if lower_is_better else max)(valid, key=valid.get)
        self.choices.append({"what": what, "chosen": pick, "measure": measure, "on": "validation",
                             "frames": len(idx), "sequences": sequences,
                             "candidates": {k: (None if v is None else round(float(v), 6)) for k, v in candidates.items()}})
        return pick

    def record(self, what: str, chosen, indices: Sequence[int], measure: str, candidates: Mapping | None = None,
               sequences: int | None = None) -> None:
        """Record a choice made elsewhere (a gate's epoch and objective) on `indices`, after the check."""
        idx = self.check(indices, what)
        self.choices.append({"what": what, "chosen": chosen, "measure": measure, "on": "validation",
                             "frames": len(idx), "sequences": sequences, "candidates": dict(candidates or {})})


def sequences_of(reader, indices: Iterable[int]) -> int:
    """How many sequences (shards) `indices` come from."""
    frames = reader.manifest["frames"]
    return len({frames[int(i)]["shard"] for i in indices})


def validation_split(reader, indices, fraction: float, seed: int) -> tuple[list[int], list[int]]:
    """Split frames into (fit, validation) by sequence (shard), per context, deterministic in seed.
    A context with fewer than 3 sequences keeps them all for fitting."""
    from fusion.data import carve_sequences

    def count(n: int) -> int:
        return max(1, int(round(fraction * n))) if n >= 3 and fraction > 0 else 0

    return carve_sequences(reader, indices, count, np.random.default_rng([seed, 7]))


def fewer_frames(reader, indices, n: int, seed: int) -> list[int]:
    """About `n` of `indices` as whole sequences (shards), the same number from each context (at least
    one sequence each), the sequences of a context in a seeded order: a smaller fitting set of the
    same design, for the gates' learning curve (`GateTrainConfig.fit_frames`). All of them when `n`
    is not below their number."""
    from collections import defaultdict

    if n >= len(indices):
        return sorted(int(i) for i in indices)
    shards: dict = defaultdict(lambda: defaultdict(list))
    for i in indices:
        f = reader.manifest["frames"][int(i)]
        shards[f["context"]][f["shard"]].append(int(i))
    rng = np.random.default_rng([seed, 11])
    out: list[int] = []
    per_context = n / len(shards)
    for context in sorted(shards):
        names = sorted(shards[context])
        rng.shuffle(names)
        length = np.mean([len(shards[context][x]) for x in names])
        for name in names[:max(1, int(round(per_context / length)))]:
            out.extend(shards[context][name])
    return sorted(out)


@dataclass(frozen=True)
class GateFrames:
    """A run's frames as its gates use them: `fit` (what a gate learns from), `val` (what its epoch,
    its objective and the study's fusion methods are chosen on), `test`; `targets` resolved
    ("holdout" | "train") and `holdout` (whether the run has a gate split)."""

    targets: str
    holdout: bool
    fit: list[int]
    val: list[int]
    test: list[int]


def gate_frames(run_cfg: dict, data, targets: str = "auto", val_fraction: float = 0.15, seed: int = 0,
                who: str = "train-gate") -> GateFrames:
    """The fitting, validation and test frames of a run's gates (see the module docstring).

    With a gate split, the validation frames are `val_fraction` of its sequences per context
    (`validation_split`), whatever `targets`; "holdout" fits on the rest of the gate split, "train"
    on every frame the detectors trained on. Without one, "train" (and "auto") carve the validation
    frames from the detectors' training frames as before, and "holdout" is refused."""
    from sensors.dataset import DatasetReader
    from sim.errors import UserError
    from study.engine.scoring import frames_for, run_train_test

    if targets not in TARGETS:
        raise UserError(f"targets: expected one of {', '.join(TARGETS)}, got {targets!r}")
    train, test = run_train_test(run_cfg, data, who)
    gate, _ = frames_for(run_cfg, data, "gate")
    reader = DatasetReader(data)
    if targets == "auto":
        targets = "holdout" if gate else "train"
    if not gate:
        if targets == "holdout":
            raise UserError(f"{who}: targets 'holdout' need a gate split, and this run has none (train it with "
                            "--gate-holdout, or study train.gate_holdout > 0)")
        fit, val = validation_split(reader, train, val_fraction, seed)
        return GateFrames("train", False, fit, val, test)
    rest, val = validation_split(reader, gate, val_fraction, seed)
    fit = rest if targets == "holdout" else list(train)
    if not fit:
        raise UserError(f"{who}: val_fraction {val_fraction:g} leaves no gate-split sequence to fit on; lower it")
    return GateFrames(targets, True, fit, val, test)
