"""`hydrabench gallery`: one scene of a dataset re-rendered under every condition and severity
(`study.experiments.gallery`)."""

from __future__ import annotations

from pathlib import Path

from study.cli import IMAGE_SUFFIXES, Formatter, dataset_dir, emit, name_arg, name_list, out_file

EPILOG = """\
Takes frame --index of the dataset, rebuilds that exact moment from its shard's seed, and renders it
again under a representative weather state of each condition and severity (the centre of the
severity table's interval; sim.weather.representative_weather), with the weather degradation models
(no random obstructions), so one row differs from the next only by the weather. Columns: right
camera, forward lidar, lidar BEV, radar BEV. Fog must look like fog; the radar must barely change
in fog.
"""


def add_parser(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=help_text, epilog=EPILOG, formatter_class=Formatter)
    p.add_argument("dir", type=dataset_dir, help="dataset directory (its manifest gives the scene's seed and profile)")
    p.add_argument("--out", required=True, type=out_file(*IMAGE_SUFFIXES), help="picture to write (.png, .pdf or .svg)")
    p.add_argument("--index", type=int, default=0, help="frame of the dataset to use as the scene")
    p.add_argument("--context", type=name_arg, default=None, help="take the --index-th frame of this context instead")
    p.add_argument("--conditions", type=name_list, default="rain,fog,snow,night",
                   help="comma-separated conditions (rows), each once")
    p.add_argument("--json", action="store_true", help="print one JSON object (what was rendered) on stdout")
    p.set_defaults(run=run)


def run(args) -> int:
    from study.experiments.gallery import render_gallery

    result = render_gallery(Path(args.dir), Path(args.out), args.index, args.context, list(args.conditions))
    emit(result, args.json, lambda r: f"wrote {r['out']} ({r['rows']} rows)")
    return 0
