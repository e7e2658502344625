"""Oriented boxes and vectorised ray casting against them (slab method).

A room is an axis-aligned interior box (walls, floor, ceiling seen from inside) plus a set
of solid boxes, each rotated about the vertical axis (yaw) after an optional tilt about its
own x axis (a chair back leaning back, a ladder shelf leaning on a wall). All functions take
one ray origin shared by every ray (a camera centre or a light) and many directions, and
test all rays against all boxes in one broadcast.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

_TINY = 1e-12


def rotations(yaw: np.ndarray, tilt: np.ndarray) -> np.ndarray:
    """Rotation matrices (n, 3, 3) ``Rz(yaw) @ Rx(tilt)``: columns are the local axes in world."""
    cy, sy = np.cos(yaw), np.sin(yaw)
    ct, st = np.cos(tilt), np.sin(tilt)
    zero, one = np.zeros_like(cy), np.ones_like(cy)
    rz = np.stack(
        [
            np.stack([cy, -sy, zero], -1),
            np.stack([sy, cy, zero], -1),
            np.stack([zero, zero, one], -1),
        ],
        -2,
    )
    rx = np.stack(
        [
            np.stack([one, zero, zero], -1),
            np.stack([zero, ct, -st], -1),
            np.stack([zero, st, ct], -1),
        ],
        -2,
    )
    return rz @ rx


@dataclass(frozen=True)
class BoxSet:
    """``n`` solid boxes in world coordinates (metres, z up).

    ``center`` (n, 3), ``half`` (n, 3) half-extents along the box's own axes, ``yaw`` (n,)
    rotation about +z applied after ``tilt`` (n,) about the box's own x axis (None: no
    tilt). Box-local coordinates are ``R^T (p - center)`` with ``R = Rz(yaw) Rx(tilt)``.
    """

    center: np.ndarray
    half: np.ndarray
    yaw: np.ndarray
    tilt: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.yaw)

    @cached_property
    def rot(self) -> np.ndarray:
        """Local-to-world rotations (n, 3, 3)."""
        tilt = np.zeros_like(self.yaw) if self.tilt is None else self.tilt
        return rotations(np.asarray(self.yaw, dtype=np.float64), np.asarray(tilt, dtype=np.float64))

    def subset(self, idx: np.ndarray) -> BoxSet:
        out = BoxSet(
            self.center[idx],
            self.half[idx],
            self.yaw[idx],
            None if self.tilt is None else self.tilt[idx],
        )
        out.__dict__["rot"] = self.rot[idx]  # carry the cached rotations over
        return out

    def corners(self) -> np.ndarray:
        """The 8 corners of every box, (n, 8, 3)."""
        signs = np.array(
            [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64
        )
        local = signs[None] * self.half[:, None, :]
        return np.einsum("nij,nkj->nki", self.rot, local) + self.center[:, None, :]

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        """World axis-aligned bounds (n, 3) min and max."""
        k = self.corners()
        return k.min(axis=1), k.max(axis=1)

    def to_local(self, points: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """Points (m, 3) in the local frame of boxes ``idx`` (m,)."""
        return np.einsum("mji,mj->mi", self.rot[idx], points - self.center[idx])

    def dir_to_local(self, dirs: np.ndarray, idx: np.ndarray) -> np.ndarray:
        return np.einsum("mji,mj->mi", self.rot[idx], dirs)

    def normal_to_world(self, local_normals: np.ndarray, idx: np.ndarray) -> np.ndarray:
        return np.einsum("mij,mj->mi", self.rot[idx], local_normals)


def _safe_inverse(d: np.ndarray) -> np.ndarray:
    return 1.0 / np.where(np.abs(d) < _TINY, _TINY, d)


def slab_intervals(
    origin: np.ndarray, dirs: np.ndarray, boxes: BoxSet
) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit parameters of every ray against every box, each (n_rays, n_boxes).

    Rays are ``origin + t * dirs``; a ray misses a box where entry > exit. float32 for speed:
    callers refine the winning hit in float64 with :func:`face_hit`.
    """
    o = np.asarray(origin, dtype=np.float64)
    rot = boxes.rot
    o_loc = np.einsum("nji,nj->ni", rot, o[None, :] - boxes.center).astype(np.float32)
    h = boxes.half.astype(np.float32)
    d = dirs.astype(np.float32)
    axes = rot.astype(np.float32)
    invs = [_safe_inverse(d @ axes[:, :, k].T) for k in range(3)]
    near = np.full((len(d), len(boxes)), -np.inf, dtype=np.float32)
    far = np.full((len(d), len(boxes)), np.inf, dtype=np.float32)
    for axis, inv in enumerate(invs):
        ta = (-h[:, axis] - o_loc[:, axis]) * inv
        tb = (h[:, axis] - o_loc[:, axis]) * inv
        np.maximum(near, np.minimum(ta, tb), out=near)
        np.minimum(far, np.maximum(ta, tb), out=far)
    return near, far


