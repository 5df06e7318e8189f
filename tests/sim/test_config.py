from dataclasses import dataclass, field

import pytest

from sim.config import from_dict, load_yaml, to_dict
from sim.errors import UserError
from sim.registry import Registry


@dataclass(frozen=True)
class Inner:
    width: int = 10
    rate_hz: float = 1.0


@dataclass(frozen=True)
class Outer:
    name: str = "x"
    inner: Inner = field(default_factory=Inner)
    sizes: tuple[int, ...] = (1, 2)
    pair: tuple[int, float] = (1, 2.0)


def test_strict_loader_roundtrip_and_errors(tmp_path):
    o = from_dict(Outer, {"name": "a", "inner": {"width": 3}, "sizes": [4, 5]})
    assert o == Outer("a", Inner(3, 1.0), (4, 5))
    assert from_dict(Outer, to_dict(o)) == o
    assert from_dict(Outer, {"pair": [3, 4]}).pair == (3, 4.0)  # fixed-length tuples keep their values
    with pytest.raises(UserError, match="expected 2 items"):
        from_dict(Outer, {"pair": [3]})
    with pytest.raises(UserError, match="unknown key 'widht'"):
        from_dict(Outer, {"inner": {"widht": 3}})
    with pytest.raises(UserError, match=r"config.inner.width: expected an integer"):
        from_dict(Outer, {"inner": {"width": "wide"}})
    with pytest.raises(UserError, match="expected a number"):
        from_dict(Outer, {"inner": {"rate_hz": True}})
    p = tmp_path / "c.yaml"
    p.write_text("name: b\nbogus: 1\n")
    with pytest.raises(UserError, match="c.yaml: unknown key 'bogus'"):
        load_yaml(Outer, p)
    p.write_text("name: [unclosed\n")
    with pytest.raises(UserError, match="not valid YAML"):
        load_yaml(Outer, p)


def test_registry_names_the_choices():
    reg = Registry("thing")
    reg.add("a", 1)
    assert reg.get("a") == 1 and "a" in reg
    with pytest.raises(UserError, match="unknown thing 'b' .choose from: a"):
        reg.get("b")
    with pytest.raises(KeyError):
        reg.add("a", 2)
