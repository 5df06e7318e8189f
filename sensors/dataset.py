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
from concurrent.futures import ThreadPoolExecutor
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


def _fsync_file(path: Path) -> None:
    with open(path, "rb") as fh:
        os.fsync(fh.fileno())


def _save(path: Path, array: np.ndarray) -> None:
    """np.save, with a strided array (neither C- nor Fortran-ordered, e.g. a stack of transposed
    views) copied to C order first: np.save writes such an array in C order under the same header
    anyway, but element by element."""
    if not array.flags.f_contiguous:
        array = np.ascontiguousarray(array)
    np.save(path, array)


def write_frames(directory: Path, frames: list, extra: dict | None = None) -> None:
    """Write frames (sensors.frame.Frame) as one shard's arrays + frames.json into `directory`.

    Each file is flushed to disk (fsync, in background threads) while the next ones are written,
    so that commit_shard, which fsyncs them all again, mostly finds them on disk already."""
    directory.mkdir(parents=True, exist_ok=True)
    with ThreadPoolExecutor(max_workers=4) as flush:
        flushed = []

        def save(name: str, array: np.ndarray) -> None:
            _save(directory / f"{name}.npy", array)
            flushed.append(flush.submit(_fsync_file, directory / f"{name}.npy"))

        for name in ARRAYS:
            save(name, np.stack([getattr(f, name) for f in frames]))
        offsets = np.cumsum([0] + [len(f.lidar_points) for f in frames]).astype(np.int64)
        save("lidar_points", np.concatenate([f.lidar_points for f in frames]).astype(np.float32))
        save("lidar_instance", np.concatenate([f.lidar_instance for f in frames]).astype(np.int64))
        save("lidar_offsets", offsets)
        records = [{"meta": f.meta, "labels": f.labels} for f in frames]
        payload = {"format_version": FORMAT_VERSION, "frames": records, **(extra or {})}
        (directory / "frames.json").write_text(json.dumps(payload, separators=(",", ":")))
        flushed.append(flush.submit(_fsync_file, directory / "frames.json"))
        for done in flushed:
            done.result()  # re-raises a failed fsync


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
    """Make the shard written in `tmp` durable, then publish it as `final` (atomic rename).

    Every file is fsynced before the rename and the parent directory after it, so an interrupted
    run leaves either no shard or a complete one. The files are fsynced concurrently (threads: the
    kernel then writes them back together instead of one flush after another)."""
    files = [p for p in tmp.rglob("*") if p.is_file()]
    with ThreadPoolExecutor(max_workers=max(1, min(16, len(files)))) as pool:
        for _ in pool.map(_fsync_file, files):  # re-raises the first error
            pass
    os.replace(tmp, final)
    _fsync_dir(final.parent)


def clean_partial(root: Path) -> int:
    """Remove leftovers of interrupted shard writes; returns how many."""
    n = 0
    for p in root.glob("shard-*.tmp-*"):
        shutil.rmtree(p, ignore_errors=True)
        n += 1
    return n


def foreign_entries(root: Path) -> list[str]:
    """Names in `root` that no dataset writer made (an existing dataset, or a partial one, is fine)."""
    import re

    if not root.is_dir():
        return []
    ours = re.compile(r"^(manifest\.json|\.manifest\.json\.tmp-\d+|shard-\d{5}(\.tmp-\d+)?)$")
    return sorted(p.name for p in root.iterdir() if not ours.match(p.name))


def write_manifest(root: Path, manifest: dict) -> None:
    tmp = root / f".manifest.json.tmp-{os.getpid()}"
    tmp.write_text(json.dumps(manifest, indent=1))
    os.replace(tmp, root / "manifest.json")


class DatasetError(UserError):
    """A dataset that cannot be read: names the file and what is wrong with it."""

    def __init__(self, root: Path, path: Path, problem: str, hint: bool = True):
        self.root, self.path, self.problem = Path(root), Path(path), problem
        self.short = f"{path}: {problem}"
        super().__init__(self.short + (f" (run `hydrabench verify {root}`)" if hint else ""))


def _expect(ok: bool, root: Path, path: Path, problem: str) -> None:
    if not ok:
        raise DatasetError(root, path, problem)


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _load_json(root: Path, path: Path):
    if not path.is_file():
        raise DatasetError(root, path, "is missing")
    try:
        return json.loads(path.read_text())
    except UnicodeDecodeError:
        raise DatasetError(root, path, "is not text (not valid JSON)") from None
    except json.JSONDecodeError as exc:
        raise DatasetError(root, path, f"is not valid JSON ({exc.msg} at line {exc.lineno})") from None
    except OSError as exc:
        raise DatasetError(root, path, f"cannot be read ({exc.strerror})") from None


