"""The context oracle as a selection file: per context, the fixed branch set that scored best there.

    hydrabench score DATA --export DIR --nuscenes lidar=lidar.json --nuscenes radar=radar.json --json > score.json
    python examples/context_oracle.py --score score.json --export DIR --out oracle.json
    hydrabench score DATA --export DIR --nuscenes ... --selection context_oracle=oracle.json

Reads a `hydrabench score --json` result and, for each context, picks among its constant methods
(each branch alone, `late`, `all_branches`) the one with the best mAP on that context's frames; every
sample of the context gets that method's branches. It is chosen on the very frames it is then scored
on, so it is a bound on any gate that reads only the context, not a gate a car could run
(study.experiments.bounds' context oracle, for detections from outside). Scored as a selection file, its interval
holds that choice fixed in every bootstrap draw, so it is optimistic (study.experiments.bounds chooses again
inside each draw). The sample's context is the export's
`sample["hydrabench"]["context"]`, read through the devkit.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from classical_common import DetectorError, load_nuscenes, write_json  # noqa: E402


def constants(score: dict) -> dict[str, list[str]]:
    """{method: its branches} of a score result's fixed methods."""
    singles = [b for b in score["branches"] if len(score["branch_sensors"][b]) == 1]
    out = {f"single:{b}": [b] for b in score["branches"]}
    if "late" in score["methods"]:
        out["late"] = singles
    if "all_branches" in score["methods"]:
        out["all_branches"] = list(score["branches"])
    return {k: v for k, v in out.items() if k in score["methods"]}


def choice(score: dict) -> dict[str, str]:
    """{context: the constant method with the best mAP there} (ties: the first in `constants`)."""
    out = {}
    for ctx in score["contexts"]:
        best = None
        for name in constants(score):
            v = score["methods"][name]["map_per_context"].get(ctx)
            if v is not None and (best is None or v > best[1]):
                best = (name, v)
        if best is not None:
            out[ctx] = best[0]
    return out


def selection(nusc, score: dict) -> tuple[dict, dict]:
    """({sample token: branches}, {context: method}) over every sample whose context was scored."""
    picked, sets = choice(score), constants(score)
    out = {}
    for s in nusc.sample:
        ctx = (s.get("hydrabench") or {}).get("context")
        if ctx in picked:
            out[s["token"]] = sets[picked[ctx]]
    return out, picked


def build() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.strip(), formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--score", type=Path, required=True, help="a `hydrabench score --json` result")
    p.add_argument("--export", type=Path, required=True, metavar="DIR", help="the nuScenes export it scored")
    p.add_argument("--out", type=Path, required=True, metavar="FILE.json", help="the selection file to write")
    p.add_argument("--version", default=None, help="the tables' folder (default: the only v1.0-* folder in DIR)")
    return p


def main(argv=None) -> int:
    args = build().parse_args(argv)
    try:
        try:
            score = json.loads(args.score.read_text())
            score["methods"], score["contexts"], score["branch_sensors"]  # noqa: B018
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise DetectorError(f"--score {args.score}: not a hydrabench score --json result ({exc})") from None
        nusc = load_nuscenes(args.export, args.version)
        chosen, picked = selection(nusc, score)
    except DetectorError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    write_json(args.out, chosen)
    print("context_oracle: " + ", ".join(f"{c} -> {m}" for c, m in picked.items()) + f"; wrote {args.out}",
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
