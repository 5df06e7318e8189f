"""A study config checked whole, before `hydrabench study` starts its first stage.

Each section's dataclass refuses its own bad values when it is loaded (`study.pipeline.config`); what no
section can see alone is checked here: references from one section to another (a gate the
evaluation uses must be one the gates stage trains) and references to things outside the config
(`train.init_from` must name a run or a reference model). A study refused here has created nothing;
one refused after its generate stage would have left a study folder and minutes of work behind.
"""

from __future__ import annotations

from pathlib import Path

from sim.errors import UserError

UNTRAINED_GATES = ("knowledge",)
"""Gates that need no training: the evaluation may use them whatever gates.gates lists."""


def check_study_config(cfg) -> None:
    """Refuse (UserError, one line naming the key) a `study.pipeline.config.StudyConfig` whose sections
    disagree or whose `train.init_from` or `train.detectors` resolves to nothing (or to detectors of
    another dataset)."""
    learned = tuple(cfg.gates.gates)
    twice = sorted({g for g in learned if learned.count(g) > 1})
    if twice:
        raise UserError(f"gates.gates names {twice[0]!r} twice")
    for key in ("hydra_gate", "eco_gate"):
        gate = getattr(cfg.evaluate, key)
        if gate not in UNTRAINED_GATES and gate not in learned:
            raise UserError(f"evaluate.{key}: {gate!r} is not among the gates gates.gates trains "
                            f"({', '.join(learned) or 'none'}); add it there or use knowledge")
    if cfg.evaluate.fusion != "validation" and cfg.evaluate.fusion != cfg.gates.fusion:
        raise UserError(f"evaluate.fusion {cfg.evaluate.fusion} is declared for every method, and gates.fusion "
                        f"{cfg.gates.fusion} would fuse EcoFusion's configurations otherwise: make them the same")
    if cfg.train.init_from:
        init_from_run(cfg.train.init_from)
    data = cfg.data.generate_config(cfg.profile).to_dict()
    if cfg.train.detectors:
        check_adopted(detectors_run(cfg.train.detectors), data, cfg.train.branches)
    if cfg.train.early_detectors:
        if not cfg.train.early_fusion:
            raise UserError("train.early_detectors: train.early_fusion is false (no early-fusion models to adopt)")
        check_adopted(detectors_run(cfg.train.early_detectors, "train.early_detectors"), data,
                      cfg.train.early_branches, "train.early_detectors")


def detectors_run(text: str, key: str = "train.detectors") -> Path:
    """train.detectors (or `key`) -> the run directory of the detectors to adopt (UserError otherwise)."""
    return init_from_run(text, key)


def check_adopted(run: Path, data_config: dict, branches, key: str = "train.detectors") -> dict:
    """The adopted run's config.json, refused (UserError) when it was trained on another dataset than
    the study's `data` (its splits would not be the study's: the detectors would be scored on frames
    they trained on) or holds other branches than `train.branches`."""
    import json

    cfg = json.loads((run / "config.json").read_text())
    theirs = json.loads(json.dumps(cfg.get("data_config") or {}))
    ours = json.loads(json.dumps(data_config))
    diff = sorted(k for k in ours.keys() | theirs.keys() if ours.get(k) != theirs.get(k))
    if diff:
        raise UserError(f"{key} {run}: trained on another dataset than the study's data section (differs in: "
                        f"{', '.join(diff)}); a study adopts detectors with the data section they were trained on")
    if branches and tuple(cfg.get("branches", ())) != tuple(branches):
        raise UserError(f"{key} {run}: its branches are {', '.join(cfg.get('branches', ()))}, "
                        f"{'train.branches' if key == 'train.detectors' else 'train.early_branches'} {', '.join(branches)}")
    return cfg


def init_from_run(text: str, key: str = "train.init_from") -> Path:
    """train.init_from (or `key`) -> the run directory whose checkpoint.pt is whole (UserError otherwise)."""
    from study.engine.checkpoints import checkpoint_problem
    from study.engine.reference_model import resolve_run

    try:
        run = resolve_run(text)
    except UserError as exc:
        raise UserError(f"{key} {text!r}: {exc}") from None
    ckpt = run / "checkpoint.pt"
    if not ckpt.is_file():
        raise UserError(f"{key} {text!r}: neither a reference model (models/, `hydrabench model list`) "
                        "nor a training run (no checkpoint.pt)")
    problem = checkpoint_problem(ckpt)
    if problem:
        raise UserError(f"{key} {text!r}: {ckpt} {problem}")
    return run
