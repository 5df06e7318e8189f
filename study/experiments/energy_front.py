"""The mAP-energy front of the fixed configurations, with every gate placed on it (issue 36).

A gate is worth running only where it lies above what a fixed configuration gives for the same
energy or less. The fixed configurations are the methods that choose nothing per frame: each single
sensor, late fusion, all_branches and the early-fusion models (where the cost table measured them).
Their front is the Pareto set of (energy, mAP): a configuration is on it when no other one is at
least as cheap and more accurate. Each other method (the learned and knowledge gates, the oracles)
is compared with the front at its own energy, i.e. with the most accurate fixed configuration that
costs no more than it (a cheaper one can always be run instead), by the study's paired sequence
bootstrap (`results.intervals`, the same draws as every other comparison): "above the front" when
the interval of the difference excludes 0 from above, "below" from below, otherwise "not resolved".

Energy is each method's mean per-frame energy in the cost table (Table 4 analogue,
`study_eval.cost_table`: measured latency x power, a learned gate charged its stems and its own
network). A fixed configuration's energy is the same on every frame, so it has no between-sequence
spread; a gate's energy varies with its choices, and the evaluation does not store per-frame
choices, so the figure shows energy as points (stated in the report)."""

from __future__ import annotations

from pathlib import Path

from study.experiments.bounds import A_POSTERIORI, CONTEXT_ORACLE, label

FIXED_FAMILIES = ("single", "early")
FIXED_NAMES = ("late", "all_branches")


def is_fixed(name: str) -> bool:
    """A method that runs the same branches on every frame."""
    return name in FIXED_NAMES or name.split(":", 1)[0] in FIXED_FAMILIES


def _results(report: dict) -> dict:
    return report["results"] if "results" in report and "methods" not in report else report


def _difference(diffs: dict, a: str, b: str) -> list[float] | None:
    """The 95 % interval of mAP(a) - mAP(b) from the study's paired bootstrap."""
    if f"{a} - {b}" in diffs:
        return list(diffs[f"{a} - {b}"])
    if f"{b} - {a}" in diffs:
        lo, hi = diffs[f"{b} - {a}"]
        return [-hi, -lo]
    return None


def pareto(points: dict[str, tuple[float, float]]) -> list[str]:
    """The names on the front of {name: (energy, mAP)}, cheapest first: each strictly more
    accurate than every configuration at most as expensive (ties in energy: the more accurate)."""
    order = sorted(points, key=lambda n: (points[n][0], -points[n][1], n))
    front, best = [], float("-inf")
    for n in order:
        if points[n][1] > best:
            front.append(n)
            best = points[n][1]
    return front


def chord(fixed: dict, front: list[str], energy: float) -> float:
    """The mAP of time-sharing between the two front neighbours of `energy` (running the cheaper on
    some frames, the dearer on the others, so that the mean energy is `energy`): their linear
    interpolation, a point value (no interval: such a mixture is not scored). Below the cheapest
    front configuration: its mAP; above the dearest: its mAP."""
    pts = [(fixed[n]["energy"], fixed[n]["map"]) for n in front]
    if energy <= pts[0][0]:
        return pts[0][1]
    for (e0, m0), (e1, m1) in zip(pts, pts[1:], strict=False):
        if energy <= e1:
            return m0 + (m1 - m0) * (energy - e0) / (e1 - e0)
    return pts[-1][1]


