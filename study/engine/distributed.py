"""Data-parallel training under `torchrun`: the process group, the model wrapper, and the few
collective steps `study.engine.train` needs. Outside torchrun (no WORLD_SIZE, or 1) every call is a no-op
and `wrap` returns the model itself, so one-process training runs exactly as it did.

torchrun sets RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR and MASTER_PORT; the backend is NCCL when the
processes train on CUDA GPUs and gloo on the CPU. Rank 0 alone writes the run directory
(config.json, checkpoints, metrics.csv); the others wait for it at barriers.
"""

from __future__ import annotations

import datetime
import os
from dataclasses import dataclass


@dataclass
class Distributed:
    """This process's place in the torchrun job (world 1 outside torchrun)."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0
    backend: str = ""
    initialised: bool = False
    device: str = "cpu"

    def init(self, device: str) -> None:
        if self.world == 1 or self.initialised:
            return
        import torch.distributed as td

        self.backend = "nccl" if device.startswith("cuda") else "gloo"
        self.device = device
        # rank 0 evaluates the test split at each epoch end while the others wait at a barrier
        td.init_process_group(self.backend, timeout=datetime.timedelta(hours=4))
        self.initialised = True

    def wrap(self, model, setup):
        """DistributedDataParallel around `model` (already on its device), or `model` when alone.
        BatchNorm layers become SyncBatchNorm on GPUs, so batch statistics cover the global batch."""
        if self.world == 1:
            return model
        import torch

        self.init(setup.device)
        if setup.is_cuda:
            has_bn = any(isinstance(m, torch.nn.modules.batchnorm._BatchNorm) for m in model.modules())
            if has_bn:
                model = torch.nn.SyncBatchNorm.convert_sync_batchnorm(model)
            return torch.nn.parallel.DistributedDataParallel(model, device_ids=[setup.torch_device().index])
        return torch.nn.parallel.DistributedDataParallel(model)

    def barrier(self) -> None:
        if self.world > 1:
            import torch.distributed as td

            td.barrier()

    def sum_dict(self, values: dict[str, float]) -> dict[str, float]:
        """Each key's value added up over the processes (the same keys in the same order on all)."""
        if self.world == 1:
            return values
        import torch
        import torch.distributed as td

        keys = sorted(values)
        t = torch.tensor([values[k] for k in keys], dtype=torch.float64, device=self.device)
        td.all_reduce(t)
        return dict(zip(keys, t.tolist()))

    def close(self) -> None:
        if self.initialised:
            import torch.distributed as td

            td.destroy_process_group()
            self.initialised = False


def from_env() -> Distributed:
    """The torchrun job this process belongs to, from its environment."""
    world = int(os.environ.get("WORLD_SIZE", "1") or 1)
    return Distributed(rank=int(os.environ.get("RANK", "0") or 0), world=world,
                       local_rank=int(os.environ.get("LOCAL_RANK", "0") or 0))
