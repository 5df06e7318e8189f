"""Dataset generation: a plan of shards, each a pure function of (config, shard index).

`plan(config)` lists the shards (one sequence each): context, severity, sequence seed, frames.
`generate_shard(config, index, out)` simulates the sequence, renders every sensor, writes the
shard atomically and returns its checksum and timings. `generate(config, out, workers)` runs the
missing shards in parallel processes (results do not depend on the number of workers) and writes
the manifest last, so an interrupted run (even kill -9) is completed by running it again.
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import signal
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from sensors import SENSOR_MODEL_VERSION
from sim.config import from_dict
from sim.errors import Terminated, UserError
from sim.scenario import CONTEXT_NAMES, MAX_DURATION_S, Context, ScenarioSpec, Simulator, stream
from sim.weather import TRANSITIONS

MAX_DATASET_FRAMES = 1_000_000
"""Most frames in one dataset (about 3 days of rendering on 2 cores at the cpu profile)."""
MAX_SEQUENCE_LENGTH = 1000
"""Most frames per sequence (= per shard): a shard is rendered in memory (~1 MB per cpu frame,
~10 MB per paper frame)."""


@dataclass(frozen=True)
class GenerateConfig:
    """What `hydrabench generate` builds. Every field is part of the manifest.

    Fields:
        contexts: context names or combinations ("fog", "city+night+rain"); "all" = the eight.
        frames_per_context: frames per context (>= 1).
        seed: root seed; shard seeds derive from (seed, context, sequence index).
        profile: sensor profile ("cpu" or "paper").
        sequence_length: frames per sequence = per shard.
        frame_rate_hz: recording rate within a sequence [Hz].
        severities: severity levels drawn uniformly per sequence for contexts with conditions
            (layout-only contexts always use 0).
        transitions: weather transitions drawn uniformly per sequence ("none" = constant weather).
        twins: also render every frame in clear weather (counterfactual pairs, `clear/`).
        degrade: apply the weather/obstruction degradation models (sensors.degrade).
        lidar_fog: lidar fog model, "ours" or "hahner" (Hahner et al. ICCV 2021 as published;
            sensors.degrade.lidar.LIDAR_FOG_MODELS); each fog frame records it in its params.
    """

    contexts: tuple[str, ...] = CONTEXT_NAMES
    frames_per_context: int = 20
    seed: int = 0
    profile: str = "cpu"
    sequence_length: int = 10
    frame_rate_hz: float = 2.0
    severities: tuple[int, ...] = (1, 2, 3, 4, 5)
    transitions: tuple[str, ...] = ("none",)
    twins: bool = False
    degrade: bool = True
    lidar_fog: str = "ours"

    def __post_init__(self) -> None:
        if not self.contexts:
            raise UserError("contexts must name at least one context")
        names = [Context.parse(c).name for c in self.contexts]
        twice = [c for k, c in enumerate(self.contexts) if names[k] in names[:k]]
        if twice:  # the same sequences twice: they could land in both a train and a test split
            raise UserError(f"contexts name {twice[0]!r} twice ({Context.parse(twice[0]).name})")
        if self.frames_per_context < 1:
            raise UserError(f"frames_per_context must be >= 1, got {self.frames_per_context}")
        total = self.frames_per_context * len(self.contexts)
        if total > MAX_DATASET_FRAMES:
            raise UserError(f"frames_per_context x contexts = {total} frames; the limit is {MAX_DATASET_FRAMES}")
        if not 1 <= self.sequence_length <= MAX_SEQUENCE_LENGTH:
            raise UserError(f"sequence_length must be 1..{MAX_SEQUENCE_LENGTH} (a sequence is rendered in memory), "
                            f"got {self.sequence_length}")
        if not (self.frame_rate_hz > 0 and math.isfinite(self.frame_rate_hz)):
            raise UserError(f"frame_rate_hz must be > 0, got {self.frame_rate_hz}")
        if self.sequence_length / self.frame_rate_hz > MAX_DURATION_S:
            raise UserError(f"a sequence of {self.sequence_length} frames at {self.frame_rate_hz:g} Hz lasts "
                            f"{self.sequence_length / self.frame_rate_hz:g} s; the limit is {MAX_DURATION_S:g} s")
        if not 0 <= self.seed < 2**63:
            raise UserError(f"seed must be 0..2**63-1, got {self.seed}")
        if not self.severities or any(not 0 <= s <= 5 for s in self.severities):
            raise UserError(f"severities must be values in 0..5, got {list(self.severities)}")
        if len(set(self.severities)) != len(self.severities):
            raise UserError(f"severities name a value twice: {list(self.severities)}")
        bad = [t for t in self.transitions if t not in TRANSITIONS]
        if bad or not self.transitions:
            raise UserError(f"unknown weather transition {bad[0] if bad else ''!r} (choose from: {', '.join(TRANSITIONS)})")
        if len(set(self.transitions)) != len(self.transitions):
            raise UserError(f"transitions name a value twice: {list(self.transitions)}")
        from sensors.degrade.lidar import LIDAR_FOG_MODELS
        from sensors.rig import profile_names

        if self.profile not in profile_names():
            raise UserError(f"unknown profile {self.profile!r} (choose from: {', '.join(profile_names())})")
        if self.lidar_fog not in LIDAR_FOG_MODELS:
            raise UserError(f"unknown lidar_fog {self.lidar_fog!r} (choose from: {', '.join(LIDAR_FOG_MODELS.names())})")

    def to_dict(self) -> dict:
        d = asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    @staticmethod
    def from_mapping(data: dict) -> GenerateConfig:
        return from_dict(GenerateConfig, data, "generate config")


@dataclass(frozen=True)
class ShardSpec:
    index: int
    context: str
    severity: int
    seed: int
    frames: int
    transition: str

    @property
    def name(self) -> str:
        from sensors.dataset import shard_name

        return shard_name(self.index)


def plan(config: GenerateConfig) -> list[ShardSpec]:
    """The shards of a dataset, in a fixed order (context by context)."""
    shards = []
    for context in config.contexts:
        ctx = Context.parse(context)
        n_seq = math.ceil(config.frames_per_context / config.sequence_length)
        for j in range(n_seq):
            rng = stream(config.seed, "sequence", ctx.name, j)
            seed = int(rng.integers(2**31 - 1))
            severity = int(rng.choice(config.severities)) if ctx.conditions else 0
            weather_like = set(ctx.conditions) - {"night"}
            transition = str(rng.choice(config.transitions)) if (severity and weather_like) else "none"
            frames = min(config.sequence_length, config.frames_per_context - j * config.sequence_length)
            shards.append(ShardSpec(len(shards), ctx.name, severity, seed, frames, transition))
    return shards


def open_sequence(spec: ShardSpec, config: GenerateConfig):
    """Simulate shard `spec`'s sequence and build its sensors: (simulator, scenes, renderer,
    degrader or None, simulation seconds). The world is built around the ego's simulated path."""
    from sensors.frame import SequenceRenderer
    from sensors.rig import load_profile

    t0 = time.perf_counter()
    sim = Simulator(ScenarioSpec(context=spec.context, severity=spec.severity, seed=spec.seed, frames=spec.frames,
                                 frame_rate_hz=config.frame_rate_hz, profile=config.profile,
                                 transition=spec.transition))
    all_scenes = list(sim.scenes())  # simulate first: the world is then built around the ego's path
    t_sim = time.perf_counter() - t0
    renderer = SequenceRenderer(all_scenes[0], load_profile(config.profile), seed=spec.seed,
                                ego_path=np.array([s.ego.position[:2] for s in all_scenes]))
    degrader = None
    if config.degrade:
        from sensors.degrade import Degrader

        degrader = Degrader(renderer.calib, spec.context, spec.seed, lidar_fog=config.lidar_fog)
    return sim, all_scenes, renderer, degrader, t_sim


