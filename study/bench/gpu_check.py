"""The one-GPU check (`scripts/gpu_check.sh`): does hydrabench train and run fast on a GPU?

On a machine with an NVIDIA GPU, in this order, each step timed:
  1. generate a small `paper` dataset (every context, --frames-per-context frames, local pool);
  2. train the seven-branch `paper` HydraFusion on it for --steps steps with bf16 AMP
     (`hydrabench train`: images/s of the whole network) and time a training step of each branch
     alone on synthetic inputs (images/s per branch, as `bench inference` does);
  3. `bench inference --device cuda`: latency at batch 1 and 8, peak GPU memory and NVML energy per
     configuration (HydraFusion Table 4's analogue), gate overheads;
and print one JSON summary on stdout. Without a GPU the same steps run on the CPU at the `cpu`
profile and a smaller size (two contexts, fewer steps, three configurations), and the summary names
what was skipped or shrunk. Progress goes to stderr.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path


def _log(msg: str) -> None:
    sys.stderr.write(f"[gpu_check {time.strftime('%H:%M:%S')}] {msg}\n")
    sys.stderr.flush()


def plan(gpu: bool, frames_per_context: int | None, steps: int | None) -> dict:
    """What the check runs: full size on a GPU, smaller on the CPU."""
    if gpu:
        return {"profile": "paper", "contexts": "all", "frames_per_context": frames_per_context or 4,
                "steps": steps or 20, "batch_size": 4, "branch_steps": 5, "repeats": 5, "batches": [1, 8],
                "configurations": None, "train_branches": None}
    return {"profile": "cpu", "contexts": "junction,fog", "frames_per_context": frames_per_context or 4,
            "steps": steps or 2, "batch_size": 2, "branch_steps": 2, "repeats": 2, "batches": [1],
            "configurations": ["single_camera", "hydra_top3_typical", "all_branches"],
            "train_branches": ["camera_right", "radar"]}


def run_check(work: Path, frames_per_context: int | None = None, steps: int | None = None,
              force_cpu: bool = False) -> dict:
    import torch

    from sensors.generate import GenerateConfig, generate
    from sim.scenario import CONTEXT_NAMES
    from study.bench.nets import bench_inference
    from study.device import available_cores, resolve_device
    from study.train import TrainConfig, train

    gpu = torch.cuda.is_available() and not force_cpu
    setup = resolve_device(device="cuda" if gpu else "cpu")
    p = plan(gpu, frames_per_context, steps)
    skipped = []
    if not gpu:
        skipped += ["GPU: none here (torch.cuda.is_available() is False); every step ran on the CPU",
                    f"size: `cpu` profile, contexts {p['contexts']}, {p['steps']} training steps, "
                    f"configurations {', '.join(p['configurations'])}, batch 1 only, per-branch training speed "
                    f"of {', '.join(p['train_branches'])} only",
                    "AMP: bf16 autocast is CUDA-only here", "energy: no NVML counter without an NVIDIA GPU",
                    "peak GPU memory: no GPU"]
    summary = {"device": setup.describe(), "plan": p, "cores": available_cores(), "torch": torch.__version__}
    t_all = time.perf_counter()

    # 1. a small dataset
    contexts = tuple(CONTEXT_NAMES) if p["contexts"] == "all" else tuple(p["contexts"].split(","))
    workers = max(1, min(len(contexts) * max(1, p["frames_per_context"] // 2), available_cores()))
    cfg = GenerateConfig(contexts=contexts, frames_per_context=p["frames_per_context"], sequence_length=2, seed=0,
                         profile=p["profile"])
    _log(f"generate: {len(contexts)} contexts x {p['frames_per_context']} frames, profile {p['profile']}, "
         f"{workers} workers")
    t = time.perf_counter()
    g = generate(cfg, work / "data", workers=workers, progress=False)
    summary["generate"] = {"frames": g["frames"], "seconds": round(time.perf_counter() - t, 2),
                           "frames_per_second": g["frames_per_second"], "workers": workers}

    # 2. training: the whole network on the dataset, then each branch alone
    from fusion.data import split_by_sequence
    from sensors.dataset import DatasetReader

    n_train = len(split_by_sequence(DatasetReader(work / "data"), 0.7, 0)[0])
    per_epoch = -(-n_train // p["batch_size"])
    epochs = max(1, -(-p["steps"] // per_epoch))
    _log(f"train: seven branches, {epochs} epoch(s) of {per_epoch} steps, batch {p['batch_size']}, "
         f"amp {setup.amp}")
    tcfg = TrainConfig(data=str(work / "data"), model_profile=p["profile"], epochs=epochs, batch_size=p["batch_size"],
                       warmup_steps=5, eval_frames=2, checkpoint_steps=10_000, device=setup.device, amp=setup.amp,
                       threads=setup.threads)
    t = time.perf_counter()
    r = train(tcfg, work / "run", progress=False)
    seconds = time.perf_counter() - t
    import csv

    with open(work / "run" / "metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    steps_done = int(rows[-1]["steps"])
    summary["train"] = {"branches": r["branches"], "steps": steps_done, "batch_size": p["batch_size"],
                        "seconds_with_evaluation": round(seconds, 2),
                        "images_per_second_with_evaluation": round(steps_done * p["batch_size"] / seconds, 3),
                        "last_total_loss": float(rows[-1]["loss_total"]), "amp": setup.amp}

    # 3. bench inference on the device (each measurement in a fresh process), with per-branch training
    _log("bench inference: latency, memory" + (", NVML energy" if gpu else "") + ", per-branch training speed")
    t = time.perf_counter()
    b = bench_inference(p["profile"], repeats=p["repeats"], threads=setup.threads, train_steps=p["branch_steps"],
                        batches=tuple(p["batches"]), device=setup.device, amp=setup.amp,
                        configurations=p["configurations"], train_branches=p["train_branches"])
    summary["bench_inference"] = {k: b[k] for k in ("latency_ms", "latency_ms_per_frame_batch_8", "peak_rss_mb",
                                                     "peak_gpu_mb", "energy_j_per_frame", "energy_source",
                                                     "ratio_top3_to_all", "gate_overhead_ms", "topk_latency_ms")
                                  if k in b}
    summary["bench_inference"]["seconds"] = round(time.perf_counter() - t, 2)
    summary["train_images_per_second_per_branch"] = b["training_images_per_second"]
    summary["skipped"] = skipped
    summary["seconds"] = round(time.perf_counter() - t_all, 1)
    return summary
