"""The identity of the code a cached result was computed by: what `hydrabench study` keys its stages on.

`code_digest(modules)` is the SHA-256 of every first-party module (`sim`, `sensors`, `fusion`,
`study`) that `modules` import, directly or through one another (every `import` statement counts,
those inside functions too, so the set errs on the side of too many). Each module counts by its
syntax tree without docstrings (`ast.dump`): a changed comment, docstring or layout keeps the
digest, a changed statement changes it.

Parsing every module is most of a command's fixed cost (2-3 s for the ~60-120 modules a stage
reads, on a 2-core EPYC), so each module's result (its syntax-tree digest and the first-party
modules it imports) is also kept on disk, in `<cache_root>/code-identity-v1.json`, under the SHA-256
of the module's text (and its name, for the imports): a value is a function of its key, so an
edited module is parsed again and a stale entry cannot be read. Where the cache directory cannot
be used, everything is computed as before.
"""

from __future__ import annotations

import ast
import hashlib
import inspect
import json
import textwrap
from functools import cache, lru_cache
from pathlib import Path

FIRST_PARTY = ("sim", "sensors", "fusion", "study")


ROOT = Path(__file__).resolve().parents[2]


@cache
def module_path(name: str) -> Path | None:
    """The source file of first-party module `name` under ROOT, or None (not first-party, not a
    module: a name imported from a module). Found on disk, nothing is imported."""
    parts = name.split(".")
    if parts[0] not in FIRST_PARTY or not all(p.isidentifier() for p in parts):
        return None
    base = ROOT.joinpath(*parts)
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


def _strip_docstrings(tree: ast.AST) -> ast.AST:
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and body and \
                isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) and \
                isinstance(body[0].value.value, str):
            node.body = body[1:] or [ast.Pass()]
    return tree


DISK_FILE = "code-identity-v1.json"
DISK_ENTRIES = 4096
"""Entries the file keeps at most: past it, a writer keeps only what it read or computed itself (each edit
of a module adds entries; without a bound the file would grow with every edit)."""
_disk: dict | None = None
_disk_dirty = False
_used: set[str] = set()


def _disk_entries() -> dict:
    """{key: value} kept on disk (module docstring); {} where the cache cannot be read."""
    global _disk
    if _disk is None:
        _disk = {}
        try:
            from study.outputs import cache_root

            loaded = json.loads((cache_root() / DISK_FILE).read_text())
            if isinstance(loaded, dict):
                _disk = loaded
        except Exception:  # no cache, an unusable one or a damaged file: compute
            pass
    return _disk


def _remembered(key: str, compute):
    global _disk_dirty
    entries = _disk_entries()
    _used.add(key)
    if key not in entries:
        entries[key] = compute()
        _disk_dirty = True
    return entries[key]


def _save_disk() -> None:
    """Write what this process added (atomically; a concurrent writer's entries may be lost, which
    only costs a parse)."""
    global _disk_dirty
    if not _disk_dirty:
        return
    _disk_dirty = False
    try:
        from study.outputs import cache_root, write_text_atomic

        path = cache_root() / DISK_FILE
        path.parent.mkdir(parents=True, exist_ok=True)
        entries = _disk_entries()
        if len(entries) > DISK_ENTRIES:
            entries = {k: v for k, v in entries.items() if k in _used}
        write_text_atomic(path, json.dumps(entries, sort_keys=True))
    except Exception:
        pass


def _text_key(kind: str, source: str, name: str = "") -> str:
    return f"{kind}:{name}:{hashlib.sha256(source.encode()).hexdigest()}"


@lru_cache(maxsize=4096)
def source_digest(source: str) -> str:
    """SHA-256 of Python source by its syntax tree, docstrings removed."""
    return _remembered(_text_key("ast", source), lambda: _ast_digest(source))


def _ast_digest(source: str) -> str:
    return hashlib.sha256(ast.dump(_strip_docstrings(ast.parse(source))).encode()).hexdigest()


def read_module(name: str) -> str:
    """The source text of module `name` (a function of its own so tests can change "the code")."""
    return module_path(name).read_text()


@lru_cache(maxsize=4096)
def _imports(name: str, source: str) -> frozenset[str]:
    """The first-party modules `source` (module `name`) imports."""
    # (relative imports resolve against the package: whether `name` is one is part of the key)
    key = _text_key("imports", source, f"{name}:{module_path(name).name}")
    found = _remembered(key, lambda: sorted(_parse_imports(name, source)))
    return frozenset(n for n in found if module_path(n) is not None)


def _parse_imports(name: str, source: str) -> set[str]:
    out: set[str] = set()
    package = name if module_path(name).name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                parts = parts[:len(parts) - node.level + 1]
                base = ".".join(parts + ([base] if base else []))
            out.add(base)
            out.update(f"{base}.{a.name}" for a in node.names)  # `from pkg import module`
    # a module imports its packages' __init__ too
    for n in list(out):
        parts = n.split(".")
        out.update(".".join(parts[:i]) for i in range(1, len(parts)))
    return out  # every name, first-party or not: which of them are modules is read from disk each time


def closure(modules) -> list[str]:
    """The first-party modules `modules` import, directly or not, `modules` included; sorted."""
    seen: set[str] = set()
    todo = [m for m in modules if module_path(m) is not None]
    while todo:
        m = todo.pop()
        if m in seen:
            continue
        seen.add(m)
        todo.extend(_imports(m, read_module(m)) - seen)
    return sorted(seen)


def code_digest(modules, functions=()) -> str:
    """SHA-256 over the modules of `closure(modules)`, the source of each of `functions` and the
    first-party modules those functions import (not the rest of the functions' own modules)."""
    sources = {f.__qualname__: textwrap.dedent(inspect.getsource(f)) for f in functions}
    entry = set(modules)
    for f, src in zip(functions, sources.values()):
        entry |= set(_imports(f.__module__, src))
    h = hashlib.sha256()
    for m in closure(sorted(entry)):
        h.update(f"{m}\0{source_digest(read_module(m))}\0".encode())
    for name, src in sources.items():
        h.update(f"{name}\0{source_digest(src)}\0".encode())
    _save_disk()
    return h.hexdigest()