def render_sequence(spec: ShardSpec, config: GenerateConfig, on_frame: Callable[[], None] | None = None):
    """Simulate and render one shard's sequence. Returns (frames, twin frames or None, timings)."""
    sim, all_scenes, renderer, degrader, t_sim = open_sequence(spec, config)
    first = all_scenes[0]
    scenes = iter(all_scenes[1:])
    frames, twins = [], [] if config.twins else None
    # The twin holds everything but the condition's own quantities: the sequence's drawn clear-air
    # visibility and (for fog, rain, snow) its light; persistent faults and random streams stay.
    clear = sim.twin_weather
    scene = first
    while True:
        raw = renderer.observe(scene)
        obs, params = raw, {}
        if degrader is not None:
            t = time.perf_counter()
            obs, params = degrader.apply(raw, scene.frame_index)
            renderer.timings["degradation"] += time.perf_counter() - t
        frames.append(renderer.finalize(scene, obs, params, clean=raw))
        if twins is not None:  # the same moment in clear weather (persistent faults stay)
            twin_raw = renderer.observe(scene, clear)
            twin_obs, twin_params = twin_raw, {}
            if degrader is not None:
                twin_obs, twin_params = degrader.apply(twin_raw, scene.frame_index)
            twins.append(renderer.finalize(scene, twin_obs, twin_params, clean=twin_raw))
        if on_frame:
            on_frame()
        scene = next(scenes, None)
        if scene is None:
            break
    timings = dict(renderer.timings)
    timings["simulation"] = t_sim
    if degrader is not None:
        timings.update({f"degrade/{k}": v for k, v in degrader.timings.items()})
    return frames, twins, timings


