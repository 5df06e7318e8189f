"""Network benchmarks (`hydrabench bench inference`): latency, peak memory and training speed per
model configuration, the analogue of HydraFusion Table 4 on this CPU.

Each configuration is measured in a fresh process (spawned), so its peak resident memory
(ru_maxrss) belongs to it alone; latency is the median of `repeats` timed forwards after warm-up.
On a CUDA device (`device`, `study.engine.device`) the forwards run there (bf16 autocast with `amp`), each
timing waits for the GPU (torch.cuda.synchronize), the peak is the GPU memory torch allocated
(max_memory_allocated) and the energy at batch 1 is measured with NVML's counter (`fusion.nvml`, the
GPU found by its UUID) over at least `energy_window_s` of repeated forwards after `energy_warmup_s`
of warm-up forwards (the counter moves in 20-100 ms steps and an idle H200 clocks at 345 MHz), with
the idle power measured beside it (`measure_energy`): measured, not modelled, and labelled so. The
time per operator kind counts each piece of time once: on the CPU each operator's self time, on a
GPU the kernel time the profiler attributes to each operator (`op_times_ms`).
A configuration is a set of branches run in one forward, plus the late-fusion block when it has
several branches (HydraFusion's Algorithm 1: stems -> selected branches -> fusion block).
`bench_gates` adds each gate's overhead and the end-to-end latency of top-k HydraFusion with the
gate wired in (stems -> gate -> k branches -> fusion block).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import resource
import statistics
import time

import numpy as np

CONFIGURATIONS = {
    # name: (branch set, branch names, description)
    "single_camera": ("paper", ["camera_right"], "no fusion: one camera branch"),
    "single_radar": ("paper", ["radar"], "no fusion: the radar branch"),
    "early_fusion_cameras": ("early_fusion", ["early_cameras"], "one network on the stacked L/R camera images"),
    "early_fusion_cameras_lidar": ("early_fusion", ["early_camera_lidar"], "one network on L/R cameras + forward lidar"),
    "late_fusion": ("paper", ["camera_left", "camera_right", "lidar", "radar"], "four single-sensor branches + fusion"),
    "hydra_top3_typical": ("paper", ["camera_right", "radar", "radar_lidar"], "stems + three selected branches + fusion"),
    "hydra_top3_worst": ("paper", ["camera_both", "camera_lidar", "radar_lidar"], "stems + three early-fusion branches + fusion"),
    "all_branches": ("paper", None, "stems + all seven branches + fusion"),
}


OP_KINDS = ("conv", "norm", "roi_align", "nms", "linear", "other")


def op_kind(name: str) -> str:
    """The kind of a torch operator, for the time breakdown (convolutions, normalisation, RoIAlign,
    NMS, fully connected layers, everything else)."""
    n = name.lower()
    if "conv" in n:
        return "conv"
    if "norm" in n:
        return "norm"
    if "roi_align" in n:
        return "roi_align"
    if "nms" in n:
        return "nms"
    if n.split("::")[-1] in ("addmm", "linear", "mm", "matmul"):
        return "linear"
    return "other"


def op_times_ms(events, cuda: bool) -> dict:
    """Milliseconds per operator kind (OP_KINDS) of a profiler table (`prof.key_averages()`), each
    piece of time counted once.

    On the CPU: each operator row's self CPU time. On a GPU the table holds operator rows (aten::*,
    torchvision::*, whose self device time is the kernel time the profiler attributes to them) and
    kernel rows (the kernels themselves, device type CUDA, the same time again): the operator rows
    are summed by kind, and kernel time no operator claims (copies, kernels launched outside any
    operator) goes to "other", so the kinds add up to the kernels' total."""
    from torch.autograd import DeviceType

    ops = dict.fromkeys(OP_KINDS, 0.0)
    kernels = 0.0
    for e in events:
        if not cuda:
            ops[op_kind(e.key)] += e.self_cpu_time_total / 1000.0
        elif e.device_type == DeviceType.CUDA:
            kernels += e.self_device_time_total / 1000.0
        else:
            ops[op_kind(e.key)] += e.self_device_time_total / 1000.0
    if cuda:
        ops["other"] += max(0.0, kernels - sum(ops.values()))
    return ops


