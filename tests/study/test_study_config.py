"""The study's config sections take each field they share with an experiment's config from it
(issue 38: `DataSection` / `GenerateConfig`, `TrainSection` / `TrainConfig`, `GatesSection` /
`GateTrainConfig`): name, type and default are defined once, there."""

from __future__ import annotations

import dataclasses
from typing import get_type_hints

import pytest

from sim.errors import UserError
from study.pipeline.config import DataSection, GatesSection, TrainSection, section_of, study_config_from_dict

SECTIONS = (DataSection, TrainSection, GatesSection)
STUDY_DEFAULTS = {DataSection: {"contexts": ("all",), "twins": True}}
"""The defaults the study chooses itself (it renders twins for its severity sweeps)."""
SAME_NAME_OTHER_MEANING = {TrainSection: {"init_from"}}
"""TrainSection.init_from names a reference model or a run; TrainConfig.init_from, runs."""


@pytest.mark.parametrize("section", SECTIONS, ids=lambda s: s.__name__)
def test_a_shared_field_has_the_experiment_configs_type_and_default(section):
    source = section.SOURCE
    want, got = get_type_hints(source), get_type_hints(section)
    defaults = {f.name: f.default for f in dataclasses.fields(section)}
    assert section.SHARED
    for name in section.SHARED:
        assert got[name] == want[name], name
        source_default = next(f.default for f in dataclasses.fields(source) if f.name == name)
        assert defaults[name] == STUDY_DEFAULTS.get(section, {}).get(name, source_default), name
        assert name in section.__doc__.rsplit("Fields shared with", 1)[1], name


@pytest.mark.parametrize("section", SECTIONS, ids=lambda s: s.__name__)
def test_no_section_redeclares_a_field_of_its_experiment_config(section):
    source_names = {f.name for f in dataclasses.fields(section.SOURCE)}
    own = {f.name for f in dataclasses.fields(section)} - set(section.SHARED)
    assert own & source_names == SAME_NAME_OTHER_MEANING.get(section, set())


def test_a_shared_field_follows_its_source_and_a_missing_one_is_refused():
    @dataclasses.dataclass(frozen=True)
    class Source:
        epochs: int = 7
        lr: float = 0.5

    @section_of(Source)
    class Section:
        epochs: Shared  # noqa: F821 (the marker, resolved by section_of)
        lr: Shared = 0.25  # noqa: F821
        own: bool = False

    assert Section() == Section(epochs=7, lr=0.25, own=False) and Section.SHARED == ("epochs", "lr")
    assert get_type_hints(Section)["epochs"] is int
    with pytest.raises(TypeError, match="no field 'epoch'"):
        @section_of(Source)
        class Misspelt:
            epoch: Shared  # noqa: F821


def test_the_experiment_configs_checks_refuse_a_bad_shared_value():
    with pytest.raises(UserError, match=r"^gates: targets: expected one of"):
        study_config_from_dict({"gates": {"targets": "test"}})
    with pytest.raises(UserError, match=r"^data: severities must be values in 0..5"):
        study_config_from_dict({"data": {"severities": [7]}})
