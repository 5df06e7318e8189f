"""Predictions: one pass of a trained network over a dataset, kept on disk, so that fusing, gating,
scoring and bootstrapping them again runs no network (`hydrabench predict`, and `compare`, which
calls it).

Per frame the pass stores every branch's detections (in its own frame, and mapped to the right
camera), each branch's four Faster R-CNN losses against the frame's labels under the run's protocol
(what the optimal gate reads and the learned gates are trained to predict: `study.engine.gate_data`, seed
`LOSS_SEED`), what the learned gates read (the stem features pooled on the gate grid) and what each
gate of `gates` predicts. Stems and branch backbones run once per batch
(`HydraFusion.detect_and_losses`); the numbers are those of `gate_tables.gate_pass` and
`gate_data.GateData` run apart.

On disk (format `hydrabench-predictions`, version `VERSION`):

    PRED/manifest.json        what the predictions are of (`identity`: the checkpoint's and the gates'
                              SHA-256, the dataset's contents `gate_data.dataset_sha256`, the code
                              `study.engine.code_identity.code_digest`, device, precision, split, frames,
                              batch size, grid, loss seed), the branches with their frames and
                              sensors, the gates, the chunks and every array's meaning
    PRED/chunk-NNNNN.npz      up to CHUNK_FRAMES frames: see ARRAYS

Why this format: numpy's .npz and JSON are readable with numpy and json alone (no pickle: every array
is numeric or unicode), from any language with a zip reader; detections are ragged, so each branch's
are stored flat with a per-frame count, and a chunk is one file that is written whole. The directory
is written beside its final place and renamed into it, so a reader finds a whole set or none; it is
reused as long as its identity is the one a new pass would have.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sim.errors import UserError

FORMAT = "hydrabench-predictions"
VERSION = 1
CHUNK_FRAMES = 64
GATES = ("knowledge", "deep", "attention", "optimal")

ARRAYS = {
    "indices": "(n,) int64: each frame's index in the dataset",
    "meta": "(n,) unicode: each frame's meta as JSON (context, sequence, weather, calibration, dataset_index)",
    "features": "(n, 64 x sensors, rows, cols) float16: stem features pooled on the gate grid (what learned gates read)",
    "losses": "(n, branches, 4) float32: each branch's Faster R-CNN losses (LOSS_NAMES order) against the labels",
    "gate.<gate>": "(n, branches) float32: the gate's predicted loss of each branch (lower is kept first)",
    "det.<branch>.count": "(n,) int32: detections of the branch per frame (its own frame)",
    "det.<branch>.boxes": "(sum count, 4) float32: [x1, y1, x2, y2] pixels of the branch's frame",
    "det.<branch>.scores": "(sum count,) float32",
    "det.<branch>.labels": "(sum count,) int16: class ids 1..8 (sim.actors.CLASSES)",
    "ref.<branch>.*": "the same in the right camera (fusion.late.to_reference), float32",
}


@dataclass
class Predictions:
    """A set of predictions in memory: `per_frame` [(meta, {branch: Detections in its own frame})],
    `predicted` {gate: (n, branches)}, `losses` (n, branches, 4), `features` (n, C, rows, cols), and
    the manifest. `selection(gate, k)` is a gate's top-k choice per frame."""

    root: Path
    manifest: dict
    per_frame: list
    predicted: dict
    losses: np.ndarray
    features: np.ndarray

    @property
    def branches(self) -> list[str]:
        return list(self.manifest["branches"])

    @property
    def branch_frames(self) -> dict:
        return dict(self.manifest["branch_frames"])

    @property
    def branch_sensors(self) -> dict:
        return {b: tuple(s) for b, s in self.manifest["branch_sensors"].items()}

    @property
    def gates(self) -> list[str]:
        return list(self.manifest["gates"])

    def selection(self, gate: str, k) -> list[tuple[str, ...]]:
        from study.engine.gate_tables import top_k_selection

        return top_k_selection(self.predicted[gate], self.branches, k)


