"""The four device options every network command shares (`study.device` resolves them):
`add_device_args(parser)` adds --device, --threads, --amp/--no-amp and --workers."""

from __future__ import annotations

import argparse

from study.cli import count_int
from study.device import available_cores


def device_arg(text: str) -> str:
    """An argparse type: auto | cpu | cuda | cuda:N, spelled right (whether the GPU is here is checked
    when the command resolves it, `study.device.parse_device`)."""
    import re

    t = str(text).strip().lower()
    if not re.fullmatch(r"auto|cpu|cuda(:\d{1,3})?", t):
        raise argparse.ArgumentTypeError(f"expected auto, cpu, cuda or cuda:N, got {text!r}")
    return t


device_arg.kind = "name"


def add_device_args(parser, *, workers: bool = True, threads_default: int = 0) -> None:
    """Add --device, --threads, --amp/--no-amp and (when `workers`) --workers to an argparse parser."""
    g = parser.add_argument_group("device")
    g.add_argument("--device", type=device_arg, default="auto", help="auto | cpu | cuda | cuda:N (auto: a GPU when one is present)")
    g.add_argument("--threads", type=count_int, default=threads_default,
                   help=f"torch CPU threads (0: the cores available, here {available_cores()})")
    g.add_argument("--amp", action=argparse.BooleanOptionalAction, default=None,
                   help="bf16 autocast of forward passes (default: on for CUDA, off on the CPU)")
    if workers:
        g.add_argument("--workers", type=count_int, default=0,
                       help="DataLoader worker processes decoding frames (0: in the main process)")
