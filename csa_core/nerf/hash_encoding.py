"""Multi-resolution hash encoding (Instant-NGP, Mueller et al. 2022) in plain PyTorch.

Positions live in the unit cube [0, 1]^3 (see ``normalization.py``). Level ``l`` has a grid
of resolution ``N_l = floor(N_min * b^l)`` with ``b`` chosen so the last level reaches
``finest_resolution``. Coarse levels whose grid fits in the table are indexed densely, finer
ones through the spatial hash. All levels share one parameter tensor (``table``), each level
owning a contiguous block of rows, so one gather serves every level and corner.

CPU notes: corner indices and trilinear weights are built per axis (2 values per axis) and
combined by broadcasting, which is ~8x less integer work than hashing 8 corners; the forward
pass is one ``embedding_bag`` (gather + weighted sum), the backward pass one ``index_add_``.
No gradient flows to the positions (the poses are fixed). Without autograd (rendering), large
batches are encoded in cache-sized blocks (``INFERENCE_BLOCK``).
On a CPU, float32 positions go through the fused C kernel of ``hash_kernel.py`` instead, on CUDA
through the Triton kernel of ``hash_triton.py`` (same arithmetic;
``HashEncodingConfig.implementation``); this module's path is their reference. On CUDA the
inference blocks above are not used: one launch over every position fills the device.
"""

from __future__ import annotations

import logging
import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from csa_core.nerf import hash_kernel, hash_triton
from csa_core.nerf.config import HashEncodingConfig

# Spatial-hash primes of Instant-NGP (x uses 1).
_PRIMES = (1, 2654435761, 805459861)


def _as_int32(value: int) -> int:
    """``value`` mod 2^32 as a signed 32-bit number (same low bits)."""
    return (value + 2**31) % 2**32 - 2**31


# Corner rows are computed in int32: products wrap modulo 2^32 exactly like the paper's uint32
# hash, and the mask keeps only low bits, so the rows equal the uint32 hash for power-of-two
# tables (tests/nerf compares them with an int64 reference). Half the memory traffic of
# int64: on a 2-core EPYC the hashing of 16k positions x 15 levels fell from 6.7 to 3.1 ms.
_INDEX = torch.int32
_INIT_SCALE = 1e-4  # table initialised uniformly in [-1e-4, 1e-4] (Instant-NGP)
# Without gradients, positions are encoded this many at a time. The corner tables are
# (levels x 8 x N) integers, so at rendering sizes (10^5-10^6 samples) every elementwise step
# streams hundreds of MB through memory; in blocks of 2^15 they stay in cache. Measured on a
# 2-core EPYC, 16 levels, 245,760 positions: 1879 ms in one block, 416 ms in blocks of 2^15.
INFERENCE_BLOCK = 2**15

log = logging.getLogger(__name__)


def level_resolutions(cfg: HashEncodingConfig) -> list[int]:
    """Grid resolution of every level."""
    if cfg.num_levels == 1:
        return [cfg.base_resolution]
    b = math.exp(
        (math.log(cfg.finest_resolution) - math.log(cfg.base_resolution)) / (cfg.num_levels - 1)
    )
    return [int(math.floor(cfg.base_resolution * b**level)) for level in range(cfg.num_levels)]


class _HashGather(torch.autograd.Function):
    """Weighted gather of table rows for idx, w ``(L, N, 8)``:
    ``out[l, i] = sum_k w[l, i, k] * table[idx[l, i, k]]`` -> ``(L, N, F)``."""

    @staticmethod
    def forward(ctx, table: Tensor, idx: Tensor, w: Tensor) -> Tensor:
        ctx.save_for_backward(idx, w)
        ctx.num_rows = table.shape[0]
        levels, n, _ = idx.shape
        out = F.embedding_bag(
            idx.reshape(levels * n, 8),
            table,
            per_sample_weights=w.reshape(levels * n, 8),
            mode="sum",
        )
        return out.view(levels, n, -1)

    @staticmethod
    def backward(ctx, grad: Tensor):
        idx, w = ctx.saved_tensors
        flat = idx.reshape(-1)
        if grad.shape[-1] == 2 and grad.dtype == torch.float32:
            # Two features scatter as one complex64 number: ~3x faster than a 2-column index_add_.
            gc = torch.view_as_complex(grad.contiguous())  # L N
            g = torch.zeros(ctx.num_rows, dtype=torch.complex64, device=grad.device)
            g.index_add_(0, flat, (gc.unsqueeze(-1) * w).reshape(-1))
            return torch.view_as_real(g), None, None
        src = w.unsqueeze(-1) * grad.unsqueeze(2)  # L N 8 F
        g = torch.zeros(ctx.num_rows, grad.shape[-1], dtype=grad.dtype, device=grad.device)
        g.index_add_(0, flat, src.reshape(-1, grad.shape[-1]))
        return g, None, None


