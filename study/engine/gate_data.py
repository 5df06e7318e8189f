"""The gate dataset of a trained run (HydraFusion Section 5.2.2) and the file identities it is keyed by.

**Gate dataset** (Section 5.2.2: "the stem outputs and branch losses of a fully trained HydraFusion
model as the inputs and targets for the gate"). For every frame of a dataset, what the learned
gates consume, `fusion.nets.branch_gates.pool_features` of the stem outputs (float16, 64 channels per
sensor on an 8 x 16 grid by default: 80 kB a frame for five sensors), and each branch's four
Faster R-CNN losses from `HydraFusion.per_sample_losses` (seed 0; the gate target is their sum).
Cached under the run directory, keyed by the checkpoint's SHA-256, the dataset's contents
(`dataset_sha256`: every shard hashed and checked against the manifest's checksums),
the grid, the sensors, the branches, the seed, and the device type and precision the network ran in
(`study.engine.device.compute_identity`):

    RUN/gate_data/<key>/info.json         what the key was made of
    RUN/gate_data/<key>/chunk-NNNNN.npz   indices (n,), features (n, C, rows, cols) float16,
                                          losses (n, n_branches, 4) float32; written atomically

Interrupted, it continues with the frames no chunk holds yet.
"""

from __future__ import annotations

import hashlib
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from sim.errors import UserError
from sim.progress import progress as progress_bar
from study.engine.device import compute_identity
from study.outputs import atomic_path, write_json_atomic

GATE_DATA_VERSION = 2
LOSS_SEED = 0


# ----- identities and small helpers -----------------------------------------------------------


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 22), b""):
            h.update(block)
    return h.hexdigest()


_SHA_CACHE: dict[tuple[str, int, int], str] = {}


def cached_sha256(path: Path) -> str:
    """file_sha256, remembered per (resolved path, size, mtime) within the process (checkpoints are
    hundreds of MB)."""
    st = Path(path).stat()
    key = (str(Path(path).resolve()), st.st_size, st.st_mtime_ns)
    if key not in _SHA_CACHE:
        _SHA_CACHE[key] = file_sha256(path)
    return _SHA_CACHE[key]


_DATA_CACHE: dict[tuple, str] = {}


def dataset_sha256(data) -> str:
    """The identity of a dataset's contents, for keying what is cached from it: the SHA-256 of its
    manifest.json, after every shard the manifest lists has been hashed (`sensors.dataset.shard_digest`:
    every file's path and bytes) and found equal to the checksum the manifest records. The manifest
    alone is not enough: a dataset whose labels were edited after generation keeps its manifest, and
    a cache keyed on it would serve results of the old labels. A shard whose files differ from their
    recorded checksum is refused (UserError naming it; `hydrabench verify` lists every problem).
    Remembered within the process per (path, size, mtime) of every file, so one command hashes a
    dataset once."""
    from sensors.dataset import shard_digest

    root = Path(data)
    manifest = root / "manifest.json"
    try:
        m = json.loads(manifest.read_text())
        shards = [(str(s["name"]), str(s["sha256"])) for s in m["shards"]]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise UserError(f"{manifest}: not a readable dataset manifest ({exc})") from None
    files = []
    for name, _ in shards:
        for p in sorted((root / name).rglob("*")):
            if p.is_file():
                st = p.stat()
                files.append((str(p.relative_to(root)), st.st_size, st.st_mtime_ns))
    st = manifest.stat()
    key = (str(root.resolve()), st.st_size, st.st_mtime_ns, tuple(files))
    if key not in _DATA_CACHE:
        for name, recorded in shards:
            if not (root / name).is_dir() or shard_digest(root / name) != recorded:
                raise UserError(f"{root}: {name} does not match the checksum its manifest records (its files changed "
                                f"after generation, so results cached from it would not be of these contents; "
                                f"hydrabench verify {root} names the problems)")
        _DATA_CACHE[key] = file_sha256(manifest)
    return _DATA_CACHE[key]


def checkpoint_path(run_dir: Path, checkpoint: str = "latest") -> Path:
    return Path(run_dir) / ("checkpoint.pt" if checkpoint == "latest" else f"{checkpoint}.pt")


def model_device(model) -> str:
    """The device the network's parameters are on ("cpu", "cuda:0")."""
    return str(next(model.parameters()).device)


# ----- the gate dataset -----------------------------------------------------------------------