def identity_of(run_dir, data, model, gates, indices, split: str, batch_size: int, setup) -> dict:
    """What a pass depends on: the key of its cache and the record in its manifest."""
    from fusion.nets.branch_gates import DEFAULT_GRID
    from study.engine.code_identity import code_digest
    from study.engine.device import compute_identity
    from study.engine.gate_data import LOSS_SEED, cached_sha256, checkpoint_path, dataset_sha256
    from study.engine.train import run_protocol

    run_dir = Path(run_dir)
    cfg = json.loads((run_dir / "config.json").read_text())
    gate_files = {g: run_dir / "gates" / g / "gate.pt" for g in gates}
    return {
        "checkpoint_sha256": cached_sha256(checkpoint_path(run_dir)),
        "gates_sha256": {g: cached_sha256(p) if p.is_file() else None for g, p in gate_files.items()},
        "dataset_sha256": dataset_sha256(data),
        "code": code_digest(["study.engine.predictions"]),
        **compute_identity(setup),
        "protocol": run_protocol(cfg), "split": split,
        "indices_sha256": hashlib.sha256(json.dumps([int(i) for i in indices]).encode()).hexdigest(),
        "frames": len(indices), "batch_size": int(batch_size), "grid": list(DEFAULT_GRID), "loss_seed": LOSS_SEED,
        "gates": list(gates), "branches": list(model.branches),
    }


def predict(run_dir, data, out=None, *, gates=GATES, split: str = "auto",
            batch_size: int = 4, setup=None, progress: bool = True, indices=None) -> Predictions:
    """The predictions of the run (or reference model's cache run) `run_dir` on `data`'s frames of
    `split` (`study.engine.scoring.frames_for`), read from `out` (default RUN/predictions/<key>/) when they
    are there with this identity, else made by one pass and written there. `gates`: those that can run
    (`usable_gates`: learned ones only where trained) predict beside the branches. `indices`: only these
    frames of the split (UserError for one outside it)."""
    from study.engine.gate_tables import setup_run

    run_dir, data = Path(run_dir), Path(data)
    model, cfg, in_split, used_split, reader = setup_run(run_dir, data, split, None, "latest", setup)
    if indices is None:
        indices = in_split
    else:
        indices = sorted({int(i) for i in indices})
        if not indices or not set(indices) <= set(in_split):
            raise UserError(f"predict: frames outside the {used_split!r} split of {data} (or none) asked for")
    trained = usable_gates(run_dir, gates)
    identity = identity_of(run_dir, data, model, trained, indices, used_split, batch_size, model.device_setup)
    key = hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()[:16]
    out = Path(out) if out is not None else run_dir / "predictions" / key
    if (out / "manifest.json").is_file():
        try:
            have = json.loads((out / "manifest.json").read_text())
        except (OSError, ValueError):
            have = {}
        if have.get("format") == FORMAT and have.get("identity") == identity:
            return load(out)
    elif out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise UserError(f"--out {out}: exists and is not a predictions directory (choose a new or empty one)")
    manifest = {"format": FORMAT, "version": VERSION, "key": key, "identity": identity, "run": str(run_dir),
                "data": str(data), "branches": list(model.branches), "branch_frames": dict(model.branch_frames),
                "branch_sensors": {b: list(s) for b, s in model.branch_sensors.items()}, "gates": trained,
                "best_gate": best_gate(run_dir, trained), "arrays": ARRAYS}
    write(out, manifest, _pass(run_dir, data, model, cfg, trained, indices, batch_size, progress))
    return load(out)


def usable_gates(run_dir: Path, gates) -> list[str]:
    """`gates` that can run on `run_dir`: those that learn nothing, and the trainable ones
    (`Gate.trainable`) with a RUN/gates/<gate>/gate.pt."""
    from fusion.nets.branch_gates import trainable_gates

    learned = trainable_gates()
    return [g for g in gates if g not in learned or (Path(run_dir) / "gates" / g / "gate.pt").is_file()]


