"""`hydrabench compare`: selective against fixed fusion on one dataset, with intervals.

One pass runs every branch of a trained run (or reference model) once per frame and every gate
beside it; then, in the right camera, with one late-fusion method (`--fusion`, fixed in advance):

- fixed choices: each single-sensor branch alone, `late` (the single-sensor branches fused: the
  paper's late-fusion baseline), `all_branches` (every branch, early-fusion ones included);
- selective: HydraFusion's gates (Table 2 (iv)): each frame's top-k branches by the gate's
  predicted loss, fused. `knowledge` reads the frame's context label; `deep` and `attention` read
  the stem features (trained with `hydrabench train-gate`); `optimal` reads the frame's own
  a-posteriori branch losses (the oracle: no deployable gate does better at choosing by loss).

Every method is scored on the same frames (VOC mAP@0.5, all classes, the run's protocol) and
compared with `late` by the paired sequence bootstrap (`study.detect.context_bootstrap`): whole
sequences drawn with replacement, every method scored on each draw. A difference whose 95 %
interval holds 0 is "not resolved". Nothing is chosen here: k and the fusion method are inputs.
"""

from __future__ import annotations

from pathlib import Path

from sim.errors import UserError

GATES = ("knowledge", "deep", "attention", "optimal")


def verdict(iv) -> str:
    """'above' / 'below' when the interval of a difference excludes 0, else 'not resolved'."""
    if iv is None:
        return "not resolved"
    return "above" if iv[0] > 0 else "below" if iv[1] < 0 else "not resolved"


def compare(run_dir, data, *, gates=GATES, k: int = 2, fusion: str = "soft-nms", split: str = "auto",
            resamples: int = 500, batch_size: int = 4, setup=None, progress: bool = True) -> dict:
    """The comparison of the module docstring -> a JSON-able dict: per method its kind, mAP, vehicle
    mAP, mAP per context, and mAP minus late fusion with its 95 % interval and verdict, overall and
    per context."""
    from study.branch_gate_study import _setup, gate_pass, parse_k
    from study.detect import context_bootstrap, difference_interval, fused, fusion_method, score
    from study.train import run_protocol

    run_dir, data = Path(run_dir), Path(data)
    method = fusion_method(fusion)
    if resamples < 0:
        raise UserError(f"--bootstrap must be >= 0, got {resamples}")
    model, cfg, indices, used_split, reader = _setup(run_dir, data, split, None, "latest", setup)
    protocol = run_protocol(cfg)
    branches = list(model.branches)
    k = parse_k(k, len(branches), "k")
    k = len(branches) if k == "all" else k
    sensors = model.branch_sensors
    singles = [b for b in branches if len(sensors[b]) == 1]
    if not singles:
        raise UserError(f"{run_dir}: no single-sensor branch, so no late-fusion baseline to compare with")
    trained = [g for g in gates if g not in ("deep", "attention") or (run_dir / "gates" / g / "gate.pt").is_file()]
    skipped = [g for g in gates if g not in trained]
    gp = gate_pass(run_dir, data, model, trained, indices, "latest", batch_size, progress)
    frames = model.branch_frames
    kinds = {f"single:{b}": "single sensor" for b in singles}
    choices = {f"single:{b}": [(b,)] * len(gp.per_frame) for b in singles}
    kinds["late"], choices["late"] = "late fusion of the single-sensor branches", [tuple(singles)] * len(gp.per_frame)
    if len(branches) > len(singles):
        kinds["all_branches"] = "every branch (early-fusion ones too)"
        choices["all_branches"] = [tuple(branches)] * len(gp.per_frame)
    for g in trained:
        name = f"hydrafusion:{g}"
        kinds[name] = (f"{g} gate, top {k} of {len(branches)} per frame"
                       + (" (oracle: reads each frame's own losses)" if g == "optimal" else ""))
        choices[name] = [tuple(branches[j] for j in sorted(r[:k])) for r in gp.rankings[g]]
    sources = {}
    for name, per_choice in choices.items():
        sources[name] = [fused([pf], ch, frames, method)[0] for pf, ch in zip(gp.per_frame, per_choice)]
    scores = {n: score(s, reader, "camera_right", protocol=protocol) for n, s in sources.items()}
    boot = (context_bootstrap(sources, reader, "camera_right", protocol=protocol, resamples=resamples,
                              classes="all", desc="bootstrap the methods") if resamples else None)
    contexts = sorted({m["context"] for m, _ in gp.per_frame})
    methods = {}
    for name in choices:
        sc = scores[name]
        row = {"kind": kinds[name], "map": sc["map"], "map_vehicles": sc["map_vehicles"],
               "map_per_context": sc["map_per_context"]}
        if boot and name != "late":
            iv = difference_interval(boot["per_context"]["all"], name, "late")
            row["minus_late"] = {"value": _diff(sc["map"], scores["late"]["map"]), "ci95": iv, "verdict": verdict(iv)}
            row["minus_late_per_context"] = {
                c: {"ci95": (iv_c := difference_interval(boot["per_context"][c], name, "late")),
                    "verdict": verdict(iv_c)} for c in contexts if c in boot["per_context"]}
        if boot:
            row["ci95"] = boot["per_context"]["all"]["map"][name]
        methods[name] = row
    picks = {g: _rates(choices[f"hydrafusion:{g}"], branches) for g in trained}
    return {
        "run": str(run_dir), "data": str(data), "split": used_split, "frames": len(gp.per_frame),
        "sequences": boot["per_context"]["all"]["sequences"] if boot else None, "contexts": contexts,
        "fusion": fusion, "k": k, "protocol": protocol, "branches": branches, "gates": trained,
        "gates_not_trained": skipped, "methods": methods, "selection_rate_pct": picks,
        "bootstrap": {"resamples": resamples, "unit": "sequence"} if boot else None,
        "metric": "VOC all-point AP at IoU 0.5, every class with ground truth, right camera",
    }


