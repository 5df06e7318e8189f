"""`hydrabench theory`: the command line of `study.experiments.theory` (what it measures is described there) and
its tables as text (`format_text`)."""

from __future__ import annotations

import os

from study.cli import Formatter, emit, name_arg, nonneg_int, pos_int, severity_arg, workers_int
from study.cli import cache_dir as cache_dir_arg
from study.experiments import theory
from study.numbers import interval_text, number_text

EPILOG = """\
conditions: rain, fog, snow, night or combinations such as rain+night, on --layout (default
motorway: the layout with the most traffic in view, so every condition sees the same kind of
scene) unless a condition names its own layout (city+night: street lamps and glare). Severity 0 is
clear weather on the condition's layout, measured once per layout.

Sample size and confidence: with the defaults (40 frames per cell in 4 sequences, 10 s of driving
each) a motorway cell holds ~107 objects; the lidar measures ~80 % of them, the radar ~all, the camera
~25 % in clear weather (it stops at 27 m and rejects unconfident matches), so ~85 objects are seen
by both active sensors and compared (the camera fused where it matched). Errors are heavy-tailed:
an MSE from ~85 of them has a relative standard error of 20-40 % (--json gives each one in
details.mse_se), up to 90 % where one or two gross errors decide it (compare the median and the
trimmed mean printed beside it, and the gross-error lines), so read factors, not digits; a mean NEES from ~25-300 values separates "right" (~2)
from "wrong" (tens to 10^4) but not 2 from 3. --frames 160
--sequences 16 quarters the variances (about 15 minutes on 2 cores).
The default sweep takes ~4 minutes on 2 cores (21 cells, 840 frames); every later run with the same
settings reads the cache and takes about a minute (the analysis: two gated fusions per object).

examples:
  hydrabench theory                                   (all conditions, severities 0-5, ~4 min cold)
  hydrabench theory --conditions fog --severities 0 3 5 --json
  hydrabench theory --frames 200 --sequences 10 --workers 2 --cache /data/theory-cache
"""


def format_text(result: dict) -> str:
    """Readable tables: per condition, the strategies' MSE and the sensors' nominal-R check."""
    cfg = result["config"]
    lines = [
        f"hydrabench theory: layout {cfg['layout']}, {cfg['frames']} frames per cell in {cfg['sequences']} sequences "
        f"(seed {cfg['seed']}, {cfg['profile']} profile); {result['frames']['measured']} frames measured, "
        f"{result['frames']['cached']} from the cache, {result['seconds']} s",
        "MSE [m^2] on the objects lidar and radar measured (n; each fuses its sensors that measured the object),",
        "strategies cross-fitted over two folds of sequences;",
        "NEES of full fusion with the nominal R against its 95 % bounds; sensor check: true/nominal variance",
        "(radial, lateral) and mean NEES of each sensor alone against its nominal R (2 if right), availability.",
    ]
    for cond, by_sev in result["results"].items():
        lines.append("")
        lines.append(f"{cond} (layout {result['details'][cond][next(iter(by_sev))]['layout']})")
        lines.append(f"  {'sev':>3} {'weather':<26} {'n':>4} {'camera':>8} {'lidar':>8} {'radar':>8} | "
                     f"{'full_nom':>8} {'full_true':>9} {'selective':>9} {'subset':<13} {'gated':>8} | "
                     f"{'NEES':>7} {'95% bounds':<14}")
        for sev, res in by_sev.items():
            det = result["details"][cond][sev]
            if res["mse_full_nominal"] is None:
                lines.append(f"  {sev:>3} {det['weather']:<26} {det['compared']:>4}  {det['note']}")
                continue
            single = res["mse_single"]
            subset = "/".join(sorted({"+".join(s[0] for s in sub) for sub in det["selective_subsets"]}))
            lo, hi = res["nees_bounds"]
            lines.append(
                f"  {sev:>3} {det['weather']:<26} {det['compared']:>4} {number_text(single['camera']):>8} {number_text(single['lidar']):>8} "
                f"{number_text(single['radar']):>8} | {number_text(res['mse_full_nominal']):>8} {number_text(res['mse_full_true']):>9} "
                f"{number_text(res['mse_selective']):>9} {subset:<13} {number_text(res['mse_gated']):>8} | "
                f"{number_text(res['nees_mean']):>7} {interval_text((lo, hi))}")
        lines.append(f"  {'sev':>3} {'sensor check':<26} " + "  ".join(
            f"{s:<31}" for s in ("camera", "lidar", "radar")))
        for sev in by_sev:
            det = result["details"][cond][sev]
            cells = []
            for s in ("camera", "lidar", "radar"):
                e = det["sensors"][s]
                if not e["n"]:
                    cells.append(f"{'not measured':<31}")
                    continue
                vr = e["variance_ratio"]
                cells.append(f"{number_text(vr[0]) + '/' + number_text(vr[1]):>13} NEES {number_text(e['nees_mean']):>6} {100 * e['availability']:3.0f}%")
            lines.append(f"  {sev:>3} {'':<26} " + "  ".join(f"{c:<31}" for c in cells))
        lines.extend(_robust_lines(result["details"][cond]))
        lines.extend(_gross_lines(result["details"][cond]))
    return "\n".join(lines)


ROBUST_COLUMNS = ("camera", "lidar", "radar", "full_nominal", "full_true", "selective", "gated", "gated_true")
ROBUST_FIGURES = (("mean", "mean"), ("se", "+- se"), ("median", "median"), ("trimmed", "trimmed"))


