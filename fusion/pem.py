"""Perception error model (PEM): a branch's detections drawn from the ground truth, with a fitted
probability of detection, box error, scores and false alarms (Piazzoni et al., "PEM: Perception Error
Model for Virtual Testing of Autonomous Vehicles", arXiv 2302.11919). Fitted per branch on a network's
detections in the right camera matched to the ground truth; then it stands in for the network.

The family of models (one `BranchPEM` per branch, every part fitted, nothing hand-set):

- **detection**: P(an object is found) = logistic(w . z(x)), z the standardised features `x` of the
  object that the branch's sensors see (`SENSOR_FEATURES`: log lidar points, log radar cells, log
  visible pixels and occlusion for the camera) plus what every branch sees (`COMMON_FEATURES`: range,
  piecewise linear; truncation; class; the weather state: log visibility, log rain and snow rate,
  log illuminance), fitted by ridge-penalised
  maximum likelihood (Newton / IRLS, penalty `RIDGE` on every weight but the intercept).
- **box error** in the right camera: e = (dcx / w, dcy / h, log(w' / w), log(h' / h)) of a found
  object's box (w, h: the true box's width and height), independent Gaussians whose mean and sd are
  fitted per range bin (`RANGE_EDGES`; a bin with under `MIN_BIN` matches uses all of them); drawn
  conditioned on the drawn box matching its object (IoU >= `MATCH_IOU`, by rejection), as the fitted
  errors are of matched boxes only.
- **scores**: a found object's score from the empirical quantiles (`QUANTILES`) of the matched
  detections' scores, per true class (a class with under 3 x `MIN_BIN` matches uses every class's)
  and per tercile of the fitted detection probability within it (so an easy object gets the scores
  easy objects of its class got).
- **class**: the detected class from the fitted confusion matrix of matched pairs (row: true class;
  prior: one correct detection per class).
- **false alarms near an object** (detections matched to no object whose IoU with some true box
  exceeds `NEAR_IOU`: duplicates and boxes placed too far off; most of a network's high-scoring
  false alarms): per object, Poisson with a rate fitted per status (found or missed by the branch:
  near false alarms / objects of that status); each one a fitted near false alarm of that status,
  its error vector e applied to this object's box, its score and class kept.
- **other false alarms**: Poisson per frame, with a rate per context (the maximum-likelihood rate: false alarms / frames; a context not fitted gets the
  pooled rate); each one a fitted false alarm drawn at random, its class and score kept and its box
  (cx / W, cy / H, log w, log h) moved by a Gaussian kernel of Silverman's bandwidth (a kernel
  density estimate of the false alarms' boxes; class and score are drawn jointly with the box, so
  a class whose false alarms score low keeps them low).

Matching (`match`): greedily by falling score, each detection to the unmatched true box of largest
IoU, found when IoU >= `MATCH_IOU`, class-agnostic (a wrong class is a found object with a confused
class, as VOC scoring then sees it: a miss and a false alarm).

Strength (`BranchPEM.sample(..., strength=s)`): s = 1 is the fitted model. A stronger detector
multiplies every object's odds of detection by s (adds ln s to the logit: the measured effect of
each feature is kept), divides the box error's mean and sd by s, and divides both false-alarm rates
by s; scores and classes are unchanged. s < 1 is a weaker one by the same rule.

Errors across branches: besides the features they share, branches find the same objects through
one standard normal per object shared by every branch (a Gaussian copula: `fit_loadings` fits each
branch's loading on it to the observed share of objects two branches both find; each branch's own
detection probability is unchanged). Box errors, scores and false alarms are drawn per branch
independently, and nothing is correlated across the frames of a sequence.

Deterministic: a frame's draws depend only on (seed, frame key, branch), not on the order frames
are drawn in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

MATCH_IOU = 0.5
RIDGE = 1e-2
RANGE_EDGES = (0.0, 15.0, 30.0, 50.0, 80.0, math.inf)
MIN_BIN = 8
QUANTILES = np.linspace(0.0, 1.0, 41)
NUM_CLASSES = 9  # 0 (background) and 1..8 (sim.actors.CLASSES)
MAX_FA_BOXES = 4000
ERROR_TRIES = 8
NEAR_IOU = 0.1

SENSOR_FEATURES = {
    "radar": ("log_radar_cells",),
    "lidar": ("log_lidar_points",),
    "fwd_lidar": ("log_lidar_points",),
    "camera_right": ("log_right_px", "right_occlusion"),
    "camera_left": ("log_left_px",),
}
"""Per sensor, the object features only it sees."""

COMMON_FEATURES = ("range_m", "range_below_10", "range_above_25", "truncation", "log_visibility", "log_rain", "log_snow", "log_illuminance",
                   *(f"class_{c}" for c in range(1, NUM_CLASSES)))
"""What every branch's detection probability reads: the object's range (piecewise linear: hinges at
10 and 25 m, as a network's recall can rise and then fall with range), how much of it is outside
the image, the weather state, and its class (one indicator per class)."""


def branch_features(sensors) -> tuple[str, ...]:
    """The features of a branch with these sensors (`SENSOR_FEATURES` of each, then `COMMON_FEATURES`)."""
    out: list[str] = []
    for s in sensors:
        for f in SENSOR_FEATURES.get(s, ()):
            if f not in out:
                out.append(f)
    return (*out, *COMMON_FEATURES)


def object_table(objects: dict, truth: dict, visible: dict, weather: dict) -> dict:
    """Per-object raw features of one frame: {feature: (n,) array} for the `truth` boxes (the scored
    ground truth in the right camera, with ids), joined by id to the frame's 3D `objects` (labels'
    "objects": lidar points, radar cells, visible pixels) and to `visible` (labels' "camera_right",
    for the occlusion; an object absent there is fully occluded), with the frame's `weather` state."""
    ids = [int(i) for i in truth["ids"]]
    n = len(ids)
    where = {int(a): k for k, a in enumerate(objects["ids"])}
    occl = {int(a): float(o) for a, o in zip(visible.get("ids", []), visible.get("occlusion", []))}

    def col(name):
        return np.array([float(objects[name][where[i]]) if i in where else 0.0 for i in ids], float)

    labels = np.asarray(truth["labels"], int).reshape(n)
    out = {
        "log_radar_cells": np.log1p(col("radar_cells")),
        "log_lidar_points": np.log1p(col("lidar_points")),
        "log_right_px": np.log1p(col("camera_right_px")),
        "log_left_px": np.log1p(col("camera_left_px")) if "camera_left_px" in objects else np.zeros(n),
        "right_occlusion": np.array([occl.get(i, 1.0) for i in ids], float),
        "range_m": np.asarray(truth["distance_m"], float).reshape(n),
        "range_below_10": np.maximum(10.0 - np.asarray(truth["distance_m"], float).reshape(n), 0.0),
        "range_above_25": np.maximum(np.asarray(truth["distance_m"], float).reshape(n) - 25.0, 0.0),
        "truncation": np.asarray(truth.get("truncation", np.zeros(n)), float).reshape(n),
        "log_visibility": np.full(n, math.log(max(float(weather.get("visibility_m", 1e4)), 1.0))),
        "log_rain": np.full(n, math.log1p(float(weather.get("rain_mm_h", 0.0)))),
        "log_snow": np.full(n, math.log1p(float(weather.get("snow_mm_h", 0.0)))),
        "log_illuminance": np.full(n, math.log(max(float(weather.get("illuminance_lux", 1e4)), 1e-3))),
    }
    for c in range(1, NUM_CLASSES):
        out[f"class_{c}"] = (labels == c).astype(float)
    return out


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(len a, len b) IoU of [x1, y1, x2, y2] boxes."""
    a, b = np.asarray(a, float).reshape(-1, 4), np.asarray(b, float).reshape(-1, 4)
    lt = np.maximum(a[:, None, :2], b[None, :, :2])
    rb = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.prod(np.clip(rb - lt, 0, None), axis=2)
    area_a = np.prod(np.clip(a[:, 2:] - a[:, :2], 0, None), axis=1)
    area_b = np.prod(np.clip(b[:, 2:] - b[:, :2], 0, None), axis=1)
    union = area_a[:, None] + area_b[None, :] - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1), 0.0)


def match(det_boxes, det_scores, gt_boxes, iou: float = MATCH_IOU) -> np.ndarray:
    """For each detection the index of its true box, or -1 (see the module docstring)."""
    det_boxes = np.asarray(det_boxes, float).reshape(-1, 4)
    out = np.full(len(det_boxes), -1, int)
    if len(det_boxes) == 0 or len(gt_boxes) == 0:
        return out
    ious = box_iou(det_boxes, gt_boxes)
    taken = np.zeros(ious.shape[1], bool)
    for d in np.argsort(-np.asarray(det_scores, float), kind="stable"):
        row = np.where(taken, -1.0, ious[d])
        g = int(np.argmax(row))
        if row[g] >= iou:
            out[d], taken[g] = g, True
    return out


def box_error(det: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """(n, 4) error vectors e (module docstring) of detections `det` of true boxes `gt`."""
    det, gt = np.asarray(det, float).reshape(-1, 4), np.asarray(gt, float).reshape(-1, 4)
    w = np.maximum(gt[:, 2] - gt[:, 0], 1.0)
    h = np.maximum(gt[:, 3] - gt[:, 1], 1.0)
    dw = np.maximum(det[:, 2] - det[:, 0], 1e-3)
    dh = np.maximum(det[:, 3] - det[:, 1], 1e-3)
    return np.column_stack([((det[:, 0] + det[:, 2]) - (gt[:, 0] + gt[:, 2])) / 2 / w,
                            ((det[:, 1] + det[:, 3]) - (gt[:, 1] + gt[:, 3])) / 2 / h,
                            np.log(dw / w), np.log(dh / h)])


def apply_error(gt: np.ndarray, e: np.ndarray) -> np.ndarray:
    """The boxes of true boxes `gt` moved by error vectors `e` (the inverse of `box_error`)."""
    gt = np.asarray(gt, float).reshape(-1, 4)
    w = np.maximum(gt[:, 2] - gt[:, 0], 1.0)
    h = np.maximum(gt[:, 3] - gt[:, 1], 1.0)
    cx = (gt[:, 0] + gt[:, 2]) / 2 + e[:, 0] * w
    cy = (gt[:, 1] + gt[:, 3]) / 2 + e[:, 1] * h
    nw, nh = w * np.exp(e[:, 2]), h * np.exp(e[:, 3])
    return np.column_stack([cx - nw / 2, cy - nh / 2, cx + nw / 2, cy + nh / 2])


def fit_logistic(x: np.ndarray, y: np.ndarray, ridge: float = RIDGE, iters: int = 50) -> np.ndarray:
    """Weights [intercept, w...] of P(y=1) = logistic(w0 + x w) by Newton's method on the log-likelihood
    minus ridge/2 |w|^2 (the intercept not penalised)."""
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    a = np.column_stack([np.ones(len(x)), x])
    w = np.zeros(a.shape[1])
    pen = np.full(a.shape[1], ridge)
    pen[0] = 0.0
    for _ in range(iters):
        p = 1.0 / (1.0 + np.exp(-(a @ w)))
        grad = a.T @ (y - p) - pen * w
        hess = (a * (p * (1 - p))[:, None]).T @ a + np.diag(pen) + 1e-9 * np.eye(len(w))
        step = np.linalg.solve(hess, grad)
        w += step
        if np.max(np.abs(step)) < 1e-8:
            break
    return w


def _quantiles(values) -> list[float]:
    v = np.asarray(values, float)
    return np.quantile(v, QUANTILES).tolist() if len(v) else []


def _draw_quantiles(q, u: np.ndarray) -> np.ndarray:
    """Inverse-CDF draws from the empirical quantiles `q` (linear between them)."""
    return np.interp(u, QUANTILES, np.asarray(q, float))


@dataclass
class BranchPEM:
    """One branch's fitted PEM (module docstring); `to_dict`/`from_dict` round-trip it through JSON."""

    features: tuple
    mean: list
    scale: list
    weights: list
    loc_mean: list  # per range bin, 4 numbers
    loc_sd: list
    p_edges: dict  # per true class ("0": any class), the detection-probability edges between score groups
    tp_score_q: dict  # per true class ("0": any class), per score group, the quantiles
    fa_score_q: list
    confusion: list  # NUM_CLASSES x NUM_CLASSES counts (true class row -> detected class) + identity prior
    fa_rate: dict  # context -> false alarms per frame
    fa_rate_pooled: float
    fa_boxes: list  # (m, 4) (cx / W, cy / H, log w, log h) of the false alarms fitted on
    fa_labels: list
    fa_scores: list
    near: list  # the near false alarms: (e (4), score, class, found) each
    near_rate: list  # near false alarms per missed object, per found object
    fa_bandwidth: list
    counts: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}

    @classmethod
    def from_dict(cls, d: dict) -> BranchPEM:
        return cls(**{**d, "features": tuple(d["features"])})

    def design(self, table: dict) -> np.ndarray:
        x = np.column_stack([np.asarray(table[f], float) for f in self.features]) if self.features else None
        return (x - np.asarray(self.mean)) / np.asarray(self.scale)

    def detection_probability(self, table: dict, strength: float = 1.0) -> np.ndarray:
        w = np.asarray(self.weights, float)
        logit = w[0] + self.design(table) @ w[1:] + math.log(strength)
        return 1.0 / (1.0 + np.exp(-logit))

    def _boxes(self, gt: np.ndarray, bins: np.ndarray, z: np.ndarray, strength: float) -> np.ndarray:
        """Each true box moved by the first of its ERROR_TRIES error draws that keeps IoU >= MATCH_IOU
        with it (the fitted errors are of matched boxes only; a draw past that would turn a found
        object into a miss and a false alarm, counted twice), else by the draw of largest IoU."""
        cand = [apply_error(gt, (np.asarray(self.loc_mean)[bins] + np.asarray(self.loc_sd)[bins] * zt) / strength)
                for zt in z]
        ious = np.stack([np.diag(box_iou(c, gt)) for c in cand])  # (tries, n)
        ok = ious >= MATCH_IOU
        pick = np.where(ok.any(axis=0), ok.argmax(axis=0), ious.argmax(axis=0))
        return np.stack(cand)[pick, np.arange(len(gt))]

    def sample(self, rng: np.random.Generator, truth: dict, table: dict, context: str, image_size: tuple,
               strength: float = 1.0, shared=None, loading: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One frame's detections (boxes (n, 4) in the right camera, scores, labels) drawn for the
        true boxes `truth` ({"boxes", "labels"}) with features `table` (`object_table`) in `context`
        on an image of `image_size` (width, height); `strength` as the module docstring says.
        `shared`: (n,) standard normal per object, the same for every branch of the frame, weighted by
        this branch's `loading` (the Gaussian copula of `fit_loadings`; 0: independent)."""
        if not strength > 0:
            raise ValueError(f"strength must be > 0, got {strength!r}")
        width, height = image_size
        gt = np.asarray(truth["boxes"], float).reshape(-1, 4)
        gl = np.asarray(truth["labels"], int).reshape(-1)
        n = len(gt)
        # fixed draw order (each part from the same stream in the same amounts) keeps frames comparable
        u_det, u_score, u_label = rng.random(n), rng.random(n), rng.random(n)
        z = rng.standard_normal((ERROR_TRIES, n, 4))
        p_calibrated = self.detection_probability(table) if n else np.zeros(0)
        p = self.detection_probability(table, strength) if n else np.zeros(0)
        if shared is not None and loading and n:
            from scipy.special import ndtr, ndtri

            z = loading * np.asarray(shared, float) + math.sqrt(1.0 - loading ** 2) * ndtri(np.clip(u_det, 1e-12, 1 - 1e-12))
            u_det = ndtr(z)
        found = u_det < p
        bins = np.clip(np.searchsorted(RANGE_EDGES, np.asarray(table["range_m"], float), side="right") - 1,
                       0, len(RANGE_EDGES) - 2) if n else np.zeros(0, int)
        boxes = self._boxes(gt, bins, z, strength) if n else np.zeros((0, 4))
        keys = [str(c) if str(c) in self.tp_score_q else "0" for c in gl]
        group = [int(np.searchsorted(self.p_edges[k], pc, side="right")) for k, pc in zip(keys, p_calibrated)]
        scores = np.array([_draw_quantiles(self.tp_score_q[k][g], np.array([u]))[0]
                           for k, g, u in zip(keys, group, u_score)])
        conf = np.asarray(self.confusion, float)
        cdf = np.cumsum(conf / np.maximum(conf.sum(axis=1, keepdims=True), 1e-12), axis=1)
        labels = np.array([int(np.searchsorted(cdf[c], u, side="right")) for c, u in zip(gl, u_label)], int)
        labels = np.clip(labels, 1, NUM_CLASSES - 1)
        # false alarms near an object: per object Poisson(near rate of its status), each a fitted one
        # of that status, its error applied to this object's box, its score and class kept
        near = np.asarray(self.near, float).reshape(-1, 7)
        counts = rng.poisson(np.asarray(self.near_rate, float)[found.astype(int)] / strength) if n else np.zeros(0, int)
        nb, ns, nl = [], [], []
        for j in np.where(counts > 0)[0] if len(near) else []:
            pool = np.where(near[:, 6] == int(found[j]))[0]
            pool = pool if len(pool) else np.arange(len(near))
            rec = near[pool[rng.integers(0, len(pool), counts[j])]]
            nb.append(apply_error(np.repeat(gt[j][None], len(rec), axis=0), rec[:, :4]))
            ns.append(rec[:, 4])
            nl.append(rec[:, 5].astype(int))
        keep = found
        boxes, scores, labels = boxes[keep], scores[keep], labels[keep]
        if nb:
            boxes, scores, labels = np.vstack([boxes, *nb]), np.r_[scores, *ns], np.r_[labels, *nl]
        # false alarms
        rate = self.fa_rate.get(context, self.fa_rate_pooled) / strength
        m = int(rng.poisson(rate)) if self.fa_boxes else 0
        if m:
            src = np.asarray(self.fa_boxes, float)
            pick = rng.integers(0, len(src), m)
            v = src[pick] + rng.standard_normal((m, 4)) * np.asarray(self.fa_bandwidth, float)
            cx, cy, w, h = v[:, 0] * width, v[:, 1] * height, np.exp(v[:, 2]), np.exp(v[:, 3])
            fb = np.column_stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2])
            fs = np.asarray(self.fa_scores, float)[pick]
            fl = np.asarray(self.fa_labels, int)[pick]
            boxes, scores, labels = np.vstack([boxes, fb]), np.r_[scores, fs], np.r_[labels, fl]
        boxes = boxes.reshape(-1, 4)
        boxes[:, [0, 2]] = np.clip(boxes[:, [0, 2]], 0, width)
        boxes[:, [1, 3]] = np.clip(boxes[:, [1, 3]], 0, height)
        ok = (boxes[:, 2] - boxes[:, 0] > 0.5) & (boxes[:, 3] - boxes[:, 1] > 0.5)
        scores = np.clip(scores, 0.0, 1.0)
        return boxes[ok], scores[ok], labels[ok].astype(int)