def energy_front(report: dict) -> dict | None:
    """{"fixed": {name: {energy, map, ci95, on_front}}, "front": [names], "placed": {name: {energy,
    map, ci95, against, minus_front, verdict, what}}, "energy_unit"}; None without a cost table or
    overall intervals. From the evaluation's front record (`study.experiments.bounds.front_record`: every
    EcoFusion configuration among the fixed ones, energy intervals) where it has one, otherwise
    from the methods of the cost table (a report made before that record)."""
    r = _results(report)
    rec = (r.get("bounds") or {}).get("front")
    if rec:
        return _from_record(rec, r)
    costs = r.get("hydra_table4") or {}
    overall = ((r.get("intervals") or {}).get("per_context") or {}).get("all")
    if not costs or not overall:
        return None
    ci, diffs = overall.get("map", {}), overall.get("difference", {})

    def point(name: str) -> dict:
        return {"energy": costs[name]["energy"], "map": r["methods"][name]["map"], "ci95": ci.get(name)}

    named = [n for n in r["methods"] if n in costs]
    fixed = {n: point(n) for n in named if is_fixed(n)}
    if not fixed:
        return None
    front = pareto({n: (p["energy"], p["map"]) for n, p in fixed.items()})
    for n, p in fixed.items():
        p["on_front"] = n in front
    placed = {n: _placed(n, point(n), fixed, front, diffs) for n in named if n not in fixed}
    return {"fixed": fixed, "front": front, "placed": placed, "energy_unit": r.get("energy_unit", ""),
            "sequences": overall.get("sequences"),
            "configurations": "the fixed methods of the cost table (a report made before every EcoFusion configuration "
                              "was scored for the front)"}


def _from_record(rec: dict, r: dict) -> dict:
    """`energy_front` from `study.experiments.bounds.front_record`: the fixed configurations are its
    configurations (each single sensor, each EcoFusion configuration, late fusion, all branches)."""
    diffs = rec["difference"]

    def point(name: str) -> dict:
        return {"energy": rec["energy_point"][name], "energy_ci95": rec["energy_ci95"][name],
                "map": rec["map_point"][name], "ci95": rec["map"][name]}

    fixed = {n: point(n) for n in rec["configurations"]}
    front = pareto({n: (p["energy"], p["map"]) for n, p in fixed.items()})
    for n, p in fixed.items():
        p["on_front"] = n in front
    return {"fixed": fixed, "front": front, "placed": {n: _placed(n, point(n), fixed, front, diffs)
                                                       for n in rec["placed"]},
            "energy_unit": r.get("energy_unit", ""), "sequences": rec.get("sequences"),
            "configurations": "every fixed branch set: each single sensor, each EcoFusion configuration, late "
                              "fusion, all branches"}


def _placed(n: str, p: dict, fixed: dict, front: list[str], diffs: dict) -> dict:
    """Method `n` (its point `p`) against the most accurate front configuration no dearer than it."""
    cheaper = [f for f in front if fixed[f]["energy"] <= p["energy"]]
    against = cheaper[-1] if cheaper else None  # the front is sorted by energy, accuracy rising
    iv = _difference(diffs, n, against) if against else None
    verdict = ("cheaper than every fixed configuration" if against is None else
               "no interval" if iv is None else
               "above the front" if iv[0] > 0 else "below the front" if iv[1] < 0 else "not resolved")
    return {**p, "against": against, "minus_front": iv, "verdict": verdict, "what": label(n),
            "minus_chord": round(p["map"] - chord(fixed, front, p["energy"]), 4),
            "bound": n in A_POSTERIORI or n == CONTEXT_ORACLE,
            "point": None if against is None else round(p["map"] - fixed[against]["map"], 4)}


def front_sentence(front: dict) -> str:
    """Where a deployable gate is worth running (above the front, resolved), in one sentence."""
    gates = {n: p for n, p in front["placed"].items() if not p["bound"]}
    above = [n for n, p in gates.items() if p["verdict"] == "above the front"]
    below = [n for n, p in gates.items() if p["verdict"] == "below the front"]
    unresolved = [n for n, p in gates.items() if p["verdict"] not in ("above the front", "below the front")]
    parts = [f"Fixed configurations on the mAP-energy front: {', '.join(front['front'])}."]
    parts.append(("Above the front (worth running at their energy): " + ", ".join(above) + ".") if above else
                 "No gate is resolved above the front: at its energy a fixed configuration is as good or better.")
    if below:
        parts.append("Resolved below the front (a cheaper fixed configuration is better): " + ", ".join(below) + ".")
    if unresolved:
        parts.append("Not resolved against the front: " + ", ".join(unresolved) + ".")
    return " ".join(parts)


