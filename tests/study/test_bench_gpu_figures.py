"""bench inference's GPU figures on the CPU: the time per operator kind counts each piece once, the
NVML energy window is seconds long after a warm-up with the idle power beside it, and the NVML
device is found by UUID, not by index (a fake profiler table, a fake meter, a fake NVML)."""

from __future__ import annotations

import ctypes
from types import SimpleNamespace

import pytest
from torch.autograd import DeviceType

import fusion.nvml as nvml
import study.bench.nets as nets
from study.bench.nets import measure_energy, measure_idle, nvml_meter, op_times_ms, timed_forwards


def _row(key, device_type, self_device_us=0.0, self_cpu_us=0.0):
    return SimpleNamespace(key=key, device_type=device_type, self_device_time_total=self_device_us,
                           self_cpu_time_total=self_cpu_us)


TABLE = [  # what key_averages() gives for a conv + linear forward on a GPU (times in microseconds)
    _row("aten::conv2d", DeviceType.CPU, 0.0, 40.0),  # its child launched the kernel
    _row("aten::cudnn_convolution", DeviceType.CPU, 3000.0, 60.0),
    _row("sm90_xmma_fprop_implicit_gemm_bf16", DeviceType.CUDA, 3000.0),  # the same 3 ms, as the kernel
    _row("aten::addmm", DeviceType.CPU, 1000.0, 20.0),
    _row("sm90_xmma_gemm_bf16bf16", DeviceType.CUDA, 1000.0),
    _row("Memcpy HtoD (Pageable -> Device)", DeviceType.CUDA, 500.0),  # launched by no operator
    _row("cudaLaunchKernel", DeviceType.CPU, 0.0, 30.0),
]


def test_gpu_time_per_operator_kind_counts_each_kernel_once():
    ops = op_times_ms(TABLE, cuda=True)
    assert ops["conv"] == pytest.approx(3.0) and ops["linear"] == pytest.approx(1.0)
    assert ops["other"] == pytest.approx(0.5)  # the copy no operator claims
    kernels = sum(r.self_device_time_total for r in TABLE if r.device_type == DeviceType.CUDA) / 1000
    assert sum(ops.values()) == pytest.approx(kernels)  # 4.5 ms, not 9 (op rows + kernel rows)


def test_cpu_time_per_operator_kind_is_self_cpu_time():
    ops = op_times_ms(TABLE, cuda=False)
    assert ops["conv"] == pytest.approx(0.1) and ops["linear"] == pytest.approx(0.02)
    assert sum(ops.values()) == pytest.approx(sum(r.self_cpu_time_total for r in TABLE) / 1000)


class FakeGpu:
    """A clock, a board drawing `idle_w` when idle and `busy_w` during forwards of `call_s` each and
    for `tail_s` after the last one (clocks still up), and an energy counter [mJ] that moves only
    every `step_s` (NVML's 20-100 ms updates)."""

    def __init__(self, idle_w=100.0, busy_w=400.0, call_s=0.01, step_s=0.1, tail_s=0.0):
        self.t, self.e = 0.0, 0.0
        self.tail_s, self.last_busy = tail_s, -1e9
        self.idle_w, self.busy_w, self.call_s, self.step_s = idle_w, busy_w, call_s, step_s
        self.history = [(0.0, 0.0)]  # (time, true energy) after each change
        self.available = True
        self.calls = 0

    def _run(self, seconds, watts):
        self.t += seconds
        self.e += watts * seconds * 1000
        self.history.append((self.t, self.e))

    def once(self):
        self.calls += 1
        self._run(self.call_s, self.busy_w)
        self.last_busy = self.t

    def sleep(self, seconds):
        tail = max(0.0, min(seconds, self.last_busy + self.tail_s - self.t))
        if tail:
            self._run(tail, self.busy_w)
        self._run(seconds - tail, self.idle_w)

    def clock(self):
        return self.t

    def energy_mj(self):
        """The true energy at the last multiple of step_s (the counter's last update)."""
        tick = int(self.t / self.step_s + 1e-9) * self.step_s
        before = [(t, e) for t, e in self.history if t <= tick + 1e-12]
        (t0, e0), after = before[-1], [h for h in self.history if h[0] > tick + 1e-12]
        if not after:
            return int(e0)
        t1, e1 = after[0]
        return int(e0 + (e1 - e0) * (tick - t0) / (t1 - t0))


