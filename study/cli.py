"""The `hydrabench` command line.

Contract (DESIGN.md): every command that reports figures takes `--json` and then prints exactly
one JSON object on stdout; progress goes to stderr. Bad input exits with code 2 and one line
naming the problem (no traceback), and leaves nothing half-written.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable

from sim.errors import UserError

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
if os.environ.get("SDL_VIDEODRIVER", "dummy") == "dummy":
    os.environ["SDL_VIDEODRIVER"] = "offscreen"

EXIT_USAGE = 2


class Parser(argparse.ArgumentParser):
    """argparse that reports errors as one line with exit code 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise UserError(f"{self.prog}: {message}")


class Formatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    pass


def nonneg_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {v}")
    return v


def pos_int(text: str) -> int:
    v = nonneg_int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {v}")
    return v


def severity_arg(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"severity must be an integer 0..5, got {text!r}") from None
    if not 0 <= v <= 5:
        raise argparse.ArgumentTypeError(f"severity must be 0..5, got {v}")
    return v


def pos_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not v > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {v}")
    return v


def emit(result: dict, as_json: bool, text: Callable[[dict], str] | None = None) -> None:
    """Print a command's result: one JSON object with --json, else readable text."""
    if as_json:
        sys.stdout.write(json.dumps(result, sort_keys=False, default=_json_default) + "\n")
    elif text is not None:
        sys.stdout.write(text(result).rstrip("\n") + "\n")
    else:
        sys.stdout.write(json.dumps(result, indent=2, default=_json_default) + "\n")
    sys.stdout.flush()


def _json_default(obj):
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if hasattr(obj, "item"):
        return obj.item()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


# ----------------------------------------------------------------------------------------------
# command table: name -> (module, help). Modules are imported only when their command runs, so
# `hydrabench --help` and light commands never import torch.

COMMANDS: dict[str, tuple[str, str]] = {
    "scenes": ("study.cmd_scenes:add_parser", "simulate scenes of a context, summarise and draw them top-down"),
    "generate": ("study.cmd_dataset:add_generate", "generate a sharded sensor dataset (cameras, lidar, radar, labels)"),
    "verify": ("study.cmd_dataset:add_verify", "check a dataset's shards against its manifest checksums"),
    "export-coco": ("study.cmd_dataset:add_export", "write a dataset's FWD labels as COCO JSON"),
    "show": ("study.cmd_dataset:add_show", "draw one frame of a dataset with every sensor and its labels"),
    "gallery": ("study.cmd_gallery:add_parser", "one scene under every condition and severity, all sensors side by side"),
    "theory": ("study.theory:add_parser", "HydraFusion Sec. 1.1 measured: single sensors vs full, selective and gated fusion per weather"),
    "train": ("study.train:add_parser", "train HydraFusion stems and branches (resumable, per-epoch CSV and checkpoints)"),
    "evaluate": ("study.evaluate:add_parser", "VOC mAP@0.5 of a run's branches fused in the right camera (per class, per context)"),
    "train-gate": ("study.gates:add_train_gate", "train the deep or attention gate on a run's stem features and branch losses"),
    "eco-data": ("study.ecofusion:add_eco_data", "EcoFusion: per-frame stem features and fused loss / AP of every branch configuration"),
    "eco-energy": ("study.ecofusion:add_eco_energy", "EcoFusion: measured stem / branch / fusion latency and energy of every configuration"),
    "eco-train-gate": ("study.ecofusion:add_eco_train_gate", "EcoFusion: train the deep or attention configuration gate"),
    "eco-evaluate": ("study.ecofusion:add_eco_evaluate", "EcoFusion at one lambda_E and gamma: mAP, loss, energy, latency per gate"),
    "eco-sweep": ("study.ecofusion:add_eco_sweep", "EcoFusion Tables 1-3 and Figures 4-5 over a lambda_E sweep"),
    "bench": ("study.bench:add_parser", "measure throughput (sim, generate, ...) and print the figures"),
}


def build_parser() -> Parser:
    parser = Parser(
        prog="hydrabench",
        description=(
            "hydrabench: a simulation-driven benchmark for context-aware selective sensor fusion.\n"
            "Generate driving scenes with known weather, light and obstruction, render camera,\n"
            "lidar and radar, and compare selective against full fusion.\n\n"
            "Run `hydrabench <command> --help` for each command."
        ),
        formatter_class=Formatter,
    )
    sub = parser.add_subparsers(dest="command", metavar="<command>", parser_class=Parser)
    sub.required = True
    for name, (target, help_text) in COMMANDS.items():
        module, func = target.split(":")
        mod = __import__(module, fromlist=[func])
        getattr(mod, func)(sub, name, help_text)
    return parser


def main(argv: list[str] | None = None) -> int:
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
        return int(args.run(args) or 0)
    except UserError as exc:
        msg = str(exc).splitlines()[0] if str(exc) else "invalid input"
        sys.stderr.write(f"hydrabench: error: {msg}\n")
        return EXIT_USAGE
    except KeyboardInterrupt:
        sys.stderr.write("hydrabench: interrupted\n")
        return 130
    except BrokenPipeError:
        return 0


if __name__ == "__main__":
    sys.exit(main())
