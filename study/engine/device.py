"""Where the networks run: one place for `--device`, `--threads`, `--amp` and `--workers`.

Every command that runs a network (train, evaluate, train-gate, the EcoFusion commands, bench
inference) adds the same four options with `study.commands.device.add_device_args(parser)` and
turns them into a `DeviceSetup` with `resolve_device(args)` (experiments pass keywords instead):

    --device auto|cpu|cuda|cuda:N   auto: the first GPU when torch sees one, else the CPU.
                                    A GPU asked for on a machine without one is bad input (exit 2).
                                    Under torchrun each process takes the GPU of its LOCAL_RANK;
                                    cuda:N there (every rank on one GPU) is refused.
    --threads N                     torch CPU threads (intra-op); default: the cores this process
                                    may use (sched_getaffinity), shared out between the processes of
                                    one machine under torchrun (LOCAL_WORLD_SIZE).
    --amp [auto|bf16] / --no-amp    bf16 autocast of the backbones (torch.autocast on the CPU or the
                                    GPU; anchors, box coding, the RPN and RoI heads and the gates stay
                                    fp32, `fusion.nets.layers.full_precision`). --amp alone: bf16.
                                    auto: bf16 where the device computes it natively (a CUDA GPU with
                                    bf16, a CPU with AMX-BF16 or AVX512-BF16; `native_bf16`), else
                                    fp32. Default (no option): training bf16 on CUDA, fp32 on the CPU;
                                    evaluation fp32 everywhere (`purpose="eval"`).
    --workers N                     DataLoader processes decoding frames (0: in the main process;
                                    default 0 on the CPU, `DEFAULT_CUDA_WORKERS` on CUDA).

The resolved device type and precision are recorded with every result (`compute_identity`). On the
CPU with fp32 and --workers 0 nothing differs from code that never heard of devices: the same
operations in the same order, so the same weights. The fp32 paths on CUDA run true fp32 (TF32 off,
`setup_torch`), so "fp32" means the same thing on both.
"""

from __future__ import annotations

import os
from contextlib import nullcontext
from dataclasses import dataclass

from sim.errors import UserError

AMP_CHOICES = ("auto", "bf16", "off")
"""Values of --amp: auto (bf16 where native, `native_bf16`), bf16 (always), off (fp32)."""

MAX_WORKERS = 256
"""Most worker processes any command starts (generation pools, DataLoader workers): beyond it a typo
(10,000 forks), not a plan. `study.cli.workers_int` and `loader_workers_int` hold every --workers to it."""

DEFAULT_CUDA_WORKERS = 4
"""DataLoader workers when training on CUDA and --workers is not given: decoding frames in the
training process would leave the GPU waiting on every batch."""


def available_cores() -> int:
    """CPU cores this process may run on (the affinity mask; cgroup quotas are not read)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def local_world_size(environ=None) -> int:
    """Processes of this job on this machine: torchrun's LOCAL_WORLD_SIZE (1 outside torchrun)."""
    env = os.environ if environ is None else environ
    try:
        return max(1, int(env.get("LOCAL_WORLD_SIZE") or env.get("WORLD_SIZE") or 1))
    except ValueError:
        return 1


