"""What a study resolves, in words and one figure, generated from its bootstrap intervals.

A study's report JSON (`hydrabench study ... --out DIR` writes DIR/report.json) holds, when
`evaluate.bootstrap` > 0, a 95 % interval of every paired difference of mAP@0.5 (all classes, right
camera) between two methods, overall and per context (`results.intervals`, written by
`study.engine.scoring.context_bootstrap`). An order is *resolved* when its interval excludes 0; an interval
that holds 0 (its bounds included) is *not resolved*: never a win, whatever the point estimates say.

- `orders(report)`: every method against late fusion, late fusion against its best single sensor,
  and every two single sensors, per group ("all", then each context), as `Order` records.
- `answer_sentences(report)`: the answer in at most four sentences (what the report opens with).
- `verdict_sentences(report)`: the answer, then those orders in a fixed wording; the same
  report gives the same sentences, byte for byte.
- `verdict_figure(report, path)`: each method's mAP minus late fusion's per context, with the
  interval, one panel per group, methods sorted by the overall difference.

Wiring: both take the report JSON dict or its "results" part (what `study.report.build.build` receives).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from math import comb, floor
from pathlib import Path

from fusion.intervals import CORRECTIONS
from study.engine.scoring import difference_interval
from study.experiments.bounds import CONTEXT_ORACLE, OPTIMISTIC, label
from study.numbers import interval_text

LATE = "late"
ORACLES = ("hydrafusion:optimal", "ecofusion:loss_based", "hydrafusion:knowledge_informed",
           "ecofusion:knowledge_informed", CONTEXT_ORACLE)
"""Methods that choose with what a car cannot know (the ground truth: the k lowest a-posteriori branch
losses, the configuration of lowest loss; the simulator's severity and lens cover; the best constant
per context chosen on the test frames): bounds on what a gate could reach, not methods a car can run,
so a sentence never counts them as a win. A report with bounds (`study.experiments.bounds`) names each for what it
is (`study.experiments.bounds.label`); an older one names them "(oracle)"."""
ALPHA = 0.05
"""A per-context order is resolved only when its adjusted p-value (`CORRECTION`) is below this (and its
interval excludes 0)."""
CORRECTION = "holm"
"""How the per-context orders' p-values are adjusted (`fusion.intervals.CORRECTIONS`): Holm's
family-wise step-down over ONE family, every per-context order the verdict prints (every pair of its
table in every context). A family per pair would let a method that scores a context's frames exactly as
another (the physical gate runs all branches on every motorway frame) be resolved where its twin is not,
only because the two pairs' other contexts differ; one family gives equal p-values equal adjusted ones."""
CORRECTION_NAMES = {"holm": "Holm-corrected", "bh": "Benjamini-Hochberg-corrected", "none": "uncorrected"}
FEW_SEQUENCES = 8
"""Below this many test sequences a group's intervals are flagged: n sequences drawn with
replacement give only comb(2n - 1, n) distinct draws (10 for n = 3, 6435 for n = 8), so a
percentile interval from them is coarse and too narrow. (Issue 27 asks for >= 8 per context.)"""


@dataclass(frozen=True)
class Order:
    """One paired difference `a` minus `b` of mAP@0.5 in one group.

    group: "all" or a context name. interval: its 95 % bootstrap interval [lo, hi] (mAP points,
    fraction in [-1, 1]); None when the report has none. sequences: the group's test sequences.
    """

    group: str
    a: str
    b: str
    interval: tuple[float, float] | None
    sequences: int
    p: float | None = None
    p_adjusted: float | None = None
    """The bootstrap p-value of the difference and, per context, its adjustment (`CORRECTION`) over the
    family of all per-context orders (None: the report stores no p-values, or the group is "all")."""

    @property
    def resolved(self) -> bool:
        """The interval excludes 0 (both bounds on one side of it, neither equal to it) and, where the
        order was corrected, the adjusted p-value is below `ALPHA`."""
        excludes = self.interval is not None and (self.interval[0] > 0 or self.interval[1] < 0)
        return excludes and (self.p_adjusted is None or self.p_adjusted < ALPHA)

    @property
    def sign(self) -> int:
        """+1: `a` resolved above `b`; -1: resolved below; 0: not resolved."""
        return 0 if not self.resolved else (1 if self.interval[0] > 0 else -1)