@dataclass
class FitFrame:
    """One fitting frame of one branch: its detections in the right camera, the scored true boxes
    (`truth`: boxes, labels), their features (`object_table`), context and image size."""

    det_boxes: np.ndarray
    det_scores: np.ndarray
    det_labels: np.ndarray
    truth: dict
    table: dict
    context: str
    image_size: tuple


def _score_groups(p: np.ndarray, scores: np.ndarray) -> tuple[list, list]:
    """Tercile edges of the detection probabilities `p` of found objects (none under 3 x MIN_BIN of
    them) and the quantiles of their `scores` per tercile."""
    edges = np.quantile(p, [1 / 3, 2 / 3]).tolist() if len(p) >= 3 * MIN_BIN else []
    group = np.searchsorted(edges, p, side="right")
    return edges, [_quantiles(scores[group == g]) if (group == g).sum() else _quantiles(scores)
                   for g in range(len(edges) + 1)]


def fit_branch(frames: list[FitFrame], sensors) -> BranchPEM:
    """A branch's PEM fitted on its matched detections in `frames` (module docstring)."""
    feats = branch_features(sensors)
    xs, ys, errs, err_range, tp_scores, tp_x, tp_class = [], [], [], [], [], [], []
    conf = np.eye(NUM_CLASSES)  # prior: one correct detection per class (a class never matched keeps its label)
    conf[0, 0] = 0.0
    fa_count: dict = {}
    fa_frames: dict = {}
    fa_boxes, fa_labels, fa_scores = [], [], []
    near: list = []  # (e (4), score, class, found) of the false alarms near an object
    objects_by_status = [0, 0]  # missed, found
    for f in frames:
        gt = np.asarray(f.truth["boxes"], float).reshape(-1, 4)
        gl = np.asarray(f.truth["labels"], int).reshape(-1)
        m = match(f.det_boxes, f.det_scores, gt)
        x = np.column_stack([np.asarray(f.table[k], float) for k in feats]) if len(gt) else np.zeros((0, len(feats)))
        found = np.zeros(len(gt), bool)
        found[m[m >= 0]] = True
        xs.append(x)
        ys.append(found)
        hit = np.where(m >= 0)[0]
        if len(hit):
            errs.append(box_error(np.asarray(f.det_boxes)[hit], gt[m[hit]]))
            err_range.append(np.asarray(f.table["range_m"], float)[m[hit]])
            tp_scores.append(np.asarray(f.det_scores, float)[hit])
            tp_x.append(x[m[hit]])
            tp_class.append(gl[m[hit]])
            for d in hit:
                conf[gl[m[d]], int(f.det_labels[d])] += 1
        miss = np.where(m < 0)[0]
        near_to = np.full(len(miss), -1)
        if len(gt) and len(miss):
            ious = box_iou(np.asarray(f.det_boxes, float)[miss], gt)
            near_to = np.where(ious.max(axis=1) > NEAR_IOU, ious.argmax(axis=1), -1)
        objects_by_status[0] += int((~found).sum())
        objects_by_status[1] += int(found.sum())
        for d, g in zip(miss, near_to):
            if g >= 0:
                near.append(box_error(np.asarray(f.det_boxes[d], float)[None], gt[g][None])[0].tolist()
                            + [float(f.det_scores[d]), int(f.det_labels[d]), int(found[g])])
        miss = miss[near_to < 0]
        fa_frames[f.context] = fa_frames.get(f.context, 0) + 1
        fa_count[f.context] = fa_count.get(f.context, 0) + len(miss)
        w, h = f.image_size
        for d in miss:
            b = np.asarray(f.det_boxes[d], float)
            bw, bh = max(b[2] - b[0], 1e-3), max(b[3] - b[1], 1e-3)
            fa_boxes.append([(b[0] + b[2]) / 2 / w, (b[1] + b[3]) / 2 / h, math.log(bw), math.log(bh)])
            fa_labels.append(int(f.det_labels[d]))
            fa_scores.append(float(f.det_scores[d]))
    x = np.vstack(xs) if xs else np.zeros((0, len(feats)))
    y = np.concatenate(ys) if ys else np.zeros(0, bool)
    if len(y) == 0:
        raise ValueError("no true boxes in the fitting frames: nothing to fit a PEM on")
    mean = x.mean(axis=0)
    scale = x.std(axis=0)
    scale = np.where(scale > 1e-9, scale, 1.0)
    w = fit_logistic((x - mean) / scale, y)
    e = np.vstack(errs) if errs else np.zeros((0, 4))
    er = np.concatenate(err_range) if err_range else np.zeros(0)
    pooled_mean = e.mean(axis=0) if len(e) else np.zeros(4)
    pooled_sd = e.std(axis=0) if len(e) > 1 else np.full(4, 0.1)
    loc_mean, loc_sd = [], []
    for lo, hi in zip(RANGE_EDGES[:-1], RANGE_EDGES[1:]):
        sel = (er >= lo) & (er < hi)
        if sel.sum() >= MIN_BIN:
            loc_mean.append(e[sel].mean(axis=0).tolist())
            loc_sd.append(e[sel].std(axis=0).tolist())
        else:
            loc_mean.append(pooled_mean.tolist())
            loc_sd.append(pooled_sd.tolist())
    # scores of found objects per class and tercile of the fitted detection probability
    tps = np.concatenate(tp_scores) if tp_scores else np.zeros(0)
    edges, tp_q = {"0": []}, {"0": [[0.5] * len(QUANTILES)]}
    if len(tps):
        tx, tc = np.vstack(tp_x), np.concatenate(tp_class)
        pt = 1.0 / (1.0 + np.exp(-(w[0] + ((tx - mean) / scale) @ w[1:])))
        for key, sel in (("0", np.ones(len(tps), bool)), *((str(c), tc == c) for c in range(1, NUM_CLASSES))):
            if key == "0" or sel.sum() >= 3 * MIN_BIN:
                edges[key], tp_q[key] = _score_groups(pt[sel], tps[sel])
    fa = np.asarray(fa_boxes, float).reshape(-1, 4)
    if len(fa) > MAX_FA_BOXES:
        keep = np.random.default_rng(0).choice(len(fa), MAX_FA_BOXES, replace=False)
        fa, fa_labels, fa_scores = fa[keep], [fa_labels[i] for i in keep], [fa_scores[i] for i in keep]
    bandwidth = (fa.std(axis=0) * (4 / (6 * max(len(fa), 1))) ** (1 / 8)).tolist() if len(fa) > 1 else [0.0] * 4
    n_frames = sum(fa_frames.values())
    return BranchPEM(
        features=feats, mean=mean.tolist(), scale=scale.tolist(), weights=w.tolist(),
        loc_mean=loc_mean, loc_sd=loc_sd, p_edges=edges, tp_score_q=tp_q,
        fa_score_q=_quantiles(fa_scores) or [0.0] * len(QUANTILES), confusion=conf.tolist(),
        fa_rate={c: fa_count[c] / fa_frames[c] for c in sorted(fa_frames)},
        fa_rate_pooled=sum(fa_count.values()) / max(n_frames, 1), fa_boxes=fa.tolist(), fa_labels=list(fa_labels),
        fa_scores=list(fa_scores), near=near,
        near_rate=[sum(1 for r in near if r[6] == k) / max(objects_by_status[k], 1) for k in (0, 1)],
        fa_bandwidth=bandwidth,
        counts={"frames": n_frames, "objects": int(len(y)), "found": int(y.sum()), "false_alarms": int(len(fa_scores))})


