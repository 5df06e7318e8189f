"""Where a study config comes from: a preset name (configs/study/<name>.yaml) or a YAML file.

Torch-free, unlike `study.pipeline.config` (whose sections take their fields from the experiments'
configs, `study.engine.train` among them): the command line resolves the name here first, so a typo is
refused in a fraction of a second instead of after the seconds torch takes to import.
"""

from __future__ import annotations

from pathlib import Path

from sim.errors import UserError

PRESETS_DIR = Path(__file__).resolve().parents[2] / "configs" / "study"


def preset_names() -> list[str]:
    return sorted(p.stem for p in PRESETS_DIR.glob("*.yaml"))


def study_config_file(spec: str) -> Path:
    """The YAML file a study config `spec` names: a preset, or a path (UserError when it is neither)."""
    path = Path(spec)
    if not spec.endswith((".yaml", ".yml")) and not path.exists():
        preset = PRESETS_DIR / f"{spec}.yaml"
        if not preset.is_file():
            raise UserError(f"{spec!r} is neither a preset ({', '.join(preset_names())}) nor a YAML file")
        path = preset
    if not path.is_file():
        raise UserError(f"{spec}: " + ("not a file" if path.exists() else "does not exist"))
    return path
