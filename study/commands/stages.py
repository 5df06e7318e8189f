"""`hydrabench stages`: the command line of `sensors.stages` (where two machines' generation parts)."""

from __future__ import annotations

import json

from sim.errors import UserError
from study.cli import Formatter, dataset_dir, emit, in_file, name_arg, nonneg_int

DESCRIPTION = """\
Generate the first frame of one context, as `hydrabench generate` does, and print a digest of
every stage: simulation, meshes, the cameras' code pass (OpenGL), the lidar and radar scans
(Embree), camera shading, degradation, the stored arrays and the labels, with the platform (CPU
flags, library versions, OpenGL renderer). Takes a few seconds.

To compare two machines: `hydrabench stages --json > a.json` on one, then
`hydrabench stages --against a.json` on the other; it names the first stage whose bytes differ
(exit 0 either way: differing machines are a finding, not an error).

`--dataset A --against-dataset B` instead checks two datasets of one generation config (made on two machines)
against the cross-machine tolerances of `sensors.stages.TOLERANCES`; exit 1 if any is exceeded."""


def add_parser(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=DESCRIPTION, formatter_class=Formatter)
    p.add_argument("--context", type=name_arg, default="city", help="context of the frame")
    p.add_argument("--seed", type=nonneg_int, default=3, help="root seed (as generate --seed)")
    p.add_argument("--profile", type=name_arg, default="cpu", help="sensor profile: cpu or paper")
    p.add_argument("--against", type=in_file, default=None, metavar="JSON",
                   help="the --json output of this command on another machine: name the first stage that differs")
    p.add_argument("--dataset", type=dataset_dir, default=None,
                   help="with --against-dataset: compare two datasets of one config against the cross-machine "
                        "tolerances instead")
    p.add_argument("--against-dataset", type=dataset_dir, default=None, help="the other dataset of --dataset")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(run=run)


def _load_record(path: str) -> dict:
    try:
        record = json.loads(open(path, encoding="utf-8").read())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UserError(f"--against {path}: not a JSON file ({exc})") from None
    if not isinstance(record, dict) or not isinstance(record.get("stages"), dict) or "config" not in record:
        raise UserError(f"--against {path}: not the --json output of hydrabench stages")
    return record


def run(args) -> int:
    from sensors import stages

    if (args.dataset is None) != (args.against_dataset is None):
        raise UserError("--dataset and --against-dataset go together (the two datasets to compare)")
    if args.dataset:
        try:
            bad = stages.dataset_differences(args.dataset, args.against_dataset)
        except ValueError as exc:
            raise UserError(f"--dataset: {exc}") from None
        emit({"datasets": [args.dataset, args.against_dataset], "within_tolerances": not bad, "violations": bad,
              "tolerances": stages.TOLERANCES}, args.json,
             lambda r: "within the cross-machine tolerances" if not bad else "\n".join(["beyond tolerance:", *bad]))
        return 0 if not bad else 1
    other = _load_record(args.against) if args.against else None
    from sensors.generate import GenerateConfig

    GenerateConfig(contexts=(args.context,), seed=args.seed, profile=args.profile)  # UserError on bad names
    record = stages.stage_digests(args.context, args.seed, args.profile)
    if other is not None:
        try:
            record["first_difference"] = stages.first_difference(record, other)
        except ValueError as exc:
            raise UserError(f"--against {args.against}: {exc}") from None
        record["against"] = {"file": args.against, "stages": other["stages"], "platform": other.get("platform")}
    emit(record, args.json, _text)
    return 0


def _text(r: dict) -> str:
    p = r["platform"]
    lines = [f"stages of the first {r['shard']['context']} frame (seed {r['config']['seed']}, profile "
             f"{r['config']['profile']}) on {p['cpu']} [{' '.join(p['cpu_flags'])}], {p['opengl']['renderer']}"]
    theirs = r.get("against", {}).get("stages", {})
    for stage, d in r["stages"].items():
        mark = "" if not theirs else ("  same" if theirs.get(stage) == d else f"  DIFFERS (theirs {theirs.get(stage)})")
        lines.append(f"  {stage:15s} {d}{mark}")
    if "first_difference" in r:
        first = r["first_difference"]
        lines.append("all stages agree" if first is None else f"first stage that differs: {first}")
    return "\n".join(lines)
