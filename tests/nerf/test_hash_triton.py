"""The Triton hash-encoding kernel (csa_core/nerf/hash_triton.py) against the PyTorch reference.

On a CPU the kernel runs in Triton's interpreter (CPU tensors), so the same source that CUDA
compiles is checked here: features, both tables' gradients, NaN positions, and the encoding's
dispatch and fallback."""

from __future__ import annotations

import dataclasses
import logging

import pytest
import torch

from csa_core.nerf import hash_triton
from csa_core.nerf.config import FieldConfig, HashEncodingConfig
from csa_core.nerf.field import SemanticField
from csa_core.nerf.hash_encoding import HashEncoding

pytest.importorskip("triton.runtime.interpreter")

# 6 levels: dense ones, then hashed ones (16^3 < 2^12 < 34^3)
SMALL = HashEncodingConfig(
    num_levels=6, log2_table_size=12, base_resolution=4, finest_resolution=128
)


def _encoding(cfg: HashEncodingConfig = SMALL, seed: int = 0) -> HashEncoding:
    enc = HashEncoding(cfg, generator=torch.Generator().manual_seed(seed))
    with torch.no_grad():  # values far from the tiny initialisation: errors would show
        enc.table.uniform_(-1.0, 1.0, generator=torch.Generator().manual_seed(seed + 1))
    return enc


def _positions(n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 3, generator=g) * 1.2 - 0.1  # some outside the cube: clamped
    x[:8] = torch.tensor([[0, 0, 0], [1, 1, 1], [1, 0, 1], [0.5, 1, 0]] * 2, dtype=torch.float32)
    return x


def _reference(
    enc: HashEncoding, x: torch.Tensor, table: torch.Tensor, levels: int
) -> torch.Tensor:
    rows, w = enc.corners_eager(x, levels)
    return enc.interpolate(rows, w, table)


@pytest.mark.parametrize("seed", [0, 1])
def test_features_match_the_reference(seed):
    enc = _encoding(seed=seed)
    assert 0 < enc._num_dense < SMALL.num_levels  # both kinds of level are covered
    x = _positions(300, seed)
    got = hash_triton.encode(x, enc.table.detach(), SMALL.num_levels, enc.kernel_layout())
    want = _reference(enc, x, enc.table.detach(), SMALL.num_levels)
    assert got.shape == want.shape == (300, SMALL.num_levels * SMALL.features_per_level)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)


def test_table_gradient_matches_the_reference():
    enc = _encoding(seed=3)
    x = _positions(300, 3)
    grad_out = torch.randn(300, SMALL.num_levels * 2, generator=torch.Generator().manual_seed(4))
    ref_table = enc.table.detach().clone().requires_grad_(True)
    (_reference(enc, x, ref_table, SMALL.num_levels) * grad_out).sum().backward()
    table = enc.table.detach().clone().requires_grad_(True)
    (
        hash_triton.encode(x, table, SMALL.num_levels, enc.kernel_layout()) * grad_out
    ).sum().backward()
    assert table.grad.abs().sum() > 0
    torch.testing.assert_close(table.grad, ref_table.grad, rtol=1e-5, atol=1e-5)


def test_a_second_table_over_the_first_levels():
    enc = _encoding(seed=5)
    levels = 3
    extra = torch.randn(enc.level_rows(levels), 2, generator=torch.Generator().manual_seed(6))
    x = _positions(200, 5)
    got = hash_triton.encode(x, extra, levels, enc.kernel_layout())
    torch.testing.assert_close(got, _reference(enc, x, extra, levels), rtol=1e-5, atol=1e-6)


def test_four_features_per_level():
    cfg = HashEncodingConfig(
        num_levels=4, features_per_level=4, log2_table_size=10, base_resolution=4,
        finest_resolution=64,
    )  # fmt: skip
    enc = _encoding(cfg, seed=7)
    x = _positions(200, 7)
    got = hash_triton.encode(x, enc.table.detach(), 4, enc.kernel_layout())
    torch.testing.assert_close(got, _reference(enc, x, enc.table.detach(), 4), rtol=1e-5, atol=1e-6)


def test_nan_positions_read_the_origin_cell():
    enc = _encoding(seed=8)
    x = torch.tensor([[float("nan"), 0.3, 0.7], [0.0, 0.3, 0.7]])
    got = hash_triton.encode(x, enc.table.detach(), SMALL.num_levels, enc.kernel_layout())
    assert torch.isfinite(got).all()
    torch.testing.assert_close(got[0], got[1])


def test_an_empty_batch():
    enc = _encoding()
    got = hash_triton.encode(torch.zeros(0, 3), enc.table.detach(), 2, enc.kernel_layout())
    assert got.shape == (0, 4)


def test_the_field_agrees_through_the_kernel(monkeypatch):
    """A whole field, outputs and every table's gradient, with the encoding routed through
    the kernel (as on CUDA) against ``implementation=torch``."""
    cfg = FieldConfig(encoding=dataclasses.replace(SMALL), semantic_grid_levels=3)
    x = _positions(150, 9).clamp(0, 1)
    dirs = torch.randn(150, 3, generator=torch.Generator().manual_seed(10))
    dirs = torch.nn.functional.normalize(dirs, dim=-1)

    def run(implementation: str) -> tuple[dict, dict]:
        cfg.encoding.implementation = implementation
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(11)  # the MLPs' initialisation, the same in both runs
            field = SemanticField(cfg, generator=torch.Generator().manual_seed(11))
        with torch.no_grad():
            field.encoding.table.uniform_(-0.5, 0.5, generator=torch.Generator().manual_seed(12))
            field.semantic_table.uniform_(-0.5, 0.5, generator=torch.Generator().manual_seed(13))
        out = field(x, dirs)
        loss = out["sigma"].sum() + out["rgb"].sum() + out["semantic_logits"].square().sum()
        loss.backward()
        grads = {"table": field.encoding.table.grad, "semantic": field.semantic_table.grad}
        return {k: v.detach() for k, v in out.items()}, grads

    monkeypatch.setattr(hash_triton, "usable", lambda x, table: True)
    monkeypatch.setattr("csa_core.nerf.hash_kernel.usable", lambda x, table: False)
    through_kernel = run("auto")
    eager = run("torch")
    for key in eager[0]:
        torch.testing.assert_close(through_kernel[0][key], eager[0][key], rtol=1e-4, atol=1e-5)
    for key in eager[1]:
        torch.testing.assert_close(through_kernel[1][key], eager[1][key], rtol=1e-4, atol=1e-5)


def test_a_failing_kernel_falls_back_to_pytorch(monkeypatch, caplog):
    enc = _encoding(seed=14)
    x = _positions(50, 14).clamp(0, 1)
    want = _reference(enc, x, enc.table.detach(), SMALL.num_levels)

    def broken(*args, **kwargs):
        raise RuntimeError("no kernel for this device")

    monkeypatch.setattr(hash_triton, "usable", lambda x, table: True)
    monkeypatch.setattr("csa_core.nerf.hash_kernel.usable", lambda x, table: False)
    monkeypatch.setattr(hash_triton, "encode", broken)
    monkeypatch.setattr(hash_triton, "_FAILED", {})
    with caplog.at_level(logging.WARNING, logger="csa_core.nerf.hash_triton"):
        with torch.no_grad():
            got = enc(x)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
    assert hash_triton._FAILED["cuda"] is True
    assert "runs in PyTorch" in caplog.text


def test_cpu_tensors_do_not_use_the_kernel():
    enc = _encoding()
    assert not hash_triton.usable(torch.zeros(4, 3), enc.table)
    assert not enc.uses_triton(torch.zeros(4, 3))
