"""Compiled cores of the camera labels (numba, cached on disk).

`instance_boxes` gives the visible-pixel boxes that scipy.ndimage.find_objects gave, and
`visible_samples` repeats the numpy occlusion test of `sensors.labels.fwd_labels` operation by
operation in float64 (tests/sensors/test_labels.py compares both with those formulations).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, error_model="numpy")
def visible_samples(uv, z, instance, depth, actor_id, min_depth):
    """(in image, seen) counts of an actor's projected sample points: a point is in the image when
    z > min_depth and its floored pixel np.floor(uv).astype(int) lies in `instance`'s frame; it is
    seen when that pixel shows the actor or the rendered depth there is not nearer than the point
    by more than 0.3 m + 2 % (depth >= z - (0.3 + 0.02 z), float32 depth compared in float64)."""
    height, width = instance.shape
    n_in = 0
    n_seen = 0
    for k in range(z.shape[0]):
        dz = z[k]
        if not dz > min_depth:
            continue
        u = int(np.floor(uv[k, 0]))
        v = int(np.floor(uv[k, 1]))
        if u < 0 or u >= width or v < 0 or v >= height:
            continue
        n_in += 1
        if instance[v, u] == actor_id or np.float64(depth[v, u]) >= dz - (0.3 + 0.02 * dz):
            n_seen += 1
    return n_in, n_seen


@njit(cache=True)
def instance_boxes(instance, ids):
    """(len(ids), 4) int64 tight pixel boxes [row0, col0, row1, col1) of each id in `ids` (sorted,
    every one present in `instance`), as scipy.ndimage.find_objects gives them for the image of
    1-based positions of the ids (np.searchsorted(ids, instance) + 1 where instance > 0, else 0)."""
    n = ids.shape[0]
    boxes = np.empty((n, 4), np.int64)
    boxes[:, 0] = instance.shape[0]
    boxes[:, 1] = instance.shape[1]
    boxes[:, 2] = 0
    boxes[:, 3] = 0
    for r in range(instance.shape[0]):
        for c in range(instance.shape[1]):
            a = instance[r, c]
            if a > 0:
                k = np.searchsorted(ids, a)
                boxes[k, 0] = min(boxes[k, 0], r)
                boxes[k, 1] = min(boxes[k, 1], c)
                boxes[k, 2] = max(boxes[k, 2], r + 1)
                boxes[k, 3] = max(boxes[k, 3], c + 1)
    return boxes