def test_energy_is_measured_over_seconds_after_a_warm_up_with_the_idle_power_beside_it():
    gpu = FakeGpu(idle_w=100.0, busy_w=400.0, call_s=0.01, step_s=0.1, tail_s=2.0)
    for _ in range(50):  # the board was just busy (the model's copy, the previous configuration)
        gpu.once()
    first_read = []
    energy_mj = gpu.energy_mj
    gpu.energy_mj = lambda: first_read.append(gpu.calls) or energy_mj()
    kw = {"warmup_s": 2.0, "window_s": 3.0, "idle_s": 1.0, "rest_s": 3.0}
    times, r = timed_forwards(gpu.once, 5, gpu, 1, kw, clock=gpu.clock, sleep=gpu.sleep)
    assert first_read[0] == 50  # the idle window came before any forward of its own
    assert len(times) == 5 and all(s == pytest.approx(0.01) for s in times)
    assert r["energy_window_s"] >= 3.0 and r["energy_calls"] == pytest.approx(300, abs=1)
    assert r["energy_warmup_calls"] == pytest.approx(200, abs=1)
    assert r["idle_power_w"] == pytest.approx(100.0, rel=0.05) and r["idle_rest_s"] == 3.0
    # 400 W x 10 ms = 4 J per frame; the counter's 100 ms steps cost at most a few per cent over 3 s
    assert r["energy_mj_per_frame"] == pytest.approx(4000.0, rel=0.04)
    assert r["power_w"] == pytest.approx(400.0, rel=0.04)
    assert r["energy_above_idle_mj_per_frame"] == pytest.approx(3000.0, rel=0.06)  # (400 - 100) W x 10 ms


def test_idle_read_in_the_second_after_the_forwards_is_the_load_s_tail():
    """Why the rest: right after forwards the board still draws its load power."""
    gpu = FakeGpu(idle_w=100.0, busy_w=400.0, call_s=0.01, step_s=0.1, tail_s=2.0)
    for _ in range(50):
        gpu.once()
    assert measure_idle(gpu, rest_s=0.0, idle_s=1.0, clock=gpu.clock, sleep=gpu.sleep)["idle_power_w"] > 350
    assert measure_idle(gpu, rest_s=3.0, idle_s=1.0, clock=gpu.clock, sleep=gpu.sleep)["idle_power_w"] == \
        pytest.approx(100.0, rel=0.05)


def test_without_a_meter_the_forwards_are_timed_and_nothing_sleeps():
    gpu = FakeGpu()
    times, r = timed_forwards(gpu.once, 4, None, clock=gpu.clock, sleep=lambda s: pytest.fail("slept"))
    assert len(times) == 4 and r == {} and gpu.calls == 5  # a warm-up call, then the timed ones


def test_five_forwards_are_too_short_for_the_counter():
    """The old window (5 forwards of ~10 ms) sees no counter step or one holding energy from outside
    the window: zero, or far from the 4 J per frame, depending on where the counter's period falls."""
    readings = []
    for phase in (0.0, 0.095):  # the counter last moved just now / 95 ms ago
        gpu = FakeGpu(call_s=0.01, step_s=0.1)
        gpu.sleep(0.1 + phase)
        e0 = gpu.energy_mj()
        for _ in range(5):
            gpu.once()
        readings.append((gpu.energy_mj() - e0) / 5)
    assert readings[0] == 0
    assert abs(readings[1] - 4000) > 0.25 * 4000