def default_threads(environ=None) -> int:
    """torch CPU threads when --threads is not given: this process's share of the cores (all of
    them alone; under torchrun cores // LOCAL_WORLD_SIZE, at least 1, so the ranks of one machine
    do not each start a thread per core and fight over them)."""
    return max(1, available_cores() // local_world_size(environ))


def cpu_bf16_flags(cpuinfo: str | None = None) -> list[str]:
    """The native-bf16 instruction sets this CPU announces in /proc/cpuinfo's flags: "amx_bf16"
    (Intel AMX, Sapphire Rapids on) and "avx512_bf16" (Cooper Lake, AMD Zen 4 on). Empty when none
    or when /proc/cpuinfo cannot be read."""
    if cpuinfo is None:
        try:
            with open("/proc/cpuinfo") as fh:
                cpuinfo = fh.read()
        except OSError:
            return []
    flags: set[str] = set()
    for line in cpuinfo.splitlines():
        if line.startswith("flags"):
            flags.update(line.split(":", 1)[-1].split())
    return [f for f in ("amx_bf16", "avx512_bf16") if f in flags]


def native_bf16(device: str = "cpu", cpuinfo: str | None = None) -> tuple[bool, str]:
    """(whether `device` computes bf16 natively, why). CUDA: torch.cuda.is_bf16_supported()
    (Ampere on). CPU: AMX-BF16 or AVX512-BF16 in /proc/cpuinfo's flags; without a readable
    /proc/cpuinfo, oneDNN's own answer (torch.ops.mkldnn._is_mkldnn_bf16_supported, which also says
    yes for AVX512 CPUs that only emulate bf16, hence the flags first). Without native bf16, autocast
    still runs but converts on every op, usually slower than fp32."""
    import torch

    if str(device).startswith("cuda"):
        ok = bool(torch.cuda.is_available() and torch.cuda.is_bf16_supported())
        return ok, ("the GPU computes bf16" if ok else "this GPU has no native bf16 (before Ampere)")
    flags = cpu_bf16_flags(cpuinfo)
    if flags:
        return True, f"the CPU has {' and '.join(flags)}"
    if cpuinfo is None and not os.path.exists("/proc/cpuinfo"):
        try:
            ok = bool(torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported())
        except (AttributeError, RuntimeError):
            ok = False
        return ok, "oneDNN " + ("supports bf16 here" if ok else "has no bf16 here") + " (no /proc/cpuinfo)"
    return False, "the CPU has neither AMX-BF16 nor AVX512-BF16 (no native bf16; bf16 would be emulated)"


def setup_torch(device: str, threads: int) -> None:
    """Apply a device choice to this process: torch's CPU threads, the current CUDA device, and
    true fp32 on CUDA: TF32 (10 mantissa bits) off for matmuls and cuDNN convolutions, which torch
    would otherwise use for "fp32" convolutions, so fp32 results (gate data, evaluation) are fp32.
    Autocast regions run in bf16 whatever these flags say."""
    import torch

    torch.set_num_threads(int(threads))
    torch.backends.cuda.matmul.allow_tf32 = False
    torch.backends.cudnn.allow_tf32 = False
    if str(device).startswith("cuda"):
        torch.cuda.set_device(torch.device(device))


@dataclass(frozen=True)
class DeviceSetup:
    """A resolved device choice.

    Fields:
        device: torch device string ("cpu", "cuda:0", ...).
        threads: torch intra-op CPU threads set for this process.
        amp: bf16 autocast of the backbones' forward passes (CPU or CUDA).
        workers: DataLoader worker processes (0: in the main process).
    """

    device: str
    threads: int
    amp: bool
    workers: int = 0

    @property
    def is_cuda(self) -> bool:
        return self.device.startswith("cuda")

    @property
    def device_type(self) -> str:
        """"cpu" or "cuda" (what torch.autocast and the records name)."""
        return self.device.split(":", 1)[0]

    def torch_device(self):
        import torch

        return torch.device(self.device)

    @property
    def precision(self) -> str:
        """The dtype the forward passes run in under `autocast()`: "fp32" (no autocast), "bf16"."""
        return "bf16" if self.amp else "fp32"

    def autocast(self):
        """Context for forward passes: bf16 autocast on this device type when `amp`, else nothing."""
        if not self.amp:
            return nullcontext()
        import torch

        return torch.autocast(device_type=self.device_type, dtype=torch.bfloat16)

    def describe(self) -> dict:
        """The choice as JSON (recorded with results), with the GPU's name when there is one."""
        out = {"device": self.device, "device_type": self.device_type, "precision": self.precision,
               "threads": self.threads, "amp": "bf16" if self.amp else False, "workers": self.workers}
        if self.is_cuda:
            import torch

            out["gpu"] = torch.cuda.get_device_name(self.torch_device())
        return out


def compute_identity(setup: DeviceSetup | None = None, *, device: str | None = None,
                     precision: str | None = None) -> dict:
    """What a result computed under `setup` depends on beyond its inputs: the device type ("cpu" or
    "cuda", not the index: two GPUs of one kind give the same numbers) and the resolved precision
    ("fp32", "bf16", "fp16": whether autocast is on and in which dtype). Part of every cache key and
    record (`study.pipeline.stages` stage keys, the gate-data cache key). Without a setup, `device` (a torch
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


def rank_device(requested: str, world: int, local_rank: int) -> str:
    """The --device a torchrun process (`world` > 1) asks for: auto and cuda become its own GPU
    (cuda:LOCAL_RANK) when there are GPUs; cuda:N, which would put every rank on one GPU (NCCL
    fails), is refused with one line. Outside torchrun `requested` as it is."""
    text = (requested or "auto").strip().lower()
    if world <= 1:
        return text
    if text.startswith("cuda:"):
        raise UserError(f"--device {text} under torchrun puts all {world} processes on one GPU; "
                        "use --device cuda (each process takes the GPU of its LOCAL_RANK)")
    import torch

    if text in ("auto", "cuda") and torch.cuda.is_available():
        return f"cuda:{local_rank}"
    return "cpu" if text == "auto" else text


def resolve_amp(amp, device: str, purpose: str = "train") -> bool:
    """Whether forward passes on `device` run under bf16 autocast.

    `amp`: None (the default: bf16 for training on CUDA; fp32 on the CPU and for evaluation, so
    evaluation numbers are fp32 unless asked), True / "bf16" / "on" (bf16), False / "off" / "fp32"
    (fp32), "auto" (bf16 where `native_bf16(device)`, else fp32). `purpose`: "train" or "eval".
    """
    if amp is None:
        return purpose == "train" and str(device).startswith("cuda")
    if isinstance(amp, bool):
        return amp
    text = str(amp).strip().lower()
    if text in ("bf16", "on", "true"):
        return True
    if text in ("off", "fp32", "false"):
        return False
    if text == "auto":
        return native_bf16(device)[0]
    raise UserError(f"--amp {amp!r}: choose from {', '.join(AMP_CHOICES)}")


def resolve_device(args=None, *, device: str | None = None, threads: int | None = None, amp=None,
                   workers: int | None = None, apply: bool = True, purpose: str = "train") -> DeviceSetup:
    """A DeviceSetup from parsed arguments (`add_device_args`) or keywords (which win).

    `amp`: see `resolve_amp` (`purpose` "train" or "eval" picks its default). `workers` None: 0 on
    the CPU, DEFAULT_CUDA_WORKERS on CUDA. `apply`: also `setup_torch` (threads, the current CUDA
    device, TF32 off). Raises UserError for a device that is not here.
    """
    def pick(name, value, default):
        if value is not None:
            return value
        return getattr(args, name, default) if args is not None else default

    dev = parse_device(pick("device", device, "auto"))
    n_threads = int(pick("threads", threads, 0) or 0) or default_threads()
    use_amp = resolve_amp(pick("amp", amp, None), dev, purpose)
    n_workers = pick("workers", workers, None)
    n_workers = (DEFAULT_CUDA_WORKERS if dev.startswith("cuda") else 0) if n_workers is None else int(n_workers)
    if not 0 <= n_workers <= MAX_WORKERS:
        raise UserError(f"workers must be in 0..{MAX_WORKERS}, got {n_workers}")
    setup = DeviceSetup(device=dev, threads=n_threads, amp=bool(use_amp), workers=n_workers)
    if apply:
        setup_torch(setup.device, n_threads)
    return setup


def to_device(inputs: dict, targets, device):
    """Batched inputs (sensor -> tensor) and per-frame targets (frame -> {boxes, labels}) on `device`;
    uint8 inputs (`fusion.data.frame_inputs(..., uint8=True)`) travel as uint8 and become float32
    there (`fusion.data.as_model_input`). On the CPU float inputs and the targets come back as they are."""
    from fusion.data import as_model_input

    if str(device) == "cpu":
        return {k: as_model_input(v) for k, v in inputs.items()}, targets
    inputs = {k: as_model_input(v.to(device, non_blocking=True)) for k, v in inputs.items()}
    if targets is not None:
        targets = [{f: {k: v.to(device, non_blocking=True) for k, v in t.items()} for f, t in per.items()}
                   for per in targets]
    return inputs, targets
