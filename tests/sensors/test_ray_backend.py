"""generate --backend ray: one Ray task per shard, the same bytes as the local pool; the local Ray
instance the command starts (on loopback) is gone when it returns."""

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import ray  # noqa: F401  (locked in requirements.lock: a broken install fails, it is not skipped)

from sensors.dataset import ARRAYS
from sensors.generate import GenerateConfig, generate
from study.cli import main

CONFIG = GenerateConfig(contexts=("fog",), frames_per_context=2, sequence_length=1, seed=5, twins=True)
ARGS = ["--contexts", "fog", "--frames-per-context", "2", "--sequence-length", "1", "--seed", "5", "--twins"]


def _digests(root: Path) -> dict:
    return {s["name"]: s["sha256"] for s in json.loads((root / "manifest.json").read_text())["shards"]}


def _processes_mentioning(text: str) -> list[int]:
    found = []
    for pid in os.listdir("/proc"):
        if pid.isdigit() and int(pid) != os.getpid():
            try:
                with open(f"/proc/{pid}/cmdline", "rb") as fh:
                    if text.encode() in fh.read():
                        found.append(int(pid))
            except OSError:
                pass
    return found


def test_ray_backend_writes_the_local_pools_bytes_and_leaves_no_process(tmp_path):
    local = tmp_path / "local"
    generate(CONFIG, local, workers=2, progress=False)
    ray_tmp = Path("/tmp") / f"hb-ray-{os.getpid()}"  # Ray's socket paths must stay short
    ray_tmp.mkdir()
    out = tmp_path / "ray"
    env = {**os.environ, "RAY_TMPDIR": str(ray_tmp)}
    done = subprocess.run([sys.executable, "-m", "study.cli", "generate", "--out", str(out), *ARGS,
                           "--backend", "ray", "--workers", "2", "--json"],
                          capture_output=True, text=True, env=env, timeout=600)
    try:
        assert done.returncode == 0, done.stderr[-3000:]
        lines = done.stdout.strip().splitlines()
        assert len(lines) == 1, done.stdout  # nothing from Ray on stdout
        r = json.loads(lines[0])
        assert r["backend"] == "ray" and r["ray"]["started_local"] and r["ray"]["cluster_cpus"] == 2
        assert r["ray"]["address"].startswith("127.0.0.1:") and r["frames_rendered"] == 2
        assert _digests(out) == _digests(local)
        for shard in _digests(local):
            for sub in ("", "clear/"):
                for name in ARRAYS + ("lidar_points",):
                    a = np.load(local / shard / f"{sub}{name}.npy")
                    b = np.load(out / shard / f"{sub}{name}.npy")
                    assert a.dtype == b.dtype and np.array_equal(a, b), (shard, sub, name)
        assert not list(out.glob("*.tmp-*"))
        deadline = time.time() + 30
        while _processes_mentioning(str(ray_tmp)) and time.time() < deadline:
            time.sleep(0.2)
        assert not _processes_mentioning(str(ray_tmp)), "the local Ray instance outlived the command"
    finally:
        for pid in _processes_mentioning(str(ray_tmp)):  # only this test's instance, by its temp dir
            try:
                os.kill(pid, 9)
            except ProcessLookupError:
                pass


def test_address_needs_the_ray_backend(tmp_path, capsys):
    assert main(["generate", "--out", str(tmp_path / "x"), "--address", "127.0.0.1:6379"]) == 2
    assert "--backend ray" in capsys.readouterr().err
    assert main(["generate", "--out", str(tmp_path / "y"), "--backend", "dask"]) == 2