ENERGY_WARMUP_S = 2.0
"""Seconds of forwards before the energy window, so the GPU's clocks have risen (an idle H200 runs
its SMs at 345 MHz, 1980 MHz under load)."""
ENERGY_WINDOW_S = 3.0
"""The shortest energy window [s]: NVML's counter moves in 20-100 ms steps, so 3 s bounds that
error to a few per cent."""
IDLE_WINDOW_S = 1.0
"""Seconds of idle GPU over which the idle power is measured (same counter)."""
IDLE_REST_S = 3.0
"""Seconds of rest before the idle window, which comes before any timed forward: a board just
loaded (the model's copy, the previous configuration's forwards) keeps its clocks and power up for a
moment, and an idle figure read then is the load's tail, not idle."""


def nvml_meter(device: str):
    """The NVML energy meter of the CUDA device `device` ("cuda:N"), matched by UUID (NVML's device
    index is not CUDA's in general)."""
    import torch

    from fusion.nvml import GpuEnergyMeter

    index = torch.device(device).index
    index = torch.cuda.current_device() if index is None else index
    return GpuEnergyMeter.for_uuid(str(torch.cuda.get_device_properties(index).uuid))


def measure_idle(meter, rest_s: float = IDLE_REST_S, idle_s: float = IDLE_WINDOW_S, clock=time.perf_counter,
                 sleep=time.sleep) -> dict:
    """The board's idle power from `meter`'s counter: `rest_s` of nothing, then the counter read at
    both ends of `idle_s` more. {} where the meter reads nothing."""
    if meter is None or not meter.available:
        return {}
    sleep(rest_s)
    e0, t0 = meter.energy_mj(), clock()
    sleep(idle_s)
    e1, t1 = meter.energy_mj(), clock()
    if e0 is None or e1 is None or t1 <= t0:
        return {}
    return {"idle_power_w": (e1 - e0) / (t1 - t0) / 1000.0, "idle_window_s": t1 - t0, "idle_rest_s": rest_s}


def measure_energy(meter, once, frames_per_call: int, idle_w: float | None = None, warmup_s: float = ENERGY_WARMUP_S,
                   window_s: float = ENERGY_WINDOW_S, clock=time.perf_counter) -> dict:
    """Energy per frame of `once()` (one finished forward of `frames_per_call` frames; it must wait
    for the device) from `meter`'s counter (`fusion.nvml.GpuEnergyMeter`): `warmup_s` of forwards,
    then forwards until at least `window_s` has passed, the counter read at the window's two ends.
    `idle_w`: the idle power measured before (`measure_idle`). {} where the meter reads nothing.

    energy_mj_per_frame = (E1 - E0) / (calls * frames)                 # the board, idle included
    energy_above_idle_mj_per_frame = (E1 - E0 - P_idle * (t1 - t0)) / (calls * frames)
    """
    if meter is None or not meter.available:
        return {}
    end = clock() + warmup_s
    warmup_calls = 0
    while clock() < end or warmup_calls == 0:
        once()
        warmup_calls += 1
    calls = 0
    e0, t0 = meter.energy_mj(), clock()
    while calls == 0 or clock() - t0 < window_s:
        once()
        calls += 1
    e1, t1 = meter.energy_mj(), clock()
    if e0 is None or e1 is None:
        return {}
    frames = calls * frames_per_call
    out = {"energy_mj_per_frame": (e1 - e0) / frames, "power_w": (e1 - e0) / (t1 - t0) / 1000.0,
           "energy_window_s": t1 - t0, "energy_calls": calls, "energy_warmup_calls": warmup_calls}
    if idle_w is not None:
        out.update({"energy_above_idle_mj_per_frame": (e1 - e0 - 1000.0 * idle_w * (t1 - t0)) / frames,
                    "idle_power_w": idle_w})
    return out


def timed_forwards(once, repeats: int, meter=None, frames_per_call: int = 1, energy_kw: dict | None = None,
                   after_warmup=None, clock=time.perf_counter, sleep=time.sleep) -> tuple[list, dict]:
    """(seconds of each of `repeats` timed calls of `once`, energy figures). With a `meter`: the idle
    power first, after a rest (`measure_idle`), before any forward of this process; then one warm-up
    call, `after_warmup()`, the timed calls, and the energy window (`measure_energy`)."""
    kw = {"warmup_s": ENERGY_WARMUP_S, "window_s": ENERGY_WINDOW_S, "idle_s": IDLE_WINDOW_S, "rest_s": IDLE_REST_S,
          **(energy_kw or {})}
    idle = measure_idle(meter, kw["rest_s"], kw["idle_s"], clock=clock, sleep=sleep) if meter is not None else {}
    once()  # warm-up (allocator, first-call overheads)
    if after_warmup is not None:
        after_warmup()
    times = []
    for _ in range(repeats):
        t = clock()
        once()
        times.append(clock() - t)
    energy = {}
    if meter is not None:
        energy = measure_energy(meter, once, frames_per_call, idle.get("idle_power_w"), kw["warmup_s"], kw["window_s"],
                                clock=clock)
        energy.update({k: v for k, v in idle.items() if k != "idle_power_w"} if energy else {})
    return times, energy