def generate_shard(config_dict: dict, spec_dict: dict, out: str) -> dict:
    """Worker entry point: render shard `spec` of `config` into `out` (atomic). Returns its record."""
    from sensors.dataset import commit_shard, shard_digest, write_frames

    config = GenerateConfig.from_mapping(config_dict)
    spec = ShardSpec(**spec_dict)
    root = Path(out)
    final = root / spec.name
    tmp = root / f"{spec.name}.tmp-{os.getpid()}"
    t0 = time.perf_counter()
    frames, twins, timings = render_sequence(spec, config)
    t_write = time.perf_counter()
    extra = {"shard": asdict(spec), "config": config.to_dict(), "sensor_model_version": SENSOR_MODEL_VERSION}
    try:
        write_frames(tmp, frames, extra)
        if twins is not None:
            write_frames(tmp / "clear", twins, {**extra, "twin": "clear"})
        digest = shard_digest(tmp)
        commit_shard(tmp, final)
    except BaseException:  # a full disk, an interrupt: no half-written shard left behind
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    timings["write"] = time.perf_counter() - t_write
    return {"name": spec.name, "sha256": digest, "frames": len(frames), **asdict(spec),
            "seconds": time.perf_counter() - t0, "timings": timings}


def worker_start_method() -> str:
    """How the local pool starts its workers: "fork" when this process holds no OpenGL context, else
    "spawn".

    A forked worker starts with this process's imports (highway-env, numpy, scipy: ~1 s of a fresh
    interpreter's start-up per worker, inside the timed run); it creates its own EGL context on its
    first render. A process that has rendered (sensors.camera keeps its offscreen renderers) must
    not fork: the child would share the parent's EGL display state. Set HYDRABENCH_START_METHOD to
    "spawn" or "fork" to choose. The arrays are the same bytes either way (each shard draws from
    its own seeded streams)."""
    import multiprocessing as mp
    import sys

    available = mp.get_all_start_methods()
    wanted = os.environ.get("HYDRABENCH_START_METHOD", "").strip()
    if wanted:
        if wanted not in available:
            raise UserError(f"HYDRABENCH_START_METHOD={wanted!r}: choose from {', '.join(available)}")
        return wanted
    camera = sys.modules.get("sensors.camera")
    if camera is not None and getattr(camera, "_RENDERERS", None):
        return "spawn"
    return "fork" if "fork" in available else "spawn"


def _init_worker(threads: int) -> None:
    os.environ["LP_NUM_THREADS"] = str(threads)
    os.environ["OMP_NUM_THREADS"] = str(threads)
    os.environ["OPENBLAS_NUM_THREADS"] = str(threads)


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
"""Ctrl-C and `kill`: the parent stops the pool's workers, removes partial shards and releases the lock."""


