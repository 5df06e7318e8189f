"""`hydrabench bench <what>`: throughput measurements (`study.bench`). Figures go to BENCHMARKS.md by
hand, with the command that produced them; nothing here asserts a time."""

from __future__ import annotations

import argparse

from study.bench.pipeline import machine
from study.cli import (
    Formatter,
    dataset_dir,
    emit,
    float_range,
    int_list,
    int_range,
    name_arg,
    name_list,
    nonneg_float,
    nonneg_int,
    out_dir,
    out_file,
    pos_float,
    pos_int,
    training_run,
)
from study.commands.device import add_device_args


def parts_arg(text: str) -> tuple[str, ...]:
    """An argparse type: comma-separated parts of `bench scale` (train, ddp, generate), each once."""
    from study.bench.scale import PARTS

    items = name_list(text)
    bad = [p for p in items if p not in PARTS]
    if bad:
        raise argparse.ArgumentTypeError(f"unknown part {bad[0]!r} (choose from: {', '.join(PARTS)})")
    return items


parts_arg.kind = "names"


def start_methods_arg(text: str) -> tuple:
    """An argparse type: comma-separated pool start methods (auto, fork, spawn), each once; auto -> None."""
    import multiprocessing as mp

    items = name_list(text)
    known = ["auto", *(m for m in ("fork", "spawn") if m in mp.get_all_start_methods())]
    bad = [m for m in items if m not in known]
    if bad:
        raise argparse.ArgumentTypeError(f"unknown start method {bad[0]!r} (choose from: {', '.join(known)})")
    return tuple(None if m == "auto" else m for m in items)


start_methods_arg.kind = "names"


def checkouts_arg(text: str) -> tuple:
    """An argparse type: comma-separated directories of other hydrabench checkouts, each once."""
    items = tuple(t.strip() for t in text.split(","))
    if not all(items):
        raise argparse.ArgumentTypeError(f"expected directories separated by commas, got {text!r}")
    if len(set(items)) != len(items):
        raise argparse.ArgumentTypeError(f"{text!r} names a directory twice")
    return items


checkouts_arg.kind = "names"


