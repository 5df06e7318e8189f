"""`hydrabench bench recipe`: training recipes and cost options judged by vehicle mAP per CPU-hour.

Each candidate is one `hydrabench train` run of one branch on the same dataset (the same split,
gate split, initial weights and frame order; `OUT/<candidate>/`, resumable), differing from the base
recipe in what the candidate names: learning rate, warm-up, augmentation (`hflip`), or model-profile
overrides (`--model`: width, output stride, sampled RoIs, ...). After training, every epoch's
checkpoint is scored on the run's **gate split** (sequences no detector trained on and that are not
test frames: a fixed held-out set, the same for every candidate), the branch alone in the right
camera, vehicle mAP@0.5. The curve of each candidate is that mAP against the CPU time its training
took so far (core-hours: the training steps' seconds times the threads), and the choice is the
candidate with the highest held-out vehicle mAP at the budget of the cheapest candidate's last
epoch (each curve interpolated linearly, flat after its end): the most learned for the same CPU
time. The last epoch also gets a 95 % interval (whole held-out sequences drawn). Nothing here reads
the test split. A second call trains nothing and rescores nothing (`ScoreMemo`).

A candidate may set its own `epochs`: candidates that differ only in it trace the *budget
frontier* (each end is a whole schedule, its learning-rate drop included), and `aim` says where a
held-out vehicle mAP is reached on it (`aim_reached`).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from study.bench.scale import cpu_model

BASE = {"lr": 0.02, "warmup_steps": 60, "clip_grad": 10.0, "batch_size": 4, "gate_holdout": 0.3,
        "model": ("width=0.5",), "amp": "auto"}
"""The `cpu` study's recipe at the reference model's width (configs/study/cpu.yaml)."""

DEFAULT_CANDIDATES: dict[str, dict] = {
    "base": {},
    "lr 0.04": {"lr": 0.04},
    "hflip 0.5": {"hflip": 0.5},
    "bev stride 16": {"model": ("width=0.5", "bev.output_stride=16")},
    "64 RoIs": {"model": ("width=0.5", "box_batch_size_per_image=64")},
}
"""Name -> the fields that differ from `BASE` (TrainConfig fields)."""

TUNABLE = ("lr", "warmup_steps", "clip_grad", "hflip", "model", "lr_drop_epoch", "epochs")
"""`epochs` gives a candidate its own schedule length (the learning-rate drop follows at 3/4 of it):
candidates that differ only in `epochs` measure what each budget buys when spent on a whole schedule."""


def parse_candidate(text: str) -> tuple[str, dict]:
    """'NAME:FIELD=VALUE+FIELD=VALUE' -> (name, fields); `model` values are one override each
    ('big lr:lr=0.04', 'narrow:model=width=0.25')."""
    import yaml

    from sim.errors import UserError

    name, colon, rest = str(text).partition(":")
    if not colon or not name.strip():
        raise UserError(f"--candidate {text!r}: expected NAME:FIELD=VALUE[+FIELD=VALUE], e.g. fast:lr=0.04")
    fields: dict = {}
    for item in filter(None, (x.strip() for x in rest.split("+"))):
        key, eq, raw = item.partition("=")
        if not eq or key not in TUNABLE:
            raise UserError(f"--candidate {name}: {item!r} is not FIELD=VALUE with FIELD one of {', '.join(TUNABLE)}")
        if key == "model":
            fields.setdefault("model", list(BASE["model"]))
            fields["model"] = [m for m in fields["model"] if m.split("=")[0] != raw.split("=")[0]] + [raw]
        else:
            fields[key] = yaml.safe_load(raw)
    if "model" in fields:
        fields["model"] = tuple(fields["model"])
    return name.strip(), fields


def _curve_at(xs, ys, budget: float) -> float:
    """The curve's value at `budget` core-hours: linear between epochs, 0 before the first point's
    x (from (0, 0)), flat after the last."""
    return float(np.interp(budget, [0.0, *xs], [0.0, *ys]))


def _check_options(out: Path, marker: Path, candidates: dict, epochs: int, bootstrap: int, aim: float | None) -> None:
    """Refuse (UserError, one line) what the bench cannot run: an --out holding other files, the
    bootstrap's draws, --aim, a candidate's epochs; before any work."""
    from sim.errors import UserError

    ours = {marker.name, *(_dir(n) for n in candidates)}
    if out.exists() and (not out.is_dir() or any(p.name not in ours and p.suffix not in (".png", ".pdf", ".svg")
                                                 for p in out.iterdir())):
        raise UserError(f"--out {out} holds other files than this bench's candidate runs, {marker.name} and its "
                        "figures; use a new or empty directory (or the same candidates)")
    if not 0 <= bootstrap <= 10000:
        raise UserError(f"--bootstrap must be 0..10000 draws, got {bootstrap}")
    if aim is not None and not 0.0 < aim <= 1.0:
        raise UserError(f"--aim must be a vehicle mAP in (0, 1], got {aim}")
    for name, fields in candidates.items():
        n_ep = fields.get("epochs", epochs)
        if isinstance(n_ep, bool) or not isinstance(n_ep, int) or not 1 <= n_ep <= 100:
            raise UserError(f"--candidate {name}: epochs must be a whole number 1..100, got {n_ep!r}")


def bench_recipe(data: str, out, branch: str = "lidar", candidates: dict | None = None, epochs: int = 3,
                 profile: str = "cpu", threads: int = 0, seed: int = 0, bootstrap: int = 200,
                 progress: bool = True, aim: float | None = None) -> dict:
    """The comparison of the module docstring -> a JSON-able dict (also written to OUT/recipe.json)."""
    import csv

    import torch

    from sensors.dataset import DatasetReader
    from sensors.dataset import check as check_dataset
    from sim.errors import UserError
    from study.engine.device import default_threads
    from study.engine.scoring import (
        context_bootstrap,
        frames_for,
        fused,
        fusion_method,
        load_run,
        run_branches,
        score,
    )
    from study.engine.train import TrainConfig, train

    out = Path(out)
    data = str(Path(data).resolve())
    candidates = dict(candidates or DEFAULT_CANDIDATES)
    marker = out / "recipe.json"
    _check_options(out, marker, candidates, epochs, bootstrap, aim)
    check_dataset(data)
    n_threads = threads or default_threads()
    reader = DatasetReader(data)
    rows, sources = {}, {}
    for name, fields in candidates.items():
        n_ep = int(fields.get("epochs", epochs))
        cfg = TrainConfig(**{"data": data, "model_profile": profile, "branches": (branch,), "epochs": n_ep,
                             "seed": seed, "threads": n_threads, "device": "cpu", "eval_frames": 1,
                             "checkpoint_seconds": 300.0, **BASE, **fields})
        t0 = time.perf_counter()
        train(cfg, out / _dir(name), progress=progress)
        with open(out / _dir(name) / "metrics.csv") as fh:
            epochs_rows = list(csv.DictReader(fh))
        if len(epochs_rows) < n_ep:
            raise UserError(f"{out / _dir(name)}: {len(epochs_rows)} epochs recorded, {n_ep} asked")
        run_cfg = json.loads((out / _dir(name) / "config.json").read_text())
        held, _ = frames_for(run_cfg, data, "gate")
        if not held:
            raise UserError(f"{data}: the run has no gate split to score on (gate_holdout {BASE['gate_holdout']})")
        protocol = run_cfg.get("protocol", "reference")
        memo = ScoreMemo(out / _dir(name), {"held_out": held, "protocol": protocol, "branch": branch,
                                            "fusion": "soft-nms", "camera": "camera_right"})
        curve, spent = [], 0.0
        for e, row in enumerate(epochs_rows[:n_ep], start=1):
            spent += float(row["train_seconds"]) * n_threads / 3600.0
            sc = memo.get(e)
            if sc is None or (e == n_ep and bootstrap):  # the last epoch's detections feed the bootstrap
                model, _ = load_run(out / _dir(name), f"epoch-{e:03d}", device="cpu")
                torch.set_num_threads(n_threads)
                per = run_branches(model, data, held, [branch], progress=f"{name}: epoch {e} on the gate split")
                alone = fused(per, [branch], model.branch_frames, fusion_method("soft-nms"))
                sc = score(alone, reader, "camera_right", protocol=protocol)
                sc = memo.put(e, {"map_vehicles": sc["map_vehicles"], "map": sc["map"]})
                if e == n_ep:
                    sources[name] = alone
            curve.append({"epoch": e, "core_hours": round(spent, 4), **sc})
        rows[name] = {"fields": {k: list(v) if isinstance(v, tuple) else v for k, v in fields.items()},
                      "curve": curve, "train_seconds": round(sum(float(r["train_seconds"]) for r in epochs_rows), 1),
                      "seconds_this_call": round(time.perf_counter() - t0, 1), "compute": run_cfg.get("compute")}
    budget = min(r["curve"][-1]["core_hours"] for r in rows.values())
    for r in rows.values():
        xs = [p["core_hours"] for p in r["curve"]]
        ys = [p["map_vehicles"] or 0.0 for p in r["curve"]]
        r["map_vehicles_at_budget"] = round(_curve_at(xs, ys, budget), 4)
        r["map_vehicles_per_core_hour"] = round(ys[-1] / xs[-1], 4) if xs[-1] > 0 else None
    if bootstrap:
        ci = context_bootstrap(sources, reader, "camera_right", resamples=bootstrap, desc="bootstrap the candidates")
        all_ = ci["per_context"]["all"]
        for name, r in rows.items():
            r["ci95_map_vehicles_last_epoch"] = all_["map_vehicles"][name]
    chosen = max(rows, key=lambda n: rows[n]["map_vehicles_at_budget"])
    extra = {"aim": aim_reached(rows, aim)} if aim is not None else {}
    result = {"cpu": cpu_model(), "threads": n_threads, "profile": profile, "branch": branch, "epochs": epochs,
              "base": {k: list(v) if isinstance(v, tuple) else v for k, v in BASE.items()}, "data": data,
              "held_out": {"split": "gate", "frames": len(held),
                           "what": "the run's gate split: sequences no candidate trained on, never test frames"},
              "budget_core_hours": round(budget, 4), "chosen": chosen, "candidates": rows, "bootstrap": bootstrap,
              "rule": "highest held-out vehicle mAP at the budget of the cheapest candidate's last epoch",
              "out": str(out), **extra}
    marker.write_text(json.dumps(result, indent=1) + "\n")
    return result


class ScoreMemo:
    """Each epoch's held-out score, kept beside the run (`RUN/held_out_scores.json`) so a second
    call rescores nothing: an entry counts only for the same checkpoint file (its SHA-256) scored
    the same way (held-out frames, protocol, branch, fusion, camera)."""

    NAME = "held_out_scores.json"

    def __init__(self, run: Path, how: dict) -> None:
        import hashlib

        self.run, self.path = run, run / self.NAME
        self.key = hashlib.sha256(json.dumps(how, sort_keys=True).encode()).hexdigest()
        try:
            kept = json.loads(self.path.read_text())
        except (OSError, ValueError):
            kept = {}
        self.entries = kept.get("epochs", {}) if isinstance(kept, dict) and kept.get("key") == self.key else {}
        self._shas: dict[int, str] = {}

    def _sha(self, epoch: int) -> str:
        """The checkpoint's digest, read once per call (`get` then `put` hash the same file)."""
        from study.engine.gate_data import file_sha256

        if epoch not in self._shas:
            self._shas[epoch] = file_sha256(self.run / f"epoch-{epoch:03d}.pt")
        return self._shas[epoch]

    def get(self, epoch: int) -> dict | None:
        e = self.entries.get(str(epoch))
        if not isinstance(e, dict) or e.get("sha256") != self._sha(epoch):
            return None
        return {"map_vehicles": e.get("map_vehicles"), "map": e.get("map")}

    def put(self, epoch: int, sc: dict) -> dict:
        from study.outputs import write_json_atomic

        self.entries[str(epoch)] = {"sha256": self._sha(epoch), **sc}
        write_json_atomic(self.path, {"key": self.key, "epochs": self.entries})
        return sc


