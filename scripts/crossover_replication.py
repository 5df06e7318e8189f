"""Measure a study's crossovers again on an independent sweep set and say whether they replicate.

    python scripts/crossover_replication.py A B [--out FILE]

A and B: crossover records of the same design (`DIR/stages/crossover-<key>/crossover.json`, or a
study's `report.json`, whose `results.crossover` is the record). The second sweep set is the same
study with another `crossover.seed` (its levels get seed + 1 .. seed + 5), stopped after the
crossover stage, in the same study directory so that nothing upstream runs again:

    sed 's/^  seed: 3000 /  seed: 3100 /' configs/study/cpu-verdict.yaml > /tmp/sweep2.yaml
    hydrabench study /tmp/sweep2.yaml --out DIR --until crossover

Prints the summary (`study.experiments.crossover_replication.replicate`: the share of levels whose two
estimates agree within their intervals, about 0.95 when the intervals are right; levels resolved in
one set and the other; contradictions; each crossing against the other's interval) and writes the
whole comparison to FILE as JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from study.experiments.crossover_replication import replicate


def load_record(path: Path) -> dict:
    rec = json.loads(Path(path).read_text())
    if "results" in rec and "conditions" not in rec:  # a study's report.json
        rec = rec["results"].get("crossover")
        if not rec:
            raise SystemExit(f"{path}: a report without a crossover record (the study has no crossover: section)")
    if "conditions" not in rec:
        raise SystemExit(f"{path}: not a crossover record (no 'conditions')")
    return rec


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("a", type=Path, help="the first crossover record (crossover.json or report.json)")
    p.add_argument("b", type=Path, help="the second, on an independent sweep set")
    p.add_argument("--out", type=Path, help="write the whole comparison here (JSON)")
    args = p.parse_args(argv)
    r = replicate(load_record(args.a), load_record(args.b))
    s = r["summary"]
    print(f"levels compared: {s['levels']}; estimates agreeing within their intervals: {s['agreement_rate']:.3f} "
          f"(about {s['agreement_expected']} if the intervals are right)")
    print(f"resolved in A {s['resolved_in_a']}, in B {s['resolved_in_b']}, in both the same way "
          f"{s['resolved_in_both_same_way']}, contradictions {s['contradictions']}")
    for c in r["crossings"]:
        if c["a"]["crossing_kind"] == c["b"]["crossing_kind"] == "none":
            continue
        both = "" if c["b_in_a"] is None else f"  B in A's interval: {c['b_in_a']}, A in B's: {c['a_in_b']}"
        print(f"{c['base']:>13} {c['condition']:>5} {c['sensor']:<12} A {c['a']['crossing_kind']:<10} "
              f"{c['a']['crossing'] if c['a']['crossing'] is not None else '-'!s:<10.6} "
              f"B {c['b']['crossing_kind']:<10} {c['b']['crossing'] if c['b']['crossing'] is not None else '-'!s:<10.6}"
              f"{both}")
    if args.out:
        args.out.write_text(json.dumps(r, indent=1) + "\n")
        print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
