"""The hash encoding against a direct per-level, per-corner implementation: every test runs
twice, through the C kernel (csa_core/nerf/hash_kernel.py) and through the PyTorch path."""

from __future__ import annotations

import pytest
import torch

from csa_core.nerf import hash_kernel
from csa_core.nerf.config import HashEncodingConfig
from csa_core.nerf.hash_encoding import HashEncoding, level_resolutions


@pytest.fixture(params=["kernel", "torch"], autouse=True)
def implementation(request, monkeypatch):
    if request.param == "torch":
        monkeypatch.setattr(HashEncoding, "uses_kernel", lambda self, x, table=None: False)
    elif not hash_kernel.available():
        pytest.skip("no C compiler here: the kernel cannot be built")
    return request.param


def _reference_encoding(enc: HashEncoding, x: torch.Tensor) -> torch.Tensor:
    """Trilinear interpolation level by level, corner by corner, with Python-int hashing."""
    cfg = enc.cfg
    T = 2**cfg.log2_table_size
    feats = []
    offset = 0
    for res, size in zip(level_resolutions(cfg), enc.level_sizes, strict=True):
        dense = (res + 1) ** 3 <= T
        pos = x.double() * res
        cell = pos.floor().clamp(max=res - 1)
        frac = pos - cell
        out = torch.zeros(x.shape[0], cfg.features_per_level, dtype=torch.float64)
        for corner in range(8):
            bits = [(corner >> a) & 1 for a in range(3)]
            w = torch.ones(x.shape[0], dtype=torch.float64)
            rows = []
            for i in range(x.shape[0]):
                c = [int(cell[i, a]) + bits[a] for a in range(3)]
                if dense:
                    r = c[0] + c[1] * (res + 1) + c[2] * (res + 1) ** 2
                else:
                    r = ((c[0] * 1) ^ (c[1] * 2654435761) ^ (c[2] * 805459861)) % (2**32) % size
                rows.append(offset + r)
            for a in range(3):
                w = w * (frac[:, a] if bits[a] else 1 - frac[:, a])
            out += w[:, None] * enc.table.detach().double()[torch.tensor(rows)]
        feats.append(out)
        offset += size
    return torch.cat(feats, dim=1)