def _crossing(curve: list[dict], aim: float) -> float | None:
    """Core-hours where the curve (from (0, 0), linear between epochs) first reaches `aim`, else None."""
    x0, y0 = 0.0, 0.0
    for p in curve:
        x1, y1 = p["core_hours"], p["map_vehicles"] or 0.0
        if y1 >= aim:
            return round(x0 + (x1 - x0) * (aim - y0) / (y1 - y0) if y1 > y0 else x1, 4)
        x0, y0 = x1, y1
    return None


def _stays_from(curve: list[dict], aim: float) -> float | None:
    """Core-hours of the first epoch from which every later epoch of the curve is at or above `aim`
    (a noisy curve may touch the aim once and fall back), else None."""
    at = None
    for p in curve:
        if (p["map_vehicles"] or 0.0) >= aim:
            at = p["core_hours"] if at is None else at
        else:
            at = None
    return at


def aim_reached(rows: dict, aim: float) -> dict:
    """Where a held-out vehicle-mAP aim is reached: per candidate, the first crossing of its curve
    and the epoch from which it stays reached; over all, the cheapest crossing. The *ends* (each
    candidate's last epoch: a whole schedule's result, not an epoch in the middle of one) form the
    budget frontier; if no curve reaches the aim, the frontier's gain per doubling of core-hours
    between its two most expensive ends gives a log-linear extrapolation of the budget that would
    reach it, labelled as such: an optimistic guess, since learning curves flatten."""
    per = {n: _crossing(r["curve"], aim) for n, r in rows.items()}
    hit = {n: x for n, x in per.items() if x is not None}
    ends = sorted(((r["curve"][-1]["core_hours"], r["curve"][-1]["map_vehicles"] or 0.0, n) for n, r in rows.items()))
    out = {"map_vehicles": aim, "per_candidate_core_hours": per,
           "per_candidate_stays_from_core_hours": {n: _stays_from(r["curve"], aim) for n, r in rows.items()},
           "frontier": [{"candidate": n, "core_hours": x, "map_vehicles": y} for x, y, n in ends]}
    if hit:
        best = min(hit, key=hit.get)
        out.update(reached=True, core_hours=hit[best], by=best)
        return out
    top = max(ends, key=lambda e: e[1])
    out.update(reached=False, best_map_vehicles=round(top[1], 4), best_core_hours=top[0])
    if len(ends) >= 2 and ends[-1][0] > ends[-2][0] > 0:
        (xa, ya, _), (xb, yb, _) = ends[-2], ends[-1]
        per_doubling = (yb - ya) / np.log2(xb / xa)
        out["gain_per_doubling"] = round(float(per_doubling), 4)
        if per_doubling > 0:
            out["extrapolated_core_hours"] = round(float(xb * 2 ** ((aim - yb) / per_doubling)), 2)
            out["extrapolation"] = ("log-linear through the two most expensive ends of the frontier; "
                                    "a guess beyond the measured range")
    return out


