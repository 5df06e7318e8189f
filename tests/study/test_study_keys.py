"""What reruns when: every kind of change reruns exactly the stages below it and nothing else.

The stages' work is replaced by recording stand-ins (the keys are what is tested, and the real
stages are run end to end in test_study_runner.py): each test runs the study once, changes one
thing (the sensor model version, the model profile, the code of a module, the device type, the
precision) and runs it again in the same directory.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

import study.pipeline.stages as stages
from study.engine.device import DeviceSetup
from study.pipeline.config import load_study_config
from study.pipeline.stages import STAGES, run_study


@pytest.fixture
def fake_stages(monkeypatch):
    """Replace each stage's work by a stand-in that records that it ran and writes what run_study reads."""
    ran: list[str] = []

    def stand_in(name):
        def work(work_dir: Path, **kwargs):
            ran.append(name)
            if name == "generate":
                (work_dir / "data").mkdir()
            if name == "report":
                for f in ("report.md", "report.html", "report.json"):
                    (work_dir / f).write_text("{}")
            return f"digest-of-{name}", {}

        return work

    for name in STAGES:
        monkeypatch.setattr(stages, f"{name}_stage", stand_in(name))
    return ran


def _setup(device="cpu", amp=False):
    return lambda cfg: DeviceSetup(device=device, threads=1, amp=amp)


def _rerun(tmp_path, ran, monkeypatch, change, setup=None) -> list[str]:
    """Stages that ran again after `change()` (the first run in the same directory ran them all)."""
    cfg = load_study_config("tiny")
    monkeypatch.setattr(stages, "_device_setup", setup or _setup())
    first = run_study(cfg, tmp_path / "study", progress=False)
    assert ran == list(STAGES) and {s["status"] for s in first["stages"].values()} == {"ran"}
    ran.clear()
    assert run_study(cfg, tmp_path / "study", progress=False) and ran == []  # nothing changed: no work
    change()
    again = run_study(cfg, tmp_path / "study", progress=False)
    assert [n for n, s in again["stages"].items() if s["status"] == "ran"] == ran
    for n, s in again["stages"].items():  # a skipped stage kept its key, a rerun one has a new key
        assert (s["key"] == first["stages"][n]["key"]) == (s["status"] == "skipped"), n
    return list(ran)


def test_a_new_sensor_model_version_reruns_every_stage(fake_stages, tmp_path, monkeypatch):
    import sensors

    assert _rerun(tmp_path, fake_stages, monkeypatch,
                  lambda: monkeypatch.setattr(sensors, "SENSOR_MODEL_VERSION", "5")) == list(STAGES)


def test_changed_model_profile_contents_rerun_train_and_below(fake_stages, tmp_path, monkeypatch):
    import fusion.nets

    real = fusion.nets.load_profile

    def changed():  # the same profile name, one number of its contents changed
        monkeypatch.setattr(fusion.nets, "load_profile", lambda name, **kw: dataclasses.replace(
            real(name, **kw), rpn_nms_thresh=real(name, **kw).rpn_nms_thresh + 0.01))

    assert _rerun(tmp_path, fake_stages, monkeypatch, changed) == list(STAGES[1:])


@pytest.mark.parametrize("module, first", [("study.report.build", "report"), ("study.engine.gate_training", "gates"),
                                           ("study.engine.train", "train"), ("sensors.generate", "generate")])
def test_changed_code_of_a_module_reruns_the_first_stage_that_runs_it_and_below(fake_stages, tmp_path, monkeypatch,
                                                                              module, first):
    import study.engine.code_identity as ci

    real = ci.read_module

    def changed():
        monkeypatch.setattr(ci, "read_module", lambda m: real(m) + ("\n_CHANGED = 1\n" if m == module else ""))

    below = list(STAGES[STAGES.index(first):])
    if first in ("gatedata", "gates"):  # the crossover stage reads the detectors and its own sweep set only
        below.remove("crossover")
    assert _rerun(tmp_path, fake_stages, monkeypatch, changed) == below


def test_a_changed_comment_or_docstring_reruns_nothing(fake_stages, tmp_path, monkeypatch):
    import study.engine.code_identity as ci

    real = ci.read_module

    def changed():
        monkeypatch.setattr(ci, "read_module", lambda m: '"""Another docstring."""\n# a comment\n' +
                            real(m).split('"""', 2)[2] if m == "study.engine.train" else real(m))

    assert _rerun(tmp_path, fake_stages, monkeypatch, changed) == []


