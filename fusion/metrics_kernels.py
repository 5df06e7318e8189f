"""The compiled core of the bootstrap's weighted AP (numba, cached on disk): `fusion.metrics.DrawScorer`."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def weighted_ap(image, tp, mult, n_pos):
    """(draws,) VOC all-point AP of one class's ranked detections under each draw's image
    multiplicities: `image` (D,) the image of each ranked detection, `tp` (D,) its flag, `mult`
    (draws, images), `n_pos` (draws,) the draw's non-difficult boxes (NaN where 0). Counts are
    integers, so precision is the same division as `fusion.metrics._recall_precision`'s."""
    n_draws, d = mult.shape[0], len(image)
    out = np.empty(n_draws)
    prec = np.empty(d)
    for r in range(n_draws):
        if n_pos[r] == 0:
            out[r] = np.nan
            continue
        ctp = 0
        cfp = 0
        for k in range(d):
            w = mult[r, image[k]]
            if tp[k]:
                ctp += w
            else:
                cfp += w
            n = ctp + cfp
            prec[k] = ctp / n if n > 0 else 0.0
        envelope = 0.0
        total = 0.0
        for k in range(d - 1, -1, -1):
            if prec[k] > envelope:
                envelope = prec[k]
            if tp[k]:
                total += mult[r, image[k]] * envelope
        out[r] = total / n_pos[r]
    return out
