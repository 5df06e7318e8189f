import contextlib
import fcntl
import os
import signal
from pathlib import Path

import pytest

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ["SDL_VIDEODRIVER"] = "offscreen"


def _pin_xdist_worker() -> None:
    """Under pytest-xdist (`make test` runs one worker per core), give each worker its own cores.

    Two workers that each let torch, numba or a subprocess use every core would fight over them
    (measured: 2 threads on a loaded 2-core machine run at 0.43-0.49 of 1 thread). Pinning the
    worker's affinity makes `study.engine.device.available_cores()`, torch's thread count and every
    subprocess the test starts use that worker's share of the machine. Results do not depend on it:
    every determinism test compares runs made under the same pinning.
    """
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1)
    if not worker.startswith("gw") or count < 2 or not hasattr(os, "sched_setaffinity"):
        return
    cores = sorted(os.sched_getaffinity(0))
    index = int(worker[2:])
    share = [c for i, c in enumerate(cores) if i % count == index % count] or [cores[index % len(cores)]]
    os.sched_setaffinity(0, share)  # (unpinned, threads only: 2026-12-08, half the suite in 7.5 min, not run out)
    os.environ["OMP_NUM_THREADS"] = str(len(share))
    import torch

    torch.set_num_threads(len(share))


_pin_xdist_worker()

# A shell that starts the suite in the background without job control (`make test &` in a script,
# nohup, some CI runners) hands it SIGINT ignored, and an ignored signal stays ignored across exec:
# the tests of Ctrl-C would send a SIGINT that neither the test process nor the commands it starts
# receive. The suite takes Python's default back, for itself and (at exec, as SIG_DFL) for its children.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

# The network the tests train: the cpu profile at a quarter of its width with a small head
# (`train --model`). What the tests check (resume, determinism, the stages, the tables' equations)
# does not depend on width, and it trains about 4x faster (the tiny study's train stage 60 s -> 13 s on
# an AVX2-only EPYC). The cpu profile's own sizes are built and run by tests/fusion/nets.
NARROW_MODEL = ("width=0.25", "roi_channels=32", "box_head_width=64")
NARROW_ARGS = [arg for item in NARROW_MODEL for arg in ("--model", item)]


# ------------------------------------------------------------------------------------------------
# `make test` hands whole files to its workers (--dist loadfile) in collection order
# (--no-loadscope-reorder: xdist would otherwise start with the files that have the most tests, and
# the few-test files below, which take most of the time, came last). These files go first, heaviest
# first (the sum of their tests' durations in a `make test` on the 2-core AVX2-only EPYC, 2026-12-07:
# 103 s for the tiny study's file down to 20 s),
# so that the many short files fill in at the end and both workers finish at about the same time.
# The two that compute the session caches come early: test_study_runner (the tiny study, read by the
# notebook test) and test_theory_measured (the theory cells, read by test_theory_cli and a notebook),
# and the notebooks only after three other files, so that no reader waits on the lock while a writer
# runs on the other worker. test_gates_fit (torch alone) comes before the theory cells: from a fresh
# clone the numba kernels compile on first use (~40 s of one core), and the tiny study and the theory
# cells both render at once, so each worker compiled the same sensor kernels beside the other; now the
# second worker trains gates while the first compiles, then renders from its cache. A file missing
# here just runs later; the order changes no result.
SLOW_FILES_FIRST = (
    "tests/study/test_study_runner.py",
    "tests/study/test_gates_fit.py",
    "tests/study/test_theory_measured.py",
    "tests/study/test_train.py",
    "tests/study/test_reference_model.py",
    "tests/notebooks/test_notebooks.py",
    "tests/study/test_fuzz.py",
    "tests/study/test_bench_scale.py",
    "tests/study/test_distributed.py",
    "tests/sensors/test_dataset.py",
    "tests/study/test_bench_generate.py",
    "tests/study/test_ecofusion.py",
    "tests/study/test_gpu_check.py",
    "tests/study/test_bench_recipe.py",
    "tests/study/test_bench_generate_against.py",
    "tests/study/test_gates.py",
    "tests/examples/test_classical_detectors.py",
    "tests/study/test_pem_study.py",
    "tests/study/test_nuscenes_metrics.py",
    "tests/study/test_gate_protocol.py",
    "tests/study/test_bench_amp.py",
    "tests/sensors/test_ray_backend.py",
)


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(SLOW_FILES_FIRST)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::")[0], len(rank)))  # stable: files stay whole


