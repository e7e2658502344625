"""Yaw-oriented boxes and vectorised ray casting against them (slab method).

A room is an axis-aligned interior box (walls, floor, ceiling seen from inside) plus a set
of solid boxes, each rotated about the vertical axis only. All functions take one ray
origin shared by every ray (a camera centre or a light) and many directions, and test all
rays against all boxes in one broadcast.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_TINY = 1e-12


@dataclass(frozen=True)
class BoxSet:
    """``n`` solid boxes in world coordinates (metres, z up).

    ``center`` (n, 3), ``half`` (n, 3) half-extents along the box's own axes, ``yaw`` (n,)
    rotation about +z. Box-local coordinates are ``R(yaw)^T (p - center)``.
    """

    center: np.ndarray
    half: np.ndarray
    yaw: np.ndarray

    def __len__(self) -> int:
        return len(self.yaw)

    @property
    def cos(self) -> np.ndarray:
        return np.cos(self.yaw)

    @property
    def sin(self) -> np.ndarray:
        return np.sin(self.yaw)

    def subset(self, idx: np.ndarray) -> BoxSet:
        return BoxSet(self.center[idx], self.half[idx], self.yaw[idx])

    def corners(self) -> np.ndarray:
        """The 8 corners of every box, (n, 8, 3)."""
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
        local = signs[None] * self.half[:, None, :]
        c, s = self.cos[:, None], self.sin[:, None]
        x = c * local[..., 0] - s * local[..., 1]
        y = s * local[..., 0] + c * local[..., 1]
        return np.stack([x, y, local[..., 2]], axis=-1) + self.center[:, None, :]

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        """World axis-aligned bounds (n, 3) min and max."""
        k = self.corners()
        return k.min(axis=1), k.max(axis=1)

    def to_local(self, points: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """Points (m, 3) in the local frame of boxes ``idx`` (m,)."""
        q = points - self.center[idx]
        c, s = self.cos[idx], self.sin[idx]
        return np.stack([c * q[:, 0] + s * q[:, 1], -s * q[:, 0] + c * q[:, 1], q[:, 2]], axis=-1)

    def dir_to_local(self, dirs: np.ndarray, idx: np.ndarray) -> np.ndarray:
        c, s = self.cos[idx], self.sin[idx]
        return np.stack([c * dirs[:, 0] + s * dirs[:, 1], -s * dirs[:, 0] + c * dirs[:, 1], dirs[:, 2]], axis=-1)

    def normal_to_world(self, local_normals: np.ndarray, idx: np.ndarray) -> np.ndarray:
        c, s = self.cos[idx], self.sin[idx]
        n = local_normals
        return np.stack([c * n[:, 0] - s * n[:, 1], s * n[:, 0] + c * n[:, 1], n[:, 2]], axis=-1)


def _safe_inverse(d: np.ndarray) -> np.ndarray:
    return 1.0 / np.where(np.abs(d) < _TINY, _TINY, d)


def slab_intervals(origin: np.ndarray, dirs: np.ndarray, boxes: BoxSet) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit parameters of every ray against every box, each (n_rays, n_boxes).

    Rays are ``origin + t * dirs``; a ray misses a box where entry > exit. float32 for speed:
    callers refine the winning hit in float64 with :func:`face_hit`.
    """
    o = np.asarray(origin, dtype=np.float64)
    c, s = boxes.cos.astype(np.float32), boxes.sin.astype(np.float32)
    q = o[None, :] - boxes.center
    o_loc = np.stack([boxes.cos * q[:, 0] + boxes.sin * q[:, 1], -boxes.sin * q[:, 0] + boxes.cos * q[:, 1], q[:, 2]], axis=-1)
    o_loc = o_loc.astype(np.float32)
    h = boxes.half.astype(np.float32)
    d = dirs.astype(np.float32)
    dx, dy = d[:, 0:1], d[:, 1:2]
    inv_x = _safe_inverse(c * dx + s * dy)
    inv_y = _safe_inverse(-s * dx + c * dy)
    inv_z = _safe_inverse(d[:, 2:3])
    near = np.full((len(d), len(boxes)), -np.inf, dtype=np.float32)
    far = np.full((len(d), len(boxes)), np.inf, dtype=np.float32)
    for axis, inv in ((0, inv_x), (1, inv_y), (2, inv_z)):
        ta = (-h[:, axis] - o_loc[:, axis]) * inv
        tb = (h[:, axis] - o_loc[:, axis]) * inv
        np.maximum(near, np.minimum(ta, tb), out=near)
        np.minimum(far, np.maximum(ta, tb), out=far)
    return near, far


def closest_hit(origin: np.ndarray, dirs: np.ndarray, boxes: BoxSet, t_max: np.ndarray, eps: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
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


def any_hit(origin: np.ndarray, dirs: np.ndarray, boxes: BoxSet, t_end: np.ndarray, eps: float = 1e-4) -> np.ndarray:
    """Whether each ray enters some box with ``eps < t < t_end`` (shadow test), (n_rays,) bool."""
    if len(boxes) == 0:
        return np.zeros(len(dirs), dtype=bool)
    near, far = slab_intervals(origin, dirs, boxes)
    blocked = (near <= far) & (near > eps) & (near < t_end[:, None])
    return blocked.any(axis=1)


def face_hit(origin: np.ndarray, dirs: np.ndarray, boxes: BoxSet, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
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


def interior_exit(origin: np.ndarray, dirs: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where rays from inside the axis-aligned box [lo, hi] leave it.

    Returns ``t`` (m,), the exit axis (m,) and the side (m,): +1 for the ``hi`` face, -1 for ``lo``.
    """
    inv = _safe_inverse(dirs)
    t_axes = np.where(dirs > 0, (hi - origin) * inv, (lo - origin) * inv)
    t_axes = np.where(np.abs(dirs) < _TINY, np.inf, t_axes)
    axis = np.argmin(t_axes, axis=1)
    rows = np.arange(len(dirs))
    return t_axes[rows, axis], axis, np.where(dirs[rows, axis] > 0, 1, -1)
