"""The one-GPU check (`scripts/gpu_check.sh`, docs/gpu.md): does hydrabench train and run fast on a GPU?

In this order, each step timed and the summary handed to `on_update` after each (so a stopped run
still leaves what it measured):
  0. probe, in child processes: how many CUDA GPUs torch sees and whether the offscreen renderer
     (pyrender on EGL) starts. This process creates no CUDA context before step 1 forks its render
     workers (a fork after CUDA is initialised can hang);
  1. generate a small dataset (every context, --frames-per-context frames, local pool); where the
     renderer cannot start, no dataset: step 2 trains on synthetic tensors and the summary says so;
  2. the device is resolved (CUDA initialised) only now. Train the seven-branch network: the timed
     optimizer steps alone (`train_steps`: a warm-up step, then --steps steps, each waited for; the
     host-to-device copy is in a step, frame decoding, model build, evaluation and checkpoints are
     not), then one epoch of `hydrabench train` end to end (`train_run`, its wall time with build,
     evaluation and checkpoint writes, reported as such);
  3. `bench inference` on the device: latency at batch 1 (and 8), peak GPU memory and NVML energy
     per configuration (HydraFusion Table 4's analogue), gate overheads, per-branch training speed.
Full size (`paper` profile) on a GPU, smaller on the CPU (`cpu` profile, two contexts, fewer steps,
three configurations); the summary's "skipped" names what was left out. Progress goes to stderr.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

PARTS = ("generate", "train", "bench")


class TimeBudgetExceeded(Exception):
    """The check's time budget (`scripts/gpu_check.sh --budget-s`) ran out."""


def _log(msg: str) -> None:
    sys.stderr.write(f"[gpu_check {time.strftime('%H:%M:%S')}] {msg}\n")
    sys.stderr.flush()


def plan(gpu: bool, frames_per_context: int | None = None, steps: int | None = None,
         contexts: str | None = None) -> dict:
    """What the check runs: full size on a GPU (sized for about 5 minutes on one H200, an estimate:
    docs/gpu.md), smaller on the CPU."""
    if gpu:
        return {"profile": "paper", "contexts": contexts or "all", "frames_per_context": frames_per_context or 2,
                "steps": steps or 20, "batch_size": 4, "branch_steps": 5, "repeats": 5, "batches": [1, 8],
                "configurations": ["single_camera", "hydra_top3_typical", "all_branches"],
                "train_branches": ["camera_right", "radar"]}
    return {"profile": "cpu", "contexts": contexts or "junction,fog", "frames_per_context": frames_per_context or 4,
            "steps": steps or 2, "batch_size": 2, "branch_steps": 2, "repeats": 2, "batches": [1],
            "configurations": ["single_camera", "hydra_top3_typical", "all_branches"],
            "train_branches": ["camera_right", "radar"]}


def _child(code: str, timeout: float) -> tuple[bool, str]:
    """Run `code` in a fresh interpreter (this one's path and environment): (succeeded, last line of
    stdout if it did, else the last line of stderr)."""
    try:
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout,
                           env={**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)})
    except subprocess.TimeoutExpired:
        return False, f"no answer in {timeout:.0f} s"
    lines = [ln.strip() for ln in ((r.stdout if r.returncode == 0 else r.stderr) or "").splitlines() if ln.strip()]
    return r.returncode == 0, (lines[-1] if lines else f"exit code {r.returncode}")


def cuda_device_count(timeout: float = 180.0) -> int:
    """The CUDA GPUs torch sees, asked in a child process: this one stays free of CUDA until it has
    forked its render workers."""
    ok, line = _child("import torch; print(torch.cuda.device_count() if torch.cuda.is_available() else 0)", timeout)
    return int(line) if ok and line.isdigit() else 0


def renderer_probe(timeout: float = 180.0) -> dict:
    """Whether the offscreen renderer starts here (in a child process, so no EGL context stays in
    this one): {"ok": True, "renderer", "version"} or {"ok": False, "error": one line}."""
    ok, line = _child("import json; from sensors.camera import gl_info; print(json.dumps(gl_info()))", timeout)
    if ok:
        try:
            return {"ok": True, **json.loads(line)}
        except ValueError:
            pass
    return {"ok": False, "error": line}


def _model(profile: str):
    import torch

    from fusion.nets import build_hydrafusion
    from study.engine.train import branch_set

    torch.manual_seed(0)
    return build_hydrafusion(profile=profile, branches=branch_set("paper", profile))


