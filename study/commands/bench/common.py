"""What several `hydrabench bench` families share: the training-bench options (`bench amp`,
`bench profile`), their `--model` overrides and a bench module's docstring as a description."""

from __future__ import annotations

from study.cli import dataset_dir, int_range, name_arg, name_list, nonneg_int


def add_training_bench_args(p, steps_help: str, data_help: str) -> None:
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


def parse_model_args(args) -> dict:
    from fusion.nets.profile import parse_model_overrides

    return parse_model_overrides(args.model)


def format_bench_doc(module: str) -> str:
    import importlib

    return importlib.import_module(module).__doc__
