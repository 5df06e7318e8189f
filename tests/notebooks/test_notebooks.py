"""The teaching notebooks run top to bottom (nbclient), so they cannot rot.

The fusion-theory notebook reads its simulated measurements from $HYDRABENCH_CACHE/theory, pointed
here at the session's shared cache: whichever of this test and tests/study/test_theory_measured.py
runs first measures study.theory.SMALL_CONFIG and the fog bank, the other reads them.
"""

import os
from pathlib import Path

import nbformat
from nbclient import NotebookClient

ROOT = Path(__file__).resolve().parents[2]


def run_notebook(name: str, monkeypatch, cache_root: Path):
    monkeypatch.setenv("HYDRABENCH_CACHE", str(cache_root))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
    monkeypatch.setenv("MPLBACKEND", "Agg")
    nb = nbformat.read(ROOT / "notebooks" / name, as_version=4)
    client = NotebookClient(nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(ROOT)}})
    client.execute()  # raises CellExecutionError, naming the cell, if any cell fails
    return nb


def test_fusion_theory_notebook_runs_and_draws_its_figures(monkeypatch, tmp_path_factory):
    nb = run_notebook("01_fusion_theory.ipynb", monkeypatch, tmp_path_factory.getbasetemp() / "hydrabench-cache")
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    figures = [o for o in outputs if "image/png" in o.get("data", {})]
    assert len(figures) >= 5
    text = "".join(o.get("text", "") for o in outputs if o.get("output_type") == "stream")
    assert "fog (layout motorway)" in text and "night (layout motorway)" in text
    assert not [o for o in outputs if o.get("output_type") == "error"]


def test_selective_fusion_notebook_reads_a_tiny_study_and_answers_its_three_questions(monkeypatch, tmp_path_factory):
    """03 on the tiny study (configs/study/tiny.yaml), shared with tests/study/test_study_runner.py:
    whichever runs first runs the study, the other finds every stage done."""
    from study.runner import load_study_config, run_study

    cache = tmp_path_factory.getbasetemp() / "hydrabench-cache"
    study = Path(os.environ.get("HYDRABENCH_TINY_STUDY") or cache / "study-tiny")
    run_study(load_study_config("tiny"), study, progress=False)
    monkeypatch.setenv("HYDRABENCH_STUDY", str(study))
    nb = run_notebook("03_selective_fusion.ipynb", monkeypatch, cache)
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"]
    figures = [o for o in outputs if "image/png" in o.get("data", {})]
    assert len(figures) >= 3  # selection per context, loss against energy, selection minus late fusion
    text = "".join(o.get("text", "") for o in outputs if o.get("output_type") == "stream")
    assert "THESE NUMBERS MEAN NOTHING" in text and "scale tiny" in text
    assert "hydrafusion / optimal" in text and "ecofusion / loss_based" in text  # what each gate picks
    assert "fog (severity 4): ranking" in text  # why: the knowledge gate's table rows
    assert "lambda_E 0 -> 1" in text and "selection - late" in text and "hurts in" in text
