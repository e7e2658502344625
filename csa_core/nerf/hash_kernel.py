"""A fused CPU kernel for the hash encoding's gather and its backward pass (C, OpenMP).

The plain-PyTorch encoding (``hash_encoding.HashEncoding.corners_eager`` + ``_HashGather``)
builds every level's corner rows and trilinear weights as ``(L, N, 8)`` tensors and then gathers;
on a CPU those temporaries, not the arithmetic, set the cost (benchmarks/results/speed.md,
"A fused C kernel for the hash encoding"). This kernel walks each
sample once per level, computes its 8 corners in registers and accumulates the table rows
straight into the output; the backward pass recomputes the corners and adds the gradient
into the table rows, one level per thread (levels own disjoint row blocks, so no two threads
write the same row).

It is the same arithmetic as the PyTorch reference: positions clamped to [0, 1], the cell
clamped into the grid, dense levels indexed ``x + y (R + 1) + z (R + 1)^2``, hashed levels
``(x ^ y * 2654435761 ^ z * 805459861) mod 2^32 & (T - 1)``, weights ``(w_z w_y) w_x``, corners
summed in the order z, y, x. Sums may round differently from ``embedding_bag``
(tests/nerf/test_hash_kernel.py compares them).

The source below is compiled once per machine with the system C compiler (``cc``, or ``$CC``)
into a cache folder (``$CSA_KERNEL_CACHE``, else ``$XDG_CACHE_HOME/csa/kernels``, else
``~/.cache/csa/kernels``) and loaded with ctypes; nothing is downloaded. Where no compiler
works, :func:`available` is ``False`` and the encoding stays in PyTorch (one warning).
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import torch
from torch import Tensor

log = logging.getLogger(__name__)

_SOURCE = r"""
#include <stdint.h>
#include <math.h>

static inline void corners(const float *p, int32_t res, int dense, int32_t offset,
                           uint32_t mask, int32_t *rows, float *w) {
    int32_t c[3];
    float f[3];
    for (int a = 0; a < 3; ++a) {
        float v = p[a];
        v = (v >= 0.0f) ? (v <= 1.0f ? v : 1.0f) : 0.0f; /* NaN -> 0: never an index outside */
        float pos = v * (float)res;
        int32_t cell = (int32_t)floorf(pos);
        if (cell > res - 1) cell = res - 1;
        c[a] = cell;
        f[a] = pos - (float)cell;
    }
    for (int k = 0; k < 8; ++k) {
        int32_t cx = c[0] + (k & 1), cy = c[1] + ((k >> 1) & 1), cz = c[2] + ((k >> 2) & 1);
        float wx = (k & 1) ? f[0] : 1.0f - f[0];
        float wy = ((k >> 1) & 1) ? f[1] : 1.0f - f[1];
        float wz = ((k >> 2) & 1) ? f[2] : 1.0f - f[2];
        w[k] = (wz * wy) * wx;
        if (dense) {
            int32_t s = res + 1;
            rows[k] = cx + cy * s + cz * s * s + offset;
        } else {
            uint32_t h = (uint32_t)cx ^ ((uint32_t)cy * 2654435761u) ^ ((uint32_t)cz * 805459861u);
            rows[k] = (int32_t)(h & mask) + offset;
        }
    }
}

void csa_hash_forward(const float *x, int64_t n, const float *table, int32_t feat,
                      int32_t levels, int32_t out_stride, const int32_t *res,
                      const int32_t *offsets, int32_t num_dense, uint32_t mask, float *out,
                      int32_t threads) {
    /* Blocks of samples, one level at a time within a block: a level's rows stay in cache. */
    const int64_t block = 512;
    #pragma omp parallel for num_threads(threads) schedule(static)
    for (int64_t b = 0; b < n; b += block) {
        int64_t end = b + block < n ? b + block : n;
        int32_t rows[8];
        float w[8];
        for (int32_t l = 0; l < levels; ++l) {
            for (int64_t i = b; i < end; ++i) {
                corners(x + 3 * i, res[l], l < num_dense, offsets[l], mask, rows, w);
                float *o = out + i * (int64_t)out_stride + l * feat;
                for (int32_t j = 0; j < feat; ++j) {
                    float acc = 0.0f;
                    for (int k = 0; k < 8; ++k) acc += w[k] * table[(int64_t)rows[k] * feat + j];
                    o[j] = acc;
                }
            }
        }
    }
}

