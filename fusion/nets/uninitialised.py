"""Build a network without drawing its initial weights, for a network whose every weight is loaded next.

Building a HydraFusion network draws every weight from the global torch generator (Kaiming normal and
uniform), and each stem builds a whole torchvision ResNet-18 of which it keeps conv1 and layer1: about
0.1 s of random draws per stem on a 2-core CPU, 0.47 s per `cpu-frontier` build, most of a model's
loading time, spent on numbers that `load_state_dict` overwrites at once. Under `uninitialised()` the
draws are skipped: tensors keep the memory `torch.empty` gave them until they are loaded.

Only for a module loaded strictly afterwards (`load_state_dict(strict=True)` covers every parameter and
persistent buffer, or raises). The global generator is left where it was (no draw is made), so what
runs next draws what it would have drawn had the model been built before the seed it sets itself.
"""

from __future__ import annotations

import torch
from torch.overrides import TorchFunctionMode

_DRAWS = frozenset({
    torch.Tensor.normal_, torch.Tensor.uniform_,
    torch.nn.init.normal_, torch.nn.init.uniform_, torch.nn.init.trunc_normal_,
    torch.nn.init.kaiming_normal_, torch.nn.init.kaiming_uniform_,
    torch.nn.init.xavier_normal_, torch.nn.init.xavier_uniform_, torch.nn.init.orthogonal_,
})


class uninitialised(TorchFunctionMode):  # noqa: N801 -- used as a context: `with uninitialised(): build()`
    """`with uninitialised(): model = build(...)`: the model's random initial draws are not made (each
    returns its tensor as it is); every other torch call runs as usual."""

    def __torch_function__(self, func, types, args=(), kwargs=None):
        if func in _DRAWS:
            return args[0] if args else kwargs["tensor"]
        return func(*args, **(kwargs or {}))