def read_manifest(root: str | Path) -> dict:
    """The manifest of dataset `root`, checked field by field (DatasetError naming what is wrong)."""
    root = Path(root)
    path = root / "manifest.json"
    if not root.is_dir():
        raise UserError(f"{root} is not a directory" if root.exists() else f"{root} does not exist")
    if not path.exists():
        raise UserError(f"{root} has no manifest.json (not a dataset, or its generation did not finish)")
    m = _load_json(root, path)
    _expect(isinstance(m, dict), root, path, f"is a JSON {type(m).__name__}, expected an object")
    if m.get("format_version") != FORMAT_VERSION:
        v = m.get("format_version")
        what = f" ({FORMAT_HISTORY[v]})" if v in FORMAT_HISTORY else ""
        raise UserError(f"{path}: dataset format version {v}{what} is not supported by this hydrabench, which "
                        f"reads format {FORMAT_VERSION} ({FORMAT_HISTORY[FORMAT_VERSION]}); regenerate it with "
                        f"`hydrabench generate`")
    _expect(isinstance(m.get("config"), dict), root, path, "'config' must be an object")
    _expect(isinstance(m.get("profile"), str), root, path, "'profile' must be a string")
    shards, frames = m.get("shards"), m.get("frames")
    _expect(isinstance(shards, list) and shards, root, path, "'shards' must be a non-empty list")
    _expect(isinstance(frames, list), root, path, "'frames' must be a list")
    sizes = {}
    for k, s in enumerate(shards):
        where = f"shards[{k}]"
        _expect(isinstance(s, dict), root, path, f"{where} must be an object")
        name = s.get("name")
        _expect(isinstance(name, str) and name.startswith("shard-") and name[6:].isdigit(), root, path,
                f"{where}.name must be a shard name like shard-00000, got {name!r}")
        _expect(name not in sizes, root, path, f"shard {name} is listed twice")
        _expect(isinstance(s.get("sha256"), str), root, path, f"{where}.sha256 must be a string")
        for key in ("frames", "severity", "seed"):
            _expect(_is_int(s.get(key)), root, path, f"{where}.{key} must be an integer, got {s.get(key)!r}")
        _expect(s["frames"] >= 1, root, path, f"{where}.frames must be >= 1")
        _expect(isinstance(s.get("context"), str), root, path, f"{where}.context must be a string")
        sizes[name] = s["frames"]
    for k, f in enumerate(frames):
        where = f"frames[{k}]"
        _expect(isinstance(f, dict), root, path, f"{where} must be an object")
        _expect(f.get("shard") in sizes, root, path, f"{where}.shard {f.get('shard')!r} is not a listed shard")
        _expect(_is_int(f.get("index")) and 0 <= f["index"] < sizes[f["shard"]], root, path,
                f"{where}.index {f.get('index')!r} is not a frame of {f['shard']}")
        _expect(isinstance(f.get("context"), str) and _is_int(f.get("severity")), root, path,
                f"{where} needs a context (string) and a severity (integer)")
    return m


def verify(root: str | Path) -> list[str]:
    """Check every shard against the manifest; returns a list of problems (empty when intact).

    An unreadable manifest is the one problem returned; a shard's problems are one line each."""
    from sim.progress import progress

    root = Path(root)
    try:
        m = read_manifest(root)
    except DatasetError as exc:
        return [exc.short]
    except UserError as exc:
        return [str(exc)]
    problems = []
    bar = progress(total=len(m["shards"]), desc="verify", unit="shard")
    for s in m["shards"]:
        d = root / s["name"]
        if not d.is_dir():
            problems.append(f"{s['name']}: missing")
        elif shard_digest(d) != s["sha256"]:
            problems.append(f"{s['name']}: checksum mismatch (corrupted)")
        bar.update(1)
    bar.close()
    return problems


def check(root: str | Path) -> dict:
    """Check a dataset's structure whole, before a command starts work: the manifest, and for every
    shard (and its clear twins) frames.json and each array's header against the manifest (frame
    counts, lidar offsets). Cheap: no pixel is read; the checksums are `verify`'s job.
    Returns the manifest; raises DatasetError naming the first damaged file."""
    reader = DatasetReader(Path(root))
    twins = DatasetReader(reader.root, clear=True) if reader.manifest["config"].get("twins") else None
    for s in reader.manifest["shards"]:
        reader.check_shard(s["name"])
        if twins is not None:
            twins.check_shard(s["name"])
    return reader.manifest


