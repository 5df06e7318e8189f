"""The device kit: what `scripts/gpu_check.sh` needs on a GPU machine whose image lacks it.

The lent GPU machine (docs/gpu.md) has Python 3.12, torch and many packages, but not the
simulator's and renderer's (shapely, trimesh, pyrender, highway-env, ...) and it reaches no
registry. `scripts/device_kit.toml` lists those packages, pinned to requirements.lock; this script

  download [--dest .whl]   fetches their cp312 manylinux wheels (building a wheel where PyPI has
                           only a source archive) into the ignored folder `.whl/`, keeps one
                           version of each, and prints the kit's size;
  gl [--dest .gl]          fetches the OpenGL/EGL loader packages (.deb, amd64) the GPU machine
                           lacks, with apt-get, as the `device` README says (about 0.4 MB);
  check                    imports every third-party module the check can reach and prints ONE
                           line naming the missing ones (exit 3), or nothing (exit 0);
  modules                  prints those modules, one per line.

Standard library only (it runs before anything is installed). The import walk parses every module
reachable from the kit file's `entry` with ast, module-level and function-level imports alike.
"""

from __future__ import annotations

import ast
import importlib
import re
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
KIT_FILE = Path(__file__).resolve().with_suffix(".toml")
FIRST_PARTY = ("sim", "sensors", "fusion", "study")
PLATFORMS = ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_24_x86_64", "manylinux_2_17_x86_64",
             "manylinux2014_x86_64", "manylinux1_x86_64")


def normalise(name: str) -> str:
    """A distribution name as PEP 503 compares them ("PyOpenGL" and "pyopengl", "Foo_Bar" and "foo-bar")."""
    return re.sub(r"[-_.]+", "-", name).lower()


def load(path: Path = KIT_FILE) -> dict:
    """The kit file: {"entry", "python", "kit": {name: {"version", "sdist", "imported_by"}},
    "lazy": {module: why}, "renderer": set of modules, "image": set of names}, names normalised."""
    raw = tomllib.loads(path.read_text())
    kit = {}
    for name, v in raw["kit"].items():
        entry = v if isinstance(v, dict) else {"version": v}
        kit[normalise(name)] = {"version": str(entry["version"]), "sdist": bool(entry.get("sdist", False)),
                                "imported_by": entry.get("imported_by")}
    return {"entry": raw["entry"], "python": raw["python"], "kit": kit, "lazy": dict(raw.get("lazy", {})),
            "renderer": set(raw.get("renderer", [])),
            "image": {normalise(n) for n in raw["image"]["packages"]}}


def _module_file(root: Path, module: str) -> Path | None:
    p = root.joinpath(*module.split("."))
    if (p / "__init__.py").is_file():
        return p / "__init__.py"
    if p.with_suffix(".py").is_file():
        return p.with_suffix(".py")
    return None  # a name imported from a module ("from sim.errors import UserError"), not a module


def _imports(tree: ast.Module, package: str):
    """(imported name, inside a function?) for every import statement of a module."""
    def visit(node, in_function):
        for child in ast.iter_child_nodes(node):
            inside = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, ast.Import):
                for a in child.names:
                    yield a.name, in_function
            elif isinstance(child, ast.ImportFrom):
                if child.level:  # relative: resolved against this module's package
                    parts = package.split(".")
                    base = ".".join(parts[:len(parts) - child.level + 1] + ([child.module] if child.module else []))
                else:
                    base = child.module
                yield base, in_function
                for a in child.names:
                    yield f"{base}.{a.name}", in_function
            yield from visit(child, inside)

    yield from visit(tree, False)


def import_walk(root: Path = ROOT, entry: str = "study.commands.gpu_check") -> tuple[dict, dict, set]:
    """Walk the first-party modules reachable from `entry` (every import followed, parents included,
    since importing a.b runs a/__init__.py). Returns (eager, lazy, modules): eager and lazy map each
    third-party top-level module to the first-party modules that import it at module level / only
    inside functions; modules is the set of first-party modules reached."""
    seen: set[str] = set()
    eager: dict[str, set] = {}
    lazy: dict[str, set] = {}
    todo = [entry]
    while todo:
        module = todo.pop()
        if module in seen:
            continue
        path = _module_file(root, module)
        if path is None:
            continue
        seen.add(module)
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        for name, in_function in _imports(ast.parse(path.read_text(), str(path)), package):
            top = name.split(".")[0]
            if top in FIRST_PARTY:
                parts = name.split(".")
                todo.extend(".".join(parts[:i]) for i in range(1, len(parts) + 1))
            elif top not in sys.stdlib_module_names and top != "__future__":
                (lazy if in_function else eager).setdefault(top, set()).add(module)
    lazy = {k: v for k, v in lazy.items() if k not in eager}
    return eager, lazy, seen


def needed_modules(root: Path = ROOT, kit: dict | None = None) -> list[str]:
    """Every third-party top-level module the check can import, but those the kit file's [lazy]
    table names (imported only inside functions the check never calls)."""
    kit = kit or load()
    eager, lazy, _ = import_walk(root, kit["entry"])
    return sorted((set(eager) | set(lazy)) - set(kit["lazy"]))


def failed_imports(modules) -> list[tuple[str, BaseException]]:
    """(module, exception) for each module that does not import here."""
    failed = []
    for m in modules:
        try:
            importlib.import_module(m)
        except Exception as exc:  # ImportError, or OSError from a library the wheel's .so needs
            failed.append((m, exc))
    return failed


def describe(failed) -> str:
    """`module (ExceptionType: first line); ...`"""
    return "; ".join(f"{m} ({type(e).__name__}: {(str(e).splitlines() or [''])[0]})" for m, e in failed)