def add_parser(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=help_text, formatter_class=Formatter)
    what = p.add_subparsers(dest="what", metavar="<what>", parser_class=type(p))
    what.required = True
    s = what.add_parser("sim", help="scene steps per second per context (one core)",
                        description="Simulate each context for --frames frames after its setup and "
                        "report steady-state scene steps per second (one process, one core).",
                        formatter_class=Formatter)
    s.add_argument("--frames", type=pos_int, default=200, help="recorded frames per context")
    s.add_argument("--seed", type=nonneg_int, default=0, help="root random seed")
    s.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    s.set_defaults(run=run_sim)
    g = what.add_parser("generate", help="full frames per second (cameras, lidar, radar, labels, degradation)",
                        description="Generate a temporary dataset over every context for each profile and "
                        "worker count, and report frames per second plus milliseconds per pipeline component "
                        "and per degradation model (summed over workers, per rendered frame).",
                        formatter_class=Formatter)
    g.add_argument("--profiles", type=name_list, default="cpu,paper", help="comma-separated sensor profiles, each once")
    g.add_argument("--workers", type=int_list(1, 256, "workers"), default="1,2", help="comma-separated worker counts, each once")
    g.add_argument("--frames-per-context", type=pos_int, default=10, help="frames per context per run")
    g.add_argument("--sequence-length", type=pos_int, default=10, help="frames per sequence (setup is amortised over it)")
    g.add_argument("--seed", type=nonneg_int, default=0, help="root random seed")
    g.add_argument("--start-methods", type=start_methods_arg, default="auto",
                   help="comma-separated ways the worker pool starts its processes, each once: auto (fork "
                   "unless this process has rendered), fork, spawn; with two or more, ratios of frames/s "
                   "against the first are reported")
    g.add_argument("--rounds", type=int_range(1, 100, "rounds"), default=1,
                   help="repeat every combination this many times, in turn (A B A B), so that drifting "
                   "machine speed slows each alike")
    g.add_argument("--twins", action="store_true",
                   help="also render each frame's clear-weather twin, as the study presets do (frames/s counts a "
                   "frame and its twin once)")
    g.add_argument("--against", type=checkouts_arg, default=(), metavar="DIR[,DIR]",
                   help="compare with other hydrabench checkouts (e.g. `git worktree add /tmp/old COMMIT`): "
                   "every run is then `python -m study.cli generate --contexts all ... --json` from each checkout "
                   "in turn (this code first) for --rounds rounds; reports each one's median frames/s, this "
                   "code's ratio to it, and whether its dataset had the same bytes")
    g.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    g.set_defaults(run=run_generate)
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
    n.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    n.set_defaults(run=run_inference)
    a = what.add_parser("amp", help="training step time fp32 against bf16 autocast on this CPU, side by side",
                        description="Two copies of one network (same profile, branches, initial weights and frames) "
                        "train a few SGD steps, fp32 and bf16 autocast interleaved step by step; reports the median "
                        "step time of each, the speed-up, the losses after the same steps, and whether this CPU has "
                        "native bf16 (AMX-BF16 / AVX512-BF16), which is what --amp auto picks by.",
                        formatter_class=Formatter)
    _training_bench_args(a, "timed steps of each precision", "train on this dataset's first frames (default: "
                         "synthetic frames)")
    a.set_defaults(run=run_amp)
    ap = what.add_parser("amp-parity", help="mAP parity of bf16 training: the same run trained in fp32 and in bf16, "
                         "both scored on its test split with a paired interval", description=_amp_parity_doc(),
                         formatter_class=Formatter)
    ap.add_argument("data", type=dataset_dir, help="dataset to train on (split by sequence as train does)")
    ap.add_argument("--out", required=True, type=out_dir, help="directory of the two runs (out/fp32, out/bf16; a "
                    "second call resumes them)")
    ap.add_argument("--profile", type=name_arg, default="cpu", help="model profile")
    ap.add_argument("--branches", type=name_list, default=("radar",), help="comma-separated branches of the paper set")
    ap.add_argument("--epochs", type=int_range(1, 1000, "epochs"), default=2, help="passes over the training split")
    ap.add_argument("--batch-size", type=int_range(1, 64, "batch-size"), default=4, help="frames per step")
    ap.add_argument("--lr", type=pos_float, default=0.02, help="SGD learning rate (the cpu study's)")
    ap.add_argument("--warmup-steps", type=int_range(0, 100000, "warmup-steps"), default=60,
                    help="steps of linear lr warm-up (the cpu study's)")
    ap.add_argument("--bootstrap", type=int_range(0, 10000, "bootstrap"), default=200,
                    help="draws of whole test sequences for the interval of bf16 - fp32 (0: none)")
    ap.add_argument("--threads", type=nonneg_int, default=0, help="torch CPU threads (0: the cores available)")
    ap.add_argument("--seed", type=nonneg_int, default=0, help="initial weights and data order of both runs")
    ap.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    ap.set_defaults(run=run_amp_parity)
    pr = what.add_parser("profile", help="where one training step's time goes: stems, layer2-4, RPN, RoIAlign, box head, "
                         "backward, optimiser", description=_doc("study.bench.step_profile"), formatter_class=Formatter)
    _training_bench_args(pr, "timed steps", "train on this dataset's first frames and time reading them (default: "
                         "synthetic frames)")
    pr.add_argument("--precision", choices=("fp32", "bf16"), default="fp32",
                    help="fp32, or bf16 autocast of the backbones (as train --amp)")
    pr.set_defaults(run=run_profile)
    rc = what.add_parser("recipe", help="training recipes and cost options judged by held-out vehicle mAP per "
                         "CPU-hour, with their curves", description=_doc("study.bench.recipe"), formatter_class=Formatter)
    rc.add_argument("data", type=dataset_dir, help="dataset to train on (the runs' gate split is the held-out set)")
    rc.add_argument("--out", required=True, type=out_dir, help="directory of the candidate runs (a second call resumes)")
    rc.add_argument("--branch", type=name_arg, default="lidar", help="the branch every candidate trains")
    rc.add_argument("--epochs", type=int_range(1, 100, "epochs"), default=3, help="epochs of every candidate")
    rc.add_argument("--candidate", action="append", default=None, metavar="NAME:FIELD=VALUE[+FIELD=VALUE]",
                    help="a candidate (repeatable): what differs from the base recipe (lr, warmup_steps, clip_grad, "
                    "hflip, lr_drop_epoch, epochs, model=KEY=VALUE); default: base, lr 0.04, hflip 0.5, bev stride 16, 64 RoIs")
    rc.add_argument("--bootstrap", type=int_range(0, 10000, "bootstrap"), default=200,
                    help="draws of whole held-out sequences for the last epoch's intervals (0: none)")
    rc.add_argument("--aim", type=float_range(0.0, 1.0, "aim", lo_open=True), default=None, metavar="MAP",
                    help="a held-out vehicle mAP to reach: where each curve reaches it, and if none does, the "
                    "budget frontier's log-linear extrapolation (candidates differing in epochs=N trace the frontier)")
    rc.add_argument("--threads", type=nonneg_int, default=0, help="torch CPU threads (0: the cores available)")
    rc.add_argument("--plot", type=out_file(".png", ".pdf", ".svg"), default=None, help="draw the curves")
    rc.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    rc.set_defaults(run=run_recipe)
    ar = what.add_parser("arch", help="training-step time of the model's cost options (width, dilation, channels_last, "
                         "stride, RoIs), fp32 and bf16, side by side", description=_doc("study.bench.arch"),
                         formatter_class=Formatter)
    ar.add_argument("--profile", type=name_arg, default="cpu", help="model profile")
    ar.add_argument("--branches", type=name_list, default=(), help="comma-separated branches (default: the profile's)")
    ar.add_argument("--variant", action="append", default=None, metavar="NAME:KEY=VALUE[+KEY=VALUE]",
                    help="a variant (repeatable; the first is the base, 'base:' for none); default: base, width 0.5, "
                    "width 0.25, channels_last, dilation, bev stride 16, 64 RoIs, width 0.5 + channels_last")
    ar.add_argument("--precisions", type=name_list, default="fp32,bf16", help="fp32 and/or bf16")
    ar.add_argument("--batch-size", type=int_range(1, 64, "batch-size"), default=4, help="frames per step")
    ar.add_argument("--steps", type=int_range(1, 1000, "steps"), default=3, help="timed steps per variant and precision")
    ar.add_argument("--warmup", type=int_range(0, 100, "warmup"), default=1, help="untimed steps first")
    ar.add_argument("--threads", type=nonneg_int, default=0, help="torch CPU threads (0: the cores available)")
    ar.add_argument("--seed", type=nonneg_int, default=0, help="initial weights, frames and sampling")
    ar.add_argument("--data", type=dataset_dir, default=None, metavar="DATASET",
                    help="train on this dataset's first frames (default: synthetic frames)")
    ar.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    ar.set_defaults(run=run_arch)
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
    c = what.add_parser("scale", help="training images/s at 1 and 2 threads, DDP 2 processes vs 1, generate local pool vs Ray",
                        description="In one run, back to back on a small dataset it generates (or --data): CPU "
                        "training images/s of `hydrabench train` at --threads 1 and 2; DDP with 2 gloo processes "
                        "(torchrun on 127.0.0.1, 1 thread each) against 1 process at 2 threads with the same global "
                        "batch (step time, images/s, and the largest difference of their final weights); and "
                        "`generate` frames/s with the local process pool against --backend ray (a local Ray started "
                        "and stopped by the command; skipped, with the reason, when Ray cannot start). Reports the "
                        "ratios, the machine and its load average before and after; training times are the steps "
                        "of the last epoch (metrics.csv train_seconds), each run a fresh process.",
                        formatter_class=Formatter)
    c.add_argument("--parts", type=parts_arg, default="train,ddp,generate",
                   help="comma-separated parts to measure: train (1 vs 2 threads), ddp (2 processes vs 1), "
                   "generate (local pool vs Ray)")
    c.add_argument("--data", type=dataset_dir, default=None, metavar="DATASET",
                   help="train on this cpu-profile dataset (default: the local-pool dataset of part generate, "
                   "or one generated for the run with --contexts etc.)")
    c.add_argument("--contexts", type=name_list, default=("all",),
                   help="'all' or comma-separated contexts of the generated dataset [all]")
    c.add_argument("--frames-per-context", type=int_range(1, 1000, "frames-per-context"), default=2,
                   help="frames per context of the generated dataset, at most 1000")
    c.add_argument("--sequence-length", type=int_range(1, 1000, "sequence-length"), default=2,
                   help="frames per sequence (one sequence per context: every frame trains, no evaluation between)")
    c.add_argument("--seed", type=nonneg_int, default=0, help="seed of the generated dataset and of the training runs")
    c.add_argument("--branches", type=name_list, default=("radar",),
                   help="comma-separated branches to train (cpu model profile) [radar]")
    c.add_argument("--batch-size", type=int_range(2, 1024, "batch-size"), default=4,
                   help="frames per SGD step, the global batch of the DDP run (2 to 1024)")
    c.add_argument("--epochs", type=int_range(1, 100, "epochs"), default=1,
                   help="epochs per training run, the last one timed (2: the first absorbs warm-up), at most 100")
    c.add_argument("--workers", type=int_range(1, 256, "workers"), default=2,
                   help="local pool processes and Ray CPUs of part generate, at most 256")
    c.add_argument("--plot", type=out_file(".png"), default=None, metavar="PNG", help="also draw the ratios into this PNG file")
    c.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    c.set_defaults(run=run_scale)


