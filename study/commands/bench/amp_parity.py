"""`hydrabench bench amp-parity`: mAP parity of bf16 training (`study.bench.amp.amp_parity`)."""

from __future__ import annotations

from study.bench.pipeline import machine
from study.cli import (
    Formatter,
    dataset_dir,
    emit,
    int_range,
    name_arg,
    name_list,
    nonneg_int,
    out_dir,
    pos_float,
)


def add_parser(what) -> None:
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
    ap.add_argument("--model", action="append", default=None, metavar="KEY=VALUE",
                    help="override a model-profile field for both runs, repeatable, as `train --model` (width=0.5, ...)")
    ap.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    ap.set_defaults(run=run_amp_parity)


def _amp_parity_doc() -> str:
    from study.bench.amp import amp_parity

    return " ".join(amp_parity.__doc__.split("\n\n")[0].split())


def run_amp_parity(args) -> int:
    from study.bench.amp import amp_parity

    r = amp_parity(str(args.data), args.out, args.profile, tuple(args.branches), epochs=args.epochs,
                   batch=args.batch_size, lr=args.lr, warmup=args.warmup_steps, threads=args.threads, seed=args.seed,
                   bootstrap=args.bootstrap, model_overrides=tuple(args.model or ()))
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
