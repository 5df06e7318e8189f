"""Do bootstrap intervals of a per-context mAP cover? A synthetic detection problem whose population
AP is known, and a coverage experiment over many independent samples of it.

The problem (`SyntheticDetection`): sequences of frames; a sequence has a difficulty d ~ N(0, sd^2)
and a traffic density (gamma, mean 1) that all its frames share, so frames within a sequence are
correlated as in the study's test sets. Per frame and class, objects ~ Poisson(rate x density); a
method detects an object when its detection noise e ~ N(0, 1) is below ``margin + offset_c - d``
(recall Phi(margin + offset_c - d) < 1) and scores it ``mu - slope d + N(0, 1)``; false positives per
frame ~ Poisson(fp_c x scale x exp(fp_slope d)) scored N(0, 1). Two methods see the same objects with
noises correlated by `shared` (a paired difference is correlated through shared frames).

Its population AP (`SyntheticDetection.true_ap`) is the AP of the expected precision-recall curve,
the limit of a pooled AP over ever more sequences: at a score threshold t, the expected true
positives per object are ``R(t) = E_d[Phi(margin + offset - d) Phi(mu - slope d - t)]`` (Gauss-Hermite
quadrature over d, exact to ~1e-12) and the false positives per frame ``F(t) = fp exp(fp_slope^2 sd^2
/ 2) Phi(-t)``; precision ``P = rate R / (rate R + F)``, and AP is the all-point sum of the recall
steps times the precision envelope (trapezoid) over a fine grid of t (1e-6; tested against a
binormal integral and against 60 000 frames).

The experiment (`coverage_experiment`): for each number of sequences n (one context of a test set),
draw `trials` independent samples, and on each the sequence bootstrap (`fusion.intervals.design_draws`
over the n sequences, scored exactly by `fusion.metrics.DrawScorer`) of a method's mAP and of a
paired difference, turned into an interval by each of `INTERVAL_METHODS`; count how often each holds
the population value (`count_coverage`), where the estimate sits in it, and what biases the estimate
and the draws carry (`diagnostics`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from fusion.intervals import map_intervals
from fusion.metrics import DrawScorer, ImageMatches


@dataclass(frozen=True)
class ClassSpec:
    """One class of the synthetic problem: `rate` objects per frame (mean, before the sequence's
    density), `offset` added to every method's detection margin (negative: harder to find), `fp`
    false positives per frame at d = 0 (before a method's `fp_scale`)."""

    name: str
    rate: float
    offset: float
    fp: float


@dataclass(frozen=True)
class MethodSpec:
    """One detector: `margin` of detection (recall Phi(margin + offset - d)), `mu` the mean score of
    a true positive at d = 0 (false positives score N(0, 1)), `fp_scale` on every class's false
    positives."""

    name: str
    margin: float
    mu: float
    fp_scale: float = 1.0


DEFAULT_CLASSES = (ClassSpec("car", 1.5, 0.5, 0.6), ClassSpec("van", 0.5, 0.0, 0.3),
                   ClassSpec("truck", 0.25, -0.3, 0.2), ClassSpec("bus", 0.12, -0.5, 0.15))
"""Four vehicle classes of falling frequency, as the study's vehicle mAP (car, van, truck, bus):
with 6 sequences of 3 frames a context holds about 2 buses, and none in about one sample of 10."""

ALL_CLASSES = DEFAULT_CLASSES + (ClassSpec("motorbike", 0.03, -1.0, 0.1), ClassSpec("bicycle", 0.03, -1.2, 0.1),
                                 ClassSpec("pedestrian", 0.6, -0.2, 0.4),
                                 ClassSpec("group_of_pedestrians", 0.02, -1.5, 0.1))
"""The study's eight classes (its per-context intervals score "all"): the vehicles, and rare, hard
two-wheelers and groups; 48 sequences of 3 frames hold about 4 of each, in a few sequences."""

CLASS_SETS = {"vehicles": DEFAULT_CLASSES, "all": ALL_CLASSES}
"""Named class sets of `SyntheticDetection` (`hydrabench bench coverage --classes`)."""

DEFAULT_METHODS = (MethodSpec("late", 0.6, 1.6), MethodSpec("all_branches", 0.8, 1.8, 0.9))
"""Two detectors of the same frames, the second a little better (the difference the verdict reads)."""


@dataclass(frozen=True)
class SyntheticDetection:
    """The synthetic problem (module docstring): `frames_per_sequence` frames share a sequence's
    difficulty d ~ N(0, `difficulty_sd`^2) and density ~ Gamma(`density_shape`, 1 / shape); a true
    positive's mean score falls by `score_slope` per unit d, false positives multiply by
    exp(`fp_slope` d); `shared` is the correlation of the two methods' detection and score noise on
    one object."""

    classes: tuple = DEFAULT_CLASSES
    methods: tuple = DEFAULT_METHODS
    frames_per_sequence: int = 3
    difficulty_sd: float = 0.8
    score_slope: float = 0.5
    fp_slope: float = 0.5
    density_shape: float = 4.0
    shared: float = 0.7
    _cache: dict = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        if not self.classes or not self.methods:
            raise ValueError("SyntheticDetection: needs at least one class and one method")
        if len({m.name for m in self.methods}) != len(self.methods):
            raise ValueError("SyntheticDetection: method names must differ")
        if self.frames_per_sequence < 1 or self.difficulty_sd < 0 or self.density_shape <= 0:
            raise ValueError("SyntheticDetection: frames_per_sequence >= 1, difficulty_sd >= 0, density_shape > 0")
        if not 0.0 <= self.shared <= 1.0:
            raise ValueError(f"SyntheticDetection: shared must be in [0, 1], got {self.shared!r}")
        for c in self.classes:
            if c.rate <= 0 or c.fp < 0:
                raise ValueError(f"SyntheticDetection: class {c.name!r} needs rate > 0 and fp >= 0")

    def method(self, name: str) -> MethodSpec:
        for m in self.methods:
            if m.name == name:
                return m
        raise ValueError(f"no method {name!r}; have {[m.name for m in self.methods]}")

    def true_ap(self, method: str, cls: int, grid: int = 40001, nodes: int = 80) -> float:
        """Population AP of class index `cls` (0-based) for `method` (module docstring): the expected
        precision-recall curve on `grid` score thresholds, the difficulty integrated by `nodes`-point
        Gauss-Hermite quadrature."""
        from scipy.stats import norm

        key = (method, cls, grid, nodes)
        if key in self._cache:
            return self._cache[key]
        m, c = self.method(method), self.classes[cls]
        x, w = np.polynomial.hermite_e.hermegauss(nodes)
        d, w = self.difficulty_sd * x, w / math.sqrt(2.0 * math.pi)  # E_d[f(d)] = sum w f(d)
        mu = m.mu - self.score_slope * d
        t = np.linspace(float(mu.max()) + 12.0, -12.0, grid)  # descending: recall rises along t
        recall = (w * norm.cdf(m.margin + c.offset - d)) @ norm.cdf(mu[:, None] - t[None, :])  # R(t)
        fp = c.fp * m.fp_scale * math.exp((self.fp_slope * self.difficulty_sd) ** 2 / 2.0) * norm.cdf(-t)  # F(t)
        tp = c.rate * recall
        precision = np.divide(tp, tp + fp, out=np.ones_like(tp), where=tp + fp > 0)
        envelope = np.maximum.accumulate(precision[::-1])[::-1]  # max precision at recall >= R(t)
        mid = 0.5 * (envelope + np.r_[envelope[0], envelope[:-1]])  # trapezoid: error O(grid^-2)
        ap = float(np.sum(np.diff(np.r_[0.0, recall]) * mid))
        self._cache[key] = ap
        return ap

    def true_map(self, method: str) -> float:
        """Population mAP of `method`: the mean of its classes' population APs."""
        return float(np.mean([self.true_ap(method, k) for k in range(len(self.classes))]))

    def sample(self, n_sequences: int, rng: np.random.Generator) -> dict[str, ImageMatches]:
        """{method: ImageMatches} of `n_sequences` new sequences (images numbered sequence by
        sequence, `frames_per_sequence` each; class ids 1..K), drawn from `rng`."""
        if n_sequences < 1:
            raise ValueError(f"n_sequences must be >= 1, got {n_sequences!r}")
        f, n_img = self.frames_per_sequence, n_sequences * self.frames_per_sequence
        d = rng.normal(0.0, self.difficulty_sd, n_sequences)
        density = rng.gamma(self.density_shape, 1.0 / self.density_shape, n_sequences)
        rho, own = self.shared, math.sqrt(1.0 - self.shared ** 2)
        rows: dict[str, list] = {m.name: [{} for _ in range(n_img)] for m in self.methods}
        for k, c in enumerate(self.classes):
            counts = rng.poisson(c.rate * np.repeat(density, f))
            image = np.repeat(np.arange(n_img), counts)
            d_obj = d[image // f]
            e_shared, s_shared = rng.normal(size=len(image)), rng.normal(size=len(image))
            for m in self.methods:
                found = rho * e_shared + own * rng.normal(size=len(image)) < m.margin + c.offset - d_obj
                score = m.mu - self.score_slope * d_obj + rho * s_shared + own * rng.normal(size=len(image))
                n_fp = rng.poisson(c.fp * m.fp_scale * np.exp(self.fp_slope * np.repeat(d, f)))
                fp_image = np.repeat(np.arange(n_img), n_fp)
                img = np.r_[image[found], fp_image]
                sc = np.r_[score[found], rng.normal(size=len(fp_image))]
                tp = np.r_[np.ones(int(found.sum()), bool), np.zeros(len(fp_image), bool)]
                order = np.lexsort((-sc, img))  # by image, then score descending
                img, sc, tp = img[order], sc[order], tp[order]
                cut = np.searchsorted(img, np.arange(n_img + 1))
                for i in range(n_img):
                    rows[m.name][i][k + 1] = (sc[cut[i]:cut[i + 1]], tp[cut[i]:cut[i + 1]], int(counts[i]))
        classes = tuple(range(1, len(self.classes) + 1))
        return {name: ImageMatches(r, classes, "all") for name, r in rows.items()}


INTERVAL_METHODS = ("percentile", "basic", "bca", "studentized", "jackknife", "percentile_rescaled", "bca_rescaled")
"""The intervals the experiment compares: `fusion.intervals.INTERVALS` on draws of n of the n
sequences (the study's per-context draws; "jackknife" uses no draw), and the percentile and BCa intervals on draws of n - 1
of them (Rao and Wu's rescaled bootstrap, `fusion.intervals.DESIGNS` "rescaled")."""


def count_coverage(intervals: Sequence, truth: float, estimates: Sequence[float] | None = None) -> dict:
    """How often `intervals` [(lo, hi) or None, one per trial] hold `truth`: covered, trials,
    coverage with its binomial standard error sqrt(p (1 - p) / trials), misses below (truth < lo:
    the interval sits high) and above, failures (no interval, counted as not covering), mean width,
    and with `estimates` the median relative position (estimate - lo) / (hi - lo) (0.5: central)."""
    n = len(intervals)
    if not n:
        raise ValueError("count_coverage: no trial")
    ok = [iv for iv in intervals if iv is not None and math.isfinite(iv[0]) and math.isfinite(iv[1])]
    covered = sum(lo <= truth <= hi for lo, hi in ok)
    p = covered / n
    out = {"covered": int(covered), "trials": n, "coverage": p, "se": math.sqrt(p * (1.0 - p) / n),
           "miss_low": int(sum(truth < lo for lo, _ in ok)), "miss_high": int(sum(truth > hi for _, hi in ok)),
           "failed": n - len(ok), "mean_width": float(np.mean([hi - lo for lo, hi in ok])) if ok else None,
           "median_width": float(np.median([hi - lo for lo, hi in ok])) if ok else None}
    if estimates is not None:
        pos = [(e - iv[0]) / (iv[1] - iv[0]) for e, iv in zip(estimates, intervals)
               if iv is not None and iv[1] > iv[0] and math.isfinite(e)]
        out["median_position"] = float(np.median(pos)) if pos else None
    return out


def trial(model: SyntheticDetection, n_sequences: int, resamples: int, seed: int,
          pair: tuple[str, str] | None = None, level: float = 0.95, studentized: bool = True) -> dict:
    """One sample of `n_sequences` sequences (seeded) and, per quantity (the first method's mAP, the
    second's minus the first's), its estimate, the draws' mean and median, and each of
    `INTERVAL_METHODS`' interval (`fusion.intervals.map_intervals`; "studentized" only when
    `studentized`); and each class's AP of the first method: estimate, draws' mean, share of draws
    without its ground truth."""
    a, b = pair or (model.methods[0].name, model.methods[-1].name)
    rng = np.random.default_rng(seed)
    matches = model.sample(n_sequences, rng)
    f = model.frames_per_sequence
    by = {"context": {j: list(range(j * f, (j + 1) * f)) for j in range(n_sequences)}}
    scorers = {n: DrawScorer(m) for n, m in matches.items()}
    plain = ("percentile", "basic", "bca", "jackknife") + (("studentized",) if studentized else ())
    one = map_intervals(matches, by, resamples, seed + 1, plain, "sequence", [(b, a)], scorers, level, keep_draws=True)
    resc = map_intervals(matches, by, resamples, seed + 2, ("percentile", "bca"), "rescaled", [(b, a)], scorers, level)
    out: dict = {"quantities": {}}
    for q, key in ((f"map:{a}", a), (f"difference:{b} - {a}", f"{b} - {a}")):
        d = one["draws"][:, one["columns"].index(key)]
        iv = {m: one["intervals"][m][key] for m in plain}
        iv.update({f"{m}_rescaled": resc["intervals"][m][key] for m in ("percentile", "bca")})
        out["quantities"][q] = {"estimate": one["estimate"][key], "draw_mean": float(np.nanmean(d)),
                                "draw_median": float(np.nanmedian(d)),
                                "intervals": {m: iv[m] for m in INTERVAL_METHODS if m in iv}}
    stat = one["statistic"]
    ca_est, ca_draw = stat.class_ap(a, np.ones((1, n_sequences), np.int64))[0], stat.class_ap(a, one["counts"])
    seen = np.isfinite(ca_draw)
    total = np.where(seen, ca_draw, 0.0).sum(axis=0)
    out["class_ap"] = {"estimate": ca_est.tolist(),
                       "draw_mean": np.divide(total, seen.sum(axis=0), out=np.full(len(total), np.nan),
                                              where=seen.any(axis=0)).tolist(),
                       "draw_absent": (~seen).mean(axis=0).tolist()}
    return out


def coverage_experiment(model: SyntheticDetection, sequences: Sequence[int] = (6, 12, 24), trials: int = 200,
                        resamples: int = 400, seed: int = 0, level: float = 0.95, studentized: bool = True,
                        progress: Callable[[int], None] | None = None) -> dict:
    """Per number of sequences n: `trials` independent samples (trial seeds derived from `seed`, n
    and the trial), each with `resamples` draws; per quantity (the first method's mAP, the last's
    minus the first's) the population value, each interval's `count_coverage`, and `diagnostics`.
    `progress(k)` is called after each trial."""
    if trials < 2 or resamples < 10:
        raise ValueError("coverage_experiment: trials >= 2, resamples >= 10")
    if not sequences or any(int(n) < 2 for n in sequences):
        raise ValueError(f"coverage_experiment: sequences per context must be >= 2, got {list(sequences)!r}")
    a, b = model.methods[0].name, model.methods[-1].name
    truth = {f"map:{a}": model.true_map(a), f"difference:{b} - {a}": model.true_map(b) - model.true_map(a)}
    true_class = [model.true_ap(a, k) for k in range(len(model.classes))]
    out: dict = {"level": level, "trials": trials, "resamples": resamples, "seed": seed,
                 "frames_per_sequence": model.frames_per_sequence, "truth": truth,
                 "true_class_ap": {c.name: ap for c, ap in zip(model.classes, true_class)}, "by_sequences": {}}
    for n in sequences:
        runs = []
        for t in range(trials):
            runs.append(trial(model, int(n), resamples, seed * 1_000_003 + int(n) * 10_007 + 7 * t, (a, b), level,
                              studentized))
            if progress is not None:
                progress(1)
        rec = out["by_sequences"][str(n)] = {"quantities": {}}
        for q, th in truth.items():
            est = [r["quantities"][q]["estimate"] for r in runs]
            methods = [m for m in INTERVAL_METHODS if m in runs[0]["quantities"][q]["intervals"]]
            rec["quantities"][q] = {
                "truth": th,
                "coverage": {m: count_coverage([r["quantities"][q]["intervals"][m] for r in runs], th, est)
                             for m in methods},
                "diagnostics": diagnostics(est, [r["quantities"][q]["draw_mean"] for r in runs],
                                           [r["quantities"][q]["draw_median"] for r in runs], th)}
        rec["class_ap"] = {}
        for k, c in enumerate(model.classes):
            e = np.array([r["class_ap"]["estimate"][k] for r in runs])
            dm = np.array([r["class_ap"]["draw_mean"][k] for r in runs])
            ok = np.isfinite(e) & np.isfinite(dm)
            rec["class_ap"][c.name] = {
                "truth": true_class[k], "absent_share": float(np.mean(~np.isfinite(e))),
                "mean_estimate": float(np.mean(e[ok])) if ok.any() else None,
                "estimator_bias": float(np.mean(e[ok]) - true_class[k]) if ok.any() else None,
                "bootstrap_bias": float(np.mean(dm[ok] - e[ok])) if ok.any() else None,
                "draw_absent_share": float(np.mean([r["class_ap"]["draw_absent"][k] for r in runs]))}
    return out


def diagnostics(estimates: Sequence[float], draw_means: Sequence[float], draw_medians: Sequence[float],
                truth: float) -> dict:
    """Why an interval sits where it does: the estimator's bias (mean estimate - truth) and spread
    against the bootstrap's bias (mean of draws' mean - estimate) and the share of trials whose draws'
    median lies above the estimate (0.5 when the draws are centred on it; the percentile interval
    sits high when it is above)."""
    e, m, md = (np.asarray(x, float) for x in (estimates, draw_means, draw_medians))
    ok = np.isfinite(e) & np.isfinite(m) & np.isfinite(md)
    e, m, md = e[ok], m[ok], md[ok]
    return {"mean_estimate": float(e.mean()), "estimator_bias": float(e.mean() - truth),
            "estimator_sd": float(e.std(ddof=1)) if len(e) > 1 else None,
            "bootstrap_bias": float(np.mean(m - e)), "draw_median_above_share": float(np.mean(md > e))}
