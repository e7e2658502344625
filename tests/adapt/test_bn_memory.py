"""Pooled BatchNorm statistics equal AdaBN over the union of the scenes' images.

Exactly so for a layer that sees the images through fixed weights (the first one, here the
only one); deeper layers see inputs normalised by per-scene instead of union statistics, so
there the mixture is an approximation.
"""

from __future__ import annotations

import torch
from torch import nn

from csa_core.adapt.bn_memory import BatchNormMemory
from csa_core.seg.adabn import recompute_batchnorm


def _net() -> nn.Module:
    torch.manual_seed(0)
    return nn.Sequential(nn.Conv2d(3, 4, 3), nn.BatchNorm2d(4), nn.ReLU(), nn.Conv2d(4, 2, 1))


def test_pooled_statistics_match_the_union_of_equal_sized_scenes():
    g = torch.Generator().manual_seed(1)
    a = torch.rand(8, 3, 12, 12, generator=g)
    b = 0.3 * torch.rand(8, 3, 12, 12, generator=g) + 0.6  # another "domain"
    model, union = _net(), _net()
    memory = BatchNormMemory()
    recompute_batchnorm(model, [a])
    memory.add("a", model)
    recompute_batchnorm(model, [b])
    memory.add("b", model)
    memory.apply(model)
    recompute_batchnorm(union, [torch.cat([a, b])])
    for bn, ref in zip(
        [m for m in model.modules() if isinstance(m, nn.BatchNorm2d)],
        [m for m in union.modules() if isinstance(m, nn.BatchNorm2d)],
        strict=True,
    ):
        torch.testing.assert_close(bn.running_mean, ref.running_mean, rtol=1e-4, atol=1e-5)
        # BatchNorm keeps the unbiased variance per batch, the pooled one is of two halves:
        # equal up to the n/(n-1) factor, which at 8 x 10 x 10 pixels is below 1e-3.
        torch.testing.assert_close(bn.running_var, ref.running_var, rtol=2e-3, atol=1e-5)
    assert memory.nbytes() == 2 * 2 * 4 * 4  # scenes x (mean, var) x channels x float32


def test_re_adding_a_scene_replaces_its_record_and_empty_memory_changes_nothing():
    model = _net()
    before = [t.clone() for t in model.state_dict().values()]
    memory = BatchNormMemory()
    memory.apply(model)
    assert all(torch.equal(x, y) for x, y in zip(before, model.state_dict().values(), strict=True))
    memory.add("a", model)
    memory.add("a", model)
    assert list(memory.scenes) == ["a"]