def check(root: Path = ROOT) -> int:
    """Import what the check needs (torch first, the way the check does). What is missing: one
    line on stdout, exit 3. A renderer module (the kit file's `renderer`) that is installed but
    cannot load its GL libraries does not stop the check, which then trains on synthetic tensors:
    one line on stderr says so."""
    kit = load()
    modules = needed_modules(root, kit)
    ordered = [m for m in ("torch", "torchvision") if m in modules] + [m for m in modules if m not in ("torch", "torchvision")]
    failed = failed_imports(ordered)
    soft = [(m, e) for m, e in failed if m in kit["renderer"] and not isinstance(e, ModuleNotFoundError)]
    fatal = [(m, e) for m, e in failed if (m, e) not in soft]
    if soft:
        sys.stderr.write(f"gpu_check: the renderer will not start here ({describe(soft)}); the check trains on "
                         "synthetic tensors (docs/gpu.md: carry .gl)\n")
    if fatal:
        sys.stdout.write(f"gpu_check: missing on this machine ({len(fatal)} of {len(modules)} modules): "
                         f"{describe(fatal)}; carry the device kit (python3 scripts/device_kit.py download, "
                         "carry .whl; docs/gpu.md)\n")
        return 3
    return 0


def wheel_name(path: Path) -> tuple[str, str]:
    """(normalised distribution, version) of a wheel file's name."""
    name, version = path.name.split("-")[:2]
    return normalise(name), version


def download(dest: Path, kit: dict | None = None, pip: tuple = (sys.executable, "-m", "pip")) -> list[Path]:
    """Fetch the kit's wheels into `dest` (see the module doc); wheels there of other packages or
    versions are removed (two versions of one package stop the install)."""
    kit = kit or load()
    dest.mkdir(parents=True, exist_ok=True)
    for path in dest.glob("*.whl"):
        name, version = wheel_name(path)
        if kit["kit"].get(name, {}).get("version") != version:
            path.unlink()
    have = {wheel_name(p)[0] for p in dest.glob("*.whl")}
    for name, spec in sorted(kit["kit"].items()):
        if name in have:
            continue
        req = f"{name}=={spec['version']}"
        if spec["sdist"]:  # pure Python with no wheel on PyPI: build one (py3-none-any)
            cmd = [*pip, "wheel", "-q", "--no-deps", "--no-binary", name, "-w", str(dest), req]
        else:
            cmd = [*pip, "download", "-q", "--no-deps", "--only-binary=:all:", "--python-version", kit["python"],
                   "--implementation", "cp", *[a for p in PLATFORMS for a in ("--platform", p)], "-d", str(dest), req]
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0:
            lines = [ln for ln in (r.stderr + r.stdout).splitlines() if "ERROR" in ln] or (r.stderr + r.stdout).splitlines()
            raise SystemExit(f"device_kit: {req}: {lines[-1] if lines else 'pip failed'}")
    wheels = sorted(dest.glob("*.whl"))
    got = {wheel_name(p)[0] for p in wheels}
    if got != set(kit["kit"]):
        raise SystemExit(f"device_kit: {dest} lacks {', '.join(sorted(set(kit['kit']) - got))}")
    return wheels


GL_PACKAGES = ("libvulkan1", "libegl1", "libglvnd0", "libopengl0", "libgl1", "libglx0", "libgles2")
"""The loaders (glvnd's libEGL, libOpenGL, ...) that pyrender's EGL platform opens; the NVIDIA driver
there brings the vendor library. Unpacked there with `dpkg -x` (docs/gpu.md)."""


def download_gl(dest: Path, lists: Path = Path("/tmp/amd64")) -> list[Path]:
    """Fetch GL_PACKAGES as amd64 .deb files into `dest` with apt-get (its lists kept in `lists`)."""
    dest.mkdir(parents=True, exist_ok=True)
    (lists / "partial").mkdir(parents=True, exist_ok=True)
    opts = ["-oAPT::Architecture=amd64", "-oAPT::Architectures=amd64", f"-oDir::State::Lists={lists}"]
    for cmd, cwd in ((["apt-get", *opts, "update", "-qq"], None), (["apt-get", *opts, "download", "-qq", *GL_PACKAGES], dest)):
        r = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
        if r.returncode != 0:
            lines = (r.stderr + r.stdout).strip().splitlines()
            raise SystemExit(f"device_kit: {' '.join(cmd[:1] + cmd[-1:])}: {lines[-1] if lines else 'failed'}")
    return sorted(dest.glob("*.deb"))


def main(argv=None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="device_kit", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True)
    d = sub.add_parser("download", help="fetch the kit's wheels into --dest")
    d.add_argument("--dest", default=str(ROOT / ".whl"))
    g = sub.add_parser("gl", help="fetch the EGL/OpenGL loader .debs into --dest")
    g.add_argument("--dest", default=str(ROOT / ".gl"))
    sub.add_parser("check", help="one line naming what the check cannot import here")
    sub.add_parser("modules", help="the third-party modules the check can import")
    args = ap.parse_args(argv)
    if args.command == "download":
        wheels = download(Path(args.dest))
        total = sum(p.stat().st_size for p in wheels)
        for p in wheels:
            sys.stdout.write(f"{p.stat().st_size / 2**20:7.2f} MiB  {p.name}\n")
        sys.stdout.write(f"{total / 2**20:7.2f} MiB  {len(wheels)} wheels in {args.dest}\n")
        return 0
    if args.command == "gl":
        debs = download_gl(Path(args.dest))
        sys.stdout.write(f"{sum(p.stat().st_size for p in debs) / 2**20:7.2f} MiB  {len(debs)} packages in {args.dest}\n")
        return 0
    if args.command == "check":
        return check()
    sys.stdout.write("".join(f"{m}\n" for m in needed_modules()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
