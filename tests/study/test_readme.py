"""The README and the pages of docs/ say what the code does: the README fits on a screen and opens with the
two commands, every `hydrabench` command they quote exists, every relative link resolves, and the
severity table is the code's."""

import contextlib
import io
import re
from pathlib import Path

import pytest

from sim.weather import SEVERITY_TABLE

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
PAGES = sorted((ROOT / "docs").glob("*.md"))
DOCS = [README, *PAGES, ROOT / "BENCHMARKS.md"]

FENCE = re.compile(r"^```.*?^```", re.M | re.S)
SPAN = re.compile(r"`([^`]+)`")  # a span may wrap a line
LINK = re.compile(r"!?\[(?:[^\]\n]|\][^(])*\]\(([^)\s]+)\)")
MAKE_TARGET = re.compile(r"^([\w-]+):", re.M)


def _fmt(x: float) -> str:
    return f"{x:g}"


def _code(text: str) -> list[str]:
    """The code of a Markdown text: its fenced blocks and its inline spans (outside the blocks)."""
    blocks = FENCE.findall(text)
    return blocks + [span.replace("\n", " ") for span in SPAN.findall(FENCE.sub("", text))]


def test_the_readme_opens_with_the_two_commands_and_fits_on_a_screen():
    text = README.read_text()
    assert text.startswith("# hydrabench\n\n```\nmake demo\nmake test\n```")
    assert text.count("\n") <= 250, f"README.md has {text.count(chr(10))} lines; move reference material to docs/"
    # one picture, committed, and the map of docs/: a link to every page
    pictures = [t for t in LINK.findall(text) if t.endswith(".png")]
    assert pictures and all((ROOT / p).is_file() for p in pictures), pictures
    linked = {(ROOT / t.split("#")[0]).resolve() for t in LINK.findall(text)}
    assert not [p.name for p in PAGES if p.resolve() not in linked], "the README's map misses a page of docs/"


def test_severity_table_in_the_docs_matches_code():
    text = (ROOT / "docs" / "sensors.md").read_text()
    for cond, spec in SEVERITY_TABLE.items():
        row = re.search(rf"^\| {cond} \|[^|]*\|(.*)\|$", text, re.M)
        assert row, cond
        cells = [c.strip() for c in row.group(1).split("|")]
        expected = [f"{_fmt(lo)}-{_fmt(hi)}" for lo, hi in spec["levels"]]
        assert cells == expected, (cond, cells, expected)


def quoted_commands(text: str) -> set[tuple[str, ...]]:
    """Each `hydrabench <command> [<subcommand>]` in the code of `text`, as the words that name it
    (the subcommand only where it could be one: a lower-case word; wildcards like `eco-*` name none)."""
    paths = set()
    for code in _code(text):
        for m in re.finditer(r"(?<![\w/.-])hydrabench\s+([a-z][a-z0-9-]*[a-z0-9])(?![\w*-])(?:[ \t]+([a-z][a-z0-9-]*))?",
                             code):
            paths.add((m.group(1),) if m.group(2) is None else (m.group(1), m.group(2)))
    return paths


def _help(parser, words) -> tuple[int, str]:
    from study.cli import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        try:
            code = main([*words, "--help"], parser=parser)
        except SystemExit as exc:
            code = exc.code
    return code, out.getvalue()


def test_every_command_the_docs_quote_exists():
    """`hydrabench X` and `hydrabench X Y` (Y a subcommand where X has subcommands) as quoted in the README,
    docs/*.md and BENCHMARKS.md: `--help` exits 0 for each distinct command path."""
    from study.cli import build_parser

    parser = build_parser()
    commands = parser._subparsers._group_actions[0].choices  # the `<command>` subparsers
    quoted = {}
    for doc in DOCS:
        for words in quoted_commands(doc.read_text()):
            sub = commands.get(words[0])
            sub_choices = sub._subparsers._group_actions[0].choices if sub is not None and sub._subparsers else {}
            # a second word is a subcommand only where the command has subcommands (else it is an argument)
            path = words if len(words) == 2 and sub_choices else words[:1]
            quoted.setdefault(path, doc.name)
    assert len(quoted) > 20, sorted(quoted)
    failed = []
    for path, doc in sorted(quoted.items()):
        code, out = _help(parser, path)
        if code != 0 or not out.startswith(f"usage: hydrabench {' '.join(path)}"):
            failed.append(f"{doc}: hydrabench {' '.join(path)} (exit {code})")
    assert not failed, "the docs quote commands that do not exist: " + "; ".join(failed)


def test_every_make_target_the_docs_quote_exists():
    targets = set(MAKE_TARGET.findall((ROOT / "Makefile").read_text()))
    quoted = {(doc.name, m) for doc in DOCS for code in _code(doc.read_text())
              for m in re.findall(r"(?<![\w-])make ([a-z][\w-]*)", code)}
    assert quoted and not [q for q in quoted if q[1] not in targets], sorted(q for q in quoted if q[1] not in targets)


