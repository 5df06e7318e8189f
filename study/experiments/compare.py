"""`hydrabench compare`: selective against fixed fusion on one dataset, with intervals.

One pass runs every branch of a trained run (or reference model) once per frame and every gate
beside it; then, in the right camera, with one late-fusion method (`--fusion`, fixed in advance):

- fixed selections: each single-sensor branch alone, `late` (the single-sensor branches fused: the
  paper's late-fusion baseline), `all_branches` (every branch, early-fusion ones included);
- selective: HydraFusion's gates (Table 2 (iv)): each frame's top-k branches by the gate's
  predicted loss, fused. `knowledge` reads the frame's context label; `deep` and `attention` read
  the stem features (trained with `hydrabench train-gate`); `optimal` reads the frame's own
  a-posteriori branch losses (it uses the frame's own ground truth, so it is not achievable; and
  it is no bound either: BEV and camera branch losses are not comparable, so its top k is not the
  best k, `study.experiments.bounds.OPTIMAL_APPENDIX`).

Every method is scored on the same frames (VOC mAP@0.5, all classes, the run's protocol) and
compared with `late` by the paired sequence bootstrap (`study.engine.scoring.context_bootstrap`): whole
sequences drawn with replacement, every method scored on each draw. A difference whose 95 %
interval holds 0 is "not resolved". Nothing is chosen here: k and the fusion method are inputs.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sim.errors import UserError
from sim.progress import progress as progress_bar
from study.engine.predictions import GATES, usable_gates
from study.numbers import number_text, rounded, rounded_interval


def gate_names(value) -> tuple[str, ...]:
    """`--gates` (a name list or a comma-separated string) checked against GATES (UserError naming the
    first unknown one)."""
    gates = tuple(value if not isinstance(value, str) else value.split(","))
    bad = [g for g in gates if g not in GATES]
    if bad:
        raise UserError(f"--gates: unknown gate {bad[0]!r} (choose from: {', '.join(GATES)})")
    return gates


def verdict(iv) -> str:
    """'above' / 'below' when the interval of a difference excludes 0, else 'not resolved'."""
    if iv is None:
        return "not resolved"
    return "above" if iv[0] > 0 else "below" if iv[1] < 0 else "not resolved"


def _selections(gp, singles: list, trained: list, k: int) -> tuple[dict, dict]:
    """The compared methods of the predictions `gp`: ({name: what it is}, {name: branches per frame}):
    each single sensor, late fusion, all branches (when early-fusion branches exist), each gate's top k."""
    n, branches = len(gp.per_frame), gp.branches
    kinds = {f"single:{b}": "single sensor" for b in singles}
    selections = {f"single:{b}": [(b,)] * n for b in singles}
    kinds["late"], selections["late"] = "late fusion of the single-sensor branches", [tuple(singles)] * n
    if len(branches) > len(singles):
        kinds["all_branches"] = "every branch (early-fusion ones too)"
        selections["all_branches"] = [tuple(branches)] * n
    for g in trained:
        name = f"hydrafusion:{g}"
        kinds[name] = (f"{g} gate, top {k} of {len(branches)} per frame"
                       + (" (a-posteriori: reads each frame's own ground-truth losses, not achievable)"
                          if g == "optimal" else ""))
        selections[name] = gp.selection(g, k)
    return kinds, selections


