"""The on-disk dataset: deterministic whatever the workers, resumable after kill -9, verifiable,
readable with numpy + json alone, exportable to COCO."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from sensors.dataset import ARRAYS, DatasetReader, _save, verify
from sensors.generate import GenerateConfig, generate, plan
from sim.errors import UserError
from study.cli import main

CONFIG = GenerateConfig(contexts=("junction", "fog"), frames_per_context=2, sequence_length=1, seed=5, twins=True)
ARGS = ["--contexts", "junction,fog", "--frames-per-context", "2", "--sequence-length", "1", "--seed", "5", "--twins"]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    out = tmp_path_factory.mktemp("ref")
    summary = generate(CONFIG, out, workers=2, progress=False)
    return out, summary


def _digests(root: Path) -> dict:
    return {s["name"]: s["sha256"] for s in json.loads((root / "manifest.json").read_text())["shards"]}


def test_same_bytes_whatever_the_number_of_workers(reference, tmp_path):
    ref, summary = reference
    assert summary["frames"] == 4 and summary["workers"] == 2
    one = tmp_path / "one"
    generate(CONFIG, one, workers=1, progress=False)
    assert _digests(one) == _digests(ref)
    for shard in _digests(ref):
        for name in ARRAYS + ("lidar_points",):
            a, b = np.load(ref / shard / f"{name}.npy"), np.load(one / shard / f"{name}.npy")
            assert a.dtype == b.dtype and np.array_equal(a, b), (shard, name)


@pytest.mark.parametrize("method", ["fork", "spawn"])
def test_same_bytes_whichever_way_the_workers_start(reference, tmp_path, method):
    """Forked from a process that has not rendered (a fresh one, as `hydrabench generate` is), and
    spawned."""
    ref, _ = reference
    code = (f"import json, sys\nfrom sensors.generate import GenerateConfig, generate\n"
            f"s = generate(GenerateConfig.from_mapping(json.loads({json.dumps(json.dumps(CONFIG.to_dict()))})), sys.argv[1], workers=2, "
            f"progress=False, start_method={method!r})\nprint(json.dumps(s))")
    run = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, timeout=600,
                         cwd=Path(__file__).resolve().parents[2])
    assert run.returncode == 0, run.stderr[-2000:]
    assert json.loads(run.stdout)["start_method"] == method
    assert _digests(tmp_path) == _digests(ref)


def test_a_process_that_has_rendered_spawns_its_workers(monkeypatch, city, tmp_path):
    from sensors import camera
    from sensors.generate import worker_start_method

    assert camera._RENDERERS  # the city fixture rendered in this process
    assert worker_start_method() == "spawn"
    monkeypatch.setattr(camera, "_RENDERERS", {})
    assert worker_start_method() == "fork"
    monkeypatch.setenv("HYDRABENCH_START_METHOD", "spawn")
    assert worker_start_method() == "spawn"
    monkeypatch.setenv("HYDRABENCH_START_METHOD", "threads")
    with pytest.raises(UserError, match="HYDRABENCH_START_METHOD='threads'"):
        worker_start_method()
    with pytest.raises(UserError, match="HYDRABENCH_START_METHOD='threads'"):  # before anything is written
        generate(CONFIG, tmp_path / "never", workers=2, progress=False)
    assert not (tmp_path / "never").exists()
    with pytest.raises(UserError, match="unknown start method"):
        generate(CONFIG, "/nonexistent-never-created", workers=2, start_method="vfork")


def test_kill_9_then_rerun_completes_identically(reference, tmp_path):
    ref, _ = reference
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "study.cli", "generate", "--out", str(out), *ARGS]
    env = dict(os.environ)
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    deadline = time.time() + 240
    while time.time() < deadline and not (out / "shard-00000").exists():
        time.sleep(0.2)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert (out / "shard-00000").exists(), "the first shard never appeared"
    assert not (out / "manifest.json").exists()
    code = subprocess.run(cmd + ["--json"], capture_output=True, text=True, env=env)
    assert code.returncode == 0, code.stderr[-2000:]
    result = json.loads(code.stdout)
    assert result["frames"] == 4 and result["frames_rendered"] < 4  # the finished shard was kept
    assert _digests(out) == _digests(ref)
    assert not list(out.glob("*.tmp-*"))


def test_verify_names_corrupted_and_missing_shards(reference, tmp_path, capsys):
    ref, _ = reference
    copy = tmp_path / "copy"
    shutil.copytree(ref, copy)
    assert verify(copy) == []
    assert main(["verify", str(copy), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["ok"] is True
    f = copy / "shard-00001" / "radar_polar.npy"
    data = bytearray(f.read_bytes())
    data[-1] ^= 0xFF
    f.write_bytes(bytes(data))
    shutil.rmtree(copy / "shard-00002")
    assert main(["verify", str(copy)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "shard-00001: checksum mismatch" in err[0] and "shard-00002: missing" in err[0]


def test_reader_is_numpy_and_json_only(reference):
    ref, _ = reference
    r = DatasetReader(ref)
    assert len(r) == 4
    frame = r[1]
    assert frame["camera_left"].shape == (188, 336, 3) and frame["camera_left"].dtype == np.uint8
    assert frame["lidar_bev"].shape == (256, 256, 3) and frame["radar_polar"].shape == (400, 288)
    assert frame["lidar_points"].shape[1] == 5 and len(frame["lidar_points"]) == len(frame["lidar_instance"])
    assert isinstance(r._arrays[(r.index[1][0], "camera_left")], np.memmap)
    meta = frame["meta"]
    assert meta["context"] == "junction" and "calibration" in meta and "degradation" in meta
    labels = frame["labels"]
    assert set(labels) == {"camera_left", "camera_right", "bev", "objects"}
    for name in ("camera_left", "camera_right"):
        boxes = np.array(labels[name]["boxes"]).reshape(-1, 4)
        assert np.all(boxes[:, 2] > boxes[:, 0]) and np.all(boxes[:, 3] > boxes[:, 1])
    probe = subprocess.run([sys.executable, "-c", "import sys; from sensors.dataset import DatasetReader; "
                            f"r = DatasetReader({str(ref)!r}); r[0]; print('torch' in sys.modules)"],
                           capture_output=True, text=True)
    assert probe.stdout.strip() == "False", probe.stderr[-500:]  # sensors/ stays free of torch
    twins = DatasetReader(ref, clear=True)
    assert twins[2]["meta"]["weather"]["fog_visibility_m"] >= 10_000 > r[2]["meta"]["weather"]["fog_visibility_m"]
    np.testing.assert_array_equal(twins[2]["lidar_points"].shape[1], 5)
    # the manifest indexes every frame with its context and severity
    m = json.loads((ref / "manifest.json").read_text())
    assert [f["context"] for f in m["frames"]] == ["junction", "junction", "fog", "fog"]
    assert m["config"]["seed"] == 5 and len(m["shards"]) == len(plan(CONFIG))


def test_coco_export_loads_in_pycocotools(reference, tmp_path, capsys):
    from pycocotools.coco import COCO

    ref, _ = reference
    out = tmp_path / "coco" / "labels.json"
    assert main(["export-coco", str(ref), "--out", str(out)]) == 0
    coco = COCO(str(out))
    assert len(coco.getImgIds()) == 4
    r = DatasetReader(ref)
    n = sum(len(r.labels(i)["camera_right"]["ids"]) for i in range(len(r)))
    assert len(coco.getAnnIds()) == n
    ann = coco.loadAnns(coco.getAnnIds(imgIds=[1]))
    first = r.labels(0)["camera_right"]
    if first["boxes"]:
        x1, y1, x2, y2 = first["boxes"][0]
        np.testing.assert_allclose(ann[0]["bbox"], [x1, y1, x2 - x1, y2 - y1])


def test_show_draws_a_frame(reference, tmp_path):
    ref, _ = reference
    png = tmp_path / "f.png"
    assert main(["show", str(ref), "--index", "-1", "--out", str(png)]) == 0
    assert png.read_bytes()[:4] == b"\x89PNG"
    assert main(["show", str(ref), "--index", "9", "--out", str(png)]) == 2


def test_show_all_contexts_draws_one_picture_per_context_in_one_call(reference, tmp_path, capsys):
    ref, _ = reference
    contexts = sorted({f["context"] for f in DatasetReader(ref).manifest["frames"]})
    assert main(["show", str(ref), "--context", "all", "--out", str(tmp_path / "frame_{context}.png")]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(f"frame_{c}.png" for c in contexts)
    single = tmp_path / "one" / "x.png"
    single.parent.mkdir()
    assert main(["show", str(ref), "--context", contexts[0], "--out", str(single)]) == 0
    assert (tmp_path / f"frame_{contexts[0]}.png").read_bytes() == single.read_bytes()  # the same frame, drawn alike
    capsys.readouterr()
    # all needs {context} in --out; an index one context lacks is refused before any picture
    assert main(["show", str(ref), "--context", "all", "--out", str(tmp_path / "x.png")]) == 2
    assert "{context}" in capsys.readouterr().err
    assert main(["show", str(ref), "--context", "all", "--index", "50", "--out", str(tmp_path / "n_{context}.png")]) == 2
    assert not list(tmp_path.glob("n_*"))


@pytest.mark.parametrize("argv, needle", [
    (["generate", "--out", "{tmp}/x", "--contexts", "volcano"], "unknown context"),
    (["generate", "--out", "{tmp}/x", "--severities", "2,9"], "severities"),
    (["generate", "--out", "/proc/nope/x"], "not writable"),
    (["generate", "--out", "{tmp}/x", "--profile", "gpu"], "unknown profile"),
    (["generate", "--out", "{tmp}/x", "--config", "{tmp}/bad.yaml"], "unknown key 'framez'"),
    (["verify", "{tmp}/nothing"], "does not exist"),
])
def test_generate_bad_input_is_one_line_exit_2(argv, needle, tmp_path, capsys):
    (tmp_path / "bad.yaml").write_text("framez: 3\n")
    code = main([a.replace("{tmp}", str(tmp_path)) for a in argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and needle in err[0], err
    assert not (tmp_path / "x" / "manifest.json").exists()


def test_a_directory_from_another_config_is_refused(reference, tmp_path, capsys):
    ref, _ = reference
    copy = tmp_path / "other"
    shutil.copytree(ref, copy)
    code = main(["generate", "--out", str(copy), "--contexts", "junction,fog", "--frames-per-context", "2",
                 "--sequence-length", "1", "--seed", "6"])
    assert code == 2 and "different generation config" in capsys.readouterr().err


def test_save_writes_np_saves_bytes_for_every_layout(tmp_path):
    """sensors.dataset._save copies strided arrays to C order (fast write); the file keeps np.save's
    bytes, Fortran-ordered arrays included (np.save stores those as such)."""
    rng = np.random.default_rng(0)
    bev = [rng.integers(0, 255, (3, 16, 16), dtype=np.uint8).transpose(1, 2, 0) for _ in range(4)]
    cases = {
        "strided_stack": np.stack(bev),  # like lidar_bev: a stack of transposed views
        "c_order": rng.uniform(size=(4, 5, 3)).astype(np.float32),
        "fortran": np.asfortranarray(rng.uniform(size=(4, 5, 3))),
        "step": np.arange(40, dtype=np.int64)[::3],
        "empty": np.zeros((0, 5), np.float32),
        "scalar": np.array(7, np.int64),
    }
    assert not cases["strided_stack"].flags.c_contiguous and not cases["strided_stack"].flags.f_contiguous
    for name, a in cases.items():
        np.save(tmp_path / f"{name}_ref.npy", a)
        _save(tmp_path / f"{name}.npy", a)
        assert (tmp_path / f"{name}.npy").read_bytes() == (tmp_path / f"{name}_ref.npy").read_bytes(), name


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="names fsynced files through /proc")
def test_commit_fsyncs_every_file_before_the_rename(tmp_path, monkeypatch):
    """The durability contract of commit_shard: every file (twins included) fsynced before the atomic
    rename, the directory after it; an fsync error aborts the commit and leaves no shard."""
    import sensors.dataset as ds

    tmp = tmp_path / "shard-00000.tmp-1"
    (tmp / "clear").mkdir(parents=True)
    files = [tmp / "a.npy", tmp / "frames.json", tmp / "clear" / "a.npy", tmp / "clear" / "frames.json"]
    for f in files:
        f.write_bytes(b"x")
    events = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        real_fsync(fd)

    def replace(a, b):
        events.append(("replace", str(b)))
        real_replace(a, b)

    monkeypatch.setattr(ds.os, "fsync", fsync)
    monkeypatch.setattr(ds.os, "replace", replace)
    final = tmp_path / "shard-00000"
    ds.commit_shard(tmp, final)
    k = events.index(("replace", str(final)))
    assert sorted(p for _, p in events[:k]) == sorted(str(f) for f in files)
    assert events[k + 1:] == [("fsync", str(tmp_path))]
    assert final.is_dir() and not tmp.exists()

    def failing(fd):
        raise OSError(5, "Input/output error")

    tmp2 = tmp_path / "shard-00001.tmp-1"
    tmp2.mkdir()
    (tmp2 / "a.npy").write_bytes(b"x")
    monkeypatch.setattr(ds.os, "fsync", failing)
    with pytest.raises(OSError):
        ds.commit_shard(tmp2, tmp_path / "shard-00001")
    assert tmp2.is_dir() and not (tmp_path / "shard-00001").exists()


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="names fsynced files through /proc")
def test_write_frames_flushes_every_file_it_writes(reference, tmp_path, monkeypatch):
    """write_frames fsyncs each file as it goes (commit_shard then finds them on disk) and reports
    a failed fsync; the files keep the bytes of the reference shard."""
    import sensors.dataset as ds
    from sensors.generate import render_sequence

    ref, _ = reference
    spec = plan(CONFIG)[0]
    frames, _, _ = render_sequence(spec, CONFIG)
    synced = []
    real_fsync = os.fsync

    def fsync(fd):
        synced.append(os.readlink(f"/proc/self/fd/{fd}"))
        real_fsync(fd)

    monkeypatch.setattr(ds.os, "fsync", fsync)
    out = tmp_path / "shard"
    extra = json.loads((ref / spec.name / "frames.json").read_text())
    extra = {k: v for k, v in extra.items() if k not in ("format_version", "frames")}
    ds.write_frames(out, frames, extra)
    written = sorted(str(p) for p in out.iterdir())
    assert sorted(synced) == written and len(written) == len(ARRAYS) + 4
    for p in out.iterdir():
        assert p.read_bytes() == (ref / spec.name / p.name).read_bytes(), p.name

    def failing(fd):
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(ds.os, "fsync", failing)
    with pytest.raises(OSError):
        ds.write_frames(tmp_path / "failing", frames, extra)
