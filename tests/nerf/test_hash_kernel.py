"""The C hash-encoding kernel (csa_core/nerf/hash_kernel.py) against the PyTorch path, in the
field as the trainer and the renderer use it, and its fallback where it cannot be built."""

from __future__ import annotations

import logging

import pytest
import torch

from csa_core.nerf import hash_kernel
from csa_core.nerf.config import FieldConfig, HashEncodingConfig
from csa_core.nerf.field import SemanticField
from csa_core.nerf.hash_encoding import HashEncoding

needs_kernel = pytest.mark.skipif(
    not hash_kernel.available(), reason="no C compiler here: the kernel cannot be built"
)


def _fields(levels: int = 6) -> tuple[SemanticField, SemanticField]:
    """Two identical fields (random tables, dense and hashed levels, a semantic table of 4
    levels), the first encoding through the kernel, the second through PyTorch."""
    enc = HashEncodingConfig(
        num_levels=levels, log2_table_size=10, base_resolution=4, finest_resolution=128
    )
    cfg = FieldConfig(encoding=enc, semantic_grid_levels=4)
    kernel = SemanticField(cfg, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        g = torch.Generator().manual_seed(1)
        kernel.encoding.table.normal_(generator=g)
        kernel.semantic_table.normal_(generator=g)
    torch_cfg = FieldConfig(
        encoding=HashEncodingConfig(**{**vars(enc), "implementation": "torch"}),
        semantic_grid_levels=4,
    )
    reference = SemanticField(torch_cfg)
    reference.load_state_dict(kernel.state_dict())
    assert 0 < kernel.encoding._num_dense < levels
    return kernel, reference


def _positions(n: int = 700) -> torch.Tensor:
    x = torch.rand(n, 3, generator=torch.Generator().manual_seed(2))
    x[0], x[1], x[2] = torch.tensor([0.0, 0.0, 0.0]), torch.tensor([1.0, 1.0, 1.0]), 0.5
    x[3] = torch.tensor([-0.2, 1.3, 0.25])  # outside the cube: clamped to its faces
    return x


@needs_kernel
def test_kernel_and_pytorch_agree_forward_and_backward_in_the_field():
    kernel, reference = _fields()
    x = _positions()
    assert kernel.encoding.uses_kernel(x) and not reference.encoding.uses_kernel(x)
    dirs = torch.nn.functional.normalize(torch.randn(x.shape[0], 3), dim=-1)
    outs = [f(x, dirs) for f in (kernel, reference)]
    for key in ("sigma", "rgb", "semantic_logits"):
        torch.testing.assert_close(outs[0][key], outs[1][key], rtol=1e-4, atol=1e-5)
    for out in outs:
        (out["sigma"].sum() + out["rgb"].sum() + out["semantic_logits"].square().mean()).backward()
    for name in ("encoding.table", "semantic_table"):
        a = dict(kernel.named_parameters())[name].grad
        b = dict(reference.named_parameters())[name].grad
        assert a is not None and a.abs().sum() > 0
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)


@needs_kernel
def test_semantic_steps_train_only_the_semantic_table_through_the_kernel():
    """``SemanticField.semantics`` (the semantic-only steps): no gradient reaches the geometry
    table, and the semantic table's equals the PyTorch path's."""
    kernel, reference = _fields()
    x = _positions()
    for f in (kernel, reference):
        sigma, logits = f.semantics(x)
        assert not sigma.requires_grad
        logits.logsumexp(-1).sum().backward()
        assert f.encoding.table.grad is None
    torch.testing.assert_close(
        kernel.semantic_table.grad, reference.semantic_table.grad, rtol=1e-4, atol=1e-5
    )


@needs_kernel
def test_a_nan_position_reads_inside_the_table():
    """A NaN coordinate (a broken pose) must not index outside the table: it reads the cell at
    the origin, as a position clamped to 0 would."""
    enc = HashEncoding(HashEncodingConfig(num_levels=4, log2_table_size=10, finest_resolution=64))
    x = torch.tensor([[float("nan"), 0.5, 0.5], [0.0, 0.5, 0.5]])
    out = enc(x)
    assert torch.equal(out[0], out[1])


@needs_kernel
def test_the_kernel_follows_the_tensors_it_can_take():
    """Float32 CPU tensors use the kernel; other dtypes, or ``implementation=torch``, PyTorch."""
    enc = HashEncoding(HashEncodingConfig(num_levels=4, log2_table_size=10, finest_resolution=64))
    x = torch.rand(10, 3)
    assert enc.uses_kernel(x)
    assert not enc.uses_kernel(x.double())
    torch_enc = HashEncoding(
        HashEncodingConfig(
            num_levels=4, log2_table_size=10, finest_resolution=64, implementation="torch"
        )
    )
    assert not torch_enc.uses_kernel(x)


def test_without_a_compiler_the_encoding_stays_in_pytorch(monkeypatch, tmp_path, caplog):
    monkeypatch.setattr(hash_kernel, "_LIB", {})
    monkeypatch.setenv("CSA_KERNEL_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("CC", str(tmp_path / "no-such-compiler"))
    with caplog.at_level(logging.WARNING, logger="csa_core.nerf.hash_kernel"):
        assert not hash_kernel.available()
    assert "the encoding runs in PyTorch" in caplog.text
    assert not any((tmp_path / "cache").glob("*.so"))  # nothing half-built left behind
    enc = HashEncoding(HashEncodingConfig(num_levels=4, log2_table_size=10, finest_resolution=64))
    x = torch.rand(10, 3)
    assert not enc.uses_kernel(x) and enc(x).shape == (10, enc.out_dim)


def test_implementation_is_checked():
    with pytest.raises(ValueError, match="encoding.implementation must be 'auto' or 'torch'"):
        HashEncodingConfig(implementation="cuda")
