"""Execute the teaching notebooks top to bottom and store them with their outputs, so that a reader who
opens one on GitHub sees its figures.

    HYDRABENCH_CACHE=out/cache python notebooks/execute.py                 (all five)
    python notebooks/execute.py notebooks/02_degradation_physics.ipynb     (one)

Notebook 03 reads the study in $HYDRABENCH_STUDY, by default the committed results/study_cpu; notebook
05 generates a small dataset unless $HYDRABENCH_BYOD_DATA names one (docs/notebooks.md says what each
notebook runs on).

Each notebook runs in a kernel whose working directory is the repository root, as under
tests/notebooks/test_notebooks.py. Nothing that changes from run to run beyond the printed timings is
stored: no per-cell execution timestamps, no notebook metadata beyond the kernelspec and language; the
prints of a cell to one stream are stored as one output.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import nbformat
from nbclient import NotebookClient

ROOT = Path(__file__).resolve().parents[1]


def _coalesce(outputs: list) -> list:
    """Consecutive prints to one stream as one output, as a reader sees them."""
    merged = []
    for out in outputs:
        if out.output_type == "stream" and merged and merged[-1].output_type == "stream" \
                and merged[-1].name == out.name:
            merged[-1].text += out.text
        else:
            merged.append(out)
    return merged


def execute(path: Path, timeout: int = 1800) -> nbformat.NotebookNode:
    """`path` executed in a fresh kernel (CellExecutionError, naming the cell, if one fails)."""
    nb = nbformat.read(path, as_version=4)
    client = NotebookClient(nb, timeout=timeout, kernel_name="python3", record_timing=False,
                            resources={"metadata": {"path": str(ROOT)}})
    client.execute()
    for cell in nb.cells:
        cell.metadata.pop("execution", None)
        if cell.cell_type == "code":
            cell.outputs = _coalesce(cell.outputs)
    nb.metadata = {k: v for k, v in nb.metadata.items() if k in ("kernelspec", "language_info")}
    return nb


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("notebooks", nargs="*", type=Path, help="notebooks to execute (default: notebooks/*.ipynb)")
    args = p.parse_args(argv)
    os.environ.setdefault("MPLBACKEND", "Agg")
    os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
    for path in args.notebooks or sorted((ROOT / "notebooks").glob("*.ipynb")):
        nb = execute(path)
        tmp = path.with_name(f".{path.name}.tmp")
        nbformat.write(nb, tmp)
        tmp.replace(path)
        print(f"{path}: executed and stored", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