def closest_hit(
    origin: np.ndarray, dirs: np.ndarray, boxes: BoxSet, t_max: np.ndarray, eps: float = 1e-4
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest box entered by each ray before ``t_max``: (t, box index), index -1 where none."""
    n = len(dirs)
    if len(boxes) == 0:
        return np.full(n, np.inf), np.full(n, -1, dtype=np.int64)
    near, far = slab_intervals(origin, dirs, boxes)
    valid = (near <= far) & (near > eps)
    near = np.where(valid, near, np.inf)
    idx = np.argmin(near, axis=1)
    t = near[np.arange(n), idx].astype(np.float64)
    hit = t < t_max
    return np.where(hit, t, np.inf), np.where(hit, idx, -1)


def any_hit(
    origin: np.ndarray, dirs: np.ndarray, boxes: BoxSet, t_end: np.ndarray, eps: float = 1e-4
) -> np.ndarray:
    """Whether each ray enters some box with ``eps < t < t_end`` (shadow test), (n_rays,) bool."""
    if len(boxes) == 0:
        return np.zeros(len(dirs), dtype=bool)
    near, far = slab_intervals(origin, dirs, boxes)
    blocked = (near <= far) & (near > eps) & (near < t_end[:, None])
    return blocked.any(axis=1)


def face_hit(
    origin: np.ndarray, dirs: np.ndarray, boxes: BoxSet, idx: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Exact float64 entry of rays into their boxes ``idx`` (all >= 0).

    Returns ``t`` (m,), the local hit point (m, 3), the face axis (m,) in 0..2 and the
    outward local normal (m, 3).
    """
    o_loc = boxes.to_local(np.broadcast_to(origin, dirs.shape), idx)
    d_loc = boxes.dir_to_local(dirs, idx)
    h = boxes.half[idx]
    inv = _safe_inverse(d_loc)
    ta = (-h - o_loc) * inv
    tb = (h - o_loc) * inv
    near = np.minimum(ta, tb)
    axis = np.argmax(near, axis=1)
    rows = np.arange(len(idx))
    t = near[rows, axis]
    local = o_loc + t[:, None] * d_loc
    normal = np.zeros_like(local)
    normal[rows, axis] = -np.sign(d_loc[rows, axis])
    return t, local, axis, normal


def interior_exit(
    origin: np.ndarray, dirs: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where rays from inside the axis-aligned box [lo, hi] leave it.

    Returns ``t`` (m,), the exit axis (m,) and the side (m,): +1 for the ``hi`` face, -1 for ``lo``.
    """
    inv = _safe_inverse(dirs)
    t_axes = np.where(dirs > 0, (hi - origin) * inv, (lo - origin) * inv)
    t_axes = np.where(np.abs(dirs) < _TINY, np.inf, t_axes)
    axis = np.argmin(t_axes, axis=1)
    rows = np.arange(len(dirs))
    return t_axes[rows, axis], axis, np.where(dirs[rows, axis] > 0, 1, -1)
