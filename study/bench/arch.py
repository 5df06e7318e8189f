"""`hydrabench bench arch`: training-step time of the model profile's cost options, side by side.

Each variant is the same network (profile, branches, frames, initial weights from `seed`) with some
`--model` overrides (`fusion.nets.profile.parse_model_overrides`): width (layer2-4 channels),
dilation, channels_last, output stride, sampled RoIs. Every variant takes its SGD steps (forward +
backward + SGD) in each precision, round-robin over the variants so that a change of the machine's
load touches all of them alike; after `warmup` untimed steps per model, the median step time of each
variant and precision, and its ratio to the first variant (the base) measured in the same run.
Also each variant's parameter count and float16 weight size. Step time is not the whole answer: a
cut that loses mAP is judged by vehicle mAP per CPU-hour (BENCHMARKS.md), not here.
"""

from __future__ import annotations

import statistics

from study.bench.amp import bench_setup, dataset_batch, synthetic_batch, train_step
from study.bench.scale import cpu_model

DEFAULT_VARIANTS: dict[str, tuple[str, ...]] = {
    "base": (),
    "width 0.5": ("width=0.5",),
    "width 0.25": ("width=0.25",),
    "channels_last": ("channels_last=true",),
    "dilation": ("dilation=true",),
    "bev stride 16": ("bev.output_stride=16",),
    "64 RoIs": ("box_batch_size_per_image=64",),
    "width 0.5 + channels_last": ("width=0.5", "channels_last=true"),
}
"""Name -> `--model` overrides; the first is the base every ratio is against."""


def parse_variant(text: str) -> tuple[str, tuple[str, ...]]:
    """'NAME:KEY=VALUE+KEY=VALUE' (or 'NAME:' for no override) -> (name, overrides)."""
    from sim.errors import UserError

    name, colon, rest = str(text).partition(":")
    if not colon or not name.strip():
        raise UserError(f"--variant {text!r}: expected NAME:KEY=VALUE[+KEY=VALUE...], e.g. narrow:width=0.5")
    return name.strip(), tuple(x for x in rest.split("+") if x.strip())


def bench_arch(profile: str = "cpu", branches: tuple[str, ...] = (), variants: dict | None = None,
               precisions: tuple[str, ...] = ("fp32", "bf16"), batch: int = 4, steps: int = 3, warmup: int = 1,
               threads: int = 0, seed: int = 0, lr: float = 2e-3, data: str | None = None,
               overrides: dict | None = None) -> dict:
    """The comparison of the module docstring -> a JSON-able dict. `overrides`: ModelProfile fields
    under every variant (tests use a tiny network)."""
    import numpy as np
    import torch

    from fusion.nets import build_hydrafusion
    from fusion.nets.profile import deep_merge, parse_model_overrides
    from sim.errors import UserError
    from study.engine.device import default_threads, native_bf16

    variants = dict(variants or DEFAULT_VARIANTS)
    if not variants:
        raise UserError("bench arch: no variant")
    bad = [p for p in precisions if p not in ("fp32", "bf16")]
    if bad or not precisions:
        raise UserError(f"--precisions: fp32 and/or bf16, got {','.join(precisions) or 'none'}")
    setups = {name: bench_setup("arch", profile, branches, steps, warmup, batch,
                                deep_merge(overrides or {}, parse_model_overrides(ov)))
              for name, ov in variants.items()}
    before = torch.get_num_threads()
    n_threads = threads or default_threads()
    torch.set_num_threads(n_threads)
    models, opts, batches, info = {}, {}, {}, {}
    try:
        for name, (prof, specs) in setups.items():
            for p in precisions:
                torch.manual_seed(seed)
                m = build_hydrafusion(profile=prof, branches=specs).train()
                models[name, p] = m
                opts[name, p] = torch.optim.SGD(m.parameters(), lr=lr, momentum=0.9, weight_decay=1e-4)
            m = models[name, precisions[0]]
            batches[name] = dataset_batch(m, data, batch) if data else synthetic_batch(m, batch, seed)
            n = sum(t.numel() for t in m.parameters())
            info[name] = {"overrides": list(variants[name]), "parameters_m": round(n / 1e6, 2),
                          "float16_mib": round(2 * n / 2**20, 1)}
        seconds = {key: [] for key in models}
        final = {}
        names = list(variants)
        for k in range(warmup + steps):
            order = names[k % len(names):] + names[:k % len(names)]  # rotate: no variant always first
            for name in order:
                inputs, targets = batches[name]
                for p in precisions:
                    s, lo = train_step(models[name, p], opts[name, p], inputs, targets, p, seed + k)
                    if not np.isfinite(lo):
                        raise UserError(f"bench arch: non-finite {p} loss of {name!r} at step {k} (lower --lr)")
                    final[name, p] = round(lo, 4)
                    if k >= warmup:
                        seconds[name, p].append(s)
    finally:
        torch.set_num_threads(before)
    base = names[0]
    med = {key: statistics.median(v) for key, v in seconds.items()}
    rows = {}
    for name in names:
        rows[name] = {**info[name],
                      "step_s": {p: round(med[name, p], 3) for p in precisions},
                      "step_s_all": {p: [round(x, 3) for x in seconds[name, p]] for p in precisions},
                      "speedup_vs_base": {p: round(med[base, p] / med[name, p], 2) for p in precisions},
                      "speedup_vs_base_fp32": {p: round(med[base, precisions[0]] / med[name, p], 2) for p in precisions},
                      "loss_after_steps": {p: final[name, p] for p in precisions}}
    native, why = native_bf16("cpu")
    return {
        "cpu": cpu_model(), "threads": n_threads, "profile": profile,
        "branches": [b.name for b in setups[base][1]], "batch": batch, "steps": steps, "warmup_steps": warmup,
        "frames": "dataset " + str(data) if data else "synthetic", "precisions": list(precisions),
        "native_bf16": native, "native_bf16_reason": why, "base": base, "variants": rows,
        "note": "median step time (forward + backward + SGD) after the warm-up steps; variants round-robin, each "
                "ratio against the base measured in the same run; speedup_vs_base_fp32 is against the base in "
                f"{precisions[0]}",
    }