def synthetic_batch(model, batch: int, seed: int = 0, device: str = "cpu"):
    """(inputs, targets) of random images of the model's input sizes and four random boxes per
    frame in each detection frame (camera_left, camera_right, bev): a training batch without data."""
    import torch

    inputs = _inputs(model, batch, seed=seed, device=device)
    rng = np.random.default_rng(seed)
    targets = []
    for _ in range(batch):
        t = {}
        for frame, size in (("camera_left", model.transform.sizes["camera"]),
                            ("camera_right", model.transform.sizes["camera"]), ("bev", model.transform.sizes["bev"])):
            h, w = size
            xy = rng.uniform(0, [w - 40, h - 30], (4, 2))
            wh = rng.uniform([8, 8], [40, 30], (4, 2))
            t[frame] = {"boxes": torch.tensor(np.hstack([xy, xy + wh]), dtype=torch.float32, device=device),
                        "labels": torch.tensor(rng.integers(1, 9, 4), device=device)}
        targets.append(t)
    return inputs, targets


def _inputs(model, batch: int, seed: int = 0, device: str = "cpu"):
    import torch

    from fusion.nets import SENSORS

    g = torch.Generator().manual_seed(seed)
    out = {}
    for s in model.sensors:
        h, w = model.transform.image_size(s)
        out[s] = torch.rand(batch, SENSORS[s].channels, h, w, generator=g).to(device)
    return out


def _dets(per: dict):
    from fusion.late import Detections

    return {n: Detections(d["boxes"].float().cpu().numpy().astype(float), d["scores"].float().cpu().numpy().astype(float),
                          d["labels"].cpu().numpy()) for n, d in per.items()}


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        import torch

        torch.cuda.synchronize(device)


def _meta(calib_dict, batch):
    return [{"calibration": calib_dict} for _ in range(batch)]


def _load_run_weights(model, run_dir) -> None:
    """Copy a trained run's weights into `model` where the module names match (nothing without a run)."""
    if not run_dir:
        return
    from study.engine.scoring import load_run

    trained, _ = load_run(run_dir)
    own = model.state_dict()
    model.load_state_dict({k: v for k, v in trained.state_dict().items() if k in own}, strict=False)


def _worker(args) -> dict:
    """Fresh process: build the configuration, time `repeats` forwards at `batch`, report peak RSS
    (on a GPU: peak GPU memory, and at batch 1 the idle power and the energy per frame,
    `timed_forwards`). `args`: (profile, set_name, names, batch, repeats, threads, run_dir, device, amp[, energy keywords])."""
    profile, set_name, names, batch, repeats, threads, run_dir, device, amp = args[:9]
    energy_kw = args[9] if len(args) > 9 else {}
    import torch

    from fusion.late import fuse
    from fusion.nets import build_hydrafusion
    from sensors.rig import load_profile as sensor_profile
    from sensors.rig import make_calibration
    from study.engine.device import resolve_device
    from study.engine.train import branch_set

    setup = resolve_device(device=device, threads=threads, amp=amp)
    cuda = setup.is_cuda
    specs = branch_set(set_name, profile)
    if names is not None:
        specs = [s for s in specs if s.name in names]
    torch.manual_seed(0)
    model = build_hydrafusion(profile=profile, branches=specs).eval()
    _load_run_weights(model, run_dir)
    model.to(device)
    calib = make_calibration(sensor_profile(profile))
    inputs = _inputs(model, batch, device=device)
    frames = model.branch_frames
    selection = [s.name for s in specs]
    base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss

    def once():
        with torch.no_grad(), setup.autocast():
            dets = model(inputs, selection=selection)
        if len(selection) > 1:
            for per in dets:
                fuse(_dets(per), frames, calib, "soft_nms")
        _sync(device)

    meter = nvml_meter(device) if cuda and batch == 1 else None  # energy at batch 1 only
    times, gpu = timed_forwards(once, repeats, meter, batch, energy_kw,
                                after_warmup=(lambda: torch.cuda.reset_peak_memory_stats(device)) if cuda else None)
    if cuda:  # the peak of the warm-up-free forwards and the energy window
        gpu["peak_gpu_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    params = sum(p.numel() for p in model.parameters())
    # where the time goes: self CPU time per operator kind of one more forward (profiled, so each
    # operator carries the profiler's overhead too: compare kinds and batch sizes, not to latency_ms)
    from torch.profiler import ProfilerActivity, profile

    # (on a GPU: the device time of each kind's kernels)
    os.environ.setdefault("KINETO_LOG_LEVEL", "6")  # the profiler library's start/stop chatter on stderr
    with profile(activities=[ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])) as prof:
        once()
    ops = op_times_ms(prof.key_averages(), cuda)
    return {"latency_ms": 1000 * statistics.median(times), "latency_ms_min": 1000 * min(times),
            "peak_rss_mb": peak / 1024, "forward_rss_mb": (peak - base_rss) / 1024, "params_m": params / 1e6,
            **gpu, **{f"ops_ms_per_frame/{k}": v / batch for k, v in ops.items()}}


