"""`hydrabench bench inference`: latency, peak memory and training speed per model configuration (`study.bench.nets`)."""

from __future__ import annotations

from study.bench.pipeline import machine
from study.cli import (
    Formatter,
    emit,
    name_arg,
    nonneg_float,
    out_file,
    pos_float,
    pos_int,
    training_run,
)
from study.commands.device import add_device_args


def add_parser(what) -> None:
    n = what.add_parser("inference", help="latency, peak memory and training speed per model configuration",
                        description="HydraFusion Table 4 on this CPU: latency (median, batch 1 and 8) and peak "
                        "resident memory of single-sensor, early-fusion, late-fusion, three-branch and seven-branch "
                        "configurations (each in a fresh process), training images per second per branch, the "
                        "late-fusion block against ensemble-boxes, each gate's overhead (gate_overhead_ms) and the "
                        "end-to-end latency of top-k HydraFusion with it, k = 1, 3, 5 (topk_latency_ms).",
                        formatter_class=Formatter)
    n.add_argument("--profile", type=name_arg, default="cpu", help="model profile")
    n.add_argument("--repeats", type=pos_int, default=5, help="timed forwards per configuration")
    n.add_argument("--run", dest="weights", type=training_run, default=None, metavar="RUN",
                   help="load this trained run's weights (default: random initialisation)")
    add_device_args(n, workers=False)
    n.add_argument("--energy-window-s", type=pos_float, default=3.0, help="on a GPU: the shortest window of repeated "
                   "batch-1 forwards over which NVML's energy counter is read [s] (it moves in 20-100 ms steps)")
    n.add_argument("--energy-warmup-s", type=nonneg_float, default=2.0, help="on a GPU: forwards before the energy "
                   "window, so the clocks have risen [s]")
    n.add_argument("--partial", type=out_file(".json"), default=None, metavar="FILE",
                   help="rewrite this JSON file with the figures measured so far after each measurement task, so a run "
                   "stopped part-way (a time budget) keeps every latency, memory and energy figure it took")
    n.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    n.set_defaults(run=run_inference)


def run_inference(args) -> int:
    from fusion.nets import load_profile
    from study.bench.boxes import bench_box_fusion
    from study.bench.nets import bench_inference
    from study.engine.device import resolve_device

    load_profile(args.profile)  # an unknown profile is refused before any worker process starts
    setup = resolve_device(args, apply=False)  # each measurement runs in a fresh process, which applies it
    partial = None
    if args.partial:
        from study.outputs import write_json_atomic

        def partial(figures):
            write_json_atomic(args.partial, {**figures, **machine(), "complete": False})

    r = bench_inference(args.profile, args.repeats, setup.threads, args.weights, device=setup.device, amp=setup.amp,
                        energy_window_s=args.energy_window_s, energy_warmup_s=args.energy_warmup_s, on_result=partial)
    boxes = bench_box_fusion(repeats=10)
    r["fusion_block_vs_ensemble_boxes"] = {m: {"ours_ms": v["ours_ms"], "ensemble_boxes_ms": v["ensemble_boxes_ms"],
                                               "speedup": v["speedup"], "equal_output": v["equal_output"]}
                                           for m, v in boxes["methods"].items()}
    r.update(machine())

    def text(r):
        lines = [f"device {r.get('device', 'cpu')} (amp {r.get('amp', False)})",
                 f"{'configuration':28s} {'batch 1 [ms]':>12s} {'batch 8 [ms/frame]':>18s} {'peak RSS [MB]':>13s}"
                 + (f" {'peak GPU [MB]':>13s} {'energy [J/frame]':>16s}" if "peak_gpu_mb" in r else "")]
        for name, ms in r["latency_ms"].items():
            gpu = ""
            if "peak_gpu_mb" in r:
                e = r["energy_j_per_frame"][name]
                gpu = f" {r['peak_gpu_mb'][name]:13.0f} {e if e is not None else '-':>16}"
            lines.append(f"{name:28s} {ms:12.1f} {r['latency_ms_per_frame_batch_8'].get(name, float('nan')):18.1f} "
                         f"{r['peak_rss_mb'][name]:13.0f}" + gpu)
        lines.append(f"ratio_top3_to_all {r['ratio_top3_to_all']} (worst case, three early-fusion branches: "
                     f"{r['ratio_top3_worst_to_all']})")
        for name, gains in r.get("batch8_gain_per_op_kind", {}).items():
            share = r["op_share_batch_1"][name]
            lines.append(f"  {name}: batch-8 gain per operator kind (share of batch-1 time): " + ", ".join(
                f"{k} {g}x ({100 * share[k]:.0f} %)" for k, g in gains.items()))
        lines.append("training images/s per branch: " + ", ".join(f"{k} {v:.2f}" for k, v in r["training_images_per_second"].items()))
        lines.append("gate overhead [ms]: " + ", ".join(
            f"{g} {v}" if v is not None else f"{g} - (needs ground truth)" for g, v in r["gate_overhead_ms"].items())
            + f"; all stems {r['stems_ms']} ms")
        for g, per in r["topk_latency_ms"].items():
            lines.append(f"top-k with the {g} gate [ms]: " + ", ".join(f"k={k} {v}" for k, v in per.items())
                         + f" (overhead {100 * r['gate_overhead_share_of_top3'].get(g, float('nan')):.2f} % of top-3)")
        lines.append("fusion block vs ensemble-boxes: " + ", ".join(
            f"{m} x{v['speedup']}" for m, v in r["fusion_block_vs_ensemble_boxes"].items()))
        return "\n".join(lines)

    if args.partial:
        from study.outputs import write_json_atomic

        write_json_atomic(args.partial, {**r, "complete": True})
    emit(r, args.json, text)
    return 0
