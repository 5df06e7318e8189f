"""A rule gate from outside: per sample, which branches to fuse, from what the car's weather sensors read.

    python examples/weather_gate.py --export DIR --out selection.json [--adverse radar] [--clear lidar]

The simplest gate of `hydrabench score --selection`: a JSON object, sample token -> list of branch
names. It reads, per sample, the weather the export records with it (`sample["hydrabench"]["weather"]`
through the devkit: what a visibility meter and a rain sensor on the car would measure, not the
scenario's label) and chooses `--adverse` when the visibility is below --visibility-m or anything
falls (rain or snow), else `--clear`. Branch names are the NAMEs given to `hydrabench score
--nuscenes NAME=FILE`.

The same rule as gates of hydrabench's gate protocol (docs/nuscenes.md, "Score your own gate"), called
per frame with what a car measures:

    hydrabench score DATA --export DIR --nuscenes lidar=lidar.json --nuscenes radar=radar.json \
        --gate weather=examples.weather_gate:switch_to_radar --gate weather_add=examples.weather_gate:add_radar

(run from the repository root, where `examples` imports).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from classical_common import DetectorError, load_nuscenes, split_samples, write_json  # noqa: E402

VISIBILITY_M = 1000.0  # below this the air is fog (the meteorological definition)


def adverse(weather: dict, visibility_m: float = VISIBILITY_M) -> bool:
    """Whether a sample's weather (visibility_m, rain_mm_h, snow_mm_h) is fog, rain or snow."""
    return (weather["visibility_m"] < visibility_m or weather["rain_mm_h"] > 0.0
            or weather["snow_mm_h"] > 0.0)


def switch_to_radar(frame) -> list[str]:
    """A gate (study.experiments.gate_protocol.GateFrame in): the radar in fog, rain or snow, the lidar otherwise."""
    return ["radar"] if adverse(frame.weather) else ["lidar"]


def add_radar(frame) -> list[str]:
    """A gate: the lidar and the radar in fog, rain or snow, the lidar alone otherwise."""
    return ["lidar", "radar"] if adverse(frame.weather) else ["lidar"]


def selection(nusc, samples: list[dict], clear: list[str], bad: list[str], visibility_m: float) -> dict:
    """{sample token: branches} for `samples`."""
    out = {}
    for s in samples:
        weather = (s.get("hydrabench") or {}).get("weather")
        if not weather:
            raise DetectorError(f"sample {s['token']}: no weather record (sample['hydrabench']['weather']): this "
                                "gate reads a hydrabench export's weather")
        out[s["token"]] = list(bad if adverse(weather, visibility_m) else clear)
    return out


def branches(text: str) -> list[str]:
    names = [b for b in text.split(",") if b]
    if not names and text:
        raise argparse.ArgumentTypeError(f"expected comma-separated branch names, got {text!r}")
    return names


def build() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.strip(),
                                epilog="example:\n  python examples/weather_gate.py --export data-ns --out gate.json\n"
                                       "  hydrabench score data --export data-ns --nuscenes lidar=lidar.json "
                                       "--nuscenes radar=radar.json --selection weather=gate.json",
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--export", type=Path, required=True, metavar="DIR", help="a nuScenes export (hydrabench export nuscenes)")
    p.add_argument("--out", type=Path, required=True, metavar="FILE.json", help="the selection file to write")
    p.add_argument("--clear", type=branches, default=["lidar"], help="branches in clear air, comma-separated [lidar]")
    p.add_argument("--adverse", type=branches, default=["radar"],
                   help="branches in fog, rain or snow, comma-separated ('' for none) [radar]")
    p.add_argument("--visibility-m", type=float, default=VISIBILITY_M, help=f"fog below this [{VISIBILITY_M:g}]")
    p.add_argument("--version", default=None, help="the tables' folder (default: the only v1.0-* folder in DIR)")
    p.add_argument("--split", default=None, help="only this split's samples (default: every sample)")
    return p


def main(argv=None) -> int:
    args = build().parse_args(argv)
    try:
        nusc = load_nuscenes(args.export, args.version)
        chosen = selection(nusc, split_samples(nusc, args.split), args.clear, args.adverse, args.visibility_m)
    except DetectorError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    write_json(args.out, chosen)
    bad = sum(v == args.adverse for v in chosen.values())
    print(f"weather_gate: {len(chosen)} samples, {bad} in fog, rain or snow -> {args.adverse}, the rest -> "
          f"{args.clear}; wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
