"""Torch side of the dataset: frames as model inputs and training targets.

`sensors.dataset.DatasetReader` stays numpy-only; this module is the one place where dataset
arrays become tensors (the network boundary). Input contract of fusion.nets (per frame):
    camera_left, camera_right, fwd_lidar: (3, H, W) float32 in 0..1
    radar: (1, S, S) float32 in 0..1 (8-bit radar BEV / 255)
    lidar: (3, S, S) float32 in 0..1 (height, density, intensity)
Targets: {"camera_left" | "camera_right" | "bev": {"boxes": (N, 4) float32 px, "labels": (N,) int64}},
without the boxes marked difficult (a detector at this resolution cannot be expected to find them;
VOC evaluation ignores them too).
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import torch
from torch.utils.data import Dataset

from sensors.dataset import DatasetReader

SENSORS = ("camera_left", "camera_right", "fwd_lidar", "radar", "lidar")
ARRAY_OF = {"camera_left": "camera_left", "camera_right": "camera_right", "fwd_lidar": "fwd_lidar",
            "radar": "radar_bev", "lidar": "lidar_bev"}
FRAMES = ("camera_left", "camera_right", "bev")


def split_by_sequence(reader: DatasetReader, train_fraction: float = 0.7, seed: int = 0) -> tuple[list[int], list[int]]:
    """Frame indices of a train/test split with no sequence (shard) in both (HydraFusion 5.1: 70:30).

    Shards are split per context (stratified), so every context is in both sets when it has at
    least two sequences. Deterministic in `seed`.
    """
    if not 0 < train_fraction < 1:
        raise ValueError(f"train_fraction must be in (0, 1), got {train_fraction}")
    by_context: dict[str, list[str]] = defaultdict(list)
    frames_of: dict[str, list[int]] = defaultdict(list)
    for i, f in enumerate(reader.manifest["frames"]):
        if f["shard"] not in frames_of:
            by_context[f["context"]].append(f["shard"])
        frames_of[f["shard"]].append(i)
    rng = np.random.default_rng(seed)
    train, test = [], []
    for context in sorted(by_context):
        shards = list(by_context[context])
        rng.shuffle(shards)
        n_train = int(round(train_fraction * len(shards)))
        if len(shards) >= 2:
            n_train = min(max(n_train, 1), len(shards) - 1)
        for k, shard in enumerate(shards):
            (train if k < n_train else test).extend(frames_of[shard])
    return sorted(train), sorted(test)


def carve_sequences(reader: DatasetReader, indices, count, rng) -> tuple[list[int], list[int]]:
    """Split frames into (rest, carved) by whole sequence (shard), per context: each context's
    sequences (sorted, then shuffled by `rng`, contexts in sorted order) give their first
    `count(number of the context's sequences)` to `carved`. What `hold_out_sequences` and the gates'
    validation carve (`study.experiments.selection.validation_split`) share; they differ in `count` and seed."""
    shards: dict[str, dict[str, list[int]]] = defaultdict(lambda: defaultdict(list))
    for i in indices:
        f = reader.manifest["frames"][int(i)]
        shards[f["context"]][f["shard"]].append(int(i))
    rest, carved = [], []
    for context in sorted(shards):
        names = sorted(shards[context])
        rng.shuffle(names)
        n = count(len(names))
        for k, name in enumerate(names):
            (carved if k < n else rest).extend(shards[context][name])
    return sorted(rest), sorted(carved)


def hold_out_sequences(reader: DatasetReader, indices, fraction: float, seed: int = 0) -> tuple[list[int], list[int]]:
    """Split frames into (kept, held out) by whole sequence (shard), per context, deterministic in
    `seed`: the gate split of a run (`study.engine.train.TrainConfig.gate_holdout`), sequences the detectors
    never train on, whose per-branch losses are what the gates learn from.

    `fraction` of each context's sequences (rounded, at least one when `fraction` > 0) is held out;
    a context keeps at least one sequence. `fraction` 0 holds out nothing.
    """
    if not 0 <= fraction < 1:
        raise ValueError(f"the held-out fraction must be in [0, 1), got {fraction}")

    def count(n: int) -> int:
        return min(max(int(round(fraction * n)), 1), n - 1) if fraction > 0 else 0

    # not the validation carve's stream (`study.experiments.selection`)
    return carve_sequences(reader, indices, count, np.random.default_rng([seed, 11]))


def crop_bev_labels(lab: dict, size: tuple[int, int], full: int) -> dict:
    """BEV labels of the crop a model sees: rows [0, H) from the top (forward) and W columns centred.

    Pixel coordinates do not move for a top crop of full width, so calibration-based mappings
    (Appendix A) stay valid; boxes are clipped to the crop and dropped when less than half of
    their area remains.
    """
    H, W = size
    if (H, W) == (full, full):
        return lab
    x0 = (full - W) / 2
    out = {k: [] for k in lab}
    for i, (x1, y1, x2, y2) in enumerate(lab["boxes"]):
        cx1, cy1, cx2, cy2 = max(x1, x0), max(y1, 0.0), min(x2, x0 + W), min(y2, float(H))
        area = (x2 - x1) * (y2 - y1)
        if cx2 <= cx1 or cy2 <= cy1 or (cx2 - cx1) * (cy2 - cy1) < 0.5 * area:
            continue
        for k in lab:
            out[k].append(lab[k][i])
        out["boxes"][-1] = [cx1 - x0, cy1, cx2 - x0, cy2]
    return out


def frame_targets(labels: dict, keep_difficult: bool = False, bev_size: tuple[int, int] | None = None,
                  bev_full: int | None = None, meta: dict | None = None, protocol=None) -> dict:
    """Training targets of one frame under the evaluation `protocol` (fusion.protocol; None = the
    stored labels as they are, i.e. `visible`; other protocols need the frame's `meta`)."""
    if protocol is not None:
        from fusion.protocol import frame_labels

        labels = frame_labels(labels, meta, protocol)
    out = {}
    for frame in FRAMES:
        lab = labels[frame]
        if frame == "bev" and bev_size is not None:
            lab = crop_bev_labels(lab, bev_size, bev_full)
        keep = [i for i, d in enumerate(lab["difficult"]) if keep_difficult or not d]
        boxes = np.array([lab["boxes"][i] for i in keep], np.float32).reshape(-1, 4)
        out[frame] = {"boxes": torch.from_numpy(boxes),
                      "labels": torch.tensor([lab["labels"][i] for i in keep], dtype=torch.int64)}
    return out


def hflip_sample(inputs: dict, targets: dict, widths: dict) -> tuple[dict, dict]:
    """Mirror one frame about the vehicle's vertical longitudinal plane: world and rig together.

    Every input is flipped left-right (camera images and the forward lidar, which lives in the
    right camera's image plane, along their columns; the radar / lidar BEV, whose columns are the
    lateral axis with the radar at the centre, likewise), and every box with it (x -> width - x).
    The result is an exact observation of the mirrored scene by the mirrored rig. In that rig the
    two cameras have changed sides, so a branch that fuses the stereo pair would see its geometry
    reversed: training refuses the flip for such branches (`study.engine.train`).

    `widths`: {target frame: image width [px]} for "camera_left", "camera_right", "bev".
    Returns new dicts; the arguments are not modified.
    """
    flipped_inputs = {s: torch.flip(x, dims=(-1,)) for s, x in inputs.items()}
    flipped_targets = {}
    for frame, t in targets.items():
        b = t["boxes"]
        w = float(widths[frame])
        boxes = torch.stack([w - b[:, 2], b[:, 1], w - b[:, 0], b[:, 3]], dim=1) if len(b) else b.clone()
        flipped_targets[frame] = {**t, "boxes": boxes}
    return flipped_inputs, flipped_targets


def frame_inputs(frame: dict, sensors=SENSORS, bev_size: tuple[int, int] | None = None, uint8: bool = False) -> dict:
    """Model inputs of one frame (the contract above); `uint8`: the stored 8-bit values as they are
    (uint8 tensors, 4x fewer bytes to move to a GPU), for `as_model_input` to scale on the device."""
    out = {}
    for s in sensors:
        arr = np.asarray(frame[ARRAY_OF[s]], np.uint8) if uint8 else np.asarray(frame[ARRAY_OF[s]], np.float32) / 255.0
        if s in ("radar", "lidar") and bev_size is not None:
            full = arr.shape[0]
            x0 = (full - bev_size[1]) // 2
            arr = arr[: bev_size[0], x0:x0 + bev_size[1]]
        if arr.ndim == 2:
            arr = arr[None]
        else:
            arr = arr.transpose(2, 0, 1)
        arr = np.ascontiguousarray(arr)
        out[s] = torch.from_numpy(arr if arr.flags.writeable else arr.copy())  # uint8 views of a read-only load
    return out


def as_model_input(x: torch.Tensor) -> torch.Tensor:
    """A sensor tensor as the network takes it: uint8 (`frame_inputs(..., uint8=True)`) becomes
    float32 / 255 where it is (the same numbers the float path computes); float32 passes unchanged."""
    return x.to(torch.float32) / 255.0 if x.dtype == torch.uint8 else x


class FrameDataset(Dataset):
    """Frames `indices` of a dataset directory as (inputs, targets, meta)."""

    def __init__(self, root, indices=None, sensors=SENSORS, clear: bool = False, keep_difficult: bool = False,
                 bev_size: tuple[int, int] | None = None, protocol=None, uint8: bool = False):
        """`bev_size` (H, W): the BEV crop the model reads (forward rows, centred columns); None = all.
        `protocol`: the evaluation protocol whose ground truth the targets are (fusion.protocol;
        None = the stored labels, `visible`). `uint8`: inputs as the stored uint8 (see
        `frame_inputs`; `as_model_input` scales them where they are used)."""
        self.protocol = protocol
        self.uint8 = bool(uint8)
        self.reader = DatasetReader(root, clear=clear)
        self.bev_full = int(self.reader.manifest.get("bev_size_px") or self.reader.meta(0)["calibration"]["bev_size_px"])
        self.bev_size = None if bev_size is None else (int(bev_size[0]), int(bev_size[1]))
        if self.bev_size is not None and (self.bev_size[0] > self.bev_full or self.bev_size[1] > self.bev_full):
            raise ValueError(f"bev_size {self.bev_size} exceeds the dataset's {self.bev_full} x {self.bev_full} BEV")
        self.indices = list(range(len(self.reader))) if indices is None else list(indices)
        unknown = [s for s in sensors if s not in SENSORS]
        if unknown:
            raise ValueError(f"unknown sensor {unknown[0]!r} (choose from: {', '.join(SENSORS)})")
        self.sensors = tuple(sensors)
        self.keep_difficult = keep_difficult

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, k: int):
        return self.item(k)

    def item(self, k: int, flip: bool = False):
        """Frame k as (inputs, targets, meta); `flip`: mirrored left-right (`hflip_sample`)."""
        i = self.indices[k]
        frame = self.reader[i]
        meta = dict(frame["meta"])
        meta["dataset_index"] = i
        inputs = frame_inputs(frame, self.sensors, self.bev_size, uint8=self.uint8)
        targets = frame_targets(frame["labels"], self.keep_difficult, self.bev_size, self.bev_full,
                                frame["meta"], self.protocol)
        if flip:
            cal = meta["calibration"]
            widths = {"camera_left": cal["camera_left"]["width"], "camera_right": cal["camera_right"]["width"],
                      "bev": self.bev_size[1] if self.bev_size is not None else self.bev_full}
            inputs, targets = hflip_sample(inputs, targets, widths)
        meta["flipped"] = bool(flip)
        return inputs, targets, meta


def collate(batch):
    """List of (inputs, targets, meta) -> (batched inputs dict, list of targets, list of metas)."""
    inputs = {s: torch.stack([b[0][s] for b in batch]) for s in batch[0][0]}
    return inputs, [b[1] for b in batch], [b[2] for b in batch]
