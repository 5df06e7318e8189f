"""`hydrabench bench generate`: full frames per second of `generate`, also against other checkouts (`study.bench.pipeline`)."""

from __future__ import annotations

import argparse

from study.cli import (
    MAX_WORKERS,
    Formatter,
    emit,
    int_list,
    int_range,
    name_list,
    nonneg_int,
    pos_int,
)


def add_parser(what) -> None:
    g = what.add_parser("generate", help="full frames per second (cameras, lidar, radar, labels, degradation)",
                        description="Generate a temporary dataset over every context for each profile and "
                        "worker count, and report frames per second plus milliseconds per pipeline component "
                        "and per degradation model (summed over workers, per rendered frame).",
                        formatter_class=Formatter)
    g.add_argument("--profiles", type=name_list, default="cpu,paper", help="comma-separated sensor profiles, each once")
    g.add_argument("--workers", type=int_list(1, MAX_WORKERS, "workers"), default="1,2", help="comma-separated worker counts, each once")
    g.add_argument("--contexts", type=name_list, default=("all",),
                   help="'all' or comma-separated contexts/combinations of each run's dataset, each once [all]")
    g.add_argument("--frames-per-context", type=pos_int, default=10, help="frames per context per run")
    g.add_argument("--sequence-length", type=pos_int, default=10, help="frames per sequence (setup is amortised over it)")
    g.add_argument("--seed", type=nonneg_int, default=0, help="root random seed")
    g.add_argument("--start-methods", type=start_methods_arg, default="auto",
                   help="comma-separated ways the worker pool starts its processes, each once: auto (fork "
                   "unless this process has rendered), fork, spawn; with two or more, ratios of frames/s "
                   "against the first are reported")
    g.add_argument("--rounds", type=int_range(1, 100, "rounds"), default=1,
                   help="repeat every combination this many times, in turn (A B A B), so that drifting "
                   "machine speed slows each alike")
    g.add_argument("--twins", action="store_true",
                   help="also render each frame's clear-weather twin, as the study presets do (frames/s counts a "
                   "frame and its twin once)")
    g.add_argument("--against", type=checkouts_arg, default=(), metavar="DIR[,DIR]",
                   help="compare with other hydrabench checkouts (e.g. `git worktree add /tmp/old COMMIT`): "
                   "every run is then `python -m study.cli generate --contexts ... --json` from each checkout "
                   "in turn (this code first) for --rounds rounds; reports each one's median frames/s, this "
                   "code's ratio to it, and whether its dataset had the same bytes")
    g.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    g.set_defaults(run=run_generate)


def start_methods_arg(text: str) -> tuple:
    """An argparse type: comma-separated pool start methods (auto, fork, spawn), each once; auto -> None."""
    import multiprocessing as mp

    items = name_list(text)
    known = ["auto", *(m for m in ("fork", "spawn") if m in mp.get_all_start_methods())]
    bad = [m for m in items if m not in known]
    if bad:
        raise argparse.ArgumentTypeError(f"unknown start method {bad[0]!r} (choose from: {', '.join(known)})")
    return tuple(None if m == "auto" else m for m in items)


start_methods_arg.kind = "names"


def checkouts_arg(text: str) -> tuple:
    """An argparse type: comma-separated directories of other hydrabench checkouts, each once."""
    items = tuple(t.strip() for t in text.split(","))
    if not all(items):
        raise argparse.ArgumentTypeError(f"expected directories separated by commas, got {text!r}")
    if len(set(items)) != len(items):
        raise argparse.ArgumentTypeError(f"{text!r} names a directory twice")
    return items


checkouts_arg.kind = "names"


def run_generate(args) -> int:
    from study.bench.pipeline import bench_generate

    if args.against:
        return _run_generate_against(args)
    result = bench_generate(profiles=args.profiles, workers=args.workers, frames_per_context=args.frames_per_context,
                            sequence_length=args.sequence_length, seed=args.seed, start_methods=args.start_methods,
                            rounds=args.rounds, twins=args.twins, contexts=args.contexts)

    def text(r):
        lines = [f"{x['profile']:6s} workers {x['workers']} ({x['start_method']}, round {x['round'] + 1}): "
                 f"{x['frames_per_second']} frames/s ({x['frames']} frames in {x['seconds']} s)" for x in r["runs"]]
        for key, ratio in r["ratios"].items():
            lines.append(f"{key} frames/s relative to {next(iter(ratio))}: "
                         + ", ".join(f"{m} {v}" for m, v in ratio.items()))
        for p, ms in r["ms_per_component"].items():
            lines.append(f"{p} ms per frame: " + ", ".join(f"{k} {v}" for k, v in ms.items() if not k.startswith("degrade/")))
            d = r["degradation"][p]
            lines.append(f"{p} degradation {d['ms_total']} ms ({d['share_of_frame']} of a frame): "
                         + ", ".join(f"{k} {v}" for k, v in d["ms_per_model"].items()))
        return "\n".join(lines)

    emit(result, args.json, text)
    return 0


def _run_generate_against(args) -> int:
    import sys

    from sim.errors import UserError
    from study.bench.pipeline import bench_generate_against, checkout_of

    if args.start_methods != (None,):
        raise UserError("--against compares checkouts with their default start method; leave out --start-methods")
    for c in args.against:
        checkout_of(c)  # a wrong directory is refused before the first run

    def progress(x):
        print(f"bench generate: round {x['round'] + 1}/{args.rounds} {x['profile']} workers {x['workers']} "
              f"{x['commit'] or x['dir']}: {x['frames_per_second']} frames/s ({x['frames']} frames in "
              f"{x['seconds']} s)", file=sys.stderr, flush=True)

    result = bench_generate_against(args.against, profiles=args.profiles, workers=args.workers,
                                    frames_per_context=args.frames_per_context, sequence_length=args.sequence_length,
                                    seed=args.seed, rounds=args.rounds, twins=args.twins, progress=progress,
                                    contexts=args.contexts)

    def text(r):
        names = {s["dir"]: s["commit"] or s["dir"] for s in [r["this"], *r["against"]]}
        lines = [f"round {x['round'] + 1} {x['profile']} workers {x['workers']} {names[x['dir']]}: "
                 f"{x['frames_per_second']} frames/s ({x['frames']} frames in {x['seconds']} s)"
                 + ("" if x["dir"] == r["this"]["dir"] else f", same bytes: {x['same_bytes']}") for x in r["runs"]]
        for key, ratio in r["ratios"].items():
            lines.append(f"{key}: this code ({names[r['this']['dir']]}) frames/s over "
                         + ", ".join(f"{names[d]}'s: {v}" for d, v in ratio.items()) + " (medians)")
        return "\n".join(lines)

    emit(result, args.json, text)
    return 0
