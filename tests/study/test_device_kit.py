"""The device kit (scripts/device_kit.toml, scripts/device_kit.py): the wheels carried to the GPU
machine are exactly what the GPU check imports and that machine's image lacks, pinned to the lock."""

from __future__ import annotations

import functools
import importlib.metadata as md
import importlib.util
import re
import sys
from pathlib import Path

import pytest
from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[2]


def _load_script():
    spec = importlib.util.spec_from_file_location("device_kit", ROOT / "scripts" / "device_kit.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


kit_script = _load_script()
KIT = kit_script.load()
N = kit_script.normalise


def _lock() -> dict:
    pins = {}
    for line in (ROOT / "requirements.lock").read_text().splitlines():
        m = re.match(r"^([A-Za-z0-9_.\-]+)==([^\s;#]+)", line)
        if m:
            pins[N(m.group(1))] = m.group(2)
    return pins


@functools.lru_cache(maxsize=1)
def _providers() -> dict:
    return md.packages_distributions()  # a walk of every installed distribution's files: once


def _distributions(module: str) -> set[str]:
    """The installed distributions that provide top-level `module` (this environment has the lock)."""
    return {N(d) for d in _providers().get(module, [])}


def _requires(dist: str) -> set[str]:
    """A distribution's Requires-Dist on the GPU machine (Python 3.12, Linux x86-64), extras left out."""
    env = {"python_version": KIT["python"], "python_full_version": KIT["python"] + ".3", "sys_platform": "linux",
           "platform_system": "Linux", "platform_machine": "x86_64", "os_name": "posix",
           "implementation_name": "cpython", "platform_python_implementation": "CPython", "extra": ""}
    out = set()
    for text in md.requires(dist) or []:
        req = Requirement(text)
        if req.marker is None or req.marker.evaluate(env):
            out.add(N(req.name))
    return out


def test_the_walk_finds_module_level_and_function_level_imports(tmp_path):
    (tmp_path / "study").mkdir()
    (tmp_path / "sim").mkdir()
    (tmp_path / "study" / "__init__.py").write_text("")
    (tmp_path / "sim" / "__init__.py").write_text("import yaml\n")
    (tmp_path / "study" / "a.py").write_text("import json\nimport numpy as np\nfrom sim import b\n\n"
                                             "def f():\n    import ray\n    from . import c\n")
    (tmp_path / "sim" / "b.py").write_text("from shapely.geometry import Point\n")
    (tmp_path / "study" / "c.py").write_text("class K:\n    import trimesh\n")
    eager, lazy, modules = kit_script.import_walk(tmp_path, "study.a")
    assert set(eager) == {"numpy", "yaml", "shapely", "trimesh"}  # a class body runs at import
    assert set(lazy) == {"ray"}
    assert modules == {"study", "study.a", "sim", "sim.b", "study.c"}


def test_every_module_the_check_imports_is_on_the_gpu_image_or_in_the_kit():
    eager, lazy, reached = kit_script.import_walk(ROOT, KIT["entry"])
    assert {"study.bench.gpu_check", "sensors.generate", "study.engine.train", "fusion.nets.branch_gates"} <= reached
    provided = KIT["image"] | set(KIT["kit"])
    for module in sorted((set(eager) | set(lazy)) - set(KIT["lazy"])):
        dists = _distributions(module)
        assert dists, f"{module}: no installed distribution provides it"
        assert dists & provided, f"{module} ({', '.join(sorted(dists))}) is neither on the GPU image nor in the kit"


def test_lazy_exceptions_are_only_imported_inside_functions():
    eager, lazy, _ = kit_script.import_walk(ROOT, KIT["entry"])
    for module in KIT["lazy"]:
        assert module not in eager, f"{module} is imported at module level by {sorted(eager[module])}"
        assert module in lazy, f"[lazy] {module}: no longer reached, drop it from the kit file"


def test_the_kit_holds_nothing_the_image_has_and_nothing_unneeded():
    eager, lazy, _ = kit_script.import_walk(ROOT, KIT["entry"])
    needed = set().union(*(_distributions(m) for m in (set(eager) | set(lazy)) - set(KIT["lazy"])))
    assert not set(KIT["kit"]) & KIT["image"], "the image has these already"
    wanted = needed - KIT["image"]
    frontier = set(wanted)
    while frontier:  # the kit packages' own Requires-Dist, transitively
        frontier = set().union(*(_requires(d) for d in frontier)) - KIT["image"] - wanted
        wanted |= frontier
    for name, spec in KIT["kit"].items():
        if spec["imported_by"]:
            owner = Path(md.distribution(spec["imported_by"]).locate_file(""))
            files = [owner / str(f) for f in md.files(spec["imported_by"]) if str(f).endswith(".py")]
            module = next(iter(m for m, ds in _providers().items() if name in map(N, ds)))
            assert any(re.search(rf"^\s*(import|from) {module}\b", f.read_text(errors="replace"), re.M) for f in files), \
                f"{spec['imported_by']} does not import {module}"
            wanted.add(name)
    assert set(KIT["kit"]) == wanted


def test_every_kit_requirement_is_met_there():
    provided = KIT["image"] | set(KIT["kit"])
    for name in KIT["kit"]:
        missing = _requires(name) - provided
        assert not missing, f"{name} requires {', '.join(sorted(missing))}, on neither the image nor the kit"


def test_kit_versions_are_the_locked_ones():
    lock = _lock()
    for name, spec in KIT["kit"].items():
        assert lock.get(name) == spec["version"], f"{name}: kit {spec['version']}, requirements.lock {lock.get(name)}"
        assert md.version(name) == spec["version"]  # so the Requires-Dist read above is the kit's


def test_the_wheels_and_gl_folders_are_ignored():
    ignored = (ROOT / ".gitignore").read_text().splitlines()
    assert "/.whl/" in ignored and "/.gl/" in ignored


def test_download_builds_the_pip_commands_and_keeps_one_version_of_each(tmp_path):
    # a stand-in for pip that writes the wheel it was asked for and logs its arguments
    fake = tmp_path / "fakepip.py"
    fake.write_text("import sys, pathlib\nargs = sys.argv[1:]\n"
                    "open(sys.argv[0] + '.log', 'a').write(' '.join(args) + '\\n')\n"
                    "dest = pathlib.Path(args[args.index('-d' if '-d' in args else '-w') + 1])\n"
                    "name, version = args[-1].split('==')\n"
                    "(dest / f\"{name.replace('-', '_')}-{version}-py3-none-any.whl\").write_bytes(b'x')\n")
    dest = tmp_path / "whl"
    dest.mkdir()
    (dest / "shapely-1.0.0-cp312-cp312-manylinux_2_28_x86_64.whl").write_bytes(b"old")  # another version
    (dest / "trimesh-5.2.0-py3-none-any.whl").write_bytes(b"kept")  # already there: not fetched again
    kit = {**KIT, "kit": {n: {**s, "bytes": 4 if n == "trimesh" else 1} for n, s in KIT["kit"].items()}}  # the stand-ins' sizes
    wheels = kit_script.download(dest, kit, pip=(sys.executable, str(fake)))
    assert {kit_script.wheel_name(p) for p in wheels} == {(n, s["version"]) for n, s in KIT["kit"].items()}
    assert not (dest / "shapely-1.0.0-cp312-cp312-manylinux_2_28_x86_64.whl").exists()
    log = (tmp_path / "fakepip.py.log").read_text().splitlines()
    assert not any("trimesh" in ln for ln in log)
    shapely = next(ln for ln in log if ln.endswith("shapely==2.2.0"))
    assert shapely.startswith("download ") and "--python-version 3.12" in shapely and "--no-deps" in shapely
    assert "--platform manylinux_2_28_x86_64" in shapely and "--only-binary=:all:" in shapely
    pyopengl = next(ln for ln in log if ln.endswith("pyopengl==3.1.0"))
    assert pyopengl.startswith("wheel ") and "--no-binary pyopengl" in pyopengl


def test_check_names_every_missing_module_on_one_line(tmp_path, monkeypatch, capsys):
    (tmp_path / "hb_broken_so.py").write_text("raise OSError('libEGL.so.1: cannot open shared object file')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(kit_script, "needed_modules", lambda root=None, kit=None: ["json", "hb_no_such_module",
                                                                                    "hb_broken_so"])
    assert kit_script.check() == 3
    out = capsys.readouterr().out
    assert out.count("\n") == 1
    assert "2 of 3 modules" in out and "hb_no_such_module (ModuleNotFoundError" in out
    assert "hb_broken_so (OSError: libEGL.so.1" in out and "json (" not in out
    monkeypatch.setattr(kit_script, "needed_modules", lambda root=None, kit=None: ["json"])
    assert kit_script.check() == 0 and capsys.readouterr().out == ""