def _results(report: dict) -> dict:
    return report["results"] if "results" in report and "methods" not in report else report


def groups(report: dict) -> list[str]:
    """"all", then the contexts in the dataset's order, those the bootstrap scored."""
    r = _results(report)
    per = (r.get("intervals") or {}).get("per_context") or {}
    return [g for g in ["all", *r["dataset"]["contexts"]] if g in per]


def _point(r: dict, name: str, group: str) -> float | None:
    m = r["methods"][name]
    return m["map"] if group == "all" else m["map_per_context"].get(group)


def singles(report: dict) -> list[str]:
    r = _results(report)
    return [f"single:{b}" for b in r.get("singles", []) if f"single:{b}" in r["methods"]]


def best_single(report: dict, group: str) -> str | None:
    """The single sensor chosen on the validation frames for the group (`results.best_single`,
    `study.experiments.bounds.best_single_on_validation`); in a report without that choice, the single sensor
    with the highest point mAP in the group (the first in the report's order on a tie); None without
    single sensors or scores."""
    r = _results(report)
    if group in (r.get("best_single") or {}):
        return r["best_single"][group]
    scored = [(s, _point(r, s, group)) for s in singles(report)]
    scored = [(s, v) for s, v in scored if v is not None]
    return max(scored, key=lambda sv: sv[1])[0] if scored else None


def orders(report: dict, correction: str = CORRECTION) -> list[Order]:
    """Per group: every method minus late fusion (report order), late fusion minus its best single
    sensor, and every two single sensors (report order), the per-context ones adjusted together
    (`correct_per_context`). Empty without intervals."""
    return correct_per_context(raw_orders(report), correction)


def raw_orders(report: dict) -> list[Order]:
    """`orders` before any correction (`p_adjusted` None everywhere)."""
    r = _results(report)
    per = (r.get("intervals") or {}).get("per_context") or {}
    out = []
    for g in groups(report):
        pg, n = per[g], per[g]["sequences"]

        def order(a, b, g=g, pg=pg, n=n):
            iv = difference_interval(pg, a, b)
            p = pg.get("p_value", {})
            p = p.get(f"{a} - {b}", p.get(f"{b} - {a}"))
            return Order(g, a, b, None if iv is None else (float(iv[0]), float(iv[1])), n, p)

        if LATE in r["methods"]:
            out += [order(m, LATE) for m in r["methods"] if m != LATE]
            best = best_single(report, g)
            if best:
                out.append(order(LATE, best))
        ss = singles(report)
        out += [order(a, b) for i, a in enumerate(ss) for b in ss[i + 1:]]
    return out


def correct_per_context(os_: list[Order], correction: str = CORRECTION) -> list[Order]:
    """Each per-context order with its p-value adjusted by `correction` (a key of
    `fusion.intervals.CORRECTIONS`) over one family: every per-context order that has a p-value, all
    pairs in all contexts together. The "all" group and orders without a p-value are left as they are.
    Equal p-values get equal adjusted ones (Holm's running maximum, BH's running minimum)."""
    if correction not in CORRECTIONS:
        raise ValueError(f"correction must be one of {sorted(CORRECTIONS)}, got {correction!r}")
    idx = [i for i, o in enumerate(os_) if o.group != "all" and o.p is not None]
    out = list(os_)
    for i, p in zip(idx, CORRECTIONS[correction]([os_[i].p for i in idx])):
        out[i] = replace(os_[i], p_adjusted=float(p))
    return out


def family_size(report: dict) -> int | None:
    """How many per-context orders the correction adjusts together (those with a p-value), None when the
    report stores no p-values."""
    return sum(1 for o in raw_orders(report) if o.group != "all" and o.p is not None) or None