LOADING_GRID = np.round(np.linspace(0.0, 0.95, 20), 3)
COPULA_DRAWS = 200


def joint_found(p: np.ndarray, loadings, draws: int = COPULA_DRAWS, seed: int = 0) -> np.ndarray:
    """(B, B) mean over objects of P(branch a and branch b find the object) when each branch finds it
    with probability p[:, b] and their draws share a standard normal with `loadings` (Monte Carlo with
    `draws` fixed draws per object, independent across objects)."""
    from scipy.special import ndtr

    rng = np.random.default_rng(seed)
    n, b = p.shape
    u = rng.standard_normal((draws, n, 1))
    e = rng.standard_normal((draws, n, b))
    lam = np.asarray(loadings, float)[None, None, :]
    found = ndtr(lam * u + np.sqrt(1 - lam ** 2) * e) < p[None, :, :]  # (draws, n, b)
    f = found.astype(float)
    return np.einsum("kna,knb->ab", f, f) / (draws * n)


def fit_loadings(found: np.ndarray, p: np.ndarray, sweeps: int = 3) -> list[float]:
    """Per branch, the loading on one normal shared by every branch of an object (a Gaussian copula:
    each branch's own detection probability is unchanged) whose joint detection P(a and b find it),
    averaged over objects, is nearest (least squares over pairs) to the observed share of objects
    `found` (n, B) by both, given the fitted probabilities `p` (n, B); coordinate descent on
    `LOADING_GRID`. The pair correlation of the latent draws is the product of the two loadings."""
    found = np.asarray(found, float)
    observed = found.T @ found / max(len(found), 1)
    b = found.shape[1]
    off = ~np.eye(b, dtype=bool)
    lam = np.zeros(b)
    # fixed draws per object: the same for every candidate, so the search is smooth
    for _ in range(sweeps):
        for j in range(b):
            best, best_err = lam[j], None
            for g in LOADING_GRID:
                cand = lam.copy()
                cand[j] = g
                err = float(((joint_found(p, cand) - observed)[off] ** 2).sum())
                if best_err is None or err < best_err:
                    best, best_err = g, err
            lam[j] = best
    return lam.tolist()


