"""What travels to the lent GPU machine (scripts/device_kit.py slim / restore, docs/gpu.md): within
60 MiB once slimmed, counted here independently of the script; slim and restore round-trip byte for
byte, also after a slim killed half-way; the GPU check reads none of the files slim moves; the
figures and the device-time plan in docs/gpu.md are these."""

from __future__ import annotations

import ast
import fnmatch
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.study.test_device_kit import KIT, kit_script

ROOT = Path(__file__).resolve().parents[2]
MIB = 2**20
GIT = ["git", "-c", "user.name=t", "-c", "user.email=t@t", "-c", "commit.gpgsign=false"]


def _git(repo: Path, *args: str) -> str:
    return subprocess.run([*GIT, *args], cwd=repo, check=True, capture_output=True, text=True).stdout


def _ls(repo: Path, *args: str) -> list[str]:
    return [p for p in _git(repo, "ls-files", "-z", *args).split("\0") if p]


def _sent(repo: Path) -> int:
    """Bytes one `device` call sends, as the tool's README says, counted without the script: tracked
    files present in the working tree, untracked files git does not ignore, and the carried .whl
    and .gl (their pinned sizes in the kit file: they are not here in CI)."""
    files = [p for p in _ls(repo) if os.path.lexists(repo / p)] + _ls(repo, "--others", "--exclude-standard")
    carried = sum(s["bytes"] for s in KIT["kit"].values()) + sum(KIT["gl"].values())
    return sum((repo / p).lstat().st_size for p in files) + carried


def _copy_checkout(dest: Path) -> Path:
    """A git repository holding this checkout's tracked files (committed) and its untracked,
    not-ignored ones (left untracked): slim runs there, never in the real checkout."""
    dest.mkdir()
    for rel in [p for p in _ls(ROOT) if (ROOT / p).is_file()] + _ls(ROOT, "--others", "--exclude-standard"):
        (dest / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / rel, dest / rel)
    untracked = set(_ls(ROOT, "--others", "--exclude-standard"))
    _git(dest, "init", "-q")
    _git(dest, "add", "--", *[p for p in _ls(ROOT) if (dest / p).exists() and p not in untracked])
    _git(dest, "commit", "-q", "-m", "copy")
    return dest


def _small_repo(tmp_path: Path) -> tuple[Path, dict]:
    """A small git repository with files to slim, two of them nested, and a kit that moves them."""
    repo = tmp_path / "repo"
    (repo / "models" / "m" / "gates" / "g").mkdir(parents=True)
    (repo / "src").mkdir()
    files = {"models/m/checkpoint.pt": os.urandom(300_000), "models/m/gates/g/gate.pt": os.urandom(5000),
             "models/m/manifest.json": b"{}", "src/code.py": b"print(1)\n", ".gitignore": b"/.whl/\n"}
    for rel, data in files.items():
        (repo / rel).write_bytes(data)
    _git(repo, "init", "-q")
    _git(repo, "add", "-A")
    _git(repo, "commit", "-q", "-m", "init")
    kit = {**KIT, "slim": {**KIT["slim"], "paths": ["models/*/checkpoint.pt", "models/*/gates/*/gate.pt"]}}
    return repo, kit


def _contents(repo: Path) -> dict:
    return {p: (repo / p).read_bytes() for p in _ls(repo)}


def test_what_travels_after_slim_is_within_the_limit_counted_exactly(tmp_path):
    repo = _copy_checkout(tmp_path / "copy")
    before = _sent(repo)
    reported = kit_script.slim(repo, out=open(os.devnull, "w"))
    after = _sent(repo)
    assert reported["total"] == after  # what slim says travels is what travels
    assert after <= 60 * MIB, f"{after / MIB:.2f} MiB would travel to the GPU machine (limit 60 MiB): see docs/gpu.md"
    journal = json.loads((kit_script._state(repo) / "journal.json").read_text())
    assert before - after == sum(e["bytes"] for e in journal["files"]) > 36 * MIB
    assert "models/cpu-ref/checkpoint.pt" not in [p for p in _ls(repo) if (repo / p).exists()]
    kit_script.restore(repo, out=open(os.devnull, "w"))
    assert _sent(repo) == before