def family_sentence(report: dict) -> str:
    """What "resolved" means per context: the correction, its family and, where the draws are too few
    for any order to pass it, how many it would take. Empty when the report stores no p-values."""
    m = family_size(report)
    if not m:
        return ""
    text = (f"Per context, an order is resolved only if its interval excludes 0 and its p-value, {CORRECTION_NAMES[CORRECTION]} "
            f"together with every per-context order of this verdict ({m}: every pair in every context, one family), "
            f"is below {ALPHA:g}.")
    intervals = _results(report)["intervals"]
    if intervals.get("per_context_interval"):  # jackknife-t per context: p-values from t, no floor set by draws
        return text + f" Per-context intervals and p-values: {intervals['per_context_interval']}."
    b = intervals["resamples"]
    p_min = 2.0 / (b + 1)  # fusion.intervals.bootstrap_p_value's smallest value
    if CORRECTION == "holm" and p_min * m >= ALPHA:
        text += (f" With {b} draws the smallest p-value a difference can have is {p_min:.4f}, so over {m} orders "
                 f"this correction resolves none; it would take at least {floor(2 * m / ALPHA)} draws.")
    return text



def _where(group: str, n: int) -> str:
    return f"Overall ({n} test sequences)" if group == "all" else f"In {group} ({n} test sequences)"


def namer(report: dict):
    """How the report names a method: bounds labelled for what they are (`study.experiments.bounds.label`) in a
    report that records them, "(oracle)" after each of `ORACLES` in an older one."""
    if "bounds" in _results(report):
        return label
    return lambda m: f"{m} (oracle)" if m in ORACLES else m


def _listing(os_: list[Order], name) -> str:
    return "; ".join(f"{name(o.a)} {interval_text(o.interval, signed=True)}" for o in os_)


def _names(ms, name) -> str:
    ms = list(ms)
    return ", ".join(name(m) for m in ms[:-1]) + (" and " if len(ms) > 1 else "") + name(ms[-1]) if ms else ""


def answer_sentences(report: dict) -> list[str]:
    """The study's answer in at most four sentences (what the report opens with): late fusion against
    the single sensors overall; whether any method that runs without ground truth is resolved above
    late fusion overall, and in which contexts; late fusion against its best single sensor per
    context. Empty without intervals or late fusion."""
    r = _results(report)
    gs = groups(report)
    if not gs or LATE not in r["methods"]:
        return []
    os_ = orders(report)
    ss = singles(report)
    name = namer(report)
    out = []
    if "all" in gs:
        s_vs = [o for o in os_ if o.group == "all" and o.b == LATE and o.a in ss]
        not_below = [o.a for o in s_vs if o.sign >= 0]
        if s_vs:
            out.append("Overall, late fusion beats every single sensor." if not not_below else
                       f"Overall, late fusion does not beat every single sensor: {_names(not_below, name)} "
                       f"{'is' if len(not_below) == 1 else 'are'} not resolved below it.")
        others = [o for o in os_ if o.group == "all" and o.b == LATE and o.a not in ss]
        up = [o.a for o in others if o.sign > 0 and o.a not in ORACLES]
        up_oracle = [o.a for o in others if o.sign > 0 and o.a in ORACLES]
        text = (f"Overall, {_names(up, name)} {'is' if len(up) == 1 else 'are'} resolved above late fusion" if up else
                "Overall, no fused method that runs without ground truth is resolved above late fusion")
        if up_oracle:
            text += f"; the {'oracle' if len(up_oracle) == 1 else 'oracles'} {', '.join(map(name if 'bounds' in r else str, up_oracle))} " \
                    f"{'is' if len(up_oracle) == 1 else 'are'}"
        out.append(text + ".")
    ctx = [g for g in gs if g != "all"]
    if ctx:
        wins = {g: [o.a for o in os_ if o.group == g and o.b == LATE and o.sign > 0 and o.a not in ORACLES
                    and o.a not in ss]
                for g in ctx}
        wins = {g: w for g, w in wins.items() if w}
        out.append("Per context, a fused method that runs without ground truth is resolved above late fusion in " +
                   ("; ".join(f"{g} ({', '.join(w)})" for g, w in wins.items()) if wins else "no context") + ".")
        best = {g: o for o in os_ if o.group in ctx and o.a == LATE and o.b in ss for g in [o.group]}
        above = [f"{g} ({best[g].b})" for g in ctx if g in best and best[g].sign > 0]
        below = [f"{g} ({best[g].b})" for g in ctx if g in best and best[g].sign < 0]
        unres = [g for g in ctx if g in best and best[g].sign == 0]
        chosen = " (chosen on the validation frames)" if r.get("best_single") else ""
        out.append(f"Late fusion against its best single sensor per context{chosen}: resolved above in "
                   f"{', '.join(above) or 'no context'}; resolved below in {', '.join(below) or 'no context'}; "
                   f"not resolved in {', '.join(unres) or 'no context'}.")
    return out


