"""The shape of the code (README, "Layout of `study/`"), read from the source without importing it.

- argparse lives in `study/cli.py` and `study/commands/` only: the experiments (`study/*.py`,
  `study/eco/`), the benches (`study/bench/`) and the library never build a parser;
- a command adapter holds parsers, argument types, `run*` functions and text, nothing else, and
  imports no torch at module level, so `hydrabench --help` and the light commands import no torch;
- experiments never import the command line back (`study.cli`, `study.commands`);
- nothing in `sim/`, `sensors/`, `fusion/` imports `study` (packages import one way);
- no two modules import each other, directly or round a longer circle, even inside a function;
- every module path the README and BENCHMARKS.md name in code spans exists;
- every path and name the "Layout of `study/`" tables of docs/development.md give exists.
"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from collections import deque
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("sim", "sensors", "fusion", "study")
STUDY = ROOT / "study"
COMMANDS = STUDY / "commands"
PARSER_CALLS = {"add_argument", "add_parser", "add_subparsers", "add_argument_group", "add_mutually_exclusive_group",
                "parse_args", "parse_known_args", "ArgumentParser"}
ADAPTER_PREFIXES = ("add_", "run", "format_", "parse_", "build_config", "main")
FILE_SUFFIXES = {"json", "yaml", "md", "html", "png", "csv", "npz", "npy", "pt", "txt"}
"""A code span such as `study.json` names a file, not a module."""


def _py(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*.py") if "__pycache__" not in p.parts)


def _tree(path: Path) -> ast.Module:
    return ast.parse(path.read_text(), filename=str(path))


def _imports(node: ast.AST) -> list[str]:
    """Every module name an import statement under `node` names (`from a.b import c`: a.b and a.b.c)."""
    out = []
    for n in ast.walk(node):
        if isinstance(n, ast.Import):
            out += [a.name for a in n.names]
        elif isinstance(n, ast.ImportFrom) and n.module and not n.level:
            out += [n.module] + [f"{n.module}.{a.name}" for a in n.names]
    return out


def _module_level_imports(tree: ast.Module) -> list[str]:
    """Imports executed when the module is imported: top-level statements, also inside a top-level
    if / try / with, but not inside functions or classes."""
    out = []
    todo = list(tree.body)
    while todo:
        n = todo.pop()
        if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            continue
        if isinstance(n, (ast.Import, ast.ImportFrom)):
            out += _imports(n)
        else:
            todo += [c for c in ast.iter_child_nodes(n) if isinstance(c, ast.stmt)]
    return out


def _rel(path: Path) -> str:
    return str(path.relative_to(ROOT))


def test_argparse_only_in_the_cli_and_the_command_adapters():
    allowed = {STUDY / "cli.py", *_py(COMMANDS)}
    offenders = []
    for pkg in ("sim", "sensors", "fusion", "study"):
        for path in _py(ROOT / pkg):
            if path in allowed:
                continue
            tree = _tree(path)
            if any(m == "argparse" or m.startswith("argparse.") for m in _imports(tree)):
                offenders.append(f"{_rel(path)} imports argparse")
            for n in ast.walk(tree):
                if isinstance(n, ast.Call):
                    name = n.func.attr if isinstance(n.func, ast.Attribute) else getattr(n.func, "id", "")
                    if name in PARSER_CALLS:
                        offenders.append(f"{_rel(path)}:{n.lineno} calls {name}")
    assert not offenders, "argparse belongs in study/cli.py and study/commands/: " + "; ".join(offenders)


def test_command_adapters_hold_parsers_types_runs_and_text_only():
    offenders = []
    for path in _py(COMMANDS):
        tree = _tree(path)
        typed = {t.value.id for n in tree.body if isinstance(n, ast.Assign) for t in n.targets
                 if isinstance(t, ast.Attribute) and t.attr == "kind" and isinstance(t.value, ast.Name)}
        for n in tree.body:
            if isinstance(n, ast.ClassDef):
                offenders.append(f"{_rel(path)} defines class {n.name} (experiments and their configs live beside "
                                 "study/commands/, not in it)")
            elif isinstance(n, ast.FunctionDef) and not n.name.startswith("_"):
                if not n.name.startswith(ADAPTER_PREFIXES) and n.name not in typed:
                    offenders.append(f"{_rel(path)} defines {n.name}() (an adapter's public functions are add_*, "
                                     "run*, format_*, parse_*, main, or argparse types carrying a .kind)")
    assert not offenders, "; ".join(offenders)


def test_command_line_imports_no_torch_at_module_level():
    for path in [STUDY / "cli.py", *_py(COMMANDS)]:
        heavy = [m for m in _module_level_imports(_tree(path)) if m.split(".")[0] in ("torch", "torchvision")]
        assert not heavy, f"{_rel(path)} imports {heavy[0]} at module level (import it inside the run function)"


def test_help_and_the_parsers_import_no_torch():
    """Building every command's parser (what `hydrabench --help` and every command do first) imports
    no torch, directly or through the experiment modules an adapter imports."""
    code = ("import sys; import study.cli as cli; cli.build_parser(); "
            "sys.exit(sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'torchvision'))[:1] or 0)")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, f"building the parsers imported {r.stderr.strip() or r.stdout.strip()}"


def test_every_command_runs_through_an_adapter_in_study_commands():
    tree = _tree(STUDY / "cli.py")
    table = next(n.value for n in tree.body if isinstance(n, ast.AnnAssign) and getattr(n.target, "id", "") == "COMMANDS")
    targets = [ast.literal_eval(v)[0] for v in table.values]
    assert targets and all(t.startswith("study.commands.") for t in targets), targets
    for t in targets:
        module, func = t.split(":")
        path = ROOT / (module.replace(".", "/") + ".py")
        if not path.is_file():  # a package of adapters (study/commands/bench/)
            path = ROOT / module.replace(".", "/") / "__init__.py"
        assert func in {n.name for n in _tree(path).body if isinstance(n, ast.FunctionDef)}, t


def test_experiments_and_benches_never_import_the_command_line():
    offenders = []
    for path in _py(STUDY):
        if path == STUDY / "cli.py" or COMMANDS in path.parents:
            continue
        for m in _imports(_tree(path)):
            if m in ("study.cli", "study.commands") or m.startswith(("study.cli.", "study.commands.")):
                offenders.append(f"{_rel(path)} imports {m}")
    assert not offenders, "; ".join(offenders)


def test_library_packages_never_import_study():
    offenders = [f"{_rel(path)} imports {m}" for pkg in ("sim", "sensors", "fusion") for path in _py(ROOT / pkg)
                 for m in _imports(_tree(path)) if m == "study" or m.startswith("study.")]
    assert not offenders, "packages import one way, sim <- sensors <- fusion <- study: " + "; ".join(offenders)


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _import_graph() -> dict[str, set[str]]:
    """Project module -> the project modules it imports, at the top or inside a function. `import
    a.b.c` names a.b.c; `from a.b import c` names a.b.c if that is a module, else a.b; a name that is
    no module names the nearest package above it."""
    paths = {_module_name(p): p for pkg in PACKAGES for p in _py(ROOT / pkg)}
    graph = {}
    for name, path in paths.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        targets = set()
        for n in ast.walk(_tree(path)):
            if isinstance(n, ast.Import):
                named = [a.name for a in n.names]
            elif isinstance(n, ast.ImportFrom):
                base = n.module or ""
                if n.level:  # relative: the package, then one package up per extra dot
                    up = package.split(".")[: package.count(".") + 2 - n.level]
                    base = ".".join([*up, base] if base else up)
                named = [f"{base}.{a.name}" if f"{base}.{a.name}" in paths else base for a in n.names]
            else:
                continue
            for target in named:
                while target and target not in paths:
                    target = target.rpartition(".")[0]
                if target and target != name:
                    targets.add(target)
        graph[name] = targets
    return graph


def _circle_through(graph: dict[str, set[str]], start: str) -> list[str] | None:
    """The shortest import path start -> ... -> start (breadth first), or None."""
    prev: dict[str, str] = {}
    todo = deque([start])
    while todo:
        m = todo.popleft()
        for t in sorted(graph.get(m, ())):
            if t == start:
                path = [m]
                while path[-1] != start:
                    path.append(prev[path[-1]])
                return [*reversed(path), start]
            if t not in prev:
                prev[t] = m
                todo.append(t)
    return None


def test_the_circle_finder_finds_circles():
    assert _circle_through({"a": {"b"}, "b": {"a"}}, "a") == ["a", "b", "a"]
    assert _circle_through({"a": {"b"}, "b": {"c"}, "c": {"a", "b"}}, "a") == ["a", "b", "c", "a"]
    assert _circle_through({"a": {"b"}, "b": {"c"}, "c": {"b"}}, "a") is None


def test_no_import_circles_among_the_projects_modules():
    """An import circle (layers <-> profile, detect <-> train) works only while one side imports
    lazily, and breaks when someone moves that import to the top: the dependency goes one way."""
    graph = _import_graph()
    assert "study.engine.run_config" in graph["study.engine.scoring"], "the graph must see imports inside functions"
    circles, seen = [], set()
    for m in sorted(graph):
        circle = _circle_through(graph, m)
        if circle and frozenset(circle) not in seen:
            seen.add(frozenset(circle))
            circles.append(" -> ".join(circle))
    assert not circles, "modules importing each other (make the dependency go one way): " + "; ".join(circles)


def _resolves(dotted: str) -> bool:
    """`a.b.c.Name.attr`: the longest prefix that is a module file or package of this repository, and
    the next part (if any) a top-level name of that module."""
    parts = dotted.split(".")
    for k in range(len(parts), 0, -1):
        base = ROOT.joinpath(*parts[:k])
        path = base.with_suffix(".py") if base.with_suffix(".py").is_file() else base / "__init__.py"
        if not path.is_file():
            continue
        if k == len(parts):
            return True
        tree = _tree(path)
        names = {n.name for n in tree.body if isinstance(n, (ast.FunctionDef, ast.ClassDef))}
        names |= {t.id for n in tree.body if isinstance(n, (ast.Assign, ast.AnnAssign))
                  for t in (n.targets if isinstance(n, ast.Assign) else [n.target]) if isinstance(t, ast.Name)}
        names |= {a.asname or a.name for n in tree.body if isinstance(n, ast.ImportFrom) for a in n.names}
        names |= {"__file__", "__doc__"}
        return parts[k] in names or (ROOT.joinpath(*parts[:k + 1]).is_dir())
    return False


def test_module_paths_named_in_the_docs_exist():
    missing = []
    for doc in ("README.md", "BENCHMARKS.md"):
        text = (ROOT / doc).read_text()
        for span in re.findall(r"`([^`\n]+)`", text):
            for ref in re.findall(r"(?<![\w/.-])((?:sim|sensors|fusion|study)(?:\.[A-Za-z_][A-Za-z0-9_]*)+)", span):
                if ref.rsplit(".", 1)[1] not in FILE_SUFFIXES and not _resolves(ref):
                    missing.append(f"{doc}: {ref}")
            for ref in re.findall(r"(?<![\w/.-])((?:sim|sensors|fusion|study|scripts)/[\w/]+\.(?:py|sh))\b", span):
                if not (ROOT / ref).is_file():
                    missing.append(f"{doc}: {ref}")
    assert not missing, "the docs name modules that do not exist: " + "; ".join(missing)


def _layout_tables(text: str) -> list[list[str]]:
    """The table cells of the "Layout of `study/`" section, one list per row (header rows skipped)."""
    section = text.split("## Layout of `study/`", 1)[1].split("\n## ", 1)[0]
    rows = [line.strip().strip("|").split("|") for line in section.splitlines() if line.startswith("|")]
    return [[c.strip() for c in row] for row in rows if not set("".join(row)) <= set("-| ")][1:]


def _top_level_names(path: Path) -> set[str]:
    tree = _tree(path)
    names = {n.name for n in tree.body if isinstance(n, (ast.FunctionDef, ast.ClassDef))}
    names |= {t.id for n in tree.body if isinstance(n, (ast.Assign, ast.AnnAssign))
              for t in (n.targets if isinstance(n, ast.Assign) else [n.target]) if isinstance(t, ast.Name)}
    return names


def _layout_problems(text: str) -> list[str]:
    """Paths in the layout tables that do not exist, and names (`GATES`, `run_study`,
    `GateTrainConfig.gate`) that no module named in the same cell defines. A path with a placeholder
    (`study/bench/<what>.py`) or a glob is not checked."""
    problems = []
    for row in _layout_tables(text):
        for cell in row:
            spans = re.findall(r"`([^`]+)`", cell)
            paths = [s for s in spans if re.fullmatch(r"(sim|sensors|fusion|study|configs|tests)/[\w/.*<>-]*|[\w-]+\.md", s)]
            real = [s for s in paths if not re.search(r"[<>*]", s)]
            for s in real:
                if not (ROOT / s).exists():
                    problems.append(f"{s} does not exist")
            modules = [ROOT / s for s in real if s.endswith(".py") and (ROOT / s).is_file()]
            defined = set().union(*(_top_level_names(m) for m in modules)) if modules else set()
            for s in spans:
                name = re.sub(r"\(.*\)$", "", s).split(".")[0]
                if s in paths or not name.isidentifier() or not modules:
                    continue
                if name not in defined:
                    problems.append(f"`{s}`: not defined in {', '.join(str(m.relative_to(ROOT)) for m in modules)}")
    return problems


def test_the_layout_tables_name_what_exists():
    assert _layout_problems((ROOT / "docs" / "development.md").read_text()) == []
    broken = "## Layout of `study/`\n\n| a | b |\n|---|---|\n| x | `study/pipeline/stages.py`: `run_studies`, `study/nope.py` |\n"
    assert _layout_problems(broken) == ["study/nope.py does not exist",
                                        "`run_studies`: not defined in study/pipeline/stages.py"]


MAX_MODULE_LINES, MAX_FUNCTION_LINES = 600, 100
"""Issue 38's aims for `study/`: a module a newcomer can read, a function that does one job."""


