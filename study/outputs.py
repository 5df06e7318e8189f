"""Output paths: checked before work starts, written atomically (temp name, then rename).

The checks create nothing: a command refused later (a bad option, a damaged dataset) leaves no
directory behind. Missing parent directories are created when the file is written. Written files
get the ordinary permissions (0666 minus the umask, 0644 usually), not the 0600 of a temp file.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

from sim.errors import UserError

NAME_MAX = 255  # bytes in one file name (Linux, macOS and most file systems)
PATH_MAX = 4096  # bytes in a whole path (Linux)


def path_problem(path: str | Path) -> str | None:
    """What makes `path` unusable whatever the command does with it, or None: a file name over
    NAME_MAX bytes, a path over PATH_MAX, a symbolic link loop on the way. Every path argument of the
    command line passes here (study.cli), so no later `exists()` raises OSError."""
    text = os.fspath(path)
    for part in Path(text).parts:
        n = len(part.encode("utf-8", "surrogateescape"))
        if n > NAME_MAX:
            return f"file name too long ({n} bytes, the limit is {NAME_MAX}): {part[:24]}..."
    if len(text.encode("utf-8", "surrogateescape")) >= PATH_MAX:
        return f"path too long (the limit is {PATH_MAX - 1} bytes)"
    try:
        os.stat(text)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            return "a symbolic link loop (too many levels of symbolic links)"
        if exc.errno == errno.ENAMETOOLONG:
            return "file name too long"
    return None


def check_path(path: str | Path) -> Path:
    """`path`, or a UserError naming it and its `path_problem`."""
    problem = path_problem(path)
    if problem:
        raise UserError(f"{path}: {problem}")
    return Path(path)


def _nearest_existing(path: Path) -> Path:
    """The closest ancestor of `path` (or `path` itself) that exists."""
    p = path.absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def _probe(directory: Path, wanted: Path) -> None:
    """Fail (UserError) unless a directory can be created in `directory`: the only test that also
    holds for root, for /proc and /sys and for read-only mounts (os.access says yes to all of them)."""
    if not directory.is_dir():
        raise UserError(f"cannot write {wanted}: {directory} is not a directory")
    try:
        probe = tempfile.mkdtemp(prefix=".hydrabench-probe-", dir=directory)
    except OSError:
        raise UserError(f"cannot write {wanted}: {directory} is not writable") from None
    os.rmdir(probe)


def check_writable_file(path: str | Path, suffixes: tuple[str, ...] | None = None) -> Path:
    """Fail early (UserError) when `path` cannot be written, or its extension is not one of `suffixes`.

    Creates nothing; `atomic_path` creates the missing parent directories when the file is written."""
    path = check_path(path)
    if suffixes and path.suffix.lower() not in suffixes:
        got = f"extension {path.suffix!r}" if path.suffix else "no extension"
        raise UserError(f"{path}: {got} is not supported (write {', '.join(suffixes)})")
    if path.is_dir():
        raise UserError(f"output {path} is a directory, expected a file path")
    if path.exists() and not path.is_file():
        raise UserError(f"output {path} exists and is not a regular file")
    _probe(_nearest_existing(path.parent), path)
    return path


def check_writable_dir(path: str | Path) -> Path:
    """Fail early (UserError) unless `path` is a directory that exists or can be created, and can be
    written. Creates nothing: the command creates it when it starts writing."""
    path = check_path(path)
    if path.exists() and not path.is_dir():
        raise UserError(f"output {path} exists and is not a directory")
    _probe(_nearest_existing(path), path)
    return path


def make_dir(path: str | Path) -> Path:
    """Create an output directory checked by `check_writable_dir` (UserError if that now fails)."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create directory {path}: {exc.strerror}") from None
    return path


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside `path`; rename it over `path` only if the block succeeds."""
    path = Path(path)
    make_dir(path.parent if str(path.parent) else Path("."))
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
    except OSError as exc:
        raise UserError(f"cannot write {path}: {exc.strerror}") from None
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write `text` to `path` atomically (`atomic_path`): readers see the old file or the whole new one."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def write_json_atomic(path: str | Path, obj, default=None) -> None:
    """`obj` as JSON (indent 1; `default` as in `json.dumps`) written to `path` atomically."""
    write_text_atomic(path, json.dumps(obj, indent=1, default=default))


def torch_save_atomic(obj, path: str | Path) -> None:
    """`torch.save(obj)` to `path` atomically (`atomic_path`): an interrupted save leaves the old file."""
    import torch

    # through a file object: torch.save to a path names the archive's records after that path (the
    # temporary name), so the same object would give other bytes on every save
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        try:
            torch.save(obj, fh)
        except RuntimeError as exc:
            # torch's archive writer turns a full disk into "unexpected pos 704 vs 598": asked while
            # the partial file still takes its space, the file system says whether it is full
            if _nearly_full(tmp.parent):
                raise OSError(errno.ENOSPC, f"{os.strerror(errno.ENOSPC)} ({str(exc).splitlines()[0][:80]})",
                              str(path)) from None
            raise


def _nearly_full(directory: Path, spare: int = 1 << 20) -> bool:
    """Whether the file system of `directory` has less than `spare` bytes left for this user."""
    try:
        st = os.statvfs(directory)
    except OSError:
        return False
    return st.f_bavail * st.f_frsize < spare


def savefig_atomic(fig, path: str | Path, **kw) -> None:
    """`fig.savefig` to `path` atomically (`atomic_path`), in the format its extension names."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format=Path(path).suffix.lstrip(".").lower() or "png", **kw)


