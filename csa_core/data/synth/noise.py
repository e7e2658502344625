"""Deterministic lattice noise for procedural textures.

Everything is a pure function of coordinates and an integer seed (no global random state),
so a texture evaluated at the same surface point always gives the same value, whichever
camera looks at it.
"""

from __future__ import annotations

import numpy as np

_PRIMES = (np.uint32(0x8DA6B343), np.uint32(0xD8163841), np.uint32(0xCB1AB31F))


def hash01(*coords: np.ndarray, seed: int = 0) -> np.ndarray:
    """Uniform pseudo-random values in [0, 1) for integer lattice coordinates.

    ``coords`` are integer-valued arrays (any sign) broadcastable together; the result is
    float64 and depends only on the coordinates and ``seed``.
    """
    h = np.full(
        np.broadcast(*coords).shape, np.uint32((seed * 0x165667B1 + 0x27D4EB2F) & 0xFFFFFFFF)
    )
    for i, c in enumerate(coords):
        ci = np.asarray(c).astype(np.int64).astype(np.uint32)
        h = h ^ (ci * _PRIMES[i % 3])
        h = h ^ (h >> np.uint32(15))
        h = h * np.uint32(0x2C1B3C6D)
    h = h ^ (h >> np.uint32(12))
    h = h * np.uint32(0x297A2D39)
    h = h ^ (h >> np.uint32(15))
    return h.astype(np.float64) / 4294967296.0


def _smooth(t: np.ndarray) -> np.ndarray:
    return t * t * (3.0 - 2.0 * t)


def value_noise3(p: np.ndarray, seed: int = 0) -> np.ndarray:
    """Smooth value noise in [0, 1] at points ``p`` (..., 3), one lattice cell per unit."""
    p = np.asarray(p, dtype=np.float64)
    base = np.floor(p)
    f = _smooth(p - base)
    ix, iy, iz = base[..., 0], base[..., 1], base[..., 2]
    fx, fy, fz = f[..., 0], f[..., 1], f[..., 2]
    out = np.zeros(p.shape[:-1])
    for dx in (0, 1):
        wx = fx if dx else 1.0 - fx
        for dy in (0, 1):
            wy = fy if dy else 1.0 - fy
            for dz in (0, 1):
                wz = fz if dz else 1.0 - fz
                out += wx * wy * wz * hash01(ix + dx, iy + dy, iz + dz, seed=seed)
    return out


def fbm3(p: np.ndarray, octaves: int = 3, seed: int = 0) -> np.ndarray:
    """Fractal sum of value noise (each octave twice the frequency, half the weight), in [0, 1]."""
    total = np.zeros(np.asarray(p).shape[:-1])
    weight, norm, scale = 1.0, 0.0, 1.0
    for k in range(octaves):
        total += weight * value_noise3(np.asarray(p) * scale, seed=seed + 7919 * k)
        norm += weight
        weight *= 0.5
        scale *= 2.0
    return total / norm
