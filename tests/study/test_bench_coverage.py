"""`hydrabench bench coverage`: a tiny run end to end (JSON and file), bad input refused, and the
coverage tables docs/study.md quotes are the stored results files'."""

import json
import re
from pathlib import Path

import pytest

from study.bench.coverage import coverage_table
from study.cli import main

ROOT = Path(__file__).resolve().parents[2]
RESULTS = {"vehicles": ROOT / "results" / "bench_coverage_2026-12-07.json",
           "all": ROOT / "results" / "bench_coverage_2026-12-07_all.json"}


def test_a_tiny_run_writes_its_result(tmp_path, capsys):
    out = tmp_path / "cov.json"
    assert main(["bench", "coverage", "--sequences", "3", "--trials", "2", "--resamples", "20",
                 "--frames-per-sequence", "1", "--no-studentized", "--json", "--out", str(out)]) == 0
    r = json.loads(capsys.readouterr().out)
    assert json.loads(out.read_text())["truth"] == r["truth"]
    rec = r["by_sequences"]["3"]["quantities"]["map:late"]
    assert rec["coverage"]["percentile"]["trials"] == 2 and "studentized" not in rec["coverage"]
    assert r["model"]["class_set"] == "vehicles" and r["frames_per_sequence"] == 1
    assert set(r["best_at_fewest"]) == set(r["truth"])
    table = coverage_table(r, "map")
    assert table.splitlines()[0].startswith("| sequences | bias | draws' bias | percentile |")


@pytest.mark.parametrize("argv, message", [
    (["--sequences", "1"], "sequences"),
    (["--trials", "1"], "trials"),
    (["--classes", "people"], "classes"),
])
def test_bad_input_is_refused(argv, message, capsys):
    assert main(["bench", "coverage", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1


def _quoted_tables(text: str) -> list[str]:
    """Every Markdown table in `text` that starts with the coverage table's header."""
    return [m.group(0).strip() for m in re.finditer(r"^\| sequences \| bias \|.*?(?=\n(?!\|))", text, re.M | re.S)]


def test_the_docs_coverage_tables_are_the_results_files():
    text = (ROOT / "docs" / "study.md").read_text()
    quoted = _quoted_tables(text)
    want = [coverage_table(json.loads(RESULTS[c].read_text()), q) for c in ("vehicles", "all") for q in ("map", "difference")]
    assert quoted == want
