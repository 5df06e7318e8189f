"""Devices and data-parallel training.

DDP (torchrun, 2 gloo processes on loopback) trains the same weights as one process with the same
global batch: each process takes half of every batch, DDP averages the gradients, and per-frame
seeded anchor / RoI sampling (fusion.nets.sampling) makes each frame's loss terms the same in one
process or two. A run killed with SIGKILL mid-training and started again finishes with the same
weights. No process outlives the test.
"""

import json
import os
import signal
import socket
import subprocess
import sys
import time

import pytest
import torch

from sensors.generate import GenerateConfig
from study.cli import main
from study.engine.train import TrainConfig, train
from tests.conftest import NARROW_ARGS, NARROW_MODEL

ARGS = dict(branches=("radar",), epochs=2, batch_size=2, warmup_steps=2, lr=2e-3, eval_frames=1, checkpoint_steps=1,
            model=NARROW_MODEL)


@pytest.fixture(scope="module")
def data(shared_dataset):  # the dataset of tests/study/test_train.py: generated once per session
    return shared_dataset(GenerateConfig(contexts=("junction", "fog"), frames_per_context=4, sequence_length=2, seed=9))


@pytest.fixture(scope="module")
def single(data, tmp_path_factory):
    """One process, global batch 2, per-frame sampling: the reference."""
    out = tmp_path_factory.mktemp("single")
    before = torch.get_num_threads()
    try:
        train(TrainConfig(data=str(data), sampling="per-frame", threads=1, device="cpu", **ARGS), out, progress=False)
    finally:
        torch.set_num_threads(before)
    return out


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _torchrun(data, out, extra=()):
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nnodes", "1", "--nproc-per-node", "2",
           "--master-addr", "127.0.0.1", "--master-port", str(_free_port()),
           "-m", "study.cli", "train", str(data), "--out", str(out), "--branches", "radar", "--epochs", "2",
           "--batch-size", "2", "--warmup-steps", "2", "--lr", "2e-3", "--eval-frames", "1", "--checkpoint-steps", "1",
           "--threads", "1", "--device", "cpu", *NARROW_ARGS, *extra]
    env = {**os.environ, "GLOO_SOCKET_IFNAME": "lo", "OMP_NUM_THREADS": "1"}
    return cmd, env