def run_sim(args) -> int:
    from study.bench.pipeline import bench_sim

    result = bench_sim(frames=args.frames, seed=args.seed)
    emit(result, args.json, lambda r: "\n".join(
        [f"{c:9s} {v:8.1f} scenes/s  (setup {r['setup_seconds'][c]:.2f} s incl. warm-up)"
         for c, v in r["scenes_per_second"].items()]))
    return 0


def run_generate(args) -> int:
    from study.bench.pipeline import bench_generate

    if args.against:
        return _run_generate_against(args)
    result = bench_generate(profiles=args.profiles, workers=args.workers, frames_per_context=args.frames_per_context,
                            sequence_length=args.sequence_length, seed=args.seed, start_methods=args.start_methods,
                            rounds=args.rounds, twins=args.twins)

    def text(r):
        lines = [f"{x['profile']:6s} workers {x['workers']} ({x['start_method']}, round {x['round'] + 1}): "
                 f"{x['frames_per_second']} frames/s ({x['frames']} frames in {x['seconds']} s)" for x in r["runs"]]
        for key, ratio in r["ratios"].items():
            lines.append(f"{key} frames/s relative to {next(iter(ratio))}: "
                         + ", ".join(f"{m} {v}" for m, v in ratio.items()))
        for p, ms in r["ms_per_component"].items():
            lines.append(f"{p} ms per frame: " + ", ".join(f"{k} {v}" for k, v in ms.items() if not k.startswith("degrade/")))
            d = r["degradation"][p]
            lines.append(f"{p} degradation {d['ms_total']} ms ({d['share_of_frame']} of a frame): "
                         + ", ".join(f"{k} {v}" for k, v in d["ms_per_model"].items()))
        return "\n".join(lines)

    emit(result, args.json, text)
    return 0


