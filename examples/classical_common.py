"""What the two classical detectors share: the command line, reading a nuScenes export through the
nuScenes devkit, sensor-to-global transforms, DBSCAN, box records in nuScenes' results format.

Nothing here imports hydrabench: a detector in examples/ sees the export as any nuScenes user sees
nuScenes (tables, sensor files, calibration, ego poses, map masks), so what it scores says that a
detector written against the devkit alone can be scored by `hydrabench score`.

A detector is a function `detect(nusc, sample, ctx) -> [Detection, ...]` (boxes in the ego frame of
the sample's sensor data); `main` runs it over the export's samples and writes the results file.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

DETECTION_NAMES = ("car", "truck", "bus", "trailer", "construction_vehicle", "pedestrian", "motorcycle", "bicycle",
                   "traffic_cone", "barrier")
"""nuScenes' ten detection classes (the devkit's `detection_cvpr_2019`): every box names one."""



class DetectorError(Exception):
    """Bad input to a detector: printed as one line, exit code 2."""


@dataclass(frozen=True)
class Detection:
    """One 3D box in a frame's ego frame (x forward, y left, z up) [m]: centre (3,), size (length,
    width, height), yaw about z [rad] with the box's length along yaw, a detection name, a score."""

    center: np.ndarray
    size: tuple[float, float, float]
    yaw: float
    name: str
    score: float


# ------------------------------------------------------------------------------------------------
# reading the export


def find_version(root: Path, version: str | None) -> str:
    """The tables' folder name under `root` (`v1.0-*`): `version` when given, else the only one there."""
    if not root.is_dir():
        raise DetectorError(f"--export {root}: no such directory (make one with: hydrabench export nuscenes DATA "
                            "--out DIR)")
    found = sorted(p.name for p in root.iterdir() if p.is_dir() and p.name.startswith("v1.0-")
                   and (p / "sample.json").is_file())
    if version is not None:
        if version not in found:
            raise DetectorError(f"--export {root}: no tables for version {version!r} (found: {', '.join(found) or 'none'})")
        return version
    if len(found) != 1:
        raise DetectorError(f"--export {root}: {'no' if not found else 'several'} nuScenes table folders "
                            f"(v1.0-*/sample.json){': ' + ', '.join(found) if found else ''}; name one with --version")
    return found[0]


def load_nuscenes(root: Path, version: str | None):
    """The devkit's `NuScenes` of an export (its tables checked for what the detectors read)."""
    from nuscenes import NuScenes

    version = find_version(root, version)
    try:
        return NuScenes(version=version, dataroot=str(root), verbose=False)
    except (AssertionError, KeyError, ValueError, OSError) as exc:
        raise DetectorError(f"--export {root}: the nuScenes devkit cannot load {version} ({type(exc).__name__}: "
                            f"{exc})") from None


def split_samples(nusc, split: str | None) -> list[dict]:
    """The samples of `split` (a split of the export's splits.json, the devkit's custom splits), or
    every sample, in the tables' order."""
    if split is None:
        return list(nusc.sample)
    path = Path(nusc.dataroot) / nusc.version / "splits.json"
    splits = json.loads(path.read_text()) if path.is_file() else {}
    if split not in splits:
        raise DetectorError(f"--split {split}: not a split of the export ({', '.join(sorted(splits)) or 'none'})")
    scenes = {s["token"] for s in nusc.scene if s["name"] in set(splits[split])}
    return [s for s in nusc.sample if s["scene_token"] in scenes]


def sensor_data(nusc, sample: dict, channel: str) -> dict:
    """The sample's sample_data record of `channel` (DetectorError when the export has none)."""
    if channel not in sample["data"]:
        raise DetectorError(f"sample {sample['token']}: no {channel} data (channels: {', '.join(sample['data'])})")
    return nusc.get("sample_data", sample["data"][channel])