def _train_worker(args) -> dict:
    profile, name, batch, steps, threads, device, amp = args
    import torch

    from fusion.nets import build_hydrafusion
    from study.engine.device import resolve_device
    from study.engine.train import branch_set

    setup = resolve_device(device=device, threads=threads, amp=amp)
    spec = [s for s in branch_set("paper", profile) if s.name == name]
    torch.manual_seed(0)
    model = build_hydrafusion(profile=profile, branches=spec).train().to(device)
    inputs, targets = synthetic_batch(model, batch, device=device)
    opt = torch.optim.SGD(model.parameters(), lr=1e-3, momentum=0.9)
    times = []
    for k in range(steps + 1):
        t0 = time.perf_counter()
        with setup.autocast():
            loss = model(inputs, targets)["total"]
        opt.zero_grad()
        loss.backward()
        opt.step()
        _sync(device)
        if k:
            times.append(time.perf_counter() - t0)
    return {"images_per_second": batch / statistics.median(times), "step_s": statistics.median(times)}


GATE_CONTEXT = {"layout": "motorway", "conditions": ["fog"], "severity": 4}
"""The frame context handed to the knowledge gate when timing it (any context costs the same)."""


def bench_gates(profile: str = "cpu", repeats: int = 5, threads: int = 2, run_dir: str | None = None,
                ks=(1, 3, 5), overrides: dict | None = None, device: str = "cpu", amp: bool = False) -> dict:
    """Gate overhead and top-k latency on the seven-branch network, batch 1.

    `gate_overhead_ms[gate]`: the gate alone, from stem features to its selection (median of
    `repeats`). The optimal gate has none: it needs every branch's loss against ground truth.
    `topk_latency_ms[gate][k]`: HydraFusion end to end with the gate wired in (every stem, since
    the gate reads all modalities; the gate; the k branches it selects; late fusion, Soft-NMS).
    `stems_ms`: every stem once. Trained weights and trained gates come from `run_dir` when given
    (gates only if trained for its latest checkpoint); otherwise random initialisation, whose
    untrained learned gates predict a constant and so pick the first k branches.
    """
    import torch

    from fusion.late import fuse
    from fusion.nets import build_hydrafusion
    from fusion.nets.branch_gates import GATES, build_gate
    from sensors.rig import load_profile as sensor_profile
    from sensors.rig import make_calibration
    from study.engine.device import resolve_device
    from study.engine.train import branch_set

    setup = resolve_device(device=device, threads=threads, amp=amp)
    torch.manual_seed(0)
    model = build_hydrafusion(profile=profile, branches=branch_set("paper", profile), **(overrides or {})).eval()
    gates_from = "random initialisation"
    _load_run_weights(model, run_dir)
    model.to(device)
    calib = make_calibration(sensor_profile(profile))
    inputs = _inputs(model, 1, device=device)
    meta = [dict(GATE_CONTEXT)]
    frames = model.branch_frames

    def median_ms(fn):
        fn()  # warm-up
        _sync(device)
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            fn()
            _sync(device)
            times.append(time.perf_counter() - t)
        return round(1000 * statistics.median(times), 3)

    with torch.no_grad(), setup.autocast():
        features = model.extract_features(inputs)
        stems_ms = median_ms(lambda: model.extract_features(inputs))
    overhead, topk, chosen, source = {}, {}, {}, {}
    for name in GATES.names():
        cls = GATES.get(name)
        if cls.reads == "losses":
            overhead[name] = None  # needs ground truth: not a deployable gate
            continue
        gate = build_gate(name, model).to(device)
        source[name] = "table" if not cls.trainable else gates_from
        if cls.trainable and run_dir:
            from pathlib import Path

            from study.engine.gate_training import load_trained_gate

            if (Path(run_dir) / "gates" / name / "gate.pt").exists():
                gate = load_trained_gate(run_dir, name, model).to(device)
                source[name] = f"trained ({run_dir}/gates/{name})"
        with torch.no_grad(), setup.autocast():
            overhead[name] = median_ms(lambda g=gate: g(features, meta))
        model.gate = gate
        topk[name], chosen[name] = {}, {}
        for k in ks:
            gate.k = k

            def once():
                with torch.no_grad(), setup.autocast():
                    dets = model(inputs, meta=meta)
                for per in dets:
                    fuse(_dets(per), frames, calib, "soft_nms")

            topk[name][str(k)] = median_ms(once)
            with torch.no_grad(), setup.autocast():
                chosen[name][str(k)] = list(gate(features, meta)[0])
        model.gate = None
    share = {g: round(overhead[g] / topk[g]["3"], 6) for g in topk if "3" in topk[g] and overhead[g] is not None}
    return {"gate_overhead_ms": overhead, "topk_latency_ms": topk, "topk_branches": chosen, "stems_ms": stems_ms,
            "gate_overhead_share_of_top3": share, "gate_weights": source, "gate_context": GATE_CONTEXT}


