"""Where the networks run: one place for `--device`, `--threads`, `--amp` and `--workers`.

Every command that runs a network (train, evaluate, train-gate, the EcoFusion commands, bench
inference) adds the same four options with `study.commands.device.add_device_args(parser)` and
turns them into a `DeviceSetup` with `resolve_device(args)` (experiments pass keywords instead):

    --device auto|cpu|cuda|cuda:N   auto: the first GPU when torch sees one, else the CPU.
                                    A GPU asked for on a machine without one is bad input (exit 2).
    --threads N                     torch CPU threads (intra-op); default: the cores this process
                                    may use (sched_getaffinity), not a fixed number.
    --amp / --no-amp                bf16 autocast of the forward passes (torch.autocast); default on
                                    for CUDA, off on the CPU (refused there: slower on most CPUs and
                                    it changes the CPU results, which must not change).
    --workers N                     DataLoader processes decoding frames (0: in the main process).

On the CPU with --no-amp and --workers 0 nothing differs from code that never heard of devices:
the same operations in the same order, so the same weights.
"""

from __future__ import annotations

import os
from contextlib import nullcontext
from dataclasses import dataclass

from sim.errors import UserError


def available_cores() -> int:
    """CPU cores this process may run on (the affinity mask; cgroup quotas are not read)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


@dataclass(frozen=True)
class DeviceSetup:
    """A resolved device choice.

    Fields:
        device: torch device string ("cpu", "cuda:0", ...).
        threads: torch intra-op CPU threads set for this process.
        amp: bf16 autocast of forward passes (CUDA only).
        workers: DataLoader worker processes (0: in the main process).
    """

    device: str
    threads: int
    amp: bool
    workers: int = 0

    @property
    def is_cuda(self) -> bool:
        return self.device.startswith("cuda")

    def torch_device(self):
        import torch

        return torch.device(self.device)

    @property
    def precision(self) -> str:
        """The dtype the forward passes run in under `autocast()`: "fp32" (no autocast), "bf16"."""
        return "bf16" if self.amp else "fp32"

    def autocast(self):
        """Context for forward passes: bf16 autocast when `amp`, else nothing."""
        if not self.amp:
            return nullcontext()
        import torch

        return torch.autocast(device_type="cuda", dtype=torch.bfloat16)

    def describe(self) -> dict:
        """The choice as JSON (recorded with results), with the GPU's name when there is one."""
        out = {"device": self.device, "threads": self.threads, "amp": "bf16" if self.amp else False,
               "workers": self.workers}
        if self.is_cuda:
            import torch

            out["gpu"] = torch.cuda.get_device_name(self.torch_device())
        return out


def compute_identity(setup: DeviceSetup | None = None, *, device: str | None = None,
                     precision: str | None = None) -> dict:
    """What a result computed under `setup` depends on beyond its inputs: the device type ("cpu" or
    "cuda", not the index: two GPUs of one kind give the same numbers) and the resolved precision
    ("fp32", "bf16", "fp16": whether autocast is on and in which dtype). Part of every cache key and
    record (`study.runner` stage keys, the gate-data cache key). Without a setup, `device` (a torch
    device or its string) and `precision` (default "fp32") say it directly."""
    dev = str(setup.device if setup is not None else (device or "cpu"))
    prec = setup.precision if setup is not None else (precision or "fp32")
    return {"device": dev.split(":", 1)[0], "precision": prec}


def parse_device(text: str) -> str:
    """'auto' | 'cpu' | 'cuda' | 'cuda:N' -> a torch device string that exists here, or UserError."""
    import torch

    text = (text or "auto").strip().lower()
    if text == "auto":
        return "cuda:0" if torch.cuda.is_available() else "cpu"
    if text == "cpu":
        return "cpu"
    if text == "cuda" or text.startswith("cuda:"):
        index = 0
        if text != "cuda":
            try:
                index = int(text.split(":", 1)[1])
            except ValueError:
                raise UserError(f"--device {text!r}: expected cuda:N with N an integer") from None
        if not torch.cuda.is_available():
            raise UserError(f"--device {text}: no CUDA GPU is available on this machine (use --device cpu or auto)")
        n = torch.cuda.device_count()
        if not 0 <= index < n:
            raise UserError(f"--device {text}: this machine has {n} CUDA GPU(s), cuda:0..cuda:{n - 1}")
        return f"cuda:{index}"
    raise UserError(f"--device {text!r}: choose from auto, cpu, cuda, cuda:N")


def resolve_device(args=None, *, device: str | None = None, threads: int | None = None, amp: bool | None = None,
                   workers: int | None = None, apply: bool = True) -> DeviceSetup:
    """A DeviceSetup from parsed arguments (`add_device_args`) or keywords (which win).

    `apply`: also set torch's CPU thread count (torch.set_num_threads) and, for CUDA, the current
    device. Raises UserError for a device that is not here or --amp on the CPU.
    """
    def pick(name, value, default):
        if value is not None:
            return value
        return getattr(args, name, default) if args is not None else default

    dev = parse_device(pick("device", device, "auto"))
    n_threads = int(pick("threads", threads, 0) or 0) or available_cores()
    use_amp = pick("amp", amp, None)
    if use_amp is None:
        use_amp = dev.startswith("cuda")
    if use_amp and not dev.startswith("cuda"):
        raise UserError("--amp is bf16 autocast on a CUDA GPU; on the CPU run without it (--no-amp)")
    setup = DeviceSetup(device=dev, threads=n_threads, amp=bool(use_amp), workers=int(pick("workers", workers, 0) or 0))
    if apply:
        import torch

        torch.set_num_threads(n_threads)
        if setup.is_cuda:
            torch.cuda.set_device(setup.torch_device())
    return setup


def to_device(inputs: dict, targets, device):
    """Batched inputs (sensor -> tensor) and per-frame targets (frame -> {boxes, labels}) on `device`.
    On the CPU the same objects come back (no copies)."""
    if str(device) == "cpu":
        return inputs, targets
    inputs = {k: v.to(device, non_blocking=True) for k, v in inputs.items()}
    if targets is not None:
        targets = [{f: {k: v.to(device, non_blocking=True) for k, v in t.items()} for f, t in per.items()}
                   for per in targets]
    return inputs, targets