def _stat(pid: int):
    """(state, parent pid) of a process, or None when it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
        return fields[0], int(fields[1])
    except (OSError, IndexError, ValueError):
        return None


def _descendants(root: int) -> list[int]:
    """root and every process below it (torchrun starts its workers in sessions of their own)."""
    parent = {}
    for pid in os.listdir("/proc"):
        if pid.isdigit() and (st := _stat(int(pid))) is not None:
            parent[int(pid)] = st[1]
    out, frontier = [root], [root]
    while frontier:
        frontier = [p for p, pp in parent.items() if pp in frontier]
        out += frontier
    return out


def _alive(pids) -> list[int]:
    return [p for p in pids if (st := _stat(p)) is not None and st[0] != "Z"]


def _weights(run):
    return torch.load(run / "checkpoint.pt", map_location="cpu", weights_only=False)["model"]


def test_two_gloo_processes_killed_with_sigkill_resume_and_train_the_weights_of_one_process(data, single, tmp_path):
    ref = _weights(single)
    out = tmp_path / "ddp"
    # 2 processes x 1 frame = the global batch of 2; SIGKILL to torchrun and both workers after the
    # first mid-epoch checkpoint, then the same command again
    cmd, env = _torchrun(data, out)
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env, start_new_session=True)
    deadline = time.time() + 240
    while time.time() < deadline and not (out / "checkpoint.pt").exists() and proc.poll() is None:
        time.sleep(0.05)
    job = _descendants(proc.pid)  # torchrun and its two workers
    for pid in job:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    proc.wait()
    deadline = time.time() + 20
    while _alive(job) and time.time() < deadline:
        time.sleep(0.1)
    assert len(job) >= 3 and not _alive(job), "processes of the killed run are still running"
    state = torch.load(out / "checkpoint.pt", weights_only=False)
    assert (state["epoch"], state["step_in_epoch"]) < (2, 0), "the kill came after the run had finished"
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["sampling"] == "per-frame" and cfg["batch_size"] == 2  # auto under torchrun; the global batch

    done = subprocess.run(cmd + ["--json"], capture_output=True, text=True, env=env, timeout=600, start_new_session=True)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "resuming" in done.stderr and "data-parallel: 2 processes (gloo)" in done.stderr
    lines = done.stdout.strip().splitlines()
    assert len(lines) == 1 and json.loads(lines[0])["processes"] == 2  # one JSON object, from rank 0
    ddp = _weights(out)
    assert ddp.keys() == ref.keys()
    first = torch.load(single / "epoch-001.pt", weights_only=False)["model"]
    assert sum(not torch.equal(ref[k], first[k]) for k in ref) > 10, "training changed the weights"
    for k in ref:
        if not ref[k].is_floating_point():
            assert torch.equal(ddp[k], ref[k]), k
            continue
        # equal in exact arithmetic; in floating point the sums run in another order, and a proposal that
        # crosses the RPN's top-k or NMS threshold changes a loss term, so the two paths part by a few %
        # of an epoch's update (5 % at most, 1.5e-5 per weight, on an AMD EPYC with AVX-512; less on an
        # AVX2 one). A wrong share of the batch or gradient weighting parts them by 50 % or more.
        step = float((ref[k].double() - first[k].double()).norm())
        gap = float((ddp[k].double() - ref[k].double()).norm())
        assert gap <= 0.2 * step + 1e-7, (k, gap, step)


def test_per_frame_sampling_changes_nothing_but_the_draws_and_global_stays_the_default(data, single, tmp_path):
    """A one-process run with the default sampling is the run the code made before devices existed
    (torchvision's sampler untouched); per-frame sampling is recorded and kept on resume."""
    from fusion.nets.sampling import FrameSeededSampler
    from study.engine.scoring import load_run

    assert json.loads((single / "config.json").read_text())["sampling"] == "per-frame"
    assert TrainConfig(data="x").sampling == "global"
    model, _ = load_run(single)
    assert not isinstance(model.branches["radar"].rpn.fg_bg_sampler, FrameSeededSampler)  # inference: untouched


def test_device_options_refuse_what_this_machine_cannot_do(data, single, tmp_path, capsys):
    from study.engine.device import resolve_device

    setup = resolve_device(device="cpu", threads=1, apply=False)
    assert (setup.device, setup.threads, setup.amp) == ("cpu", 1, False)
    assert resolve_device(device="auto", apply=False).device == ("cuda:0" if torch.cuda.is_available() else "cpu")
    if not torch.cuda.is_available():
        code = main(["train", str(data), "--out", str(tmp_path / "gpu"), "--branches", "radar", "--device", "cuda"])
        err = capsys.readouterr().err
        assert code == 2 and "no CUDA GPU" in err and len(err.strip().splitlines()) == 1
        assert not (tmp_path / "gpu" / "checkpoint.pt").exists()
    code = main(["train", str(data), "--out", str(tmp_path / "amp"), "--branches", "radar", "--device", "cpu",
                 "--amp", "fp16"])
    err = capsys.readouterr().err
    assert code == 2 and "--amp" in err and len(err.strip().splitlines()) == 1
    assert main(["train", str(data), "--out", str(tmp_path / "x"), "--device", "tpu"]) == 2
    assert "--device: expected auto, cpu, cuda or cuda:N" in capsys.readouterr().err
    with pytest.MonkeyPatch.context() as m:  # a rank of torchrun (its variables faked) asking for cuda:N
        for k, v in {"WORLD_SIZE": "2", "RANK": "0", "LOCAL_RANK": "0", "LOCAL_WORLD_SIZE": "2"}.items():
            m.setenv(k, v)
        code = main(["train", str(data), "--out", str(tmp_path / "one-gpu"), "--device", "cuda:1"])
    err = capsys.readouterr().err
    assert code == 2 and "under torchrun" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "one-gpu").exists()
    assert main(["train", str(data), "--out", str(tmp_path / "x"), "--device", "tpu"]) == 2
    assert "--device: expected auto, cpu, cuda or cuda:N" in capsys.readouterr().err
    if not torch.cuda.is_available():  # every network command shares the same options and refusal
        for argv in (["evaluate", str(single), str(data)], ["train-gate", str(single), str(data), "--gate", "deep"],
                     ["bench", "inference"]):
            assert main([*argv, "--device", "cuda:0"]) == 2, argv
            assert "no CUDA GPU" in capsys.readouterr().err


def test_gpu_check_plans_a_smaller_cpu_run_and_says_so():
    from study.bench.gpu_check import plan

    gpu, cpu = plan(True, None, None), plan(False, None, None)
    assert gpu["profile"] == "paper" and gpu["contexts"] == "all" and gpu["batches"] == [1, 8]
    assert cpu["profile"] == "cpu" and cpu["steps"] < gpu["steps"] and len(cpu["configurations"]) == 3
    assert os.access(os.path.join(os.path.dirname(__file__), "..", "..", "scripts", "gpu_check.sh"), os.X_OK)


def test_dataloader_workers_decode_the_same_batches_as_the_main_process(data):
    import numpy as np

    from fusion.data import FrameDataset
    from study.engine.train import _batch_stream

    ds = FrameDataset(data, list(range(8)), bev_size=(128, 256))
    order = np.random.default_rng(0).permutation(8)
    batches = [order[k:k + 3] for k in range(0, 8, 3)]
    flips = np.random.default_rng(1).random(8) < 0.5
    main_process = list(_batch_stream(ds, batches, flips, 1, 0, False))  # from step 1, as a resumed epoch
    workers = list(_batch_stream(ds, batches, flips, 1, 2, False))
    assert [k for k, _ in main_process] == [k for k, _ in workers] == [1, 2]
    for (_, (ia, ta, ma)), (_, (ib, tb, mb)) in zip(main_process, workers):
        assert [m["dataset_index"] for m in ma] == [m["dataset_index"] for m in mb]
        assert [m["flipped"] for m in ma] == [m["flipped"] for m in mb]
        for s in ia:
            assert torch.equal(ia[s], ib[s])
        for x, y in zip(ta, tb):
            for f in x:
                assert torch.equal(x[f]["boxes"], y[f]["boxes"]) and torch.equal(x[f]["labels"], y[f]["labels"])