@dataclass
class DatasetReader:
    """Lazy reader: arrays are memory-mapped per shard, labels loaded per shard on first use.

    `reader[i]` returns a dict with the frame's arrays (read-only views), "lidar_points",
    "lidar_instance", "labels" and "meta". `clear=True` reads the clear-weather twins.
    Each shard is checked (`check_shard`) the first time it is used, so a damaged file gives a
    DatasetError naming it, never a numpy or JSON traceback.
    """

    root: Path
    clear: bool = False
    manifest: dict = field(init=False)
    index: list = field(init=False)
    _arrays: dict = field(default_factory=dict, init=False)
    _json: dict = field(default_factory=dict, init=False)
    _checked: set = field(default_factory=set, init=False)

    def __post_init__(self) -> None:
        self.root = Path(self.root)
        self.manifest = read_manifest(self.root)
        if self.clear and not self.manifest["config"].get("twins"):
            raise UserError(f"{self.root} has no clear twins (generate with --twins)")
        self.index = [(f["shard"], f["index"]) for f in self.manifest["frames"]]
        self._frames = {s["name"]: s["frames"] for s in self.manifest["shards"]}

    def __len__(self) -> int:
        return len(self.index)

    def _dir(self, shard: str) -> Path:
        return self.root / shard / "clear" if self.clear else self.root / shard

    def check_shard(self, shard: str) -> None:
        """Check one shard's frames.json and array headers against the manifest (DatasetError)."""
        if shard in self._checked:
            return
        d = self._dir(shard)
        if not d.is_dir():
            raise DatasetError(self.root, d, "is missing")
        n = self._frames[shard]
        self._load_records(shard)
        arrays = {name: self._open(shard, name) for name in ARRAYS + POINT_ARRAYS}
        for name in ARRAYS:
            a = arrays[name]
            _expect(a.ndim >= 3 and a.shape[0] == n and a.dtype == np.uint8, self.root, d / f"{name}.npy",
                    f"holds {a.dtype} {a.shape}, expected uint8 with {n} frames")
        pts, inst, off = arrays["lidar_points"], arrays["lidar_instance"], arrays["lidar_offsets"]
        _expect(pts.ndim == 2 and pts.shape[1] == 5 and pts.dtype == np.float32, self.root, d / "lidar_points.npy",
                f"holds {pts.dtype} {pts.shape}, expected float32 (N, 5)")
        _expect(inst.shape == (len(pts),), self.root, d / "lidar_instance.npy",
                f"holds {inst.shape}, expected ({len(pts)},) like lidar_points")
        _expect(off.shape == (n + 1,) and off.dtype.kind in "iu", self.root, d / "lidar_offsets.npy",
                f"holds {off.dtype} {off.shape}, expected integers ({n + 1},)")
        o = np.asarray(off)
        _expect(o[0] == 0 and o[-1] == len(pts) and bool(np.all(np.diff(o) >= 0)), self.root,
                d / "lidar_offsets.npy", f"offsets do not index lidar_points ({len(pts)} points)")
        self._checked.add(shard)

    def _open(self, shard: str, name: str) -> np.ndarray:
        key = (shard, name)
        if key not in self._arrays:
            path = self._dir(shard) / f"{name}.npy"
            if not path.is_file():
                raise DatasetError(self.root, path, "is missing")
            try:
                self._arrays[key] = np.load(path, mmap_mode="r", allow_pickle=False)
            except Exception as exc:  # truncated, bad header, pickled: numpy's reasons vary
                reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                raise DatasetError(self.root, path, f"is not a readable .npy array ({reason})") from None
        return self._arrays[key]

    def _array(self, shard: str, name: str) -> np.ndarray:
        self.check_shard(shard)
        return self._open(shard, name)

    def _load_records(self, shard: str) -> list:
        if shard not in self._json:
            path = self._dir(shard) / "frames.json"
            doc = _load_json(self.root, path)
            _expect(isinstance(doc, dict) and isinstance(doc.get("frames"), list), self.root, path,
                    "must be an object with a 'frames' list")
            recs = doc["frames"]
            _expect(len(recs) == self._frames[shard], self.root, path,
                    f"has {len(recs)} frames, the manifest says {self._frames[shard]}")
            for k, r in enumerate(recs):
                _expect(isinstance(r, dict) and isinstance(r.get("meta"), dict) and isinstance(r.get("labels"), dict),
                        self.root, path, f"frames[{k}] must be an object with 'meta' and 'labels' objects")
            self._json[shard] = recs
        return self._json[shard]

    def records(self, shard: str) -> list:
        self.check_shard(shard)
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
