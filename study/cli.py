"""The `hydrabench` command line.

Contract (DESIGN.md): every command that reports figures takes `--json` and then prints exactly
one JSON object on stdout; progress goes to stderr. Bad input exits with code 2 and one line
naming the problem (no traceback), and leaves nothing half-written.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import json
import math
import os
import signal
import sys
import threading
from collections.abc import Callable
from pathlib import Path

from fusion.metrics import MAX_BOOTSTRAP
from sim.errors import Terminated, UserError
from study.engine.device import MAX_WORKERS

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
if os.environ.get("SDL_VIDEODRIVER", "dummy") == "dummy":
    os.environ["SDL_VIDEODRIVER"] = "offscreen"

EXIT_USAGE = 2


class Parser(argparse.ArgumentParser):
    """argparse that reports errors as one line with exit code 2.

    It also refuses a value given twice to a list option (nargs '+' / '*'), so every command's
    space-separated lists behave like the comma lists of `name_list`.
    """

    def error(self, message: str) -> None:  # type: ignore[override]
        raise UserError(f"{self.prog}: {message}")

    def parse_known_args(self, args=None, namespace=None):
        if args is None:
            args = sys.argv[1:]
        args = list(args)
        if self._subparsers is not None and args:
            # `hydrabench --bogus`: name the flag, not the missing command
            lead = next((a for a in args if not a.startswith("-")), None)
            for a in args[: args.index(lead) if lead is not None else len(args)]:
                if a not in self._option_string_actions:
                    self.error(f"unrecognized argument {a!r} (options go after the command: "
                               f"{self.prog} <command> [options])")
        ns, extra = super().parse_known_args(args, namespace)
        for action in self._actions:
            if action.nargs in ("+", "*") and action.option_strings:
                values = getattr(ns, action.dest, None)
                if isinstance(values, list):
                    seen = set()
                    for v in values:
                        if v in seen:
                            self.error(f"argument {'/'.join(action.option_strings)}: {v!r} is given twice")
                        seen.add(v)
        return ns, extra


class Formatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Help with each option's default appended once: not when the help already states a default
    ("[20]", "(default: ...)", "default ..."), and not when the default is None, False or empty."""

    def _get_help_string(self, action):
        text = action.help or ""
        default = action.default
        if (default is argparse.SUPPRESS or default is None or default is False or default in ("", [], ())
                or "%(default)" in text or "default" in text.lower() or text.rstrip().endswith("]")
                or not (action.option_strings or action.nargs in (argparse.OPTIONAL, argparse.ZERO_OR_MORE))):
            return text
        return text + " (default: %(default)s)"


# ----------------------------------------------------------------------------------------------
# Argument types: one parser per kind of input. Each carries `kind` (and bounds or suffixes) so the
# fuzz test (tests/study/test_fuzz.py) can read from the parser which bad values to try.

MAX_COUNT = 1_000_000
"""Largest value any count option accepts (epochs, repeats, frames, ...): beyond it a typo, not a plan.
Sizes that drive memory or days of work have tighter documented limits in their configs."""
MAX_SEED = 2**63 - 1


def _typed(func, kind: str, **attrs):
    func.kind = kind
    for k, v in attrs.items():
        setattr(func, k, v)
    return func


def int_range(lo: int, hi: int, name: str) -> Callable[[str], int]:
    """An argparse type: an integer in [lo, hi]."""

    def parse(text: str) -> int:
        try:
            v = int(str(text).strip())
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if v < lo:
            raise argparse.ArgumentTypeError(f"must be >= {lo}, got {v}")
        if v > hi:
            raise argparse.ArgumentTypeError(f"must be <= {hi}, got {v}")
        return v

    parse.__name__ = name
    return _typed(parse, "int", lo=lo, hi=hi)


pos_int = int_range(1, MAX_COUNT, "pos_int")
count_int = int_range(0, MAX_COUNT, "count_int")
nonneg_int = int_range(0, MAX_SEED, "nonneg_int")
severity_arg = int_range(0, 5, "severity_arg")
workers_int = int_range(1, MAX_WORKERS, "workers_int")
"""Processes of a pool (generate, theory, study, the benches): 1..MAX_WORKERS."""
loader_workers_int = int_range(0, MAX_WORKERS, "loader_workers_int")
"""DataLoader processes decoding frames (train, evaluate, compare, train-gate, ...): 0 decodes in the
main process; the same bound as every other worker count."""
bootstrap_int = int_range(0, MAX_BOOTSTRAP, "bootstrap_int")


