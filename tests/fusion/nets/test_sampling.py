"""Per-frame seeded anchor / RoI sampling: an image's draw depends on its key alone."""

import torch
from torchvision.models.detection._utils import BalancedPositiveNegativeSampler

from fusion.nets.sampling import FrameSeededSampler, sample_seed


def _matched(n, n_pos, n_ignored, seed):
    g = torch.Generator().manual_seed(seed)
    m = torch.zeros(n, dtype=torch.int64)
    idx = torch.randperm(n, generator=g)
    m[idx[:n_pos]] = torch.randint(1, 5, (n_pos,), generator=g)
    m[idx[n_pos:n_pos + n_ignored]] = -1
    return m


def test_an_images_draw_does_not_depend_on_the_other_images_of_its_batch():
    a, b, c = _matched(900, 40, 100, 0), _matched(700, 5, 50, 1), _matched(800, 200, 0, 2)
    s = FrameSeededSampler(256, 0.5)
    s.seeds = [11, 22, 33]
    pos3, neg3 = s([a, b, c])
    s.seeds = [22]
    pos1, neg1 = s([b])
    assert torch.equal(pos3[1], pos1[0]) and torch.equal(neg3[1], neg1[0])
    s.seeds = [33, 11]
    pos2, neg2 = s([c, a])  # another order, another batch: the same draw per image
    assert torch.equal(pos2[1], pos3[0]) and torch.equal(neg2[0], neg3[2])
    # torchvision's counts: at most 128 positives, 256 in all, only from labelled anchors
    for m, p, n in zip([a, b, c], pos3, neg3):
        assert int(p.sum()) == min(int((m >= 1).sum()), 128)
        assert int(p.sum() + n.sum()) == 256
        assert bool((m[p.bool()] >= 1).all()) and bool((m[n.bool()] == 0).all())
    s.seeds = [12, 22, 33]
    assert not torch.equal(s([a, b, c])[1][0], neg3[0])  # another key, another draw


def test_without_seeds_it_is_torchvisions_sampler():
    ms = [_matched(900, 40, 100, 0), _matched(700, 5, 50, 1)]
    torch.manual_seed(5)
    ref = BalancedPositiveNegativeSampler(128, 0.25)(ms)
    torch.manual_seed(5)
    mine = FrameSeededSampler(128, 0.25)(ms)
    for x, y in zip(ref[0] + ref[1], mine[0] + mine[1]):
        assert torch.equal(x, y)


def test_seeds_are_stable_hashes_of_their_keys():
    assert sample_seed(0, 3, 17) == sample_seed(0, 3, 17)
    assert len({sample_seed(0, s, i) for s in range(20) for i in range(20)}) == 400
    assert 0 <= sample_seed(2**40, 1) < 2**63
