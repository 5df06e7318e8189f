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
    assert table.splitlines()[0].startswith("| sequences | bias | draws' bias | estimate in percentile | percentile |")


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


def test_the_docs_reading_of_the_coverage_files_holds():
    """Each claim of docs/study.md's reading, checked on the files: the percentile interval's misses
    lie mostly above the truth for a method's mAP; the draws' bias has the estimator's sign and is a
    sixth to a half of it; jackknife covers every paired difference (within 2 binomial standard errors
    of 0.95) and the mAP at 48 sequences, 1.1-1.9x the percentile's median width; the studentized
    interval's median width exceeds 1 at 6 sequences; no interval both covers the mAP at 6 sequences
    and is under 0.6 wide; the binomial standard errors are at most 0.023 (400 samples) and 0.042 (120)."""
    text = (ROOT / "docs" / "study.md").read_text()
    assert "declared: jackknife-t" in text and "a sixth to a half of it" in text and "1.1-1.9x" in text
    for name, res in RESULTS.items():
        r = json.loads(res.read_text())
        worst = max(c["se"] for rec in r["by_sequences"].values() for q in rec["quantities"].values()
                    for c in q["coverage"].values())
        assert worst <= {"vehicles": 0.023, "all": 0.042}[name] + 5e-4
        for n, rec in r["by_sequences"].items():
            m, d = rec["quantities"]["map:late"], rec["quantities"]["difference:all_branches - late"]
            assert m["coverage"]["percentile"]["miss_low"] > 2 * m["coverage"]["percentile"]["miss_high"]
            dg = m["diagnostics"]
            assert dg["estimator_bias"] > 0 and 1 / 6 - 0.02 <= dg["bootstrap_bias"] / dg["estimator_bias"] <= 0.5
            jk = d["coverage"]["jackknife"]
            assert jk["coverage"] >= 0.95 - 2 * jk["se"]
            for q in (m, d):
                ratio = q["coverage"]["jackknife"]["median_width"] / q["coverage"]["percentile"]["median_width"]
                assert 1.1 <= ratio <= 1.9
            if n == "48":
                assert m["coverage"]["jackknife"]["coverage"] >= 0.95 - 2 * m["coverage"]["jackknife"]["se"]
            if n == "6":
                assert m["coverage"]["studentized"]["median_width"] > 1
                assert not any(c["coverage"] >= 0.95 - 2 * c["se"] and c["median_width"] < 0.6
                               for c in m["coverage"].values())
