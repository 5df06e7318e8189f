"""Dataset shards as Ray tasks (`hydrabench generate --backend ray`).

A shard is a pure function of (generation config, shard spec) (`sensors.generate.generate_shard`),
so one shard is one Ray task. The task renders the shard into a scratch directory on whichever node
runs it and returns the shard's files as bytes; the driver writes them under a temporary name and
renames the directory, exactly as the local pool's workers do. The dataset directory therefore only
has to exist where the command runs (no shared file system across the cluster), and its arrays are
byte-identical to the local pool's.

Without an address a local Ray instance is started for the command (as many CPUs as --workers, no
dashboard, every port on 127.0.0.1) and shut down at the end. With `address` ("HOST:PORT" of `ray start --head`, or "auto")
the command joins that cluster and only disconnects at the end. Every node needs this checkout (or
hydrabench installed) with its dependencies; on the machine that started the head the driver's
sys.path is passed on to the workers by Ray itself.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from pathlib import Path

from sim.errors import UserError


def write_shard_files(root: Path, name: str, files: dict[str, bytes]) -> None:
    """Write a shard's files under a temporary name in `root`, then rename it into place."""
    from sensors.dataset import commit_shard

    tmp = root / f"{name}.tmp-{os.getpid()}"
    for rel, data in files.items():
        p = tmp / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)
    commit_shard(tmp, root / name)


def run_shards(task: Callable[[dict, dict], tuple[dict, dict[str, bytes]]], config_dict: dict, specs: list[dict],
               root: Path, collect: Callable[[dict], None], workers: int = 1, address: str | None = None) -> dict:
    """Render `specs` as Ray tasks and write each shard into `root` as it completes (`collect` gets
    its record). `task(config_dict, spec_dict)` renders one shard and returns (its record, {path
    relative to the shard directory: bytes}) (`sensors.generate.shard_files`); it runs on whichever
    node Ray picks. Returns {"address", "cluster_cpus", "started_local"}."""
    if not address:
        # A local instance on loopback: this command's alone, not a service on the network. Ray
        # advertises the node's network address on Linux unless this (read when ray is imported) is 0.
        os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
    try:
        import ray
    except ImportError:
        raise UserError("--backend ray needs the ray package (pip install ray==2.60.0)") from None
    from sensors.dataset import shard_digest

    started = False
    owned = not ray.is_initialized()  # a caller's own Ray session is used as it is and left running
    if owned:
        common = dict(include_dashboard=False, log_to_driver=False, logging_level=logging.WARNING,
                      configure_logging=True)
        try:
            if address:
                ray.init(address=address, **common)
            else:
                ray.init(address="local", num_cpus=max(1, workers), **common)
                started = True
        except Exception as exc:  # noqa: BLE001 - Ray raises bare Exception when its processes start too slowly
            ray.shutdown()  # whatever part of a local instance did start
            where = f"the Ray cluster at {address}" if address else "a local Ray instance"
            hint = "" if address else " (on a busy machine start one with `ray start --head` and pass --address)"
            raise UserError(f"--backend ray: could not start or join {where}: {str(exc).splitlines()[0]}{hint}") from None
    try:
        remote = ray.remote(num_cpus=1, max_retries=2)(task)
        cfg_ref = ray.put(config_dict)
        pending = {remote.remote(cfg_ref, spec): spec for spec in specs}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                pending.pop(ref)
                record, files = ray.get(ref)
                t = time.perf_counter()
                write_shard_files(root, record["name"], files)
                record["timings"]["write"] = record["timings"].get("write", 0.0) + time.perf_counter() - t
                if shard_digest(root / record["name"]) != record["sha256"]:
                    raise RuntimeError(f"shard {record['name']}: written files differ from what the task rendered")
                collect(record)
        info = {"address": ray.get_runtime_context().gcs_address, "cluster_cpus": ray.cluster_resources().get("CPU"),
                "started_local": started}
    finally:
        if owned:
            ray.shutdown()  # stops the instance this command started; only disconnects from a cluster
    return info
