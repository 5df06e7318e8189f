"""`hydrabench bench scale`: the ratios are the quotients of the rates measured, the DDP run trains the
one-process weights (so both did the same work), and no process the bench starts outlives it, whether
a job ends, fails, orphans a worker or is interrupted. End to end with the Ray part left out (its
own test, tests/sensors/test_ray_backend.py, starts and stops a local Ray)."""

import json
import os
import signal
import sys
import tempfile
import time
from pathlib import Path

import pytest

from sim.errors import UserError
from study.bench.scale import alive, ratios, run_job, stop_tree
from study.cli import main
from tests.conftest import NARROW_ARGS


def _processes_mentioning(text: str) -> list[int]:
    found = []
    for pid in os.listdir("/proc"):
        if pid.isdigit() and int(pid) != os.getpid():
            try:
                with open(f"/proc/{pid}/cmdline", "rb") as fh:
                    if text.encode() in fh.read() and alive(int(pid)):
                        found.append(int(pid))
            except OSError:
                pass
    return found


def test_ratios_are_the_quotients_of_the_measured_rates_and_none_where_nothing_was_measured():
    run = lambda ips, step: {"images_per_second": ips, "step_seconds": step}  # noqa: E731
    result = {"parts": {
        "train": {"threads_1": run(0.5, 8.0), "threads_2": run(0.8, 5.0)},
        "ddp": {"one_process": run(0.8, 5.0), "processes_2": run(1.0, 4.0)},
        "generate": {"local": {"frames_per_second": 2.0}, "ray": {"frames_per_second": 1.5}},
    }}
    r = ratios(result)
    assert r == {"threads_2_over_1": 1.6, "ddp_speedup": 1.25, "ddp_over_1_thread": 2.0, "ray_over_local": 0.75}
    result["parts"]["generate"]["ray"] = {"backend": "ray", "skipped": "could not start a local Ray instance"}
    del result["parts"]["train"]
    r = ratios(result)
    assert r["ray_over_local"] is None and r["threads_2_over_1"] is None and r["ddp_over_1_thread"] is None
    assert r["ddp_speedup"] == 1.25  # step time 5.0 / 4.0 with the same global batch


# a job that starts a worker in a session of its own (as torchrun does), then sleeps (or exits soon,
# leaving the worker behind); the worker ignores SIGTERM and says it is up by writing a marker file
WORKER = "import signal, sys, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); open(sys.argv[1], 'w').write('up'); time.sleep(120)"
JOB = ("import subprocess, sys, time; subprocess.Popen([sys.executable, '-c', sys.argv[1], sys.argv[2]], "
       "start_new_session=True); time.sleep(float(sys.argv[3]))")


def _job(tmp_path, parent_sleeps: float):
    marker = tmp_path / f"up-{parent_sleeps}"
    return [sys.executable, "-c", JOB, WORKER, str(marker), str(parent_sleeps)], marker


def _wait_for(path: Path, timeout=120.0):
    deadline = time.time() + timeout
    while not path.exists() and time.time() < deadline:
        time.sleep(0.05)
    assert path.exists(), "the test job's worker did not start"


def test_stop_tree_ends_the_job_and_its_worker_in_another_session_even_when_it_ignores_sigterm(tmp_path):
    import subprocess

    argv, marker = _job(tmp_path, 120)
    proc = subprocess.Popen(argv, stderr=subprocess.DEVNULL, start_new_session=True)
    _wait_for(marker)
    t0 = time.time()
    stop_tree(proc, grace=1.0)
    assert proc.returncode is not None and time.time() - t0 < 30
    assert _processes_mentioning(str(marker)) == []


def test_a_job_that_leaves_a_worker_behind_or_fails_leaves_no_process_and_names_its_error(tmp_path):
    argv, marker = _job(tmp_path, 5)  # the parent exits normally after 5 s; its worker would sleep on
    seconds, _ = run_job(argv, dict(os.environ), "leaver", tmp_path / "out1", progress=False)
    assert seconds >= 5 and marker.exists()
    assert _processes_mentioning(str(marker)) == []
    fail = [sys.executable, "-c", "import sys; print('hydrabench: error: the data is bad', file=sys.stderr); "
            "print('====', file=sys.stderr); sys.exit(2)"]
    with pytest.raises(UserError, match=r"failer exited with code 2: hydrabench: error: the data is bad"):
        run_job(fail, dict(os.environ), "failer", tmp_path / "out2", progress=False)