def heading_anchors(text: str) -> set[str]:
    """GitHub's anchors of the Markdown headings of `text` (lower case, punctuation dropped, spaces to -)."""
    anchors = set()
    for title in re.findall(r"^#{1,6} (.+)$", FENCE.sub("", text), re.M):
        slug = re.sub(r"[^\w\- ]", "", title.strip().lower()).replace(" ", "-")
        anchors.add(slug)
    return anchors


def broken_links(doc: Path) -> list[str]:
    broken = []
    for target in LINK.findall(FENCE.sub("", doc.read_text())):
        if re.match(r"[a-z]+:", target):  # https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        dest = (doc.parent / path).resolve() if path else doc
        if not dest.exists():
            broken.append(f"{doc.name}: {target} (no such file)")
        elif anchor and dest.suffix == ".md" and anchor not in heading_anchors(dest.read_text()):
            broken.append(f"{doc.name}: {target} (no such heading)")
    return broken


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_every_relative_link_resolves(doc):
    assert not broken_links(doc)


def test_the_link_check_sees_a_broken_link_and_anchor(tmp_path):
    (tmp_path / "b.md").write_text("# A page\n\n## Its `second` part\n")
    doc = tmp_path / "a.md"
    doc.write_text("[ok](b.md) [ok](b.md#its-second-part) [web](https://x.org/y) ![pic](c.png) [x](b.md#nothing)\n"
                   "```\n[not a link](in-code.md)\n```\n")
    assert broken_links(doc) == ["a.md: c.png (no such file)", "a.md: b.md#nothing (no such heading)"]


def test_the_command_check_sees_quotes_in_code_only():
    text = ("hydrabench is a benchmark. Run `hydrabench bench sim --json` and `hydrabench eco-*`, or\n"
            "```\nhydrabench train data --out runs/x\nhydrabench evaluate runs/x data\n```\n")
    assert quoted_commands(text) == {("bench", "sim"), ("train", "data"), ("evaluate", "runs")}


def _expand(pattern: str) -> list[str]:
    """`a{b,c}d` as [abd, acd] (the shell's brace expansion, one level at a time)."""
    m = re.search(r"\{([^{}]*)\}", pattern)
    if not m:
        return [pattern]
    return [x for alt in m[1].split(",") for x in _expand(pattern[:m.start()] + alt + pattern[m.end():])]


def test_every_results_file_the_docs_name_exists():
    """A figure's file in results/ (`results/x.json`, `results/ref3_e4_{fog,rain}twins*.json`) is there."""
    missing, named = [], 0
    for doc in DOCS:
        for code in _code(doc.read_text()):
            for ref in re.findall(r"(?<![\w/.-])results/[\w./{},*-]*[\w*}]", code):
                named += 1
                if not all(list(ROOT.glob(p)) for p in _expand(ref)):
                    missing.append(f"{doc.name}: {ref}")
    assert named > 10 and not missing, missing


def test_module_paths_named_in_the_docs_pages_exist():
    """tests/study/test_layout.py checks the README and BENCHMARKS.md; the same check over docs/*.md."""
    from tests.study.test_layout import FILE_SUFFIXES, _resolves

    missing = []
    for doc in PAGES:
        for span in _code(doc.read_text()):
            for ref in re.findall(r"(?<![\w/.-])((?:sim|sensors|fusion|study)(?:\.[A-Za-z_][A-Za-z0-9_]*)+)", span):
                if ref.rsplit(".", 1)[1] not in FILE_SUFFIXES and not _resolves(ref):
                    missing.append(f"{doc.name}: {ref}")
            for ref in re.findall(r"(?<![\w/.-])((?:sim|sensors|fusion|study|scripts|notebooks)/[\w/]+\.(?:py|sh))\b",
                                  span):
                if not (ROOT / ref).is_file():
                    missing.append(f"{doc.name}: {ref}")
    assert not missing, "the docs name modules that do not exist: " + "; ".join(missing)


def test_the_demo_time_the_readme_quotes_is_its_newest_measurement():
    """README: "make demo ... (N s on CPU: scripts/time_demo.sh, results/demo_time_DATE.json)": the
    newest file of scripts/time_demo.sh, its seconds and CPU."""
    import json
    import re

    files = sorted((ROOT / "results").glob("demo_time_*.json"))
    assert files, "no results/demo_time_*.json: run scripts/time_demo.sh"
    newest = files[-1]
    t = json.loads(newest.read_text())
    readme = " ".join((ROOT / "README.md").read_text().split())
    m = re.search(r"\((\d+) s on an? ([^:]+): `scripts/time_demo.sh`, `(results/demo_time_[0-9-]+\.json)`\)", readme)
    assert m, "README's demo time sentence is missing"
    assert m.group(3) == f"results/{newest.name}" and int(m.group(1)) == round(t["seconds"]) and m.group(2) == t["cpu"]
    minutes = {1: "a minute", 1.5: "a minute and a half", 2: "two minutes", 2.5: "two and a half minutes",
               3: "three minutes", 3.5: "three and a half minutes", 4: "four minutes", 5: "five minutes"}
    assert f"about {minutes[max(1, round(t['seconds'] / 30) / 2)]}" in readme  # to the nearest half minute
