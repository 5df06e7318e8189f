"""The code identity's disk cache (`study.engine.code_identity`): values keyed by the module's text,
read back by the next process, ignored where damaged or unusable; the digest is the same either way."""

import json

import pytest

import study.engine.code_identity as ci

MODULES = ["study.outputs", "study.engine.code_identity"]  # a small closure: a few modules, a few parses


def _fresh_process(monkeypatch):
    """What a new process starts with: no entries read, no parse remembered."""
    monkeypatch.setattr(ci, "_disk", None)
    monkeypatch.setattr(ci, "_disk_dirty", False)
    monkeypatch.setattr(ci, "_used", set())
    ci.source_digest.cache_clear()
    ci._imports.cache_clear()


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("HYDRABENCH_CACHE", str(tmp_path / "cache"))
    _fresh_process(monkeypatch)
    yield tmp_path / "cache" / ci.DISK_FILE
    _fresh_process(monkeypatch)


def test_a_second_process_reads_the_parses_back_and_gets_the_same_digest(cache, monkeypatch):
    first = ci.code_digest(MODULES)
    entries = json.loads(cache.read_text())
    assert {k.split(":")[0] for k in entries} == {"ast", "imports"} and len(entries) >= 2 * len(ci.closure(MODULES))
    _fresh_process(monkeypatch)
    monkeypatch.setattr(ci, "_ast_digest", lambda source: pytest.fail("parsed again"))
    monkeypatch.setattr(ci, "_parse_imports", lambda name, source: pytest.fail("parsed again"))
    assert ci.code_digest(MODULES) == first


def test_an_edited_module_is_parsed_again_under_its_new_text(cache, monkeypatch):
    first = ci.code_digest(MODULES)
    real = ci.read_module
    monkeypatch.setattr(ci, "read_module", lambda name: real(name) + ("\nEDITED = 1\n" if name == MODULES[0] else ""))
    _fresh_process(monkeypatch)
    assert ci.code_digest(MODULES) != first  # the old entry is under the old text's key


def test_a_damaged_or_unusable_cache_changes_nothing(cache, tmp_path, monkeypatch):
    first = ci.code_digest(MODULES)
    cache.write_text("{not json")
    _fresh_process(monkeypatch)
    assert ci.code_digest(MODULES) == first
    assert json.loads(cache.read_text())  # written again, whole
    monkeypatch.setenv("HYDRABENCH_CACHE", "/proc/no-such-cache")
    _fresh_process(monkeypatch)
    assert ci.code_digest(MODULES) == first


def test_past_its_bound_the_file_keeps_what_the_writer_used(cache, monkeypatch):
    first = ci.code_digest(MODULES)
    used = set(json.loads(cache.read_text()))
    stale = {f"ast::{i:064x}": "0" * 64 for i in range(40)}  # entries of module texts edited away long ago
    cache.write_text(json.dumps({**json.loads(cache.read_text()), **stale}))
    monkeypatch.setattr(ci, "DISK_ENTRIES", len(used) + 10)
    _fresh_process(monkeypatch)
    real = ci.read_module
    monkeypatch.setattr(ci, "read_module", lambda name: real(name) + ("\nEDITED = 2\n" if name == MODULES[0] else ""))
    assert ci.code_digest(MODULES) != first  # one module parsed again: the file is written, now over its bound
    kept = set(json.loads(cache.read_text()))
    assert not kept & set(stale) and len(kept - used) == 2 and len(used - kept) == 2  # the edited module: new text, new keys
