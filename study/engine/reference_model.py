"""Reference models: trained detectors (and their gates) committed to the repository, usable by name.

A reference model is a directory `models/<name>/` that is also a training run (`hydrabench train
--out`), reduced to what inference, gates and warm starts read:

    config.json          the training run's config (branches, resolved model profile, the dataset's
                         generation config)
    checkpoint.pt        {"model": state dict}, floating tensors in float16 (weights only: no
                         optimiser, no RNG states); loading copies them into the float32 network
    gates/<g>/gate.pt    HydraFusion gates trained on exactly this checkpoint (`train-gate`)
    manifest.json        what it is and how it was made: the command and commit, the CPU, the
                         dataset's generation config and its digest, the sha256 and size of every
                         file, the measured mAP

Every command that takes a RUN takes `NAME` (a directory of `MODEL_DIR`) or the directory's path:
the files are checked against the manifest (a damaged file or a Git LFS pointer is a one-line
error); one in `MODEL_DIR` is copied once into a writable cache run,
`study.outputs.cache_root()/models/<name>-<sha12>/` (`$HYDRABENCH_CACHE`, default `~/.cache/hydrabench`), because evaluation
writes its caches into the run and the repository stays clean; one elsewhere is used in place.

Making one (`scripts/make_reference_model.sh`): `hydrabench model export RUN --out DIR` writes the
float16 run, `train-gate` trains the gates on it, `hydrabench model export DIR --out models/NAME
--measured EVAL.json` packs it with its manifest (the checkpoint is then copied byte for byte, so
the gates stay valid).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

from sim.errors import UserError
from study.engine.gate_data import file_sha256 as sha256
from study.outputs import cache_root

MODEL_DIR = Path(__file__).resolve().parents[2] / "models"
"""Where named reference models live (in the repository)."""

KIND = "hydrabench-reference-model"
MAX_BYTES = 40 * 2**20
"""Issue 27's budget for a committed model's weights (about 40 MB)."""


def available_models() -> list[str]:
    """Names of the reference models in `MODEL_DIR`."""
    return sorted(p.parent.name for p in MODEL_DIR.glob("*/manifest.json"))


def model_dir(text: str) -> Path | None:
    """The reference-model directory `text` names (a name in `MODEL_DIR` or a directory holding a
    reference-model manifest), or None when it names none (an ordinary run directory, say)."""
    path = Path(text)
    if not path.exists() and os.sep not in str(text) and (MODEL_DIR / str(text) / "manifest.json").is_file():
        path = MODEL_DIR / str(text)
    man = path / "manifest.json"
    if not man.is_file():
        return None
    try:
        kind = json.loads(man.read_text()).get("kind")
    except (OSError, ValueError, AttributeError):
        return None
    return path if kind == KIND else None


def read_manifest(path: Path) -> dict:
    try:
        man = json.loads((Path(path) / "manifest.json").read_text())
    except (OSError, ValueError) as err:
        raise UserError(f"{path}/manifest.json: unreadable ({err.__class__.__name__})") from None
    if not isinstance(man, dict) or man.get("kind") != KIND or not isinstance(man.get("files"), dict):
        raise UserError(f"{path}/manifest.json is not a reference-model manifest")
    return man


def verify(path: Path) -> dict:
    """The manifest of the reference model at `path`, after checking every file it lists (sha256 and
    size) and that its config.json describes the same network (profile and branches). UserError
    (one line) on the first mismatch."""
    path = Path(path)
    man = read_manifest(path)
    for rel, want in man["files"].items():
        f = path / rel
        if not f.is_file():
            raise UserError(f"reference model {man.get('name')!r}: {rel} is missing from {path}")
        size = f.stat().st_size
        if size != want["bytes"] or sha256(f) != want["sha256"]:
            hint = " (a Git LFS pointer? run `git lfs pull`)" if size < 1024 else ""
            raise UserError(f"reference model {man.get('name')!r}: {rel} does not match its manifest "
                            f"({size} bytes, sha256 differs){hint}")
    cfg = json.loads((path / "config.json").read_text())
    if cfg.get("model_profile") != man["profile"] or _fields_sha(cfg) != man["profile_fields_sha256"]:
        raise UserError(f"reference model {man.get('name')!r}: config.json's model profile is not the manifest's "
                        f"({cfg.get('model_profile')!r} against {man['profile']!r})")
    if list(cfg.get("branches", [])) != list(man["branches"]):
        raise UserError(f"reference model {man.get('name')!r}: config.json's branches {cfg.get('branches')} are not "
                        f"the manifest's {man['branches']}")
    return man


def resolve_run(text: str) -> Path:
    """A RUN argument -> the run directory to use. A reference model in `MODEL_DIR` (by name or path)
    is verified and copied into its cache run (once; atomic), so nothing is written into the
    repository; one elsewhere (a model you exported) is verified and used in place, so the gates
    trained on it land beside it; anything else is returned as given."""
    src = model_dir(text)
    if src is None:
        return Path(text)
    man = verify(src)
    if MODEL_DIR.resolve() not in src.resolve().parents:
        return src
    dest = cache_root() / "models" / f"{man['name']}-{man['files']['checkpoint.pt']['sha256'][:12]}"
    if dest.is_dir() and all((dest / rel).is_file() and (dest / rel).stat().st_size == v["bytes"]
                             for rel, v in man["files"].items()):
        return dest
    tmp = dest.with_name(dest.name + f".tmp-{os.getpid()}")
    try:
        dest.parent.mkdir(parents=True, exist_ok=True)
        shutil.rmtree(tmp, ignore_errors=True)
        for rel in [*man["files"], "manifest.json"]:
            (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src / rel, tmp / rel)
        shutil.rmtree(dest, ignore_errors=True)
        os.replace(tmp, dest)
    except OSError as exc:  # a full disk: no half copy left in the cache
        shutil.rmtree(tmp, ignore_errors=True)
        raise UserError(f"cannot copy reference model {man['name']!r} into the cache {dest.parent} "
                        f"({exc.strerror}); free space there or set HYDRABENCH_CACHE") from None
    return dest


def _fields_sha(cfg: dict) -> str:
    return hashlib.sha256(json.dumps(cfg.get("profile_fields"), sort_keys=True).encode()).hexdigest()


def _git_commit() -> str | None:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=MODEL_DIR.parent, capture_output=True, text=True,
                             timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None


def half_checkpoint(src: Path, dest: Path) -> int:
    """RUN/checkpoint.pt -> `dest` holding {"model": state dict} with floating tensors in float16;
    returns the parameter count. Refuses weights float16 cannot hold (|w| > 65504)."""
    import torch

    from study.engine.checkpoints import load_checkpoint

    state = load_checkpoint(src)["model"]
    out, n = {}, 0
    for k, v in state.items():
        if torch.is_floating_point(v):
            if v.numel() and float(v.abs().max()) > torch.finfo(torch.float16).max:
                raise UserError(f"{src}: tensor {k} exceeds float16's range; cannot export it in float16")
            out[k] = v.detach().to(torch.float16).contiguous()
            n += v.numel()
        else:
            out[k] = v
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(dest.name + ".tmp")
    torch.save({"model": out}, tmp)
    os.replace(tmp, dest)
    return n


def _is_half(path: Path) -> bool:
    import torch

    from study.engine.checkpoints import load_checkpoint

    ckpt = load_checkpoint(path)
    return set(ckpt) == {"model"} and all(v.dtype == torch.float16 for v in ckpt["model"].values()
                                          if torch.is_floating_point(v))


def export_model(run: Path, out: Path, *, name: str, measured: dict | None = None, max_bytes: int = MAX_BYTES,
                 training_commit: str | None = None) -> dict:
    """Write the reference model of training run `run` to `out` (module docstring) -> its manifest.

    A float32 checkpoint is converted to float16 (weights only); a float16 weights-only one (a run
    this function wrote) is copied byte for byte, with every gate in RUN/gates trained on it. Gates
    trained on another checkpoint are left out (listed in the manifest's "skipped_gates").
    `measured`: a JSON-able record of what the model scored (`hydrabench evaluate --json`).
    `training_commit`: the commit the run trained at, 7 to 40 hex digits (default: this checkout's
    HEAD, which is also recorded as the commit that exported it). The manifest's training command is
    written from the run's config.json (`train_command`). The weights are loaded into the network the
    config describes first: a checkpoint of another network is refused, and nothing is left behind.
    Refuses an `out` that holds anything but an earlier export, and weights over `max_bytes`.
    """
    run, out = Path(run), Path(out)
    cfg_path, ckpt = run / "config.json", run / "checkpoint.pt"
    if not cfg_path.is_file() or not ckpt.is_file():
        raise UserError(f"{run} is not a training run (needs config.json and checkpoint.pt)")
    if not re.fullmatch(r"[a-z0-9][a-z0-9_-]{0,39}", str(name)):
        raise UserError(f"--name {name!r}: lower-case letters, digits, '-' and '_', starting with a letter or digit")
    if training_commit is not None and not re.fullmatch(r"[0-9a-f]{7,40}", str(training_commit)):
        raise UserError(f"--training-commit {training_commit!r}: 7 to 40 hexadecimal digits of a git commit")
    if out.exists() and any(out.iterdir()) and not (out / "manifest.json").is_file():
        raise UserError(f"{out} exists and is not a reference model; choose an empty or new --out")
    from study.engine.scoring import load_run

    load_run(run)  # the weights fit the network config.json describes (UserError naming the file otherwise)
    cfg = json.loads(cfg_path.read_text())
    tmp = out.with_name(out.name + ".export-tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        manifest = _write_export(run, out, tmp, cfg, name, measured, max_bytes, training_commit)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    shutil.rmtree(out, ignore_errors=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    os.replace(tmp, out)
    return manifest


def train_command(cfg: dict) -> str:
    """The `hydrabench train` command line that makes a run with this config.json (the dataset as
    DATA, the run as RUN; device options left out)."""
    args = ["hydrabench train DATA --out RUN", f"--profile {cfg.get('model_profile', 'cpu')}",
            f"--branch-set {cfg.get('branch_set', 'paper')}"]
    if cfg.get("branches"):
        args.append("--branches " + ",".join(cfg["branches"]))
    for key, flag in (("epochs", "--epochs"), ("batch_size", "--batch-size"), ("lr", "--lr"),
                      ("warmup_steps", "--warmup-steps"), ("lr_drop_epoch", "--lr-drop-epoch"),
                      ("clip_grad", "--clip-grad"), ("seed", "--seed"), ("gate_holdout", "--gate-holdout"),
                      ("hflip", "--hflip"), ("protocol", "--protocol"), ("sampling", "--sampling")):
        if cfg.get(key) is not None:
            args.append(f"{flag} {cfg[key]:g}" if isinstance(cfg[key], float) else f"{flag} {cfg[key]}")
    precision = (cfg.get("compute") or {}).get("precision")
    args.append("--amp bf16" if precision == "bf16" else "--no-amp")
    args += [f"--model {m}" for m in cfg.get("model", [])]
    return " ".join(args)


def _write_export(run: Path, out: Path, tmp: Path, cfg: dict, name: str, measured, max_bytes: int,
                  training_commit) -> dict:
    from study.bench.scale import cpu_model
    from study.engine.checkpoints import load_checkpoint

    ckpt, cfg_path = run / "checkpoint.pt", run / "config.json"
    if _is_half(ckpt):
        shutil.copyfile(ckpt, tmp / "checkpoint.pt")
        params = sum(v.numel() for v in load_checkpoint(ckpt)["model"].values() if v.is_floating_point())
    else:
        params = half_checkpoint(ckpt, tmp / "checkpoint.pt")
    size = (tmp / "checkpoint.pt").stat().st_size
    if size > max_bytes:
        raise UserError(f"{run}: {params / 1e6:.1f} M parameters are {size / 2**20:.1f} MiB in float16, over the "
                        f"{max_bytes / 2**20:.0f} MiB budget; train a narrower model (train --model width=0.5)")
    shutil.copyfile(cfg_path, tmp / "config.json")
    ck_sha = sha256(tmp / "checkpoint.pt")
    gates, skipped = [], []
    for g in sorted(p.parent.name for p in (run / "gates").glob("*/gate.pt")):
        saved = load_checkpoint(run / "gates" / g / "gate.pt", ("state",))
        if saved.get("checkpoint_sha256") == ck_sha:
            (tmp / "gates" / g).mkdir(parents=True)
            shutil.copyfile(run / "gates" / g / "gate.pt", tmp / "gates" / g / "gate.pt")
            gates.append(g)
        else:
            skipped.append(g)
    files = {rel: {"sha256": sha256(tmp / rel), "bytes": (tmp / rel).stat().st_size}
             for rel in ["config.json", "checkpoint.pt", *(f"gates/{g}/gate.pt" for g in gates)]}
    data_cfg = cfg.get("data_config")
    manifest = {
        "kind": KIND, "name": name, "profile": cfg.get("model_profile"),
        "profile_fields_sha256": _fields_sha(cfg), "model_overrides": list(cfg.get("model", [])),
        "branches": list(cfg.get("branches", [])), "protocol": cfg.get("protocol"),
        "weights": {"dtype": "float16", "parameters": params, "bytes": size},
        "gates": gates, "skipped_gates": skipped, "files": files,
        "training": {"command": train_command(cfg), "commit": training_commit or _git_commit(),
                     "exported_at_commit": _git_commit(), "exported_on_cpu": cpu_model(),
                     "compute": cfg.get("compute"), "epochs": cfg.get("epochs"), "lr": cfg.get("lr"),
                     "gate_holdout": cfg.get("gate_holdout")},
        "data": {"generation_config": data_cfg,
                 "generation_config_sha256": hashlib.sha256(json.dumps(data_cfg, sort_keys=True).encode()).hexdigest()},
        "measured": measured or {},
    }
    (tmp / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")
    return manifest


MEASURED_KEYS = ("split", "frames", "fusion", "map", "map_vehicles", "map_per_branch_reference",
                 "map_vehicles_per_context", "map_per_context", "device")


def compact_measured(r: dict) -> dict:
    """The figures of a `hydrabench evaluate --json` result a manifest keeps: overall and per-context
    mAP, each branch's mAP and vehicle mAP (with its 95 % interval when bootstrapped). Any other JSON
    is kept whole."""
    if not isinstance(r, dict) or "map_per_branch_reference" not in r:
        return r
    out = {k: r[k] for k in MEASURED_KEYS if k in r}
    out["map_vehicles_per_branch_reference"] = {b: v.get("map_vehicles") for b, v in r.get("per_branch_reference", {}).items()}
    iv = (r.get("ci95") or {}).get("per_context", {}).get("all", {})
    if iv:
        out["ci95_map_vehicles"] = iv.get("map_vehicles")
        out["bootstrap"] = {"resamples": r["ci95"].get("resamples"), "sequences": iv.get("sequences")}
    return out