def verdict_sentences(report: dict) -> list[str]:
    """The study's answer (`answer_sentences`), then what "resolved" means, then the orders in fixed
    sentences, the overall group first, then each context.

    Per group: whether late fusion beats every single sensor (or which it does not), late fusion
    against the best single sensor, the methods resolved above and below late fusion and those not
    resolved against it (each with its interval of "method minus late"), and the orders among the
    single sensors. Intervals are those stored; nothing is re-estimated.
    """
    r = _results(report)
    if not (r.get("intervals") or {}).get("per_context"):
        return ["This study has no bootstrap intervals (evaluate.bootstrap = 0), so it resolves no order."]
    iv = r["intervals"]
    head = (f"Resolved means the 95 % interval of a paired difference of mAP@0.5 excludes 0 ({iv['resamples']} draws "
            "of whole test sequences, every method scored on each draw); an interval that holds 0 is not resolved, "
            "whatever the point estimates.")
    if family_sentence(report):
        head += " " + family_sentence(report)
    out = bounds_sentences(report)
    all_orders = orders(report)
    ss = singles(report)
    name = namer(report)
    for g in groups(report):
        og = [o for o in all_orders if o.group == g]
        where = _where(g, og[0].sequences if og else r["intervals"]["per_context"][g]["sequences"])
        vs_late = [o for o in og if o.b == LATE]
        if vs_late:
            s_vs = [o for o in vs_late if o.a in ss]
            below = [o for o in s_vs if o.sign < 0]
            if s_vs and len(below) == len(s_vs):
                out.append(f"{where}, late fusion beats every single sensor (single sensor minus late: "
                           f"{_listing(s_vs, name)}).")
            elif s_vs:
                rest = [o for o in s_vs if o.sign >= 0]
                out.append(f"{where}, late fusion does not beat every single sensor (not resolved below late: "
                           f"{_listing(rest, name)}).")
            best = next((o for o in og if o.a == LATE and o.b in ss), None)
            if best is not None and best.interval is not None:
                word = {1: "resolved above", -1: "resolved below", 0: "not resolved against"}[best.sign]
                on = " on the validation frames" if g in (r.get("best_single") or {}) else ""
                out.append(f"{where}, late fusion is {word} its best single sensor{on}, {best.b}: "
                           f"late minus {best.b} {interval_text(best.interval, signed=True)}.")
            others = [o for o in vs_late if o.a not in ss and o.interval is not None]
            above = [o for o in others if o.sign > 0]
            lower = [o for o in others if o.sign < 0]
            unres = [o for o in others if o.sign == 0]
            out.append(f"{where}, resolved above late fusion: {_listing(above, name) if above else 'none'}.")
            out.append(f"{where}, resolved below late fusion: {_listing(lower, name) if lower else 'none'}.")
            if unres:
                out.append(f"{where}, not resolved against late fusion (the interval holds 0): "
                           f"{', '.join(name(o.a) for o in unres)}.")
        pairs = [o for o in og if o.a in ss and o.b in ss and o.interval is not None]
        if pairs:
            res = [f"{o.a if o.sign > 0 else o.b} above {o.b if o.sign > 0 else o.a} "
                   f"{interval_text(o.interval if o.sign > 0 else (-o.interval[1], -o.interval[0]), signed=True)}" for o in pairs if o.resolved]
            unres = [f"{o.a} and {o.b}" for o in pairs if not o.resolved]
            text = f"{where}, among single sensors: " + ("; ".join(res) if res else "no order resolved")
            out.append(text + (f"; not resolved: {'; '.join(unres)}." if unres else "."))
    few = [g for g in groups(report) if g != "all" and r["intervals"]["per_context"][g]["sequences"] < FEW_SEQUENCES]
    if few:
        n = min(r["intervals"]["per_context"][g]["sequences"] for g in few)
        out.append(f"Caution: {', '.join(few)} {'has' if len(few) == 1 else 'have'} fewer than {FEW_SEQUENCES} test "
                   f"sequences (down to {n}); "
                   f"{n} sequences drawn with replacement give only {comb(2 * n - 1, n)} distinct draws, so their "
                   "intervals are coarse and likely too narrow.")
    return [*answer_sentences(report), head, *out]