void csa_hash_backward(const float *x, int64_t n, const float *grad, int32_t feat,
                       int32_t levels, int32_t grad_stride, const int32_t *res,
                       const int32_t *offsets, int32_t num_dense, uint32_t mask,
                       float *table_grad, int32_t threads) {
    /* One level per iteration: levels own disjoint row blocks, so threads never collide. */
    #pragma omp parallel for num_threads(threads) schedule(dynamic, 1)
    for (int32_t l = 0; l < levels; ++l) {
        int32_t rows[8];
        float w[8];
        for (int64_t i = 0; i < n; ++i) {
            const float *g = grad + i * (int64_t)grad_stride + l * feat;
            corners(x + 3 * i, res[l], l < num_dense, offsets[l], mask, rows, w);
            for (int k = 0; k < 8; ++k) {
                float *t = table_grad + (int64_t)rows[k] * feat;
                for (int32_t j = 0; j < feat; ++j) t[j] += w[k] * g[j];
            }
        }
    }
}
"""

_FLAGS = ["-O3", "-fopenmp", "-shared", "-fPIC", "-std=c99"]
_LIB: dict[str, object] = {}
_LOCK = threading.Lock()


def cache_dir() -> Path:
    """Where the compiled kernel is kept (see the module's description)."""
    if os.environ.get("CSA_KERNEL_CACHE"):
        return Path(os.environ["CSA_KERNEL_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "csa" / "kernels"


def _build(target: Path, compiler: str) -> None:
    """Compile the source into ``target`` through a temporary file (never a half-written .so)."""
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
        src = Path(tmp) / "hash_kernel.c"
        src.write_text(_SOURCE)
        out = Path(tmp) / target.name
        subprocess.run(
            [compiler, *_FLAGS, str(src), "-o", str(out), "-lm"],
            check=True,
            capture_output=True,
            timeout=120,
        )
        os.replace(out, target)


def _load() -> ctypes.CDLL | None:
    compiler = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        raise RuntimeError("no C compiler (cc, gcc or $CC) on PATH")
    key = hashlib.sha256(
        "\0".join([_SOURCE, *_FLAGS, compiler, platform.machine(), platform.system()]).encode()
    ).hexdigest()[:16]
    target = cache_dir() / f"csa_hash_{key}.so"
    if not target.exists():
        _build(target, compiler)
    lib = ctypes.CDLL(str(target))
    i32, i64, u32, ptr = ctypes.c_int32, ctypes.c_int64, ctypes.c_uint32, ctypes.c_void_p
    args = [ptr, i64, ptr, i32, i32, i32, ptr, ptr, i32, u32, ptr, i32]
    for fn in (lib.csa_hash_forward, lib.csa_hash_backward):
        fn.argtypes = args
        fn.restype = None
    return lib


def library() -> ctypes.CDLL | None:
    """The compiled kernel, built on first use; ``None`` where it cannot be built."""
    if "lib" in _LIB:
        return _LIB["lib"]  # type: ignore[return-value]
    with _LOCK:
        if "lib" not in _LIB:
            try:
                _LIB["lib"] = _load()
            except (OSError, RuntimeError, subprocess.SubprocessError) as e:
                detail = getattr(e, "stderr", b"") or b""
                log.warning(
                    "the C hash-encoding kernel is unavailable, "
                    "the encoding runs in PyTorch: %s %s",
                    e,
                    detail.decode(errors="replace")[:500],
                )
                _LIB["lib"] = None
        return _LIB["lib"]  # type: ignore[return-value]


def available() -> bool:
    """Whether the kernel can run here (it builds on first call)."""
    return library() is not None


def usable(x: Tensor, table: Tensor) -> bool:
    """Whether the kernel can encode ``x`` with ``table``: both float32 on the CPU."""
    return (
        x.device.type == "cpu"
        and table.device.type == "cpu"
        and x.dtype == torch.float32
        and table.dtype == torch.float32
        and available()
    )


class LevelLayout(NamedTuple):
    """What the kernel needs of an encoding (``HashEncoding.kernel_layout``, from its buffers):
    per-level resolutions and row offsets (int32 CPU tensors), how many leading levels are
    dense, and the hash mask."""

    res: Tensor
    offsets: Tensor
    num_dense: int
    mask: int


def _ptr(t: Tensor) -> int:
    return t.data_ptr()


def _forward(x: Tensor, table: Tensor, levels: int, layout: LevelLayout) -> Tensor:
    n, feat = x.shape[0], table.shape[1]
    out = torch.empty(n, levels * feat, dtype=torch.float32)
    if n:
        library().csa_hash_forward(  # type: ignore[union-attr]
            _ptr(x), n, _ptr(table), feat, levels, levels * feat, _ptr(layout.res),
            _ptr(layout.offsets), layout.num_dense, layout.mask, _ptr(out),
            torch.get_num_threads(),
        )  # fmt: skip
    return out


def _backward(
    x: Tensor, grad: Tensor, shape: torch.Size, levels: int, layout: LevelLayout
) -> Tensor:
    table_grad = torch.zeros(shape, dtype=torch.float32)
    if x.shape[0]:
        library().csa_hash_backward(  # type: ignore[union-attr]
            _ptr(x), x.shape[0], _ptr(grad), shape[1], levels, grad.shape[1],
            _ptr(layout.res), _ptr(layout.offsets), layout.num_dense, layout.mask,
            _ptr(table_grad), torch.get_num_threads(),
        )  # fmt: skip
    return table_grad


class Backend(NamedTuple):
    """A fused encoding kernel: ``forward(x, table, levels, layout)`` -> features and
    ``backward(x, grad, table_shape, levels, layout)`` -> the table's gradient, on contiguous
    float32 tensors (this module's C kernel, ``hash_triton``'s Triton kernel)."""

    forward: Callable[[Tensor, Tensor, int, LevelLayout], Tensor]
    backward: Callable[[Tensor, Tensor, torch.Size, int, LevelLayout], Tensor]


class _KernelEncode(torch.autograd.Function):
    """``table`` features at positions ``x`` (N, 3) -> (N, levels * F) through a ``Backend``;
    gradient to the table only."""

    @staticmethod
    def forward(ctx, x: Tensor, table: Tensor, levels: int, layout: LevelLayout, backend: Backend):
        x = x.detach().contiguous()
        ctx.save_for_backward(x)
        ctx.levels, ctx.layout, ctx.shape, ctx.backend = levels, layout, table.shape, backend
        return backend.forward(x, table.detach().contiguous(), levels, layout)

    @staticmethod
    def backward(ctx, grad: Tensor):
        (x,) = ctx.saved_tensors
        grad = grad.contiguous().float()
        table_grad = ctx.backend.backward(x, grad, ctx.shape, ctx.levels, ctx.layout)
        return None, table_grad, None, None, None


def encode_with(
    backend: Backend, x: Tensor, table: Tensor, levels: int, layout: LevelLayout
) -> Tensor:
    """Features ``(N, levels * F)`` of ``table`` at ``x`` (N, 3) in [0, 1]^3 through ``backend``;
    differentiable with respect to ``table``."""
    if torch.is_grad_enabled() and table.requires_grad:
        return _KernelEncode.apply(x, table, levels, layout, backend)
    return backend.forward(x.detach().contiguous(), table.detach().contiguous(), levels, layout)


C_KERNEL = Backend(_forward, _backward)


def encode(x: Tensor, table: Tensor, levels: int, layout: LevelLayout) -> Tensor:
    """Features ``(N, levels * F)`` of ``table`` at ``x`` (N, 3) in [0, 1]^3, through the kernel
    (call only where :func:`usable`); differentiable with respect to ``table``."""
    return encode_with(C_KERNEL, x, table, levels, layout)
