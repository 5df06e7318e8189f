"""`hydrabench bench generate`: every profile x worker count x start method x round is a run, in turn,
and the ratios are the quotients of the median rates measured. Run in a fresh process, as a user runs
it: this test process has rendered, and a pool must not fork from it."""

import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

import pytest

from study.bench.pipeline import bench_generate
from study.cli import main

ROOT = Path(__file__).resolve().parents[2]


def test_bench_generate_alternates_start_methods_and_reports_their_ratio():
    cmd = [sys.executable, "-m", "study.cli", "bench", "generate", "--profiles", "cpu", "--workers", "2",
           "--contexts", "city,fog", "--frames-per-context", "1", "--sequence-length", "1",
           "--start-methods", "spawn,fork", "--rounds", "2", "--twins", "--json"]
    env = {**os.environ, "HYDRABENCH_PROGRESS_S": "0"}
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=900, cwd=ROOT, env=env)
    assert run.returncode == 0, run.stderr[-2000:]
    r = json.loads(run.stdout)
    assert [(x["round"], x["start_method"]) for x in r["runs"]] == [(0, "spawn"), (0, "fork"), (1, "spawn"), (1, "fork")]
    assert all(x["frames"] == 2 and x["frames_per_second"] > 0 for x in r["runs"]) and r["contexts"] == ["city", "fog"]
    med = {m: statistics.median(x["frames_per_second"] for x in r["runs"] if x["start_method"] == m)
           for m in ("spawn", "fork")}
    assert r["ratios"]["cpu/2"] == {"spawn": 1.0, "fork": round(med["fork"] / med["spawn"], 3)}
    assert set(r["ms_per_component"]["cpu"]) >= {"simulation", "camera_raster", "camera_shading", "write"}
    assert r["twins"] is True
    assert "generate: 2/2 frame" in run.stderr  # progress lines in a log


@pytest.mark.parametrize("argv, needle", [
    (["--start-methods", "threads"], "unknown start method 'threads'"),
    (["--start-methods", "fork,fork"], "named twice"),
    (["--rounds", "0"], "--rounds: must be >= 1"),
])
def test_bench_generate_bad_input_is_one_line_exit_2(argv, needle, capsys):
    assert main(["bench", "generate", *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0]


def test_bench_generate_refuses_zero_rounds():
    with pytest.raises(ValueError, match="rounds"):
        bench_generate(profiles=("cpu",), workers=(1,), rounds=0)


def test_each_run_goes_to_a_fresh_child_of_a_process_that_has_not_rendered(monkeypatch):
    import os

    import sensors.generate as gen
    from study.bench.pipeline import _in_fresh_child

    monkeypatch.setattr(gen, "worker_start_method", lambda: "fork")
    child = _in_fresh_child(os.getpid)
    assert child != os.getpid()
    assert _in_fresh_child(lambda a, b=0: a + b, 2, b=3) == 5
    with pytest.raises(RuntimeError, match="ZeroDivisionError"):
        _in_fresh_child(lambda: 1 / 0)
    with pytest.raises(RuntimeError, match="died"):
        _in_fresh_child(os._exit, 3)
    # a process that has rendered (or cannot fork) runs the call itself
    monkeypatch.setattr(gen, "worker_start_method", lambda: "spawn")
    assert _in_fresh_child(os.getpid) == os.getpid()


def test_dataset_digest_sees_every_byte_and_name(tmp_path):
    from study.bench.pipeline import dataset_digest

    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "x.npy").write_bytes(b"\x00\x01")
    (tmp_path / "b.json").write_text("{}")
    first = dataset_digest(tmp_path)
    assert dataset_digest(tmp_path) == first
    (tmp_path / "a" / "x.npy").write_bytes(b"\x00\x02")
    assert dataset_digest(tmp_path) != first
    (tmp_path / "a" / "x.npy").write_bytes(b"\x00\x01")
    (tmp_path / "b.json").rename(tmp_path / "c.json")
    assert dataset_digest(tmp_path) != first