def bounds_sentences(report: dict) -> list[str]:
    """Room for context (`study.experiments.bounds`): the context oracle minus all branches overall and per
    context, with its interval and how optimistic it is; empty in a report without bounds."""
    r = _results(report)
    room = (r.get("bounds") or {}).get("room_for_context")
    if not room:
        return []
    a = room.get("all") or {}
    ctx = [f"{g} {interval_text(v['interval'], signed=True)}" for g, v in room.items() if g != "all"]
    out = [f"Room for context ({label(CONTEXT_ORACLE)} minus all_branches): overall {number(a.get('estimate'))}, "
           f"95 % interval {interval_text(a.get('interval'), signed=True)}; per context: {'; '.join(ctx)}. "
           f"{OPTIMISTIC}"]
    rc = (r.get("bounds") or {}).get("room_corrected")
    if rc:  # issue 50: the same room without its selection optimism, each beside what noise alone makes
        naive, split = rc["naive"], rc["split"]
        halves = (f"not estimated ({split['skipped']})" if "skipped" in split else
                  f"{number(split['estimate'])} {interval_text(split['interval'], signed=True)}, where equal constants "
                  f"give {number(split['null_mean'])} on average and {number(split['null_upper'])} at their 95th "
                  f"percentile ({'above' if split['above_null'] else 'not above'} it)")
        out.append(f"Without its optimism (per-context rooms weighted by sequences): chosen on one half of the test "
                   f"sequences and scored on the other, {halves}; chosen and scored on the same "
                   f"sequences {number(naive['estimate'])}, where noise alone gives {number(naive['null_mean'])} "
                   f"(95th percentile {number(naive['null_upper'])}).")
    cc, methods = r.get("context_constant"), r.get("methods") or {}
    if cc and "context_constant" in methods and "all_branches" in methods:
        pg = ((r.get("intervals") or {}).get("per_context") or {}).get("all")
        iv = difference_interval(pg, "context_constant", "all_branches") if pg else None
        out.append(f"Reachable by a gate that reads only the context: the per-context constant chosen on the "
                   f"validation frames minus all_branches, "
                   f"{number(methods['context_constant']['map'] - methods['all_branches']['map'])} "
                   f"{interval_text(iv, signed=True)} on test.")
    return out


def number(v) -> str:
    return "-" if v is None else f"{v + 0.0:+.3f}"


FAMILY_COLORS = {
    "single": "#7f7f7f", "early": "#8c564b", "all_branches": "#17becf",
    "hydrafusion": "#1f77b4", "ecofusion": "#2ca02c",
}
FAMILY_LABELS = {"single": "single sensor", "early": "early fusion model", "all_branches": "all branches",
                 "hydrafusion": "HydraFusion (gate)", "ecofusion": "EcoFusion (gate)"}


