"""Coverage of per-context bootstrap intervals of mAP on a synthetic detection problem whose population
AP is known (`fusion.ap_coverage`): for n sequences per context, many independent samples, each with
the sequence bootstrap the study runs per context, turned into percentile, basic, BCa, studentized, jackknife-t
and rescaled (n - 1 of n) intervals; how often each holds the population value of a method's mAP and of a
paired difference, where the estimate sits in it, and the biases that explain it. Asserts nothing."""

from __future__ import annotations

import time


def bench_coverage(sequences=(6, 12, 24), trials: int = 200, resamples: int = 400, seed: int = 0,
                   level: float = 0.95, frames_per_sequence: int = 3, studentized: bool = True,
                   classes: str = "vehicles", progress: bool = False) -> dict:
    """`fusion.ap_coverage.coverage_experiment` on the default `SyntheticDetection` (with
    `frames_per_sequence` and the class set `classes`, `fusion.ap_coverage.CLASS_SETS`), timed; the result names the interval that covers best at the fewest
    sequences (`best_at_fewest`: closest to `level` among those not below it by more than 2 binomial
    standard errors, per quantity)."""
    from fusion.ap_coverage import CLASS_SETS, SyntheticDetection, coverage_experiment
    from sim.progress import progress as progress_bar

    if classes not in CLASS_SETS:
        raise ValueError(f"classes must be one of {sorted(CLASS_SETS)}, got {classes!r}")
    model = SyntheticDetection(classes=CLASS_SETS[classes], frames_per_sequence=frames_per_sequence)
    t0 = time.perf_counter()
    with progress_bar(total=trials * len(sequences), desc="coverage trials", unit="trial", enabled=progress) as bar:
        r = coverage_experiment(model, tuple(sequences), trials, resamples, seed, level, studentized, bar.update)
    r["seconds"] = round(time.perf_counter() - t0, 1)
    r["model"] = {"class_set": classes, "classes": [c.__dict__ for c in model.classes], "methods": [m.__dict__ for m in model.methods],
                  "difficulty_sd": model.difficulty_sd, "score_slope": model.score_slope, "fp_slope": model.fp_slope,
                  "density_shape": model.density_shape, "shared": model.shared}
    fewest = str(min(sequences))
    r["best_at_fewest"] = {}
    for q, rec in r["by_sequences"][fewest]["quantities"].items():
        fine = {m: c for m, c in rec["coverage"].items() if c["coverage"] >= level - 2 * max(c["se"], 1e-9)}
        pick = min(fine or rec["coverage"], key=lambda m: abs(rec["coverage"][m]["coverage"] - level))
        r["best_at_fewest"][q] = pick
    return r


QUANTITY_LABELS = {"map": "a method's mAP", "difference": "a paired difference"}


def coverage_table(result: dict, quantity: str) -> str:
    """The Markdown table docs/study.md quotes for `quantity` ("map" or "difference": the result's
    quantity of that kind): one row per number of sequences, one cell per interval, "coverage (median
    width)" to 3 decimals, and beside them the estimator's bias (mean estimate - population value),
    the draws' bias (mean of a sample's draws - its estimate) and the median position of the estimate
    in its percentile interval (0.5: central; below: the interval sits high)."""
    key = next(q for q in result["truth"] if q.split(":", 1)[0] == quantity)
    first = next(iter(result["by_sequences"].values()))["quantities"][key]["coverage"]
    methods = list(first)
    lines = ["| sequences | bias | draws' bias | estimate in percentile | " + " | ".join(methods) + " |",
             "|" + "---|" * (4 + len(methods))]
    for n, rec in result["by_sequences"].items():
        q = rec["quantities"][key]
        dg = q["diagnostics"]
        cells = [f"{q['coverage'][m]['coverage']:.3f} ({q['coverage'][m]['median_width']:.2f})" for m in methods]
        pos = q["coverage"]["percentile"]["median_position"]
        lines.append(f"| {n} | {dg['estimator_bias']:+.3f} | {dg['bootstrap_bias']:+.3f} | {pos:.2f} | "
                     + " | ".join(cells) + " |")
    return "\n".join(lines)
