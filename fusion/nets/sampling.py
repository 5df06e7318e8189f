"""Per-frame seeded anchor and RoI sampling for the Faster R-CNN heads of every branch.

torchvision's RPN and RoI heads pick the anchors and RoIs that enter their losses at random
(`BalancedPositiveNegativeSampler`: up to `batch_size_per_image` per image, at most
`positive_fraction` of them objects) with torch's global generator, one image after the other.
Which samples an image gets therefore depends on the images before it in the batch and on the
process: a batch split over data-parallel processes draws different samples than the same batch
in one process. `FrameSeededSampler` draws each image's samples with its own generator, seeded
from a key the caller sets per image (training: seed, step, dataset index, branch, stage), so an
image's samples are a pure function of that key: the same in one process, in two, in any order.

With the default counts (256 anchors, 128 RoIs per image; an image nearly always has that many
negatives) every image contributes the same number of samples, so the batch loss, torchvision's
mean over all sampled anchors / RoIs of the batch, equals the mean over images of the per-image
losses, and the mean of per-process batch losses (what DDP's gradient averaging computes) equals
the one-process loss of the whole batch.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor
from torchvision.models.detection._utils import BalancedPositiveNegativeSampler

STAGES = {"rpn": 0, "roi": 1}


def sample_seed(*key: int) -> int:
    """A 63-bit generator seed from integer key parts (numpy SeedSequence hashing)."""
    return int(np.random.SeedSequence([int(k) for k in key]).generate_state(1, np.uint64)[0] >> np.uint64(1))


class FrameSeededSampler(BalancedPositiveNegativeSampler):
    """`BalancedPositiveNegativeSampler` with one generator per image.

    `seeds`: list of ints, one per image of the next call (set before each forward); None makes the
    sampler behave exactly like torchvision's (global generator). Each image's positives and
    negatives are chosen by `torch.randperm` on a CPU generator seeded with its seed.
    """

    def __init__(self, batch_size_per_image: int, positive_fraction: float) -> None:
        super().__init__(batch_size_per_image, positive_fraction)
        self.seeds: list[int] | None = None

    def __call__(self, matched_idxs: list[Tensor]) -> tuple[list[Tensor], list[Tensor]]:
        if self.seeds is None:
            return super().__call__(matched_idxs)
        if len(self.seeds) != len(matched_idxs):
            raise ValueError(f"seeds: {len(self.seeds)} for {len(matched_idxs)} images")
        pos_masks, neg_masks = [], []
        for m, seed in zip(matched_idxs, self.seeds):
            g = torch.Generator().manual_seed(int(seed))
            positive = torch.where(m >= 1)[0]
            negative = torch.where(m == 0)[0]
            n_pos = min(positive.numel(), int(self.batch_size_per_image * self.positive_fraction))
            n_neg = min(negative.numel(), self.batch_size_per_image - n_pos)
            take_pos = positive[torch.randperm(positive.numel(), generator=g)[:n_pos].to(positive.device)]
            take_neg = negative[torch.randperm(negative.numel(), generator=g)[:n_neg].to(negative.device)]
            pos, neg = torch.zeros_like(m, dtype=torch.uint8), torch.zeros_like(m, dtype=torch.uint8)
            pos[take_pos] = 1
            neg[take_neg] = 1
            pos_masks.append(pos)
            neg_masks.append(neg)
        return pos_masks, neg_masks


def use_frame_seeded_sampling(model) -> None:
    """Replace the samplers of every branch's RPN and RoI heads by `FrameSeededSampler`s with the
    same counts (they keep torchvision's behaviour until `set_sample_keys` gives them seeds)."""
    for branch in model.branches.values():
        for head in (branch.rpn, branch.roi_heads):
            old = head.fg_bg_sampler
            if not isinstance(old, FrameSeededSampler):
                head.fg_bg_sampler = FrameSeededSampler(old.batch_size_per_image, old.positive_fraction)


def set_sample_keys(model, keys: list[tuple[int, ...]] | None) -> None:
    """Seed every branch's samplers for the next training forward: `keys[j]` identifies image j of
    the batch (e.g. (seed, step, dataset index)); the branch's position and the stage are appended.
    None: back to torch's global generator. Needs `use_frame_seeded_sampling` first."""
    for b, branch in enumerate(model.branches.values()):
        for stage, head in (("rpn", branch.rpn), ("roi", branch.roi_heads)):
            sampler = head.fg_bg_sampler
            if not isinstance(sampler, FrameSeededSampler):
                raise TypeError("set_sample_keys: call use_frame_seeded_sampling(model) first")
            sampler.seeds = None if keys is None else [sample_seed(*k, b, STAGES[stage]) for k in keys]
