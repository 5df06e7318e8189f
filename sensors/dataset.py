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

import contextlib
import errno
import fcntl
import functools
import hashlib
import json
import math
import os
import re
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
    try:
        np.save(path, array)
    except OSError as exc:
        if exc.errno is not None:
            raise
        # numpy reports a short write ("127780 requested and 110560 written") without an errno: the
        # disk (or the quota) is full; said so, so that the command can say it in one line
        raise OSError(errno.ENOSPC, f"{os.strerror(errno.ENOSPC)} ({exc})", str(path)) from None


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
    if not root.is_dir():
        return []
    ours = re.compile(r"^(manifest\.json|\.manifest\.json\.tmp-\d+|\.generate\.lock|shard-\d{5}(\.tmp-\d+)?)$")
    return sorted(p.name for p in root.iterdir() if not ours.match(p.name))


def lock_name(command: str) -> str:
    """The lock file of `command`'s output directory: .generate.lock, .train.lock."""
    return f".{command}.lock"


@contextlib.contextmanager
def output_lock(root: Path, command: str = "generate"):
    """Hold an exclusive lock on the output directory `root` of `command` (a dataset for generate,
    a run for train: fcntl.flock on root/.<command>.lock, which holds the holder's PID) while
    writing it; a second writer is refused (UserError naming the holder's PID), not left to race
    the first. The lock goes with the process (a killed run holds nothing); the file is removed on
    release."""
    path = Path(root) / lock_name(command)
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise UserError(f"cannot lock {root} for writing ({exc.strerror})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
            os.close(fd)
            raise UserError(f"{root} is being written by another hydrabench {command} "
                            f"({'PID ' + holder if holder.isdigit() else 'its PID not yet recorded'}); "
                            "wait for it to finish, or use another --out") from None
        st = os.fstat(fd)
        try:
            now = os.stat(path)
        except FileNotFoundError:
            now = None
        if now is not None and (now.st_dev, now.st_ino) == (st.st_dev, st.st_ino):
            break
        os.close(fd)  # the holder removed the file between our open and our lock: lock the new one
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield path
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)
        os.close(fd)


def write_manifest(root: Path, manifest: dict) -> None:
    """Write root/manifest.json atomically: a temporary file renamed over it, removed when the write
    fails (a full disk leaves no partial manifest)."""
    tmp = root / f".manifest.json.tmp-{os.getpid()}"
    try:
        tmp.write_text(json.dumps(manifest, indent=1))
        os.replace(tmp, root / "manifest.json")
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


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


def _not_finite(obj, where: str = "") -> str | None:
    """Where in a JSON value the first NaN or infinity is (a path such as frames[0].labels.bev.boxes[2][1])."""
    if isinstance(obj, float):
        return None if math.isfinite(obj) else where or "the value"
    if isinstance(obj, dict):
        items = ((f"{where}.{k}" if where else str(k), v) for k, v in obj.items())
    elif isinstance(obj, list):
        items = ((f"{where}[{i}]", v) for i, v in enumerate(obj))
    else:
        return None
    for w, v in items:
        found = _not_finite(v, w)
        if found:
            return found
    return None


# A number with a 3-digit exponent (1e999 reads as infinity); what precedes it tells a JSON number
# from letters and digits inside a string (a hex id such as "7ce3e50e0c0e728a")
_BIG_EXPONENT = re.compile(r"[-+.0-9]*[0-9][eE]\+?[0-9]{3,}")


class _NotFinite(Exception):
    pass


def _no_constant(name: str):
    raise _NotFinite(name)  # json calls this for NaN, Infinity and -Infinity (JSON has none of them)


def _may_overflow(text: str) -> bool:
    return any(m.start() == 0 or text[m.start() - 1] in ":,[ \n\t" for m in _BIG_EXPONENT.finditer(text))


def _load_json(root: Path, path: Path):
    """A dataset JSON file, parsed, with every number finite (DatasetError naming the file and where)."""
    if not path.is_file():
        raise DatasetError(root, path, "is missing")
    try:
        text = path.read_text(encoding="utf-8")
        doc = json.loads(text, parse_constant=_no_constant)
        not_finite = _may_overflow(text)
    except _NotFinite:
        doc, not_finite = json.loads(text), True
    except UnicodeDecodeError:
        raise DatasetError(root, path, "is not text (not valid JSON)") from None
    except json.JSONDecodeError as exc:
        raise DatasetError(root, path, f"is not valid JSON ({exc.msg} at line {exc.lineno})") from None
    except OSError as exc:
        raise DatasetError(root, path, f"cannot be read ({exc.strerror})") from None
    if not_finite:  # (the walk, to say where, only when the text holds one: a fast path)
        where = _not_finite(doc)
        if where:
            raise DatasetError(root, path, f"{where} is not a finite number (NaN or infinity)")
    return doc