def compare(run_dir, data, *, gates=GATES, k: int = 2, fusion: str = "soft-nms", split: str = "auto",
            resamples: int = 500, batch_size: int = 4, setup=None, progress: bool = True,
            twins: bool = False, coverage_deals: int = 0, coverage_designs=("sequence",),
            interval: str = "sequence", need_intervals: str | None = None, predictions=None) -> dict:
    """The comparison of the module docstring -> a JSON-able dict: per method its kind, mAP, vehicle
    mAP, mAP per context, and mAP minus late fusion with its 95 % interval and verdict, overall and
    per context. The network runs once (`study.engine.predictions.predict`, whose result is cached under the
    run and reused while model, data and code are unchanged); `predictions`: a predictions directory
    of this run on `data` to score instead, with no network. `twins`: also each method's robustness
    on the clear-weather twins (`robustness`). `coverage_deals`: also check the intervals on this test
    set (`coverage`), by each bootstrap design in `coverage_designs` (`fusion.intervals.DESIGNS`);
    `interval`: the design of the reported intervals. `need_intervals`: what needs the intervals (an
    option's name, "--plot"): refused before the networks run when there can be none (no bootstrap,
    or no ground-truth box to score on the frames)."""
    from sensors.dataset import DatasetReader
    from study.engine.gate_tables import parse_k, selection_rates
    from study.engine.scoring import (
        context_bootstrap,
        difference_interval,
        fuse_selection,
        fusion_method,
        score,
    )

    run_dir, data = Path(run_dir), Path(data)
    method = fusion_method(fusion)
    if resamples < 0:
        raise UserError(f"--bootstrap must be >= 0, got {resamples}")
    if need_intervals and not resamples:
        raise UserError(f"{need_intervals} needs intervals: give --bootstrap N > 0")
    reader = DatasetReader(data)
    gp = _predictions(run_dir, data, reader, predictions, gates, split, batch_size, setup, progress, need_intervals,
                      twins)
    protocol = gp.manifest["identity"]["protocol"]
    used_split = gp.manifest["identity"]["split"]
    indices = [int(m["dataset_index"]) for m, _ in gp.per_frame]
    if need_intervals:
        _need_ground_truth(need_intervals, reader, indices, protocol, used_split, data)
    branches = gp.branches
    k = parse_k(k, len(branches), "k")
    k = len(branches) if k == "all" else k
    sensors = gp.branch_sensors
    singles = [b for b in branches if len(sensors[b]) == 1]
    if not singles:
        raise UserError(f"{run_dir}: no single-sensor branch, so no late-fusion baseline to compare with")
    trained = [g for g in gates if g in gp.gates]
    skipped = [g for g in gates if g not in trained]
    frames = gp.branch_frames
    kinds, selections = _selections(gp, singles, trained, k)
    memo: dict = {}  # one method: each (frame, branch set) fused once, each branch mapped once
    sources = {name: fuse_selection(gp.per_frame, selection, frames, method, memo=memo)
               for name, selection in selections.items()}
    scores = {n: score(s, reader, "camera_right", protocol=protocol) for n, s in sources.items()}
    boot = (context_bootstrap(sources, reader, "camera_right", protocol=protocol, resamples=resamples,
                              classes="all", desc="bootstrap the methods", design=interval) if resamples else None)
    contexts = sorted({m["context"] for m, _ in gp.per_frame})
    methods = {}
    for name in selections:
        sc = scores[name]
        row = {"kind": kinds[name], "map": sc["map"], "map_vehicles": sc["map_vehicles"],
               "map_per_context": sc["map_per_context"]}
        if boot and name != "late":
            iv = difference_interval(boot["per_context"]["all"], name, "late")
            row["minus_late"] = {"value": map_difference(sc["map"], scores["late"]["map"]), "ci95": iv, "verdict": verdict(iv)}
            row["minus_late_per_context"] = {
                c: {"ci95": (iv_c := difference_interval(boot["per_context"][c], name, "late")),
                    "verdict": verdict(iv_c)} for c in contexts if c in boot["per_context"]}
        if boot and name.startswith("hydrafusion:") and "all_branches" in scores:
            # what choosing adds over running and fusing every branch (HydraFusion's "all" column)
            iv = difference_interval(boot["per_context"]["all"], name, "all_branches")
            row["minus_all_branches"] = {"value": map_difference(sc["map"], scores["all_branches"]["map"]), "ci95": iv,
                                         "verdict": verdict(iv)}
        if boot:
            row["ci95"] = boot["per_context"]["all"]["map"][name]
        methods[name] = row
    rates = {g: selection_rates(selections[f"hydrafusion:{g}"], branches) for g in trained}
    best = _best_of(gp.manifest.get("best_gate"), trained)
    rob = None
    if twins:
        from study.engine.gate_tables import setup_run

        model = setup_run(run_dir, data, "all", None, "latest", setup)[0]
        rob = robustness(run_dir, data, model, reader, gp, selections, sources, [g for g in trained if g != "optimal"],
                         k, method, protocol, indices, resamples, batch_size, progress)
    cov = (coverage(sources, reader, protocol, coverage_deals, resamples, progress, coverage_designs)
           if coverage_deals else None)
    return {
        "run": str(run_dir), "data": str(data), "split": used_split, "frames": len(gp.per_frame),
        "sequences": boot["per_context"]["all"]["sequences"] if boot else None, "contexts": contexts,
        "fusion": fusion, "k": k, "protocol": protocol, "branches": branches, "gates": trained,
        "gates_not_trained": skipped, "methods": methods, "selection_rate_pct": rates, "best_gate": best,
        "bootstrap": {"resamples": resamples, "unit": "sequence", "design": interval} if boot else None,
        "metric": "VOC all-point AP at IoU 0.5, every class with ground truth, right camera",
        "predictions": str(gp.root),
        **({"robustness": rob} if rob is not None else {}),
        **({"coverage": cov} if cov is not None else {}),
    }