def dataset_batches(data: Path, model, batch_size: int, count: int) -> list:
    """`count` batches of training frames decoded on the CPU (frames reused when there are fewer)."""
    from fusion.data import FrameDataset, collate, split_by_sequence
    from sensors.dataset import DatasetReader

    train_idx = split_by_sequence(DatasetReader(data), 0.7, 0)[0]
    ds = FrameDataset(data, train_idx, sensors=model.sensors_for(None), bev_size=model.transform.image_size("radar"))
    order = [k % len(ds) for k in range(count * batch_size)]
    frames = {k: ds[k] for k in sorted(set(order))}  # each frame decoded once
    return [collate([frames[k] for k in order[i:i + batch_size]])[:2] for i in range(0, len(order), batch_size)]


def synthetic_batches(model, batch_size: int, count: int) -> list:
    """`count` batches of random images and boxes of the model's input sizes (no renderer needed)."""
    from study.bench.nets import synthetic_batch

    return [synthetic_batch(model, batch_size, seed=k) for k in range(count)]


def time_train_steps(model, batches: list, setup, lr: float = 1e-3) -> dict:
    """Optimizer steps alone: batches[0] is a warm-up step (allocator, cuDNN's algorithm search),
    then one timed step per further batch, each waited for (the host-to-device copy included)."""
    import torch

    from study.engine.device import to_device

    model.train().to(setup.torch_device())
    params = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.SGD(params, lr=lr, momentum=0.9, weight_decay=1e-4)

    def step(inputs, targets) -> float:
        t0 = time.perf_counter()
        inputs, targets = to_device(inputs, targets, setup.device)
        with setup.autocast():
            total = model(inputs, targets)["total"]
        opt.zero_grad(set_to_none=True)
        total.backward()
        opt.step()
        if setup.is_cuda:
            torch.cuda.synchronize(setup.device)
        return time.perf_counter() - t0

    first = step(*batches[0])
    times = [step(*b) for b in batches[1:]]
    images = sum(len(t) for _, t in batches[1:])
    loss = None
    with torch.no_grad(), setup.autocast():
        inputs, targets = to_device(*batches[-1], setup.device)
        loss = float(model(inputs, targets)["total"])
    return {"steps": len(times), "batch_size": len(batches[0][1]), "seconds": round(sum(times), 3),
            "images_per_second": round(images / sum(times), 3) if times else None,
            "step_s_median": round(statistics.median(times), 4) if times else None,
            "warmup_step_s": round(first, 3), "loss_after": round(loss, 4)}


