"""`hydrabench bench scale`: what more threads, more processes and Ray buy on this machine, measured
back to back in one run (issue 15, "Figures in BENCHMARKS.md").

Three parts, each a ratio of two runs of the same work taken one after the other:

    train     CPU training images/s of `hydrabench train` at --threads 1 and at --threads 2 (one
              process each, same branches, batch, frames and steps).
    ddp       data-parallel training: 2 gloo processes under torchrun (loopback, a free port,
              1 thread each) against 1 process at 2 threads, with the same global batch, so the
              same cores and the same SGD steps; step time and images/s. With per-frame sampling
              both train the same weights (tests/study/test_distributed.py); the largest weight
              difference is reported as a check that they did the same work.
    generate  `generate` frames/s with the local process pool against `--backend ray` (a local Ray
              instance on loopback, started and stopped by the command), both with --workers
              processes / CPUs, and whether their shards are byte-identical. When Ray cannot start
              (not installed, or its processes too slow to register on a loaded machine) the part
              is reported as skipped with the reason.

Training times are `train_seconds` of the run's metrics.csv (the SGD steps of the last epoch, without
the per-epoch evaluation and without process start-up); every run is a fresh `python -m study.cli
train` process, so none inherits another's warmed-up allocator or threads. Generation times are
`generate()`'s own (from after planning to the last shard written: worker or Ray start-up included,
as a user waits for it). The machine description holds the load average before and after: on a
shared machine absolute figures move with the load, and only the ratios of one run mean much.

Every process this command starts is stopped when it ends, also on an error or Ctrl-C: training
subprocesses (and torchrun's workers, which run in sessions of their own) are signalled as a tree.
"""

from __future__ import annotations

import csv
import json
import os
import platform
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path

from sim.errors import UserError

PARTS = ("train", "ddp", "generate")
REPO = Path(__file__).resolve().parents[2]


@dataclass(frozen=True)
class ScaleConfig:
    """One `bench scale` run.

    Fields:
        parts: which of train, ddp, generate to measure.
        data: training dataset (cpu profile); None: the local-pool dataset of part generate, or one
            generated for the run with the fields below.
        contexts: contexts of the generated dataset ("all" = the eight).
        frames_per_context: frames per context of the generated dataset.
        sequence_length: frames per sequence (= shard; one sequence per context puts every frame in
            the training split, so no evaluation runs between the timed steps).
        seed: root seed of the generated dataset and of the training runs.
        branches: branches trained (cpu model profile).
        batch_size: frames per SGD step, the global batch of the DDP run (>= 2: one frame per process).
        epochs: epochs per training run; the last epoch is timed (2: the first absorbs warm-up).
        workers: local pool processes and Ray CPUs of part generate.
        model: `KEY=VALUE` overrides of the cpu model profile for every training run (`train --model`).
    """

    parts: tuple[str, ...] = PARTS
    data: str | None = None
    contexts: tuple[str, ...] = ("all",)
    frames_per_context: int = 2
    sequence_length: int = 2
    seed: int = 0
    branches: tuple[str, ...] = ("radar",)
    batch_size: int = 4
    epochs: int = 1
    workers: int = 2
    model: tuple[str, ...] = ()

    def generate_config(self):
        from sensors.generate import GenerateConfig
        from sim.scenario import CONTEXT_NAMES

        contexts = tuple(CONTEXT_NAMES) if tuple(self.contexts) == ("all",) else tuple(self.contexts)
        return GenerateConfig(contexts=contexts, frames_per_context=self.frames_per_context,
                              sequence_length=self.sequence_length, seed=self.seed, profile="cpu")


def check(cfg: ScaleConfig) -> None:
    """Refuse a config that would fail part-way (UserError), before any work."""
    from study.engine.train import branch_set

    bad = [p for p in cfg.parts if p not in PARTS]
    if bad or not cfg.parts:
        raise UserError(f"--parts: unknown part {bad[0] if bad else ''!r} (choose from: {', '.join(PARTS)})")
    from fusion.nets.profile import load_profile, parse_model_overrides

    load_profile("cpu", **parse_model_overrides(cfg.model))  # a malformed --model before any process starts
    names = [s.name for s in branch_set("paper", "cpu")]
    unknown = [b for b in cfg.branches if b not in names]
    if unknown or not cfg.branches:
        raise UserError(f"--branches: unknown branch {unknown[0] if unknown else ''!r} (choose from: {', '.join(names)})")
    if cfg.batch_size < 2:
        raise UserError(f"--batch-size {cfg.batch_size}: the DDP run needs one frame per process, at least 2")
    if "generate" in cfg.parts or cfg.data is None:
        cfg.generate_config()  # unknown contexts, sizes beyond the limits
    if cfg.data is not None:
        from sensors.dataset import DatasetReader

        profile = DatasetReader(cfg.data).manifest.get("profile")
        if profile != "cpu":
            raise UserError(f"--data {cfg.data}: a {profile!r}-profile dataset; bench scale trains the cpu model profile")


