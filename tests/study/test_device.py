"""`study.engine.device` and the device-facing parts of training, checked on the CPU: the precision choice
(--amp auto reads the CPU's bf16 flags), TF32 off, torchrun's refusal of cuda:N and its per-rank
thread share, the CUDA RNG state in checkpoints (faked generators), loss sums without host syncs."""

import pytest
import torch

import study.engine.device as device
from sim.errors import UserError

INTEL_AMX = "processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f avx512_bf16 amx_bf16 amx_tile\n"
AMD_ZEN4 = "processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f avx512bw avx512_bf16\n"
OLD_XEON = "processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f avx512bw avx512vl\n"


def test_native_bf16_is_read_from_the_cpu_flags():
    assert device.cpu_bf16_flags(INTEL_AMX) == ["amx_bf16", "avx512_bf16"]
    assert device.cpu_bf16_flags(AMD_ZEN4) == ["avx512_bf16"]
    assert device.native_bf16("cpu", INTEL_AMX)[0] and device.native_bf16("cpu", AMD_ZEN4)[0]
    ok, why = device.native_bf16("cpu", OLD_XEON)  # AVX512 without bf16: oneDNN would emulate it
    assert not ok and "neither AMX-BF16 nor AVX512-BF16" in why


def test_amp_auto_picks_bf16_only_where_native_and_defaults_keep_the_cpu_fp32(monkeypatch):
    assert device.resolve_amp(None, "cpu", "train") is False  # CPU results unchanged by default
    assert device.resolve_amp(None, "cuda:0", "train") is True  # bf16 training on a GPU by default
    assert device.resolve_amp(None, "cuda:0", "eval") is False  # evaluation fp32 unless asked
    assert device.resolve_amp("bf16", "cpu") is True and device.resolve_amp("off", "cuda:0") is False
    real = device.cpu_bf16_flags
    for cpuinfo, want in ((AMD_ZEN4, True), (OLD_XEON, False)):
        monkeypatch.setattr(device, "cpu_bf16_flags", lambda text=None, c=cpuinfo, f=real: f(c))
        assert device.resolve_amp("auto", "cpu") is want
    with pytest.raises(UserError, match="--amp"):
        device.resolve_amp("fp16", "cpu")
    setup = device.resolve_device(device="cpu", threads=1, amp="bf16", apply=False)
    assert (setup.precision, setup.describe()["precision"], setup.describe()["device_type"]) == ("bf16", "bf16", "cpu")
    assert device.compute_identity(setup) == {"device": "cpu", "precision": "bf16"}
    with setup.autocast():  # CPU autocast, not CUDA's
        assert torch.is_autocast_enabled("cpu") and torch.get_autocast_dtype("cpu") == torch.bfloat16


def test_the_device_options_take_amp_values_and_leave_workers_to_the_device():
    import argparse

    from study.commands.device import add_device_args

    p = argparse.ArgumentParser()
    add_device_args(p)
    assert p.parse_args(["--amp"]).amp == "bf16" and p.parse_args(["--amp", "auto"]).amp == "auto"
    assert p.parse_args(["--no-amp"]).amp == "off" and p.parse_args([]).amp is None
    assert p.parse_args([]).workers is None  # 0 on the CPU, DEFAULT_CUDA_WORKERS on a GPU
    assert device.resolve_device(device="cpu", threads=1, apply=False).workers == 0


def test_setup_turns_tf32_off():
    before = torch.get_num_threads()
    torch.backends.cuda.matmul.allow_tf32 = True
    torch.backends.cudnn.allow_tf32 = True
    try:
        device.resolve_device(device="cpu", threads=1)
        assert torch.backends.cuda.matmul.allow_tf32 is False
        assert torch.backends.cudnn.allow_tf32 is False
    finally:
        torch.set_num_threads(before)


