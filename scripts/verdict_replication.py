"""Score a study's verdict again on an independent test set and say whether it replicates.

    python scripts/verdict_replication.py A B [--extract FILE] [--out FILE]

A and B: study reports (`report.json`) of the same design whose test sets differ (`data.test.seed`),
or the extract `--extract` writes of one. The second is the same study with another test seed, in
the same study directory so that only the test set, the evaluation and what follows run again (the
gates train again only if their code or the machine's compute identity changed):

    sed 's/^    seed: 2001/    seed: 2002/' configs/study/cpu-verdict.yaml > /tmp/test2.yaml
    hydrabench study /tmp/test2.yaml --out DIR

Prints the summary (`study.experiments.verdict_replication.replicate`: the share of (pair, context) estimates
whose two values agree within their intervals, about 0.95 when the intervals are right; pairs
resolved in one report and the other; contradictions), the headline pairs side by side, the gates'
kept objectives and the physical gate's rules; `--out` writes the comparison as JSON (every row too
with `--pairs`),
`--extract` what of B the comparison reads (methods' mAP, intervals, gates, rules: a few hundred kB
instead of the whole report), so that the comparison can be checked again without B's report.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from study.experiments.verdict_replication import replicate

KEPT = ("machine", "dataset", "intervals", "gate_training", "physical_gate")
"""What an extract keeps of a report's results besides each method's mAP (overall and per context)."""


def load_results(path: Path) -> dict:
    rec = json.loads(Path(path).read_text())
    res = rec.get("results", rec)
    if "methods" not in res or "intervals" not in res:
        raise SystemExit(f"{path}: not a study report or extract (no results.methods / results.intervals)")
    return res


def extract(res: dict) -> dict:
    """The part of a report's results that `replicate` reads."""
    out = {k: res[k] for k in KEPT if k in res}
    out["methods"] = {m: {"map": v.get("map"), "map_per_context": v.get("map_per_context")}
                      for m, v in res["methods"].items()}
    g = out.get("gate_training") or {}
    out["gate_training"] = {n: {k: v.get(k) for k in ("objective", "val_regret", "objectives", "choice")}
                            for n, v in g.items()}
    pg = out.get("physical_gate") or {}
    out["physical_gate"] = {"rules": pg.get("rules")}
    return {"what": "the part of a study report that scripts/verdict_replication.py reads", "results": out}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("a", type=Path, help="the first report (report.json, or an extract)")
    p.add_argument("b", type=Path, help="the second, scored on an independent test set")
    p.add_argument("--out", type=Path, help="write the comparison here (JSON): summary, headline pairs, gates, rules; "
                                            "with --pairs also every (pair, context) row")
    p.add_argument("--pairs", action="store_true", help="with --out: every (pair, context) row too")
    p.add_argument("--extract", type=Path, help="write what the comparison reads of B here (JSON)")
    args = p.parse_args(argv)
    ra, rb = load_results(args.a), load_results(args.b)
    r = replicate(ra, rb)
    s = r["summary"]
    print(f"test sets {s['test_sets'][0]} / {s['test_sets'][1]}; machines {s['machines'][0]} / {s['machines'][1]}")
    print(f"(pair, context) estimates compared: {s['pairs']}; agreeing within their intervals: "
          f"{s['agreement_rate']:.3f} (about {s['agreement_expected']} if the intervals are right; the pairs share "
          f"methods, so this is less sure than its count)")
    print(f"resolved in A {s['resolved_in_a']}, in B {s['resolved_in_b']}, in both the same way "
          f"{s['resolved_in_both_same_way']}, contradictions {s['contradictions']}")
    for h in r["headline"]:
        print(f"{h['pair']:<44} A {h['a']:+.3f} [{h['interval_a'][0]:+.3f}, {h['interval_a'][1]:+.3f}]  "
              f"B {h['b']:+.3f} [{h['interval_b'][0]:+.3f}, {h['interval_b'][1]:+.3f}]  agree {h['agree']}")
    for name, g in r["gates"].items():
        print(f"{name}: objective kept A {g['objective'][0]}, B {g['objective'][1]}; B's validation regret per "
              f"objective {g['objectives_b']}")
    print(f"physical gate rules: A {r['physical_gate_rules'][0]}; B {r['physical_gate_rules'][1]}")
    if args.out:
        out = r if args.pairs else {k: v for k, v in r.items() if k != "pairs"}
        args.out.write_text(json.dumps(out, indent=1) + "\n")
        print(f"wrote {args.out}", file=sys.stderr)
    if args.extract:
        args.extract.write_text(json.dumps(extract(rb), indent=1) + "\n")
        print(f"wrote {args.extract}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
