"""`hydrabench bench profile`: where one training step's time goes, per part of the network.

One network of a model profile (its branches, initial weights from `seed`) trains `warmup + steps`
SGD steps on the same frames (synthetic, or a dataset's first frames as training reads them). In
each timed step:

- forward, per part: every stem, and in every branch the merge conv, layer2, layer3, layer4, the
  neck, the RPN (head, anchors, proposals and its losses), RoIAlign, the box head, the box
  predictor, and the rest of the RoI heads (sampling, losses); wall time between a module's forward
  pre-hook and its forward hook, summed over branches. CPU execution is synchronous, so each span
  is that module's own work;
- backward as a whole, and the optimiser step;
- data: the time to read and collate the step's frames from the dataset (`--data` only).

One more step runs under `torch.profiler` and splits the backward pass by autograd node kind
(convolution, RoIAlign, linear, normalisation, the rest), by each node's total CPU time.

Reported: the median over the timed steps of each part in ms and as % of the step, the feature
map size each branch's layer2..4 runs at, and the CPU. Hooks add a few microseconds per module
call; the step time beside them is measured in the same steps.
"""

from __future__ import annotations

import statistics
import time
from collections import defaultdict

from study.bench.amp import bench_setup, dataset_batch, synthetic_batch
from study.bench.scale import cpu_model

PARTS = ("stems", "merge", "layer2", "layer3", "layer4", "neck", "rpn", "roi_align", "box_head", "box_predictor",
         "roi_heads_rest")
"""The forward parts, in the order data flows through them."""

BACKWARD_KINDS = (("convolution", ("convolution",)), ("roi_align", ("roialign", "roi_align")),
                  ("linear", ("addmm", "mmbackward", "linear")), ("normalisation", ("groupnorm", "batchnorm")))
"""Autograd node names (lower-case substrings) per backward kind; anything else is "rest"."""
NODE = "autograd::engine::evaluate_function: "
"""How torch.profiler names the run of one autograd node (its total covers the node's kernels)."""


class _Timer:
    """Forward pre-hooks and hooks that sum the wall time of each named part."""

    def __init__(self) -> None:
        self.open: dict[int, float] = {}
        self.total: dict[str, float] = defaultdict(float)
        self.handles = []

    def watch(self, module, part: str) -> None:
        if module is None:
            return
        key = id(module)

        def pre(_m, _a):
            self.open[key] = time.perf_counter()

        def post(_m, _a, _o):
            self.total[part] += time.perf_counter() - self.open.pop(key)

        self.handles += [module.register_forward_pre_hook(pre), module.register_forward_hook(post)]

    def reset(self) -> None:
        self.total = defaultdict(float)

    def remove(self) -> None:
        for h in self.handles:
            h.remove()


def _watch_model(model, timer: _Timer) -> None:
    for stem in model.stems.values():
        timer.watch(stem, "stems")
    for b in model.branches.values():
        for part in ("merge", "layer2", "layer3", "layer4", "neck", "rpn"):
            timer.watch(getattr(b, part, None), part)
        rh = b.roi_heads
        timer.watch(rh, "_roi_heads")
        timer.watch(rh.box_roi_pool, "roi_align")
        timer.watch(rh.box_head, "box_head")
        timer.watch(rh.box_predictor, "box_predictor")


def _backward_kinds(prof) -> dict[str, float]:
    """CPU seconds of the backward pass's autograd nodes per kind (BACKWARD_KINDS, "rest"): each
    node's total time (its kernels included; nodes run one after another, they do not nest)."""
    out: dict[str, float] = defaultdict(float)
    for ev in prof.key_averages():
        if not ev.key.startswith(NODE):
            continue
        name = ev.key[len(NODE):].lower()
        kind = next((k for k, subs in BACKWARD_KINDS if any(s in name for s in subs)), "rest")
        out[kind] += ev.cpu_time_total / 1e6
    return dict(out)


