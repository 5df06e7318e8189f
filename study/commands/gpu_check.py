"""`scripts/gpu_check.sh`: the command line of the one-GPU check (`study.bench.gpu_check` measures;
this prints its JSON summary on stdout, writes it to --json after every step, progress on stderr).
Every failure is one line on stderr (exit 2 for bad input, 1 otherwise, 124 when the time budget
ran out), and the JSON then holds what was measured before it and the error."""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import tempfile
import time
import traceback
from pathlib import Path

from study.bench import gpu_check


def _write(path: Path | None, summary: dict) -> None:
    if path is None:
        return
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(summary, indent=1) + "\n")
    os.replace(tmp, path)


def _where(exc: BaseException) -> str:
    """The innermost frame of our own code (or the last one) where `exc` was raised: "file:line"."""
    frames = traceback.extract_tb(exc.__traceback__)
    root = str(Path(__file__).resolve().parents[2])
    ours = [f for f in frames if f.filename.startswith(root)] or frames
    return f"{os.path.relpath(ours[-1].filename, root)}:{ours[-1].lineno}" if ours else "?"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="gpu_check", description=gpu_check.__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", default=None, help="keep the dataset and the run under this directory, in a new "
                    "attempt-* folder per call (a rerun times generation and training again instead of resuming an "
                    "earlier attempt's); default: a temporary directory, removed at the end")
    ap.add_argument("--frames-per-context", type=int, default=None, help="dataset size (default 2 on a GPU, 4 on "
                    "the CPU)")
    ap.add_argument("--contexts", default=None, help="comma-separated contexts (default: all on a GPU, junction,fog "
                    "on the CPU)")
    ap.add_argument("--steps", type=int, default=None, help="timed training steps of the seven-branch network "
                    "(default 20 on a GPU, 2 on the CPU)")
    ap.add_argument("--device", choices=["auto", "cpu"], default="auto", help="auto: the first CUDA GPU if torch "
                    "sees one; cpu: the CPU version even where a GPU is present")
    ap.add_argument("--cpu", action="store_true", help="the same as --device cpu")
    ap.add_argument("--parts", default=",".join(gpu_check.PARTS), help="which steps: comma-separated of "
                    f"{', '.join(gpu_check.PARTS)} (the probes always run)")
    ap.add_argument("--json", default=None, metavar="FILE", help="also write the summary here, after every step")
    ap.add_argument("--budget-s", type=float, default=300.0, help="stop after this many seconds, the JSON holding "
                    "what was measured (0: no limit)")
    args = ap.parse_args(argv)
    for name in ("frames_per_context", "steps"):
        if getattr(args, name) is not None and getattr(args, name) < 1:
            ap.error(f"--{name.replace('_', '-')} must be >= 1")
    if not args.budget_s >= 0:
        ap.error("--budget-s must be >= 0")
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    os.environ["SDL_VIDEODRIVER"] = "offscreen"
    from sim.errors import UserError

    out = Path(args.json) if args.json else None
    parts = tuple(p.strip() for p in args.parts.split(",") if p.strip())
    latest: dict = {}

    def update(summary: dict) -> None:
        if work is not None:
            summary["work"] = str(work)
        latest.clear()
        latest.update(summary)
        _write(out, summary)

    def on_alarm(signum, frame):
        raise gpu_check.TimeBudgetExceeded(f"the time budget of {args.budget_s:g} s ran out")

    previous = signal.signal(signal.SIGALRM, on_alarm) if args.budget_s > 0 else None
    if args.budget_s > 0:
        signal.setitimer(signal.ITIMER_REAL, args.budget_s)
    force_cpu = args.cpu or args.device == "cpu"
    work = None
    try:
        if args.work:
            Path(args.work).mkdir(parents=True, exist_ok=True)
            work = Path(tempfile.mkdtemp(prefix=f"attempt-{time.strftime('%Y%m%d-%H%M%S')}-", dir=args.work))
            sys.stderr.write(f"[gpu_check] this attempt's files: {work}\n")
            summary = gpu_check.run_check(work, args.frames_per_context, args.steps, force_cpu, parts, args.contexts,
                                          on_update=update)
        else:
            with tempfile.TemporaryDirectory(prefix="hydrabench-gpu-check-") as tmp:
                summary = gpu_check.run_check(Path(tmp), args.frames_per_context, args.steps, force_cpu, parts,
                                              args.contexts, on_update=update)
    except Exception as exc:  # one line, never a traceback (UserError, the budget, anything else)
        code = 2 if isinstance(exc, UserError) else 124 if isinstance(exc, gpu_check.TimeBudgetExceeded) else 1
        message = (str(exc).splitlines() or [""])[0]
        done = latest.get("completed", [])
        latest["error"] = {"type": type(exc).__name__, "message": message, "where": _where(exc),
                           "after": done[-1] if done else None}
        _write(out, latest)
        sys.stderr.write(f"gpu_check: error{' after ' + done[-1] if done else ''}: {type(exc).__name__}: {message} "
                         f"({_where(exc)})\n")
        return code
    finally:
        if args.budget_s > 0:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, previous)
    _write(out, summary)
    sys.stdout.write(json.dumps(summary) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