def _predictions(run_dir, data, reader, predictions, gates, split, batch_size, setup, progress, need_intervals,
                 twins=False):
    """The predictions `compare` scores: `predictions` loaded and checked against the run and the data,
    or made by one pass (`study.engine.predictions.predict`; refused first when `need_intervals` and no
    frame holds a box to find)."""
    from study.engine.predictions import load, predict

    if predictions is None:
        if need_intervals:  # before the network runs: the frames and protocol from the run's config alone
            import json

            from study.engine.scoring import frames_for
            from study.engine.train import run_protocol

            cfg = json.loads((run_dir / "config.json").read_text())
            indices, used_split = frames_for(cfg, data, split)
            _need_ground_truth(need_intervals, reader, indices, run_protocol(cfg), used_split, data)
        return predict(run_dir, data, gates=gates, split=split, batch_size=batch_size, setup=setup, progress=progress)
    gp = load(predictions)
    check_predictions(gp, run_dir, data)
    if twins and gp.manifest.get("pem"):
        raise UserError("--twins runs the network on the clear-weather twins: not with a perception error model's "
                        "--predictions (draw the PEM on the twins' dataset and compare that instead)")
    missing = [g for g in usable_gates(run_dir, gates) if g not in gp.gates]
    if missing and gp.manifest.get("pem"):
        raise UserError(f"--predictions {predictions}: drawn by a perception error model, which has no stem features "
                        f"or losses, so no {missing[0]!r} gate: give --gates knowledge")
    if missing:
        raise UserError(f"--predictions {predictions}: holds no outputs of gate {missing[0]!r} (it has: "
                        f"{', '.join(gp.gates) or 'none'}; hydrabench predict --gates names them)")
    if split != "auto" and split != gp.manifest["identity"]["split"]:
        raise UserError(f"--split {split}: the predictions are of the {gp.manifest['identity']['split']!r} split")
    return gp


def _need_ground_truth(need_intervals: str, reader, indices, protocol, used_split: str, data) -> None:
    """UserError when no interval can exist on the frames `indices` (no box to find)."""
    if not _has_ground_truth(reader, indices, protocol):
        raise UserError(f"{need_intervals} needs intervals, and none can exist: the {len(indices)} frames of the "
                        f"{used_split} split of {data} hold no box to find under protocol {protocol!r} (every mAP is undefined)")


