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


def bench_generate(profiles=("cpu", "paper"), workers=(1, 2), frames_per_context: int = 10,
                   sequence_length: int = 10, seed: int = 0, start_methods=(None,), rounds: int = 1,
                   twins: bool = False) -> dict:
    """Generate a temporary dataset over every context for each profile, worker count and start
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
    configs = {profile: GenerateConfig(frames_per_context=frames_per_context, sequence_length=sequence_length,
                                       seed=seed, profile=profile, twins=twins)
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
            "twins": twins,
            **machine()}
