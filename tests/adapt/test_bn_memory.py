"""Pooled BatchNorm statistics equal AdaBN over the union of the scenes' images.

Exactly so for a layer that sees the images through fixed weights (the first one, here the
only one); deeper layers see inputs normalised by per-scene instead of union statistics, so
there the mixture is an approximation.
"""

from __future__ import annotations

import copy

import pytest
import torch
from torch import nn

from csa_core.adapt.bn_memory import BatchNormMemory
from csa_core.errors import CSAInputError
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


def _recorded(scenes: int) -> tuple[nn.Module, BatchNormMemory]:
    g = torch.Generator().manual_seed(2)
    model, memory = _net(), BatchNormMemory()
    for k in range(scenes):
        recompute_batchnorm(model, [torch.rand(4, 3, 8, 8, generator=g) * (k + 1)])
        memory.add(f"scene {k}/ü", model)  # any name: names live in the header
    return model, memory


def test_save_and_load_keep_every_record_bit_for_bit_in_order(tmp_path):
    model, memory = _recorded(3)
    path = tmp_path / "bn.safetensors"
    assert memory.save(path) == path.stat().st_size
    loaded = BatchNormMemory.load(path)
    assert list(loaded.scenes) == list(memory.scenes)
    for name, record in memory.scenes.items():
        for (m, v), (lm, lv) in zip(record, loaded.scenes[name], strict=True):
            assert torch.equal(m, lm) and torch.equal(v, lv)
    # The pooled statistics of the loaded memory are those of the original, bit for bit.
    other = copy.deepcopy(model)
    memory.apply(model)
    loaded.apply(other)
    assert all(
        torch.equal(a, b)
        for a, b in zip(model.state_dict().values(), other.state_dict().values(), strict=True)
    )


def test_a_damaged_or_foreign_file_is_an_input_error_naming_it(tmp_path):
    _, memory = _recorded(2)
    good = memory.to_bytes()
    cases = {
        "cut.safetensors": good[: len(good) // 2],
        "text.safetensors": b"not a tensor file",
    }
    from safetensors.torch import save

    cases["foreign.safetensors"] = save({"w": torch.zeros(2)}, metadata={"csa": '{"format": "x"}'})
    cases["missing.safetensors"] = save(
        {"0.0.mean": torch.zeros(4)},
        metadata={"csa": '{"format": "csa-batchnorm-memory", "version": 1, "scenes": ["a"]}'},
    )
    for name, data in cases.items():
        path = tmp_path / name
        path.write_bytes(data)
        with pytest.raises(CSAInputError, match=name):
            BatchNormMemory.load(path)
    with pytest.raises(CSAInputError, match="not found"):
        BatchNormMemory.load(tmp_path / "absent.safetensors")


def test_records_of_another_network_are_refused():
    _, memory = _recorded(1)
    torch.manual_seed(0)
    wider = nn.Sequential(nn.Conv2d(3, 6, 3), nn.BatchNorm2d(6))
    with pytest.raises(ValueError, match="do not match"):
        memory.apply(wider)


def test_one_record_is_applied_bit_for_bit():
    """The mixture of one scene is that scene's statistics exactly (not (v + m^2) - m^2, which
    differs by rounding), so a one-scene run and one adapt job end with the same statistics."""
    model, memory = _recorded(1)
    recorded = [t.clone() for pair in memory.scenes["scene 0/ü"] for t in pair]
    for bn in (m for m in model.modules() if isinstance(m, nn.BatchNorm2d)):
        bn.running_mean.add_(1.0)  # anything else
    memory.apply(model)
    applied = [
        t
        for m in model.modules()
        if isinstance(m, nn.BatchNorm2d)
        for t in (m.running_mean, m.running_var)
    ]
    assert all(torch.equal(a, b) for a, b in zip(applied, recorded, strict=True))
    # The formula the mixture uses would not have given them back exactly here.
    mean, var = memory.scenes["scene 0/ü"][0]
    assert not torch.equal((var + mean.square()) - mean.square(), var)