CACHE_ENV = "HYDRABENCH_CACHE"


def cache_root() -> Path:
    """hydrabench's own cache directory (reference-model copies, the theory measurements), checked
    writable: $HYDRABENCH_CACHE, else $XDG_CACHE_HOME/hydrabench (an absolute XDG_CACHE_HOME, as the
    XDG spec asks), else $HOME/.cache/hydrabench. Creates nothing. UserError, one line saying how to
    fix it, when that directory cannot be written, HYDRABENCH_CACHE names an unusable path, or HOME is
    empty or relative (an empty HOME once put the cache at /.cache, the file system's root)."""
    explicit = os.environ.get(CACHE_ENV)
    if explicit is not None:
        if not explicit.strip():
            raise UserError(f"{CACHE_ENV} is set but empty: unset it, or set it to a writable directory")
        path, source = Path(explicit), f"{CACHE_ENV}={explicit}"
    elif os.path.isabs(os.environ.get("XDG_CACHE_HOME", "")):
        path, source = Path(os.environ["XDG_CACHE_HOME"]) / "hydrabench", "XDG_CACHE_HOME"
    else:
        home = os.environ.get("HOME")
        if home is not None and not os.path.isabs(home):
            raise UserError(f"HOME is {'empty' if not home else f'not an absolute path ({home!r})'}, so hydrabench has "
                            f"no cache directory: set HOME, or {CACHE_ENV} to a writable directory")
        path, source = Path(os.path.expanduser("~")) / ".cache" / "hydrabench", f"HOME={os.path.expanduser('~')}"
    try:
        return check_writable_dir(path)
    except UserError as exc:
        raise UserError(f"the cache directory ({source}): {exc}; set {CACHE_ENV} to a writable directory") from None


def replace_marked_block(text: str, begin: str, end: str, block: str) -> str:
    """`text` with what stands between the markers `begin` and `end` replaced by `block` (a generated
    part of a page, such as the README's results); ValueError unless there is exactly one `begin`
    followed by one `end`."""
    if text.count(begin) != 1 or text.count(end) != 1 or text.index(begin) > text.index(end):
        raise ValueError(f"the README needs exactly one {begin!r} followed by one {end!r}")
    head, rest = text.split(begin, 1)
    _, tail = rest.split(end, 1)
    return f"{head}{begin}\n{block.strip()}\n{end}{tail}"


def update_page(path: str | Path, old: str, new: str, check: bool) -> int:
    """A generated block's writer's exit code: with `check`, 0 when the page `path` (whose text is
    `old`) already holds `new` and 1 when not, writing nothing; else `new` written atomically when
    it differs, and 0."""
    if check:
        return 0 if new == old else 1
    if new != old:
        write_text_atomic(path, new)
    return 0
