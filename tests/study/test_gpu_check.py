"""The one-GPU check (scripts/gpu_check.sh, study/bench/gpu_check.py) on the CPU: its JSON, its
synthetic fallback, its order (render workers forked before CUDA), its one-line failures."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from study.bench import gpu_check
from study.commands import gpu_check as command
from tests.fusion.nets.conftest import TINY

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(autouse=True)
def _restore_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


@pytest.fixture
def tiny_model(monkeypatch):
    from fusion.nets import build_hydrafusion
    from study.engine.train import branch_set

    def build(profile):
        torch.manual_seed(0)
        return build_hydrafusion(profile=profile, branches=branch_set("paper", profile), **TINY)

    monkeypatch.setattr(gpu_check, "_model", build)


def test_plans_a_smaller_cpu_run_and_a_gpu_run_sized_for_minutes():
    gpu, cpu = gpu_check.plan(True), gpu_check.plan(False)
    assert gpu["profile"] == "paper" and gpu["contexts"] == "all" and cpu["profile"] == "cpu"
    assert cpu["steps"] < gpu["steps"] and gpu["batches"] == [1, 8] and cpu["batches"] == [1]
    assert gpu_check.plan(True, 3, 7, "fog")["frames_per_context"] == 3 and gpu_check.plan(False, 3, 7, "fog")["contexts"] == "fog"


def test_where_the_renderer_cannot_start_it_trains_on_synthetic_tensors_and_says_so(tmp_path, monkeypatch, capsys,
                                                                                     tiny_model):
    monkeypatch.setattr(gpu_check, "renderer_probe", lambda: {"ok": False, "error": "EGL: eglInitialize failed"})
    monkeypatch.setattr("sensors.generate.generate", lambda *a, **k: pytest.fail("generated without a renderer"))
    out = tmp_path / "check.json"
    assert command.main(["--device", "cpu", "--parts", "generate,train", "--steps", "1", "--work", str(tmp_path),
                         "--json", str(out), "--budget-s", "0"]) == 0
    printed = json.loads(capsys.readouterr().out)
    s = json.loads(out.read_text())
    assert s == printed
    assert s["completed"] == ["probe", "train_steps"] and "generate" not in s and "train_run" not in s
    assert s["renderer"] == {"ok": False, "error": "EGL: eglInitialize failed"}
    assert any(x.startswith("dataset: the renderer did not start (EGL: eglInitialize failed); training ran on "
                            "synthetic tensors") for x in s["skipped"])
    t = s["train_steps"]
    assert t["data"] == "synthetic" and t["steps"] == 1 and t["batch_size"] == 2 and len(t["branches"]) == 7
    assert t["images_per_second"] == pytest.approx(2 / t["seconds"], rel=1e-2)
    assert t["step_s_median"] > 0 and t["warmup_step_s"] > 0 and t["loss_after"] > 0
    assert s["device"]["device"] == "cpu" and s["gpus"] == 0


def test_training_speed_counts_the_timed_steps_alone(monkeypatch):
    """A slow warm-up step, model building and anything after the steps stay out of images/s."""
    now = {"t": 0.0}
    monkeypatch.setattr(gpu_check.time, "perf_counter", lambda: now["t"])

    class Model(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.w = torch.nn.Parameter(torch.ones(1))
            self.calls = 0

        def forward(self, inputs, targets):
            self.calls += 1
            now["t"] += 30.0 if self.calls == 1 else 0.5  # the first (warm-up) step is slow
            return {"total": (self.w * inputs["x"]).sum()}

    from study.engine.device import resolve_device

    setup = resolve_device(device="cpu", threads=1, amp=False)
    batches = [({"x": torch.ones(4, 1)}, [{}] * 4) for _ in range(5)]
    r = gpu_check.time_train_steps(Model(), batches, setup)
    assert r["steps"] == 4 and r["seconds"] == pytest.approx(2.0) and r["images_per_second"] == pytest.approx(8.0)
    assert r["warmup_step_s"] == pytest.approx(30.0) and r["step_s_median"] == pytest.approx(0.5)


def test_render_workers_are_forked_before_cuda_is_initialised(tmp_path, monkeypatch):
    """Pretend a GPU: the dataset is generated before this process resolves the device (which
    initialises CUDA) or calls anything in torch.cuda; the GPU count comes from a child process."""
    events = []
    monkeypatch.setattr(gpu_check, "cuda_device_count", lambda: 1)
    monkeypatch.setattr(gpu_check, "renderer_probe", lambda: {"ok": True, "renderer": "NVIDIA H200"})
    for name in ("is_available", "device_count", "init", "set_device", "current_device", "synchronize"):
        monkeypatch.setattr(torch.cuda, name, lambda *a, _n=name, **k: events.append(f"torch.cuda.{_n}"))

    def fake_generate(cfg, out, workers=1, progress=True, **kw):
        assert not torch.cuda.is_initialized()
        events.append("generate")
        assert cfg.profile == "paper" and len(cfg.contexts) == 8
        return {"frames": 16, "frames_per_second": 1.0}

    class Stop(Exception):
        pass

    def fake_resolve(*a, **k):
        events.append("resolve_device")
        raise Stop

    monkeypatch.setattr("sensors.generate.generate", fake_generate)
    monkeypatch.setattr("study.engine.device.resolve_device", fake_resolve)
    with pytest.raises(Stop):
        gpu_check.run_check(tmp_path, parts=("generate", "train"))
    assert events == ["generate", "resolve_device"]


def test_the_probes_run_in_child_processes():
    before = set(sys.modules)
    assert gpu_check.cuda_device_count() == (torch.cuda.device_count() if torch.cuda.is_available() else 0)
    ok, line = gpu_check._child("import sys; sys.exit('EGL: no display')", 60)
    assert not ok and line == "EGL: no display"
    assert "sensors.camera" not in set(sys.modules) - before  # the renderer probe's child holds the EGL context


def test_a_failure_is_one_line_and_the_json_keeps_what_was_measured(tmp_path, monkeypatch, capsys):
    def run_check(work, *a, on_update=None, **k):
        on_update({"completed": ["probe", "generate"], "generate": {"frames": 16}})
        raise RuntimeError("CUDA error: an illegal memory access was encountered\nmore text")

    monkeypatch.setattr(gpu_check, "run_check", run_check)
    out = tmp_path / "check.json"
    assert command.main(["--json", str(out), "--budget-s", "0"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith("gpu_check: error after generate: RuntimeError: CUDA error: an illegal memory access")
    s = json.loads(out.read_text())
    assert s["generate"] == {"frames": 16}
    assert s["error"]["type"] == "RuntimeError" and s["error"]["after"] == "generate"
    assert s["error"]["where"].startswith("tests/study/test_gpu_check.py:")


def test_the_time_budget_stops_the_check_with_what_it_had(tmp_path, monkeypatch, capsys):
    def run_check(work, *a, on_update=None, **k):
        on_update({"completed": ["probe"]})
        time.sleep(30)

    monkeypatch.setattr(gpu_check, "run_check", run_check)
    out = tmp_path / "check.json"
    t = time.perf_counter()
    assert command.main(["--json", str(out), "--budget-s", "0.5"]) == 124
    assert time.perf_counter() - t < 10
    assert "the time budget of 0.5 s ran out" in capsys.readouterr().err
    assert json.loads(out.read_text())["error"]["type"] == "TimeBudgetExceeded"


def test_bad_parts_are_refused_in_one_line(tmp_path, capsys):
    assert command.main(["--parts", "generate,fly", "--work", str(tmp_path), "--budget-s", "0"]) == 2
    assert "--parts: unknown fly" in capsys.readouterr().err


def test_the_script_names_what_cannot_be_imported_on_one_line(tmp_path):
    """A machine without the kit: gpu_check.sh stops before any work with one line."""
    fake = tmp_path / "site" / "shapely"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("raise ImportError('no shapely on this machine')\n")
    empty = tmp_path / "no-wheels"
    empty.mkdir()
    env = {**os.environ, "PYTHONPATH": str(tmp_path / "site"), "PYTHON": sys.executable, "KIT_WHEELS": str(empty)}
    r = subprocess.run([str(ROOT / "scripts" / "gpu_check.sh"), "--device", "cpu"], capture_output=True, text=True,
                       env=env, timeout=300)
    assert r.returncode == 3, r.stderr
    assert r.stderr.count("\n") == 1 and r.stdout == ""
    assert "gpu_check: missing on this machine (1 of" in r.stderr and "shapely (ImportError: no shapely" in r.stderr


def _stub_wheel(folder: Path, name: str, version: str) -> Path:
    """A pure-Python wheel of an importable stub package `name`."""
    import zipfile

    files = {f"{name}/__init__.py": "FROM_THE_KIT = True\n",
             f"{name}-{version}.dist-info/METADATA": f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n",
             f"{name}-{version}.dist-info/WHEEL": "Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\n"
                                                  "Tag: py3-none-any\n"}
    files[f"{name}-{version}.dist-info/RECORD"] = "".join(f"{p},,\n" for p in [*files, f"{name}-{version}.dist-info/RECORD"])
    path = folder / f"{name}-{version}-py3-none-any.whl"
    with zipfile.ZipFile(path, "w") as z:
        for p, text in files.items():
            z.writestr(p, text)
    return path


def test_the_script_installs_the_kit_where_a_module_is_missing_and_goes_on(tmp_path):
    """What the GPU machine does: shapely missing, the kit's wheel installed into a scratch site,
    the imports tried again, then the check itself starts (here it refuses --parts at once)."""
    fake = tmp_path / "site" / "shapely"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("raise ImportError('no shapely on this machine')\n")
    wheels = tmp_path / "whl"
    wheels.mkdir()
    _stub_wheel(wheels, "shapely", "2.2.0")
    site = tmp_path / "scratch-site"
    env = {**os.environ, "PYTHONPATH": str(tmp_path / "site"), "PYTHON": sys.executable, "KIT_WHEELS": str(wheels),
           "KIT_SITE": str(site)}
    r = subprocess.run([str(ROOT / "scripts" / "gpu_check.sh"), "--parts", "none", "--budget-s", "0"],
                       capture_output=True, text=True, env=env, timeout=300)
    assert (site / "shapely" / "__init__.py").read_text() == "FROM_THE_KIT = True\n"
    assert r.returncode == 2, r.stderr
    assert r.stderr.count("\n") == 1 and r.stderr.startswith("gpu_check: error: UserError: --parts: unknown none")


def test_the_bench_step_hands_its_plan_to_bench_inference_and_keeps_the_gpu_figures(tmp_path, monkeypatch):
    import study.bench.nets

    calls = []
    fake = {"latency_ms": {"all_branches": 9.0}, "peak_gpu_mb": {"all_branches": 900.0},
            "energy_j_per_frame": {"all_branches": 0.5}, "energy_above_idle_j_per_frame": {"all_branches": 0.3},
            "power_w": {"all_branches": 420.0}, "idle_power_w": {"all_branches": 80.0},
            "energy_source": "measured: NVML", "training_images_per_second": {"radar": 3.0}, "details": {"x": 1}}
    monkeypatch.setattr(study.bench.nets, "bench_inference", lambda *a, **k: calls.append((a, k)) or dict(fake))
    s = gpu_check.run_check(tmp_path, force_cpu=True, parts=("bench",))
    (profile,), kw = calls[0]
    plan = gpu_check.plan(False)
    assert profile == "cpu" and kw["device"] == "cpu" and kw["configurations"] == plan["configurations"]
    assert kw["batches"] == (1,) and kw["train_branches"] == plan["train_branches"]
    b = s["bench_inference"]
    assert b["energy_above_idle_j_per_frame"] == {"all_branches": 0.3} and b["idle_power_w"] == {"all_branches": 80.0}
    assert "details" not in b and s["train_images_per_second_per_branch"] == {"radar": 3.0}
    assert s["completed"] == ["probe", "bench"]


def test_each_call_gets_a_fresh_work_directory_so_a_rerun_times_everything_again(tmp_path, monkeypatch, capsys):
    seen = []

    def run_check(work, *a, on_update=None, **k):
        seen.append((work, sorted(p.name for p in work.iterdir())))
        (work / "data").mkdir()  # what a first attempt leaves: the next must not resume it
        summary = {"completed": ["probe"]}
        on_update(summary)
        return summary

    monkeypatch.setattr(gpu_check, "run_check", run_check)
    out = tmp_path / "check.json"
    for _ in range(2):
        assert command.main(["--work", str(tmp_path / "gc"), "--json", str(out), "--budget-s", "0"]) == 0
        assert json.loads(out.read_text())["work"] == str(seen[-1][0])
    (first, files1), (second, files2) = seen
    assert first != second and files1 == files2 == []
    assert first.parent == second.parent == tmp_path / "gc" and first.name.startswith("attempt-")
    assert (first / "data").is_dir()  # kept (--work), beside the new one
    capsys.readouterr()


def test_the_bench_figures_reach_the_json_as_each_task_ends(tmp_path, monkeypatch, capsys):
    import study.bench.nets

    def bench_inference(*a, on_result=None, **k):
        on_result({"latency_ms": {"single_camera": 5.0}, "training_images_per_second": {},
                   "tasks": {"done": 1, "of": 6}, "details": {"x": 1}})
        raise gpu_check.TimeBudgetExceeded("the time budget of 300 s ran out")

    monkeypatch.setattr(study.bench.nets, "bench_inference", bench_inference)
    out = tmp_path / "check.json"
    assert command.main(["--device", "cpu", "--parts", "bench", "--json", str(out), "--budget-s", "0"]) == 124
    s = json.loads(out.read_text())
    assert s["bench_inference"]["latency_ms"] == {"single_camera": 5.0}
    assert s["bench_inference"]["tasks"] == {"done": 1, "of": 6} and "details" not in s["bench_inference"]
    assert s["error"]["type"] == "TimeBudgetExceeded" and "bench" not in s["completed"]
    capsys.readouterr()
