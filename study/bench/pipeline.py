"""Pipeline throughput (`hydrabench bench sim`, `hydrabench bench generate`): scene steps per
second of the simulator, and full generated frames per second with milliseconds per pipeline
component and per degradation model. Figures go to BENCHMARKS.md by hand, with the command that
produced them; nothing here asserts a time."""

from __future__ import annotations

import os
import platform
import time


def machine() -> dict:
    """The machine a figure was measured on (recorded with every bench result)."""
    return {"cores": os.cpu_count(), "machine": platform.machine(), "python": platform.python_version()}


def bench_sim(frames: int = 200, seed: int = 0) -> dict:
    """Simulate each context for `frames` frames after its setup (severity 3 for conditions, 0 for
    layouts) and report steady-state scene steps per second (one process, one core) and the setup
    time of each context."""
    from sim.progress import progress
    from sim.scenario import CONTEXT_NAMES, Context, ScenarioSpec, Simulator

    per_ctx, setup = {}, {}
    for c in progress(iterable=CONTEXT_NAMES, desc="bench sim", unit="context"):
        sev = 3 if Context.parse(c).conditions else 0
        t0 = time.perf_counter()
        sim = Simulator(ScenarioSpec(context=c, severity=sev, seed=seed, frames=frames))
        t1 = time.perf_counter()
        n = sum(1 for _ in sim.scenes())
        t2 = time.perf_counter()
        per_ctx[c] = round(n / (t2 - t1), 1)
        setup[c] = round(t1 - t0, 3)
    return {
        "scenes_per_second": per_ctx,
        "setup_seconds": setup,
        "frames": frames,
        "min_scenes_per_second": min(per_ctx.values()),
        **machine(),
    }


def _in_fresh_child(fn, *args, **kwargs):
    """`fn(*args, **kwargs)` in a forked child of this process, its result sent back.

    A process that has rendered spawns its generation workers instead of forking them
    (`sensors.generate.worker_start_method`), and a one-worker run renders in the calling process;
    so each run of a bench goes to its own child, forked from this process before it has rendered,
    and every run measures what `hydrabench generate` would. Where fork is unavailable or this
    process has rendered already, the call runs here."""
    import multiprocessing as mp
    import traceback

    from sensors.generate import worker_start_method

    if worker_start_method() != "fork":
        return fn(*args, **kwargs)
    ctx = mp.get_context("fork")
    receive, send = ctx.Pipe(duplex=False)

    def target():
        try:
            send.send(("ok", fn(*args, **kwargs)))
        except BaseException as e:  # noqa: BLE001 - reported in the parent
            send.send(("error", f"{type(e).__name__}: {e}\n{traceback.format_exc()}"))

    child = ctx.Process(target=target, daemon=False)
    child.start()
    send.close()
    try:
        status, value = receive.recv()
    except EOFError:
        child.join()
        raise RuntimeError(f"the bench's child process died (exit code {child.exitcode})") from None
    child.join()
    if status != "ok":
        raise RuntimeError(f"the bench's child process failed: {value}")
    return value


def _contexts(contexts) -> list[str]:
    """A `--contexts` value as `GenerateConfig` takes it: ("all",) -> the eight contexts."""
    from sim.scenario import CONTEXT_NAMES

    return list(CONTEXT_NAMES) if tuple(contexts) == ("all",) else list(contexts)