def _init_pool_worker(threads: int) -> None:
    """A local pool's worker. Ctrl-C reaches the whole process group: the parent alone handles it
    (it terminates the pool and removes partial shards); a worker that took it would print its
    KeyboardInterrupt traceback. SIGTERM gets its default action back (a forked worker inherits the
    parent's flag-setting handler, and the pool stops its workers with SIGTERM). The worker starts
    with both blocked (`_start_pool`), so SIGINT is ignored from its first instruction on."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, set(STOP_SIGNALS))
    _init_worker(threads)


def _start_pool(ctx, workers: int, threads: int):
    """ctx.Pool with SIGINT and SIGTERM blocked while its workers (and the thread that replaces them)
    start: a Ctrl-C or a `kill` in between stays pending here and is taken in this process once the
    pool is up."""
    old = signal.pthread_sigmask(signal.SIG_BLOCK, set(STOP_SIGNALS))
    try:
        return ctx.Pool(workers, initializer=_init_pool_worker, initargs=(threads,), maxtasksperchild=None)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


@contextlib.contextmanager
def _ctrl_c_as_flag():
    """While the pool runs, SIGINT and SIGTERM set an event that the waiting loop turns into
    KeyboardInterrupt (`Terminated`, its subclass, for SIGTERM).

    Python raises KeyboardInterrupt wherever the main thread happens to be when the signal's handler
    runs; inside a finalizer or a weakref callback (the pool's and its results' are many) the
    exception is printed as "Exception ignored" and lost, and the run went on to the end with exit
    0. A flag cannot be lost. In a thread other than the main one the handlers are left as they are
    (the event then never fires); so is a signal that is ignored."""
    import threading

    flag = threading.Event()
    received: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield flag
        return

    def handler(signum, frame):
        received.append(signum)
        flag.set()

    old = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}
    for sig in STOP_SIGNALS:
        if old[sig] is not signal.SIG_IGN:
            signal.signal(sig, handler)
    try:
        yield flag
        if flag.is_set():  # a stop while the pool was stopping (after the last result): still an interrupt
            raise KeyboardInterrupt
    except KeyboardInterrupt:
        if signal.SIGTERM in received:
            raise Terminated from None
        raise
    finally:
        for sig in STOP_SIGNALS:
            signal.signal(sig, old[sig])


def shard_files(config_dict: dict, spec_dict: dict) -> tuple[dict, dict[str, bytes]]:
    """A Ray task's body (`sensors.ray_backend.run_shards`): render one shard in a scratch
    directory and return (its record, {path relative to the shard directory: bytes})."""
    import tempfile

    _init_worker(1)  # one CPU per task (the task's num_cpus)
    with tempfile.TemporaryDirectory(prefix="hydrabench-ray-shard-") as tmp:
        record = generate_shard(config_dict, spec_dict, tmp)
        d = Path(tmp) / record["name"]
        files = {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}
    return record, files


def existing_record(root: Path, spec: ShardSpec, config: GenerateConfig, digest: bool = True) -> dict | None:
    """The record of an already complete shard, if it was made by the same config (UserError if it
    was made by another); `digest=False` only checks."""
    import json

    from sensors.dataset import shard_digest

    d = root / spec.name
    fj = d / "frames.json"
    if d.exists() and not d.is_dir():
        raise UserError(f"{d} is not a directory (a damaged shard); delete it and run again to render that shard anew")
    if d.is_dir() and not fj.exists():
        raise UserError(f"{d} has no frames.json (a damaged shard); delete {d} and run again to render it anew")
    if not fj.exists():
        return None
    try:
        head = json.loads(fj.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError):
        head = None
    if not isinstance(head, dict) or not isinstance(head.get("frames"), list):
        raise UserError(f"{fj} is damaged; delete {d} and run again to render that shard anew")
    if head.get("config") != config.to_dict() or head.get("shard") != asdict(spec):
        raise UserError(
            f"{root} holds shard {spec.name} of a different generation config; use an empty --out directory"
        )
    if head.get("sensor_model_version") != SENSOR_MODEL_VERSION:
        raise UserError(
            f"{root} holds shard {spec.name} made by sensor model version {head.get('sensor_model_version')!r} "
            f"(this code: {SENSOR_MODEL_VERSION!r}); use an empty --out directory"
        )
    if not digest:
        return None
    return {"name": spec.name, "sha256": shard_digest(d), "frames": len(head["frames"]), **asdict(spec),
            "seconds": 0.0, "timings": {}}


def generate(config: GenerateConfig, out: str | Path, workers: int = 1, progress: bool = True,
             backend: str = "local", address: str | None = None, start_method: str | None = None) -> dict:
    """Generate (or complete) the dataset in `out`. Returns a summary with timings.

    `backend`: "local" (this process, or a pool of `workers` processes) or "ray" (one Ray task per
    shard, `sensors.ray_backend`; `address` joins a running cluster, None starts a local instance
    with `workers` CPUs). The arrays are the same bytes whichever runs them. `start_method`: how the
    local pool starts its processes ("fork", "spawn"; None = `worker_start_method()`)."""
    if backend not in ("local", "ray"):
        raise UserError(f"unknown backend {backend!r} (choose from: local, ray)")
    if address and backend != "ray":
        raise UserError("--address is the Ray cluster to join: it needs --backend ray")
    import multiprocessing as mp

    if start_method is not None and start_method not in mp.get_all_start_methods():
        raise UserError(f"unknown start method {start_method!r} (choose from: {', '.join(mp.get_all_start_methods())})")
    # chosen (and HYDRABENCH_START_METHOD checked) before anything is touched; used if a pool runs
    pool_method = (start_method or worker_start_method()) if backend == "local" and workers > 1 else None

    from sensors.dataset import FORMAT_VERSION, clean_partial, foreign_entries, output_lock, write_manifest
    from sim.progress import progress as progress_bar

    root = Path(out)
    foreign = foreign_entries(root)
    if foreign:
        raise UserError(f"{root} is not empty and not a dataset (it holds {foreign[0]!r}); "
                        "use a new or empty --out directory")
    shards = plan(config)
    for s in shards:  # refuse a dataset of another config before touching anything
        existing_record(root, s, config, digest=False)
    root.mkdir(parents=True, exist_ok=True)
    # one generate at a time per --out (a second one is refused naming the holder); a failed or
    # interrupted run leaves no shard-*.tmp-PID/ behind (kill -9 does: the next run removes them)
    with output_lock(root, "generate"):
        try:
            clean_partial(root)
            records: dict[str, dict] = {}
            todo = []
            for s in shards:
                rec = existing_record(root, s, config)
                if rec is None:
                    todo.append(s)
                else:
                    records[s.name] = rec
            total = sum(s.frames for s in shards)
            bar = progress_bar(total=total, initial=sum(r["frames"] for r in records.values()), unit="frame",
                               desc="generate", enabled=progress)
            t0 = time.perf_counter()
            timings: dict[str, float] = {}

            def collect(rec: dict) -> None:
                records[rec["name"]] = rec
                for k, v in rec["timings"].items():
                    timings[k] = timings.get(k, 0.0) + v
                bar.update(rec["frames"])

            cfg = config.to_dict()
            ray_info = None
            method = None  # the local pool's start method, when a pool ran
            if backend == "ray":
                from sensors.ray_backend import run_shards

                ray_info = run_shards(shard_files, cfg, [asdict(s) for s in todo], root, collect, workers=workers,
                                      address=address)
            elif workers <= 1 or len(todo) <= 1:
                _init_worker(max(1, os.cpu_count() or 1))
                for s in todo:
                    collect(generate_shard(cfg, asdict(s), str(root)))
            else:
                method = pool_method
                ctx = mp.get_context(method)
                threads = max(1, (os.cpu_count() or 1) // workers)
                with _ctrl_c_as_flag() as interrupted, _start_pool(ctx, workers, threads) as pool:
                    results = [pool.apply_async(generate_shard, (cfg, asdict(s), str(root))) for s in todo]
                    for r in results:
                        while not r.ready() and not interrupted.is_set():
                            r.wait(0.2)
                        if interrupted.is_set():
                            raise KeyboardInterrupt
                        collect(r.get())
            bar.close()
            seconds = time.perf_counter() - t0
            frames_index = []
            for s in shards:
                for k in range(s.frames):
                    frames_index.append({"shard": s.name, "index": k, "context": s.context, "severity": s.severity})
            manifest = {
                "format_version": FORMAT_VERSION,
                "sensor_model_version": SENSOR_MODEL_VERSION,
                "created_by": "hydrabench generate",
                "config": cfg,
                "seed": config.seed,
                "profile": config.profile,
                "shards": [{k: v for k, v in records[s.name].items() if k not in ("timings", "seconds")} for s in shards],
                "frames": frames_index,
            }
            write_manifest(root, manifest)
            rendered = sum(records[s.name]["frames"] for s in todo)
            return {
                "frames": total,
                "frames_rendered": rendered,
                "seconds": round(seconds, 3),
                "frames_per_second": round(rendered / seconds, 3) if seconds > 0 and rendered else None,
                "profile": config.profile,
                "workers": workers,
                "backend": backend,
                **({"start_method": method} if method else {}),
                **({"ray": ray_info} if ray_info else {}),
                "ms_per_frame": {k: round(1000 * v / max(rendered, 1), 2) for k, v in sorted(timings.items())},
                "out": str(root),
            }
        except BaseException:
            clean_partial(root)
            raise
