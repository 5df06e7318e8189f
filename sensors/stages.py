"""A digest of every generation stage for one frame, to find where two machines part.

Generation is a chain: traffic simulation -> static and actor meshes -> the cameras' code pass
(pyrender on Mesa llvmpipe) -> the lidar and radar scans (Embree) -> camera shading (numba
kernels, Embree shadow rays) -> degradation (numpy random streams, numba) -> the stored arrays
(camera model, lidar and radar images) -> labels. `stage_digests` runs that chain for the first
frame of one context's first sequence, exactly as `hydrabench generate` does, and hashes each
stage's output; `first_difference` compares two such records (from two machines, or from one
machine under two settings) and names the first stage whose bytes differ. A stage that differs
while every stage above it agrees is where the machines part.

Measured with this tool (2026-12-02, the same Xeon, Embree's ISA forced through its device
config): Embree's AVX-512 and AVX2 kernels give the same camera bytes but a few lidar points and
radar bins differ (1-2 points of ~27,000 a frame), so Embree, which dispatches on the CPU, is one
source of cross-CPU differences; the reference dataset in `tests/data/reference/` shows the
camera arrays differ too across CPUs (docs/dataset.md, "Determinism").
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import platform
from importlib import metadata

import numpy as np

STAGES = (
    "simulation", "static_mesh", "actors_mesh", "camera_raster", "lidar_scan", "radar_scan",
    "camera_shading", "degradation", "camera_images", "lidar_images", "radar_images", "labels",
)
"""The stages in the order generation runs them (`stage_digests` keys, `first_difference` order)."""

LIBRARIES = ("numpy", "scipy", "numba", "embreex", "trimesh", "pyrender", "PyOpenGL", "highway-env", "shapely")
CPU_FLAGS = ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512_bf16", "amx_bf16")
"""The /proc/cpuinfo flags that decide which kernels numpy, numba, Embree and llvmpipe dispatch to."""


def digest(value) -> str:
    """sha256 (first 16 hex) of a value: arrays by dtype, shape and bytes; dataclasses by their
    fields; dicts by sorted keys; lists and tuples in order; anything else by its repr."""
    h = hashlib.sha256()
    _feed(h, value)
    return h.hexdigest()[:16]


def _feed(h, value) -> None:
    if isinstance(value, np.ndarray):
        a = np.ascontiguousarray(value)
        h.update(f"nd|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    elif dataclasses.is_dataclass(value) and not isinstance(value, type):
        h.update(f"dc|{type(value).__name__}|".encode())
        for f in dataclasses.fields(value):
            h.update(f.name.encode())
            _feed(h, getattr(value, f.name))
    elif isinstance(value, dict):
        h.update(b"dict|")
        for k in sorted(value, key=str):
            h.update(str(k).encode())
            _feed(h, value[k])
    elif isinstance(value, (list, tuple)):
        h.update(f"seq|{len(value)}|".encode())
        for v in value:
            _feed(h, v)
    else:
        h.update(f"{type(value).__name__}|{value!r}|".encode())


def platform_record() -> dict:
    """What decides the bytes besides the code: CPU model and flags, library versions, OpenGL."""
    flags, model = set(), ""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as fh:
            for line in fh:
                key, _, val = line.partition(":")
                if key.strip() == "model name" and not model:
                    model = val.strip()
                elif key.strip() == "flags" and not flags:
                    flags = set(val.split())
    except OSError:
        pass
    versions = {}
    for lib in LIBRARIES:
        try:
            versions[lib] = metadata.version(lib)
        except metadata.PackageNotFoundError:
            versions[lib] = None
    return {
        "machine": platform.machine(),
        "cpu": model or platform.processor(),
        "cpu_flags": [f for f in CPU_FLAGS if f in flags],
        "python": platform.python_version(),
        "libraries": versions,
        "env": {k: os.environ[k] for k in ("PYOPENGL_PLATFORM", "NPY_DISABLE_CPU_FEATURES", "NUMBA_CPU_NAME",
                                            "LP_NATIVE_VECTOR_WIDTH", "OPENBLAS_CORETYPE") if k in os.environ},
    }


def stage_digests(context: str = "city", seed: int = 3, profile: str = "cpu") -> dict:
    """Run generation's first frame of `context` (the first shard of
    `GenerateConfig(contexts=(context,), seed=seed, profile=profile)`) and digest each stage.

    Returns {"config", "shard": {context, severity, seed}, "stages": {stage: digest} in STAGES
    order, "platform": platform_record()}."""
    from sensors.camera import gl_info
    from sensors.generate import GenerateConfig, open_sequence, plan

    config = GenerateConfig(contexts=(context,), frames_per_context=1, sequence_length=1, seed=seed, profile=profile)
    spec = plan(config)[0]
    _sim, scenes, renderer, degrader, _ = open_sequence(spec, config)
    scene = scenes[0]
    d = {"simulation": digest([(s.actors, s.ego, s.weather, s.light) for s in scenes]),
         "static_mesh": digest(renderer.static)}
    trace: dict = {}
    raw = renderer.observe(scene, trace=trace)
    for stage in ("actors_mesh", "camera_raster", "lidar_scan", "radar_scan", "camera_shading"):
        d[stage] = digest(trace[stage])
    obs, params = raw, {}
    if degrader is not None:
        obs, params = degrader.apply(raw, scene.frame_index)
    d["degradation"] = digest((obs.camera_left, obs.camera_right, obs.lidar, obs.radar, params))
    frame = renderer.finalize(scene, obs, params, clean=raw)
    d["camera_images"] = digest((frame.camera_left, frame.camera_right))
    d["lidar_images"] = digest((frame.lidar_points, frame.lidar_instance, frame.lidar_bev, frame.fwd_lidar))
    d["radar_images"] = digest((frame.radar_polar, frame.radar_bev))
    d["labels"] = digest(frame.labels)
    return {
        "config": {"context": context, "seed": seed, "profile": profile},
        "shard": {"context": spec.context, "severity": spec.severity, "seed": spec.seed},
        "stages": {s: d[s] for s in STAGES},
        "platform": {**platform_record(), "opengl": gl_info()},
    }


def first_difference(a: dict, b: dict) -> str | None:
    """The first stage (in STAGES order) whose digest differs between two `stage_digests`
    records, or None when all agree. Records of different configs cannot be compared."""
    if a.get("config") != b.get("config"):
        raise ValueError(f"the records are of different configs: {a.get('config')} vs {b.get('config')}")
    for stage in STAGES:
        if a["stages"].get(stage) != b["stages"].get(stage):
            return stage
    return None


# --- two datasets of one config made on two machines ------------------------------------------

TOLERANCES = {
    "object_max_abs": 1e-3,
    "box_px_max_abs": 2.0,
    "box_rel": 0.1,
    "box_min_px": 20,
    "count_rel": 0.10,
    "count_abs": 5,
    "camera_mean_abs": 2.0,
    "camera_far_fraction": 0.02,
    "lidar_points_rel": 0.005,
    "image_diff_fraction": 0.01,
    "radar_mean_abs": 0.5,
    "radar_far_fraction": 0.01,
}
"""How far two machines' datasets of one config may differ (the cross-machine contract,
docs/dataset.md "Determinism"). On one machine bytes are identical; across CPUs the renderer and
ray caster dispatch on the CPU (Embree's AVX-512 and AVX2 kernels hit a few triangle edges
differently), so what is compared is what a user reads from a dataset:

