"""Compiled core of the camera labels' occlusion test (numba, cached on disk).

`visible_samples` repeats the numpy test of `sensors.labels.fwd_labels` operation by operation in
float64 (tests/sensors/test_labels.py compares it with that formulation on real frames).
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