def _has_ground_truth(reader, indices, protocol) -> bool:
    """Whether any of the frames `indices` holds a box to find (not difficult) in the right camera
    under `protocol`: without one every mAP, and so every interval, is undefined."""
    from study.engine.scoring import frame_ground_truth

    return any((~frame_ground_truth(reader, {**reader.meta(i), "dataset_index": i}, "camera_right", None,
                                    protocol)["difficult"]).any() for i in indices)


def coverage(sources: dict, reader, protocol, deals: int, resamples: int, progress: bool = True,
             designs=("sequence",)) -> dict:
    """Do the intervals of minus late fusion hold on this test set? The test set dealt `deals` times
    into as many disjoint sets as it allows (`study.experiments.bounds.coverage_sets`), each set's interval
    against the pooled rest's estimate (`study.experiments.interval_coverage.coverage_over_deals`, once per bootstrap
    design in `designs`), for every method but the single sensors; {"skipped": why} when the test set is too small."""
    from study.experiments.bounds import StudyMatches, coverage_sets
    from study.experiments.interval_coverage import coverage_over_deals

    sm = StudyMatches.of(sources, {}, {}, reader, protocol)
    n, why = coverage_sets(sm.contexts, sm.sequences)
    if why:
        return {"skipped": why, "sets": n}
    pairs = [(m, "late") for m in sources if m != "late" and not m.startswith("single:")]
    return coverage_over_deals(sm.matches, sm.contexts, sm.sequences, pairs, n_sets=n, deals=deals,
                               resamples=max(1, resamples), designs=designs, progress=progress)