def _gate_worker(args) -> dict:
    """Fresh process: `bench_gates`."""
    profile, repeats, threads, run_dir, device, amp = args
    return bench_gates(profile, repeats, threads, run_dir, device=device, amp=amp)


def bench_inference(profile: str = "cpu", repeats: int = 5, threads: int = 2, run_dir: str | None = None,
                    train_steps: int = 3, batches=(1, 8), device: str = "cpu", amp: bool = False,
                    configurations=None, train_branches=None, energy_warmup_s: float = ENERGY_WARMUP_S,
                    energy_window_s: float = ENERGY_WINDOW_S, idle_s: float = IDLE_WINDOW_S,
                    idle_rest_s: float = IDLE_REST_S, on_result=None) -> dict:
    """HydraFusion Table 4 on this machine (see the module doc). `configurations` / `train_branches`:
    subsets of CONFIGURATIONS and of the paper branches to measure (default: all). `energy_*`,
    `idle_*`: the energy measurement's windows on a GPU (`timed_forwards`). `on_result(figures)`:
    called after each spawned task with the figures so far (`summarise_inference`), so a run stopped
    part-way (a time budget) keeps what it measured."""
    energy_kw = {"warmup_s": energy_warmup_s, "window_s": energy_window_s, "idle_s": idle_s, "rest_s": idle_rest_s}
    if run_dir:  # its weights loaded here first: a damaged run is refused before any worker starts
        from study.engine.scoring import load_run

        load_run(run_dir)
    from study.engine.train import branch_set

    configs = [(n, c) for n, c in CONFIGURATIONS.items() if configurations is None or n in configurations]
    branches = [s.name for s in branch_set("paper", profile) if train_branches is None or s.name in train_branches]
    results: dict = {}
    training: dict = {}
    gates: dict = {}
    tasks = {"done": 0, "of": len(configs) * len(batches) + len(branches) + 1}

    def summary() -> dict:
        return summarise_inference(results, training, gates, profile=profile, device=device, amp=amp, run_dir=run_dir,
                                   energy_kw=energy_kw, tasks=tasks)

    def task_done() -> None:
        tasks["done"] += 1
        if on_result is not None:
            on_result(summary())

    ctx = mp.get_context("spawn")
    with ctx.Pool(1, maxtasksperchild=1) as pool:
        for name, (set_name, names, _desc) in configs:
            results[name] = {}
            for b in batches:
                r = pool.apply(_worker, ((profile, set_name, names, b, repeats, threads, run_dir, device, amp,
                                          energy_kw),))
                results[name][f"batch_{b}"] = {k: round(v, 2) if isinstance(v, float) else v for k, v in r.items()}
                task_done()
        for name in branches:
            r = pool.apply(_train_worker, ((profile, name, 4, train_steps, threads, device, amp),))
            training[name] = {k: round(v, 3) for k, v in r.items()}
            task_done()
        gates.update(pool.apply(_gate_worker, ((profile, repeats, threads, run_dir, device, amp),)))
        task_done()
    return summary()