def test_slim_then_restore_round_trips_byte_for_byte_and_git_status_stays_clean(tmp_path):
    repo, kit = _small_repo(tmp_path)
    before = _contents(repo)
    kit_script.slim(repo, kit, out=open(os.devnull, "w"))
    assert not (repo / "models/m/checkpoint.pt").exists() and not (repo / "models/m/gates/g/gate.pt").exists()
    assert (repo / "models/m/manifest.json").exists()
    assert _git(repo, "status", "--porcelain") == ""  # skip-worktree: no "deleted", nothing for `commit -a`
    _git(repo, "commit", "-q", "-a", "--allow-empty", "-m", "while slim")
    assert "checkpoint.pt" in _git(repo, "ls-tree", "-r", "--name-only", "HEAD")
    assert kit_script.restore(repo, out=open(os.devnull, "w")) == 2
    assert _contents(repo) == before
    assert not [ln for ln in _git(repo, "ls-files", "-v").splitlines() if ln.startswith("S ")]
    assert not kit_script._state(repo).exists()
    assert kit_script.restore(repo, out=open(os.devnull, "w")) == 0  # idempotent
    assert _contents(repo) == before and _git(repo, "status", "--porcelain") == ""


def test_restore_after_a_slim_killed_half_way_puts_everything_back(tmp_path, monkeypatch):
    repo, kit = _small_repo(tmp_path)
    before = _contents(repo)
    real_rename, calls = os.rename, []

    def dies_on_the_second_move(a, b):
        calls.append(a)
        if len(calls) == 2:
            raise KeyboardInterrupt  # the journal is written and one file has moved
        real_rename(a, b)

    monkeypatch.setattr(kit_script.os, "rename", dies_on_the_second_move)
    with pytest.raises(KeyboardInterrupt):
        kit_script.slim(repo, kit, out=open(os.devnull, "w"))
    monkeypatch.undo()
    assert (kit_script._state(repo) / "journal.json").exists()
    assert sum(not (repo / p).exists() for p in before) == 1
    kit_script.restore(repo, out=open(os.devnull, "w"))
    assert _contents(repo) == before and _git(repo, "status", "--porcelain") == ""
    assert not [ln for ln in _git(repo, "ls-files", "-v").splitlines() if ln.startswith("S ")]


def test_a_second_slim_restores_first_and_a_conflict_keeps_both_copies(tmp_path):
    repo, kit = _small_repo(tmp_path)
    before = _contents(repo)
    kit_script.slim(repo, kit, out=open(os.devnull, "w"))
    kit_script.slim(repo, kit, out=open(os.devnull, "w"))  # not "already moved": restored, then slimmed again
    (repo / "models/m/checkpoint.pt").write_bytes(b"retrained meanwhile")
    with pytest.raises(kit_script.SlimError, match="models/m/checkpoint.pt is both in the working tree"):
        kit_script.restore(repo, out=open(os.devnull, "w"))
    assert (repo / "models/m/checkpoint.pt").read_bytes() == b"retrained meanwhile"
    assert (kit_script._state(repo) / "files/models/m/checkpoint.pt").read_bytes() == before["models/m/checkpoint.pt"]
    (repo / "models/m/checkpoint.pt").unlink()
    kit_script.restore(repo, out=open(os.devnull, "w"))
    assert _contents(repo) == before


def test_slim_above_the_limit_is_refused_in_one_line_and_moves_nothing(tmp_path):
    repo, kit = _small_repo(tmp_path)
    with open(repo / "big.bin", "wb") as fh:  # untracked, not ignored: it travels (sparse: no disk used)
        fh.truncate(61 * MIB)
    before = _contents(repo)
    r = subprocess.run([sys.executable, str(ROOT / "scripts" / "device_kit.py"), "slim", "--root", str(repo)],
                       capture_output=True, text=True)
    assert r.returncode == 2 and r.stdout == "" and r.stderr.count("\n") == 1 and "Traceback" not in r.stderr
    assert "over the 60 MiB limit" in r.stderr and "untracked 61.00" in r.stderr
    assert _contents(repo) == before and not kit_script._state(repo).exists()
    r = subprocess.run([sys.executable, str(ROOT / "scripts" / "device_kit.py"), "restore", "--root", str(repo)],
                       capture_output=True, text=True)
    assert r.returncode == 0 and r.stderr == ""