def front_figure(front: dict, path: str | Path, title: str = "") -> Path:
    """mAP@0.5 against energy: the fixed configurations (squares, the front joined as a staircase;
    branch sets off the front and not a single sensor, late or all_branches: small, grey, unnamed),
    every other method placed on it (circles: filled above the front, hollow not resolved, crossed
    below; grey: bounds that no deployable gate reaches). Bars: 95 % intervals of mAP (vertical)
    and of energy (horizontal, where the evaluation drew them)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from study.outputs import savefig_atomic
    from study.report.verdict import FAMILY_COLORS

    fig, ax = plt.subplots(figsize=(13.0, 6.0), dpi=100)
    fx = front["fixed"]
    xs = [fx[n]["energy"] for n in front["front"]]
    ys = [fx[n]["map"] for n in front["front"]]
    right = max([p["energy"] for p in (*fx.values(), *front["placed"].values())]) * 1.08
    ax.step([*xs, right], [*ys, ys[-1]], where="post", color="black", lw=1.2, alpha=0.7,
            label="front of the fixed configurations")
    for n, p in fx.items():
        named = p["on_front"] or is_fixed(n)  # the front, the singles, late, all_branches; other branch sets unnamed
        color = FAMILY_COLORS.get(n.split(":", 1)[0], "#444444") if is_fixed(n) else "#bbbbbb"
        if p["ci95"] and named:
            ax.plot([p["energy"]] * 2, p["ci95"], color=color, lw=1.6, alpha=0.8)
        ax.plot(p["energy"], p["map"], "s", ms=8 if named else 6, color=color, markeredgecolor="black",
                markeredgewidth=1.2 if p["on_front"] else 0.4)
        if named:
            ax.annotate(n, (p["energy"], p["map"]), textcoords="offset points", xytext=(6, -4), fontsize=8)
    if len(xs) > 1:
        ax.plot(xs, ys, ls="--", color="black", lw=0.8, alpha=0.5,
                label="time-sharing between front neighbours (point values)")
    from matplotlib.lines import Line2D

    handles = []
    for i, (n, p) in enumerate(sorted(front["placed"].items(), key=lambda kv: (kv[1]["energy"], -kv[1]["map"])), 1):
        color = "#999999" if p["bound"] else FAMILY_COLORS.get(n.split(":", 1)[0], "#9467bd")
        x = p["energy"] * (1 + 0.006 * (i % 3))  # a hair apart: gates at nearly the same energy
        if p["ci95"]:
            ax.plot([x] * 2, p["ci95"], color=color, lw=1.6, alpha=0.8)
        if p.get("energy_ci95"):
            ax.plot(p["energy_ci95"], [p["map"]] * 2, color=color, lw=1.6, alpha=0.8)
        marker = "X" if p["verdict"] == "below the front" else "o"
        face = color if p["verdict"] in ("above the front", "below the front") else "white"
        ax.plot(x, p["map"], marker, ms=8, color=color, markerfacecolor=face, markeredgewidth=1.6)
        ax.annotate(str(i), (x, p["map"]), textcoords="offset points", xytext=(-11 if i % 2 else 4, 7), fontsize=8,
                    fontweight="bold")
        handles.append(Line2D([], [], marker=marker, ls="", color=color, markerfacecolor=face, markeredgewidth=1.6,
                              label=f"{i} {n}: {'bound, ' if p['bound'] else ''}{p['verdict']}"))
    first = ax.legend(loc="lower right", fontsize=8)
    ax.add_artist(first)
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8,
              title="placed on the front (filled: resolved)", title_fontsize=8)
    ax.set_xlabel(f"energy per frame ({front['energy_unit'].split(':')[0] or 'J'})")
    ax.set_ylabel("mAP@0.5 (all classes), 95 % interval")
    ax.set_xlim(left=0)
    ax.grid(alpha=0.3)
    ax.set_title(title or f"mAP against energy ({front.get('sequences')} test sequences)", fontsize=10)
    fig.tight_layout()
    savefig_atomic(fig, path)
    plt.close(fig)
    return Path(path)