def summarise_inference(results: dict, training: dict, gates: dict, *, profile: str, device: str, amp: bool,
                        run_dir: str | None, energy_kw: dict, tasks: dict | None = None) -> dict:
    """`bench inference`'s figures from what its tasks measured so far: `results[configuration]
    ["batch_N"]` (`_worker`), `training[branch]` (`_train_worker`), `gates` (`bench_gates`). A
    configuration or batch not measured yet is left out of every figure that needs it."""
    one = {n: r["batch_1"] for n, r in results.items() if "batch_1" in r}
    eight = {n: r["batch_8"] for n, r in results.items() if "batch_8" in r}
    both = {n: (one[n], eight[n]) for n in one if n in eight}
    lat = {n: r["latency_ms"] for n, r in one.items()}
    gpu = {}
    if device.startswith("cuda"):
        def joules(key):
            return {n: (None if r.get(key) is None else round(r[key] / 1000, 4)) for n, r in one.items()}

        gpu = {"peak_gpu_mb": {n: r["peak_gpu_mb"] for n, r in one.items()},
               "energy_j_per_frame": joules("energy_mj_per_frame"),
               "energy_above_idle_j_per_frame": joules("energy_above_idle_mj_per_frame"),
               "idle_power_w": {n: r.get("idle_power_w") for n, r in one.items()},
               "power_w": {n: r.get("power_w") for n, r in one.items()}}
        measured = any(r.get("energy_mj_per_frame") is not None for r in one.values())
        gpu["energy_source"] = (f"measured: NVML board energy counter (device matched by UUID) over >= "
                                f"{energy_kw['window_s']} s of repeated batch-1 forwards after {energy_kw['warmup_s']} s "
                                f"of warm-up; idle power over {energy_kw['idle_s']} s after {energy_kw['rest_s']} s of "
                                "rest, before any timed forward" if measured else
                                "none: NVML counter unavailable" if one else "none yet: no batch-1 configuration measured")

    def ratio(a, b):
        return round(lat[a] / lat[b], 3) if {a, b} <= set(lat) else None

    def ops(r, k):
        return r[f"ops_ms_per_frame/{k}"]

    return {
        **gpu,
        "latency_ms": lat,
        "latency_ms_per_frame_batch_8": {n: round(r["latency_ms"] / 8, 2) for n, r in eight.items()},
        "peak_rss_mb": {n: r["peak_rss_mb"] for n, r in one.items()},
        "params_m": {n: r["params_m"] for n, r in one.items()},
        "ratio_top3_to_all": ratio("hydra_top3_typical", "all_branches"),
        "ratio_top3_worst_to_all": ratio("hydra_top3_worst", "all_branches"),
        "batch8_throughput_gain": {n: round(a["latency_ms"] / (b["latency_ms"] / 8), 2) for n, (a, b) in both.items()},
        "training_images_per_second": {n: v["images_per_second"] for n, v in training.items()},
        # per operator kind, batch 8 against batch 1 (profiled self CPU time per frame): which parts
        # batching speeds up and which it cannot
        "batch8_gain_per_op_kind": {n: {k: round(ops(a, k) / ops(b, k), 2) for k in OP_KINDS if ops(b, k) > 0}
                                    for n, (a, b) in both.items()},
        "op_share_batch_1": {n: {k: round(ops(r, k) / max(sum(ops(r, j) for j in OP_KINDS), 1e-9), 3) for k in OP_KINDS}
                             for n, r in one.items()},
        "configurations": {n: d for n, (_, _, d) in CONFIGURATIONS.items() if n in results},
        "device": device,
        "amp": "bf16" if amp else False,
        "details": results,
        "profile": profile,
        "weights": run_dir or "random initialisation",
        **({"tasks": dict(tasks)} if tasks is not None else {}),
        **gates,
    }


__all__ = ["bench_gates", "bench_inference", "summarise_inference", "CONFIGURATIONS"]
