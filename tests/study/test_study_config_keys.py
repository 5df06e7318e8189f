"""The stage keys of every preset are what they were before the config sections were derived from
the experiments' configs (issue 38): a refactoring of the config may not rerun a finished study.

A stage key hashes the stage's config inputs and, through `stage_identity`, the code, the device and
the profiles (`study.pipeline.stages` module docstring). Only the config part is a function of the config
alone, so the test takes that part: `stage_identity` returns nothing and the stages are stand-ins
that return fixed digests. `data/study_config_keys.json` holds, per preset (and for an empty config) and stage, the inputs and
the key computed by the code before the change (`python -m tests.study.test_study_config_keys` from
the checkout's root rewrites it; do that only for a change that is meant to rerun studies).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

import study.pipeline.cache as stage_cache
import study.pipeline.stages as stages
from study.engine.device import DeviceSetup
from study.pipeline.config import PRESETS_DIR, StudyConfig, load_study_config

FIXTURE = Path(__file__).parent / "data" / "study_config_keys.json"
DEFAULTS = "(defaults)"
"""An empty config: every field's default."""
PRESETS = sorted(p.stem for p in PRESETS_DIR.glob("*.yaml")) + [DEFAULTS]


def config_keys(preset: str, out: Path, patch) -> dict:
    """{stage: {"key": ..., "inputs": ...}} of `preset` with stand-in stages and no stage identity."""
    seen = {}

    def stand_in(name):
        def work(work_dir: Path, **kwargs):
            if name == "generate":
                (work_dir / "data").mkdir()
            if name == "report":
                for f in ("report.md", "report.html", "report.json"):
                    (work_dir / f).write_text("{}")
            if name == "train":  # the paper's checkpoint digest: what the gate stages read (stages._paper_view)
                return f"digest-of-{name}", {"checkpoints_sha256": {"paper": "digest-of-paper"}}
            return f"digest-of-{name}", {}
        return work

    real_stage = stage_cache.Study.stage

    def recording_stage(self, name, inputs, upstream, func, **kwargs):
        rec = real_stage(self, name, inputs, upstream, func, **kwargs)
        seen[name] = {"key": rec.key, "inputs": json.loads(json.dumps(inputs, sort_keys=True, default=str))}
        return rec

    for name in stages.STAGES:
        patch(stages, f"{name}_stage", stand_in(name))
    patch(stages, "stage_identity", lambda name, cfg, setup: {})
    patch(stages, "_device_setup", lambda cfg: DeviceSetup(device="cpu", threads=1, amp=False))
    patch(stage_cache.Study, "stage", recording_stage)
    stages.run_study(StudyConfig() if preset == DEFAULTS else load_study_config(preset), out, progress=False)
    return seen


@pytest.mark.parametrize("preset", PRESETS)
def test_the_config_part_of_every_stage_key_is_unchanged(preset, tmp_path, monkeypatch):
    want = json.loads(FIXTURE.read_text())[preset]
    got = config_keys(preset, tmp_path / "study", monkeypatch.setattr)
    assert sorted(got) == sorted(want)  # the stages of the preset (with a gate or test set: their own stages too)
    # every stage in order; the crossover, pem and transitions stages exactly when the preset has their section
    expected = [s for s in stages.STAGES if s not in ("crossover", "pem", "transitions") or s in want]
    assert [s for s in got if s in stages.STAGES] == expected
    for stage in want:
        assert got[stage]["inputs"] == want[stage]["inputs"], f"{preset} {stage}: the config inputs changed"
        assert got[stage]["key"] == want[stage]["key"], f"{preset} {stage}: the key changed"


def test_the_fixture_covers_every_preset():
    assert sorted(json.loads(FIXTURE.read_text())) == sorted(PRESETS)


if __name__ == "__main__":  # rewrite the fixture from this code
    import tempfile

    class _Patch:
        def __init__(self):
            self.undo = []

        def __call__(self, obj, name, value):
            self.undo.append((obj, name, getattr(obj, name)))
            setattr(obj, name, value)

    table = {}
    for p in PRESETS:
        patch = _Patch()
        with tempfile.TemporaryDirectory() as tmp:
            table[p] = config_keys(p, Path(tmp) / "study", patch)
        for obj, name, value in reversed(patch.undo):
            setattr(obj, name, value)
    FIXTURE.write_text(json.dumps(table, indent=1, sort_keys=True) + "\n")
    print(f"wrote {FIXTURE} ({len(table)} presets)", file=sys.stderr)