def float_range(lo: float, hi: float, name: str, lo_open: bool = False) -> Callable[[str], float]:
    """An argparse type: a finite number in [lo, hi] ((lo, hi] with lo_open)."""

    def parse(text: str) -> float:
        try:
            v = float(str(text).strip())
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not math.isfinite(v):
            raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
        if v < lo or (lo_open and v == lo):
            raise argparse.ArgumentTypeError(f"must be {'>' if lo_open else '>='} {lo:g}, got {v:g}")
        if v > hi:
            raise argparse.ArgumentTypeError(f"must be <= {hi:g}, got {v:g}")
        return v

    parse.__name__ = name
    return _typed(parse, "float", lo=lo, hi=hi, lo_open=lo_open)


pos_float = float_range(0.0, 1e9, "pos_float", lo_open=True)
nonneg_float = float_range(0.0, 1e9, "nonneg_float")
probability = float_range(0.0, 1.0, "probability")


def holdout_fraction(text: str) -> float:
    """An argparse type: the share of data held out, a number in [0, 1)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not 0.0 <= v < 1.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 1), got {v}")
    return v


def open_fraction(text: str) -> float:
    """An argparse type: a share strictly between 0 and 1 (a split with something on both sides)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not 0.0 < v < 1.0:
        raise argparse.ArgumentTypeError(f"must be in (0, 1), got {text}")
    return v


_typed(open_fraction, "float", lo=0.0, hi=1.0, lo_open=True)