def test_batch_size_divides_the_energy_and_no_meter_reads_nothing():
    gpu = FakeGpu(call_s=0.08, step_s=0.02)
    r = measure_energy(gpu, gpu.once, 8, warmup_s=0.5, window_s=3.0, clock=gpu.clock)
    assert "energy_above_idle_mj_per_frame" not in r  # no idle power handed in
    assert r["energy_mj_per_frame"] == pytest.approx(400 * 0.08 * 1000 / 8, rel=0.02)
    assert measure_energy(None, gpu.once, 1) == {}
    assert measure_energy(SimpleNamespace(available=False), gpu.once, 1) == {}
    assert measure_idle(None) == {} and measure_idle(SimpleNamespace(available=False)) == {}


class FakeNvml:
    """libnvidia-ml's calls as fusion.nvml makes them through ctypes, for GPUs listed in NVML's order."""

    def __init__(self, uuids, energies):
        self.uuids, self.energies = uuids, energies

    def nvmlDeviceGetCount_v2(self, count):
        count._obj.value = len(self.uuids)
        return 0

    def nvmlDeviceGetHandleByIndex_v2(self, index, handle):
        if index.value >= len(self.uuids):
            return 2  # NVML_ERROR_INVALID_ARGUMENT
        handle._obj.value = index.value + 1  # handles are opaque non-null pointers
        return 0

    def nvmlDeviceGetUUID(self, handle, buf, size):
        buf.value = self.uuids[handle.value - 1].encode()
        return 0

    def nvmlDeviceGetTotalEnergyConsumption(self, handle, value):
        value._obj.value = self.energies[handle.value - 1]
        return 0

    def nvmlDeviceGetPowerUsage(self, handle, value):
        value._obj.value = 1000 * (handle.value - 1) + 70_000
        return 0


A = "4a5b6c7d-0000-1111-2222-333344445555"
B = "99999999-8888-7777-6666-555544443333"


def test_uuids_compare_across_torch_and_nvml_spellings():
    assert nvml.same_gpu(A, "GPU-" + A) and nvml.same_gpu(A.upper(), "gpu-" + A)
    assert nvml.same_gpu(A.replace("-", ""), "GPU-" + A)
    assert not nvml.same_gpu(A, "GPU-" + B) and not nvml.same_gpu("", "GPU-")


def test_the_meter_is_the_nvml_device_with_the_cuda_devices_uuid():
    lib = FakeNvml(["GPU-" + B, "GPU-" + A], [111, 222])  # NVML lists cuda:0's GPU second
    meter = nvml.GpuEnergyMeter.for_uuid(A, lib=lib)
    assert meter.available and meter.energy_mj() == 222 and meter.power_w() == pytest.approx(71.0)
    assert nvml.GpuEnergyMeter(0, lib=lib).energy_mj() == 111  # what indexing by CUDA's number read
    missing = nvml.GpuEnergyMeter.for_uuid("00000000-0000-0000-0000-000000000000", lib=lib)
    assert not missing.available and missing.energy_mj() is None and missing.power_w() is None


def test_bench_takes_the_uuid_of_the_cuda_device_it_runs_on(monkeypatch):
    import torch

    lib = FakeNvml(["GPU-" + B, "GPU-" + A], [111, 222])
    monkeypatch.setattr(nvml, "_lib", lambda: lib)
    props = {0: SimpleNamespace(uuid=A), 1: SimpleNamespace(uuid=B)}
    monkeypatch.setattr(torch.cuda, "get_device_properties", lambda i: props[i])
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 1)
    assert nvml_meter("cuda:0").energy_mj() == 222
    assert nvml_meter("cuda:1").energy_mj() == 111
    assert nvml_meter("cuda").energy_mj() == 111  # no index: the current device


def test_without_nvml_every_reading_is_none(monkeypatch):
    monkeypatch.setattr(nvml, "_lib", lambda: None)
    meter = nvml.GpuEnergyMeter.for_uuid(A)
    assert not meter.available and meter.energy_mj() is None
    assert isinstance(ctypes.c_uint(), ctypes.c_uint)  # ctypes only: no pynvml needed


