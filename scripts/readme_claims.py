"""Regenerate the README's table of claims from the stored cpu-verdict files.

    python scripts/readme_claims.py results/study_cpu_verdict           (rewrites README.md in place)
    python scripts/readme_claims.py results/study_cpu_verdict --check   (exit 1 when README.md is stale)

Each claim the README makes about the `cpu-verdict` study is judged in every stored scoring that can
judge it: the study's test set (seed 2001, `report.json`), an independent test set scored with the
same detectors (seed 2002, `report_test2002_extract.json`) and detectors trained with a second seed
on that set (`report_seed1_test2002_extract.json`); the crossovers on two sweep sets (`report.json`'s
and `crossover_replication.json`'s), the recurrent gate on two sets of weather sequences (`report.json`'s
and `transitions_seed4100.json`). A cell says "holds", "does not hold" or "not resolved" with the
estimate and its 95 % interval, or "not measured" where that scoring lacks a method. An overall order
is resolved when its interval excludes 0; a per-context order only with the verdict's correction over
its whole family (`study.report.verdict.orders`). The block lies between BEGIN and END; nothing else changes.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from study.engine.scoring import difference_interval
from study.numbers import interval_text, rounded
from study.outputs import replace_marked_block, update_page
from study.report.verdict import orders

BEGIN = "<!-- study-claims:begin (scripts/readme_claims.py writes this block; do not edit by hand) -->"
END = "<!-- study-claims:end -->"
ROOT = Path(__file__).resolve().parents[1]

TEST_SETS = (("test set 2001, seed 0", "report.json"), ("test set 2002, seed 0", "report_test2002_extract.json"),
             ("test set 2002, seed 1", "report_seed1_test2002_extract.json"))
"""(column, file in the stored folder): each scoring of a whole test set, detectors' training seed named."""
GATES = ("hydrafusion:deep", "hydrafusion:attention", "ecofusion:deep", "ecofusion:attention")
HOLDS, FAILS, OPEN, ABSENT = "holds", "does not hold", "not resolved", "not measured"
WORD = {1: HOLDS, -1: FAILS, 0: OPEN}
"""A claim that `a` lies above `b`, by the sign of its resolved order."""


def _sign(iv) -> int:
    """+1 / -1: the interval lies above / below 0 (strictly, as `study.report.verdict.Order.resolved`); 0: not resolved."""
    return 1 if iv[0] > 0 else -1 if iv[1] < 0 else 0


def _pair(r: dict, a: str, b: str):
    """(estimate, interval) of `a` minus `b` over all test sequences, None when the scoring lacks either.
    Fixed branch sets (radar_lidar) are scored only on the mAP-energy front of the report's bounds."""
    ci = r["intervals"]["per_context"]["all"]
    if a in r["methods"] and b in r["methods"]:
        return r["methods"][a]["map"] - r["methods"][b]["map"], difference_interval(ci, a, b)
    front = (r.get("bounds") or {}).get("front") or {}
    if a in front.get("map_point", {}) and b in front.get("map_point", {}):
        return front["map_point"][a] - front["map_point"][b], difference_interval(front, a, b)
    return None


def _estimate(est: float, iv) -> str:
    """A difference and its interval; the difference rounded as stored (4 decimals) first, so a
    difference of two stored mAPs prints as the stored difference does."""
    return f"{rounded(est) + 0.0:+.3f} {interval_text(iv, signed=True)}"


def _text(name: str, est: float, iv) -> str:
    return f"{name} {_estimate(est, iv)}"


def _above(r: dict, a: str, b: str) -> str:
    """`a` is resolved above `b`: the cell."""
    got = _pair(r, a, b)
    if got is None:
        return ABSENT
    est, iv = got
    return f"{WORD[_sign(iv)]}: {_estimate(est, iv)}"


def _all_above(r: dict, a: str, bs: list[str]) -> str:
    """`a` is resolved above every one of `bs`: the verdict, with the pair nearest to failing it."""
    got = {b: _pair(r, a, b) for b in bs}
    if not got or any(v is None for v in got.values()):
        return ABSENT
    worst = min(got, key=lambda b: got[b][1][0])
    signs = [_sign(iv) for _, iv in got.values()]
    verdict = HOLDS if all(s == 1 for s in signs) else FAILS if any(s == -1 for s in signs) else OPEN
    return f"{verdict}; weakest: {_text(f'minus {worst}', *got[worst])}"