def _is_number(v) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


LABEL_FRAMES = ("camera_left", "camera_right", "bev")
"""The 2D label sets of a frame: columnar lists of one length, with at least these columns."""
LABEL_COLUMNS = ("ids", "labels", "boxes", "difficult")

BOX_MARGIN = 0.5
"""How far a 2D label box may reach beyond its image (or BEV grid), as a fraction of that image's
width (x) or height (y). `generate` clips every box to its image (measured: no box of 96 frames of
every context, twins included, reaches beyond it), so the margin is for a truncated object's unclipped
box from another labelling tool; a box beyond it (x1 = -5000 on a 336-pixel image) is damage."""
RIGID_TOLERANCE = 1e-3
"""A stored extrinsic's rotation R must have |R R' - I| and |det R - 1| under this (max abs entry)."""
MATRIX_TOLERANCE = 1e-9
"""Entries of K that must be 0 (below the diagonal and the skew) or 1 (K[2][2]) must be within this."""
EXTRINSICS = ("ego_from_lidar", "ego_from_radar")
"""The calibration's sensor poses beside the cameras' ego_from_camera: 4x4 rigid transforms."""


def _matrix(m, rows: int) -> bool:
    return (isinstance(m, list) and len(m) == rows
            and all(isinstance(r, list) and len(r) == rows and all(_is_number(x) for x in r) for r in m))


def _intrinsics_problem(K) -> str | None:
    """What is wrong with a camera matrix K (None: it is [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with
    fx, fy > 0, the form `sensors.rig.CameraCalibration` projects with; such a K is never singular)."""
    if not _matrix(K, 3):
        return "must be 3x3 numbers"
    if K[0][0] <= 0 or K[1][1] <= 0:
        return f"focal lengths K[0][0], K[1][1] must be > 0, got {K[0][0]:g}, {K[1][1]:g} (0 makes K singular)"
    if max(abs(K[0][1]), abs(K[1][0]), abs(K[2][0]), abs(K[2][1]), abs(K[2][2] - 1.0)) > MATRIX_TOLERANCE:
        return f"must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (upper triangular, no skew), got {str(K)[:60]}"
    return None


def _rigid_problem(T) -> str | None:
    """What makes a 4x4 pose T not a rigid transform (None: rotation orthonormal with det +1 within
    RIGID_TOLERANCE, last row 0 0 0 1). Plain Python: 3x3 products per frame cost microseconds."""
    if not _matrix(T, 4):
        return "must be 4x4 numbers"
    if T[3] != [0, 0, 0, 1]:
        return f"last row must be [0, 0, 0, 1], got {T[3]}"
    R = [row[:3] for row in T[:3]]
    off = max(abs(sum(R[i][k] * R[j][k] for k in range(3)) - (i == j)) for i in range(3) for j in range(3))
    det = (R[0][0] * (R[1][1] * R[2][2] - R[1][2] * R[2][1]) - R[0][1] * (R[1][0] * R[2][2] - R[1][2] * R[2][0])
           + R[0][2] * (R[1][0] * R[2][1] - R[1][1] * R[2][0]))
    if off > RIGID_TOLERANCE or abs(det - 1.0) > RIGID_TOLERANCE:
        return (f"is not a rigid transform (its rotation must be orthonormal with determinant +1: "
                f"|R R' - I| = {off:.3g}, det = {det:.3g})")
    return None


_NUMBER_TYPES = (int, float)  # (JSON numbers; a bool's type is bool, so true and false are not numbers)


