"""Shared fixtures: a tiny HydraFusion (cpu profile, small images and heads) and random batches."""

import pytest
import torch

from fusion.nets import FRAMES, SENSORS, build_hydrafusion

torch.set_num_threads(min(2, torch.get_num_threads()))

# The cpu profile's architecture at test size: 64 x 96 camera and 64 x 64 BEV images, narrower
# RoI heads and fewer proposals, so a seven-branch forward + backward takes about a second.
TINY = {
    "camera": {"size": (64, 96)},
    "bev": {"size": (64, 64)},
    "roi_channels": 32,
    "box_head_width": 64,
    "box_batch_size_per_image": 32,
    "rpn_pre_nms_top_n_train": 200,
    "rpn_post_nms_top_n_train": 100,
    "rpn_pre_nms_top_n_test": 100,
    "rpn_post_nms_top_n_test": 50,
}


def make_inputs(model, batch, seed=0, sensors=None):
    """Random float inputs in 0..1 for every sensor (or `sensors`) at the model's sizes."""
    g = torch.Generator().manual_seed(seed)
    out = {}
    for s in sensors or SENSORS:
        h, w = model.transform.image_size(s)
        out[s] = torch.rand(batch, SENSORS[s].channels, h, w, generator=g)
    return out


def make_targets(model, batch, seed=0, n=3):
    """Random boxes (8..30 px) and labels 1..8 inside every frame."""
    g = torch.Generator().manual_seed(seed + 1000)
    out = []
    for _ in range(batch):
        t = {}
        for frame, view in FRAMES.items():
            h, w = model.transform.sizes[view]
            wh = 8 + torch.rand(n, 2, generator=g) * 22
            xy = torch.rand(n, 2, generator=g) * (torch.tensor([w, h]) - wh)
            t[frame] = {
                "boxes": torch.cat([xy, xy + wh], 1),
                "labels": torch.randint(1, 9, (n,), generator=g),
            }
        out.append(t)
    return out


@pytest.fixture(scope="session")
def _tiny_model():
    torch.manual_seed(0)
    return build_hydrafusion(profile="cpu", **TINY)


@pytest.fixture
def model(_tiny_model):
    """The session's seven-branch tiny model, in eval mode with no gradients, no gate, no fusion."""
    _tiny_model.eval()
    _tiny_model.zero_grad(set_to_none=True)
    return _tiny_model
