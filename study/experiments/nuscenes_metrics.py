"""The nuScenes devkit's own detection evaluation (`nuscenes.eval.detection.evaluate.DetectionEval`) of
nuScenes results on a hydrabench export, overall, per context and per severity: what
`hydrabench score --nuscenes-metrics` prints beside VOC mAP@0.5.

What the devkit computes (its config `detection_cvpr_2019`, named in every result): AP by centre
distance on the ground plane (matched at 0.5, 1, 2 and 4 m, averaged), the true-positive errors at
2 m (translation ATE [m], scale ASE = 1 - aligned 3D IoU, orientation AOE [rad], velocity AVE [m/s],
attribute AAE = 1 - accuracy), and NDS = (5 mAP + sum over the five of (1 - min(1, error))) / 10. It
scores the ground truth within the class's range of the ego (50 m for vehicles, 40 m for
pedestrians and two-wheelers) that has at least one lidar or radar point, all around the car: not
only what the right camera sees, which is all VOC mAP@0.5 reads.

Classes: the devkit averages over its ten detection classes; a hydrabench export has at most six
(docs/nuscenes.md) and a subset of frames often fewer, and a class without ground truth scores AP 0
and errors 1 there. So beside the devkit's own numbers (`devkit`: mean_ap, tp_errors, nd_score over
its ten classes, as it prints them), `map`, the errors and `nds` are means over the detection
classes present in the ground truth the devkit scores in that subset of frames (`classes`).

NDS where the fields exist: a file some of whose boxes give a NaN velocity (not estimated) has no
mAVE, one some of whose boxes have an empty attribute_name has no mAAE, and without both no NDS
(the `devkit` block still holds what the devkit computes, which counts a missing attribute as wrong).

Subsets: the devkit evaluates one split (`--split`: hydrabench-all for all); a context's or a
severity's numbers are that evaluation's boxes restricted to those frames' sample tokens (the ground
truth loaded and filtered by the devkit once).
"""

from __future__ import annotations

import contextlib
import copy
import io
import json
import math
import tempfile
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

from sim.errors import UserError

CONFIG = "detection_cvpr_2019"
TP_NAMES = {"trans_err": "mATE", "scale_err": "mASE", "orient_err": "mAOE", "vel_err": "mAVE", "attr_err": "mAAE"}


def check_fields(path, doc: dict, tokens) -> dict:
    """The devkit's box fields hydrabench's reader does not need, checked on the boxes of `tokens`:
    `velocity` two numbers (NaN: not estimated), `attribute_name` a nuScenes attribute or "".
    UserError naming the file and the record otherwise. Returns which the file gives for every box
    ({"velocity": bool, "attribute": bool})."""
    from nuscenes.eval.detection.constants import ATTRIBUTE_NAMES

    velocity = attribute = True
    for token in tokens:
        for j, b in enumerate(doc["results"].get(token, [])):
            where = f"{path}: results[{token!r}][{j}]"
            v = b.get("velocity")
            if not isinstance(v, list | tuple) or len(v) != 2 or not all(
                    isinstance(x, int | float) and not isinstance(x, bool) and not math.isinf(x) for x in v):
                raise UserError(f"{where}: velocity must be [vx, vy] in m/s (NaN: not estimated), got {v!r} "
                                "(--nuscenes-metrics)")
            a = b.get("attribute_name")
            if not isinstance(a, str) or (a and a not in ATTRIBUTE_NAMES):
                raise UserError(f"{where}: attribute_name must be a nuScenes attribute or \"\", got {a!r} "
                                "(--nuscenes-metrics)")
            velocity = velocity and not any(math.isnan(x) for x in v)
            attribute = attribute and bool(a)
    return {"velocity": velocity, "attribute": attribute}


def open_export(export):
    """The devkit's NuScenes on a hydrabench export."""
    from nuscenes import NuScenes

    from sensors.export.nuscenes import VERSION

    with contextlib.redirect_stdout(io.StringIO()):
        return NuScenes(version=VERSION, dataroot=str(export), verbose=False)


def _subset(boxes, tokens):
    from nuscenes.eval.common.data_classes import EvalBoxes

    out = EvalBoxes()
    for t in tokens:
        out.add_boxes(t, boxes[t])
    return out


def _value(v, digits: int = 4):
    from study.numbers import rounded

    return rounded(v, digits)