# ------------------------------------------------------------------------------------------------
# One cache for the whole session, shared by the xdist workers: the theory measurements and the
# tiny study are computed once (by whichever test needs them first) and read by the others. A file
# lock makes a second worker wait for the first instead of computing the same thing beside it.


@pytest.fixture(scope="session")
def shared_cache(tmp_path_factory) -> Path:
    """`<session tmp>/hydrabench-cache`, the same folder for every xdist worker of the session."""
    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent  # each worker's basetemp is <session tmp>/popen-gwN
    root = base / "hydrabench-cache"
    root.mkdir(parents=True, exist_ok=True)
    return root


@pytest.fixture(scope="session")
def cache_lock(shared_cache):
    """`with cache_lock("theory"):` holds an exclusive lock on one part of the shared cache."""

    @contextlib.contextmanager
    def hold(name: str):
        with open(shared_cache / f".{name}.lock", "w") as fh:
            fcntl.flock(fh, fcntl.LOCK_EX)
            try:
                yield shared_cache / name
            finally:
                fcntl.flock(fh, fcntl.LOCK_UN)

    return hold


@pytest.fixture(scope="session")
def shared_dataset(cache_lock):
    """`shared_dataset(GenerateConfig(...))`: that dataset, generated once per session (workers=1) by
    whichever test asks first and read by every other file that asks for the same config, on any
    xdist worker. Tests read it and never change it: one that damages or extends a dataset copies it."""
    import hashlib
    import json

    def get(config) -> Path:
        from sensors.generate import generate

        key = hashlib.sha256(json.dumps(config.to_dict(), sort_keys=True).encode()).hexdigest()[:16]
        with cache_lock(f"dataset-{key}") as out:
            if not (out / "manifest.json").exists():
                generate(config, out, workers=1, progress=False)
        return out

    return get


@pytest.fixture(scope="session")
def shared_nuscenes_export(shared_dataset, cache_lock):
    """`shared_nuscenes_export(GenerateConfig(...))`: (that dataset, its nuScenes export with the default
    splits), each made once per session by whichever test asks first. Read-only, as shared_dataset."""

    def get(config) -> tuple[Path, Path]:
        from study.experiments.nuscenes_export import export_nuscenes

        data = shared_dataset(config)
        with cache_lock(f"nuscenes-{data.name}") as root:
            out = root / "export"
            root.mkdir(parents=True, exist_ok=True)
            if not (out / "hydrabench_export.json").exists():
                export_nuscenes(data, out, progress=False)
        return data, out

    return get


# ------------------------------------------------------------------------------------------------
# Disk: the suite trains and checkpoints real networks (100-500 MB a run directory) and generates
# datasets; kept until the session ends, that is about 9 GB, more than a CI machine may have left
# beside the 5.5 GB venv (a CI run failed writing a checkpoint). pyproject's
# `tmp_path_retention_policy = "failed"` removes a passed test's tmp_path at its teardown; this
# removes what a module's own fixtures made with tmp_path_factory once the module is done, when
# none of its tests failed (a failure keeps everything, to look at). The session cache is kept.


@pytest.fixture(scope="module", autouse=True)
def _module_temp_removed_when_done(request, tmp_path_factory):
    import shutil

    base = tmp_path_factory.getbasetemp()
    before = set(base.iterdir())
    failed = request.session.testsfailed
    yield
    if request.session.testsfailed != failed:
        return
    for path in set(base.iterdir()) - before:
        if path.name != "hydrabench-cache" and path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