def _robust_lines(details: dict) -> list[str]:
    """Mean, its standard error, median and 10 % trimmed mean of the squared errors, per column; each
    strategy's paired difference from the better of lidar and radar alone (mean and its se)."""
    head = [f"{'camera':>8} {'lidar':>8} {'radar':>8}", f"{'full_nom':>8} {'full_true':>9} {'selective':>9} "
            f"{'gated':>8} {'gated_true':>10}"]
    lines = [f"  {'sev':>3} {'squared error':<14} {head[0]} | {head[1]}"]
    for sev, det in details.items():
        if "robust" not in det:
            continue
        rob = det["robust"]
        for i, (key, label) in enumerate(ROBUST_FIGURES):
            v = [number_text(rob[c][key]) for c in ROBUST_COLUMNS]
            lines.append(f"  {sev if i == 0 else '':>3} {label:<14} {v[0]:>8} {v[1]:>8} {v[2]:>8} | {v[3]:>8} "
                         f"{v[4]:>9} {v[5]:>9} {v[6]:>8} {v[7]:>10}")
        paired = det["paired_vs_best_single"]
        for key, label in (("mean", f"- {paired['best_single']}"), ("se", "  +- se")):
            v = [number_text(paired[c][key]) if key == "se" or paired[c][key] is None
                 else f"{paired[c][key]:+.3g}" for c in ROBUST_COLUMNS[3:]]
            lines.append(f"  {'':>3} {label:<14} {'':>8} {'':>8} {'':>8} | {v[0]:>8} {v[1]:>9} {v[2]:>9} {v[3]:>8} "
                         f"{v[4]:>10}")
    return lines


def _gross_lines(details: dict) -> list[str]:
    """Gross errors per sensor (count of measured, causes), the gate's verdicts, the fused SSE they carry."""
    lines = [f"  {'sev':>3} gross errors, NEES > {number_text(_gross_bound())} against each sensor's nominal R (its gate: 'gated') "
             "or measured R (its gate: 'gated_true'):",
             f"  {'':>3} gross/measured (causes) | what the gate did | share of full fusion's summed squared error "
             "on those objects; MSE on the other objects"]
    for sev, det in details.items():
        if "gross" not in det:
            continue
        g = det["gross"]
        for i, (kind, fused) in enumerate((("nominal", "full_nominal"), ("measured", "full_true"))):
            parts, gate = [], {}
            for s, d in g["per_sensor"][kind].items():
                causes = ", ".join(f"{c} {n}" for c, n in d["causes"].items())
                parts.append(f"{s} {d['gross']}/{d['n']}" + (f" ({causes})" if causes else ""))
                for o, n in d["gate"][kind].items():
                    gate[o] = gate.get(o, 0) + n
            verdict = ", ".join(f"{o} {n}" for o, n in gate.items()) or "-"
            share = g["sse_share"][fused]
            without = g["mse_without_gross"][kind]
            rest = ", ".join(f"{name} {number_text(without[name])}" for name in ("lidar", "radar", fused))
            lines.append(f"  {sev if i == 0 else '':>3} {kind + ' R:':<12} " + "; ".join(parts)
                         + f" | gate: {verdict} | {fused} SSE share {_pct(share)}; MSE without them: {rest}")
    return lines


def _gross_bound() -> float:
    from fusion.estimation.gross import GROSS_BOUND

    return GROSS_BOUND


def _pct(v) -> str:
    return "-" if v is None else f"{100 * v:.0f} %"



def add_parser(sub, name: str, help_text: str) -> None:
    p = sub.add_parser(name, help=help_text, description=help_text + "\n\n" + theory.__doc__.split("\n\n", 1)[1],
                       epilog=EPILOG, formatter_class=Formatter)
    p.add_argument("--conditions", nargs="+", type=name_arg, default=list(theory.TheoryConfig.conditions),
                   help="conditions (rain, fog, snow, night), combinations (rain+night), optionally on "
                        "their own layout (city+night)")
    p.add_argument("--severities", nargs="+", type=severity_arg, default=list(theory.TheoryConfig.severities),
                   help="severities 0-5 (0 = clear, shared by all conditions)")
    p.add_argument("--layout", default=theory.TheoryConfig.layout, choices=theory.LAYOUTS,
                   help="road layout of the conditions that name none")
    p.add_argument("--frames", type=pos_int, default=theory.TheoryConfig.frames, help="frames per condition and severity")
    p.add_argument("--sequences", type=pos_int, default=theory.TheoryConfig.sequences,
                   help="sequences the frames of a cell are split into (>= 2)")
    p.add_argument("--seed", type=nonneg_int, default=theory.TheoryConfig.seed, help="root random seed")
    p.add_argument("--profile", type=name_arg, default=theory.TheoryConfig.profile, help="sensor profile (cpu, paper)")
    p.add_argument("--cache", type=cache_dir_arg, default=None,
                   help="cache directory for the measurements (default: $HYDRABENCH_CACHE/theory or "
                        "~/.cache/hydrabench/theory)")
    p.add_argument("--workers", type=workers_int, default=min(2, os.cpu_count() or 1),
                   help="parallel worker processes for uncached sequences")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(run=run)


def run(args) -> int:
    from study.outputs import check_writable_dir

    config = theory.TheoryConfig(conditions=tuple(dict.fromkeys(theory.condition_name(c) for c in args.conditions)),
                          severities=tuple(dict.fromkeys(int(s) for s in args.severities)),
                          layout=args.layout, frames=args.frames, sequences=args.sequences, seed=args.seed,
                          profile=args.profile)
    cache_dir = check_writable_dir(args.cache if args.cache is not None else theory.default_cache_dir())
    result = theory.run_theory(config, cache_dir, workers=args.workers, progress=True)
    emit(result, args.json, format_text)
    return 0