def bench_profile(profile: str = "cpu", branches: tuple[str, ...] = (), batch: int = 4, steps: int = 3,
                  warmup: int = 1, threads: int = 0, seed: int = 0, lr: float = 2e-3, precision: str = "fp32",
                  data: str | None = None, overrides: dict | None = None) -> dict:
    """The profile of a training step (module docstring) -> a JSON-able dict. `precision`: "fp32" or
    "bf16" (autocast of the backbones, as `hydrabench train --amp`)."""
    import torch

    from fusion.nets import build_hydrafusion
    from sim.errors import UserError
    from study.engine.device import DeviceSetup, default_threads

    if precision not in ("fp32", "bf16"):
        raise UserError(f"--precision must be fp32 or bf16, got {precision!r}")
    prof, specs = bench_setup("profile", profile, branches, steps, warmup, batch, overrides)
    before = torch.get_num_threads()
    n_threads = threads or default_threads()
    torch.set_num_threads(n_threads)
    timer = _Timer()
    try:
        torch.manual_seed(seed)
        model = build_hydrafusion(profile=prof, branches=specs).train()
        opt = torch.optim.SGD(model.parameters(), lr=lr, momentum=0.9, weight_decay=1e-4)
        setup = DeviceSetup("cpu", n_threads, precision == "bf16")
        t0 = time.perf_counter()
        inputs, targets = dataset_batch(model, data, batch) if data else synthetic_batch(model, batch, seed)
        data_s = time.perf_counter() - t0 if data else None
        _watch_model(model, timer)
        rows: list[dict] = []
        sizes: dict[str, dict] = {}

        shape_handles = [getattr(b, part).register_forward_hook(
            lambda _m, _a, out, n=n, part=part: sizes.setdefault(n, {}).__setitem__(part, list(out.shape[-2:])))
            for n, b in model.branches.items() for part in ("layer2", "layer3", "layer4")]
        for k in range(warmup + steps + 1):
            torch.manual_seed(seed + k)
            timer.reset()
            profiled = k == warmup + steps
            ctx = torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) if profiled else None
            if ctx is not None:
                ctx.__enter__()
            t_step = time.perf_counter()
            with setup.autocast():
                losses = model(inputs, targets)
            t_fwd = time.perf_counter()
            opt.zero_grad(set_to_none=True)
            losses["total"].backward()
            t_bwd = time.perf_counter()
            opt.step()
            t_end = time.perf_counter()
            if ctx is not None:
                ctx.__exit__(None, None, None)
                backward_kinds = _backward_kinds(ctx)
                continue
            if not torch.isfinite(losses["total"]):
                raise UserError(f"bench profile: non-finite loss at step {k} (lower --lr)")
            if k < warmup:
                continue
            t = dict(timer.total)
            rest = t.pop("_roi_heads", 0.0) - sum(t.get(p, 0.0) for p in ("roi_align", "box_head", "box_predictor"))
            row = {p: t.get(p, 0.0) for p in PARTS if p != "roi_heads_rest"}
            row["roi_heads_rest"] = max(rest, 0.0)
            row["forward_other"] = max((t_fwd - t_step) - sum(row.values()), 0.0)
            row["forward"] = t_fwd - t_step
            row["backward"] = t_bwd - t_fwd
            row["optimiser"] = t_end - t_bwd
            row["step"] = t_end - t_step
            rows.append(row)
        for h in shape_handles:
            h.remove()
    finally:
        timer.remove()
        torch.set_num_threads(before)
    med = {key: statistics.median(r[key] for r in rows) for key in rows[0]}
    step = med["step"]
    parts = [*PARTS, "forward_other", "backward", "optimiser"]
    bw_total = sum(backward_kinds.values()) or 1.0
    return {
        "cpu": cpu_model(), "threads": n_threads, "profile": profile, "branches": [b.name for b in specs],
        "precision": precision, "batch": batch, "steps": steps, "warmup_steps": warmup,
        "frames": "dataset " + str(data) if data else "synthetic",
        "step_ms": round(1000 * step, 1),
        "forward_ms": round(1000 * med["forward"], 1),
        "parts_ms": {p: round(1000 * med[p], 1) for p in parts},
        "parts_pct": {p: round(100 * med[p] / step, 1) for p in parts},
        "backward_by_kind_pct": {k: round(100 * v / bw_total, 1) for k, v in sorted(backward_kinds.items())},
        "data_ms": None if data_s is None else round(1000 * data_s, 1),
        "feature_map_hw": sizes,
        "note": "median over the timed steps; forward parts by module hooks (summed over branches), backward "
                "split by autograd node kind in one extra profiled step (node total CPU time)",
    }