def bench_generate(profiles=("cpu", "paper"), workers=(1, 2), frames_per_context: int = 10,
                   sequence_length: int = 10, seed: int = 0, start_methods=(None,), rounds: int = 1,
                   twins: bool = False, contexts=("all",)) -> dict:
    """Generate a temporary dataset over `contexts` (default every context) for each profile, worker count and start
    method of the worker pool (None: `sensors.generate.worker_start_method()`, "fork", "spawn"):
    frames per second, and (at the first worker count and method, first round) milliseconds per
    pipeline component and per degradation model, summed over workers, per rendered frame.

    `rounds` > 1 repeats every combination in turn (A B A B ...), so that a machine whose speed
    drifts slows each alike; `ratios` gives, per profile and worker count, each method's median
    frames/s over the first method's. `twins`: also render every frame's clear twin (as the study
    presets do); frames/s then counts each frame once, its twin included."""
    import statistics
    import tempfile

    from sensors.generate import GenerateConfig, generate

    profiles, workers, start_methods = list(profiles), list(workers), list(start_methods)
    if rounds < 1:
        raise ValueError(f"rounds must be >= 1, got {rounds}")
    chosen = _contexts(contexts)
    configs = {profile: GenerateConfig(contexts=chosen, frames_per_context=frames_per_context,
                                       sequence_length=sequence_length, seed=seed, profile=profile, twins=twins)
               for profile in profiles}  # all valid first
    runs, components = [], {}
    for round_ in range(rounds):
        for profile in profiles:
            for w in workers:
                for method in start_methods:
                    config = configs[profile]
                    with tempfile.TemporaryDirectory(prefix="hydrabench-bench-") as tmp:
                        r = _in_fresh_child(generate, config, tmp, workers=w, progress=True, start_method=method)
                    runs.append({"round": round_, "profile": profile, "workers": w, "requested": method or "auto",
                                 "start_method": r.get("start_method", "none (one process)"),
                                 "frames": r["frames"], "seconds": r["seconds"],
                                 "frames_per_second": r["frames_per_second"]})
                    if round_ == 0 and w == workers[0] and method == start_methods[0]:
                        components[profile] = r["ms_per_frame"]
    ratios = {}
    if len(start_methods) > 1:
        for profile in profiles:
            for w in workers:
                med = {}
                for method in start_methods:
                    got = [x for x in runs if x["profile"] == profile and x["workers"] == w
                           and x["requested"] == (method or "auto")]
                    med[method or "auto"] = statistics.median(x["frames_per_second"] for x in got) if got else None
                first = med[start_methods[0] or "auto"]
                ratios[f"{profile}/{w}"] = {m: (round(v / first, 3) if v and first else None) for m, v in med.items()}
    degradation = {}
    for profile, ms in components.items():
        total = sum(v for k, v in ms.items() if not k.startswith("degrade/") and k != "degradation")
        total += ms.get("degradation", 0.0)
        degradation[profile] = {
            "ms_per_model": {k.split("/", 1)[1]: v for k, v in ms.items() if k.startswith("degrade/")},
            "ms_total": ms.get("degradation", 0.0),
            "share_of_frame": round(ms.get("degradation", 0.0) / total, 3) if total else None,
        }
    return {"runs": runs, "ratios": ratios, "ms_per_component": components, "degradation": degradation,
            "frames_per_context": frames_per_context, "sequence_length": sequence_length, "rounds": rounds,
            "twins": twins, "contexts": chosen,
            **machine()}


