"""`hydrabench bench <what>`: throughput measurements (`study.bench`). Figures go to BENCHMARKS.md by
hand, with the command that produced them; nothing here asserts a time.

One module per `<what>` (its name with `-` as `_`): its `add_parser(what)` adds the subcommand and
its options, its `run_*` measures and prints the figures. A new bench is a new module here, named in
FAMILIES."""

from __future__ import annotations

from study.cli import Formatter
from study.commands.bench import (
    amp,
    amp_parity,
    arch,
    bootstrap,
    boxes,
    coverage,
    generate,
    inference,
    lidar_fog,
    profile,
    recipe,
    scale,
    sim,
)

FAMILIES = (sim, generate, boxes, bootstrap, coverage, inference, amp, amp_parity, profile, recipe, arch, lidar_fog, scale)
"""The subcommands, in the order `hydrabench bench --help` lists them."""


def add_parser(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=help_text, formatter_class=Formatter)
    what = p.add_subparsers(dest="what", metavar="<what>", parser_class=type(p))
    what.required = True
    for family in FAMILIES:
        family.add_parser(what)