def test_another_device_reruns_every_stage_that_runs_a_network(fake_stages, tmp_path, monkeypatch):
    assert _rerun(tmp_path, fake_stages, monkeypatch,
                  lambda: monkeypatch.setattr(stages, "_device_setup", _setup("cuda:0"))) == list(STAGES[1:])


def test_another_precision_reruns_every_stage_that_runs_a_network(fake_stages, tmp_path, monkeypatch):
    assert _rerun(tmp_path, fake_stages, monkeypatch,
                  lambda: monkeypatch.setattr(stages, "_device_setup", _setup("cuda:0", amp=True)),
                  setup=_setup("cuda:0")) == list(STAGES[1:])


def test_every_stage_records_its_device_and_precision(fake_stages, tmp_path, monkeypatch):
    monkeypatch.setattr(stages, "_device_setup", _setup("cuda:3", amp=True))
    r = run_study(load_study_config("tiny"), tmp_path / "study", progress=False)
    for name, s in r["stages"].items():
        manifest = json.loads((Path(s["dir"]) / "manifest.json").read_text())
        # training in bf16 on the GPU; gate data, gates and evaluation in fp32 unless asked
        want = {"device": "cpu", "precision": "fp32"} if name in ("generate", "report") else \
            {"device": "cuda", "precision": "bf16" if name == "train" else "fp32"}
        assert manifest["compute"] == s["compute"] == want, name
        assert manifest["inputs"]["code"] and manifest["key"] == s["key"]


def test_train_model_overrides_and_init_from_are_checked_and_keyed(tmp_path, monkeypatch):
    """train.model is refused at load when malformed; train.init_from resolves a reference model (or run) and
    the train stage's identity carries its checkpoint's digest, not its name."""
    import shutil

    from sim.errors import UserError
    from study.engine import reference_model as rm
    from study.pipeline.stages import _init_from, stage_identity

    cfg = load_study_config("tiny")
    with pytest.raises(UserError, match="fixed by the dataset"):
        dataclasses.replace(cfg.train, model=("camera.size=[1, 2]",))
    with pytest.raises(UserError, match="neither a reference model"):
        _init_from(str(tmp_path / "nothing"))
    monkeypatch.setenv("HYDRABENCH_CACHE", str(tmp_path / "cache"))
    assert _init_from("") == ""
    resolved = _init_from("cpu-ref")  # the committed model, by name: its verified cache copy
    assert resolved.startswith(str(tmp_path / "cache")) and (rm.Path(resolved) / "checkpoint.pt").is_file()
    setup = DeviceSetup(device="cpu", threads=1, amp=False)
    plain = stage_identity("train", cfg, setup)
    warm = stage_identity("train", dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, init_from="cpu-ref")),
                          setup)
    assert "init_from_sha256" not in plain
    digest = json.loads((rm.MODEL_DIR / "cpu-ref" / "manifest.json").read_text())["files"]["checkpoint.pt"]["sha256"]
    assert warm["init_from_sha256"] == digest[:16]
    other = tmp_path / "copy"  # the same weights under another path: the same identity
    shutil.copytree(rm.MODEL_DIR / "cpu-ref", other)
    again = stage_identity("train", dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, init_from=str(other))),
                           setup)
    assert again["init_from_sha256"] == warm["init_from_sha256"]


def test_no_stage_above_evaluate_holds_evaluation_code_in_its_key():
    """A change to the evaluation (study.pipeline.evaluation, study.experiments.bounds, the report) reruns evaluate and
    report only: the gates stage once imported a string constant from study.pipeline.evaluation, and every
    change of the evaluation retrained the gates."""
    import inspect
    import textwrap

    import study.pipeline.stages as st
    from study.engine.code_identity import _imports, closure

    evaluation = {"study.pipeline.evaluation", "study.experiments.bounds", "study.report.build", "study.experiments.energy_front", "study.report.verdict"}
    for name in ("generate", "train", "gatedata", "gates"):
        modules, func = st.STAGE_CODE[name]
        entry = set(modules) | set(_imports(func.__module__, textwrap.dedent(inspect.getsource(func))))
        assert not evaluation & set(closure(sorted(entry))), name