def best_gate(run_dir: Path, gates) -> dict | None:
    """The learned gate with the lowest validation regret recorded when it was trained (`train-gate`:
    the run's validation sequences, never the frames compared here), with every gate's value; None
    when no learned gate recorded one."""
    import torch

    from fusion.nets.branch_gates import trainable_gates

    vals = {}
    learned = trainable_gates()
    for g in gates:
        path = Path(run_dir) / "gates" / g / "gate.pt"
        if g in learned and path.is_file():
            res = (torch.load(path, map_location="cpu", weights_only=False).get("result") or {})
            if res.get("val_regret") is not None:
                vals[g] = float(res["val_regret"])
    if not vals:
        return None
    return {"name": min(vals, key=vals.get), "validation_regret": vals,
            "by": "lowest validation regret recorded by train-gate (the run's validation sequences)"}


def _pass(run_dir, data, model, cfg, gates, indices, batch_size, progress):
    """Yield the chunks' arrays ({name: array}) of one pass over `indices`."""
    import torch
    from torch.utils.data import DataLoader

    from fusion.data import FrameDataset, collate
    from fusion.late import to_reference
    from fusion.nets import LOSS_NAMES
    from fusion.nets.branch_gates import DEFAULT_GRID, gate_sensors, pool_features
    from sensors.rig import Calibration
    from sim.progress import progress as progress_bar
    from study.engine.device import to_device
    from study.engine.gate_data import LOSS_SEED
    from study.engine.gate_tables import gate_on_device, make_gate
    from study.engine.scoring import to_detections
    from study.engine.train import run_protocol

    setup = model.device_setup
    gate_objs = {g: gate_on_device(make_gate(g, model, run_dir, "latest"), model) for g in gates}
    branches = list(model.branches)
    frames = model.branch_frames
    sensors = gate_sensors(model)
    ds = FrameDataset(data, indices, sensors=model.sensors, bev_size=model.transform.image_size("radar"),
                      protocol=run_protocol(cfg), uint8=setup.is_cuda)
    loader = DataLoader(ds, batch_size=batch_size, shuffle=False, collate_fn=collate, num_workers=setup.workers,
                        pin_memory=setup.is_cuda)
    pending: dict = {}

    def take(name, value):
        pending.setdefault(name, []).append(value)

    def chunk():
        out = {}
        for name, parts in pending.items():
            out[name] = np.concatenate(parts) if name not in ("meta",) else np.array(sum(parts, []), dtype=str)
        pending.clear()
        return out

    model.eval()
    bar = progress_bar(total=len(indices), desc="predict", unit="frame", enabled=progress)
    with torch.no_grad():
        for inputs, targets, metas in loader:
            inputs, targets = to_device(inputs, targets, setup.device)
            with setup.autocast():
                feats = model.extract_features(inputs)
                gate_feats = feats if set(sensors) == set(feats) else model.extract_features(inputs, sensors)
                pooled = pool_features(gate_feats, sensors, DEFAULT_GRID)
                # the stems ran once: the branches reuse them where they need exactly these sensors
                # (each stem saw the same batch as detect_and_losses' own run would give it)
                need = model.stem_sensors(inputs)
                reuse = next((f for f in (feats, gate_feats) if set(f) == set(need)), None)
                dets, per = model.detect_and_losses(inputs, targets, seed=LOSS_SEED, features=reuse)
            losses = np.array([[[float(p[b][n]) for n in LOSS_NAMES] for b in branches] for p in per], np.float32)
            summed = losses.sum(axis=2)  # what GateData.branch_losses gives the optimal gate
            metas = [dict(m, branch_losses=dict(zip(branches, map(float, row)))) for m, row in zip(metas, summed)]
            with setup.autocast():
                for g, gate in gate_objs.items():
                    take(f"gate.{g}", gate.predict(feats, metas).float().cpu().numpy().astype(np.float32))
            take("indices", np.array([int(m["dataset_index"]) for m in metas], np.int64))
            take("meta", [json.dumps({k: v for k, v in m.items() if k != "branch_losses"}) for m in metas])
            take("features", pooled.half().cpu().numpy())
            take("losses", losses)
            for meta, d in zip(metas, dets):
                calib = Calibration.from_dict(meta["calibration"])
                for b in branches:
                    det = to_detections(d[b])
                    for prefix, x in (("det", det), ("ref", to_reference(det, frames[b], calib))):
                        take(f"{prefix}.{b}.count", np.array([len(x.scores)], np.int32))
                        take(f"{prefix}.{b}.boxes", x.boxes.astype(np.float32).reshape(-1, 4))
                        take(f"{prefix}.{b}.scores", x.scores.astype(np.float32))
                        take(f"{prefix}.{b}.labels", x.labels.astype(np.int16))
            bar.update(len(metas))
            if sum(len(v) for v in pending["indices"]) >= CHUNK_FRAMES:
                yield chunk()
    bar.close()
    if pending:
        yield chunk()