def _family(name: str) -> str:
    return name.split(":", 1)[0]


def verdict_figure(report: dict, path: str | Path) -> Path | None:
    """Each method's mAP@0.5 minus late fusion's, with its 95 % interval, one panel per group
    ("all" first, then the contexts); methods sorted by the overall difference, best at the top, in
    the same order in every panel; filled markers are resolved (the interval excludes 0), hollow ones
    are not. PNG (or the format of `path`'s suffix), written atomically. None (and no file) without
    intervals or late fusion."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    from study.outputs import savefig_atomic

    r = _results(report)
    gs = groups(report)
    if not gs or LATE not in r["methods"]:
        return None
    by = {(o.group, o.a): o for o in orders(report) if o.b == LATE}
    methods = [m for m in r["methods"] if m != LATE]

    def diff(m, g):
        a, b = _point(r, m, g), _point(r, LATE, g)
        return None if a is None or b is None else a - b

    rank = {m: i for i, m in enumerate(methods)}  # ties and unscored methods keep the report's order
    methods.sort(key=lambda m: (diff(m, "all") is None, -(diff(m, "all") or 0.0), rank[m]))
    name = namer(report)
    cols = 3
    rows = -(-len(gs) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(15, 1.2 + 0.34 * len(methods) * rows), dpi=100,
                             sharey=True, squeeze=False)
    y = list(range(len(methods)))[::-1]
    for k, g in enumerate(gs):
        ax = axes[k // cols][k % cols]
        # each panel its own symmetric scale: the overall differences are a tenth of a context's
        lim = max([abs(v) for m in methods if (o := by.get((g, m))) and o.interval for v in o.interval]
                  + [abs(d) for m in methods if (d := diff(m, g)) is not None] + [0.01]) * 1.1
        ax.axvline(0.0, color="black", lw=0.9)
        for yi, m in zip(y, methods, strict=True):
            o, d = by.get((g, m)), diff(m, g)
            color = FAMILY_COLORS.get(_family(m), "#9467bd")
            if o is not None and o.interval is not None:
                ax.plot(o.interval, [yi, yi], color=color, lw=2.2, solid_capstyle="butt")
            if d is not None:
                filled = o is not None and o.resolved
                ax.plot([d], [yi], "o", ms=6, color=color, markerfacecolor=color if filled else "white",
                        markeredgewidth=1.6)
        n = r["intervals"]["per_context"][g]["sequences"]
        ax.set_title(f"{'overall' if g == 'all' else g} ({n} test sequences)", fontsize=10,
                     fontweight="bold" if g == "all" else "normal")
        ax.set_xlim(-lim, lim)
        ax.grid(axis="x", color="#dddddd", lw=0.6)
        ax.tick_params(labelsize=8)
        if k % cols == 0:
            ax.set_yticks(y, [name(m) for m in methods], fontsize=8)
        if k // cols == rows - 1:
            ax.set_xlabel("mAP@0.5 minus late fusion's", fontsize=9)
    for k in range(len(gs), rows * cols):
        axes[k // cols][k % cols].axis("off")
    handles = [Line2D([], [], color=c, lw=2.2, marker="o", label=FAMILY_LABELS[f])
                for f, c in FAMILY_COLORS.items()
               if any(_family(m) == f for m in methods)]
    handles += [Line2D([], [], ls="", marker="o", color="black", markerfacecolor="black", label="resolved (interval excludes 0)"),
                Line2D([], [], ls="", marker="o", color="black", markerfacecolor="white", label="not resolved (interval holds 0)")]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=9, frameon=False)
    fig.suptitle(f"mAP@0.5 minus late fusion's per context, 95 % interval of the paired difference "
                 f"({r['intervals']['resamples']} draws of whole test sequences; each panel its own scale)", fontsize=11)
    fig.tight_layout(rect=(0, 0.04, 1, 0.97))
    savefig_atomic(fig, path)
    plt.close(fig)
    return Path(path)
