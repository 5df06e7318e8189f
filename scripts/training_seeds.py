"""Training variance beside test-set variance: a study's headline rows side by side.

    python scripts/training_seeds.py --report LABEL=REPORT [--report ...] --seeds A,B [--test-sets A,C]
                                     [--out FILE] [--extract LABEL=FILE]

REPORT: a study's `report.json` or an extract (`scripts/verdict_replication.py --extract`). `--seeds`:
two labels whose detectors were trained with different seeds (`train.seed`), scored on the same test
set; `--test-sets`: two labels of one training scored on independent test sets. For example, the
second detector seed of issue 36 (the verdict preset with `train.seed: 1` and no `detectors`, the test
set of the replication):

    python scripts/training_seeds.py --report seed0=results/study_cpu_verdict/report_test2002_extract.json \\
        --report seed1=SEED1/report.json --report seed0_test2001=results/study_cpu_verdict/report.json \\
        --seeds seed0,seed1 --test-sets seed0,seed0_test2001 --out training_seeds.json

Prints the headline rows (`study.experiments.training_seeds`) and how far each pair moves between the seeds and
between the test sets, in units of the test interval's half-width.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from verdict_replication import extract, load_results

from study.experiments.training_seeds import training_variance


def _labelled(text: str) -> tuple[str, Path]:
    label, sep, path = text.partition("=")
    if not sep or not label or not path:
        raise argparse.ArgumentTypeError(f"expected LABEL=PATH, got {text!r}")
    return label, Path(path)


def _two(text: str) -> tuple[str, str]:
    parts = text.split(",")
    if len(parts) != 2 or not all(parts):
        raise argparse.ArgumentTypeError(f"expected two labels A,B, got {text!r}")
    return parts[0], parts[1]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--report", type=_labelled, action="append", required=True, metavar="LABEL=REPORT",
                   help="a study report (report.json) or an extract, with its label; repeat")
    p.add_argument("--seeds", type=_two, required=True, metavar="A,B",
                   help="two labels trained with different seeds, scored on the same test set")
    p.add_argument("--test-sets", type=_two, default=None, metavar="A,C",
                   help="two labels of one training, scored on independent test sets")
    p.add_argument("--out", type=Path, help="write the record here (JSON)")
    p.add_argument("--extract", type=_labelled, action="append", default=[], metavar="LABEL=FILE",
                   help="also write what this tool reads of LABEL's report (a few hundred kB) to FILE")
    args = p.parse_args(argv)
    reports = {label: load_results(path) for label, path in args.report}
    for label in (*args.seeds, *(args.test_sets or ())):
        if label not in reports:
            p.error(f"no --report labelled {label!r}")
    try:
        r = training_variance(reports, args.seeds, args.test_sets)
    except ValueError as e:
        p.error(str(e))
    labels = list(reports)
    for k, v in r["reports"].items():
        print(f"{k}: test set {v['test_set']}, machine {v['machine']}")
    print(f"{'pair':<40} " + "  ".join(f"{k:>28}" for k in labels))
    for row in r["headline"]:
        cells = [f"{c['estimate']:+.3f} [{c['ci95'][0]:+.3f}, {c['ci95'][1]:+.3f}]" for c in
                 (row["per"][k] for k in labels)]
        print(f"{row['pair']:<40} " + "  ".join(f"{c:>28}" for c in cells))
    for name in ("training", "test_set"):
        s = r[name]
        if s is None:
            continue
        print(f"{name} ({s['between'][0]} -> {s['between'][1]}): |difference| / half-width median {s['median_ratio']}, "
              f"largest {s['max_ratio']}, mean |difference| {s['mean_abs_difference']}; verdicts changed: "
              f"{', '.join(s['verdicts_changed']) or 'none'}")
    if args.out:
        args.out.write_text(json.dumps(r, indent=1) + "\n")
        print(f"wrote {args.out}", file=sys.stderr)
    for label, path in args.extract:
        if label not in reports:
            p.error(f"--extract: no --report labelled {label!r}")
        path.write_text(json.dumps(extract(reports[label]), indent=1) + "\n")
        print(f"wrote {path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