def write(out: Path, manifest: dict, chunks) -> None:
    """Write the chunks and the manifest into a folder beside `out`, then rename it into place (a
    stale set at `out` is replaced only once the new one is whole)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f"{out.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        names, n = [], 0
        for arrays in chunks:
            name = f"chunk-{len(names):05d}.npz"
            np.savez(tmp / name, **arrays)
            names.append(name)
            n += len(arrays["indices"])
        size = sum((tmp / c).stat().st_size for c in names)
        manifest = {**manifest, "frames": n, "chunks": names, "bytes": size,
                    "mb_per_1000_frames": round(size / 1e6 * 1000 / max(n, 1), 2)}
        (tmp / "manifest.json").write_text(json.dumps(manifest, indent=1, sort_keys=True))
        old = None
        if out.exists():
            old = out.with_name(f"{out.name}.old-{os.getpid()}")
            os.replace(out, old)
        os.replace(tmp, out)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def load(root) -> Predictions:
    """Read a predictions directory (UserError naming what is wrong with it)."""
    from fusion.late import Detections

    root = Path(root)
    try:
        manifest = json.loads((root / "manifest.json").read_text())
    except (OSError, ValueError) as exc:
        raise UserError(f"{root} is not a predictions directory (manifest.json: {exc}; see hydrabench predict)") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise UserError(f"{root}/manifest.json is not a {FORMAT} manifest")
    if manifest.get("version") != VERSION:
        raise UserError(f"{root}: predictions of format version {manifest.get('version')!r}; this code reads {VERSION} "
                        "(run hydrabench predict again)")
    branches, gates = manifest["branches"], manifest["gates"]
    per_frame, predicted, losses, features = [], {g: [] for g in gates}, [], []
    for name in manifest["chunks"]:
        try:
            z = np.load(root / name, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise UserError(f"{root / name}: not a readable chunk ({exc})") from None
        with z:
            metas = [json.loads(m) for m in z["meta"]]
            losses.append(z["losses"])
            features.append(z["features"])
            for g in gates:
                predicted[g].append(z[f"gate.{g}"])
            cols = {}
            for b in branches:
                ends = np.cumsum(z[f"det.{b}.count"])
                cols[b] = (np.r_[0, ends[:-1]], ends, z[f"det.{b}.boxes"].astype(np.float64),
                           z[f"det.{b}.scores"].astype(np.float64), z[f"det.{b}.labels"].astype(np.int64))
            for j, meta in enumerate(metas):
                per = {}
                for b, (starts, ends, bx, sc, lb) in cols.items():
                    s, e = starts[j], ends[j]
                    per[b] = Detections(bx[s:e], sc[s:e], lb[s:e])
                per_frame.append((meta, per))
    return Predictions(root, manifest, per_frame, {g: np.concatenate(v) for g, v in predicted.items()},
                       np.concatenate(losses) if losses else np.zeros((0, len(branches), 4), np.float32),
                       np.concatenate(features) if features else np.zeros((0,), np.float16))