def poses(nusc, sd: dict) -> tuple[np.ndarray, np.ndarray]:
    """(ego_from_sensor, global_from_ego), 4x4 each, of a sample_data record (its calibrated sensor
    and its ego pose)."""
    from nuscenes.utils.geometry_utils import transform_matrix
    from pyquaternion import Quaternion

    cs = nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
    ep = nusc.get("ego_pose", sd["ego_pose_token"])
    return (transform_matrix(cs["translation"], Quaternion(cs["rotation"])),
            transform_matrix(ep["translation"], Quaternion(ep["rotation"])))


def transform(points: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """(N, 3) points through a 4x4 rigid transform."""
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def map_mask_of(nusc, sample: dict):
    """The devkit's `MapMask` (road and sidewalks) of the sample's log."""
    scene = nusc.get("scene", sample["scene_token"])
    log = scene["log_token"]
    for m in nusc.map:
        if log in m["log_tokens"]:
            return m["mask"]
    raise DetectorError(f"sample {sample['token']}: its log {log} has no map (--no-map runs without one)")


# ------------------------------------------------------------------------------------------------
# pieces of the detectors


def clusters(xy: np.ndarray, eps: float, min_points: int, voxel: float = 0.0) -> list[np.ndarray]:
    """Indices of each DBSCAN cluster of the points `xy` (N, 2) [m] (noise dropped), largest first.

    `voxel` > 0: the points are first merged into square cells of that side and the cells clustered
    (`min_points` then counts cells), each point taking its cell's cluster: the same clusters as
    Euclidean clustering at `eps` up to a cell, at a fraction of the neighbour searches."""
    if len(xy) == 0:
        return []
    from sklearn.cluster import DBSCAN

    if voxel > 0:
        cells = np.floor(xy / voxel).astype(np.int64)
        key = (cells[:, 0] - cells[:, 0].min()) * (cells[:, 1].max() - cells[:, 1].min() + 1) + cells[:, 1] - cells[:, 1].min()
        _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
        labels = DBSCAN(eps=eps, min_samples=min_points, algorithm="kd_tree").fit_predict((cells[first] + 0.5) * voxel)[inverse.ravel()]
    else:
        labels = DBSCAN(eps=eps, min_samples=min_points, algorithm="kd_tree").fit_predict(xy)
    keep = np.flatnonzero(labels >= 0)
    order = keep[np.argsort(labels[keep], kind="stable")]
    groups = np.split(order, np.flatnonzero(np.diff(labels[order])) + 1) if len(order) else []
    return sorted(groups, key=len, reverse=True)


def along_line_of_sight(center_xy: np.ndarray, sensor_xy: np.ndarray, yaw: float, length: float, width: float,
                        seen_extent: float) -> np.ndarray:
    """A box's centre (2,) when only its near side was seen: the seen points' centre `center_xy`
    moved away from the sensor by half of what the box's footprint (length x width at `yaw`) extends
    along the line of sight beyond the `seen_extent` [m] measured along it."""
    u = center_xy - sensor_xy
    dist = float(np.hypot(*u))
    if dist < 1e-6:
        return center_xy
    u = u / dist
    c, s = math.cos(yaw), math.sin(yaw)
    depth = abs(length * (u[0] * c + u[1] * s)) + abs(width * (-u[0] * s + u[1] * c))
    return center_xy + u * max(depth - seen_extent, 0.0) / 2.0


def result_box(token: str, det: Detection, global_from_ego: np.ndarray) -> dict:
    """A nuScenes results box: `det` (ego frame) in the global frame, size (width, length, height),
    rotation (w, x, y, z). A single sweep gives no velocity and no moving/stopped attribute: velocity
    NaN and attribute "" say "not estimated" (so the devkit's metrics report no mAVE, mAAE or NDS for
    them rather than errors of a guess)."""
    from pyquaternion import Quaternion

    c, s = math.cos(det.yaw), math.sin(det.yaw)
    rot = global_from_ego[:3, :3] @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    q = Quaternion(matrix=rot, rtol=1e-6, atol=1e-6)
    length, width, height = det.size
    return {"sample_token": token, "translation": [float(v) for v in transform(det.center[None], global_from_ego)[0]],
            "size": [float(width), float(length), float(height)], "rotation": [float(v) for v in q.elements],
            "velocity": [math.nan, math.nan], "detection_name": det.name, "detection_score": float(det.score),
            "attribute_name": ""}


# ------------------------------------------------------------------------------------------------
# the command line


def parser(description: str, epilog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=description, epilog=epilog,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--export", type=Path, required=True, metavar="DIR",
                   help="a nuScenes export (hydrabench export nuscenes DATA --out DIR), or any dataset in the "
                        "nuScenes v1.0 layout with the channel this detector reads")
    p.add_argument("--out", type=Path, required=True, metavar="FILE.json",
                   help="the nuScenes detection-results JSON to write (replaced when complete)")
    p.add_argument("--version", default=None, help="the tables' folder (default: the only v1.0-* folder in DIR)")
    p.add_argument("--split", default=None,
                   help="detect only on this split's scenes (the export's splits.json; default: every sample)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    return p


def write_json(path: Path, doc) -> None:
    """`doc` as JSON at `path`, written beside it and renamed when complete."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(doc))
    os.replace(tmp, path)


def write_results(path: Path, results: dict, meta: dict) -> None:
    """A nuScenes detection-results file: {"meta": meta, "results": {sample token: [box, ...]}}."""
    write_json(path, {"meta": meta, "results": results})


def run(args, channel: str, detect, meta: dict, name: str) -> int:
    """`detect(nusc, sample, ctx)` on every sample of `args.split`; the results file at `args.out`."""
    if args.out.is_dir():
        raise DetectorError(f"--out {args.out}: is a directory; give a file name (e.g. {name}.json)")
    t0 = time.perf_counter()
    nusc = load_nuscenes(args.export, args.version)
    samples = split_samples(nusc, args.split)
    if not samples:
        raise DetectorError(f"--export {args.export}: no samples{' in split ' + args.split if args.split else ''}")
    ctx: dict = {}
    results, count = {}, 0
    for i, sample in enumerate(samples):
        sd = sensor_data(nusc, sample, channel)
        _, global_from_ego = poses(nusc, sd)
        dets = detect(nusc, sample, ctx)
        results[sample["token"]] = [result_box(sample["token"], d, global_from_ego) for d in dets]
        count += len(dets)
        if not args.quiet and (i + 1 == len(samples) or (i + 1) % 16 == 0):
            print(f"{name}: {i + 1}/{len(samples)} samples, {count} boxes, {time.perf_counter() - t0:.1f} s",
                  file=sys.stderr)
    write_results(args.out, results, meta)
    if not args.quiet:
        print(f"{name}: wrote {count} boxes on {len(samples)} samples to {args.out} "
              f"({time.perf_counter() - t0:.1f} s)", file=sys.stderr)
    return 0


def command(doc: str, channel: str, detect, sensor: str) -> argparse.ArgumentParser:
    """The command line of a detector of one `sensor` ("lidar", "radar") on `channel`: `doc` (its
    module docstring: what it does, step by step) as its description, --no-map, its meta block from
    the sensor and the map."""
    name = f"{sensor}_detector"
    p = parser(doc.strip(), f"example:\n  hydrabench export nuscenes data --out data-ns\n"
               f"  python examples/{name}.py --export data-ns --out {sensor}.json\n"
               f"  hydrabench score data --export data-ns --nuscenes {sensor}={sensor}.json")
    p.add_argument("--no-map", action="store_true",
                   help="keep what lies off the road and sidewalks too (meta use_map false)")

    def go(args):
        meta = {"use_camera": False, "use_lidar": sensor == "lidar", "use_radar": sensor == "radar",
                "use_map": not args.no_map, "use_external": False}
        return run(args, channel, lambda nusc, sample, ctx: detect(nusc, sample, {**ctx, "use_map": not args.no_map}),
                   meta, name)

    p.set_defaults(run=go)
    return p


def main(build, argv=None) -> int:
    """Parse, run, and turn a DetectorError into one line and exit code 2."""
    args = build().parse_args(argv)
    try:
        return args.run(args)
    except DetectorError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