def shared_normals(seed: int, key: int, n: int) -> np.ndarray:
    """The (n,) shared standard normals of a frame's objects (the same for every branch; its own
    stream, apart from every branch's `frame_rng`)."""
    return np.random.default_rng([int(seed), int(key), SHARED_STREAM]).standard_normal(n)


SHARED_STREAM = 2 ** 31 - 1


def frame_rng(seed: int, key: int, branch_index: int) -> np.random.Generator:
    """The random stream of one frame and branch (module docstring: order-free)."""
    return np.random.default_rng([int(seed), int(key), int(branch_index)])


# ----- a known-answer world for the gates (issue 49, item 4) ---------------------------------------

KNOWN_ANSWER_RULE = {"city": "camera_right", "junction": "camera_right", "motorway": "camera_right",
                     "rural": "camera_right", "night": "lidar", "fog": "radar", "rain": "radar", "snow": "radar"}
"""Per context, the sensor a known-answer world makes strongest, where physics lets it be: the camera
(passive, the finest resolution) in clear daylight, the lidar (active: it needs no light) at night,
the radar (its 4 mm wavelength passes fog, rain and snow) in the three weathers."""


def known_answer_world(branch_sensors: dict, contexts, strong: float = 8.0, weak: float = 0.125,
                       rule: dict | None = None) -> tuple[dict, dict]:
    """({branch: {context: strength}}, {context: answer branch}) of the world where, in each context,
    the single-sensor branch of the sensor `rule` names (default `KNOWN_ANSWER_RULE`) is drawn at
    strength `strong` and every other branch at `weak` (the strength knob of `BranchPEM.sample`:
    odds of detection x s, box error / s, false alarms / s). With strong / weak = 64 the answer
    branch finds an object at 64 times the odds, with a box error 64 times smaller and 64 times fewer
    false alarms: the best branch of that context by construction, even where its fitted model is
    the weakest (cpu-frontier's camera branch: mAP 0.10 against radar_lidar's 0.32; at 16 the
    radar_lidar branch still beat the camera on junction's validation frames).
    ValueError for a context the rule does not name or a sensor no single-sensor branch reads."""
    if not (strong > weak > 0):
        raise ValueError(f"strong must exceed weak and both be > 0, got {strong}, {weak}")
    rule = KNOWN_ANSWER_RULE if rule is None else rule
    single = {tuple(s)[0]: b for b, s in branch_sensors.items() if len(tuple(s)) == 1}
    answer = {}
    for ctx in contexts:
        if ctx not in rule:
            raise ValueError(f"context {ctx!r}: the known-answer rule names no sensor for it (it has: {', '.join(rule)})")
        if rule[ctx] not in single:
            raise ValueError(f"context {ctx!r}: no single-sensor branch reads {rule[ctx]} (branches: {', '.join(branch_sensors)})")
        answer[ctx] = single[rule[ctx]]
    world = {b: {ctx: (strong if answer[ctx] == b else weak) for ctx in answer} for b in branch_sensors}
    return world, answer