def test_torchrun_with_cuda_n_is_refused(monkeypatch, tmp_path):
    for k, v in {"WORLD_SIZE": "2", "RANK": "1", "LOCAL_RANK": "1", "LOCAL_WORLD_SIZE": "2"}.items():
        monkeypatch.setenv(k, v)
    with pytest.raises(UserError, match="puts all 2 processes on one GPU"):
        device.rank_device("cuda:1", 2, 1)
    assert device.rank_device("cpu", 2, 1) == "cpu"
    assert device.rank_device("cuda:1", 1, 0) == "cuda:1"  # outside torchrun: as asked
    if not torch.cuda.is_available():
        assert device.rank_device("auto", 2, 1) == "cpu"
    from study.engine.train import TrainConfig, train

    with pytest.raises(UserError, match="under torchrun"):  # before the dataset is read or --out made
        train(TrainConfig(data=str(tmp_path / "no-data"), device="cuda:1"), tmp_path / "run", progress=False)
    assert not (tmp_path / "run").exists()  # (the command: tests/study/test_distributed.py)


def test_under_torchrun_each_rank_takes_its_share_of_the_cores(monkeypatch):
    monkeypatch.setattr(device, "available_cores", lambda: 16)
    assert device.default_threads({}) == 16
    assert device.default_threads({"WORLD_SIZE": "4", "LOCAL_WORLD_SIZE": "4"}) == 4
    assert device.default_threads({"WORLD_SIZE": "8", "LOCAL_WORLD_SIZE": "2"}) == 8  # 2 per machine
    monkeypatch.setattr(device, "available_cores", lambda: 2)
    assert device.default_threads({"LOCAL_WORLD_SIZE": "3"}) == 1  # at least one
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "2")
    monkeypatch.setenv("WORLD_SIZE", "2")
    assert device.resolve_device(device="cpu", apply=False).threads == 1


def test_checkpoints_carry_the_cuda_generators_when_training_on_cuda(monkeypatch):
    import study.engine.train as st

    assert st.rng_state(cuda=False)["cuda_rng"] is None  # CPU-only: nothing CUDA is touched
    gens = [torch.arange(4, dtype=torch.uint8), torch.arange(4, 8, dtype=torch.uint8)]
    restored = {}
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_rng_state_all", lambda: gens)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    monkeypatch.setattr(torch.cuda, "set_rng_state", lambda s, i: restored.__setitem__(i, s))
    state = st.rng_state(cuda=True)
    assert torch.equal(state["torch_rng"], torch.get_rng_state()) and state["cuda_rng"] is gens
    st.restore_rng(state)
    assert list(restored) == [0] and torch.equal(restored[0], gens[0])  # a machine with fewer GPUs: what fits
    restored.clear()
    st.restore_rng({"torch_rng": torch.get_rng_state()})  # a checkpoint from before: the CPU state alone
    assert restored == {}


def test_loss_sums_stay_on_the_device_and_equal_float_sums():
    import study.engine.train as st

    g = torch.Generator().manual_seed(0)
    sums, ref = {}, {}
    for _ in range(50):
        branches = {b: {k: torch.rand((), generator=g) * 3 for k in ("a", "b", "c", "d")} for b in ("radar", "lidar")}
        total = sum(sum(ld.values()) for ld in branches.values())
        st.add_losses(sums, {"branches": branches, "total": total}, 1.0, 1)
        for b, ld in branches.items():  # what the loop did before: a Python float per step
            ref[b] = ref.get(b, 0.0) + float(sum(v.detach() for v in ld.values()))
        ref["total"] = ref.get("total", 0.0) + float(total)
    assert all(isinstance(v, torch.Tensor) and v.dtype == torch.float64 for v in sums.values())
    assert st.sums_as_floats(sums) == ref and list(sums) == list(ref)


def test_a_checkpoint_saved_twice_has_the_same_bytes(tmp_path):
    """The study keys on checkpoint bytes: saving through a random temporary name must not leak the name."""
    import study.engine.train as st

    obj = {"model": {"w": torch.arange(6.0)}, "epoch": 1}
    st.torch_save_atomic(obj, tmp_path / "a.pt")
    st.torch_save_atomic(obj, tmp_path / "b" / "checkpoint.pt")
    assert (tmp_path / "a.pt").read_bytes() == (tmp_path / "b" / "checkpoint.pt").read_bytes()
    assert torch.equal(torch.load(tmp_path / "a.pt")["model"]["w"], obj["model"]["w"])