def _run_generate_against(args) -> int:
    import sys

    from sim.errors import UserError
    from study.bench.pipeline import bench_generate_against, checkout_of

    if args.start_methods != (None,):
        raise UserError("--against compares checkouts with their default start method; leave out --start-methods")
    for c in args.against:
        checkout_of(c)  # a wrong directory is refused before the first run

    def progress(x):
        print(f"bench generate: round {x['round'] + 1}/{args.rounds} {x['profile']} workers {x['workers']} "
              f"{x['commit'] or x['dir']}: {x['frames_per_second']} frames/s ({x['frames']} frames in "
              f"{x['seconds']} s)", file=sys.stderr, flush=True)

    result = bench_generate_against(args.against, profiles=args.profiles, workers=args.workers,
                                    frames_per_context=args.frames_per_context, sequence_length=args.sequence_length,
                                    seed=args.seed, rounds=args.rounds, twins=args.twins, progress=progress)

    def text(r):
        names = {s["dir"]: s["commit"] or s["dir"] for s in [r["this"], *r["against"]]}
        lines = [f"round {x['round'] + 1} {x['profile']} workers {x['workers']} {names[x['dir']]}: "
                 f"{x['frames_per_second']} frames/s ({x['frames']} frames in {x['seconds']} s)"
                 + ("" if x["dir"] == r["this"]["dir"] else f", same bytes: {x['same_bytes']}") for x in r["runs"]]
        for key, ratio in r["ratios"].items():
            lines.append(f"{key}: this code ({names[r['this']['dir']]}) frames/s over "
                         + ", ".join(f"{names[d]}'s: {v}" for d, v in ratio.items()) + " (medians)")
        return "\n".join(lines)

    emit(result, args.json, text)
    return 0


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


