"""`hydrabench labels`: the command line of `study.experiments.label_stats` (what it counts is described there)."""

from __future__ import annotations

from sim.errors import UserError
from study.cli import Formatter, dataset_dir, emit, name_list
from study.experiments import label_stats


def add_parser(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=label_stats.__doc__.split("\n\n", 1)[1], formatter_class=Formatter)
    p.add_argument("data", type=dataset_dir, help="dataset directory (format 2: with 3D ground truth)")
    p.add_argument("--protocols", type=name_list, default=("visible", "reference"),
                   help="comma-separated: reference, visible, bev")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(run=run)


def run(args) -> int:
    from fusion.protocol import PROTOCOLS

    protocols = list(args.protocols)
    bad = [x for x in protocols if x not in PROTOCOLS]
    if bad:
        raise UserError(f"--protocols: unknown protocol {bad[0]!r} (choose from: {', '.join(PROTOCOLS)})")
    result = label_stats.label_statistics(args.data, tuple(protocols))

    def text(r):
        lines = [f"{r['frames']} frames of {r['data']}: right-camera vehicle boxes to find / ignored per range bin"]
        for p, frames in r["protocols"].items():
            v = frames["camera_right"]["vehicles"]
            lines.append(f"  {p}: " + ", ".join(f"{b} {c['to_find']}/{c['ignored']}" for b, c in v.items()))
        obs = r["vehicles_within_r_max_observed_by"]
        lines.append("  vehicles within R_max observed (clean render) by: "
                     + ", ".join(f"{k} {v}" for k, v in obs.items()))
        return "\n".join(lines)

    emit(result, args.json, text)
    return 0