class HashEncoding(nn.Module):
    """``(N, 3)`` positions in [0, 1]^3 -> ``(N, num_levels * features_per_level)`` features."""

    def __init__(self, cfg: HashEncodingConfig, generator: torch.Generator | None = None):
        super().__init__()
        self.cfg = cfg
        table_size = 2**cfg.log2_table_size
        resolutions = level_resolutions(cfg)
        sizes, dense, offsets, start = [], [], [], 0
        for res in resolutions:
            n_dense = (res + 1) ** 3
            is_dense = n_dense <= table_size
            size = n_dense if is_dense else table_size
            sizes.append(size)
            dense.append(is_dense)
            offsets.append(start)
            start += size
        if any(dense[i] and not dense[i - 1] for i in range(1, len(dense))):
            raise ValueError("hash encoding: resolutions must grow with the level")
        self.level_sizes = sizes
        self._num_dense = sum(dense)
        self._hash_mask = table_size - 1
        self.register_buffer(
            "resolutions", torch.tensor(resolutions, dtype=torch.float32), persistent=False
        )
        self.register_buffer("_res_int", torch.tensor(resolutions, dtype=_INDEX), persistent=False)
        self.register_buffer("_offsets", torch.tensor(offsets, dtype=_INDEX), persistent=False)
        strides = [[1, r + 1, (r + 1) ** 2] for r in resolutions[: self._num_dense]]
        self.register_buffer(
            "_dense_strides",
            torch.tensor(strides, dtype=_INDEX).reshape(-1, 3),
            persistent=False,
        )
        self.register_buffer(
            "_primes", torch.tensor([_as_int32(p) for p in _PRIMES], dtype=_INDEX), persistent=False
        )
        init = (
            torch.rand(start, cfg.features_per_level, generator=generator) * 2 - 1
        ) * _INIT_SCALE
        self.table = nn.Parameter(init)

    @property
    def out_dim(self) -> int:
        return self.cfg.num_levels * self.cfg.features_per_level

    def corners(self, x: Tensor, levels: int | None = None) -> tuple[Tensor, Tensor]:
        """Table rows and trilinear weights of the 8 cell corners, each ``(L, N, 8)`` (the bags
        of ``embedding_bag``, one per level and sample), of every level or of the first
        ``levels`` (compiled with ``HashEncodingConfig.compile``)."""
        if self.cfg.compile and x.shape[0] > 0 and _compiled_corners() is not None:
            try:
                return _compiled_corners()(self, x, levels)
            except Exception as e:  # noqa: BLE001 - any compiler failure: stay correct, eagerly
                log.warning("torch.compile of the hash encoding failed, running eagerly: %s", e)
                _COMPILED["fn"] = None
        return self.corners_eager(x, levels)

    def corners_eager(self, x: Tensor, levels: int | None = None) -> tuple[Tensor, Tensor]:
        """:meth:`corners` in plain PyTorch (the reference for the compiled version).

        Computed level-major, sample-minor: every broadcast runs over a contiguous inner
        dimension of N samples (several times faster on CPU than a trailing corner dimension)
        and the dense and hashed level groups join by plain concatenation. One transposition
        at the end gives the bag layout, which every table then reads without copying
        (benchmarks/results/speed.md, "Fewer band samples and one corner layout").
        """
        levels = self.cfg.num_levels if levels is None else min(levels, self.cfg.num_levels)
        res = self.resolutions[:levels].view(-1, 1, 1)
        pos = x.detach().clamp(0.0, 1.0).T.unsqueeze(0) * res  # L 3 N
        # Clamped so that a position on the far face interpolates inside the last cell.
        cell = pos.floor().to(_INDEX).clamp_max(self._res_int[:levels].view(-1, 1, 1) - 1)
        frac = pos - cell
        w = torch.stack([1 - frac, frac], dim=1)  # L x 2 (corner) x 3 (axis) x N
        weights = (w[:, :, None, None, 2] * w[:, None, :, None, 1]) * w[
            :, None, None, :, 0
        ]  # L z y x N
        c = torch.stack([cell, cell + 1], dim=1)  # L x 2 x 3 x N
        nd = min(self._num_dense, levels)
        n = x.shape[0]
        rows = torch.empty(
            levels, 2, 2, 2, n, dtype=_INDEX, device=x.device
        )  # written in place, no concatenation
        if nd > 0:  # dense levels: x + y * (R + 1) + z * (R + 1)^2 + level offset
            cd = c[:nd] * self._dense_strides[:nd].view(nd, 1, 3, 1)
            zy = cd[:, :, None, None, 2] + cd[:, None, :, None, 1]
            torch.add(
                zy, cd[:, None, None, :, 0] + self._offsets[:nd].view(nd, 1, 1, 1, 1), out=rows[:nd]
            )
        if nd < levels:  # hashed levels: (x p0 ^ y p1 ^ z p2) mod T + level offset
            ch = c[nd:] * self._primes.view(1, 1, 3, 1)
            hashed = rows[nd:]
            torch.bitwise_xor(
                ch[:, :, None, None, 2] ^ ch[:, None, :, None, 1],
                ch[:, None, None, :, 0],
                out=hashed,
            )
            hashed &= self._hash_mask
            hashed += self._offsets[nd:levels].view(-1, 1, 1, 1, 1)
        # n, not -1: n may be 0
        rows = rows.reshape(levels, 8, n).transpose(1, 2).contiguous()
        return rows, weights.reshape(levels, 8, n).transpose(1, 2).contiguous()

    def level_rows(self, levels: int) -> int:
        """Number of table rows used by the first ``levels`` levels (their blocks come first)."""
        return int(sum(self.level_sizes[:levels]))

    def uses_kernel(self, x: Tensor, table: Tensor | None = None) -> bool:
        """Whether positions ``x`` are encoded by the C kernel (``csa_core.nerf.hash_kernel``):
        ``implementation`` ``auto``, float32 on the CPU, and the kernel built here."""
        table = self.table if table is None else table
        return self.cfg.implementation == "auto" and hash_kernel.usable(x, table)

    def uses_triton(self, x: Tensor, table: Tensor | None = None) -> bool:
        """Whether positions ``x`` are encoded by the Triton kernel (``hash_triton``):
        ``implementation`` ``auto``, float32 on CUDA, and Triton there."""
        table = self.table if table is None else table
        return self.cfg.implementation == "auto" and hash_triton.usable(x, table)

    def kernel_layout(self) -> hash_kernel.LevelLayout:
        """This encoding's level layout as the C kernel reads it (its own int32 buffers)."""
        return hash_kernel.LevelLayout(
            self._res_int, self._offsets, self._num_dense, self._hash_mask
        )

    def forward(
        self,
        x: Tensor,
        extra: Tensor | None = None,
        extra_levels: int = 0,
        detach_main: bool = False,
    ) -> Tensor | tuple[Tensor, Tensor]:
        """Features ``(N, L * F)``; with ``extra`` (a second table laid out like the first
        ``extra_levels`` levels of this one) also that table's features ``(N, extra_levels * F')``,
        interpolated with the same corners and weights (computed once). ``detach_main``: no
        gradient reaches this encoding's own table (only ``extra``'s)."""
        n = x.shape[0]
        main = self.table.detach() if detach_main else self.table
        if self.uses_kernel(x, main) and (extra is None or hash_kernel.usable(x, extra)):
            layout = self.kernel_layout()
            feats = hash_kernel.encode(x, main, self.cfg.num_levels, layout)
            if extra is None:
                return feats
            return feats, hash_kernel.encode(x, extra, extra_levels, layout)
        if self.uses_triton(x, main) and (extra is None or hash_triton.usable(x, extra)):
            try:
                layout = self.kernel_layout()
                feats = hash_triton.encode(x, main, self.cfg.num_levels, layout)
                if extra is None:
                    return feats
                return feats, hash_triton.encode(x, extra, extra_levels, layout)
            except Exception as e:  # noqa: BLE001 - a kernel that fails to build: PyTorch path
                hash_triton.mark_failed(e)
        if n > INFERENCE_BLOCK and not torch.is_grad_enabled() and not x.is_cuda:
            parts = [
                self(x[i : i + INFERENCE_BLOCK], extra, extra_levels, detach_main)
                for i in range(0, n, INFERENCE_BLOCK)
            ]
            if extra is None:
                return torch.cat(parts)
            return torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])
        if n == 0:
            empty = x.new_zeros(0, self.out_dim)
            return (
                empty if extra is None else (empty, x.new_zeros(0, extra_levels * extra.shape[1]))
            )
        rows, weights = self.corners(x)
        feats = self.interpolate(rows, weights, main)
        if extra is None:
            return feats
        return feats, self.interpolate(rows[:extra_levels], weights[:extra_levels], extra)

    def interpolate(self, rows: Tensor, weights: Tensor, table: Tensor | None = None) -> Tensor:
        """Features ``(N, L * F)`` of ``table`` (default: this encoding's) at corners from
        :meth:`corners` (``L`` levels, the table laid out like this one's first ``L`` levels)."""
        table = self.table if table is None else table
        if rows.shape[1] == 0:
            return table.new_zeros(0, rows.shape[0] * table.shape[1])
        out = _HashGather.apply(table, rows, weights.to(table.dtype))
        return out.transpose(0, 1).reshape(rows.shape[1], -1)


_COMPILED: dict[str, object] = {}


def _compiled_corners():
    """``HashEncoding.corners_eager`` compiled once per process (dynamic sizes), or ``None``
    where torch.compile is unavailable or has failed."""
    if "fn" not in _COMPILED:
        try:
            _COMPILED["fn"] = torch.compile(HashEncoding.corners_eager, dynamic=True)
        except Exception as e:  # noqa: BLE001 - no compiler on this platform
            log.warning("torch.compile unavailable, the hash encoding runs eagerly: %s", e)
            _COMPILED["fn"] = None
    return _COMPILED["fn"]
