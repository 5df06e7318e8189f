"""Reading checkpoints (`checkpoint.pt`, `epoch-NNN.pt`, a gate's `gate.pt`): the one place a torch
file enters, so a truncated, foreign or empty file is a UserError naming it, never a torch traceback."""

from __future__ import annotations

from pathlib import Path

from sim.errors import UserError


def checkpoint_problem(path: str | Path) -> str | None:
    """Why `path` cannot be a torch checkpoint, from its zip directory alone (milliseconds, no tensor
    read: torch.save writes a zip archive whose directory is at the end, so a truncated file has
    none), or None. `load_checkpoint` still reads it whole when it is used."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as z:
            names = z.namelist()
    except (zipfile.BadZipFile, EOFError):
        return "is not a readable checkpoint (truncated, or not a torch file)"
    except OSError as exc:
        return f"cannot be read ({exc.strerror})"
    if not any(n.endswith("data.pkl") for n in names):
        return "is not a torch checkpoint (a zip archive without data.pkl)"
    return None


def load_checkpoint(path: str | Path, keys: tuple[str, ...] = ("model",)) -> dict:
    """The dict saved in `path`, on the CPU, holding at least `keys` (UserError otherwise)."""
    import torch

    path = Path(path)
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except FileNotFoundError:
        raise UserError(f"{path} does not exist") from None
    except IsADirectoryError:
        raise UserError(f"{path} is a directory, expected a checkpoint file") from None
    except Exception as exc:  # truncated zip, not a torch file, unpickling errors: torch's reasons vary
        reason = str(exc).splitlines()[0][:120] if str(exc) else type(exc).__name__
        raise UserError(f"{path} is not a readable checkpoint ({reason}); it may be truncated: "
                        "delete it, or restore it from a copy") from None
    if not isinstance(state, dict):
        raise UserError(f"{path} is not a hydrabench checkpoint (it holds a {type(state).__name__}, not a dict)")
    missing = [k for k in keys if k not in state]
    if missing:
        raise UserError(f"{path} is not a hydrabench checkpoint (no {missing[0]!r} entry)")
    return state


def load_weights(module, state_dict, path: str | Path) -> None:
    """module.load_state_dict(state_dict), a mismatch (weights of another model) as a UserError naming `path`."""
    try:
        module.load_state_dict(state_dict)
    except (RuntimeError, KeyError, TypeError, ValueError, AttributeError) as exc:
        reason = " ".join(str(exc).split())[:160]
        raise UserError(f"{path} holds weights of another model ({reason})") from None
