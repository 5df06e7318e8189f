"""Benches: throughput and latency measurements, called by `hydrabench bench <what>`
(`study.commands.bench`) and by `scripts/gpu_check.sh` (`study.commands.gpu_check`).

    pipeline   scene steps/s of the simulator, generated frames/s and ms per component (sim, generate)
    boxes      fusion.boxes NMS / Soft-NMS / WBF against ensemble-boxes (boxes)
    nets       latency, memory, training speed and gate overheads per model configuration (inference)
    lidar_fog  our lidar fog model against Hahner et al. ICCV 2021 on the same clean clouds (lidar-fog)
    scale      threads, DDP processes and Ray against one process, back to back (scale)
    gpu_check  the one-GPU check: generate, train and bench inference on a GPU (or smaller on the CPU)

Each returns its figures as a dict; printing is the command's. Nothing here asserts a time.
"""
