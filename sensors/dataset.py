"""The on-disk dataset: shards of frames, readable with numpy and json alone.

Layout of a dataset directory DIR:

    DIR/manifest.json            format version, the full generation config, seed, per-shard
                                 sha256 / frame count / context / severity, per-frame index
    DIR/shard-00000/             one sequence = one shard (a unit of work: a pure function of
                                 (config, seed, shard index))
        frames.json              per frame: meta (context, weather, degradation params,
                                 calibration, ego pose, ...) and labels (FWD per camera, BEV,
                                 3D objects with their clean observability)
        camera_left.npy          (L, H, W, 3) uint8        camera_right.npy  (L, H, W, 3) uint8
        fwd_lidar.npy            (L, H, W, 3) uint8        lidar_bev.npy     (L, S, S, 3) uint8
        radar_polar.npy          (L, A, B) uint8 (0.5 dB/count)   radar_bev.npy (L, S, S) uint8
        lidar_points.npy         (N, 5) float32 x, y, z [m] (lidar frame), intensity, ring
        lidar_instance.npy       (N,) int64 actor id per point   lidar_offsets.npy (L + 1,) int64
        clear/                   optional counterfactual twins: the same arrays and frames.json
                                 for the same moments rendered in clear weather

A shard is written to `shard-XXXXX.tmp-<pid>` and renamed when complete (rename is atomic), so a
shard is never half-written; an interrupted generation resumes by skipping complete shards.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sim.errors import UserError

# 2: labels["objects"] (3D boxes with their clean observability) and twins that differ only by the
#    condition (same clear-air visibility and light); 1: visible-pixel and BEV boxes only.
FORMAT_VERSION = 2
FORMAT_HISTORY = {1: "visible-pixel and BEV boxes only, no 3D ground truth", 2: "3D ground truth per frame"}
ARRAYS = ("camera_left", "camera_right", "fwd_lidar", "lidar_bev", "radar_polar", "radar_bev")
POINT_ARRAYS = ("lidar_points", "lidar_instance", "lidar_offsets")
SHARD_FMT = "shard-{:05d}"


def shard_name(index: int) -> str:
    return SHARD_FMT.format(index)


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_frames(directory: Path, frames: list, extra: dict | None = None) -> None:
    """Write frames (sensors.frame.Frame) as one shard's arrays + frames.json into `directory`."""
    directory.mkdir(parents=True, exist_ok=True)
    for name in ARRAYS:
        np.save(directory / f"{name}.npy", np.stack([getattr(f, name) for f in frames]))
    offsets = np.cumsum([0] + [len(f.lidar_points) for f in frames]).astype(np.int64)
    np.save(directory / "lidar_points.npy", np.concatenate([f.lidar_points for f in frames]).astype(np.float32))
    np.save(directory / "lidar_instance.npy", np.concatenate([f.lidar_instance for f in frames]).astype(np.int64))
    np.save(directory / "lidar_offsets.npy", offsets)
    records = [{"meta": f.meta, "labels": f.labels} for f in frames]
    payload = {"format_version": FORMAT_VERSION, "frames": records, **(extra or {})}
    (directory / "frames.json").write_text(json.dumps(payload, separators=(",", ":")))


def shard_digest(directory: Path) -> str:
    """sha256 over every file of a shard (relative path and bytes, in sorted order)."""
    h = hashlib.sha256()
    for p in sorted(directory.rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(directory)).encode())
            with open(p, "rb") as fh:
                for chunk in iter(lambda: fh.read(1 << 20), b""):
                    h.update(chunk)
    return h.hexdigest()


def commit_shard(tmp: Path, final: Path) -> None:
    for p in tmp.rglob("*"):
        if p.is_file():
            with open(p, "rb") as fh:
                os.fsync(fh.fileno())
    os.replace(tmp, final)
    _fsync_dir(final.parent)


def clean_partial(root: Path) -> int:
    """Remove leftovers of interrupted shard writes; returns how many."""
    n = 0
    for p in root.glob("shard-*.tmp-*"):
        shutil.rmtree(p, ignore_errors=True)
        n += 1
    return n


def write_manifest(root: Path, manifest: dict) -> None:
    tmp = root / f".manifest.json.tmp-{os.getpid()}"
    tmp.write_text(json.dumps(manifest, indent=1))
    os.replace(tmp, root / "manifest.json")


def read_manifest(root: str | Path) -> dict:
    root = Path(root)
    path = root / "manifest.json"
    if not root.is_dir():
        raise UserError(f"{root} is not a directory")
    if not path.exists():
        raise UserError(f"{root} has no manifest.json (not a dataset, or its generation did not finish)")
    try:
        m = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise UserError(f"{path} is not valid JSON ({exc.msg})") from None
    if m.get("format_version") != FORMAT_VERSION:
        v = m.get("format_version")
        what = f" ({FORMAT_HISTORY[v]})" if v in FORMAT_HISTORY else ""
        raise UserError(f"{path}: dataset format version {v}{what} is not supported by this hydrabench, which "
                        f"reads format {FORMAT_VERSION} ({FORMAT_HISTORY[FORMAT_VERSION]}); regenerate it with "
                        f"`hydrabench generate`")
    return m