def _random_table_encoding(
    num_levels: int, log2_table_size: int, base: int, finest: int
) -> HashEncoding:
    """An encoding with 2 features per level whose table is filled with N(0, 1) values (the
    default initialisation is too small to tell rows apart)."""
    cfg = HashEncodingConfig(
        num_levels=num_levels,
        features_per_level=2,
        log2_table_size=log2_table_size,
        base_resolution=base,
        finest_resolution=finest,
    )
    enc = HashEncoding(cfg, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        enc.table.normal_(generator=torch.Generator().manual_seed(1))
    return enc


def test_matches_direct_implementation_on_dense_and_hashed_levels():
    enc = _random_table_encoding(num_levels=6, log2_table_size=10, base=4, finest=64)
    x = torch.rand(50, 3, generator=torch.Generator().manual_seed(2))
    x[0] = torch.tensor([1.0, 1.0, 1.0])  # far corner of the cube
    x[1] = torch.tensor([0.0, 0.5, 1.0])
    assert 0 < enc._num_dense < enc.cfg.num_levels
    got = enc(x).double()
    torch.testing.assert_close(got, _reference_encoding(enc, x), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("features", [2, 3])  # 2: the complex scatter; 3: the general one
def test_backward_scatters_into_the_touched_rows(features):
    cfg = HashEncodingConfig(
        num_levels=4,
        features_per_level=features,
        log2_table_size=12,
        base_resolution=4,
        finest_resolution=128,
    )
    enc = HashEncoding(cfg, generator=torch.Generator().manual_seed(0))
    x = torch.rand(20, 3, generator=torch.Generator().manual_seed(3))
    w = torch.randn(20, enc.out_dim, generator=torch.Generator().manual_seed(4))
    (enc(x) * w).sum().backward()
    # Autograd through a plain gather gives the same gradient.
    rows, weights = enc.corners(x)
    table = enc.table.detach().clone().requires_grad_()
    assert rows.shape == weights.shape == (4, 20, 8)  # (levels, samples, corners)
    plain = (table[rows] * weights[..., None]).sum(2).transpose(0, 1).reshape(20, -1)
    (plain * w).sum().backward()
    torch.testing.assert_close(enc.table.grad, table.grad, rtol=1e-5, atol=1e-6)
    assert enc.table.grad.abs().sum() > 0


def test_int32_hashing_matches_uint32_reference_at_fine_resolutions():
    # Cell coordinates up to 2048 times the primes overflow 32 bits many times over: the int32
    # arithmetic must still give the paper's uint32 hash modulo a 2^19 table.
    enc = _random_table_encoding(num_levels=3, log2_table_size=19, base=512, finest=2048)
    x = torch.rand(40, 3, generator=torch.Generator().manual_seed(5)) * 0.2 + 0.8
    assert enc._num_dense == 0
    torch.testing.assert_close(enc(x).double(), _reference_encoding(enc, x), rtol=1e-5, atol=1e-5)


def test_inference_blocks_give_the_same_features(monkeypatch):
    from csa_core.nerf import hash_encoding

    cfg = HashEncodingConfig(
        num_levels=5,
        features_per_level=2,
        log2_table_size=11,
        base_resolution=4,
        finest_resolution=96,
    )
    enc = HashEncoding(cfg, generator=torch.Generator().manual_seed(0))
    extra = torch.randn(enc.level_rows(3), 3, generator=torch.Generator().manual_seed(6))
    x = torch.rand(1000, 3, generator=torch.Generator().manual_seed(7))
    whole, whole_extra = enc(x, extra, 3)  # gradients on: one block
    monkeypatch.setattr(hash_encoding, "INFERENCE_BLOCK", 128)
    with torch.no_grad():
        blocked, blocked_extra = enc(x, extra, 3)
        alone = enc(x)
    assert torch.equal(blocked, whole.detach())
    assert torch.equal(blocked_extra, whole_extra)
    assert torch.equal(alone, whole.detach())


def test_corners_of_the_first_levels_are_those_of_all_levels():
    """The renderer finds the corners of the semantic levels alone; they must be the first
    levels' corners of the full computation (dense and hashed levels alike)."""
    cfg = HashEncodingConfig(
        num_levels=6, log2_table_size=10, base_resolution=4, finest_resolution=96
    )
    enc = HashEncoding(cfg, generator=torch.Generator().manual_seed(0))
    x = torch.rand(300, 3, generator=torch.Generator().manual_seed(1))
    rows, weights = enc.corners(x)
    for levels in (1, 3, 6):
        r, w = enc.corners(x, levels)
        assert torch.equal(r, rows[:levels]) and torch.equal(w, weights[:levels])
    assert 0 < enc._num_dense < 6  # both kinds of level are covered


@pytest.mark.slow
def test_compiled_corners_agree_with_the_eager_reference():
    """``HashEncodingConfig.compile`` runs the corner computation through torch.compile (tens of
    seconds to compile on a CPU, hence slow); it must give the eager rows and weights exactly."""
    cfg = HashEncodingConfig(
        num_levels=6, log2_table_size=10, base_resolution=4, finest_resolution=96
    )
    cfg.compile = True
    enc = HashEncoding(cfg, generator=torch.Generator().manual_seed(0))
    for n in (300, 1000):  # two sizes: one compiled graph with dynamic shapes
        x = torch.rand(n, 3, generator=torch.Generator().manual_seed(n))
        rows, weights = enc.corners(x)
        ref_rows, ref_weights = enc.corners_eager(x)
        assert torch.equal(rows, ref_rows)
        torch.testing.assert_close(weights, ref_weights, atol=1e-7, rtol=0)
        r, w = enc.corners(x, 3)
        assert torch.equal(r, ref_rows[:3])


def test_zero_positions_give_empty_features_with_gradients():
    """A batch without samples (e.g. every ray skipped by an empty occupancy grid) encodes to
    empty features, through the corners and both tables, and still backpropagates."""
    from csa_core.nerf.config import FieldConfig
    from csa_core.nerf.field import SemanticField

    enc = HashEncoding(HashEncodingConfig(num_levels=4, log2_table_size=10, finest_resolution=64))
    x = torch.zeros(0, 3)
    rows, weights = enc.corners(x)
    assert rows.shape == weights.shape == (4, 0, 8)
    assert enc.interpolate(rows, weights).shape == (0, enc.out_dim)
    extra = torch.zeros(enc.level_rows(2), 3)
    feats, more = enc(x, extra, 2)
    assert feats.shape == (0, enc.out_dim) and more.shape == (0, 6)

    field = SemanticField(FieldConfig(encoding=enc.cfg), generator=torch.Generator().manual_seed(0))
    sigma, logits = field.semantics(x)
    assert sigma.shape == (0,) and logits.shape[0] == 0
    out = field(x, torch.zeros(0, 3))
    assert out["rgb"].shape == (0, 3) and out["semantic_logits"].shape == logits.shape
    (logits.sum() + out["rgb"].sum()).backward()
    assert all(p.grad is None or not p.grad.any() for p in field.parameters())