def test_ecofusion_energy_counter_reads_the_nvml_device_of_its_cuda_device(monkeypatch):
    """eco-energy's NVML counter (fusion.eco.energy.NvmlCounter) goes through the same UUID match."""
    import torch

    from fusion.eco.energy import NvmlCounter

    lib = FakeNvml(["GPU-" + B, "GPU-" + A], [111_000, 222_000])
    monkeypatch.setattr(nvml, "_lib", lambda: lib)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    props = {0: SimpleNamespace(uuid=A), 1: SimpleNamespace(uuid=B)}
    monkeypatch.setattr(torch.cuda, "get_device_properties", lambda i: props[i])
    counter = NvmlCounter("cuda:0")
    assert counter.read() == 222_000 and counter.joules(111_000, 222_000) == pytest.approx(111.0)
    assert NvmlCounter("cuda:1").read() == 111_000
    with pytest.raises(OSError, match="no energy counter"):
        NvmlCounter(meter=nvml.GpuEnergyMeter(None, lib=lib))


class FakePool:
    """mp's spawn Pool, run in this process: canned figures per task, in the order asked."""

    def __init__(self, *a, **k):
        self.asked = []

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def apply(self, fn, args):
        (args,) = args
        self.asked.append(fn.__name__)
        if fn.__name__ == "_worker":
            batch = args[3]
            return {"latency_ms": 10.0 * batch, "peak_rss_mb": 900.0, "params_m": 1.0, "peak_gpu_mb": 500.0,
                    "energy_mj_per_frame": 2000.0, "energy_above_idle_mj_per_frame": 1500.0, "idle_power_w": 90.0,
                    "power_w": 300.0, **{f"ops_ms_per_frame/{k}": 1.0 for k in nets.OP_KINDS}}
        if fn.__name__ == "_train_worker":
            return {"images_per_second": 3.0, "step_s": 1.0}
        return {"gate_overhead_ms": {"deep": 0.1}, "topk_latency_ms": {}}


def test_bench_inference_hands_over_its_figures_after_every_task(monkeypatch):
    monkeypatch.setattr(nets.mp, "get_context", lambda method: SimpleNamespace(Pool=FakePool))
    seen = []
    r = nets.bench_inference("cpu", device="cuda:0", batches=(1, 8), configurations=["single_camera", "all_branches"],
                             train_branches=["radar"], on_result=seen.append)
    assert [s["tasks"]["done"] for s in seen] == [1, 2, 3, 4, 5, 6] and seen[-1]["tasks"]["of"] == 6
    first = seen[0]  # single_camera at batch 1 only: every figure it can have, nothing it cannot
    assert first["latency_ms"] == {"single_camera": 10.0} and first["energy_j_per_frame"] == {"single_camera": 2.0}
    assert first["latency_ms_per_frame_batch_8"] == {} and first["ratio_top3_to_all"] is None
    assert seen[1]["latency_ms_per_frame_batch_8"] == {"single_camera": 10.0}
    assert seen[3]["latency_ms"] == {"single_camera": 10.0, "all_branches": 10.0}
    assert seen[4]["training_images_per_second"] == {"radar": 3.0} and "gate_overhead_ms" not in seen[4]
    assert r == seen[-1] and r["gate_overhead_ms"] == {"deep": 0.1}
    assert "after 3.0 s of rest, before any timed forward" in r["energy_source"]


def test_bench_inference_partial_keeps_what_was_measured_when_stopped(monkeypatch, tmp_path):
    """`hydrabench bench inference --partial FILE`: the file holds the figures after each task, so a
    run stopped part-way (here: interrupted after two tasks) keeps them; a finished run marks it whole."""
    import json

    from study.cli import main

    def stopped(*args, on_result=None, **kw):
        on_result({"latency_ms": {"radar": 11.0}, "tasks": {"done": 1, "of": 9}})
        on_result({"latency_ms": {"radar": 11.0, "lidar": 12.5}, "tasks": {"done": 2, "of": 9}})
        raise KeyboardInterrupt

    monkeypatch.setattr(nets, "bench_inference", stopped)
    out = tmp_path / "partial.json"
    assert main(["bench", "inference", "--partial", str(out)]) != 0
    kept = json.loads(out.read_text())
    assert kept["latency_ms"] == {"radar": 11.0, "lidar": 12.5} and kept["tasks"]["done"] == 2
    assert kept["complete"] is False and kept["cores"] >= 1
