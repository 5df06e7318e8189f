"""The README's severity table must say what the code does."""

import re
from pathlib import Path

from sim.weather import SEVERITY_TABLE


def _fmt(x: float) -> str:
    return f"{x:g}"


def test_readme_severity_table_matches_code():
    text = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    assert text.startswith("# hydrabench\n\n```\nmake demo\nmake test\n```")
    for cond, spec in SEVERITY_TABLE.items():
        row = re.search(rf"^\| {cond} \|[^|]*\|(.*)\|$", text, re.M)
        assert row, cond
        cells = [c.strip() for c in row.group(1).split("|")]
        expected = [f"{_fmt(lo)}-{_fmt(hi)}" for lo, hi in spec["levels"]]
        assert cells == expected, (cond, cells, expected)