def robustness(run_dir, data, model, reader, gp, selections, sources, twin_gates, k, method, protocol, indices,
               resamples, batch_size, progress) -> dict:
    """Each method on the clear-weather twins of the degraded frames: per condition and severity,
    vehicle mAP degraded and clear and their ratio RA (MultiCorrupt's relative accuracy, paired:
    the twins of exactly those frames, `fusion.robustness.twin_relative_accuracy`, whole sequences
    drawn), the severity's measured physical quantity (median over its frames), and per method mRA,
    mRR and mCE against late fusion (Robo3D; `fusion.robustness`). A gate chooses afresh on each
    twin from the twin's own sensors (the knowledge gate reads the context label, which the twin
    keeps). The optimal gate is left out: its losses are not computed on twins."""
    from fusion import robustness as R
    from sensors.dataset import DatasetReader
    from sim.actors import CLASSES
    from study.engine.gate_tables import gate_pass
    from study.engine.scoring import VEHICLES, fuse_selection, ground_truth, image_matches

    if not reader.manifest["config"].get("twins"):
        raise UserError(f"--twins: {data} has no clear-weather twins (generate it with --twins)")
    clear_reader = DatasetReader(data, clear=True)
    gc = gate_pass(run_dir, data, model, twin_gates, indices, "latest", batch_size, progress, clear=True)
    frames = model.branch_frames
    names = [n for n in selections if not n.startswith("hydrafusion:") or n.split(":", 1)[1] in twin_gates]
    clear_selections = {n: (selections[n] if not n.startswith("hydrafusion:") else gc.selection(n.split(":", 1)[1], k))
                        for n in names}
    metas = [m for m, _ in gp.per_frame]
    groups: dict = {}
    for i, m in enumerate(metas):
        conds = list(m.get("conditions") or [])
        if len(conds) == 1 and int(m.get("severity", 0)) > 0:
            groups.setdefault((conds[0], int(m["severity"])), []).append(i)
    if not groups:
        raise UserError(f"--twins: {data} has no degraded frames of a single condition (fog, rain, snow, night)")
    vehicles = [CLASSES.index(c) + 1 for c in VEHICLES]
    keys = [int(m["dataset_index"]) for m in metas]
    gts_d = [ground_truth(reader.labels(kk), "camera_right", None, m, protocol) for kk, m in zip(keys, metas)]
    gts_c = [ground_truth(clear_reader.labels(kk), "camera_right", None, m, protocol) for kk, m in zip(keys, metas)]
    out_methods: dict = {}
    bar = progress_bar(total=len(names) * len(groups) * resamples, desc="bootstrap the twins", unit="draw",
                       enabled=progress)
    for n in names:
        clr = fuse_selection(gc.per_frame, clear_selections[n], frames, method)
        md, mc = image_matches(sources[n], keys, gts_d, vehicles), image_matches(clr, keys, gts_c, vehicles)
        per = {}
        for (cond, sev), idx in sorted(groups.items()):
            t = R.twin_relative_accuracy(lambda items, idx=idx, md=md: md.mean_ap([idx[i] for i in items]),
                                         lambda items, idx=idx, mc=mc: mc.mean_ap([idx[i] for i in items]),
                                         [metas[i]["sequence_id"] for i in idx], resamples=resamples,
                                         on_draw=lambda: bar.update(1))
            per.setdefault(cond, {})[str(sev)] = {
                "degraded": rounded(t.degraded, 6), "clear": rounded(t.clear, 6), "ra": rounded(t.ra),
                "ra_ci95": rounded_interval(t.interval), "sequences": t.sequences, "frames": t.frames}
        out_methods[n] = {"per_condition": per}
    bar.close()
    def scores(row, key):  # {condition: {severity: score}}, as fusion.robustness takes them
        return {c: {int(s): v[key] for s, v in per.items()} for c, per in row["per_condition"].items()}

    base = scores(out_methods["late"], "degraded")
    for row in out_methods.values():
        deg, clr = scores(row, "degraded"), scores(row, "clear")
        ra = R.relative_accuracies(deg, clr)
        row["mRA"] = rounded(R.mean_relative_accuracy(ra))
        row["mRR"] = rounded(R.mean_resilience_rate(deg, clr))
        row["mCE_vs_late"] = rounded(R.mean_corruption_error(deg, base))
    physical = {}
    for (cond, sev), idx in sorted(groups.items()):
        q = R.severity_quantity(cond)
        vals = [float(metas[i]["weather"][q]) for i in idx if q in metas[i].get("weather", {})]
        physical.setdefault(cond, {"quantity": q, "unit": R.severity_value(cond, 1)[1], "per_severity": {}})
        physical[cond]["per_severity"][str(sev)] = rounded(float(np.median(vals)), 3) if vals else None
    return {"methods": out_methods, "physical": physical, "gates": list(twin_gates),
            "metric": "vehicle mAP@0.5 (car, van, truck, bus), right camera; RA = degraded / clear twins of the same "
                      "frames; mRA (MultiCorrupt), mRR and mCE against late fusion (Robo3D)",
            "resamples": resamples, "unit": "sequence"}




def check_predictions(pred, run_dir, data) -> None:
    """UserError unless `pred` are predictions of the run's checkpoint on exactly `data`'s contents
    (scoring them against another dataset's labels would be silently wrong)."""
    from study.engine.gate_data import cached_sha256, checkpoint_path, dataset_sha256

    ident = pred.manifest["identity"]
    if ident.get("checkpoint_sha256") != cached_sha256(checkpoint_path(Path(run_dir))):
        raise UserError(f"--predictions {pred.root}: made by another model than {run_dir} (checkpoint SHA-256 differs)")
    if ident.get("dataset_sha256") != dataset_sha256(data):
        raise UserError(f"--predictions {pred.root}: made on another dataset than {data} (contents differ)")


def _best_of(best: dict | None, gates) -> dict | None:
    """`best_gate`'s record restricted to `gates`."""
    vals = {g: v for g, v in ((best or {}).get("validation_regret") or {}).items() if g in gates}
    if not vals:
        return None
    return {**best, "name": min(vals, key=vals.get), "validation_regret": vals}