def verify(root: str | Path) -> list[str]:
    """Check every shard against the manifest; returns a list of problems (empty when intact)."""
    root = Path(root)
    m = read_manifest(root)
    problems = []
    for s in m["shards"]:
        d = root / s["name"]
        if not d.is_dir():
            problems.append(f"{s['name']}: missing")
            continue
        if shard_digest(d) != s["sha256"]:
            problems.append(f"{s['name']}: checksum mismatch (corrupted)")
    return problems


@dataclass
class DatasetReader:
    """Lazy reader: arrays are memory-mapped per shard, labels loaded per shard on first use.

    `reader[i]` returns a dict with the frame's arrays (read-only views), "lidar_points",
    "lidar_instance", "labels" and "meta". `clear=True` reads the clear-weather twins.
    """

    root: Path
    clear: bool = False
    manifest: dict = field(init=False)
    index: list = field(init=False)
    _arrays: dict = field(default_factory=dict, init=False)
    _json: dict = field(default_factory=dict, init=False)

    def __post_init__(self) -> None:
        self.root = Path(self.root)
        self.manifest = read_manifest(self.root)
        if self.clear and not self.manifest["config"].get("twins"):
            raise UserError(f"{self.root} has no clear twins (generate with --twins)")
        self.index = [(f["shard"], f["index"]) for f in self.manifest["frames"]]

    def __len__(self) -> int:
        return len(self.index)

    def _dir(self, shard: str) -> Path:
        return self.root / shard / "clear" if self.clear else self.root / shard

    def _array(self, shard: str, name: str) -> np.ndarray:
        key = (shard, name)
        if key not in self._arrays:
            path = self._dir(shard) / f"{name}.npy"
            if not path.exists():
                raise UserError(f"{path} is missing (run `hydrabench verify {self.root}`)")
            self._arrays[key] = np.load(path, mmap_mode="r")
        return self._arrays[key]

    def records(self, shard: str) -> list:
        if shard not in self._json:
            self._json[shard] = json.loads((self._dir(shard) / "frames.json").read_text())["frames"]
        return self._json[shard]

    def meta(self, i: int) -> dict:
        shard, k = self.index[i]
        return self.records(shard)[k]["meta"]

    def labels(self, i: int) -> dict:
        shard, k = self.index[i]
        return self.records(shard)[k]["labels"]

    def __getitem__(self, i: int) -> dict:
        if not -len(self) <= i < len(self):
            raise IndexError(f"frame index {i} out of range (dataset has {len(self)} frames)")
        shard, k = self.index[i]
        out = {name: self._array(shard, name)[k] for name in ARRAYS}
        off = self._array(shard, "lidar_offsets")
        a, b = int(off[k]), int(off[k + 1])
        out["lidar_points"] = self._array(shard, "lidar_points")[a:b]
        out["lidar_instance"] = self._array(shard, "lidar_instance")[a:b]
        rec = self.records(shard)[k]
        out["labels"] = rec["labels"]
        out["meta"] = rec["meta"]
        return out


def to_coco(reader: DatasetReader, camera: str = "camera_right") -> dict:
    """FWD labels of one camera as a COCO detection dict (pycocotools-loadable).

    Images are referenced as "<shard>/<camera>.npy#<index>" (the pixels live in the .npy arrays).
    Difficult boxes carry "iscrowd": 0 and "ignore": 1 (COCO tools skip them when asked to).
    """
    from sim.actors import CLASSES

    if camera not in ("camera_left", "camera_right"):
        raise UserError(f"camera must be camera_left or camera_right, got {camera!r}")
    images, annotations = [], []
    ann_id = 1
    for i in range(len(reader)):
        shard, k = reader.index[i]
        meta = reader.meta(i)
        cal = meta["calibration"][camera]
        images.append({"id": i + 1, "file_name": f"{shard}/{camera}.npy#{k}", "width": cal["width"],
                       "height": cal["height"], "context": meta["context"], "severity": meta["severity"]})
        lab = reader.labels(i)[camera]
        for aid, cls, box, diff, occ in zip(lab["ids"], lab["labels"], lab["boxes"], lab["difficult"], lab["occlusion"]):
            x1, y1, x2, y2 = box
            annotations.append({"id": ann_id, "image_id": i + 1, "category_id": int(cls),
                                "bbox": [x1, y1, x2 - x1, y2 - y1], "area": (x2 - x1) * (y2 - y1),
                                "iscrowd": 0, "ignore": int(bool(diff)), "track_id": int(aid),
                                "occlusion": occ})
            ann_id += 1
    categories = [{"id": i + 1, "name": c, "supercategory": "road_user"} for i, c in enumerate(CLASSES)]
    return {"info": {"description": "hydrabench FWD labels", "camera": camera,
                     "dataset": str(reader.root), "format_version": FORMAT_VERSION},
            "images": images, "annotations": annotations, "categories": categories}
