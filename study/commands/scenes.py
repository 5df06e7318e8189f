"""`hydrabench scenes`: simulate a context, summarise it and draw it top-down (`study.experiments.scenes`)."""

from __future__ import annotations

from study.cli import (
    IMAGE_SUFFIXES,
    Formatter,
    emit,
    name_arg,
    nonneg_int,
    out_path,
    pos_float,
    pos_int,
    severity_arg,
)

EPILOG = """\
contexts: city, junction, motorway, rural (road layouts) and rain, fog, snow, night (conditions,
each on its default layout: rain->junction, fog->motorway, snow->rural, night->city), or a
combination of one layout and conditions such as city+night+rain. 'all' runs the eight names.

examples:
  hydrabench scenes --context junction --frames 20 --seed 0 --plot junction.png
  hydrabench scenes --context fog --severity 4 --json
  hydrabench scenes --context all --severity 3 --plot pictures/   (one PNG per context)
"""


def add_parser(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=help_text, epilog=EPILOG, formatter_class=Formatter)
    p.add_argument("--context", type=name_arg, default="city", help="context name, combination, or 'all'")
    p.add_argument("--severity", type=severity_arg, default=None,
                   help="0-5 for the conditions of the context (default: 3 for conditions, 0 for layouts)")
    p.add_argument("--frames", type=pos_int, default=20,
                   help="frames per sequence (at most 36000, and at most 3600 s of simulated time)")
    p.add_argument("--seed", type=nonneg_int, default=0, help="root random seed")
    p.add_argument("--frame-rate", type=pos_float, default=10.0, help="recording rate [Hz]")
    p.add_argument("--transition", default="none", choices=["none", "onset", "clearing", "bank"],
                   help="weather change along the sequence")
    p.add_argument("--plot", type=out_path, default=None,
                   help="write a top-down picture (.png, .pdf or .svg) of the last frame (a directory when --context all)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(run=run)


def format_scenes(result: dict) -> str:
    lines = []
    for r in result.get("contexts", {}).values() if "contexts" in result else [result]:
        lines.append(f"{r['context']} (layout {r['layout']}, severity {r['severity']}): "
                     f"{r['frames']} frames in {r['seconds']} s ({r['scenes_per_second']} scenes/s)")
        lines.append("  actors per frame: " + ", ".join(f"{k} {v}" for k, v in r["actors_per_class"].items()))
        lines.append("  structures: " + ", ".join(f"{k} {v}" for k, v in r["structures"].items()))
        w = r["weather_last"]
        lines.append(
            f"  weather: visibility {w['visibility_m']} m, rain {w['rain_mm_h']} mm/h, snow {w['snow_mm_h']} mm/h, "
            f"film {w['water_film_mm']} mm, {w['illuminance_lux']} lx, lens {w['lens_coverage_pct']} %"
        )
        if r.get("plot"):
            lines.append(f"  picture: {r['plot']}")
    return "\n".join(lines)


def run(args) -> int:
    from sim.scenario import CONTEXT_NAMES, Context, ScenarioSpec
    from study.outputs import check_writable_dir, check_writable_file

    contexts = list(CONTEXT_NAMES) if args.context == "all" else [args.context]
    specs = []
    for c in contexts:
        ctx = Context.parse(c)
        sev = args.severity if args.severity is not None else (3 if ctx.conditions else 0)
        if not ctx.conditions and args.context == "all":
            sev = 0
        specs.append(ScenarioSpec(context=c, severity=sev, seed=args.seed, frames=args.frames,
                                  frame_rate_hz=args.frame_rate, transition=args.transition))
    plots = {}
    if args.plot:
        if len(specs) > 1:
            out = check_writable_dir(args.plot)
            plots = {s.context: out / f"scene_{Context.parse(s.context).name.replace('+', '_')}.png" for s in specs}
        else:
            plots = {specs[0].context: check_writable_file(args.plot, IMAGE_SUFFIXES)}
    from study.experiments.scenes import simulate_scenes

    results = {}
    for spec in specs:
        r = simulate_scenes(spec, plots.get(spec.context))
        results[r["context"]] = r
    result = next(iter(results.values())) if len(results) == 1 else {"contexts": results}
    emit(result, args.json, format_scenes)
    return 0