def _dir(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)


def plot_recipe(r: dict, path) -> None:
    """Held-out vehicle mAP against core-hours, one curve per candidate, the budget marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from study.outputs import savefig_atomic

    a = r.get("aim")
    bold = a["by"] if a and a["reached"] else r["chosen"]
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for name, row in r["candidates"].items():
        xs = [0.0] + [p["core_hours"] for p in row["curve"]]
        ys = [0.0] + [p["map_vehicles"] or 0.0 for p in row["curve"]]
        line, = ax.plot(xs, ys, "o-", ms=4, lw=2.2 if name == bold else 1.2, label=name)
        iv = row.get("ci95_map_vehicles_last_epoch")
        if iv:
            ax.plot([xs[-1], xs[-1]], iv, color=line.get_color(), lw=3, alpha=0.35)
    ax.axvline(r["budget_core_hours"], color="k", ls=":", lw=0.8)
    if a:
        ax.axhline(a["map_vehicles"], color="tab:red", ls="--", lw=0.9, label=f"aim {a['map_vehicles']:g}")
        if len(a["frontier"]) > 1:  # each candidate's end: what a whole schedule of that length buys
            ax.plot([0.0] + [f["core_hours"] for f in a["frontier"]], [0.0] + [f["map_vehicles"] for f in a["frontier"]],
                    "k--", marker="D", ms=5, lw=0.9, label="ends of the schedules")
    ax.set_xlabel(f"training core-hours ({r['threads']} threads x hours), {r['cpu'] or 'CPU'}")
    ax.set_ylabel("vehicle mAP@0.5 on the gate split (held out)")
    lengths = sorted({len(c["curve"]) for c in r["candidates"].values()})
    each = f"{lengths[0]} epochs each" if len(lengths) == 1 else f"{'/'.join(map(str, lengths))} epochs"
    if a:
        stays = _stays_from(r["candidates"][a["by"]]["curve"], a["map_vehicles"]) if a["reached"] else None
        said = (f"aim {a['map_vehicles']:g} first reached at {a['core_hours']} core-h ({a['by']})"
                + (f", stays from {stays}" if stays is not None else "") if a["reached"]
                else f"aim {a['map_vehicles']:g} not reached (best {a['best_map_vehicles']:.3f})")
    else:
        said = f"chosen: {r['chosen']} (dotted: budget)"
    ax.set_title(f"{r['branch']} branch, {each}\n{said}", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    savefig_atomic(fig, path)
    plt.close(fig)
