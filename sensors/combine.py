"""One dataset made of several: a view whose shards are links to the parts' shards.

A study's detectors train on one dataset and its gates and test on others, each with its own seed
and size, so that enlarging the gate or test set regenerates only that set and retrains no detector.
Everything downstream reads one dataset and picks its frames by index (`DatasetReader`, the split
lists of a run); `combine` gives it one: ``out/shard-NNNNN`` links to each part's shards in the order
the parts are given, and ``out/manifest.json`` lists every part's frames in that order, with
``parts[name] = {"start", "stop", "config", "manifest_sha256"}`` saying which frames came from which
part. The links are relative, so a folder holding both the parts and the view can move.

The view's config holds the fields on which every part agrees (profile, contexts, twins, ...) and,
under "combined", each part's own config: two views of the same parts have the same config, and a
view of a changed part has another. A sequence keeps its `sequence_id` (a hash of its scenario and
seed), so sequences of parts generated with different seeds never collide; `combine` refuses parts
that share one.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from collections.abc import Mapping
from pathlib import Path

from sensors.dataset import DatasetReader, read_manifest, shard_name, write_manifest
from sim.errors import UserError


def _sequence_ids(reader: DatasetReader) -> set[str]:
    return {reader.meta(int(first))["sequence_id"] for first in _first_frames(reader)}


def _first_frames(reader: DatasetReader) -> list[int]:
    seen, out = set(), []
    for i, (shard, _k) in enumerate(reader.index):
        if shard not in seen:
            seen.add(shard)
            out.append(i)
    return out


def combine(parts: Mapping[str, str | Path], out: str | Path) -> dict:
    """Write the view of `parts` {name: dataset directory} (in that order) into `out`; returns its
    manifest. `out` must not exist or be a view of exactly these parts (then it is left as it is)."""
    if not parts:
        raise UserError("combine: no parts")
    out = Path(out)
    manifests = {name: read_manifest(path) for name, path in parts.items()}
    first = next(iter(manifests.values()))
    for name, m in manifests.items():
        if m["profile"] != first["profile"] or m.get("format_version") != first.get("format_version"):
            raise UserError(f"combine: part {name!r} has sensor profile {m['profile']!r} (format "
                            f"{m.get('format_version')}), the first part {first['profile']!r} "
                            f"(format {first.get('format_version')}): a view needs one")
    seqs: dict[str, str] = {}
    for name, path in parts.items():
        for s in _sequence_ids(DatasetReader(Path(path))):
            if s in seqs:
                raise UserError(f"combine: sequence {s} is in both {seqs[s]!r} and {name!r} (same seed?)")
            seqs[s] = name
    configs = {name: m["config"] for name, m in manifests.items()}
    shared = {k: v for k, v in first["config"].items() if all(c.get(k) == v for c in configs.values())}
    view = {"format_version": first["format_version"], "profile": first["profile"],
            "config": {**shared, "combined": configs}, "seed": None, "shards": [], "frames": [], "parts": {}}
    links = []
    for name, path in parts.items():
        src, m = Path(path).resolve(), manifests[name]
        rename = {}
        for s in m["shards"]:
            new = shard_name(len(view["shards"]))
            rename[s["name"]] = new
            view["shards"].append({**s, "name": new})
            links.append((src / s["name"], new))
        start = len(view["frames"])
        view["frames"].extend({**f, "shard": rename[f["shard"]]} for f in m["frames"])
        view["parts"][name] = {"start": start, "stop": len(view["frames"]), "config": m["config"],
                               "manifest_sha256": hashlib.sha256((src / "manifest.json").read_bytes()).hexdigest()}
    if (out / "manifest.json").exists():
        if json.loads((out / "manifest.json").read_text()) == view:
            return view
        raise UserError(f"combine: {out} already holds another dataset; choose an empty folder")
    if out.exists() and any(out.iterdir()):
        raise UserError(f"combine: {out} is not empty")
    tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for target, new in links:
        os.symlink(os.path.relpath(target, out.resolve()), tmp / new)  # tmp becomes out: relative to out
    write_manifest(tmp, view)
    if out.exists():
        out.rmdir()
    os.replace(tmp, out)
    return view


def part_indices(manifest: dict, name: str) -> list[int]:
    """The frame indices of the view that came from part `name`."""
    parts = manifest.get("parts") or {}
    if name not in parts:
        raise UserError(f"not a part of this dataset: {name!r} (parts: {', '.join(parts) or 'none'})")
    return list(range(parts[name]["start"], parts[name]["stop"]))