def test_restore_outside_a_git_checkout_has_nothing_to_do(tmp_path):
    assert kit_script.restore(tmp_path, out=open(os.devnull, "w")) == 0


def test_the_gpu_check_reads_none_of_the_files_slim_moves():
    _, _, reached = kit_script.import_walk(ROOT, KIT["entry"])
    assert "study.engine.reference_model" not in reached  # the one module that opens models/
    tops = {g.split("/")[0] + "/" for g in KIT["slim"]["paths"]}
    for module in reached:
        path = kit_script._module_file(ROOT, module)
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                assert not any(node.value.startswith(t) or f"/{t}" in node.value for t in tops), \
                    f"{module} names {node.value!r}, under a folder slim empties"
    for glob in KIT["slim"]["paths"]:  # each glob still matches something (no stale entry)
        assert any(fnmatch.fnmatchcase(p, glob) for p in _ls(ROOT)), glob


def test_download_refuses_a_wheel_of_another_size():
    spec = KIT["kit"]["shapely"]
    assert kit_script.size_problem(spec["bytes"], spec) is None
    assert "pins" in kit_script.size_problem(spec["bytes"] + 1, spec)
    built = KIT["kit"]["pyopengl"]  # built here: a few bytes either way are another builder's metadata
    assert kit_script.size_problem(built["bytes"] + 100, built) is None
    assert kit_script.size_problem(int(built["bytes"] * 1.05), built) is not None
    assert all(s["bytes"] for s in KIT["kit"].values()) and set(KIT["gl"]) == set(kit_script.GL_PACKAGES)


DOC = (ROOT / "docs" / "gpu.md").read_text()


def _table(heading: str) -> list[list[str]]:
    section = DOC.split(heading, 1)[1].split("\n## ", 1)[0]
    rows = [ln for ln in section.splitlines() if ln.startswith("|")][2:]
    return [[c.strip() for c in ln.strip("|").split("|")] for ln in rows]


def test_the_doc_states_what_travels_as_slim_counts_it():
    files = kit_script.slim_files(ROOT, KIT)
    t = kit_script.travel(ROOT, carry=[], kit=KIT, leaving=files)  # a fresh clone: no untracked file
    want = {"tracked files": t["tracked"], ".whl": kit_script.pinned_size(".whl", KIT),
            ".gl": kit_script.pinned_size(".gl", KIT), "moved by slim": sum((ROOT / p).stat().st_size for p in files)}
    want["in all"] = want["tracked files"] + want[".whl"] + want[".gl"]
    rows = {r[0]: float(r[1].strip("*")) for r in _table("## What travels")}
    for part, size in want.items():
        key = next(k for k in rows if part in k)
        assert abs(rows[key] - size / MIB) <= 0.5, f"docs/gpu.md: {key} {rows[key]} MiB, counted {size / MIB:.2f}"
    assert rows[next(k for k in rows if "in all" in k)] <= 60


def test_the_device_time_plan_fits_in_12_of_the_15_minutes():
    rows = _table("## Device time")
    total = next(r for r in rows if r[0].startswith("**total"))
    minutes = [float(r[1]) for r in rows if r is not total]
    assert len(minutes) >= 6 and all(m > 0 for m in minutes)
    assert sum(minutes) == pytest.approx(float(total[1].strip("*")))
    assert sum(minutes) <= 12
    assert any("rerun" in r[0] for r in rows) and any("start" in r[0] for r in rows) and any("transfer" in r[0] for r in rows)


def test_the_documented_call_fails_when_the_check_fails():
    call = DOC.split("## The call", 1)[1].split("```sh\n", 1)[1].split("```", 1)[0]
    assert "| tee" in call and call.index("set -o pipefail") < call.index("| tee")
    assert "device_kit.py slim" in DOC and "device_kit.py restore" in DOC