def summarize(ev, tokens, fields: dict) -> dict:
    """The devkit's evaluation `ev` on the frames `tokens`: present-class means and the devkit's own."""
    sub = copy.copy(ev)
    sub.gt_boxes, sub.pred_boxes = _subset(ev.gt_boxes, tokens), _subset(ev.pred_boxes, tokens)
    metrics, _ = sub.evaluate()
    counts = Counter(b.detection_name for t in tokens for b in sub.gt_boxes[t])
    present = [c for c in ev.cfg.class_names if counts[c]]
    aps = {c: float(metrics.mean_dist_aps[c]) for c in present}
    given = {"vel_err": fields["velocity"], "attr_err": fields["attribute"]}
    errors = {}
    for metric, short in TP_NAMES.items():
        values = [metrics.get_label_tp(c, metric) for c in present]
        values = [v for v in values if not math.isnan(v)]
        errors[short] = float(np.mean(values)) if values and given.get(metric, True) else None
    m = float(np.mean(list(aps.values()))) if aps else None
    nds = None
    if m is not None and all(e is not None for e in errors.values()):
        w = ev.cfg.mean_ap_weight
        nds = (w * m + sum(1.0 - min(1.0, e) for e in errors.values())) / (w + len(errors))
    return {"frames": len(tokens), "classes": present, "map": _value(m),
            "ap_per_class": {c: _value(v) for c, v in aps.items()},
            "ground_truth_per_class": {c: int(counts[c]) for c in present},
            "tp_errors": {k: _value(v) for k, v in errors.items()}, "nds": _value(nds),
            "devkit": {"mean_ap": _value(metrics.mean_ap), "nd_score": _value(metrics.nd_score),
                       "tp_errors": {TP_NAMES[k]: _value(v) for k, v in metrics.tp_errors.items()}}}


def evaluate_file(nusc, path, doc: dict, frames: list[int], metas: dict, index, split: str = "all",
                  config: str = CONFIG) -> dict:
    """The devkit's detection evaluation of the results `doc` (read from `path`, checked by
    `study.experiments.external.read_nuscenes`) on `frames` of the export `index` describes: overall, per context
    and per severity (`metas`: frame -> meta). Frames the file leaves out count as frames without
    detections (as `--missing empty` scores them; refused before this otherwise)."""
    from nuscenes.eval.common.config import config_factory
    from nuscenes.eval.detection.evaluate import DetectionEval

    tokens = [index.token_of[f] for f in frames]
    fields = check_fields(path, doc, tokens)
    eval_set = "hydrabench-all" if split == "all" else split
    with tempfile.TemporaryDirectory(prefix="hydrabench-nuscenes-eval-") as tmp:
        results = Path(tmp) / "results.json"
        results.write_text(json.dumps({"meta": doc["meta"], "results": {t: doc["results"].get(t, []) for t in tokens}}))
        try:
            with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
                ev = DetectionEval(nusc, config_factory(config), str(results), eval_set, str(Path(tmp) / "eval"),
                                   verbose=False)
        except (AssertionError, KeyError, ValueError) as exc:
            raise UserError(f"{path}: the nuScenes devkit refuses it ({type(exc).__name__}: "
                            f"{' '.join(str(exc).split())[:300]})") from None
    by_context, by_severity = defaultdict(list), defaultdict(list)
    for f, t in zip(frames, tokens):
        by_context[metas[f]["context"]].append(t)
        by_severity[str(metas[f].get("severity", 0))].append(t)
    return {"overall": summarize(ev, tokens, fields),
            "per_context": {c: summarize(ev, ts, fields) for c, ts in sorted(by_context.items())},
            "per_severity": {s: summarize(ev, ts, fields) for s, ts in sorted(by_severity.items())},
            "fields": fields, "config": config}


def score_nuscenes(ext, index, export, split: str = "all", config: str = CONFIG) -> dict:
    """{branch: `evaluate_file`} for every branch of `ext` (`study.experiments.external.ExternalSet`) read from
    nuScenes results, on the frames it scores. UserError when there is none (COCO results are 2D)."""
    from study.experiments.external import load_json

    if not ext.nuscenes_files:
        raise UserError("--nuscenes-metrics: the devkit scores 3D boxes: give nuScenes results (--nuscenes); COCO "
                        "results are 2D")
    frames = [int(m["dataset_index"]) for m, _ in ext.per_frame]
    metas = {int(m["dataset_index"]): m for m, _ in ext.per_frame}
    nusc = open_export(export)
    return {b: evaluate_file(nusc, path, load_json(Path(path), "results"), frames, metas, index, split, config)
            for b, path in ext.nuscenes_files.items()}


def describe(config: str = CONFIG) -> dict:
    """What the numbers are, for the result JSON."""
    return {"config": config, "evaluation": "nuscenes.eval.detection.evaluate.DetectionEval (nuscenes-devkit)",
            "classes": "map, tp_errors and nds: means over the detection classes present in the ground truth the "
                       "devkit scores (listed per subset); devkit: its own numbers over its ten classes",
            "scope": "ground truth within the class range with a lidar or radar point, all around the car",
            "nds": "null where a file gives no velocity (NaN) or no attribute for some box"}