class GateData:
    """Pooled stem features and per-branch losses of a dataset's frames under one run checkpoint.

    Args:
        run_dir: the training run; the cache lives in `run_dir/gate_data/<key>/`.
        data: dataset directory.
        model: the run's network at `checkpoint` (eval mode), as `study.engine.scoring.load_run` gives it.
        checkpoint: "latest" or "epoch-NNN" (its file's SHA-256 is part of the key).
        grid: the pooling grid of `pool_features` (rows, columns).
        seed: RNG seed of the per-sample loss sampling.
    """

    def __init__(self, run_dir, data, model, checkpoint: str = "latest", grid=None, seed: int = LOSS_SEED) -> None:
        from fusion.nets.branch_gates import DEFAULT_GRID, gate_sensors

        self.run_dir, self.data, self.model = Path(run_dir), Path(data), model
        self.grid = tuple(int(g) for g in (grid or DEFAULT_GRID))
        self.seed = int(seed)
        self.sensors = gate_sensors(model)
        if not self.sensors:
            raise UserError("gates read stem features, and this run's branches have no shared stems")
        self.branches = tuple(model.branches)
        ckpt = checkpoint_path(self.run_dir, checkpoint)
        if not ckpt.exists():
            raise UserError(f"{ckpt} does not exist")
        manifest = self.data / "manifest.json"
        if not manifest.exists():
            raise UserError(f"{self.data} has no manifest.json (not a dataset)")
        from study.engine.train import run_protocol

        # the per-branch losses are measured against the ground truth of the run's protocol
        self.protocol = run_protocol(json.loads((self.run_dir / "config.json").read_text()))
        self.identity = {
            "protocol": self.protocol,
            "version": GATE_DATA_VERSION, "checkpoint": checkpoint, "checkpoint_sha256": cached_sha256(ckpt),
            "dataset_sha256": dataset_sha256(self.data), "grid": list(self.grid), "sensors": list(self.sensors),
            "branches": list(self.branches), "loss_seed": self.seed,
            "bev_size": list(model.transform.image_size("radar")),
        }
        # where and in which precision the network ran: `ensure` runs it where it is, without autocast
        self.identity.update(compute_identity(device=model_device(model), precision="fp32"))
        self.identity.update(self.extra_identity())
        self.key = hashlib.sha256(json.dumps(self.identity, sort_keys=True).encode()).hexdigest()[:16]
        # what a gate trained on this cache depends on besides its training frames: the same network,
        # settings and targets on any dataset (a study's gates fit on its gate set and run on its test set)
        self.model_key = hashlib.sha256(json.dumps(
            {k: v for k, v in self.identity.items() if k != "dataset_sha256"}, sort_keys=True).encode()
        ).hexdigest()[:16]
        self.dir = self.run_dir / self.subdir / self.key
        self._index: dict[int, tuple[Path, int]] | None = None

    subdir = "gate_data"
    """Directory under the run that holds this kind of cache (subclasses: their own)."""

    def extra_identity(self) -> dict:
        """What else the cache key is made of (subclasses add their settings)."""
        return {}

    def compute(self, model, inputs, targets, metas, features) -> dict[str, np.ndarray]:
        """Per-frame arrays of one batch (first axis = the batch's frames), stored in the chunks
        beside "indices" and "features": here each branch's four Faster R-CNN losses, (B, n_branches, 4)."""
        from fusion.nets import LOSS_NAMES

        per = model.per_sample_losses(inputs, targets, seed=self.seed)
        return {"losses": np.array([[[float(p[b][n]) for n in LOSS_NAMES] for b in self.branches] for p in per],
                                   np.float32)}

    # -- what is on disk
    def _chunks(self) -> list[Path]:
        return sorted(self.dir.glob("chunk-*.npz")) if self.dir.is_dir() else []

    def index(self) -> dict[int, tuple[Path, int]]:
        """Dataset frame index -> (chunk file, row) for every frame already cached."""
        if self._index is None:
            out: dict[int, tuple[Path, int]] = {}
            for path in self._chunks():
                with np.load(path) as z:
                    for row, i in enumerate(z["indices"].tolist()):
                        out.setdefault(int(i), (path, row))
            self._index = out
        return self._index

    def missing(self, indices) -> list[int]:
        have = self.index()
        return sorted({int(i) for i in indices} - set(have))

    # -- building
    def ensure(self, indices, batch_size: int = 4, chunk_frames: int = 32, progress: bool = True) -> int:
        """Compute and cache every frame of `indices` not cached yet; returns how many were computed."""
        import torch

        from fusion.data import FrameDataset, collate
        from fusion.nets.branch_gates import pool_features

        todo = self.missing(indices)
        if not todo:
            return 0
        self.dir.mkdir(parents=True, exist_ok=True)
        info = self.dir / "info.json"
        if not info.exists():
            write_json_atomic(info, {**self.identity, "key": self.key, "run": str(self.run_dir),
                                     "data": str(self.data)})
        from study.engine.device import to_device

        model = self.model.eval()
        device = model_device(model)  # the network runs where it is (`study.engine.device`), in float32
        ds = FrameDataset(self.data, todo, sensors=model.sensors, bev_size=model.transform.image_size("radar"),
                          protocol=self.protocol, uint8=str(device).startswith("cuda"))  # float32 on the GPU (`to_device`)
        n_chunk = len(self._chunks())
        bar = progress_bar(total=len(todo), desc=self.subdir.replace("_", " "), enabled=progress)
        pending: dict[str, list] = defaultdict(list)

        def flush():
            nonlocal n_chunk
            if not pending["indices"]:
                return
            while (self.dir / f"chunk-{n_chunk:05d}.npz").exists():
                n_chunk += 1
            path = self.dir / f"chunk-{n_chunk:05d}.npz"
            with atomic_path(path) as tmp:
                np.savez(tmp, indices=np.asarray(pending["indices"], np.int64),
                         **{k: np.concatenate(v) for k, v in pending.items() if k != "indices"})
            n_chunk += 1
            pending.clear()

        with torch.no_grad():
            for start in range(0, len(todo), batch_size):
                items = [ds[k] for k in range(start, min(start + batch_size, len(todo)))]
                inputs, targets, metas = collate(items)
                inputs, targets = to_device(inputs, targets, device)
                feats = model.extract_features(inputs, self.sensors)
                pooled = pool_features(feats, self.sensors, self.grid)
                pending["indices"].extend(int(m["dataset_index"]) for m in metas)
                pending["features"].append(pooled.half().cpu().numpy())
                for k, v in self.compute(model, inputs, targets, metas, feats).items():
                    pending[k].append(v)
                bar.update(len(items))
                if len(pending["indices"]) >= chunk_frames:
                    flush()
        flush()
        bar.close()
        self._index = None
        return len(todo)

    # -- reading
    def arrays(self, indices, keys) -> dict[str, np.ndarray]:
        """The cached arrays `keys` of `indices`, in that order (first axis = frames). Every frame
        must be cached (`ensure`)."""
        idx = self.index()
        missing = [i for i in indices if int(i) not in idx]
        if missing:
            raise UserError(f"{self.subdir.replace('_', ' ')} {self.dir} has no frame {missing[0]} (build it first)")
        by_chunk: dict[Path, list[tuple[int, int]]] = defaultdict(list)
        for k, i in enumerate(indices):
            path, row = idx[int(i)]
            by_chunk[path].append((k, row))
        out: dict[str, np.ndarray] = {}
        if not by_chunk and self._chunks():  # no frames asked: empty arrays of the cached shapes
            with np.load(self._chunks()[0]) as z:
                return {key: np.zeros((0, *z[key].shape[1:]), z[key].dtype) for key in keys}
        for path, pairs in by_chunk.items():
            ks, rows = [k for k, _ in pairs], [r for _, r in pairs]
            with np.load(path) as z:
                for key in keys:
                    a = z[key]
                    if key not in out:
                        out[key] = np.empty((len(indices), *a.shape[1:]), a.dtype)
                    out[key][ks] = a[rows]
        return out

    def load(self, indices) -> tuple[np.ndarray, np.ndarray]:
        """(features (n, C, rows, cols) float16, losses (n, n_branches) float32, the sum of the four
        Faster R-CNN losses) for `indices`, in that order. Every frame must be cached (`ensure`)."""
        idx = self.index()
        missing = [i for i in indices if int(i) not in idx]
        if missing:
            raise UserError(f"gate dataset {self.dir} has no frame {missing[0]} (build it first)")
        by_chunk: dict[Path, list[tuple[int, int]]] = defaultdict(list)
        for k, i in enumerate(indices):
            path, row = idx[int(i)]
            by_chunk[path].append((k, row))
        feats = losses = None
        for path, pairs in by_chunk.items():
            with np.load(path) as z:
                f, lo = z["features"], z["losses"]
                if feats is None:
                    feats = np.empty((len(indices), *f.shape[1:]), np.float16)
                    losses = np.empty((len(indices), lo.shape[1]), np.float32)
                ks = [k for k, _ in pairs]
                rows = [r for _, r in pairs]
                feats[ks] = f[rows]
                losses[ks] = lo[rows].sum(axis=2)
        if feats is None:
            c = 64 * len(self.sensors)
            return np.zeros((0, c, *self.grid), np.float16), np.zeros((0, len(self.branches)), np.float32)
        return feats, losses

    def branch_losses(self, indices) -> list[dict[str, float]]:
        """Per frame: branch name -> a-posteriori loss (what the optimal gate reads)."""
        _, losses = self.load(indices)
        return [dict(zip(self.branches, map(float, row))) for row in losses]
