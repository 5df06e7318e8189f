"""`hydrabench bench <what>`: throughput measurements. Figures go to BENCHMARKS.md by hand,
with the command that produced them; nothing here asserts a time."""

from __future__ import annotations

import os
import platform
import time

from study.cli import Formatter, emit, pos_int


def machine() -> dict:
    return {"cores": os.cpu_count(), "machine": platform.machine(), "python": platform.python_version()}


def add_parser(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=help_text, formatter_class=Formatter)
    what = p.add_subparsers(dest="what", metavar="<what>", parser_class=type(p))
    what.required = True
    s = what.add_parser("sim", help="scene steps per second per context (one core)",
                        description="Simulate each context for --frames frames after its setup and "
                        "report steady-state scene steps per second (one process, one core).",
                        formatter_class=Formatter)
    s.add_argument("--frames", type=pos_int, default=200, help="recorded frames per context")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    s.set_defaults(run=run_sim)


def run_sim(args) -> int:
    from tqdm import tqdm

    from sim.scenario import CONTEXT_NAMES, Context, ScenarioSpec, Simulator

    per_ctx, setup = {}, {}
    for c in tqdm(CONTEXT_NAMES, desc="bench sim", file=__import__("sys").stderr, disable=None):
        sev = 3 if Context.parse(c).conditions else 0
        t0 = time.perf_counter()
        sim = Simulator(ScenarioSpec(context=c, severity=sev, seed=args.seed, frames=args.frames))
        t1 = time.perf_counter()
        n = sum(1 for _ in sim.scenes())
        t2 = time.perf_counter()
        per_ctx[c] = round(n / (t2 - t1), 1)
        setup[c] = round(t1 - t0, 3)
    result = {
        "scenes_per_second": per_ctx,
        "setup_seconds": setup,
        "frames": args.frames,
        "min_scenes_per_second": min(per_ctx.values()),
        **machine(),
    }
    emit(result, args.json, lambda r: "\n".join(
        [f"{c:9s} {v:8.1f} scenes/s  (setup {r['setup_seconds'][c]:.2f} s incl. warm-up)"
         for c, v in r["scenes_per_second"].items()]))
    return 0
