"""The study's `pem:` section (issue 49 item 3; `study.pipeline.sections.PemSection`): the verdict over
detector strength, on the study's own detectors and frames.

1. **Fit.** The study's detectors (the train stage's paper run) predict the gate frames' *fitting*
   sequences (`study.experiments.selection.gate_frames`, the gates' own split: the gate set's, or the
   run's gate split `train.gate_holdout`; `study.engine.predictions.predict` with those indices), and
   one perception error model per branch is fitted on them (`study.experiments.pem.fit`). No test
   frame and no validation frame is read; the record lists the frames it was fitted on.
2. **Sweep.** `study.experiments.pem_sweep.sweep` at each `pem.strengths`: the PEM drawn on the
   study's test frames (seed `pem.seed`) and on the gate frames the study chooses on (seed + 1): its
   validation sequences (`gates.val_fraction`, `gates.seed`), or, where those carve none, the fitting
   sequences themselves (as the study's own choices fall back; the record says which). The gate
   frames are a split of the study's dataset (or view), not a dataset of their own, so the sweep takes
   them as frame indices (`sweep(gate_frames=...)`), and refuses any that is a test frame.
3. **Record.** `pem.json`: the sweep's record (every comparison per strength with its value, 95 %
   interval and verdict), the fit's summary, the seconds per point; `pem_sweep.png`
   (`pem_sweep.plot_sweep`). Paths inside the stage's folder are stored relative to it (the folder is
   renamed when the stage ends).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from sim.errors import UserError

FIGURE = "pem_sweep.png"


def _relative(value, work: Path):
    """`value` (a path string, or a dict or list holding some) with every path inside `work` relative to it."""
    if isinstance(value, dict):
        return {k: _relative(v, work) for k, v in value.items()}
    if isinstance(value, list):
        return [_relative(v, work) for v in value]
    if isinstance(value, str) and value.startswith(str(work)):
        return str(Path(value).relative_to(work)) if value != str(work) else "."
    return value


def fitting_frames(run_paper: Path, data: Path, val_fraction: float, seed: int) -> tuple[list[int], list[int]]:
    """(fitting, validation) frame indices of the study's gate frames (`gate_frames`, targets "auto");
    UserError when the study has no gate frames (no gate set and `train.gate_holdout` 0): the PEM would
    be fitted on the detectors' own training frames."""
    from study.experiments.selection import gate_frames

    run_cfg = json.loads((Path(run_paper) / "config.json").read_text())
    frames = gate_frames(run_cfg, data, "auto", val_fraction, seed, "pem")
    if not frames.holdout:
        raise UserError("pem: the study has no gate frames (data.gate, or train.gate_holdout > 0): the PEM is fitted "
                        "on frames the detectors never trained on")
    return sorted(int(i) for i in frames.fit), sorted(int(i) for i in frames.val)


def run_pem_section(work: Path, run_paper: Path, data: Path, section, *, val_fraction: float, val_seed: int, k: int,
                    batch_size: int, setup, progress: bool) -> dict:
    """Fit, sweep and plot (module docstring) in `work` -> the record written to work/pem.json."""
    from study.eco.latency_energy import machine_description
    from study.engine.predictions import predict
    from study.experiments.pem import fit
    from study.experiments.pem_sweep import plot_sweep, sweep

    work, data = Path(work), Path(data)
    t0 = time.perf_counter()
    fit_idx, val_idx = fitting_frames(run_paper, data, val_fraction, val_seed)
    pred = predict(run_paper, data, work / "network_gate_fit", gates=("knowledge",), split="gate", indices=fit_idx,
                   batch_size=batch_size, setup=setup, progress=progress)
    model = work / "pem_model.json"
    fitted = fit(run_paper, data, model, predictions=pred.root, progress=progress)
    t1 = time.perf_counter()
    rec = sweep(run_paper, data, model, section.strengths, work / "draws", gate_set=data, seed=section.seed,
                resamples=section.bootstrap, fusion=section.fusion, k=k, progress=progress,
                gate_frames={"fit": fit_idx, "val": val_idx})
    t2 = time.perf_counter()
    plot_sweep(rec, work / FIGURE)
    t3 = time.perf_counter()
    doc = json.loads(model.read_text())
    out = {**rec, "fit": {**{n: fitted[n] for n in ("frames", "branches", "loadings")},
                          "split": "gate", "indices": doc["fit_indices"], "validation_frames": len(val_idx),
                          "network_predictions": "network_gate_fit", "model": model.name},
           "seconds_per_point": {f"{p['strength']:g}": p["seconds"] for p in rec["points"]},
           "seconds": {"fit": round(t1 - t0, 1), "sweep": round(t2 - t1, 1), "figure": round(t3 - t2, 1),
                       "total": round(t3 - t0, 1)},
           "machine": machine_description(setup.threads if setup else 1), "figure": FIGURE}
    out = _relative(out, work)
    from study.outputs import write_json_atomic

    write_json_atomic(work / "pem.json", out)
    return out
