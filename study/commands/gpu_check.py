"""`scripts/gpu_check.sh`: the command line of the one-GPU check (`study.bench.gpu_check` measures;
this prints its JSON summary on stdout, progress on stderr, and exits 2 on bad input)."""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

from study.bench import gpu_check


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="gpu_check", description=gpu_check.__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", default=None, help="directory for the dataset and the run (default: a temporary one, "
                    "removed at the end)")
    ap.add_argument("--frames-per-context", type=int, default=None, help="dataset size (default 4)")
    ap.add_argument("--steps", type=int, default=None, help="training steps of the seven-branch network "
                    "(default 20 on a GPU, 2 on the CPU)")
    ap.add_argument("--cpu", action="store_true", help="run the CPU version even where a GPU is present")
    args = ap.parse_args(argv)
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    os.environ["SDL_VIDEODRIVER"] = "offscreen"
    from sim.errors import UserError

    try:
        if args.work:
            work = Path(args.work)
            work.mkdir(parents=True, exist_ok=True)
            summary = gpu_check.run_check(work, args.frames_per_context, args.steps, args.cpu)
        else:
            with tempfile.TemporaryDirectory(prefix="hydrabench-gpu-check-") as tmp:
                summary = gpu_check.run_check(Path(tmp), args.frames_per_context, args.steps, args.cpu)
    except UserError as exc:
        sys.stderr.write(f"gpu_check: error: {str(exc).splitlines()[0]}\n")
        return 2
    sys.stdout.write(json.dumps(summary) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
