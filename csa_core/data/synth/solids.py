"""Capsules, and the solids of a room: oriented boxes and capsules cast together.

A capsule is every point within ``radius`` of a segment ``a``-``b``: a round rod with
hemispherical ends (chair legs and spindles, lamp poles, plant stems, castors when the
segment has no length). A chain of capsules sharing end points bends smoothly, which is how
curved parts (a bentwood crest rail, an arc lamp) are built. Ray casting is exact and
vectorised like the slab test of :mod:`csa_core.data.synth.boxes`: one ray origin, many
directions, all rays against all capsules in one broadcast (float64).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from csa_core.data.synth.boxes import BoxSet, any_hit, closest_hit, face_hit

_TINY = 1e-12


@dataclass(frozen=True)
class CapsuleSet:
    """``n`` capsules: segment ends ``a`` and ``b`` (n, 3) and ``radius`` (n,), metres."""

    a: np.ndarray
    b: np.ndarray
    radius: np.ndarray

    def __len__(self) -> int:
        return len(self.radius)

    def subset(self, idx: np.ndarray) -> CapsuleSet:
        return CapsuleSet(self.a[idx], self.b[idx], self.radius[idx])

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        r = self.radius[:, None]
        return np.minimum(self.a, self.b) - r, np.maximum(self.a, self.b) + r

    def corners(self) -> np.ndarray:
        """The 8 corners of every capsule's world bounds, (n, 8, 3)."""
        lo, hi = self.aabb()
        pick = np.array(
            [[sx, sy, sz] for sx in (0, 1) for sy in (0, 1) for sz in (0, 1)], dtype=bool
        )
        return np.where(pick[None], hi[:, None, :], lo[:, None, :])

    def frame(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unit axis ``ez`` (a to b) and two unit normals ``ex``, ``ey`` of capsules ``idx``."""
        ba = self.b[idx] - self.a[idx]
        length = np.linalg.norm(ba, axis=1, keepdims=True)
        ez = np.where(length > _TINY, ba / np.maximum(length, _TINY), [0.0, 0.0, 1.0])
        ref = np.where(np.abs(ez[:, 2:3]) < 0.9, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
        ex = np.cross(ref, ez)
        ex /= np.linalg.norm(ex, axis=1, keepdims=True)
        return ex, np.cross(ez, ex), ez


def _entry(bard, rdoa, rdob, baba, baoa, oaoa, obob, r2) -> np.ndarray:
    """Unit-ray entry parameters into capsules (inf on a miss and for rays starting inside),
    from the dot products of the unit directions with the axis ``ba = b - a`` (``bard``), with
    ``oa = origin - a`` (``rdoa``) and ``ob = origin - b`` (``rdob``), and the per-capsule
    ``ba.ba``, ``ba.oa``, ``oa.oa``, ``ob.ob`` and ``radius**2`` (broadcast against them).

    The capsule is the union of the lateral surface of its cylinder between the end discs and
    the two end balls, so its entry is the earliest of those three entries (the end discs lie
    inside the balls).
    """
    qa = baba - bard * bard
    qb = baba * rdoa - baoa * bard
    qc = baba * oaoa - baoa * baoa - r2 * baba
    disc = qb * qb - qa * qc
    with np.errstate(divide="ignore", invalid="ignore"):
        t_body = (-qb - np.sqrt(np.maximum(disc, 0.0))) / qa
        y = baoa + t_body * bard
        body = (disc >= 0) & (qa > _TINY * np.maximum(baba, _TINY)) & (y > 0) & (y < baba)
    best = np.where(body & (t_body > 0), t_body, np.inf)
    for hb, occ in ((rdoa, oaoa), (rdob, obob)):
        hd = hb * hb - (occ - r2)
        t_ball = -hb - np.sqrt(np.maximum(hd, 0.0))
        best = np.minimum(best, np.where((hd >= 0) & (t_ball > 0) & (occ > r2), t_ball, np.inf))
    inside = ((qc < 0) & (baoa > 0) & (baoa < baba)) | (oaoa <= r2) | (obob <= r2)
    return np.where(inside, np.inf, best)


def _terms(origin: np.ndarray, caps: CapsuleSet) -> tuple[np.ndarray, ...]:
    o = np.asarray(origin, dtype=np.float64)
    ba, oa, ob = caps.b - caps.a, o - caps.a, o - caps.b
    dot = lambda u, v: np.einsum("...j,...j->...", u, v)  # noqa: E731
    return ba, oa, ob, dot(ba, ba), dot(ba, oa), dot(oa, oa), dot(ob, ob), caps.radius**2


def _unit(dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = np.asarray(dirs, dtype=np.float64)
    norm = np.maximum(np.linalg.norm(d, axis=-1), _TINY)
    return d / norm[..., None], norm


def capsule_entry(origin: np.ndarray, dirs: np.ndarray, caps: CapsuleSet) -> np.ndarray:
    """Ray parameter where each ray first enters each capsule, (n_rays, n_caps); inf on a miss
    and for rays starting inside. Rays are ``origin + t * dirs`` (``dirs`` need not be unit).

    float32 for speed, like the slab test: callers refine the winning hit with
    :func:`capsule_entry_paired` (float64)."""
    rd, norm = _unit(dirs)
    rd = rd.astype(np.float32)
    ba, oa, ob, *scalars = (v.astype(np.float32) for v in _terms(origin, caps))
    t = _entry(rd @ ba.T, rd @ oa.T, rd @ ob.T, *(v[None, :] for v in scalars))
    return t / norm[:, None].astype(np.float32)


def capsule_entry_paired(origin: np.ndarray, dirs: np.ndarray, caps: CapsuleSet) -> np.ndarray:
    """Like :func:`capsule_entry` for ray k against capsule k only, (n,)."""
    rd, norm = _unit(dirs)
    ba, oa, ob, *scalars = _terms(origin, caps)
    dot = lambda u, v: np.einsum("ij,ij->i", u, v)  # noqa: E731
    return _entry(dot(rd, ba), dot(rd, oa), dot(rd, ob), *scalars) / norm


def capsule_surface(
    origin: np.ndarray, dirs: np.ndarray, caps: CapsuleSet, idx: np.ndarray, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """At hits ``origin + t * dirs`` on capsules ``idx``: the texture frame point (m, 3) and
    the outward world normal (m, 3).

    The texture frame point is (radius, arc length around the axis, distance along the axis
    from the middle), read on a "face" whose tangent coordinates are its last two entries
    (``textures.face_uv`` with axis 0), so grain runs along the rod.
    """
    p = origin + t[:, None] * dirs
    a, b, r = caps.a[idx], caps.b[idx], caps.radius[idx]
    ba = b - a
    baba = np.maximum(np.einsum("ij,ij->i", ba, ba), _TINY)
    s = np.clip(np.einsum("ij,ij->i", p - a, ba) / baba, 0.0, 1.0)
    radial = p - (a + s[:, None] * ba)
    normal = radial / np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), _TINY)
    ex, ey, ez = caps.frame(idx)
    phi = np.arctan2(np.einsum("ij,ij->i", normal, ey), np.einsum("ij,ij->i", normal, ex))
    along = np.einsum("ij,ij->i", p - (a + b) / 2, ez)
    return np.stack([r, r * phi, along], axis=-1), normal


@dataclass(frozen=True)
class Solids:
    """The solids of a room: ``boxes`` then ``caps`` in one index space (box k is solid k,
    capsule k is solid ``len(boxes) + k``)."""

    boxes: BoxSet
    caps: CapsuleSet

    def __len__(self) -> int:
        return len(self.boxes) + len(self.caps)

    def split(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        nb = len(self.boxes)
        idx = np.asarray(idx)
        return idx[idx < nb], idx[idx >= nb] - nb

    def subset(self, idx: np.ndarray) -> Solids:
        bi, ci = self.split(idx)
        return Solids(self.boxes.subset(bi), self.caps.subset(ci))

    def corners(self) -> np.ndarray:
        return np.concatenate([self.boxes.corners(), self.caps.corners()])

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        blo, bhi = self.boxes.aabb()
        clo, chi = self.caps.aabb()
        return np.concatenate([blo, clo]), np.concatenate([bhi, chi])

    def closest_hit(
        self, origin: np.ndarray, dirs: np.ndarray, t_max: np.ndarray, eps: float = 1e-4
    ) -> tuple[np.ndarray, np.ndarray]:
        """Nearest solid entered by each ray before ``t_max``: (t, solid index), -1 where none."""
        t, idx = closest_hit(origin, dirs, self.boxes, t_max, eps)
        if len(self.caps):
            tc = capsule_entry(origin, dirs, self.caps)
            tc[tc <= eps] = np.inf
            k = np.argmin(tc, axis=1)
            tk = tc[np.arange(len(dirs)), k]
            better = (tk < t) & (tk < t_max)
            t = np.where(better, tk, t)
            idx = np.where(better, len(self.boxes) + k, idx)
        return t, idx

    def any_hit(
        self, origin: np.ndarray, dirs: np.ndarray, t_end: np.ndarray, eps: float = 1e-4
    ) -> np.ndarray:
        """Whether each ray enters some solid with ``eps < t < t_end`` (shadow test)."""
        blocked = any_hit(origin, dirs, self.boxes, t_end, eps)
        if len(self.caps):
            tc = capsule_entry(origin, dirs, self.caps)
            blocked |= ((tc > eps) & (tc < t_end[:, None])).any(axis=1)
        return blocked

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """Exact signed distance (m, n) of points (m, 3) to every solid: negative inside."""
        pts = np.asarray(points, dtype=np.float64)
        q = np.einsum("nji,mnj->mni", self.boxes.rot, pts[:, None, :] - self.boxes.center[None])
        excess = np.abs(q) - self.boxes.half[None]
        box_d = np.linalg.norm(np.maximum(excess, 0.0), axis=-1) + np.minimum(
            excess.max(axis=-1), 0.0
        )
        ba = self.caps.b - self.caps.a
        pa = pts[:, None, :] - self.caps.a[None]
        s = np.clip(
            np.einsum("mnj,nj->mn", pa, ba) / np.maximum(np.einsum("nj,nj->n", ba, ba), _TINY),
            0.0,
            1.0,
        )
        cap_d = np.linalg.norm(pa - s[..., None] * ba[None], axis=-1) - self.caps.radius[None]
        return np.concatenate([box_d, cap_d], axis=1)

    def surface(
        self, origin: np.ndarray, dirs: np.ndarray, idx: np.ndarray, t_hint: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Exact float64 entry of rays into their solids ``idx`` (all >= 0): ``t`` (m,), the
        texture-frame point (m, 3), the face axis (m,) and the outward world normal (m, 3).
        ``t_hint`` is the float32 entry from :meth:`closest_hit`, kept for a ray that grazes a
        capsule so closely that float64 finds no entry."""
        m = len(idx)
        t, local, axis, normal = (
            np.zeros(m),
            np.zeros((m, 3)),
            np.zeros(m, dtype=np.int64),
            np.zeros((m, 3)),
        )
        nb = len(self.boxes)
        on_box = idx < nb
        if on_box.any():
            bi = idx[on_box]
            tb, lb, ab, nl = face_hit(origin, dirs[on_box], self.boxes, bi)
            t[on_box], local[on_box], axis[on_box] = tb, lb, ab
            normal[on_box] = self.boxes.normal_to_world(nl, bi)
        on_cap = ~on_box
        if on_cap.any():
            ci = idx[on_cap] - nb
            tc = capsule_entry_paired(origin, dirs[on_cap], self.caps.subset(ci))
            tc = np.where(np.isfinite(tc), tc, t_hint[on_cap])
            lc, nc = capsule_surface(origin, dirs[on_cap], self.caps, ci, tc)
            t[on_cap], local[on_cap], normal[on_cap] = tc, lc, nc
        return t, local, axis, normal