def run_amp(args) -> int:
    from study.bench.amp import bench_amp

    r = bench_amp(args.profile, tuple(args.branches), batch=args.batch_size, steps=args.steps, warmup=args.warmup,
                  threads=args.threads, seed=args.seed, data=str(args.data) if args.data else None,
                  overrides=_model_overrides(args))
    r["model_overrides"] = list(args.model or ())
    r.update(machine())
    emit(r, args.json, lambda r: "\n".join([
        f"{r['cpu'] or 'CPU'}, {r['threads']} threads; {r['profile']} profile, {', '.join(r['branches'])} "
        f"({r['parameters_m']} M parameters), batch {r['batch']}, {r['frames']} frames",
        f"native bf16: {r['native_bf16']} ({r['native_bf16_reason']}); --amp auto picks {r['amp_auto_picks']}",
        f"step time fp32 {r['step_s']['fp32']} s, bf16 {r['step_s']['bf16']} s: x{r['speedup_bf16']} "
        f"(median of {r['steps']} steps each, interleaved)",
        "loss per step fp32 " + ", ".join(map(str, r["loss_per_step"]["fp32"]))
        + "; bf16 " + ", ".join(map(str, r["loss_per_step"]["bf16"]))]))
    return 0


def _amp_parity_doc() -> str:
    from study.bench.amp import amp_parity

    return " ".join(amp_parity.__doc__.split("\n\n")[0].split())


def run_amp_parity(args) -> int:
    from study.bench.amp import amp_parity

    r = amp_parity(str(args.data), args.out, args.profile, tuple(args.branches), epochs=args.epochs,
                   batch=args.batch_size, lr=args.lr, warmup=args.warmup_steps, threads=args.threads, seed=args.seed,
                   bootstrap=args.bootstrap)
    r.update(machine())

    def text(r):
        lines = [f"{r['cpu'] or 'CPU'}, {r['threads']} threads; native bf16: {r['native_bf16']} "
                 f"({r['native_bf16_reason']}); {r['profile']} profile, {', '.join(r['branches'])}, {r['epochs']} "
                 f"epoch(s), {r['test_frames']} test frames"]
        for p, run in r["runs"].items():
            per = ", ".join(f"{b} vehicle mAP {v['map_vehicles']} (all classes {v['map']})" for b, v in run["branches"].items())
            lines.append(f"{p}: {per}; trained {run['train_seconds']} s, loss per epoch {run['loss_total_per_epoch']}")
        for b in r["branches"]:
            iv = (r["ci95_vehicle_map"].get(b) or {}).get("bf16_minus_fp32")
            if iv:
                lines.append(f"{b}: bf16 - fp32 vehicle mAP 95 % interval [{iv[0]:+.3f}, {iv[1]:+.3f}] "
                             f"({r['bootstrap']} draws of {r['ci95_vehicle_map']['sequences']} test sequences)")
        return "\n".join(lines)

    emit(r, args.json, text)
    return 0