def test_a_renderer_that_cannot_load_its_gl_libraries_does_not_stop_the_check(tmp_path, monkeypatch, capsys):
    (tmp_path / "hb_gl.py").write_text("raise ImportError('Unable to load EGL library')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(kit_script, "load", lambda: {**KIT, "renderer": {"hb_gl", "hb_gl_absent"}})
    monkeypatch.setattr(kit_script, "needed_modules", lambda root=None, kit=None: ["json", "hb_gl"])
    assert kit_script.check() == 0
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1
    assert "the renderer will not start here (hb_gl (ImportError: Unable to load EGL library))" in err
    # a renderer package that is not there at all is a missing kit, not a missing driver
    monkeypatch.setattr(kit_script, "needed_modules", lambda root=None, kit=None: ["hb_gl_absent"])
    assert kit_script.check() == 3 and "hb_gl_absent (ModuleNotFoundError" in capsys.readouterr().out


def test_the_renderer_modules_are_the_ones_the_training_path_does_not_import():
    """Only modules that generation alone needs may fail softly: training and bench must not import them."""
    eager, lazy, _ = kit_script.import_walk(ROOT, "study.engine.train")
    for entry in ("study.bench.nets", "fusion.nets.branch_gates", "study.engine.device"):
        e, lz, _ = kit_script.import_walk(ROOT, entry)
        eager.update(e)
        lazy.update(lz)
    assert KIT["renderer"] and not KIT["renderer"] & (set(eager) | set(lazy))
    assert KIT["renderer"] <= set(kit_script.needed_modules(ROOT, KIT))


@pytest.mark.parametrize("name,expected", [("PyOpenGL", "pyopengl"), ("Farama_Notifications", "farama-notifications"),
                                           ("pygame.ce", "pygame-ce")])
def test_names_compare_as_pep_503_says(name, expected):
    assert N(name) == expected
