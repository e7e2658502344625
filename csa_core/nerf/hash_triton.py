"""The hash encoding's gather and its backward pass as one Triton kernel, for CUDA.

On a GPU the plain-PyTorch encoding (``hash_encoding.HashEncoding.corners_eager`` +
``_HashGather``) spends most of a training step in ``embedding_bag``'s per-bag kernel and in
the dozen elementwise kernels that build the ``(L, N, 8)`` corner rows and weights
(benchmarks/results/gpu.md "The GPU path"). This kernel does what the CPU's C kernel
(``hash_kernel.py``) does, one program per block of samples: it loads each position once, walks
the levels, computes the 8 corners of each level in registers and accumulates the table rows
into the output; the backward pass recomputes the corners and adds the gradient into the table
with atomic adds (levels share no rows, samples of one level do).

Same arithmetic as the PyTorch reference and the C kernel: positions clamped to [0, 1] (NaN
reads the origin cell), the cell clamped into the grid, dense levels indexed
``x + y (R + 1) + z (R + 1)^2``, hashed levels ``(x ^ y * 2654435761 ^ z * 805459861) & (T - 1)``
(computed in int64: the mask keeps only low bits, which equal the uint32 hash's), weights
``(w_z w_y) w_x``, corners summed with x fastest. Sums may round differently from
``embedding_bag``; the atomic adds of the backward pass make its sums order-dependent (tests
compare within float32 rounding: tests/nerf/test_hash_triton.py, which runs the kernel in
Triton's interpreter on a CPU).

Where Triton is missing or the kernel fails to compile, :func:`usable` turns ``False`` (one
warning) and the encoding stays in PyTorch.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

import torch
from torch import Tensor

from csa_core.nerf.hash_kernel import Backend, LevelLayout, encode_with

try:  # the kernel's body refers to ``tl`` as a global, as Triton requires
    import triton.language as tl
except Exception:  # noqa: BLE001 - no Triton on this platform: the PyTorch path serves
    tl = None

log = logging.getLogger(__name__)

BLOCK = 128  # samples per program
_PRIME_Y, _PRIME_Z = 2654435761, 805459861

_LOCK = threading.Lock()
_KERNELS: dict[bool, Any] = {}  # interpret -> the kernel object, or None where it failed
_FAILED: dict[str, bool] = {}


def _hash_grid(
    x_ptr, table_ptr, out_ptr, grad_ptr, res_ptr, off_ptr,
    n, num_levels, num_dense, hash_mask, out_stride,
    F: tl.constexpr, BLOCK: tl.constexpr, BACKWARD: tl.constexpr,
):  # fmt: skip
    """Forward: ``out[i, l F + f] = sum_k w_k table[row_k, f]``; backward (``BACKWARD``): adds
    ``w_k grad[i, l F + f]`` into ``table`` (the table's gradient) at ``row_k``."""
    pid = tl.program_id(0)
    rows = pid * BLOCK + tl.arange(0, BLOCK)
    ok = rows < n
    feat = tl.arange(0, F)
    ok2 = ok[:, None] & (feat[None, :] < F)
    px = tl.load(x_ptr + rows * 3 + 0, mask=ok, other=0.0)
    py = tl.load(x_ptr + rows * 3 + 1, mask=ok, other=0.0)
    pz = tl.load(x_ptr + rows * 3 + 2, mask=ok, other=0.0)
    # Clamp to [0, 1]; NaN fails both comparisons and reads 0.
    px = tl.where(px >= 0.0, tl.minimum(px, 1.0), 0.0)
    py = tl.where(py >= 0.0, tl.minimum(py, 1.0), 0.0)
    pz = tl.where(pz >= 0.0, tl.minimum(pz, 1.0), 0.0)
    out_rows = rows.to(tl.int64)[:, None] * out_stride + feat[None, :]
    for level in range(num_levels):
        res = tl.load(res_ptr + level)
        offset = tl.load(off_ptr + level).to(tl.int64)
        rf = res.to(tl.float32)
        fx, fy, fz = px * rf, py * rf, pz * rf
        cx = tl.minimum(tl.floor(fx).to(tl.int32), res - 1)
        cy = tl.minimum(tl.floor(fy).to(tl.int32), res - 1)
        cz = tl.minimum(tl.floor(fz).to(tl.int32), res - 1)
        fx = fx - cx.to(tl.float32)
        fy = fy - cy.to(tl.float32)
        fz = fz - cz.to(tl.float32)
        dense = level < num_dense
        s1 = (res + 1).to(tl.int64)
        if BACKWARD:
            g = tl.load(grad_ptr + out_rows + level * F, mask=ok2, other=0.0)
        else:
            acc = tl.full((BLOCK, F), 0.0, tl.float32)
        for k in tl.static_range(8):
            ix = (cx + (k & 1)).to(tl.int64)
            iy = (cy + ((k >> 1) & 1)).to(tl.int64)
            iz = (cz + ((k >> 2) & 1)).to(tl.int64)
            wx = fx if (k & 1) else 1.0 - fx
            wy = fy if ((k >> 1) & 1) else 1.0 - fy
            wz = fz if ((k >> 2) & 1) else 1.0 - fz
            w = (wz * wy) * wx
            hashed = (ix ^ (iy * 2654435761) ^ (iz * 805459861)) & hash_mask
            row = tl.where(dense, ix + iy * s1 + iz * s1 * s1, hashed) + offset
            where = row[:, None] * F + feat[None, :]
            if BACKWARD:
                tl.atomic_add(table_ptr + where, w[:, None] * g, mask=ok2)
            else:
                acc += w[:, None] * tl.load(table_ptr + where, mask=ok2, other=0.0)
        if not BACKWARD:
            tl.store(out_ptr + out_rows + level * F, acc, mask=ok2)


def _kernel(interpret: bool) -> Any:
    """The kernel, compiled with ``triton.jit`` (CUDA) or wrapped for Triton's interpreter
    (CPU tensors, for the tests); ``None`` where Triton cannot be imported."""
    with _LOCK:
        if interpret not in _KERNELS:
            try:
                import triton

                fn = _hash_grid
                if interpret:
                    from triton.runtime.interpreter import InterpretedFunction

                    _KERNELS[interpret] = InterpretedFunction(fn)
                else:
                    _KERNELS[interpret] = triton.jit(fn)
            except Exception as e:  # noqa: BLE001 - no Triton here: PyTorch path
                log.warning("Triton unavailable, the hash encoding runs in PyTorch: %s", e)
                _KERNELS[interpret] = None
        return _KERNELS[interpret]


def usable(x: Tensor, table: Tensor) -> bool:
    """Whether the kernel can encode ``x`` with ``table``: float32 CUDA tensors, Triton there,
    and no earlier failure in this process."""
    return (
        x.is_cuda
        and table.is_cuda
        and x.dtype == torch.float32
        and table.dtype == torch.float32
        and table.shape[1] in (1, 2, 4, 8)
        and not _FAILED.get("cuda", False)
        and _kernel(False) is not None
    )


def _launch(
    x: Tensor, table: Tensor, out: Tensor | None, grad: Tensor | None, levels: int,
    layout: LevelLayout, backward: bool,
) -> None:  # fmt: skip
    n, feat = x.shape[0], table.shape[1]
    if n == 0:
        return
    kernel = _kernel(not x.is_cuda)
    res = layout.res.to(x.device)
    offsets = layout.offsets.to(x.device)
    dummy = table  # the pointer the other direction does not read
    grid = ((n + BLOCK - 1) // BLOCK,)
    kernel[grid](
        x, table, dummy if out is None else out, dummy if grad is None else grad, res, offsets,
        n, levels, layout.num_dense, layout.mask, levels * feat,
        F=feat, BLOCK=BLOCK, BACKWARD=backward,
    )  # fmt: skip


def _forward(x: Tensor, table: Tensor, levels: int, layout: LevelLayout) -> Tensor:
    out = torch.empty(x.shape[0], levels * table.shape[1], dtype=torch.float32, device=x.device)
    _launch(x, table, out, None, levels, layout, backward=False)
    return out


def _backward(
    x: Tensor, grad: Tensor, shape: torch.Size, levels: int, layout: LevelLayout
) -> Tensor:
    table_grad = torch.zeros(shape, dtype=torch.float32, device=x.device)
    _launch(x, table_grad, None, grad, levels, layout, backward=True)
    return table_grad


TRITON_KERNEL = Backend(_forward, _backward)


def encode(x: Tensor, table: Tensor, levels: int, layout: LevelLayout) -> Tensor:
    """Features ``(N, levels * F)`` of ``table`` at ``x`` (N, 3) in [0, 1]^3 through the kernel
    (call where :func:`usable`, or with CPU tensors in Triton's interpreter); differentiable
    with respect to ``table``."""
    return encode_with(TRITON_KERNEL, x, table, levels, layout)


def mark_failed(error: Exception) -> None:
    """Stop using the kernel in this process after ``error`` (one warning)."""
    if not _FAILED.get("cuda"):
        log.warning("the Triton hash kernel failed, the encoding runs in PyTorch: %s", error)
    _FAILED["cuda"] = True