def _diff(a, b):
    return None if a is None or b is None else round(a - b, 4)


def _rates(per_frame: list[tuple[str, ...]], branches) -> dict[str, float]:
    n = max(len(per_frame), 1)
    return {b: round(100.0 * sum(b in ch for ch in per_frame) / n, 1) for b in branches}


def format_table(r: dict) -> str:
    """The comparison as text: one row per method, fixed first, then selective."""
    lines = [f"{r['frames']} frames ({r['split']}), {r['sequences']} sequences; fusion {r['fusion']}, "
             f"gates keep top {r['k']} of {len(r['branches'])}; mAP@0.5, all classes",
             f"{'method':24s} {'mAP':>6s} {'veh.':>6s}   minus late (95 % interval)"]
    for name, row in r["methods"].items():
        d = row.get("minus_late")
        tail = "-" if d is None else (f"{d['value']:+.3f} [{d['ci95'][0]:+.3f}, {d['ci95'][1]:+.3f}] {d['verdict']}"
                                      if d["ci95"] else f"{d['value']:+.3f}")
        lines.append(f"{name:24s} {_f(row['map'])} {_f(row['map_vehicles'])}   {tail}")
    if r["gates_not_trained"]:
        lines.append("not trained on this run (hydrabench train-gate): " + ", ".join(r["gates_not_trained"]))
    return "\n".join(lines)


def _f(v) -> str:
    return f"{v:6.3f}" if v is not None else "     -"


def plot_compare(r: dict, path) -> None:
    """Each method's mAP minus late fusion with its 95 % interval, overall (fixed choices grey,
    selective blue, the oracle hatched)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from study.outputs import savefig_atomic

    rows = [(n, m["minus_late"]) for n, m in r["methods"].items() if m.get("minus_late") and m["minus_late"]["ci95"]]
    if not rows:
        raise UserError("--plot needs intervals (--bootstrap > 0)")
    fig, ax = plt.subplots(figsize=(7.5, 0.45 * len(rows) + 1.6))
    for y, (name, d) in enumerate(rows):
        lo, hi = d["ci95"]
        colour = "#888888" if not name.startswith("hydrafusion:") else "#c05a00" if name.endswith("optimal") else "#1f5fa8"
        ax.plot([lo, hi], [y, y], color=colour, lw=3, solid_capstyle="butt")
        ax.plot([d["value"]], [y], "o", color=colour, ms=7)
        ax.text(hi, y + 0.22, f" {d['verdict']}", fontsize=8, color=colour, va="center")
    ax.axvline(0, color="k", lw=0.8)
    ax.set_yticks(range(len(rows)), [n for n, _ in rows])
    ax.invert_yaxis()
    ax.set_xlabel("mAP@0.5 minus late fusion (95 % interval, whole-sequence bootstrap)")
    ax.set_title(f"{r['frames']} frames, {r['sequences']} sequences; {r['fusion']}, top {r['k']} of "
                 f"{len(r['branches'])} (grey fixed, blue gates, orange oracle)", fontsize=9)
    fig.tight_layout()
    savefig_atomic(fig, path)
    plt.close(fig)
