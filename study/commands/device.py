"""The four device options every network command shares (`study.engine.device` resolves them):
`add_device_args(parser)` adds --device, --threads, --amp [auto|bf16] / --no-amp and --workers."""

from __future__ import annotations

import argparse

from study.cli import count_int, loader_workers_int
from study.engine.device import AMP_CHOICES, DEFAULT_CUDA_WORKERS, available_cores


def device_arg(text: str) -> str:
    """An argparse type: auto | cpu | cuda | cuda:N, spelled right (whether the GPU is here is checked
    when the command resolves it, `study.engine.device.parse_device`)."""
    import re

    t = str(text).strip().lower()
    if not re.fullmatch(r"auto|cpu|cuda(:\d{1,3})?", t):
        raise argparse.ArgumentTypeError(f"expected auto, cpu, cuda or cuda:N, got {text!r}")
    return t


device_arg.kind = "name"


def amp_arg(text: str) -> str:
    """An argparse type: auto | bf16 | off (`study.engine.device.resolve_amp`)."""
    t = str(text).strip().lower()
    if t not in AMP_CHOICES:
        raise argparse.ArgumentTypeError(f"expected {', '.join(AMP_CHOICES)}, got {text!r}")
    return t


amp_arg.kind = "name"


def add_device_args(parser, *, workers: bool = True, threads_default: int = 0, purpose: str = "train") -> None:
    """Add --device, --threads, --amp [auto|bf16] / --no-amp and (when `workers`) --workers to an
    argparse parser. `purpose` ("train" or "eval") only words the help: the default precision is
    bf16 for training on CUDA and fp32 otherwise (`study.engine.device.resolve_amp`)."""
    g = parser.add_argument_group("device")
    g.add_argument("--device", type=device_arg, default="auto", help="auto | cpu | cuda | cuda:N (auto: a GPU when one is present)")
    g.add_argument("--threads", type=count_int, default=threads_default,
                   help=f"torch CPU threads (0: the cores available, here {available_cores()}; under torchrun "
                   "each process's share)")
    default = "bf16 on CUDA, fp32 on the CPU" if purpose == "train" else "fp32"
    g.add_argument("--amp", type=amp_arg, nargs="?", const="bf16", default=None, metavar="auto|bf16",
                   help="bf16 autocast of the backbones (anchors, boxes, heads and gates stay fp32). --amp: bf16; "
                   "--amp auto: bf16 where the device has native bf16 (AMX-BF16/AVX512-BF16 CPUs, Ampere+ GPUs), "
                   f"else fp32 (default: {default})")
    g.add_argument("--no-amp", dest="amp", action="store_const", const="off", help="fp32 forward passes")
    if workers:
        g.add_argument("--workers", type=loader_workers_int, default=None,
                       help="DataLoader worker processes decoding frames (0: in the main process; "
                       f"default 0 on the CPU, {DEFAULT_CUDA_WORKERS} on CUDA)")
