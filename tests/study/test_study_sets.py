"""A study's gate and test sets generated apart from the detectors' data (`data.gate`, `data.test`,
issue 36): each is its own stage with its own key, so enlarging one regenerates only it and reruns
only what reads it, never the detectors' training; and `train.detectors` adopts finished detectors
(by their checkpoint's digest) instead of training them.

The keys are tested with stand-in stages (as tests/study/test_study_keys.py); the real stages on
these sets run end to end in test_study_runner.py's tiny study with sets."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import pytest

import study.pipeline.stages as stages
from sim.errors import UserError
from study.engine.device import DeviceSetup
from study.pipeline.config import SetSection, load_study_config, study_config_from_dict
from study.pipeline.stages import STAGES, run_study


@pytest.fixture
def fake_stages(monkeypatch):
    """Each stage's work replaced by a stand-in that records the stage's name (from its record)."""
    from study.pipeline import cache as stage_cache

    ran: list[str] = []

    def stand_in(name):
        def work(work_dir: Path, **kwargs):
            if name == "generate":
                (work_dir / "data").mkdir()
            if name == "report":
                for f in ("report.md", "report.html", "report.json"):
                    (work_dir / f).write_text("{}")
            if name == "train":  # as train_stage: the digest of its checkpoints' digests
                t = kwargs["train_cfg"]
                cps = {"paper": "sha-of-paper", **({"early": f"sha-of-early-{t.epochs}"} if t.early_fusion else {})}
                return stage_cache.json_digest(cps), {"checkpoints_sha256": cps}
            return f"digest-of-{work_dir.name.split('-')[0]}", {}

        return work

    real = stage_cache.Study.stage

    def recording(self, name, inputs, upstream, func, **kwargs):
        rec = real(self, name, inputs, upstream, func, **kwargs)
        if rec.status == "ran":
            ran.append(name)
        return rec

    for name in STAGES:
        monkeypatch.setattr(stages, f"{name}_stage", stand_in(name))
    monkeypatch.setattr(stage_cache.Study, "stage", recording)
    monkeypatch.setattr(stages, "_device_setup", lambda cfg: DeviceSetup(device="cpu", threads=1, amp=False))
    return ran


GATE, TEST = SetSection(4, 2, 11), SetSection(4, 2, 12)


def _with_sets(cfg, gate=GATE, test=TEST):
    return dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, gate=gate, test=test))


def test_enlarging_the_test_set_reruns_only_its_generation_and_evaluation(fake_stages, tmp_path):
    cfg = _with_sets(load_study_config("tiny"))
    first = run_study(cfg, tmp_path / "s", progress=False)
    assert fake_stages == ["generate", "gateset", "testset", "train", "gatedata", "gates", "crossover", "evaluate",
                           "pem", "transitions", "report"]
    fake_stages.clear()
    bigger = _with_sets(load_study_config("tiny"), test=SetSection(8, 2, 12))
    again = run_study(bigger, tmp_path / "s", progress=False)
    assert fake_stages == ["testset", "evaluate", "pem", "report"]  # (the pem stage draws on the test frames)
    for name in ("generate", "gateset", "train", "gatedata", "gates"):
        assert again["stages"][name]["key"] == first["stages"][name]["key"], name


def test_enlarging_the_gate_set_reruns_the_gates_and_below_and_trains_nothing(fake_stages, tmp_path):
    run_study(_with_sets(load_study_config("tiny")), tmp_path / "s", progress=False)
    fake_stages.clear()
    run_study(_with_sets(load_study_config("tiny"), gate=SetSection(8, 2, 11)), tmp_path / "s", progress=False)
    assert fake_stages == ["gateset", "gatedata", "gates", "evaluate", "pem", "transitions", "report"]


def test_adding_or_retraining_the_early_fusion_model_reruns_no_gate_stage(fake_stages, tmp_path):
    """The gate stages read the paper's branches alone (`stages._paper_view`): the early-fusion
    model is evaluated, never read by the gate data or the gates."""
    tiny = _with_sets(load_study_config("tiny"))
    without = dataclasses.replace(tiny, train=dataclasses.replace(tiny.train, early_fusion=False))
    first = run_study(without, tmp_path / "s", progress=False)
    fake_stages.clear()
    second = run_study(tiny, tmp_path / "s", progress=False)
    assert fake_stages == ["train", "evaluate", "report"]
    fake_stages.clear()
    longer = dataclasses.replace(tiny, train=dataclasses.replace(tiny.train, epochs=tiny.train.epochs + 1))
    run_study(longer, tmp_path / "s", progress=False)  # the paper's branches train again too: everything below
    assert fake_stages == ["train", "gatedata", "gates", "crossover", "evaluate", "pem", "transitions", "report"]
    for name in ("gatedata", "gates"):
        assert second["stages"][name]["key"] == first["stages"][name]["key"], name
    assert second["stages"]["train"]["key"] != first["stages"]["train"]["key"]


def test_a_larger_sweep_set_reruns_the_crossover_and_the_evaluation_only_and_none_runs_without_it(fake_stages,
                                                                                                  tmp_path):
    tiny = _with_sets(load_study_config("tiny"))
    run_study(tiny, tmp_path / "s", progress=False)
    fake_stages.clear()
    more = dataclasses.replace(tiny, crossover=dataclasses.replace(tiny.crossover, frames_per_step=2))
    run_study(more, tmp_path / "s", progress=False)
    assert fake_stages == ["crossover", "evaluate", "report"]
    fake_stages.clear()
    run_study(dataclasses.replace(tiny, crossover=None), tmp_path / "s2", progress=False)
    assert "crossover" not in fake_stages and "evaluate" in fake_stages


def test_a_study_without_sets_has_the_stages_it_had(fake_stages, tmp_path):
    run_study(load_study_config("tiny"), tmp_path / "s", progress=False)
    assert fake_stages == list(STAGES)


def test_the_sets_are_checked_when_the_config_is_loaded():
    base = {"data": {"frames_per_context": 4, "sequence_length": 2, "seed": 3}}
    with pytest.raises(UserError, match=r"data.test.seed 3 is data.seed's"):
        study_config_from_dict({"data": {**base["data"], "test": {"frames_per_context": 4, "seed": 3}}})
    with pytest.raises(UserError, match=r"data.test.seed 5 is data.gate.seed's"):
        study_config_from_dict({"data": {**base["data"], "gate": {"frames_per_context": 4, "seed": 5},
                                         "test": {"frames_per_context": 4, "seed": 5}}})
    with pytest.raises(UserError, match="not a whole number of sequences"):
        study_config_from_dict({"data": {**base["data"], "gate": {"frames_per_context": 5, "sequence_length": 2}}})
    with pytest.raises(UserError, match="unknown key 'frames'"):
        study_config_from_dict({"data": {**base["data"], "gate": {"frames": 5}}})
    cfg = study_config_from_dict({"data": {**base["data"], "test": {"frames_per_context": 6, "sequence_length": 3,
                                                                    "seed": 9}}})
    assert cfg.data.parts() == ("detectors", "test")
    g = cfg.data.generate_config(cfg.profile, "test")
    own = cfg.data.generate_config(cfg.profile)
    assert (g.frames_per_context, g.sequence_length, g.seed) == (6, 3, 9)
    assert dataclasses.replace(g, frames_per_context=4, sequence_length=2, seed=3) == own  # nothing else differs


def test_the_verdict_preset_sizes_its_sets_for_the_question():
    cfg = load_study_config("cpu-verdict")
    contexts = len(cfg.data.generate_config(cfg.profile).contexts)
    gate, test = cfg.data.gate, cfg.data.test
    assert gate.frames_per_context * contexts >= 1536 and (test.frames_per_context // test.sequence_length) * contexts >= 384
    fit_sequences = (gate.frames_per_context // gate.sequence_length) * (1 - cfg.gates.val_fraction)
    assert fit_sequences * gate.sequence_length * contexts >= 1536  # the learning curve's largest size
    assert cfg.train.detectors and cfg.gates.energy_frames >= 32


def _run_of(tmp_path: Path, data_config: dict, branches=("radar", "camera_right", "lidar")) -> Path:
    run = tmp_path / "run"
    run.mkdir()
    (run / "checkpoint.pt").write_bytes(b"weights")
    (run / "config.json").write_text(json.dumps({"data_config": data_config, "branches": list(branches)}))
    return run


def test_adopted_detectors_must_come_from_the_studys_data(tmp_path):
    from study.pipeline.checks import check_adopted

    cfg = load_study_config("tiny")
    mine = cfg.data.generate_config(cfg.profile).to_dict()
    run = _run_of(tmp_path, {**mine, "seed": 99})
    with pytest.raises(UserError, match=r"another dataset .*differs in: seed"):
        check_adopted(run, mine, cfg.train.branches)
    (run / "config.json").write_text(json.dumps({"data_config": mine, "branches": ["radar"]}))
    with pytest.raises(UserError, match="its branches are radar"):
        check_adopted(run, mine, cfg.train.branches)


def test_the_train_stage_adopts_detectors_and_keys_them_by_digest(tmp_path, monkeypatch):
    from study.pipeline.stages import stage_identity, train_stage

    cfg = load_study_config("tiny")
    mine = cfg.data.generate_config(cfg.profile).to_dict()
    run = _run_of(tmp_path, mine)
    data = tmp_path / "data"
    data.mkdir()
    monkeypatch.setattr("sensors.dataset.read_manifest", lambda root: {"config": mine} if Path(root) == data else {})
    monkeypatch.setattr("study.pipeline.checks.init_from_run", lambda text, key="": Path(text))
    t = dataclasses.replace(cfg.train, detectors=str(run), early_fusion=False)
    said = []
    digest, extra = train_stage(tmp_path / "work", data, t, cfg.profile, None, said.append, progress=False)
    assert (tmp_path / "work" / "paper" / "checkpoint.pt").read_bytes() == b"weights"
    copied = json.loads((tmp_path / "work" / "paper" / "config.json").read_text())
    assert copied["adopted_from"] == str(run) and copied["data"] == str(data.resolve())
    assert "adopting" in said[0] and list(extra["checkpoints_sha256"]) == ["paper"]
    setup = DeviceSetup(device="cpu", threads=1, amp=False)
    ident = stage_identity("train", dataclasses.replace(cfg, train=t), setup)
    other = tmp_path / "elsewhere"
    shutil.copytree(run, other)  # the same weights elsewhere: the same identity
    assert stage_identity("train", dataclasses.replace(cfg, train=dataclasses.replace(t, detectors=str(other))),
                          setup)["detectors_sha256"] == ident["detectors_sha256"]
    (other / "checkpoint.pt").write_bytes(b"other weights")
    assert stage_identity("train", dataclasses.replace(cfg, train=dataclasses.replace(t, detectors=str(other))),
                          setup)["detectors_sha256"] != ident["detectors_sha256"]
    with pytest.raises(UserError, match="give one of them"):
        dataclasses.replace(t, init_from="cpu-ref")


def test_the_train_stage_adopts_the_early_fusion_models_too(tmp_path, monkeypatch):
    from study.pipeline.checks import check_study_config
    from study.pipeline.stages import train_stage

    cfg = load_study_config("tiny")
    mine = cfg.data.generate_config(cfg.profile).to_dict()
    paper = _run_of(tmp_path, mine)
    early = tmp_path / "early_run"
    shutil.copytree(paper, early)
    (early / "config.json").write_text(json.dumps({"data_config": mine, "branches": ["early_radar_lidar"]}))
    data = tmp_path / "data"
    monkeypatch.setattr("sensors.dataset.read_manifest", lambda root: {"config": mine} if Path(root) == data else {})
    monkeypatch.setattr("study.pipeline.checks.init_from_run", lambda text, key="": Path(text))
    t = dataclasses.replace(cfg.train, detectors=str(paper), early_detectors=str(early))
    said = []
    digest, extra = train_stage(tmp_path / "work", data, t, cfg.profile, None, said.append, progress=False)
    assert sorted(extra["checkpoints_sha256"]) == ["early", "paper"] and len(said) == 2
    assert json.loads((tmp_path / "work" / "early" / "config.json").read_text())["branches"] == ["early_radar_lidar"]
    check_study_config(dataclasses.replace(cfg, train=t))
    with pytest.raises(UserError, match=r"train.early_detectors .*its branches are radar"):
        check_study_config(dataclasses.replace(cfg, train=dataclasses.replace(t, early_detectors=str(paper))))
    with pytest.raises(UserError, match="early_fusion is false"):
        check_study_config(dataclasses.replace(cfg, train=dataclasses.replace(t, early_fusion=False)))