def _check_boxes(root: Path, path: Path, where: str, boxes: list, width, height) -> None:
    """Every box 4 numbers [x1, y1, x2, y2], not inverted, within BOX_MARGIN of the image. (One
    condition per box, the reason worked out only for a box that fails: a dataset has millions.)"""
    lo_x, lo_y = -BOX_MARGIN * width, -BOX_MARGIN * height
    hi_x, hi_y = width - lo_x, height - lo_y
    num = _NUMBER_TYPES
    for j, b in enumerate(boxes):
        if (type(b) is list and len(b) == 4 and type(b[0]) in num and type(b[1]) in num and type(b[2]) in num
                and type(b[3]) in num and lo_x <= b[0] <= b[2] <= hi_x and lo_y <= b[1] <= b[3] <= hi_y):
            continue
        _expect(isinstance(b, list) and len(b) == 4 and all(_is_number(x) for x in b), root, path,
                f"{where}.boxes[{j}] must be 4 numbers [x1, y1, x2, y2], got {str(b)[:40]}")
        x1, y1, x2, y2 = b
        _expect(x1 <= x2 and y1 <= y2, root, path, f"{where}.boxes[{j}] is inverted (x2 < x1 or y2 < y1): {b}")
        raise DatasetError(root, path, f"{where}.boxes[{j}] {b} reaches beyond its {width}x{height} image by more "
                                       f"than {BOX_MARGIN:g} of its size")


def _check_record(root: Path, path: Path, k: int, rec: dict, camera: tuple[int, int], bev: int) -> None:
    """One frames.json record: the cameras' calibration (width x height of the profile, K, a rigid
    ego_from_camera), the other extrinsics (rigid), the BEV grid (`bev` pixels, the profile's), the label
    sets (columns of one length, boxes [x1, y1, x2, y2] numbers within BOX_MARGIN of their image and not
    inverted, integer ids and classes) and the 3D objects (columns of one length, positive sizes). NaN
    and infinity are refused for the whole file by _load_json."""
    cal = rec["meta"].get("calibration")
    _expect(isinstance(cal, dict), root, path, f"frames[{k}].meta.calibration must be an object")
    for name in ("camera_left", "camera_right"):
        c = cal.get(name)
        _expect(isinstance(c, dict) and (c.get("height"), c.get("width")) == camera, root, path,
                f"frames[{k}].meta.calibration.{name} must give the profile's {camera[1]}x{camera[0]} "
                f"(width x height)")
        problem = _intrinsics_problem(c.get("K"))
        _expect(problem is None, root, path, f"frames[{k}].meta.calibration.{name}.K {problem}")
        problem = _rigid_problem(c.get("ego_from_camera"))
        _expect(problem is None, root, path, f"frames[{k}].meta.calibration.{name}.ego_from_camera {problem}")
    for name in EXTRINSICS:
        problem = _rigid_problem(cal.get(name))
        _expect(problem is None, root, path, f"frames[{k}].meta.calibration.{name} {problem}")
    _expect(cal.get("bev_size_px") == bev, root, path,
            f"frames[{k}].meta.calibration.bev_size_px must be the profile's {bev}, got {cal.get('bev_size_px')!r}")
    where = f"frames[{k}].labels"
    labels = rec["labels"]
    for frame in LABEL_FRAMES:
        lab = labels.get(frame)
        _expect(isinstance(lab, dict), root, path, f"{where} has no {frame!r} object")
        for col in LABEL_COLUMNS:
            _expect(isinstance(lab.get(col), list), root, path, f"{where}.{frame}.{col} must be a list")
        n = len(lab["boxes"])
        for col, v in lab.items():
            _expect(isinstance(v, list) and len(v) == n, root, path,
                    f"{where}.{frame}.{col} must be a list of {n} entries, like boxes")
        size = (bev, bev) if frame == "bev" else (camera[1], camera[0])
        _check_boxes(root, path, f"{where}.{frame}", lab["boxes"], *size)
        for col in ("ids", "labels"):
            _expect(all(_is_int(x) for x in lab[col]), root, path, f"{where}.{frame}.{col} must be integers")
    objects = labels.get("objects")
    _expect(isinstance(objects, dict) and isinstance(objects.get("ids"), list), root, path,
            f"{where}.objects must be an object with an 'ids' list")
    for col, v in objects.items():
        _expect(isinstance(v, list) and len(v) == len(objects["ids"]), root, path,
                f"{where}.objects.{col} must be a list of {len(objects['ids'])} entries, like ids")
    num = _NUMBER_TYPES
    for j, s in enumerate(objects.get("size", ())):
        if not (type(s) is list and len(s) == 3 and type(s[0]) in num and type(s[1]) in num and type(s[2]) in num
                and s[0] > 0 and s[1] > 0 and s[2] > 0):
            raise DatasetError(root, path, f"{where}.objects.size[{j}] must be 3 positive numbers (length, width, "
                                           f"height) [m], got {str(s)[:40]}")