def map_difference(a, b):
    """a - b of two stored mAPs, rounded as stored; None when either is missing."""
    return None if a is None or b is None else round(a - b, 4)



def format_table(r: dict) -> str:
    """The comparison as text: one row per method, fixed first, then selective."""
    lines = [f"{r['frames']} frames ({r['split']}), {r['sequences']} sequences; fusion {r['fusion']}, "
             f"gates keep top {r['k']} of {len(r['branches'])}; mAP@0.5, all classes",
             f"{'method':24s} {'mAP':>6s} {'veh.':>6s}   {'minus late (95 % interval)':40s} minus all_branches"]
    for name, row in r["methods"].items():
        cells = []
        for key in ("minus_late", "minus_all_branches"):
            d = row.get(key)
            cells.append("-" if d is None else (f"{d['value']:+.3f} [{d['ci95'][0]:+.3f}, {d['ci95'][1]:+.3f}] "
                                                f"{d['verdict']}" if d["ci95"] else f"{d['value']:+.3f}"))
        lines.append(f"{name:24s} {number_text(row['map']):>6} {number_text(row['map_vehicles']):>6}   {cells[0]:40s} "
                     f"{cells[1] if name.startswith('hydrafusion:') else ''}".rstrip())
    if r["gates_not_trained"]:
        lines.append("not trained on this run (hydrabench train-gate): " + ", ".join(r["gates_not_trained"]))
    if "robustness" in r:
        lines.append(format_robustness(r))
    cov = r.get("coverage")
    if cov and "skipped" in cov:
        lines.append(f"interval coverage: skipped ({cov['skipped']})")
    elif cov:
        first = next(iter(next(iter(cov["designs"].values()))["pairs"].values()))
        lines.append(f"interval coverage: the test set dealt {cov['deals']} times into {cov['sets']} disjoint sets; each "
                     f"set's 95 % interval against the rest's estimate (exact intervals: about "
                     f"{first['expected_if_exact']:.3f})")
        for design, rec in cov["designs"].items():
            lines.append(f"  bootstrap: {design}")
            for name, v in rec["pairs"].items():
                lines.append(f"    {name:34s} covered {v['covered']}/{v['sets']} ({v['coverage']:.3f}), between-set "
                             f"spread / bootstrap se {number_text(v['spread_over_se_mean'])}, mean width "
                             f"{number_text(v['mean_width'])}")
    return "\n".join(lines)