def _none_ordered(r: dict, pairs: list[tuple[str, str]], ways: tuple[int, ...] = (1, -1)) -> str:
    """No pair of `pairs` is resolved in a direction of `ways`: the verdict, with the pair nearest to an order."""
    got = {p: _pair(r, *p) for p in pairs}
    got = {p: v for p, v in got.items() if v is not None}
    if not got:
        return ABSENT

    def reach(p):  # how far the interval's bound on the side of `ways` lies past 0 (> 0: resolved that way)
        lo, hi = got[p][1]
        return max(lo if 1 in ways else -1.0, -hi if -1 in ways else -1.0)

    near = max(got, key=reach)
    ordered = [p for p in got if _sign(got[p][1]) in ways]
    verdict = FAILS if ordered else HOLDS
    return f"{verdict} ({len(ordered)} of {len(got)} ordered); nearest: {_text(' - '.join(near), *got[near])}"


def _per_context(report: dict) -> str:
    """No per-context order is resolved under the verdict's correction over its family."""
    r = report["results"]
    if "singles" not in r:  # an extract keeps no list of singles: the scored single sensors are they
        report = {**report, "results": {**r, "singles": [m.split(":", 1)[1] for m in r["methods"]
                                                          if m.startswith("single:")]}}
    per = [o for o in orders(report) if o.group != "all" and o.p is not None]
    if not per:
        return ABSENT
    n = sum(o.resolved for o in per)
    return f"{FAILS if n else HOLDS} ({n} of {len(per)} orders resolved)"


def test_set_rows(reports: list[dict]) -> list[tuple[str, list[str]]]:
    """(claim, one cell per scoring) for the claims judged on whole test sets."""
    rs = [x["results"] for x in reports]
    singles = [m for m in rs[0]["methods"] if m.startswith("single:")]
    rows = [("late fusion above every single sensor", [_all_above(r, "late", singles) for r in rs]),
            ("all_branches above late fusion", [_above(r, "all_branches", "late") for r in rs])]
    rows += [(f"{g} above late fusion", [_above(r, g, "late") for r in rs]) for g in GATES]
    rows.append(("no learned gate ordered against all_branches",
                 [_none_ordered(r, [(g, "all_branches") for g in GATES]) for r in rs]))
    rows.append(("no learned gate above the fixed radar_lidar branch (costs less)",
                 [_none_ordered(r, [(g, "radar_lidar") for g in GATES], ways=(1,)) for r in rs]))
    rows.append(("room for context: context oracle (chosen on test, optimistic) above all_branches",
                 [_above(r, "context_oracle", "all_branches") for r in rs]))
    rows.append(("physical knowledge gate above all_branches", [_above(r, "physical_gate", "all_branches") for r in rs]))
    rows.append(("no per-context order (Holm over the verdict's family)", [_per_context(x) for x in reports]))
    return rows


def _crossing(cur: dict, unit: str) -> str:
    """A crossover curve's cell: fusing the sensor is resolved to cost mAP from some level on (holds),
    crosses zero without a level resolved below it (not resolved), or never crosses (does not hold)."""
    if cur["crossing_kind"] == "none":
        return f"{FAILS}: no crossing"

    def num(v):
        return "open" if v is None else f"{v:.3g}"

    lo, hi = cur["crossing_interval"]
    where = f"{cur['crossing']:.3g} {unit} [{num(lo)}, {num(hi)}]"
    if cur["first_resolved_below"] is None:
        return f"{OPEN}: crosses at {where}, no level resolved below 0"
    return f"{HOLDS}: crosses at {where}, resolved below 0 from {cur['first_resolved_below']:.3g} {unit}"


def _recurrent(tx: dict) -> str:
    rec = tx["gates"]["recurrent"]["variants"]
    x = next(v for k, v in rec.items() if k.startswith("recurrent ("))
    iv = x["regret_transitions_minus_deep_interval"]
    return f"{WORD[_sign(iv)]}: {interval_text(iv, signed=True)}"