def _training_bench_args(p, steps_help: str, data_help: str) -> None:
    """The options `bench amp` and `bench profile` share: the network, the frames, the steps."""
    p.add_argument("--profile", type=name_arg, default="cpu", help="model profile")
    p.add_argument("--branches", type=name_list, default=(), help="comma-separated branches (default: the profile's)")
    p.add_argument("--batch-size", type=int_range(1, 64, "batch-size"), default=4, help="frames per step")
    p.add_argument("--steps", type=int_range(1, 1000, "steps"), default=3, help=steps_help)
    p.add_argument("--warmup", type=int_range(0, 100, "warmup"), default=1, help="untimed steps first")
    p.add_argument("--threads", type=nonneg_int, default=0, help="torch CPU threads (0: the cores available)")
    p.add_argument("--seed", type=nonneg_int, default=0, help="initial weights, frames and sampling")
    p.add_argument("--data", type=dataset_dir, default=None, metavar="DATASET", help=data_help)
    p.add_argument("--model", action="append", default=None, metavar="KEY=VALUE",
                   help="override a model-profile field, repeatable, as `train --model` (width=0.5, dilation=true, "
                   "channels_last=true, bev.output_stride=16, box_batch_size_per_image=64, ...)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")


def _model_overrides(args) -> dict:
    from fusion.nets.profile import parse_model_overrides

    return parse_model_overrides(args.model)


def _doc(module: str) -> str:
    import importlib

    return importlib.import_module(module).__doc__


def run_recipe(args) -> int:
    from sim.errors import UserError
    from study.bench.recipe import bench_recipe, parse_candidate, plot_recipe

    cands = dict(parse_candidate(c) for c in args.candidate) if args.candidate else None
    if args.candidate and len(cands) != len(args.candidate):
        raise UserError("--candidate: each name once")
    r = bench_recipe(str(args.data), args.out, args.branch, cands, epochs=args.epochs, threads=args.threads,
                     bootstrap=args.bootstrap, aim=args.aim)
    r.update(machine())
    if args.plot:
        plot_recipe(r, args.plot)
        r["plot"] = str(args.plot)

    def text(r):
        lines = [f"{r['cpu'] or 'CPU'}, {r['threads']} threads; {r['branch']} branch, {r['epochs']} epochs each; "
                 f"held out: {r['held_out']['frames']} gate-split frames; budget {r['budget_core_hours']} core-hours",
                 f"{'candidate':16s} {'core-h':>7s} {'veh. mAP':>8s} {'at budget':>9s}  per epoch"]
        for name, c in r["candidates"].items():
            last = c["curve"][-1]
            lines.append(f"{name:16s} {last['core_hours']:7.3f} {last['map_vehicles'] or 0:8.3f} "
                         f"{c['map_vehicles_at_budget']:9.3f}  " + " ".join(f"{p['map_vehicles'] or 0:.3f}" for p in c["curve"]))
        lines.append(f"chosen: {r['chosen']} ({r['rule']})")
        a = r.get("aim")
        if a and a["reached"]:
            stays = a["per_candidate_stays_from_core_hours"][a["by"]]
            lines.append(f"aim {a['map_vehicles']:g}: reached at {a['core_hours']} core-hours ({a['by']})"
                         + (f", stays reached from {stays}" if stays is not None else ", falls back below it"))
        elif a:
            guess = (f"; at the frontier's last gain of {a['gain_per_doubling']:+.3f} per doubling it would be reached "
                     f"near {a['extrapolated_core_hours']} core-hours (extrapolated)") if "extrapolated_core_hours" in a else ""
            lines.append(f"aim {a['map_vehicles']:g}: not reached (best {a['best_map_vehicles']:.3f} at "
                         f"{a['best_core_hours']} core-hours){guess}")
        return "\n".join(lines)

    emit(r, args.json, text)
    return 0


