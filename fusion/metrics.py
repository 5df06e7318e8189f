"""Detection metrics: PASCAL VOC average precision at IoU 0.5 (HydraFusion Sec. 5.3, Eq. 16-17).

Deterministic numpy, no torch. The protocol is the VOC devkit's (2010 onwards):

- Per class, the detections of all images are ranked by score (stable: ties keep image order,
  then detection order) and walked from the best. A detection is matched to the ground-truth box
  of its class and image that it overlaps most (Eq. 14). If that IoU is >= `iou_thr` (the paper's
  "IoU >= 0.5"; the devkit writes ``>``, which differs only at exactly 0.5):
  a *difficult* box makes the detection ignored (neither TP nor FP); an unclaimed box makes it a
  true positive and claims the box; an already claimed box makes it a false positive (duplicate).
  Any other detection is a false positive. The best-overlap box is chosen among all boxes of the
  class, claimed or not, as in the devkit (COCO instead falls back to the best *unclaimed* box).
- P = TP / (TP + FP) and R = TP / n_pos after each ranked detection (Eq. 16), where n_pos counts
  the non-difficult ground-truth boxes of the class.
- AP = sum_n (R_n - R_{n-1}) P_n (Eq. 17) over every recall step, with P_n the interpolated
  precision max_{R >= R_n} P(R) ("all" points, VOC2010+). "11" (VOC2007, mean of the interpolated
  precision at R = 0, 0.1, ..., 1) and "101" (COCO, R = 0, 0.01, ..., 1) are available for
  comparison with other tools.
- mAP is the mean of the per-class APs over the classes that have at least one non-difficult
  ground-truth box. A class without any (only detections, or only difficult boxes) has AP NaN,
  is listed in `VOCResult.excluded` and is *not* in the mean: its detections are all false
  positives, but there is no recall to measure.

Boxes are [x1, y1, x2, y2] in any one unit (pixels or normalised); no "+1 pixel" convention.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

Interpolation = Literal["all", "11", "101"]
INTERPOLATIONS = ("all", "11", "101")


def box_iou(boxes1, boxes2) -> np.ndarray:
    """Pairwise intersection over union (HydraFusion Eq. 14).

    Args:
        boxes1: (N, 4) [x1, y1, x2, y2].
        boxes2: (M, 4) [x1, y1, x2, y2], same unit.

    Returns:
        (N, M) float64 IoU in [0, 1]; 0 where both boxes have zero area.
    """
    a = np.asarray(boxes1, np.float64).reshape(-1, 4)
    b = np.asarray(boxes2, np.float64).reshape(-1, 4)
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    w = np.clip(np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0]), 0, None)
    h = np.clip(np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1]), 0, None)
    inter = w * h
    union = area_a[:, None] + area_b[None, :] - inter
    return np.divide(inter, union, out=np.zeros_like(inter), where=union > 0)


def average_precision(recall, precision, interpolation: Interpolation = "all") -> float:
    """Area under a precision-recall curve, Eq. 17 with interpolated precision.

    Args:
        recall: (D,) recall after each ranked detection (non-decreasing, in [0, 1]).
        precision: (D,) precision after each ranked detection.
        interpolation: "all" (VOC2010+: every recall step), "11" (VOC2007: R = 0, 0.1, ..., 1)
            or "101" (COCO: R = 0, 0.01, ..., 1).

    Returns:
        AP in [0, 1] (0 for an empty curve).
    """
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, got {interpolation!r}")
    rec = np.asarray(recall, np.float64)
    prec = np.asarray(precision, np.float64)
    if rec.shape != prec.shape or rec.ndim != 1:
        raise ValueError(f"recall and precision must be 1-d of equal length, got {rec.shape} and {prec.shape}")
    if len(rec) == 0:
        return 0.0
    if interpolation == "all":
        mrec = np.concatenate([[0.0], rec, [1.0]])
        mpre = np.concatenate([[0.0], prec, [0.0]])
        mpre = np.maximum.accumulate(mpre[::-1])[::-1]  # P_n = max precision at recall >= R_n
        step = np.flatnonzero(mrec[1:] != mrec[:-1])
        return float(np.sum((mrec[step + 1] - mrec[step]) * mpre[step + 1]))  # Eq. 17
    envelope = np.maximum.accumulate(prec[::-1])[::-1]
    points = np.linspace(0.0, 1.0, 11 if interpolation == "11" else 101)
    at = np.searchsorted(rec, points, side="left")  # first detection reaching each recall point
    values = np.where(at < len(rec), envelope[np.minimum(at, len(rec) - 1)], 0.0)
    return float(values.mean())


@dataclass(frozen=True)
class VOCResult:
    """Per-class and mean average precision of a set of images.

    Fields:
        ap: {class id: AP in [0, 1]}, NaN for classes without non-difficult ground truth.
        mean_ap: mean of the finite APs (NaN if there are none).
        n_positives: {class id: number of non-difficult ground-truth boxes}.
        n_detections: {class id: detections of the class, including ignored ones}.
        n_true_positives: {class id: detections that claimed a ground-truth box}.
        excluded: class ids left out of the mean (no non-difficult ground truth).
        precision, recall: {class id: (D,) curve after each ranked, non-ignored detection}.
        iou_thr: the match threshold.
        interpolation: "all", "11" or "101".
    """

    ap: dict[int, float]
    mean_ap: float
    n_positives: dict[int, int]
    n_detections: dict[int, int]
    n_true_positives: dict[int, int]
    excluded: tuple[int, ...]
    precision: dict[int, np.ndarray] = field(repr=False)
    recall: dict[int, np.ndarray] = field(repr=False)
    iou_thr: float = 0.5
    interpolation: str = "all"


@dataclass(frozen=True)
class _Image:
    det_boxes: np.ndarray
    det_scores: np.ndarray
    det_labels: np.ndarray
    gt_boxes: np.ndarray
    gt_labels: np.ndarray
    gt_difficult: np.ndarray


def _field(record, key: str, position: int, where: str, optional: bool = False):
    if isinstance(record, Mapping):
        if key in record:
            return record[key]
    elif isinstance(record, Sequence) and not isinstance(record, str):
        if position < len(record):
            return record[position]
    else:
        raise ValueError(f"{where} must be a mapping with 'boxes', ... or a tuple, got {type(record).__name__}")
    if optional:
        return None
    raise ValueError(f"{where} has no {key!r}")


def _array(value, where: str, shape_tail: tuple, dtype=np.float64) -> np.ndarray:
    try:
        arr = np.asarray(value.detach().cpu().numpy() if hasattr(value, "detach") else value, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where} is not a numeric array ({exc})") from None
    if arr.size == 0:
        arr = arr.reshape((0, *shape_tail))
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        raise ValueError(f"{where} must have shape (N{''.join(f', {d}' for d in shape_tail)}), got {arr.shape}")
    if dtype is np.float64 and not np.isfinite(arr).all():
        raise ValueError(f"{where} contains NaN or inf")
    return arr


def _class_ids(value, where: str) -> np.ndarray:
    arr = _array(value, where, ())
    if not (arr == np.round(arr)).all():
        raise ValueError(f"{where} must hold integer class ids, got {arr[arr != np.round(arr)][:3].tolist()}")
    return arr.astype(np.int64)


def _images(detections, ground_truths) -> list[_Image]:
    if len(detections) != len(ground_truths):
        raise ValueError(f"detections has {len(detections)} images but ground_truths has {len(ground_truths)}")
    images = []
    for i, (det, gt) in enumerate(zip(detections, ground_truths, strict=True)):
        d_boxes = _array(_field(det, "boxes", 0, f"detections[{i}]"), f"detections[{i}]['boxes']", (4,))
        d_scores = _array(_field(det, "scores", 1, f"detections[{i}]"), f"detections[{i}]['scores']", ())
        d_labels = _class_ids(_field(det, "labels", 2, f"detections[{i}]"), f"detections[{i}]['labels']")
        g_boxes = _array(_field(gt, "boxes", 0, f"ground_truths[{i}]"), f"ground_truths[{i}]['boxes']", (4,))
        g_labels = _class_ids(_field(gt, "labels", 1, f"ground_truths[{i}]"), f"ground_truths[{i}]['labels']")
        difficult = _field(gt, "difficult", 2, f"ground_truths[{i}]", optional=True)
        if difficult is None:
            g_difficult = np.zeros(len(g_labels), bool)
        else:
            g_difficult = _array(difficult, f"ground_truths[{i}]['difficult']", (), dtype=bool)
        for name, arr, n in [("scores", d_scores, len(d_boxes)), ("labels", d_labels, len(d_boxes))]:
            if len(arr) != n:
                raise ValueError(f"detections[{i}]['{name}'] has {len(arr)} entries for {n} boxes")
        for name, arr in [("labels", g_labels), ("difficult", g_difficult)]:
            if len(arr) != len(g_boxes):
                raise ValueError(f"ground_truths[{i}]['{name}'] has {len(arr)} entries for {len(g_boxes)} boxes")
        images.append(_Image(d_boxes, d_scores, d_labels, g_boxes, g_labels, g_difficult))
    return images


def _evaluate_class(images: list[_Image], cls: int, iou_thr: float, hits: list[np.ndarray] | None = None,
                    ranked: list | None = None):
    """(tp, fp) flags of the class's ranked non-ignored detections, n_pos, n_det.
    `hits`: per image, a boolean array over its ground truth, set where a true positive matched.
    `ranked`: receives the scores of those detections, in the same (rank) order."""
    image_idx, det_scores, best_gt, best_iou = [], [], [], []
    difficult_of, offset = [], 0  # ground truth of the class, numbered across images
    owner = []  # (image, box) of each of those
    n_pos = 0
    for i, im in enumerate(images):
        d = im.det_labels == cls
        g = im.gt_labels == cls
        owner.extend((i, int(b)) for b in np.flatnonzero(g))
        gt_boxes, gt_difficult = im.gt_boxes[g], im.gt_difficult[g]
        n_pos += int((~gt_difficult).sum())
        n_d = int(d.sum())
        if n_d:
            image_idx.append(np.full(n_d, i))
            det_scores.append(im.det_scores[d])
            if len(gt_boxes):
                ious = box_iou(im.det_boxes[d], gt_boxes)
                j = ious.argmax(axis=1)  # first maximum: ties go to the earlier box
                best_gt.append(offset + j)
                best_iou.append(ious[np.arange(n_d), j])
            else:
                best_gt.append(np.full(n_d, -1))
                best_iou.append(np.full(n_d, -1.0))
        difficult_of.append(gt_difficult)
        offset += len(gt_boxes)
    if not det_scores:
        if ranked is not None:
            ranked.append(np.zeros(0))
        return np.zeros(0, bool), np.zeros(0, bool), n_pos, 0
    scores = np.concatenate(det_scores)
    order = np.argsort(-scores, kind="stable")  # images were concatenated in order: ties stay put
    gt = np.concatenate(best_gt)[order]
    matched = np.concatenate(best_iou)[order] >= iou_thr
    difficult = np.concatenate(difficult_of) if offset else np.zeros(0, bool)
    ignored = matched & difficult[np.where(matched, gt, 0)] if offset else np.zeros(len(gt), bool)
    claims = matched & ~ignored
    tp = np.zeros(len(gt), bool)
    if claims.any():
        # the first (best-ranked) claim on a box is the true positive, later ones are duplicates
        _, first = np.unique(gt[claims], return_index=True)
        tp[np.flatnonzero(claims)[first]] = True
    if hits is not None:
        for t in gt[tp]:
            i, b = owner[t]
            hits[i][b] = True
    keep = ~ignored
    if ranked is not None:
        ranked.append(scores[order][keep])
    return tp[keep], ~tp[keep], n_pos, len(scores)


def _classes_of(images: list[_Image], classes) -> np.ndarray:
    if classes is None:
        seen = [im.det_labels for im in images] + [im.gt_labels for im in images]
        return np.unique(np.concatenate(seen)) if seen else np.zeros(0, np.int64)
    return np.unique(_class_ids(list(classes), "classes"))


def matched_ground_truth(detections: Sequence, ground_truths: Sequence, *, iou_thr: float = 0.5,
                         classes: Sequence[int] | None = None) -> list[np.ndarray]:
    """Per image, a boolean array over its ground-truth boxes: True where a detection matched the
    box as a true positive under exactly `evaluate_detections`' protocol (same arguments), so the
    count of True over non-difficult boxes of `classes` is its `n_true_positives`. For recall by an
    attribute of the boxes (distance, size, occlusion)."""
    images = _images(detections, ground_truths)
    hits = [np.zeros(len(im.gt_boxes), bool) for im in images]
    for cls in (int(c) for c in _classes_of(images, classes)):
        _evaluate_class(images, cls, float(iou_thr), hits)
    return hits


def _recall_precision(tp: np.ndarray, n_pos: int) -> tuple[np.ndarray, np.ndarray]:
    """Recall and precision (Eq. 16) down a ranked list of true-positive flags (the rest are false
    positives: every step is one or the other, so no 0 / 0); recall is NaN without ground truth."""
    ctp, cfp = np.cumsum(tp), np.cumsum(~tp)
    prec = ctp / np.maximum(ctp + cfp, 1)
    return (ctp / n_pos if n_pos else np.full(len(ctp), np.nan)), prec


MAX_BOOTSTRAP = 100_000
"""Most bootstrap draws a command accepts (`--bootstrap`): 1000 give a table's intervals to two digits;
beyond this, hours of pooling for no visible change."""


def sequence_draws(by_seq: Mapping, resamples: int, seed: int):
    """Yield `resamples` draws of whole sequences with replacement (a cluster bootstrap): each the
    concatenated members of as many sequences as there are, drawn from `by_seq` {sequence: [items]}.
    Frames of one sequence share traffic and weather, so the sequence, not the frame, is the unit
    drawn; the generator is seeded, so the same `seed` gives the same draws."""
    seqs = sorted(by_seq)
    rng = np.random.default_rng(seed)
    for _ in range(resamples):
        yield [k for j in rng.integers(0, len(seqs), len(seqs)) for k in by_seq[seqs[j]]]


@dataclass(frozen=True)
class ImageMatches:
    """Each image's VOC matching, kept apart so that AP over any multiset of the images (a bootstrap
    draw) needs no new matching: a detection only ever matches ground truth of its own image, so
    ranking, duplicates and difficult boxes resolve image by image.

    per_image[i][cls] = (scores, tp, n_pos): the scores of image i's non-ignored detections of the
    class in rank order, their true-positive flags, and its number of non-difficult boxes.
    """

    per_image: list
    classes: tuple
    interpolation: str

    @classmethod
    def of(cls, detections: Sequence, ground_truths: Sequence, *, iou_thr: float = 0.5,
           classes: Sequence[int] | None = None, interpolation: Interpolation = "all") -> ImageMatches:
        """Arguments as `evaluate_detections` (same validation and errors)."""
        if not 0.0 <= float(iou_thr) <= 1.0:
            raise ValueError(f"iou_thr must be in [0, 1], got {iou_thr!r}")
        if interpolation not in INTERPOLATIONS:
            raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, got {interpolation!r}")
        images = _images(detections, ground_truths)
        class_ids = tuple(int(c) for c in _classes_of(images, classes))
        per_image = []
        for im in images:
            row = {}
            for c in class_ids:
                ranked: list = []
                tp, _fp, n_pos, _n_det = _evaluate_class([im], c, float(iou_thr), ranked=ranked)
                row[c] = (ranked[0], tp, n_pos)
            per_image.append(row)
        return cls(per_image, class_ids, interpolation)

    def ap_of_class(self, c: int, images: Sequence[int]) -> float:
        """AP of class `c` over these images (repeats allowed, in this order), as `ap`."""
        rows = [self.per_image[i][c] for i in images]
        n_pos = sum(r[2] for r in rows)
        if not n_pos:
            return float("nan")
        scores = np.concatenate([r[0] for r in rows]) if rows else np.zeros(0)
        tp = np.concatenate([r[1] for r in rows]) if rows else np.zeros(0, bool)
        tp = tp[np.argsort(-scores, kind="stable")]  # ties keep image order, as when pooled
        return average_precision(*_recall_precision(tp, n_pos), self.interpolation)

    def ap(self, images: Sequence[int]) -> dict[int, float]:
        """AP per class over these images (repeats allowed, in this order): equal to
        `evaluate_detections` on the same list of images, to the last bit (tested)."""
        return {c: self.ap_of_class(c, images) for c in self.classes}

    def mean_ap(self, images: Sequence[int]) -> float:
        """Mean of `ap` over the classes with ground truth in these images (NaN when none has)."""
        finite = [v for v in self.ap(images).values() if not np.isnan(v)]
        return float(np.mean(finite)) if finite else float("nan")

    def mean_ap_draws(self, draws: Sequence[Sequence[int]]) -> np.ndarray:
        """`mean_ap` of each draw (a list of images, repeats allowed), equal to it to rounding
        (1e-12; tested): the pooled detections are ranked once, and a draw only weights them
        (`DrawScorer`). Interpolation "all" only."""
        return DrawScorer(self).mean_ap(draws)


class DrawScorer:
    """VOC all-point AP of many draws of the same images, each scored without ranking again.

    A draw takes each image some number of times (its multiplicity m_i: 0, 1, 2, ...). Matching is
    per image, so every detection keeps its true-positive flag in every draw; only the ranking
    could change, and it does not: the pooled detections of a class are ranked once (by score,
    stable over image then rank order), and in a draw a detection stands for m_i consecutive
    copies of itself. The precision after detection k is then TP_k / (TP_k + FP_k) with the counts
    weighted by m, n_pos = sum_i m_i n_pos_i, and AP = sum over true positives of m_k / n_pos
    times the precision envelope max_{j >= k} P_j: within a run of true positives precision only
    rises and within a run of false positives it only falls, so the envelope at every copy of a
    true positive is the envelope after its last copy, and the false positives' intermediate
    points never raise it. The sum is the same as `average_precision`'s over the expanded list.

    One thing can differ: detections of equal score are visited in the draw's order of images
    (`ImageMatches.ap` concatenates the draw and sorts stably), and when such a tie mixes true and
    false positives the order changes the curve. A class holding a tie like that (scores rounded by
    a fusion, copies of one image) is scored for that draw the old way (`ImageMatches.ap`'s
    pooling), so every draw's AP is what the per-draw ranking gives; `fallback_classes` names them.
    """

    def __init__(self, matches: ImageMatches) -> None:
        if matches.interpolation != "all":
            raise ValueError(f"DrawScorer: only 'all' interpolation, got {matches.interpolation!r}")
        self.matches = matches
        self.n_images = len(matches.per_image)
        self.classes = matches.classes
        self.ranked: dict = {}  # class -> (image of each ranked detection, tp flags)
        self.n_pos: dict = {}  # class -> (n_images,) non-difficult boxes per image
        self.fallback_classes: list = []
        for c in self.classes:
            rows = [r[c] for r in matches.per_image]
            scores = np.concatenate([r[0] for r in rows]) if rows else np.zeros(0)
            tp = np.concatenate([r[1] for r in rows]).astype(bool) if rows else np.zeros(0, bool)
            image = np.repeat(np.arange(len(rows)), [len(r[0]) for r in rows])
            order = np.argsort(-scores, kind="stable")
            self.ranked[c] = (image[order].astype(np.int64), tp[order])
            self.n_pos[c] = np.array([r[2] for r in rows], np.int64)
            if _mixed_ties(scores[order], tp[order]):
                self.fallback_classes.append(c)

    def multiplicities(self, draws: Sequence[Sequence[int]]) -> np.ndarray:
        """(draws, images) how often each draw takes each image."""
        out = np.zeros((len(draws), self.n_images), np.int64)
        for r, d in enumerate(draws):
            out[r] = np.bincount(np.asarray(d, np.int64).reshape(-1), minlength=self.n_images)
        return out

    def ap(self, draws: Sequence[Sequence[int]]) -> dict[int, np.ndarray]:
        """{class: (draws,) AP}, NaN where a draw holds no ground truth of the class."""
        draws = [list(d) for d in draws]
        return self.ap_of_multiplicities(self.multiplicities(draws), draws)

    def ap_of_multiplicities(self, mult: np.ndarray, draws: Sequence[Sequence[int]] | None = None
                             ) -> dict[int, np.ndarray]:
        """`ap` of draws given as (draws, images) multiplicities (each image taken that many times). A
        class with mixed ties is scored by pooling each draw's images in the order `draws` lists them
        (`ap`'s draws), else in image order."""
        mult = np.asarray(mult, np.int64)
        if mult.ndim != 2 or mult.shape[1] != self.n_images or (mult.size and mult.min() < 0):
            raise ValueError(f"multiplicities must be (draws, {self.n_images}) counts >= 0, got shape {mult.shape}")
        drawn = mult.any(axis=0)  # images no draw takes weigh 0 everywhere: leave them out of the walk
        out = {}
        for c in self.classes:
            if c in self.fallback_classes:
                order = draws if draws is not None else [np.repeat(np.arange(self.n_images), m) for m in mult]
                out[c] = np.array([self.matches.ap_of_class(c, d) for d in order])
                continue
            image, tp = self.ranked[c]
            keep = drawn[image]
            out[c] = _weighted_ap(image[keep], tp[keep], mult, mult @ self.n_pos[c])
        return out

    def mean_ap(self, draws: Sequence[Sequence[int]]) -> np.ndarray:
        """(draws,) mean AP over the classes with ground truth in each draw (NaN when none has), as
        `ImageMatches.mean_ap`."""
        draws = [list(d) for d in draws]
        return self.mean_ap_of_multiplicities(self.multiplicities(draws), draws)

    def mean_ap_of_multiplicities(self, mult: np.ndarray, draws: Sequence[Sequence[int]] | None = None) -> np.ndarray:
        """`mean_ap` of draws given as (draws, images) multiplicities (`ap_of_multiplicities`)."""
        per = self.ap_of_multiplicities(mult, draws)
        if not per:
            return np.full(len(mult), np.nan)
        table = np.stack([per[c] for c in self.classes], axis=1)
        out = np.full(len(table), np.nan)
        for r, row in enumerate(table):
            finite = row[~np.isnan(row)]
            if len(finite):
                out[r] = float(np.mean(finite))
        return out


def _mixed_ties(scores: np.ndarray, tp: np.ndarray) -> bool:
    """Whether ranked detections hold a run of equal scores with both true and false positives."""
    if len(scores) < 2:
        return False
    starts = np.flatnonzero(np.r_[True, scores[1:] != scores[:-1]])
    any_tp = np.maximum.reduceat(tp.astype(np.int8), starts)
    all_tp = np.minimum.reduceat(tp.astype(np.int8), starts)
    return bool(np.any(any_tp != all_tp))


def _weighted_ap(image: np.ndarray, tp: np.ndarray, mult: np.ndarray, n_pos: np.ndarray) -> np.ndarray:
    """(draws,) all-point AP of ranked detections (`image` of each, `tp` flags) weighted by each
    draw's image multiplicities `mult` (draws, images); NaN where `n_pos` is 0 (`DrawScorer`)."""
    from fusion.metrics_kernels import weighted_ap

    return weighted_ap(np.ascontiguousarray(image, np.int64), np.ascontiguousarray(tp, np.bool_),
                       np.ascontiguousarray(mult, np.int64), np.ascontiguousarray(n_pos, np.int64))


def evaluate_detections(detections: Sequence, ground_truths: Sequence, *, iou_thr: float = 0.5,
                        classes: Sequence[int] | None = None,
                        interpolation: Interpolation = "all") -> VOCResult:
    """PASCAL VOC AP per class and its mean over a list of images (HydraFusion Sec. 5.3).

    Args:
        detections: one entry per image, a mapping {"boxes": (D, 4), "scores": (D,),
            "labels": (D,)} (torchvision's output keys; torch tensors are accepted) or a
            (boxes, scores, labels) tuple as returned by `fusion.boxes`.
        ground_truths: one entry per image, {"boxes": (G, 4), "labels": (G,), optional
            "difficult": (G,) bool} or a (boxes, labels[, difficult]) tuple. Difficult boxes are
            neither required nor penalised: a detection matching one is ignored.
        iou_thr: a detection matches a box when their IoU is >= iou_thr (VOC: 0.5).
        classes: class ids to evaluate (default: every id in the detections or ground truth);
            detections and boxes of other classes are ignored.
        interpolation: "all" (VOC2010+, default), "11" (VOC2007) or "101" (COCO).

    Returns:
        VOCResult with per-class AP and the mean over classes with ground truth (see the module
        docstring for the exact protocol).

    Raises:
        ValueError: naming the field (``detections[3]['scores']``) for mismatched lengths, wrong
            shapes, NaN / inf values or non-integer class ids.
    """
    if not 0.0 <= float(iou_thr) <= 1.0:
        raise ValueError(f"iou_thr must be in [0, 1], got {iou_thr!r}")
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, got {interpolation!r}")
    images = _images(detections, ground_truths)
    class_ids = _classes_of(images, classes)

    ap, n_positives, n_detections, n_tp, precision, recall = {}, {}, {}, {}, {}, {}
    for cls in (int(c) for c in class_ids):
        tp, _fp, n_pos, n_det = _evaluate_class(images, cls, float(iou_thr))
        rec, prec = _recall_precision(tp, n_pos)
        ap[cls] = average_precision(rec, prec, interpolation) if n_pos else float("nan")
        n_positives[cls], n_detections[cls], n_tp[cls] = n_pos, n_det, int(tp.sum())
        precision[cls], recall[cls] = prec, rec
    finite = [v for v in ap.values() if not np.isnan(v)]
    return VOCResult(
        ap=ap,
        mean_ap=float(np.mean(finite)) if finite else float("nan"),
        n_positives=n_positives,
        n_detections=n_detections,
        n_true_positives=n_tp,
        excluded=tuple(c for c, v in ap.items() if np.isnan(v)),
        precision=precision,
        recall=recall,
        iou_thr=float(iou_thr),
        interpolation=interpolation,
    )


def mean_average_precision(detections: Sequence, ground_truths: Sequence, **kwargs) -> float:
    """VOC mAP@0.5: `evaluate_detections(...).mean_ap` (same arguments)."""
    return evaluate_detections(detections, ground_truths, **kwargs).mean_ap