def _sizes(root: Path) -> tuple[list, list]:
    too_long_modules, too_long_functions = [], []
    for path in sorted(root.rglob("*.py")):
        src = path.read_text()
        if len(src.splitlines()) > MAX_MODULE_LINES:
            too_long_modules.append(f"{path.relative_to(root.parent)}: {len(src.splitlines())} lines")
        for node in ast.walk(ast.parse(src)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    too_long_functions.append(f"{path.relative_to(root.parent)}:{node.lineno} {node.name}: {n} lines")
    return too_long_modules, too_long_functions


def test_no_study_module_over_600_lines_and_no_function_over_100(tmp_path):
    assert _sizes(ROOT / "study") == ([], [])
    # the check sees what it is for
    pkg = tmp_path / "study"
    pkg.mkdir()
    (pkg / "big.py").write_text("def f():\n" + "    x = 1\n" * 100 + "\n" * 500)
    modules, functions = _sizes(pkg)
    assert modules == ["study/big.py: 601 lines"] and functions == ["study/big.py:1 f: 101 lines"]


ROOMS = ("engine", "experiments", "report", "pipeline", "commands", "eco", "bench")


def test_study_is_arranged_in_rooms_by_job():
    """Issue 47 item 4: at most 15 top-level modules and rooms in `study/`, every room a package whose
    docstring says what it holds, and docs/development.md's table of rooms naming each one."""
    study = ROOT / "study"
    top = sorted(p.name for p in study.iterdir() if (p.suffix == ".py" or (p.is_dir() and p.name != "__pycache__")))
    assert len(top) <= 15, top
    rooms = sorted(p.name for p in study.iterdir() if p.is_dir() and p.name != "__pycache__")
    assert set(rooms) == set(ROOMS), rooms
    doc = (ROOT / "docs" / "development.md").read_text()
    for room in rooms:
        init = study / room / "__init__.py"
        assert init.is_file() and ast.get_docstring(ast.parse(init.read_text())), f"study/{room}/__init__.py: no docstring"
        assert f"`study/{room}/`" in doc, f"docs/development.md: no row for study/{room}/"