def plot_compare(r: dict, path) -> None:
    """Each method's mAP minus late fusion with its 95 % interval, overall (fixed selections grey,
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


COLOURS = {"single:radar": "#d62728", "single:camera_right": "#2ca02c", "single:lidar": "#9467bd", "late": "#000000",
           "all_branches": "#7f7f7f"}
GATE_COLOURS = ("#1f77b4", "#17becf", "#ff7f0e", "#8c564b")


def plot_robustness(r: dict, path) -> None:
    """RA (degraded / clear twins, vehicle mAP) against each condition's physical severity, with 95 %
    intervals: single sensors, late fusion and the gates, one panel per condition."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, NullFormatter

    from study.outputs import savefig_atomic

    rob = r["robustness"]
    conds = sorted(rob["physical"])
    best = (r.get("best_gate") or {}).get("name")
    shown = [n for n in rob["methods"] if n.startswith("single:") or n == "late" or n == f"hydrafusion:{best}"]
    top = 2.0
    fig, axes = plt.subplots(1, len(conds), figsize=(4.2 * len(conds), 3.8), squeeze=False)
    gi = 0
    colours = {}
    for n in shown:
        if n in COLOURS:
            colours[n] = COLOURS[n]
        else:
            colours[n], gi = GATE_COLOURS[gi % len(GATE_COLOURS)], gi + 1
    for ax, cond in zip(axes[0], conds):
        phys = rob["physical"][cond]
        sevs = sorted(phys["per_severity"], key=int)
        xs = [phys["per_severity"][s] for s in sevs]
        log = all(x and x > 0 for x in xs)  # every quantity spans decades across the five levels
        for j, n in enumerate(shown):
            per = rob["methods"][n]["per_condition"].get(cond, {})
            spread = 1.04 ** (j - len(shown) / 2) if log else 1 + 0.02 * (j - len(shown) / 2)
            pts = [(x * spread, per[s]) for x, s in zip(xs, sevs) if s in per and per[s]["ra"] is not None and x]
            if not pts:
                continue
            x, v = zip(*pts)
            ys = [p["ra"] for p in v]
            lo = [p["ra"] - p["ra_ci95"][0] if p["ra_ci95"] else 0 for p in v]
            hi = [p["ra_ci95"][1] - p["ra"] if p["ra_ci95"] else 0 for p in v]
            ax.errorbar(x, ys, yerr=[lo, hi], color=colours[n], marker="o", ms=4,
                        lw=2 if n == "late" or n.startswith("hydrafusion:") else 1, capsize=2, label=n)
            for xx, y in zip(x, ys):  # a ratio above the axis: its value at the top edge
                if y > top:
                    ax.annotate(f"{y:.1f}", (xx, top), fontsize=6, color=colours[n], ha="center", va="top")
        ax.set_ylim(0, top)
        if log:
            ax.set_xscale("log")
        ax.set_xticks([x for x in xs if x])  # one tick per severity, at its measured value
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:.3g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.tick_params(axis="x", labelsize=7)
        if phys["unit"] in ("m", "lux"):
            ax.invert_xaxis()  # harsher to the right: lower visibility, less light
        ax.axhline(1, color="k", lw=0.6, ls=":")
        seqs = min((rob["methods"]["late"]["per_condition"].get(cond, {}).get(s, {}).get("sequences") or 0) for s in sevs)
        ax.set_title(f"{cond} (at least {seqs} sequences per severity)", fontsize=9)
        ax.set_xlabel(f"{phys['quantity']} [{phys['unit']}] (median of the frames)", fontsize=8)
        ax.set_ylabel("RA = vehicle mAP degraded / clear twin")
    axes[0][0].legend(fontsize=7, loc="lower left")
    fig.suptitle(f"Relative accuracy against physical severity, 95 % intervals from whole-sequence draws ({r['frames']} "
                 f"frames; the gate keeps top {r['k']}; gate: the lowest validation regret; axis clipped at {top:g})",
                 fontsize=10)
    fig.tight_layout()
    savefig_atomic(fig, path)
    plt.close(fig)


def format_robustness(r: dict) -> str:
    """mRA, mRR and mCE (against late fusion) of each method, and RA per condition and severity."""
    rob = r["robustness"]
    lines = ["robustness on the clear-weather twins (vehicle mAP): " + rob["metric"],
             f"{'method':24s} {'mRA':>6s} {'mRR':>6s} {'mCE':>6s}"]
    for n, row in rob["methods"].items():
        lines.append(f"{n:24s} {number_text(row['mRA']):>6} {number_text(row['mRR']):>6} {number_text(row['mCE_vs_late']):>6}")
    for cond, phys in sorted(rob["physical"].items()):
        sevs = sorted(phys["per_severity"], key=int)
        lines.append(f"  {cond}: RA [95 % interval] at " + ", ".join(
            f"{phys['per_severity'][s]:g} {phys['unit']}" for s in sevs if phys["per_severity"][s] is not None))
        for n, row in rob["methods"].items():
            per = row["per_condition"].get(cond, {})
            lines.append(f"    {n:22s} " + "  ".join(
                (f"{per[s]['ra']:.2f} [{per[s]['ra_ci95'][0]:.2f}, {per[s]['ra_ci95'][1]:.2f}]"
                 if s in per and per[s]["ra"] is not None and per[s]["ra_ci95"] else "  -  ") for s in sevs))
    return "\n".join(lines)