def run_arch(args) -> int:
    from sim.errors import UserError
    from study.bench.arch import bench_arch, parse_variant

    variants = dict(parse_variant(v) for v in args.variant) if args.variant else None
    if args.variant and len(variants) != len(args.variant):
        raise UserError("--variant: each name once")
    precisions = tuple(args.precisions if not isinstance(args.precisions, str) else args.precisions.split(","))
    r = bench_arch(args.profile, tuple(args.branches), variants, precisions, batch=args.batch_size, steps=args.steps,
                   warmup=args.warmup, threads=args.threads, seed=args.seed,
                   data=str(args.data) if args.data else None)
    r.update(machine())

    def text(r):
        ps = r["precisions"]
        lines = [f"{r['cpu'] or 'CPU'}, {r['threads']} threads; {r['profile']} profile, {', '.join(r['branches'])}, "
                 f"batch {r['batch']}, {r['frames']} frames, median of {r['steps']} steps; ratios against "
                 f"{r['base']!r} in the same run",
                 f"{'variant':28s} {'M params':>8s} {'fp16 MiB':>8s} " + " ".join(f"{p + ' s':>8s} {'x':>5s}" for p in ps)]
        for name, v in r["variants"].items():
            lines.append(f"{name:28s} {v['parameters_m']:8.1f} {v['float16_mib']:8.1f} " + " ".join(
                f"{v['step_s'][p]:8.3f} {v['speedup_vs_base'][p]:5.2f}" for p in ps))
        return "\n".join(lines)

    emit(r, args.json, text)
    return 0


def run_profile(args) -> int:
    from study.bench.step_profile import bench_profile

    r = bench_profile(args.profile, tuple(args.branches), batch=args.batch_size, steps=args.steps, warmup=args.warmup,
                      threads=args.threads, seed=args.seed, precision=args.precision,
                      data=str(args.data) if args.data else None, overrides=_model_overrides(args))
    r["model_overrides"] = list(args.model or ())
    r.update(machine())

    def text(r):
        lines = [f"{r['cpu'] or 'CPU'}, {r['threads']} threads; {r['profile']} profile, {', '.join(r['branches'])}, "
                 f"batch {r['batch']}, {r['precision']}, {r['frames']} frames: step {r['step_ms']} ms "
                 f"(median of {r['steps']})"]
        for p, ms in r["parts_ms"].items():
            lines.append(f"  {p:16s} {ms:9.1f} ms  {r['parts_pct'][p]:5.1f} %")
        lines.append("  backward by kind: " + ", ".join(f"{k} {v} %" for k, v in r["backward_by_kind_pct"].items()))
        if r["data_ms"] is not None:
            lines.append(f"  data (read + collate, outside the step) {r['data_ms']} ms")
        lines.append("  layer2/3/4 feature maps (H, W): " + "; ".join(
            f"{b} " + " ".join(f"{k} {v[0]}x{v[1]}" for k, v in s.items()) for b, s in r["feature_map_hw"].items()))
        return "\n".join(lines)

    emit(r, args.json, text)
    return 0


def run_inference(args) -> int:
    from fusion.nets import load_profile
    from study.bench.boxes import bench_box_fusion
    from study.bench.nets import bench_inference
    from study.device import resolve_device

    load_profile(args.profile)  # an unknown profile is refused before any worker process starts
    setup = resolve_device(args, apply=False)  # each measurement runs in a fresh process, which applies it
    r = bench_inference(args.profile, args.repeats, setup.threads, args.weights, device=setup.device, amp=setup.amp,
                        energy_window_s=args.energy_window_s, energy_warmup_s=args.energy_warmup_s)
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

    emit(r, args.json, text)
    return 0


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


def run_scale(args) -> int:
    from study.bench.scale import ScaleConfig, bench_scale, check, plot_scale, text_table
    from study.outputs import check_writable_file

    cfg = ScaleConfig(parts=tuple(args.parts), data=args.data, contexts=tuple(args.contexts),
                      frames_per_context=args.frames_per_context, sequence_length=args.sequence_length, seed=args.seed,
                      branches=tuple(args.branches), batch_size=args.batch_size, epochs=args.epochs, workers=args.workers)
    check(cfg)  # everything refusable is refused before any work
    plot = check_writable_file(args.plot, (".png",)) if args.plot else None
    r = bench_scale(cfg)
    if plot is not None:
        plot_scale(r, plot)
    r["plot"] = str(plot) if plot is not None else None
    emit(r, args.json, text_table)
    return 0