def pool_grid(text: str) -> tuple[int, int]:
    """An argparse type: the ROWSxCOLS grid stem features are pooled to (`8x16`), at least 4x4."""
    try:
        rows, cols = (int(t) for t in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected ROWSxCOLS such as 8x16, got {text!r}") from None
    if rows < 4 or cols < 4:
        raise argparse.ArgumentTypeError(f"grid must be at least 4x4, got {text!r}")
    return rows, cols


def name_list(text: str) -> tuple[str, ...]:
    """A comma-separated list of names: no empty items, no name twice, no dangling '+' in a combination
    ("rain+", "+fog", "city++rain"). Whether each name exists is the command's check."""
    items = [t.strip() for t in str(text).split(",")]
    if not any(items):
        raise argparse.ArgumentTypeError("expected one name or more, separated by commas, got nothing")
    for item in items:
        if not item:
            raise argparse.ArgumentTypeError(f"empty item in {text!r} (names are separated by single commas)")
        parts = item.split("+")
        if len(parts) > 1 and not all(p.strip() for p in parts):
            raise argparse.ArgumentTypeError(f"dangling '+' in {item!r} (combine names as in city+night+rain)")
    seen = set()
    for item in items:
        if item in seen:
            raise argparse.ArgumentTypeError(f"{item!r} is named twice in {text!r}")
        seen.add(item)
    return tuple(items)


_typed(name_list, "names")


def fusion_arg(text: str) -> str:
    """A late-fusion method of `fusion.boxes.FUSION_METHODS` by its name or label, as its label
    ("soft-nms"); the registry is read only when a value is parsed (its kernels load slowly)."""
    from fusion.boxes import method_label

    try:
        return method_label(str(text).strip())
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


FUSION_HELP = "a late-fusion method of fusion.boxes by its label (nms, soft-nms and wbf are the paper's)"


def name_arg(text: str) -> str:
    """One name (a profile, a condition, a combination such as city+night+rain): not empty, no comma,
    no dangling '+'. Whether it exists is the command's check."""
    text = str(text).strip()
    if not text:
        raise argparse.ArgumentTypeError("expected a name, got nothing")
    if "," in text:
        raise argparse.ArgumentTypeError(f"expected one name, got a list {text!r}")
    if not all(p.strip() for p in text.split("+")):
        raise argparse.ArgumentTypeError(f"dangling '+' in {text!r} (combine names as in city+night+rain)")
    return text


_typed(name_arg, "name")


def int_list(lo: int, hi: int, name: str) -> Callable[[str], tuple[int, ...]]:
    """A comma-separated list of integers in [lo, hi], none twice."""
    one = int_range(lo, hi, name)

    def parse(text: str) -> tuple[int, ...]:
        items = name_list(text)
        values = tuple(one(t) for t in items)
        if len(set(values)) != len(values):
            raise argparse.ArgumentTypeError(f"a value is given twice in {text!r}")
        return values

    parse.__name__ = name
    return _typed(parse, "ints", lo=lo, hi=hi)


def _path_text(text: str) -> str:
    if not str(text).strip():
        raise argparse.ArgumentTypeError("expected a path, got an empty string")
    if "\x00" in str(text):
        raise argparse.ArgumentTypeError("a path cannot contain a NUL character")
    from study.outputs import path_problem

    problem = path_problem(str(text))
    if problem:
        raise argparse.ArgumentTypeError(problem)
    return str(text)


def _as_type_error(func, *args):
    try:
        return func(*args)
    except UserError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


IMAGE_SUFFIXES = (".png", ".pdf", ".svg")


def out_file(*suffixes: str) -> Callable[[str], str]:
    """An argparse type: a file to write (extension one of `suffixes` when given), whose directory
    exists or can be created. Nothing is created here: the command creates it when it writes."""

    def parse(text: str) -> str:
        from study.outputs import check_writable_file

        return str(_as_type_error(check_writable_file, _path_text(text), suffixes or None))

    parse.__name__ = "out_file"
    return _typed(parse, "out_file", suffixes=suffixes)


def out_dir(text: str) -> str:
    """An argparse type: a directory to write into (existing, or creatable; not created here)."""
    from study.outputs import check_writable_dir

    return str(_as_type_error(check_writable_dir, _path_text(text)))


_typed(out_dir, "out_dir")


def out_path(text: str) -> str:
    """An argparse type: a file or a directory to write, checked by the command (it depends on other options)."""
    return _path_text(text)


_typed(out_path, "out_path")


def in_file(text: str) -> str:
    """An argparse type: an existing readable file."""
    path = Path(_path_text(text))
    if not path.is_file():
        raise argparse.ArgumentTypeError(f"{text} is not a file" if path.exists() else f"{text} does not exist")
    return str(path)


_typed(in_file, "in_file")


def cache_dir(text: str) -> str:
    """An argparse type: a cache directory (existing, or creatable; not created here). Unlike an
    output directory it may hold other files."""
    from study.outputs import check_writable_dir

    return str(_as_type_error(check_writable_dir, _path_text(text)))


_typed(cache_dir, "cache_dir")


def checkpoint_arg(text: str) -> str:
    """An argparse type: which checkpoint of a run, 'latest' or 'epoch-NNN'."""
    import re

    if not re.fullmatch(r"latest|epoch-\d{3,}", str(text).strip()):
        raise argparse.ArgumentTypeError(f"expected 'latest' or 'epoch-NNN' (e.g. epoch-003), got {text!r}")
    return str(text).strip()


_typed(checkpoint_arg, "checkpoint")


def dataset_path(text: str) -> str:
    """An argparse type: a dataset directory that the command itself examines (hydrabench verify)."""
    return _path_text(text)


_typed(dataset_path, "dataset", checked=False)


def dataset_dir(text: str) -> str:
    """An argparse type: a dataset directory, checked whole before any work (`sensors.dataset.check`:
    manifest, every shard's frames.json and array headers; not the checksums, which is `verify`)."""
    from sensors.dataset import check

    _as_type_error(check, _path_text(text))
    return str(text)


_typed(dataset_dir, "dataset", checked=True)


def predictions_dir(text: str) -> str:
    """An argparse type: a predictions directory (hydrabench predict --out), its manifest readable."""
    path = Path(_path_text(text))
    if not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is not a directory" if path.exists() else f"{text} does not exist")
    from study.engine.predictions import FORMAT

    try:
        fmt = json.loads((path / "manifest.json").read_text()).get("format")
    except (OSError, ValueError, AttributeError):
        fmt = None
    if fmt != FORMAT:
        raise argparse.ArgumentTypeError(f"{text} is not a predictions directory (no {FORMAT} manifest.json; see "
                                         "hydrabench predict)")
    return str(path)


_typed(predictions_dir, "predictions")


def training_run(text: str) -> str:
    """An argparse type: a training run directory (hydrabench train --out), or a reference model
    (`study.engine.reference_model`: a name in models/ or its directory), checked against its manifest and
    copied into its cache run, whose path is returned."""
    from study.engine.reference_model import resolve_run

    path = Path(_as_type_error(resolve_run, _path_text(text)))
    if not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is not a directory" if path.exists() else f"{text} does not exist")
    if not (path / "config.json").is_file():
        raise argparse.ArgumentTypeError(f"{text} is not a training run (no config.json; see hydrabench train)")
    from study.engine.checkpoints import checkpoint_problem

    for ckpt in sorted(path.glob("*.pt")):  # checkpoint.pt and epoch-NNN.pt: whole, before any work
        problem = checkpoint_problem(ckpt)
        if problem:
            raise argparse.ArgumentTypeError(f"{ckpt} {problem}")
    return str(path)


_typed(training_run, "run")


def study_config(text: str):
    """An argparse type: a study preset name (configs/study/<name>.yaml) or a YAML file of
    `study.pipeline.config.StudyConfig` fields, loaded and checked whole (unknown keys, bad values)."""
    from study.pipeline.presets import study_config_file

    path = _as_type_error(study_config_file, _path_text(text))  # (torch-free: a typo is refused at once)
    from study.pipeline.config import load_study_config

    return _as_type_error(load_study_config, str(path))


_typed(study_config, "study_config")


def module_doc(name: str) -> str:
    """The docstring of module `name`, read from its source without importing it: a command's help can
    quote its experiment's docstring without importing what the experiment imports (torch)."""
    import ast
    import importlib.util

    spec = importlib.util.find_spec(name)
    return ast.get_docstring(ast.parse(Path(spec.origin).read_text()), clean=False) or ""


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
    "scenes": ("study.commands.scenes:add_parser", "simulate scenes of a context, summarise and draw them top-down"),
    "generate": ("study.commands.dataset:add_generate", "generate a sharded sensor dataset (cameras, lidar, radar, labels)"),
    "verify": ("study.commands.dataset:add_verify", "check a dataset whole: what every command checks first, and each shard's checksum"),
    "export-coco": ("study.commands.dataset:add_export", "write a dataset's FWD labels as COCO JSON"),
    "export": ("study.commands.export:add_parser", "write a dataset in another tool's format: nuscenes (every sensor, "
               "3D boxes, splits; the nuScenes devkit loads it) or coco (one camera's FWD labels)"),
    "labels": ("study.commands.labels:add_parser", "what each evaluation protocol asks a detector to find (counts per range bin)"),
    "stages": ("study.commands.stages:add_parser", "a digest of every generation stage for one frame, to compare two machines"),
    "show": ("study.commands.dataset:add_show", "draw one frame of a dataset with every sensor and its labels"),
    "gallery": ("study.commands.gallery:add_parser", "one scene under every condition and severity, all sensors side by side"),
    "theory": ("study.commands.theory:add_parser", "HydraFusion Sec. 1.1 measured: single sensors vs full, selective and gated fusion per weather"),
    "train": ("study.commands.train:add_parser", "train HydraFusion stems and branches (resumable, per-epoch CSV and checkpoints)"),
    "evaluate": ("study.commands.evaluate:add_parser", "VOC mAP@0.5 of a run's branches fused in the right camera (per class, per context)"),
    "train-gate": ("study.commands.train_gate:add_train_gate", "train the deep or attention gate on a run's stem features and branch losses"),
    "eco-data": ("study.commands.eco:add_eco_data", "EcoFusion: per-frame stem features and fused loss / AP of every branch configuration"),
    "eco-energy": ("study.commands.eco:add_eco_energy", "EcoFusion: measured stem / branch / fusion latency and energy of every configuration"),
    "eco-train-gate": ("study.commands.eco:add_eco_train_gate", "EcoFusion: train the deep or attention configuration gate"),
    "eco-evaluate": ("study.commands.eco:add_eco_evaluate", "EcoFusion at one lambda_E and gamma: mAP, loss, energy, latency per gate"),
    "eco-sweep": ("study.commands.eco:add_eco_sweep", "EcoFusion Tables 1-3 and Figures 4-5 over a lambda_E sweep"),
    "predict": ("study.commands.predict:add_parser", "run a model once over a dataset and keep every branch's "
                "detections, losses and gate inputs (the predictions every score reads)"),
    "pem": ("study.commands.pem:add_parser", "perception error models fitted on a model's predictions: fit, draw "
            "predictions compare scores (detector strength as a knob), check against the network"),
    "compare": ("study.commands.compare:add_parser", "selective (gated) against fixed fusion on one dataset, with intervals"),
    "score": ("study.commands.score:add_parser", "score detections and per-frame selections made outside hydrabench "
              "(nuScenes or COCO results) as compare scores the own networks"),
    "model": ("study.commands.model:add_parser", "reference models: export a trained run (float16, gates, manifest), list them"),
    "study": ("study.commands.study:add_parser", "the whole HydraFusion + EcoFusion study as cached, resumable stages, "
              "and its report"),
    "bench": ("study.commands.bench:add_parser", "measure throughput (sim, generate, ...) and print the figures"),
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


EXIT_TERMINATED = 128 + 15
"""The exit code of a command stopped by SIGTERM (the shell's code for a process killed by it)."""
DISK_FULL = (errno.ENOSPC, errno.EDQUOT)


@contextlib.contextmanager
def _terminate_as_interrupt():
    """SIGTERM raises `Terminated` (a KeyboardInterrupt) in the main thread while a command runs, so
    `kill` cleans up as Ctrl-C does; Python's default SIGTERM exits at once and runs no clean-up (a
    pool's workers were left to finish their shards, the lock file stayed). Not under torchrun, whose
    agent stops its ranks with SIGTERM then SIGKILL (a rank waiting in a collective would not run a
    Python handler), nor outside the main thread, nor where SIGTERM is ignored."""
    if (threading.current_thread() is not threading.main_thread() or "TORCHELASTIC_RUN_ID" in os.environ
            or signal.getsignal(signal.SIGTERM) is signal.SIG_IGN):
        yield
        return

    def handler(signum, frame):
        raise Terminated

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def _home_from_passwd() -> None:
    """An empty or relative HOME: the account's home directory from the password database instead
    (what Python uses when HOME is unset), so that nothing (hydrabench's cache, matplotlib's) lands in
    /.cache at the file system's root or in a folder relative to where the command runs."""
    home = os.environ.get("HOME")
    if home is None or os.path.isabs(home):
        return
    try:
        import pwd

        entry = pwd.getpwuid(os.getuid()).pw_dir
    except (ImportError, KeyError):
        return
    if os.path.isabs(entry):
        os.environ["HOME"] = entry


def main(argv: list[str] | None = None, parser: Parser | None = None) -> int:
    """Run one command; `parser`: a `build_parser()` to reuse (tests calling main many times)."""
    _home_from_passwd()
    try:
        with _terminate_as_interrupt():
            parser = parser or build_parser()
            args = parser.parse_args(argv)
            return int(args.run(args) or 0)
    except UserError as exc:
        msg = str(exc).splitlines()[0] if str(exc) else "invalid input"
        sys.stderr.write(f"hydrabench: error: {msg}\n")
        return EXIT_USAGE
    except Terminated:
        sys.stderr.write("hydrabench: terminated\n")
        return EXIT_TERMINATED
    except KeyboardInterrupt:
        sys.stderr.write("hydrabench: interrupted\n")
        return 130
    except BrokenPipeError:
        return 0
    except OSError as exc:
        if exc.errno not in DISK_FULL:
            raise
        where = f" writing {exc.filename}" if exc.filename else ""
        sys.stderr.write(f"hydrabench: error: {exc.strerror or 'no space left on device'}{where}: free some space and "
                         "run the command again\n")
        return EXIT_USAGE


if __name__ == "__main__":
    sys.exit(main())
