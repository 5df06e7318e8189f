"""`hydrabench bench boxes`: our NMS / Soft-NMS / WBF against ensemble-boxes (`study.bench.boxes`)."""

from __future__ import annotations

from study.bench.pipeline import machine
from study.cli import (
    Formatter,
    emit,
    int_range,
    nonneg_int,
    pos_int,
)


def add_parser(what) -> None:
    b = what.add_parser("boxes", help="our NMS / Soft-NMS / WBF against ensemble-boxes (ms, speed-up, equal output)",
                        description="Time fusion.boxes against ensemble-boxes 1.0.9 on identical synthetic inputs "
                        "(n lists x n boxes, HydraFusion's IoU 0.4 / skip 0.01 / sigma 0.5), check that compat mode "
                        "returns the package's detections, and measure what the package's deviations do to VOC mAP.",
                        formatter_class=Formatter)
    b.add_argument("--lists", type=int_range(1, 100, "lists"), default=7, help="detection lists (branches), at most 100")
    b.add_argument("--boxes", type=int_range(1, 10_000, "boxes"), default=100, help="boxes per list, at most 10000")
    b.add_argument("--repeats", type=pos_int, default=30, help="calls per timing round")
    b.add_argument("--seed", type=nonneg_int, default=0, help="random seed of the synthetic boxes")
    b.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    b.set_defaults(run=run_boxes)


def run_boxes(args) -> int:
    from study.bench.boxes import bench_box_fusion, compat_map_effect

    timing = bench_box_fusion(n_lists=args.lists, n_boxes=args.boxes, repeats=args.repeats, seed=args.seed)
    effect = compat_map_effect(n_lists=args.lists, n_boxes=args.boxes, seed=args.seed)
    result = {"timing": timing, "compat_map_effect": effect, **machine()}

    def text(r):
        lines = [f"{r['timing']['n_lists']} lists x {r['timing']['n_boxes']} boxes (CPU ms per call, median of rounds)"]
        for m, v in r["timing"]["methods"].items():
            lines.append(f"  {m:8s} ours {v['ours_ms']:.3f} ms  ensemble-boxes {v['ensemble_boxes_ms']:.3f} ms  "
                         f"x{v['speedup']}  equal output: {v['equal_output']}")
        lines.append(f"compat-mode effect on VOC mAP@0.5 (single list alone: {r['compat_map_effect']['single_list_map']}):")
        for m, modes in r["compat_map_effect"]["methods"].items():
            lines.append(f"  {m:8s} textbook {modes['textbook']['no_weights']['map']}  compat {modes['compat']['no_weights']['map']}"
                         f"  compat+equal weights {modes['compat']['equal_weights']['map']}")
        return "\n".join(lines)

    emit(result, args.json, text)
    return 0
