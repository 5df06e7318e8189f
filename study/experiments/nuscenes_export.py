"""`hydrabench export nuscenes`: a dataset in nuScenes format with hydrabench's own splits.

The format is `sensors.export.nuscenes`; this adds the split lists, drawn exactly as a training run
and its gates draw them (`study.experiments.selection.gate_frames` on a run config holding the split settings):
    hydrabench-train       the frames the detectors train on (`study.engine.train.TrainConfig`'s split)
    hydrabench-gate        the frames the gates fit on (the gate split less its validation
                           sequences, or, without a gate split, the detectors' train split less them)
    hydrabench-validation  the sequences every choice is made on (`study.experiments.selection.validation_split`)
    hydrabench-test        the test split
    hydrabench-all         every scene
A dataset view (`sensors.combine`) with a gate or a test part takes them whole, as the study does.
All are whole sequences, so whole nuScenes scenes; the devkit reads them from splits.json as custom
splits (`DetectionEval(..., eval_set="hydrabench-test")`).
"""

from __future__ import annotations

from pathlib import Path

SPLIT_NAMES = ("hydrabench-train", "hydrabench-gate", "hydrabench-validation", "hydrabench-test", "hydrabench-all")


def hydrabench_splits(data: str | Path, *, train_fraction: float = 0.7, split_seed: int = 0,
                      gate_holdout: float = 0.0, val_fraction: float = 0.15, gate_seed: int = 0) -> dict[str, list[str]]:
    """{split name: shard names} of dataset `data` under these split settings (the defaults are
    `TrainConfig`'s and `GateTrainConfig`'s)."""
    from sensors.dataset import DatasetReader
    from study.experiments.selection import gate_frames

    reader = DatasetReader(Path(data))
    manifest = reader.manifest
    parts = manifest.get("parts") or {}
    data_config = parts["detectors"]["config"] if "detectors" in parts else manifest["config"]
    run_cfg = {"train_fraction": train_fraction, "split_seed": split_seed, "gate_holdout": gate_holdout,
               "data_config": data_config, "data": str(data)}
    from study.engine.scoring import run_train_test

    train, _ = run_train_test(run_cfg, data, "export nuscenes")
    frames = gate_frames(run_cfg, data, "auto", val_fraction, gate_seed, "export nuscenes")

    def shards(indices) -> list[str]:
        return sorted({reader.index[int(i)][0] for i in indices})

    return {"hydrabench-train": shards(train), "hydrabench-gate": shards(frames.fit),
            "hydrabench-validation": shards(frames.val), "hydrabench-test": shards(frames.test),
            "hydrabench-all": [s["name"] for s in manifest["shards"]]}


def export_nuscenes(data: str | Path, out: str | Path, *, clear: bool = False, progress: bool = True,
                    **split_settings) -> dict:
    """Export `data` in nuScenes format to `out` with hydrabench's splits (`hydrabench_splits`'s
    settings as keywords); returns the export's summary with the time it took."""
    import time

    from sensors.export import nuscenes

    t0 = time.perf_counter()
    splits = hydrabench_splits(data, **split_settings)
    result = nuscenes.export_nuscenes(data, out, splits=splits, clear=clear, progress=progress)
    result["seconds"] = round(time.perf_counter() - t0, 3)
    result["split_scenes"] = {name: len(v) for name, v in splits.items()}
    return result