def test_an_interrupted_job_leaves_no_process(tmp_path):
    argv, marker = _job(tmp_path, 120)

    def interrupt(signum, frame):
        if marker.exists():
            raise KeyboardInterrupt
        signal.setitimer(signal.ITIMER_REAL, 0.2)  # not yet started: ask again shortly

    old = signal.signal(signal.SIGALRM, interrupt)
    signal.setitimer(signal.ITIMER_REAL, 0.5)
    try:
        with pytest.raises(KeyboardInterrupt):
            run_job(argv, dict(os.environ), "interrupted", tmp_path / "out", progress=False)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    assert marker.exists() and _processes_mentioning(str(marker)) == []


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from sensors.generate import GenerateConfig, generate

    out = tmp_path_factory.mktemp("scale_data")
    generate(GenerateConfig(contexts=("junction",), frames_per_context=2, sequence_length=2, seed=4), out,
             workers=1, progress=False)
    return out


def test_train_and_ddp_parts_end_to_end(tiny, tmp_path, capsys, monkeypatch):
    """One frame per process and one SGD step per run: 1 and 2 threads, 2 gloo processes. The DDP run
    ends with the weights of one process (HydraFusion's per-frame losses averaged over the global
    batch either way), the ratios are the quotients of the runs' rates, and nothing is left."""
    work = tmp_path / "tmp"
    work.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(work))
    png = tmp_path / "ratios.png"
    code = main(["bench", "scale", "--parts", "train,ddp", "--data", str(tiny), "--batch-size", "2",
                 "--plot", str(png), "--json", *NARROW_ARGS])  # the quarter-width test network: same mechanics
    out, err = capsys.readouterr()
    assert code == 0, err[-3000:]
    r = json.loads(out)  # one JSON object on stdout
    assert set(r["parts"]) == {"train", "ddp"} and set(r["ratios"]) == {
        "threads_2_over_1", "ddp_speedup", "ddp_over_1_thread", "ray_over_local"}
    t1, t2 = r["parts"]["train"]["threads_1"], r["parts"]["train"]["threads_2"]
    ddp = r["parts"]["ddp"]
    assert ddp["one_process"] == t2 and ddp["backend"] == "gloo"
    for run, threads, procs in ((t1, 1, 1), (t2, 2, 1), (ddp["processes_2"], 1, 2)):
        assert (run["threads_per_process"], run["processes"]) == (threads, procs)
        assert run["train_frames"] == 2 and run["steps"] == 1  # one sequence: every frame trains
        assert run["images_per_second"] == pytest.approx(2 / run["train_seconds"], rel=1e-3)
        assert 0 < run["train_seconds"] < run["wall_seconds"]
    assert ddp["max_weight_difference"] < 1e-4
    assert r["ratios"]["threads_2_over_1"] == pytest.approx(t2["images_per_second"] / t1["images_per_second"], rel=1e-2)
    assert r["ratios"]["ddp_speedup"] == pytest.approx(t2["step_seconds"] / ddp["processes_2"]["step_seconds"], rel=1e-2)
    assert r["ratios"]["ray_over_local"] is None
    m = r["machine"]
    assert m["cores"] >= 1 and len(m["load_average_before"]) == 3 and len(m["load_average_after"]) == 3
    assert "bench scale: ddp 2 processes x 1 thread" in err  # progress on stderr
    assert png.stat().st_size > 5000 and png.read_bytes()[:4] == b"\x89PNG"
    assert [n for n in os.listdir(work) if n.startswith("hydrabench-")] == []  # the runs' temporary directory is gone
    assert _processes_mentioning(str(work)) == []


def test_bad_options_are_refused_before_any_work(tiny, tmp_path, capsys, monkeypatch):
    work = tmp_path / "tmp"
    work.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(work))
    for argv, needle in ((["--parts", "train,gpu"], "gpu"), (["--branches", "sonar"], "sonar"), (["--model", "width=0.3"], "width"),
                         (["--contexts", "moon"], "moon"), (["--batch-size", "1"], "batch-size")):
        assert main(["bench", "scale", "--data", str(tiny), *argv]) == 2
        err = capsys.readouterr().err
        assert needle in err and len(err.strip().splitlines()) == 1, (argv, err)
    assert [n for n in os.listdir(work) if n.startswith("hydrabench-")] == []