@functools.lru_cache(maxsize=256)
def _context_problem(name: str) -> str | None:
    """Why `name` is not a context this hydrabench generates (its canonical name, as sim writes it),
    or None when it is one."""
    from sim.scenario import CONTEXT_NAMES, Context

    try:
        canonical = Context.parse(name).name
    except UserError:
        return f"{name!r} is not a known context (one of {', '.join(CONTEXT_NAMES)}, or a combination as in city+night+rain)"
    return None if canonical == name else f"{name!r} is not a context's canonical name (that is {canonical!r})"


MANIFEST_KEYS = frozenset({"format_version", "sensor_model_version", "created_by", "config", "seed", "profile",
                           "shards", "frames", "parts"})
"""The keys a manifest may hold (`sensors.generate.generate` writes all but "parts", which a view of
several datasets adds, `sensors.combine`); any other is refused, as the YAML loader refuses unknown keys."""


def read_manifest(root: str | Path) -> dict:
    """The manifest of dataset `root`, checked field by field (DatasetError naming what is wrong)."""
    root = Path(root)
    path = root / "manifest.json"
    try:
        is_dir, exists, has_manifest = root.is_dir(), root.exists(), path.exists()
    except OSError as exc:  # a file name too long, a symlink loop
        raise UserError(f"{root}: cannot be read as a dataset ({exc.strerror})") from None
    if not is_dir:
        raise UserError(f"{root} is not a directory" if exists else f"{root} does not exist")
    if not has_manifest:
        raise UserError(f"{root} has no manifest.json (not a dataset, or its generation did not finish)")
    m = _load_json(root, path)
    _expect(isinstance(m, dict), root, path, f"is a JSON {type(m).__name__}, expected an object")
    unknown = sorted(set(m) - MANIFEST_KEYS)
    if unknown:
        raise DatasetError(root, path, f"unknown key {unknown[0][:40]!r} (a manifest holds "
                                       f"{', '.join(sorted(MANIFEST_KEYS))})")
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
        _expect(_context_problem(s["context"]) is None, root, path, f"{where}.context: {_context_problem(s['context'])}")
        sizes[name] = s["frames"]
    for k, f in enumerate(frames):
        where = f"frames[{k}]"
        _expect(isinstance(f, dict), root, path, f"{where} must be an object")
        _expect(f.get("shard") in sizes, root, path, f"{where}.shard {f.get('shard')!r} is not a listed shard")
        _expect(_is_int(f.get("index")) and 0 <= f["index"] < sizes[f["shard"]], root, path,
                f"{where}.index {f.get('index')!r} is not a frame of {f['shard']}")
        _expect(isinstance(f.get("context"), str) and _is_int(f.get("severity")), root, path,
                f"{where} needs a context (string) and a severity (integer)")
        _expect(_context_problem(f["context"]) is None, root, path, f"{where}.context: {_context_problem(f['context'])}")
    return m


def verify(root: str | Path) -> list[str]:
    """Everything `check` refuses, plus every shard's checksum against the manifest; returns a list
    of problems (empty when intact).

    An unreadable manifest is the one problem returned; otherwise each unlisted shard folder, and
    each shard's missing folder, checksum mismatch and first structural problem (of the shard and
    of its twins), is one line."""
    from sim.progress import progress

    root = Path(root)
    try:
        m = read_manifest(root)
    except DatasetError as exc:
        return [exc.short]
    except UserError as exc:
        return [str(exc)]
    problems = [f"{name}: {UNLISTED}" for name in unlisted_shards(root, m)]
    readers = [DatasetReader(root)] + ([DatasetReader(root, clear=True)] if m["config"].get("twins") else [])
    bar = progress(total=len(m["shards"]), desc="verify", unit="shard")
    for s in m["shards"]:
        d = root / s["name"]
        if not d.is_dir():
            problems.append(f"{s['name']}: missing")
        else:
            if shard_digest(d) != s["sha256"]:
                problems.append(f"{s['name']}: checksum mismatch (corrupted)")
            for reader in readers:  # the same check every other command runs first
                try:
                    reader.check_shard(s["name"])
                except DatasetError as exc:
                    problems.append(exc.short)
        bar.update(1)
    bar.close()
    return problems


UNLISTED = "a shard folder manifest.json does not list (the manifest lost shards, or is another generation's)"