def checkout_of(path) -> dict:
    """A source checkout of hydrabench to run `generate` from: {"dir", "commit"} (commit None when
    the directory is not a git work tree). Raises UserError when it holds no `study/cli.py`."""
    import subprocess
    from pathlib import Path

    from sim.errors import UserError

    root = Path(path).expanduser().resolve()
    if not (root / "study" / "cli.py").is_file():
        raise UserError(f"{path}: not a hydrabench checkout (no study/cli.py there)")
    git = subprocess.run(["git", "-C", str(root), "rev-parse", "--short=12", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True)
    commit = git.stdout.strip() if git.returncode == 0 else None
    if commit and dirty.returncode == 0 and dirty.stdout.strip():
        commit += "+changes"
    return {"dir": str(root), "commit": commit}


def dataset_digest(root) -> str:
    """sha256 over every file of a dataset (relative path and bytes, in path order): equal digests =
    byte-identical datasets."""
    import hashlib
    from pathlib import Path

    root = Path(root)
    h = hashlib.sha256()
    for f in sorted(p for p in root.rglob("*") if p.is_file()):
        h.update(str(f.relative_to(root)).encode() + b"\0")
        with open(f, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


def _generate_from(checkout: dict, out: str, profile: str, workers: int, frames_per_context: int,
                   sequence_length: int, seed: int, twins: bool, timeout_s: float, contexts=("all",)) -> dict:
    """`python -m study.cli generate ... --json` run from a checkout (its code first on sys.path)."""
    import json
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "study.cli", "generate", "--out", out, "--contexts", ",".join(contexts),
           "--frames-per-context", str(frames_per_context), "--sequence-length", str(sequence_length),
           "--seed", str(seed), "--profile", profile, "--workers", str(workers), "--json"]
    if twins:
        cmd.append("--twins")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    run = subprocess.run(cmd, cwd=checkout["dir"], env=env, capture_output=True,
                         text=True, timeout=timeout_s)
    if run.returncode != 0:
        raise RuntimeError(f"generate from {checkout['dir']} failed (exit {run.returncode}): {run.stderr.strip()[-1500:]}")
    lines = [line for line in run.stdout.splitlines() if line.startswith("{")]
    if not lines:
        raise RuntimeError(f"generate from {checkout['dir']} printed no JSON result")
    return json.loads(lines[-1])


def bench_generate_against(checkouts, profiles=("cpu",), workers=(2,), frames_per_context: int = 20,
                           sequence_length: int = 10, seed: int = 0, rounds: int = 3, twins: bool = False,
                           timeout_s: float = 3600.0, progress=None, contexts=("all",)) -> dict:
    """This code's `generate` against other checkouts' (e.g. a git worktree of an older commit), in turn.

    Every run is `python -m study.cli generate --out TMP --contexts CONTEXTS ... --json` started from a
    checkout's directory, so each side pays the same process start-up and each times itself with its
    own `frames_per_second` (frames / wall seconds inside `generate`). Per round: this code, then each
    other checkout in the given order (A B C A B C ...), so a machine whose speed drifts slows each
    alike. `ratios[profile/workers][dir]` = this code's median frames/s over that checkout's; a ratio
    measured this way holds across machines where absolute frames/s do not. `same_bytes` says whether
    the checkout's dataset was byte-identical to this code's in every round (sha256 of all files)."""
    import statistics
    import tempfile
    from pathlib import Path

    here = checkout_of(Path(__file__).resolve().parents[2])
    others = [checkout_of(c) for c in checkouts]
    if not others:
        raise ValueError("checkouts must name at least one other checkout")
    if len({s["dir"] for s in [here, *others]}) != len(others) + 1:
        from sim.errors import UserError

        raise UserError(f"--against names this checkout ({here['dir']}) or one directory twice")
    if rounds < 1:
        raise ValueError(f"rounds must be >= 1, got {rounds}")
    from sensors.generate import GenerateConfig

    GenerateConfig(contexts=_contexts(contexts))  # an unknown context is refused here, not in a child
    sides = [here, *others]
    runs = []
    for round_ in range(rounds):
        for profile in profiles:
            for w in workers:
                digests = {}
                for side in sides:
                    with tempfile.TemporaryDirectory(prefix="hydrabench-against-") as tmp:
                        out = str(Path(tmp) / "data")
                        r = _generate_from(side, out, profile, w, frames_per_context, sequence_length, seed, twins,
                                           timeout_s, contexts)
                        digests[side["dir"]] = dataset_digest(out)
                    runs.append({"round": round_, "profile": profile, "workers": w, "dir": side["dir"],
                                 "commit": side["commit"], "frames": r["frames"], "seconds": r["seconds"],
                                 "frames_per_second": r["frames_per_second"],
                                 "ms_per_frame_total": round(sum(v for k, v in r.get("ms_per_frame", {}).items()
                                                                 if "/" not in k), 2),
                                 "same_bytes": digests[side["dir"]] == digests[here["dir"]]})
                    if progress:
                        progress(runs[-1])
    ratios, same = {}, {}
    for profile in profiles:
        for w in workers:
            med = {s["dir"]: statistics.median(x["frames_per_second"] for x in runs
                                               if x["profile"] == profile and x["workers"] == w and x["dir"] == s["dir"])
                   for s in sides}
            ratios[f"{profile}/{w}"] = {s["dir"]: round(med[here["dir"]] / med[s["dir"]], 3) for s in others}
    for s in others:
        same[s["dir"]] = all(x["same_bytes"] for x in runs if x["dir"] == s["dir"])
    return {"this": here, "against": others, "runs": runs, "ratios": ratios, "same_bytes": same,
            "frames_per_context": frames_per_context, "sequence_length": sequence_length, "rounds": rounds,
            "twins": twins, "seed": seed, "contexts": _contexts(contexts), **machine()}
