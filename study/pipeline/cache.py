"""The stage cache of `hydrabench study`: a study directory (`Study`), its stages' keys and records,
and the link farms the stages below `train` work on. What goes into a key and which stage runs
what: `study.pipeline.stages`."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from sim.config import to_dict
from sim.errors import UserError
from study.outputs import write_json_atomic

if TYPE_CHECKING:
    from study.pipeline.config import StudyConfig

STUDY_VERSION = 2
MARKER = "study.json"
"""The file that makes DIR a study directory (a folder of other files is refused)."""


def json_digest(obj) -> str:
    """SHA-256 of `obj` as sorted JSON. (Its name is in the stage functions' source, which their keys
    hash: renaming it reruns every study; it was `_digest` until the stages stopped importing a private name.)"""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def link_farm(src: Path, dst: Path) -> None:
    """Recreate `src`'s directories under `dst` and symlink its files (relative links); entries
    already in `dst` are kept (a resumed stage keeps what it wrote)."""
    src, dst = Path(src).resolve(), Path(dst)
    for dirpath, _dirs, filenames in os.walk(src):
        rel = Path(dirpath).relative_to(src)
        target_dir = dst / rel
        target_dir.mkdir(parents=True, exist_ok=True)
        for f in filenames:
            if f.startswith(".") and ".tmp" in f:
                continue
            link = target_dir / f
            if not link.exists() and not link.is_symlink():
                os.symlink(os.path.relpath(Path(dirpath) / f, target_dir.resolve()), link)


@dataclass
class StageRecord:
    name: str
    key: str
    dir: Path
    status: str = "pending"
    seconds: float = 0.0
    digest: str = ""
    manifest: dict = field(default_factory=dict)


class Study:
    """One study directory: its config, its stages and their records."""

    def __init__(self, cfg: StudyConfig, out: str | Path, progress: bool = True) -> None:
        self.cfg, self.out, self.progress = cfg, Path(out), progress
        self.stages_dir = self.out / "stages"
        self.records: dict[str, StageRecord] = {}

    # -- bookkeeping --
    def say(self, text: str) -> None:
        if self.progress:
            sys.stderr.write(f"[study] {text}\n")
            sys.stderr.flush()

    def prepare(self) -> None:
        """Refuse a directory of other files; write the marker and the config."""
        if self.out.exists():
            if not self.out.is_dir():
                raise UserError(f"--out {self.out} exists and is not a directory")
            entries = [e.name for e in self.out.iterdir()]
            if entries and MARKER not in entries:
                raise UserError(f"--out {self.out} is not empty and holds no study (no {MARKER}); use a new or "
                                "empty directory")
        self.stages_dir.mkdir(parents=True, exist_ok=True)
        write_json_atomic(self.out / MARKER, {"version": STUDY_VERSION, "config": to_dict(self.cfg)}, default=str)

    @staticmethod
    def key(name: str, inputs: dict) -> str:
        """The key of stage `name` made of `inputs` (with their "upstream" part): 16 hex digits."""
        return json_digest({"stage": name, "version": STUDY_VERSION, **inputs})[:16]

    def stage(self, name: str, inputs: dict, upstream: tuple[StageRecord, ...], func, **kwargs) -> StageRecord:
        """Run `func(work_dir, **kwargs) -> (outputs digest, extra manifest fields)` unless the stage
        with this key is done. The key is made of `inputs` (with what `stage_identity` adds) and the
        key and digest of each `upstream` stage; see the module docstring."""
        inputs = {**inputs, "upstream": {r.name: {"key": r.key, "digest": r.digest} for r in upstream}}
        key = self.key(name, inputs)
        final = self.stages_dir / f"{name}-{key}"
        partial = self.stages_dir / f"{name}-{key}.partial"
        rec = StageRecord(name, key, final)
        manifest_path = final / "manifest.json"
        if manifest_path.is_file():
            rec.manifest = json.loads(manifest_path.read_text())
            rec.status, rec.digest = "skipped", rec.manifest["digest"]
            self.say(f"{name}: skipped (done, key {key}, took {rec.manifest['seconds']} s when it ran)")
            self.records[name] = rec
            return rec
        resumed = partial.exists()
        partial.mkdir(parents=True, exist_ok=True)
        self.say(f"{name}: {'resuming' if resumed else 'running'} (key {key})")
        t0 = time.perf_counter()
        rec.dir = partial
        digest, extra = func(partial, **kwargs)
        rec.seconds = round(time.perf_counter() - t0, 2)
        rec.digest = digest
        rec.manifest = {"stage": name, "key": key, "compute": inputs.get("compute"), "inputs": inputs,
                        "digest": digest, "seconds": rec.seconds,
                        "finished": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), **extra}
        write_json_atomic(partial / "manifest.json", rec.manifest, default=str)
        if final.exists():  # a stale final directory without a manifest (cannot happen via rename) is replaced
            shutil.rmtree(final)
        os.replace(partial, final)
        rec.dir, rec.status = final, "ran"
        self.say(f"{name}: done in {rec.seconds} s")
        self.records[name] = rec
        return rec

    def summary(self) -> dict:
        return {n: {"key": r.key, "status": r.status, "seconds": r.seconds, "dir": str(r.dir),
                    "compute": r.manifest.get("compute")} for n, r in self.records.items()}