# ----------------------------------------------------------------------------------------------
# the machine


def load_average() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict:
    import torch

    from study.engine.device import available_cores

    return {"cores": os.cpu_count(), "cores_available": available_cores(), "cpu": cpu_model(),
            "machine": platform.machine(), "python": platform.python_version(), "torch": torch.__version__,
            "torch_threads_default": torch.get_num_threads(), "load_average_before": load_average()}


# ----------------------------------------------------------------------------------------------
# processes: started in a session of their own, stopped as a tree


def _stat(pid: int) -> tuple[str, int, int] | None:
    """(state, parent pid, start time in clock ticks) of a process, or None when it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
        return fields[0], int(fields[1]), int(fields[19])
    except (OSError, IndexError, ValueError):
        return None


def descendants(root: int) -> dict[int, int]:
    """`root` and every process below it, {pid: start time}, found through /proc (torchrun starts its
    workers in sessions of their own, so a process group does not hold them)."""
    stats = {int(n): st for n in os.listdir("/proc") if n.isdigit() and (st := _stat(int(n))) is not None}
    children: dict[int, list[int]] = {}
    for pid, st in stats.items():
        children.setdefault(st[1], []).append(pid)
    out, frontier = [root], [root]
    while frontier:
        frontier = [c for p in frontier for c in children.get(p, [])]
        out += frontier
    return {pid: stats[pid][2] for pid in out if pid in stats}


def alive(pid: int, started: int | None = None) -> bool:
    """Whether `pid` runs (not a zombie) and, given `started`, is the process that started then
    (not a later one that reused the number)."""
    st = _stat(pid)
    return st is not None and st[0] != "Z" and (started is None or st[2] == started)


def stop_tree(proc: subprocess.Popen, known: dict[int, int] | None = None, grace: float = 5.0) -> None:
    """Stop `proc` and everything it started: SIGTERM to its tree, to its process group and to the
    processes in `known` ({pid: start time} seen below it earlier: workers orphaned when their
    parent died), then SIGKILL to whatever is still there after `grace` seconds; `proc` is reaped."""
    tree = dict(known or {})
    for sig in (signal.SIGTERM, signal.SIGKILL):
        if proc.poll() is None:
            tree.update(descendants(proc.pid))
        tree = {p: t for p, t in tree.items() if alive(p, t)}
        if not tree:
            break
        for pid in tree:
            try:
                os.kill(pid, sig)
            except (ProcessLookupError, PermissionError):
                pass
        try:
            os.killpg(proc.pid, sig)  # started with a session of its own: the group id is its pid
        except (ProcessLookupError, PermissionError):
            pass
        deadline = time.monotonic() + grace
        while time.monotonic() < deadline and any(alive(p, t) for p, t in tree.items()):
            proc.poll()  # reap it, so that it does not linger as a zombie
            time.sleep(0.05)
    try:
        proc.wait(timeout=grace)
    except subprocess.TimeoutExpired:
        pass


def run_job(argv: list[str], env: dict, label: str, stdout_path: Path, progress: bool = True) -> tuple[float, str]:
    """Run one command to its end, its stderr passed on line by line (prefixed with `label`) and its
    stdout written to `stdout_path`. Returns (wall seconds, stdout). A non-zero exit raises
    UserError with the command's last line. Whatever ends it (its exit, an error, Ctrl-C), no process
    it started is left running."""
    tail: deque[str] = deque(maxlen=30)
    own: deque[str] = deque(maxlen=5)  # hydrabench's error lines (a rank's, before torchrun's long banner)
    t0 = time.perf_counter()
    with open(stdout_path, "w") as out:
        proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, env=env,
                                text=True, errors="replace", start_new_session=True)

        def pump():
            for line in proc.stderr:
                tail.append(line.rstrip("\n"))
                if line.startswith("hydrabench") and "error:" in line:
                    own.append(line.rstrip("\n"))
                if progress:
                    sys.stderr.write(f"[{label}] {line}")
                    sys.stderr.flush()

        reader = threading.Thread(target=pump, daemon=True)
        reader.start()
        seen: dict[int, int] = {}
        try:
            while True:
                try:
                    proc.wait(timeout=2.0)
                    break
                except subprocess.TimeoutExpired:
                    seen.update(descendants(proc.pid))  # remembered, should its workers outlive it
        finally:
            seen.pop(proc.pid, None)
            stop_tree(proc, seen)
            reader.join(timeout=5)
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        raise UserError(f"bench scale: {label} exited with code {proc.returncode}: {_culprit([*own, *tail])[:300]}")
    return seconds, stdout_path.read_text()


def _culprit(lines) -> str:
    """The line of a failed command's stderr that says what went wrong: hydrabench's own error line
    (`hydrabench: error:`, or argparse's `hydrabench train: error:`),
    else the last line naming an error (torchrun ends with banners), else the last line with words."""
    lines = [x.strip() for x in lines if x.strip().strip("=-")]
    for pick in (lambda x: x.startswith("hydrabench") and "error:" in x, lambda x: "Error" in x or "error:" in x, bool):
        found = [x for x in lines if pick(x)]
        if found:
            return found[-1]
    return "(no output)"


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ----------------------------------------------------------------------------------------------
# the measurements


def _child_env(threads: int) -> dict:
    path = os.environ.get("PYTHONPATH", "")
    return {**os.environ, "PYTHONPATH": str(REPO) + (os.pathsep + path if path else ""),
            "OMP_NUM_THREADS": str(threads), "GLOO_SOCKET_IFNAME": "lo"}


def train_argv(cfg: ScaleConfig, data: str, out: Path, threads: int) -> list[str]:
    """`hydrabench train` arguments of every training run of the bench (only --threads differs)."""
    return ["-m", "study.cli", "train", str(data), "--out", str(out), "--branches", ",".join(cfg.branches),
            "--epochs", str(cfg.epochs), "--batch-size", str(cfg.batch_size), "--seed", str(cfg.seed),
            "--eval-frames", "1", "--sampling", "per-frame", "--device", "cpu", "--no-amp", "--workers", "0",
            "--threads", str(threads), "--json", *[arg for item in cfg.model for arg in ("--model", item)]]


def train_run(cfg: ScaleConfig, data: str, out: Path, *, threads: int, processes: int = 1,
              progress: bool = True) -> dict:
    """One training run in fresh processes; its last epoch's steps timed (metrics.csv train_seconds)."""
    args = train_argv(cfg, data, out, threads)
    if processes == 1:
        argv, label = [sys.executable, *args], f"train {threads} thread{'s' if threads > 1 else ''}"
    else:
        argv = [sys.executable, "-m", "torch.distributed.run", "--nnodes", "1", "--nproc-per-node", str(processes),
                "--master-addr", "127.0.0.1", "--master-port", str(free_port()), *args]
        label = f"ddp {processes} processes x {threads} thread{'s' if threads > 1 else ''}"
    if progress:
        sys.stderr.write(f"bench scale: {label} ...\n")
    wall, stdout = run_job(argv, _child_env(threads), label, out.parent / f"{out.name}.stdout", progress)
    summary = json.loads(stdout.strip().splitlines()[-1])
    with open(out / "metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    last = rows[-1]
    steps = int(last["steps"]) - (int(rows[-2]["steps"]) if len(rows) > 1 else 0)
    seconds = float(last["train_seconds"])
    frames = int(summary["train_frames"])
    return {"threads_per_process": threads, "processes": processes, "train_frames": frames, "steps": steps,
            "train_seconds": seconds, "step_seconds": round(seconds / steps, 3),
            "images_per_second": round(frames / seconds, 4), "wall_seconds": round(wall, 1),
            "loss_total": float(last["loss_total"])}


def max_weight_difference(run_a: Path, run_b: Path) -> float:
    """Largest absolute difference between the final weights of two runs (same architecture)."""
    import torch

    a = torch.load(run_a / "checkpoint.pt", map_location="cpu", weights_only=False)["model"]
    b = torch.load(run_b / "checkpoint.pt", map_location="cpu", weights_only=False)["model"]
    if a.keys() != b.keys():
        raise ValueError(f"{run_a} and {run_b} hold different models")
    return max((float((a[k].double() - b[k].double()).abs().max()) if a[k].numel() else 0.0) for k in a)


def generate_run(gcfg, out: Path, workers: int, backend: str, progress: bool = True) -> dict:
    from sensors.generate import generate

    if progress:
        sys.stderr.write(f"bench scale: generate, {backend} backend, {workers} workers ...\n")
    r = generate(gcfg, out, workers=workers, progress=progress, backend=backend)
    shards = json.loads((out / "manifest.json").read_text())["shards"]
    return {"backend": backend, "workers": workers, "frames": r["frames_rendered"], "seconds": r["seconds"],
            "frames_per_second": r["frames_per_second"], "shard_sha256": [s["sha256"] for s in shards],
            **({"ray": r["ray"]} if "ray" in r else {})}


def _ratio(num, den) -> float | None:
    if num is None or den is None or den == 0:
        return None
    return round(num / den, 3)


def ratios(result: dict) -> dict:
    """The ratios of a `bench_scale` result's parts (None for a part not measured or skipped):

        threads_2_over_1       training images/s at 2 threads / at 1 thread (one process)
        ddp_speedup            step time of 1 process (2 threads) / of 2 processes (1 thread each),
                               the same global batch: = their images/s ratio
        ddp_over_1_thread      images/s of the 2 processes / of 1 process at 1 thread
        ray_over_local         generate frames/s with the Ray backend / with the local pool
    """
    parts = result.get("parts", {})
    train, ddp, gen = parts.get("train") or {}, parts.get("ddp") or {}, parts.get("generate") or {}
    one = (train.get("threads_1") or {}).get("images_per_second")
    two = (train.get("threads_2") or {}).get("images_per_second")
    ref, par = ddp.get("one_process") or {}, ddp.get("processes_2") or {}
    local, ray = gen.get("local") or {}, gen.get("ray") or {}
    return {
        "threads_2_over_1": _ratio(two, one),
        "ddp_speedup": _ratio(ref.get("step_seconds"), par.get("step_seconds")),
        "ddp_over_1_thread": _ratio(par.get("images_per_second"), one),
        "ray_over_local": _ratio(ray.get("frames_per_second"), local.get("frames_per_second")),
    }


def bench_scale(cfg: ScaleConfig, progress: bool = True, workdir: str | None = None) -> dict:
    """Measure the parts of `cfg` back to back (see the module docstring); returns the result
    (machine, sizes, per-part seconds and rates, ratios). Temporary datasets and runs live in
    `workdir` (default: a temporary directory, removed at the end)."""
    check(cfg)
    with _terminate_as_interrupt():
        return _bench_scale(cfg, progress, workdir)


@contextmanager
def _terminate_as_interrupt():
    """SIGTERM raises KeyboardInterrupt while the bench runs, so that `kill` stops its subprocesses
    and removes its temporary files as Ctrl-C does (Python's default SIGTERM runs no cleanup)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def _bench_scale(cfg: ScaleConfig, progress: bool, workdir: str | None) -> dict:
    t_start = time.perf_counter()
    result: dict = {"machine": machine_info(), "config": {**asdict(cfg), "parts": list(cfg.parts)}, "parts": {}}
    with tempfile.TemporaryDirectory(prefix="hydrabench-scale-", dir=workdir) as tmp:
        tmp = Path(tmp)
        data = cfg.data
        gcfg = cfg.generate_config() if ("generate" in cfg.parts or data is None) else None
        if "generate" in cfg.parts:
            local = generate_run(gcfg, tmp / "gen-local", cfg.workers, "local", progress)
            try:
                ray = generate_run(gcfg, tmp / "gen-ray", cfg.workers, "ray", progress)
                ray["same_bytes_as_local"] = ray["shard_sha256"] == local["shard_sha256"]
            except KeyboardInterrupt:
                raise
            except Exception as exc:  # noqa: BLE001 - Ray's failures to start are bare Exceptions; the rest still counts
                reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                ray = {"backend": "ray", "skipped": reason}
                if progress:
                    sys.stderr.write(f"bench scale: Ray part skipped: {reason}\n")
            for r in (local, ray):
                r.pop("shard_sha256", None)
            result["parts"]["generate"] = {"local": local, "ray": ray}
            if data is None:
                data = str(tmp / "gen-local")
        train_parts = [p for p in ("train", "ddp") if p in cfg.parts]
        if train_parts and data is None:
            from sensors.generate import generate

            if progress:
                sys.stderr.write("bench scale: generating the training dataset ...\n")
            generate(gcfg, tmp / "data", workers=cfg.workers, progress=progress)
            data = str(tmp / "data")
        runs: dict[str, dict] = {}
        if "train" in cfg.parts:
            runs["threads_1"] = train_run(cfg, data, tmp / "run-t1", threads=1, progress=progress)
        if train_parts:
            runs["threads_2"] = train_run(cfg, data, tmp / "run-t2", threads=2, progress=progress)
        if "train" in cfg.parts:
            result["parts"]["train"] = {"threads_1": runs["threads_1"], "threads_2": runs["threads_2"]}
        if "ddp" in cfg.parts:
            ddp = train_run(cfg, data, tmp / "run-ddp", threads=1, processes=2, progress=progress)
            result["parts"]["ddp"] = {
                "one_process": runs["threads_2"], "processes_2": ddp, "backend": "gloo",
                "max_weight_difference": max_weight_difference(tmp / "run-t2", tmp / "run-ddp")}
        if train_parts:
            result["training_data"] = {"path": cfg.data or "(generated for the run, removed)",
                                       "train_frames": runs["threads_2"]["train_frames"]}
    result["machine"]["load_average_after"] = load_average()
    result["ratios"] = ratios(result)
    result["seconds"] = round(time.perf_counter() - t_start, 1)
    return result


# ----------------------------------------------------------------------------------------------
# output


def text_table(r: dict) -> str:
    m = r["machine"]
    lines = [f"machine: {m['cores']} cores ({m['cpu']}), torch {m['torch']} ({m['torch_threads_default']} threads "
             f"by default), load average before {m['load_average_before']}, after {m.get('load_average_after')}"]
    parts = r["parts"]
    if "train" in parts or "ddp" in parts:
        lines.append(f"{'training run':34s} {'frames':>6s} {'steps':>5s} {'seconds':>8s} {'s/step':>8s} {'images/s':>9s}")
        rows = []
        if "train" in parts:
            rows += [("1 process, 1 thread", parts["train"]["threads_1"]), ("1 process, 2 threads", parts["train"]["threads_2"])]
        if "ddp" in parts:
            if "train" not in parts:
                rows.append(("1 process, 2 threads", parts["ddp"]["one_process"]))
            rows.append(("DDP 2 processes x 1 thread (gloo)", parts["ddp"]["processes_2"]))
        for name, x in rows:
            lines.append(f"{name:34s} {x['train_frames']:6d} {x['steps']:5d} {x['train_seconds']:8.2f} "
                         f"{x['step_seconds']:8.2f} {x['images_per_second']:9.3f}")
        if "ddp" in parts:
            lines.append(f"DDP final weights vs 1 process: max |difference| {parts['ddp']['max_weight_difference']:.2e}")
    if "generate" in parts:
        g = parts["generate"]
        for name in ("local", "ray"):
            x = g[name]
            if "skipped" in x:
                lines.append(f"generate, {name:5s} backend: skipped ({x['skipped']})")
            else:
                same = f", shards byte-identical to local: {x['same_bytes_as_local']}" if name == "ray" else ""
                lines.append(f"generate, {name:5s} backend, {x['workers']} workers: {x['frames_per_second']} frames/s "
                             f"({x['frames']} frames in {x['seconds']} s{same})")
    lines.append("ratios: " + ", ".join(f"{k} {v if v is not None else '-'}" for k, v in r["ratios"].items()))
    if r.get("plot"):
        lines.append(f"plot: {r['plot']}")
    return "\n".join(lines)


RATIO_LABELS = {"threads_2_over_1": "train: 2 threads / 1", "ddp_speedup": "DDP 2 proc. / 1 proc. (2 thr.)",
                "ddp_over_1_thread": "DDP 2 proc. / 1 thread", "ray_over_local": "generate: Ray / local pool"}


def plot_scale(r: dict, path) -> None:
    """The measured ratios as bars, with 1 (no gain) and 2 (two cores' worth) marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from study.outputs import savefig_atomic

    keys = list(RATIO_LABELS)
    values = [r["ratios"].get(k) for k in keys]
    fig, ax = plt.subplots(figsize=(7.5, 3.6))
    ys = range(len(keys))
    ax.barh(ys, [v or 0.0 for v in values], color=["tab:blue", "tab:orange", "tab:orange", "tab:green"])
    for y, v in zip(ys, values):
        ax.text((v or 0.0) + 0.02, y, f"{v:.2f}x" if v is not None else "not measured", va="center", fontsize=9)
    ax.axvline(1.0, color="k", lw=1)
    ax.axvline(2.0, color="grey", lw=1, ls="--")
    ax.set_yticks(list(ys), [RATIO_LABELS[k] for k in keys])
    ax.invert_yaxis()
    ax.set_xlim(0, max([2.3] + [v + 0.4 for v in values if v is not None]))
    m = r["machine"]
    ax.set(xlabel="ratio (higher: faster)",
           title=f"bench scale: {m['cores']} cores, 1-min load average {m['load_average_before'][0] if m['load_average_before'] else '?'}"
                 f" -> {m['load_average_after'][0] if m.get('load_average_after') else '?'}")
    ax.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    savefig_atomic(fig, path, dpi=120)
    plt.close(fig)