- object_max_abs: the simulation's 3D objects (ids and classes equal; centre, size [m], yaw [rad],
  velocity [m/s] within this);
- box_px_max_abs [px], box_rel, box_min_px: each camera's visible-pixel boxes of the same actors
  (same ids), of those seen by at least box_min_px pixels on both, within box_px_max_abs or
  box_rel of the box's width / height;
- count_rel, count_abs: per-object counts (visible pixels, lidar points, radar cells) within
  count_rel of the larger, or count_abs;
- camera_mean_abs [levels of 255] and camera_far_fraction: mean |difference| of each camera image,
  and the share of pixels that differ by more than 16 levels;
- lidar_points_rel: points per frame;
- image_diff_fraction: share of lidar BEV / forward-image pixels that differ at all;
- radar_mean_abs [counts, 0.5 dB each] and radar_far_fraction: mean |difference| of the radar
  images, and the share of cells that differ by more than 4 counts (2 dB).
"""


def _counts_close(a, b) -> bool:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return a.shape == b.shape and bool(np.all(np.abs(a - b) <= np.maximum(
        TOLERANCES["count_abs"], TOLERANCES["count_rel"] * np.maximum(np.abs(a), np.abs(b)))))


def dataset_differences(a, b) -> list[str]:
    """Compare two datasets of one generation config, shard by shard and frame by frame (numpy
    and json only). Returns the violations of TOLERANCES, one line each ([] = within the contract).
    Raises ValueError if their configs or shard plans differ (nothing to compare)."""
    import json
    from pathlib import Path

    a, b = Path(a), Path(b)
    ma, mb = (json.loads((d / "manifest.json").read_text()) for d in (a, b))
    if ma["config"] != mb["config"] or [s["name"] for s in ma["shards"]] != [s["name"] for s in mb["shards"]]:
        raise ValueError("the datasets are of different generation configs")
    bad: list[str] = []
    for shard in (s["name"] for s in ma["shards"]):
        sa, sb = a / shard, b / shard
        bad += [f"{shard}/{m}" for m in _array_differences(sa, sb)]
        fa, fb = (json.loads((s / "frames.json").read_text())["frames"] for s in (sa, sb))
        if len(fa) != len(fb):
            bad.append(f"{shard}: {len(fa)} vs {len(fb)} frames")
            continue
        for k, (x, y) in enumerate(zip(fa, fb)):
            bad += [f"{shard}/frame {k}: {m}" for m in _label_differences(x["labels"], y["labels"])]
    return bad


def _array_differences(sa, sb) -> list[str]:
    T, bad = TOLERANCES, []
    for name in ("camera_left", "camera_right"):
        x, y = (np.load(s / f"{name}.npy").astype(np.int16) for s in (sa, sb))
        if x.shape != y.shape:
            bad.append(f"{name}: shape {x.shape} vs {y.shape}")
            continue
        d = np.abs(x - y)
        if d.mean() > T["camera_mean_abs"] or (d > 16).mean() > T["camera_far_fraction"]:
            bad.append(f"{name}: mean |diff| {d.mean():.3f} levels, {(d > 16).mean():.4f} of pixels > 16")
    na, nb = (np.diff(np.load(s / "lidar_offsets.npy")) for s in (sa, sb))  # (frames + 1,) starts
    if na.shape != nb.shape or np.any(np.abs(na - nb) > T["lidar_points_rel"] * np.maximum(na, nb)):
        bad.append(f"lidar points per frame {na.tolist()} vs {nb.tolist()}")
    for name in ("lidar_bev", "fwd_lidar"):
        x, y = (np.load(s / f"{name}.npy") for s in (sa, sb))
        if x.shape != y.shape or np.any(x != y, axis=-1).mean() > T["image_diff_fraction"]:
            bad.append(f"{name}: {np.any(x != y, axis=-1).mean() if x.shape == y.shape else 'shape'} of pixels differ")
    for name in ("radar_polar", "radar_bev"):
        x, y = (np.load(s / f"{name}.npy").astype(np.int16) for s in (sa, sb))
        if x.shape != y.shape:
            bad.append(f"{name}: shape {x.shape} vs {y.shape}")
            continue
        d = np.abs(x - y)
        if d.mean() > T["radar_mean_abs"] or (d > 4).mean() > T["radar_far_fraction"]:
            bad.append(f"{name}: mean |diff| {d.mean():.3f} counts, {(d > 4).mean():.4f} of cells > 4")
    return bad


def _label_differences(la: dict, lb: dict) -> list[str]:
    T, bad = TOLERANCES, []
    oa, ob = la["objects"], lb["objects"]
    if oa["ids"] != ob["ids"] or oa["labels"] != ob["labels"]:
        return ["3D objects: different actors or classes"]
    for key in ("center", "size", "yaw", "velocity"):
        d = np.abs(np.asarray(oa[key], float) - np.asarray(ob[key], float))
        if d.size and d.max() > T["object_max_abs"]:
            bad.append(f"3D objects: {key} differs by {d.max():.4g}")
    for key in ("camera_left_px", "camera_right_px", "lidar_points", "radar_cells"):
        if not _counts_close(oa[key], ob[key]):
            bad.append(f"3D objects: {key} beyond the count tolerance")
    for cam in ("camera_left", "camera_right"):
        ca, cb = la[cam], lb[cam]
        common = sorted(set(ca["ids"]) & set(cb["ids"]))
        ia = [ca["ids"].index(i) for i in common]
        ib = [cb["ids"].index(i) for i in common]
        # an actor seen by a handful of pixels may be seen on one machine only
        only = [i for i in set(ca["ids"]) ^ set(cb["ids"])
                if max(_px(ca, i), _px(cb, i)) > T["count_abs"]]
        if only:
            bad.append(f"{cam}: actors {sorted(only)} boxed on one machine only")
        # boxes of actors seen by enough pixels on both: one pixel more of a thin fragment can
        # stretch the box of a barely visible actor
        big = [k for k, i in enumerate(common) if min(_px(ca, i), _px(cb, i)) >= T["box_min_px"]]
        ba, bb = (np.asarray(c["boxes"], float).reshape(-1, 4)[ix][big] for c, ix in ((ca, ia), (cb, ib)))
        size = np.tile(np.maximum(ba[:, 2:] - ba[:, :2], bb[:, 2:] - bb[:, :2]), 2)  # w, h, w, h
        over = np.abs(ba - bb) > np.maximum(T["box_px_max_abs"], T["box_rel"] * size)
        if over.any():
            bad.append(f"{cam}: boxes of actors {[common[big[k]] for k in np.flatnonzero(over.any(axis=1))]} differ by "
                       f"up to {np.abs(ba - bb).max():.1f} px")
        if not _counts_close(np.asarray(ca["visible_px"])[ia], np.asarray(cb["visible_px"])[ib]):
            bad.append(f"{cam}: visible pixels beyond the count tolerance")
    return bad


def _px(cam_labels: dict, actor_id: int) -> int:
    ids = cam_labels["ids"]
    return cam_labels["visible_px"][ids.index(actor_id)] if actor_id in ids else 0


def platform_key(record: dict | None = None) -> str:
    """One line naming what the bytes of a dataset depend on besides the code: CPU model and
    dispatch flags, OpenGL renderer and version, the versions of the dispatching libraries. Two
    machines with the same key are expected to make the same bytes (tests/sensors/test_determinism.py
    records digests by it)."""
    from sensors.camera import gl_info

    r = record or {**platform_record(), "opengl": gl_info()}
    libs = ", ".join(f"{k} {r['libraries'][k]}" for k in ("numpy", "numba", "embreex", "pyrender"))
    return (f"{r['machine']} {r['cpu']} [{' '.join(r['cpu_flags'])}] | {r['opengl']['renderer']}, "
            f"{r['opengl']['version']} | {libs}")