def unlisted_shards(root: Path, manifest: dict) -> list[str]:
    """The shard folders (shard-NNNNN) of `root` that the manifest does not list."""
    listed = {s["name"] for s in manifest["shards"]}
    return sorted(p.name for p in Path(root).iterdir() if re.fullmatch(r"shard-\d{5}", p.name) and p.name not in listed)


def check(root: str | Path) -> dict:
    """Check a dataset's structure whole, before a command starts work: the manifest, no shard
    folder it does not list, and for every shard (and its clear twins) frames.json (contexts
    included) and each array's header against the manifest (frame counts, lidar offsets), and the
    lidar points finite. Cheap: no pixel is read; the checksums are `verify`'s job.
    Returns the manifest; raises DatasetError naming the first damaged file."""
    reader = DatasetReader(Path(root))
    unlisted = unlisted_shards(reader.root, reader.manifest)
    if unlisted:
        raise DatasetError(reader.root, reader.root / unlisted[0], UNLISTED)
    twins = DatasetReader(reader.root, clear=True) if reader.manifest["config"].get("twins") else None
    for s in reader.manifest["shards"]:
        reader.check_shard(s["name"])
        if twins is not None:
            twins.check_shard(s["name"])
    return reader.manifest


@functools.lru_cache(maxsize=8)
def _profile_shapes(name: str) -> dict:
    """Each array's per-frame shape under sensor profile `name` (configs/profiles, read once)."""
    from sensors.rig import load_profile

    p = load_profile(name)
    cam, s = (p.camera.height, p.camera.width, 3), p.bev.size_px
    return {"camera_left": cam, "camera_right": cam, "fwd_lidar": cam, "lidar_bev": (s, s, 3),
            "radar_polar": (p.radar.azimuths, p.radar.range_bins), "radar_bev": (s, s)}


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
        self._contexts = {(f["shard"], f["index"]): f["context"] for f in self.manifest["frames"]}
        self._shapes: dict | None = None

    def frame_shapes(self) -> dict:
        """Each array's per-frame shape under the dataset's sensor profile (DatasetError when the
        manifest names a profile this hydrabench does not have)."""
        if self._shapes is None:
            from sensors.rig import profile_names

            name = self.manifest["profile"]
            _expect(name in profile_names(), self.root, self.root / "manifest.json",
                    f"profile {name!r} is not a sensor profile of this hydrabench ({', '.join(profile_names())})")
            self._shapes = _profile_shapes(name)
        return self._shapes

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
        shapes = self.frame_shapes()
        for name in ARRAYS:
            a, want = arrays[name], (n, *shapes[name])
            _expect(a.shape == want and a.dtype == np.uint8, self.root, d / f"{name}.npy",
                    f"holds {a.dtype} {a.shape}, expected uint8 {want} ({n} frames at profile "
                    f"{self.manifest['profile']})")
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
        # one summing pass (NaN and infinity survive a sum; float32 values cannot overflow a float64
        # one); the slower search for where only when it fails
        if len(pts) and not math.isfinite(float(np.add.reduce(pts, axis=None, dtype=np.float64))):
            row = int(np.flatnonzero(~np.isfinite(pts).all(axis=1))[0])
            k = int(np.searchsorted(o, row, side="right")) - 1
            raise DatasetError(self.root, d / "lidar_points.npy",
                               f"frame {k}: point {row - int(o[k])} is not finite (NaN or infinity)")
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
            camera, bev = self.frame_shapes()["camera_right"][:2], self.frame_shapes()["radar_bev"][0]
            for k, r in enumerate(recs):
                _expect(isinstance(r, dict) and isinstance(r.get("meta"), dict) and isinstance(r.get("labels"), dict),
                        self.root, path, f"frames[{k}] must be an object with 'meta' and 'labels' objects")
                _check_record(self.root, path, k, r, camera, bev)
                self._check_context(shard, path, k, r["meta"].get("context"))
            self._json[shard] = recs
        return self._json[shard]

    def _check_context(self, shard: str, path: Path, k: int, context) -> None:
        """A frame's meta.context: a known context, the one the manifest lists for the frame."""
        _expect(isinstance(context, str), self.root, path, f"frames[{k}].meta.context must be a string")
        problem = _context_problem(context)
        _expect(problem is None, self.root, path, f"frames[{k}].meta.context: {problem}")
        listed = self._contexts.get((shard, k))
        _expect(listed in (None, context), self.root, path,
                f"frames[{k}].meta.context is {context!r}, manifest.json lists the frame as {listed!r}")

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
