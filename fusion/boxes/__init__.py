"""Late fusion of per-source detections: NMS, Soft-NMS and WBF (HydraFusion Sec. 4.4).

The three functions take the arguments of the `ensemble-boxes` 1.0.9 package, so code written for
it switches by changing the import::

    from fusion.boxes import weighted_boxes_fusion
    boxes, scores, labels = weighted_boxes_fusion(boxes_list, scores_list, labels_list,
                                                  weights=[2, 1, 1], iou_thr=0.4, skip_box_thr=0.01)

Input: one list entry per source (branch, model); ``boxes_list[t]`` is (N_t, 4) [x1, y1, x2, y2]
in normalised image coordinates (0..1), ``scores_list[t]`` (N_t,) confidences, ``labels_list[t]``
(N_t,) class ids. Output: ``(boxes (K, 4), scores (K,), labels (K,))`` numpy arrays.
Every function takes a keyword-only ``compat``: False (default) is the textbook behaviour,
True reproduces ensemble-boxes output for output (within 1e-6; tested against it). The
differences are listed in `fusion.boxes.nms` and `fusion.boxes.wbf`.

`FUSION_METHODS` is the registry of late-fusion methods. An entry is called as
``entry(boxes_list, scores_list, labels_list, weights=None, **params) -> (boxes, scores, labels)``
with the arrays above; `params` are the method's keyword arguments (iou_thr, sigma, ...).
A method has one name in the registry ("soft_nms") and one on the command line and in reports, its
label ("soft-nms"): `method_name` takes either, `method_label` and `method_labels` give labels. Every
caller reads them from here, so a new method is its function and its two lines below (its
registration and its `HYDRAFUSION_PARAMS`).
"""

from __future__ import annotations

from collections.abc import Callable

from fusion.boxes.nms import nms, soft_nms
from fusion.boxes.wbf import weighted_boxes_fusion
from sim.registry import Registry

FUSION_METHODS: Registry[Callable] = Registry(
    "box fusion method",
    doc="entry(boxes_list, scores_list, labels_list, weights=None, **params) -> (boxes, scores, labels)",
)
FUSION_METHODS.add("nms", nms)
FUSION_METHODS.add("soft_nms", soft_nms)
FUSION_METHODS.add("wbf", weighted_boxes_fusion)

# HydraFusion Sec. 5.2.1: IoU threshold 0.4, skip-box threshold 0.01, Soft-NMS sigma 0.5.
HYDRAFUSION_PARAMS: dict[str, dict] = {
    "nms": {"iou_thr": 0.4},
    "soft_nms": {"method": 2, "iou_thr": 0.4, "sigma": 0.5},
    "wbf": {"iou_thr": 0.4, "skip_box_thr": 0.01},
}



def method_labels() -> list[str]:
    """Every late-fusion method's label ("nms", "soft-nms", "wbf"), in registry order."""
    return [n.replace("_", "-") for n in FUSION_METHODS.names()]


def method_name(name: str) -> str:
    """The registry's name of the late-fusion method `name`, given by its name or its label (the one
    normalisation: dashes are underscores). ValueError naming the choices for an unknown one."""
    key = str(name).replace("-", "_")
    if key not in FUSION_METHODS:
        raise ValueError(f"unknown fusion method {name!r} (choose from: {', '.join(method_labels())})")
    return key


def method_label(name: str) -> str:
    """The label ("soft-nms") of the late-fusion method `name` (its name or label)."""
    return method_name(name).replace("_", "-")


__all__ = ["FUSION_METHODS", "HYDRAFUSION_PARAMS", "method_label", "method_labels", "method_name", "nms", "soft_nms",
           "weighted_boxes_fusion"]
