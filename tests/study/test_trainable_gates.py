"""Which gates learn is read from the gate registries (`Gate.trainable`), never from a list of names:
a trainable gate registered later is listed, required and used like deep and attention."""

import pytest

from fusion.eco.config_gates import CONFIG_GATES
from fusion.nets.branch_gates import GATES, Gate, trainable_gates


@pytest.fixture
def new_gate():
    """A trainable gate registered for this test only (removed after, so no other test sees it)."""

    class NewGate(Gate):
        name = "new_learned"
        trainable = True

    GATES.add(NewGate.name, NewGate)
    try:
        yield NewGate.name
    finally:
        GATES._entries.pop(NewGate.name)


def test_the_registries_list_their_trainable_gates_a_new_one_too(new_gate):
    assert trainable_gates() == ["deep", "attention", new_gate]
    assert trainable_gates(CONFIG_GATES) == ["deep", "attention"]


def test_compare_runs_a_new_trainable_gate_only_once_the_run_holds_it(new_gate, tmp_path):
    from study.engine.predictions import usable_gates

    asked = ["knowledge", "deep", new_gate, "optimal"]
    assert usable_gates(tmp_path, asked) == ["knowledge", "optimal"]
    (tmp_path / "gates" / new_gate).mkdir(parents=True)
    (tmp_path / "gates" / new_gate / "gate.pt").write_bytes(b"")
    assert usable_gates(tmp_path, asked) == ["knowledge", new_gate, "optimal"]
