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
  modules                  prints those modules, one per line;
  slim [--dry-run]         before a `device` call: moves the tracked files the check never reads
                           (the kit file's [slim]) into the git directory, a journal written first,
                           prints what travels (MiB by part) and refuses (exit 2) above the limit;
  restore                  after it: puts them back, also after a slim that was interrupted.

Standard library only (it runs before anything is installed). The import walk parses every module
reachable from the kit file's `entry` with ast, module-level and function-level imports alike.
"""

from __future__ import annotations

import ast
import importlib
import io
import json
import os
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
    "lazy": {module: why}, "renderer": set of modules, "gl": {package: bytes}, "slim": {"paths": globs,
    "carry": paths, "limit_mib"}, "image": set of names}, names normalised; "bytes": the wheel's size."""
    raw = tomllib.loads(path.read_text())
    kit = {}
    for name, v in raw["kit"].items():
        entry = v if isinstance(v, dict) else {"version": v}
        kit[normalise(name)] = {"version": str(entry["version"]), "sdist": bool(entry.get("sdist", False)),
                                "imported_by": entry.get("imported_by"), "bytes": entry.get("bytes")}
    slim = raw.get("slim", {})
    return {"entry": raw["entry"], "python": raw["python"], "kit": kit, "lazy": dict(raw.get("lazy", {})),
            "renderer": set(raw.get("renderer", [])), "gl": dict(raw.get("gl", {})),
            "slim": {"paths": list(slim.get("paths", [])), "carry": list(slim.get("carry", [".whl", ".gl"])),
                     "limit_mib": float(slim.get("limit_mib", 60))},
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
    for p in wheels:
        problem = size_problem(p.stat().st_size, kit["kit"][wheel_name(p)[0]])
        if problem:
            raise SystemExit(f"device_kit: {p.name}: {problem}")
    return wheels


SDIST_SIZE_TOLERANCE = 0.02
"""A wheel built here from a source archive differs by a few bytes with the builder's version (its
metadata); a downloaded one is the registry's file, byte for byte."""


def size_problem(size: int, spec: dict) -> str | None:
    """Why a wheel of `size` bytes is not the kit file's (None: it is)."""
    pinned = spec.get("bytes")
    if pinned is None:
        return "no `bytes` in the kit file (add the size, it counts towards what travels)"
    tolerance = SDIST_SIZE_TOLERANCE * pinned if spec.get("sdist") else 0
    if abs(size - pinned) > tolerance:
        return f"{size} bytes, the kit file pins {pinned} (another build? update scripts/device_kit.toml)"
    return None


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
    debs = sorted(dest.glob("*.deb"))
    pinned = load()["gl"]
    grown = [p.name for p in debs if p.stat().st_size > pinned.get(p.name.split("_")[0], 0)]
    if grown:  # apt's versions move: a warning, the travel test counts the pinned sizes
        sys.stderr.write(f"device_kit: larger than scripts/device_kit.toml's [gl] sizes: {', '.join(grown)}\n")
    return debs


MIB = 2**20
STATE = "device-kit-slim"
"""The folder under the git directory (`git rev-parse --git-dir`: per worktree, on the working tree's
filesystem, so a move is one atomic rename) where `slim` parks files, with its journal."""


def _git(root: Path, *args: str) -> str:
    r = subprocess.run(["git", *args], cwd=root, capture_output=True, text=True)
    if r.returncode != 0:
        raise SlimError(f"git {' '.join(args[:2])}: {(r.stderr.strip().splitlines() or ['failed'])[-1]}")
    return r.stdout


class SlimError(Exception):
    """What `slim` / `restore` refuse to do, in one line (exit 2)."""


def _git_files(root: Path, *args: str) -> list[str]:
    return [p for p in _git(root, "ls-files", "-z", *args).split("\0") if p]


def _size(path: Path) -> int:
    """Bytes under `path` (a file, a link as a link, or a folder walked without following links)."""
    if path.is_symlink() or path.is_file():
        return path.lstat().st_size
    return sum(p.lstat().st_size for p in path.rglob("*") if p.is_symlink() or p.is_file())


def slim_files(root: Path = ROOT, kit: dict | None = None) -> list[str]:
    """The tracked files, present in the working tree, that the kit file's [slim] globs match."""
    from fnmatch import fnmatchcase

    kit = kit or load()
    return [p for p in _git_files(root) if any(fnmatchcase(p, g) for g in kit["slim"]["paths"])
            and (root / p).is_file() and not (root / p).is_symlink()]


def pinned_size(carried: str, kit: dict) -> int | None:
    """What the kit file says a carried folder weighs where it is not here (.whl, .gl), else None."""
    name = carried.strip("/")
    if name == ".whl":
        return sum(s["bytes"] or 0 for s in kit["kit"].values())
    if name == ".gl":
        return sum(kit["gl"].values())
    return None


def travel(root: Path = ROOT, carry=None, kit: dict | None = None, leaving=()) -> dict:
    """What one `device` call sends (bytes by part): tracked files present in the working tree,
    untracked files git does not ignore, the folder shared/ where the checkout has one, and each
    carried path (measured where it is here, else the kit file's pinned size, "pinned": True).
    `leaving`: tracked paths to count as gone (what `slim` would move)."""
    kit = kit or load()
    carry = kit["slim"]["carry"] if carry is None else list(carry)
    gone = set(leaving)
    tracked = [p for p in _git_files(root) if p not in gone]
    parts = {"tracked": sum((root / p).lstat().st_size for p in tracked if os.path.lexists(root / p)),
             "untracked": sum((root / p).lstat().st_size for p in _git_files(root, "--others", "--exclude-standard"))}
    shared = root / "shared"
    if shared.is_dir():  # it travels even where ignored: count what the two lists above left out
        listed = {str(root / p) for p in tracked} | {str(root / p) for p in _git_files(root, "--others", "--exclude-standard")}
        parts["shared/"] = sum(p.lstat().st_size for p in shared.rglob("*")
                               if (p.is_symlink() or p.is_file()) and str(p) not in listed)
    carried = {}
    for c in carry:
        here = root / c
        if os.path.lexists(here):
            carried[c] = {"bytes": _size(here), "pinned": False}
        else:
            carried[c] = {"bytes": pinned_size(c, kit) or 0, "pinned": pinned_size(c, kit) is not None}
    total = sum(parts.values()) + sum(c["bytes"] for c in carried.values())
    return {**parts, "carried": carried, "total": total, "limit_mib": kit["slim"]["limit_mib"]}


def format_travel(t: dict) -> str:
    lines = [f"{t['tracked'] / MIB:7.2f} MiB  tracked files in the working tree",
             f"{t['untracked'] / MIB:7.2f} MiB  untracked files git does not ignore"]
    if "shared/" in t:
        lines.append(f"{t['shared/'] / MIB:7.2f} MiB  shared/")
    for c, v in t["carried"].items():
        lines.append(f"{v['bytes'] / MIB:7.2f} MiB  carried {c}" + (" (not here: the kit file's pinned size)" if v["pinned"] else ""))
    lines.append(f"{t['total'] / MIB:7.2f} MiB  in all (limit {t['limit_mib']:g} MiB)")
    return "\n".join(lines)


def _state(root: Path) -> Path:
    git_dir = Path(_git(root, "rev-parse", "--git-dir").strip())
    return (git_dir if git_dir.is_absolute() else root / git_dir) / STATE


def _write_journal(journal: Path, entries: list[dict]) -> None:
    """Written (and flushed to disk) before any file moves, so `restore` always knows what moved."""
    journal.parent.mkdir(parents=True, exist_ok=True)
    tmp = journal.with_name(journal.name + ".tmp")
    with open(tmp, "w") as fh:
        json.dump({"version": 1, "files": entries}, fh, indent=1)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, journal)


def slim(root: Path = ROOT, kit: dict | None = None, dry_run: bool = False, carry=None, out=sys.stdout) -> dict:
    """Move the [slim] files into the git directory (a journal first), hide them from `git status`
    (skip-worktree, which also keeps `git commit -a` from recording them as deleted), print what
    travels. Refused (SlimError, nothing moved) where that would still pass the limit. A slim state
    left before is restored first."""
    kit = kit or load()
    if not dry_run:
        restore(root, out=io.StringIO())
    files = slim_files(root, kit)
    t = travel(root, carry, kit, leaving=files)
    if t["total"] > t["limit_mib"] * MIB:
        parts = ", ".join(f"{k} {v / MIB:.2f}" for k, v in t.items() if k in ("tracked", "untracked", "shared/")) + ", " + \
            ", ".join(f"{c} {v['bytes'] / MIB:.2f}" for c, v in t["carried"].items())
        raise SlimError(f"{t['total'] / MIB:.2f} MiB would travel ({parts} MiB), over the {t['limit_mib']:g} MiB limit "
                        "even slimmed: add large tracked files the GPU check does not read to [slim] in "
                        "scripts/device_kit.toml, or remove untracked ones")
    out.write(format_travel(t) + "\n")
    moved = sum((root / p).stat().st_size for p in files)
    out.write(f"{moved / MIB:7.2f} MiB  in {len(files)} tracked files {'that slim would move' if dry_run else 'moved'}"
              " out of the working tree (scripts/device_kit.toml [slim])\n")
    if dry_run or not files:
        return t
    state = _state(root)
    _write_journal(state / "journal.json", [{"path": p, "bytes": (root / p).stat().st_size} for p in files])
    _git(root, "update-index", "--skip-worktree", "--", *files)
    for p in files:
        (state / "files" / p).parent.mkdir(parents=True, exist_ok=True)
        os.rename(root / p, state / "files" / p)
    where = "" if Path(root).resolve() == ROOT else f" --root {root}"
    out.write(f"python3 scripts/device_kit.py restore{where}   # after the `device` call (make demo / make test do it too)\n")
    return t


def restore(root: Path = ROOT, out=sys.stdout) -> int:
    """Put back what `slim` moved, from its journal, also after a slim killed half-way; nothing to do
    is no error (idempotent). Returns the number of files put back. A file that is in both places
    with other bytes is left in both (SlimError): the journal stays for the next try."""
    try:
        state = _state(root)
    except (SlimError, OSError):  # no git checkout (an unpacked archive) or no git: nothing was slimmed
        return 0
    journal = state / "journal.json"
    if not journal.exists():
        return 0
    entries = json.loads(journal.read_text())["files"]
    back, conflicts, lost = 0, [], []
    for e in entries:
        here, parked = root / e["path"], state / "files" / e["path"]
        if parked.exists() and here.exists():
            if parked.read_bytes() != here.read_bytes():
                conflicts.append(e["path"])
                continue
            parked.unlink()
        elif parked.exists():
            here.parent.mkdir(parents=True, exist_ok=True)
            os.rename(parked, here)
            back += 1
        elif not here.exists():
            lost.append(e["path"])
    paths = [e["path"] for e in entries]
    tracked = set(_git_files(root, "--", *paths))
    if tracked:
        _git(root, "update-index", "--no-skip-worktree", "--", *sorted(tracked))
    if lost:  # tracked: git has the committed bytes
        _git(root, "checkout", "--", *lost)
    if conflicts:
        raise SlimError(f"{conflicts[0]} is both in the working tree and in {state / 'files'}, with other bytes "
                        f"({len(conflicts)} such): keep one and run restore again")
    journal.unlink()
    import shutil

    shutil.rmtree(state, ignore_errors=True)
    out.write(f"restored {back} files moved by `slim`" + (f" ({len(lost)} from git: {', '.join(lost)})" if lost else "") + "\n")
    return back


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
    s = sub.add_parser("slim", help="move the tracked files the check does not read ([slim]) out of the working "
                       "tree before a `device` call; print what travels; exit 2 above the limit")
    s.add_argument("--dry-run", action="store_true", help="print what would travel and move nothing")
    s.add_argument("--carry", nargs="*", default=None, help="the paths the call carries (default: the kit file's)")
    s.add_argument("--json", action="store_true", help="print the sizes as one JSON object instead")
    r = sub.add_parser("restore", help="put back what slim moved (also after an interrupted slim); nothing to do is fine")
    for p in (s, r):
        p.add_argument("--root", default=str(ROOT), help="the checkout (default: this script's)")
    args = ap.parse_args(argv)
    if args.command in ("slim", "restore"):
        try:
            root = Path(args.root)
            if args.command == "restore":
                restore(root)
            elif args.json:
                t = slim(root, dry_run=args.dry_run, carry=args.carry, out=io.StringIO())
                sys.stdout.write(json.dumps(t) + "\n")
            else:
                slim(root, dry_run=args.dry_run, carry=args.carry)
        except SlimError as exc:
            sys.stderr.write(f"device_kit: {exc}\n")
            return 2
        return 0
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