def own_set_rows(report: dict, crossover_rep: dict, transitions_b: dict) -> tuple[list[str], list[tuple[str, list[str]]]]:
    """(column heads, rows) for the claims measured on sets of their own: the crossovers on two sweep
    sets, the recurrent gate in the transitions of two sets of weather sequences."""
    r = report["results"]
    seeds = crossover_rep["summary"]["seeds"]
    tx = r["transitions"]

    def weather(t):
        return ", ".join(str(v) for k, v in t["seeds"].items() if k.startswith("test"))

    heads = [f"sweep seeds {min(seeds['a'].values())}-{max(seeds['a'].values())}; weather seeds {weather(tx)}",
             f"sweep seeds {min(seeds['b'].values())}-{max(seeds['b'].values())}; weather seeds {weather(transitions_b)}"]
    rows = []
    for cond, sensor, what in (("fog", "lidar", "fusing the lidar costs mAP in dense fog"),
                               ("night", "camera_right", "fusing camera_right costs mAP at night")):
        c = next(x for x in crossover_rep["crossings"]
                 if x["base"] == "all_branches" and x["condition"] == cond and x["sensor"] == sensor)
        rows.append((f"{what} (all branches with minus without it)", [_crossing(c[s], c["unit"]) for s in ("a", "b")]))
    rows.append(("recurrent gate's regret above the deep gate's in transitions",
                 [_recurrent(tx), _recurrent(transitions_b)]))
    return heads, rows


def _table(first: str, heads: list[str], rows) -> list[str]:
    return ([f"| {first} | " + " | ".join(heads) + " |", "|---|" + "---|" * len(heads)]
            + [f"| {claim} | " + " | ".join(cells) + " |" for claim, cells in rows])


def claims_block(folder: Path, root: Path = ROOT) -> str:
    """The Markdown block for the stored cpu-verdict folder (`results/study_cpu_verdict`), named from
    `root` (the README's folder) where it lies under it, else as DIR."""
    try:
        shown = folder.resolve().relative_to(root.resolve()).as_posix()
    except ValueError:
        shown = "DIR"
    reports = [json.loads((folder / name).read_text()) for _, name in TEST_SETS]
    heads = [f"{col} ({x['results']['machine']['cpu'].split(' Processor')[0].replace('(R)', '')})"
             for (col, _), x in zip(TEST_SETS, reports)]
    lines = [f"Generated by `python scripts/readme_claims.py {shown}` from its stored files: each "
             "claim in each scoring, with its estimate (minus) and 95 % interval over the test sequences "
             "(500 draws); the decisive pair is named where a claim spans several.", ""]
    lines += _table("claim (test sets)", heads, test_set_rows(reports))
    oh, orows = own_set_rows(reports[0], json.loads((folder / "crossover_replication.json").read_text()),
                             json.loads((folder / "transitions_seed4100.json").read_text()))
    lines += ["", *_table("claim (sets of its own)", oh, orows)]
    return "\n".join(lines)


def replace_block(readme: str, block: str) -> str:
    """`readme` with the text between BEGIN and END replaced by `block` (ValueError without both markers)."""
    return replace_marked_block(readme, BEGIN, END, block)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("folder", help="the stored cpu-verdict folder (results/study_cpu_verdict)")
    p.add_argument("--readme", default=str(ROOT / "README.md"), help="README to update")
    p.add_argument("--check", action="store_true", help="exit 1 when the README's block differs, write nothing")
    args = p.parse_args(argv)
    try:
        readme = Path(args.readme).read_text()
        new = replace_block(readme, claims_block(Path(args.folder), Path(args.readme).parent))
    except (OSError, ValueError, KeyError, StopIteration) as exc:
        sys.stderr.write(f"readme_claims: {exc!r}\n" if isinstance(exc, StopIteration) else f"readme_claims: {exc}\n")
        return 2
    return update_page(args.readme, readme, new, args.check)


if __name__ == "__main__":
    sys.exit(main())
