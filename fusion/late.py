"""The late-fusion block (HydraFusion Section 4.4 / 5.2.3): bring every branch's detections into
the fused reference frame, the right camera image, with the frame's own calibration, then fuse.

- BEV branches (radar, lidar, radar_lidar): Appendix A, `sensors.rig.bev_boxes_to_camera`
  (BEV pixel -> metric -> class height -> camera -> pixels); detections outside the camera's field
  of view are dropped, as in the paper (the camera FOV is the reference because it covers least).
- camera_left branches: `sensors.rig.camera_boxes_to_camera` (flat-ground stereo disparity).
- camera_right branches: as they are.
Then `fusion.boxes` (NMS, Soft-NMS or WBF) with per-branch weights on boxes normalised to 0..1.
Plain numpy: no torch here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fusion.boxes import FUSION_METHODS, HYDRAFUSION_PARAMS
from sensors.rig import Calibration, bev_boxes_to_camera, camera_boxes_to_camera

REFERENCE = "camera_right"
FRAMES = ("camera_left", "camera_right", "bev")


@dataclass
class Detections:
    """Columnar detections in one frame: boxes (N, 4) [x1, y1, x2, y2] px, scores (N,), labels (N,) 1..8."""

    boxes: np.ndarray
    scores: np.ndarray
    labels: np.ndarray

    @staticmethod
    def empty() -> Detections:
        return Detections(np.zeros((0, 4)), np.zeros(0), np.zeros(0, np.int64))

    def __len__(self) -> int:
        return len(self.scores)

    def __getitem__(self, index) -> Detections:
        return Detections(self.boxes[index], self.scores[index], self.labels[index])


def to_reference(dets: Detections, frame: str, calib: Calibration) -> Detections:
    """Map detections made in `frame` ("camera_left" | "camera_right" | "bev") to the right camera."""
    if frame not in FRAMES:
        raise ValueError(f"frame must be one of {FRAMES}, got {frame!r}")
    if len(dets) == 0 or frame == REFERENCE:
        return dets
    if frame == "bev":
        boxes, keep = bev_boxes_to_camera(dets.boxes, dets.labels, calib, REFERENCE)
        return Detections(boxes, dets.scores[keep], dets.labels[keep])
    boxes = camera_boxes_to_camera(dets.boxes, calib, frame, REFERENCE)
    cam = calib.camera(REFERENCE)
    boxes[:, [0, 2]] = np.clip(boxes[:, [0, 2]], 0, cam.width)
    boxes[:, [1, 3]] = np.clip(boxes[:, [1, 3]], 0, cam.height)
    ok = (boxes[:, 2] - boxes[:, 0] > 0.5) & (boxes[:, 3] - boxes[:, 1] > 0.5)
    return Detections(boxes[ok], dets.scores[ok], dets.labels[ok])


def fuse(per_branch: dict[str, Detections], frames: dict[str, str], calib: Calibration, method: str = "soft_nms",
         weights: dict[str, float] | None = None, **params) -> Detections:
    """Late fusion of several branches' detections into the right camera frame.

    Args:
        per_branch: branch name -> Detections in that branch's own frame.
        frames: branch name -> its frame ("camera_left", "camera_right", "bev").
        calib: the frame's Calibration (stored with every frame).
        method: "nms" | "soft_nms" | "wbf" (fusion.boxes; textbook behaviour). A single branch still
            goes through the method, which removes its duplicate boxes.
        weights: branch name -> weight (default 1 for every branch).
        params: overrides of HydraFusion's thresholds (iou_thr 0.4, skip_box_thr 0.01, sigma 0.5).
    """
    if method not in FUSION_METHODS:
        raise ValueError(f"unknown fusion method {method!r} (choose from: {', '.join(FUSION_METHODS.names())})")
    cam = calib.camera(REFERENCE)
    scale = np.array([cam.width, cam.height, cam.width, cam.height], float)
    names = [n for n in per_branch if len(per_branch[n])]
    if not names:
        return Detections.empty()
    mapped = {n: to_reference(per_branch[n], frames[n], calib) for n in names}
    names = [n for n in names if len(mapped[n])]
    if not names:
        return Detections.empty()
    kw = dict(HYDRAFUSION_PARAMS[method])
    kw.update(params)
    w = [float((weights or {}).get(n, 1.0)) for n in names]
    boxes, scores, labels = FUSION_METHODS.get(method)(
        [np.clip(mapped[n].boxes / scale, 0.0, 1.0) for n in names],
        [mapped[n].scores for n in names],
        [mapped[n].labels for n in names],
        weights=w, **kw,
    )
    return Detections(np.asarray(boxes) * scale, np.asarray(scores), np.asarray(labels).astype(np.int64))
