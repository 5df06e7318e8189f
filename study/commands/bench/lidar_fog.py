"""`hydrabench bench lidar-fog`: lidar fog: our model against Hahner et al. ICCV 2021 (`study.bench.lidar_fog`)."""

from __future__ import annotations

from study.bench.pipeline import machine
from study.cli import (
    Formatter,
    emit,
    int_range,
    name_list,
    nonneg_int,
    out_file,
)


def add_parser(what) -> None:
    f = what.add_parser("lidar-fog", help="lidar fog: our model against Hahner et al. ICCV 2021 on the same clean clouds",
                        description="Render clear frames (one short sequence per layout), apply the lidar fog "
                        "models under pure fog at each visibility with the same random streams, and report per "
                        "range bin of the clean return (0-15, 15-30, 30-50, 50-100 m) the fraction of returns kept "
                        "(hard return still detected), replaced by fog points and lost, over all returns and over "
                        "actor returns, for ours, Hahner's model with this sensor's detection, and Hahner's decision "
                        "as written (no point removed); plus fog points on rays without a return, and the apply time "
                        "per frame. Differences over 0.1 in bins holding objects are listed.",
                        formatter_class=Formatter)
    f.add_argument("--visibilities", default="30,50,75,150,300,600", help="comma-separated fog MOR values [m]")
    f.add_argument("--layouts", type=name_list, default=("city", "motorway", "rural", "junction"),
                   help="comma-separated road layouts to render")
    f.add_argument("--frames-per-layout", type=int_range(1, 1000, "frames-per-layout"), default=2,
                   help="clear frames per layout (a 1 Hz sequence), at most 1000")
    f.add_argument("--seed", type=nonneg_int, default=0, help="seed of the scenes and of the fog models' random draws")
    f.add_argument("--plot", type=out_file(".png"), default=None, metavar="PNG",
                   help="also draw the table into this PNG file")
    f.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    f.set_defaults(run=run_lidar_fog)


def run_lidar_fog(args) -> int:
    from sim.errors import UserError
    from study.bench.lidar_fog import LAYOUTS, lidar_fog_comparison, plot_lidar_fog
    from study.outputs import check_writable_file

    try:
        vis = [float(v) for v in args.visibilities.split(",") if v.strip()]
    except ValueError:
        raise UserError(f"--visibilities must be numbers [m] separated by commas, got {args.visibilities!r}") from None
    if not vis or min(vis) <= 0:
        raise UserError(f"--visibilities must list positive visibilities [m], got {args.visibilities!r}")
    layouts = list(args.layouts)
    bad = [t for t in layouts if t not in LAYOUTS]
    if bad or not layouts:
        raise UserError(f"unknown layout {bad[0] if bad else ''!r} in --layouts (choose from: {', '.join(LAYOUTS)})")
    plot = check_writable_file(args.plot) if args.plot else None
    r = lidar_fog_comparison(vis, layouts, frames_per_layout=args.frames_per_layout, seed=args.seed)
    if plot is not None:
        plot_lidar_fog(r, plot)
    r["plot"] = str(plot) if plot is not None else None
    r.update(machine())

    def text(r):
        lines = [f"{r['frames']} clear frames ({', '.join(r['layouts'])}); fractions of clean returns "
                 "kept/fog/lost: ours | hahner (this sensor) | hahner as written (kept/fog)"]
        for row in r["table"]:
            o, h, w = row["ours"], row["hahner"], row["hahner_as_written"]
            if row["returns"] == 0:
                continue
            lines.append(f"MOR {row['visibility_m']:5.0f} m {row['subset']:7s} {row['range_bin_m'][0]:3.0f}-"
                         f"{row['range_bin_m'][1]:3.0f} m (n={row['returns']:6d}): "
                         f"{o['kept']:.2f}/{o['fog']:.2f}/{o['lost']:.2f} | {h['kept']:.2f}/{h['fog']:.2f}/{h['lost']:.2f}"
                         f" | {w['kept']:.2f}/{w['fog']:.2f}")
        lines.append("sky rays with a fog point: " + "; ".join(
            f"{m} " + ", ".join(f"{v}: {x}" for v, x in fr.items()) for m, fr in r["sky_rays"]["fog_fraction"].items()))
        lines.append(f"{len(r['differences'])} object bins differ by > {r['difference_limit']}; apply ms/frame: "
                     + ", ".join(f"{m} {v}" for m, v in r["apply_ms_per_frame"].items()))
        if r["plot"]:
            lines.append(f"plot: {r['plot']}")
        return "\n".join(lines)

    emit(r, args.json, text)
    return 0