def run_check(work: Path, frames_per_context: int | None = None, steps: int | None = None, force_cpu: bool = False,
              parts=PARTS, contexts: str | None = None, on_update=None) -> dict:
    """The check (see the module doc); returns the summary, and hands it to `on_update` after each step."""
    unknown = set(parts) - set(PARTS)
    if unknown:
        from sim.errors import UserError

        raise UserError(f"--parts: unknown {', '.join(sorted(unknown))} (choose from {', '.join(PARTS)})")
    t_all = time.perf_counter()
    summary: dict = {"parts": [p for p in PARTS if p in parts]}

    def done(step: str) -> None:
        summary["completed"] = summary.get("completed", []) + [step]
        summary["seconds"] = round(time.perf_counter() - t_all, 1)
        if on_update is not None:
            on_update(summary)

    # 0. probes, in child processes (no CUDA, no EGL context here)
    gpus = 0 if force_cpu else cuda_device_count()
    gpu = gpus > 0
    p = plan(gpu, frames_per_context, steps, contexts)
    summary.update({"plan": p, "gpus": gpus})
    render = renderer_probe() if "generate" in parts else {"ok": False, "error": "not asked (--parts)"}
    summary["renderer"] = render
    skipped = []
    if not gpu:
        skipped += ["GPU: none " + ("asked for (--device cpu)" if force_cpu else
                                    "here (torch.cuda.is_available() is False)") + "; every step ran on the CPU",
                    f"size: `cpu` profile, contexts {p['contexts']}, {p['steps']} training steps, "
                    f"configurations {', '.join(p['configurations'])}, batch 1 only, per-branch training speed "
                    f"of {', '.join(p['train_branches'])} only",
                    "AMP: bf16 autocast is CUDA-only here", "energy: no NVML counter without an NVIDIA GPU",
                    "peak GPU memory: no GPU"]
    summary["skipped"] = skipped
    done("probe")

    # 1. a small dataset, rendered before this process touches CUDA (the pool forks)
    data = None
    if "generate" in parts and render["ok"]:
        from sensors.generate import GenerateConfig, generate
        from sim.scenario import CONTEXT_NAMES
        from study.engine.device import available_cores

        names = tuple(CONTEXT_NAMES) if p["contexts"] == "all" else tuple(p["contexts"].split(","))
        workers = max(1, min(len(names) * max(1, p["frames_per_context"] // 2), available_cores()))
        cfg = GenerateConfig(contexts=names, frames_per_context=p["frames_per_context"], sequence_length=2, seed=0,
                             profile=p["profile"])
        _log(f"generate: {len(names)} contexts x {p['frames_per_context']} frames, profile {p['profile']}, "
             f"{workers} workers")
        t = time.perf_counter()
        g = generate(cfg, work / "data", workers=workers, progress=False)
        summary["generate"] = {"frames": g["frames"], "seconds": round(time.perf_counter() - t, 2),
                               "frames_per_second": g["frames_per_second"], "workers": workers}
        data = work / "data"
        done("generate")
    elif "generate" in parts:
        skipped.append(f"dataset: the renderer did not start ({render['error']}); training ran on synthetic "
                       "tensors and `hydrabench train` end to end did not run")

    # 2. CUDA from here on
    import torch

    from study.engine.device import available_cores, resolve_device

    setup = resolve_device(device="cuda" if gpu else "cpu")
    summary.update({"device": setup.describe(), "cores": available_cores(), "torch": torch.__version__})
    if "train" in parts:
        model = _model(p["profile"])
        count = p["steps"] + 1
        if data is not None:
            batches, source = dataset_batches(data, model, p["batch_size"], count), "dataset"
        else:
            batches, source = synthetic_batches(model, p["batch_size"], count), "synthetic"
        _log(f"train steps: seven branches, 1 warm-up + {p['steps']} timed steps at batch {p['batch_size']} "
             f"({source}), amp {setup.amp}")
        summary["train_steps"] = {"data": source, "branches": list(model.branches), "amp": setup.amp,
                                  **time_train_steps(model, batches, setup)}
        del model, batches
        done("train_steps")
        if data is not None:
            summary["train_run"] = _train_run(data, work / "run", p, setup)
            done("train_run")

    # 3. bench inference on the device (each measurement in a fresh, spawned process)
    if "bench" in parts:
        _bench(summary, p, setup, gpu, on_update)
        done("bench")
    return summary


BENCH_KEYS = ("latency_ms", "latency_ms_per_frame_batch_8", "peak_rss_mb", "peak_gpu_mb", "energy_j_per_frame",
              "energy_above_idle_j_per_frame", "power_w", "idle_power_w", "energy_source", "ratio_top3_to_all",
              "gate_overhead_ms", "topk_latency_ms", "tasks")
"""What the summary keeps of `bench inference`'s figures (its `details` stay out)."""


def _bench(summary: dict, p: dict, setup, gpu: bool, on_update=None) -> None:
    """`bench inference` on the device into `summary`, handed to `on_update` after each of its
    spawned tasks too (a budget that runs out part-way keeps the configurations measured)."""
    from study.bench.nets import bench_inference

    _log("bench inference: latency, memory" + (", NVML energy" if gpu else "") + ", per-branch training speed")
    t = time.perf_counter()

    def keep(b: dict) -> None:
        summary["bench_inference"] = {k: b[k] for k in BENCH_KEYS if k in b}
        summary["bench_inference"]["seconds"] = round(time.perf_counter() - t, 2)
        summary["train_images_per_second_per_branch"] = b["training_images_per_second"]

    def partial(b: dict) -> None:
        keep(b)
        if on_update is not None:
            on_update(summary)

    keep(bench_inference(p["profile"], repeats=p["repeats"], threads=setup.threads, train_steps=p["branch_steps"],
                         batches=tuple(p["batches"]), device=setup.device, amp=setup.amp,
                         configurations=p["configurations"], train_branches=p["train_branches"], on_result=partial))


def _train_run(data: Path, out: Path, p: dict, setup) -> dict:
    """One epoch of `hydrabench train` end to end: does the real loop run here, and what it costs
    with model build, evaluation and checkpoint writes (not a training speed: `train_steps` is)."""
    import csv

    from study.engine.train import TrainConfig, train

    _log(f"train run: one epoch of `hydrabench train`, batch {p['batch_size']}, amp {setup.amp}")
    cfg = TrainConfig(data=str(data), model_profile=p["profile"], epochs=1, batch_size=p["batch_size"],
                      warmup_steps=5, eval_frames=2, checkpoint_steps=10_000, device=setup.device, amp=setup.amp,
                      threads=setup.threads)
    t = time.perf_counter()
    r = train(cfg, out, progress=False)
    seconds = time.perf_counter() - t
    with open(out / "metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    return {"steps": int(rows[-1]["steps"]), "batch_size": p["batch_size"], "branches": r["branches"],
            "seconds_with_build_evaluation_checkpoints": round(seconds, 2),
            "train_seconds_of_the_epoch": float(rows[-1]["train_seconds"]),
            "last_total_loss": float(rows[-1]["loss_total"])}
