"""Scene normalisation: the metric world box that the hash grid covers.

Callers always use metric world poses; the field sees ``(x - center) / extent + 0.5`` in the
unit cube. The box is found from the camera centres and the measured depth (robust
percentiles, so flying pixels do not inflate it, reaching at most three quarters of the size
of the bulk of the points beyond it, so that a few percent of far outliers cannot either),
padded by a margin, and made a cube so that the grid is isotropic. It is stored in every checkpoint. Ray parameters ``t`` stay metric
z-depth along unit-z camera rays, so rendered depth needs no conversion.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from csa_core.data.camera import Intrinsics, backproject
from csa_core.data.scene import Frame
from csa_core.errors import CSAInputError

DEFAULT_EXTENT_WITHOUT_DEPTH = 6.0  # metres of scene around the cameras when no depth is known
_MARGIN = 0.1  # fraction of the box added on every side
_PERCENTILES = (0.5, 99.5)  # robust extent of the depth point cloud
# The bulk of the points, and how far beyond it (a fraction of its size) the extent may reach:
# sensors' far outliers (a few percent of the pixels 20-60 m away) would otherwise set the
# 99.5th percentile and stretch a room's box over tens of metres. Rooms need far less reach:
# at most 0.21 in the synthetic families, 0.29 on the real 7-Scenes kitchen.
_BULK_PERCENTILES = (5.0, 95.0)
_MAX_REACH = 0.75


@dataclass(frozen=True)
class SceneBox:
    """An axis-aligned cube in world coordinates (metres): centre and edge length."""

    center: tuple[float, float, float]
    extent: float

    def to_unit(self, x: Tensor) -> Tensor:
        """World points (..., 3) -> unit-cube coordinates."""
        c = torch.as_tensor(self.center, dtype=x.dtype, device=x.device)
        return (x - c) / self.extent + 0.5

    def from_unit(self, u: Tensor) -> Tensor:
        """Unit-cube coordinates (..., 3) -> world points."""
        c = torch.as_tensor(self.center, dtype=u.dtype, device=u.device)
        return (u - 0.5) * self.extent + c

    @property
    def diagonal(self) -> float:
        return float(self.extent * np.sqrt(3.0))

    def ray_interval(self, origins: Tensor, dirs: Tensor, near: float) -> tuple[Tensor, Tensor]:
        """``t`` where each ray enters (at least ``near``) and leaves the box; ``t_far <= t_near`` if it misses."""
        lo = (
            torch.as_tensor(self.center, dtype=origins.dtype, device=origins.device)
            - 0.5 * self.extent
        )
        hi = lo + self.extent
        safe = torch.where(dirs.abs() < 1e-9, torch.full_like(dirs, 1e-9), dirs)
        t0, t1 = (lo - origins) / safe, (hi - origins) / safe
        t_near = torch.minimum(t0, t1).amax(dim=-1).clamp_min(near)
        t_far = torch.maximum(t0, t1).amin(dim=-1)
        return t_near, t_far

    def to_dict(self) -> dict:
        return {"center": list(self.center), "extent": self.extent}

    @classmethod
    def from_dict(cls, d: dict) -> SceneBox:
        c = [float(v) for v in d["center"]]
        if len(c) != 3 or not np.all(np.isfinite(c)) or not 0 < float(d["extent"]) < np.inf:
            raise ValueError(
                "scene box needs a finite 3-vector center and a finite positive extent"
            )
        return cls((c[0], c[1], c[2]), float(d["extent"]))


def scene_box_from_frames(
    frames: Sequence[Frame], intrinsics: Intrinsics, max_points: int = 200_000, seed: int = 0
) -> SceneBox:
    """The box of the camera centres and the measured surface points of ``frames``.

    Without any depth, the box is the camera centres padded by ``DEFAULT_EXTENT_WITHOUT_DEPTH``.
    """
    if not frames:
        raise CSAInputError("scene", "no frames to normalise")
    centres = np.stack([np.asarray(f.pose, dtype=np.float64)[:3, 3] for f in frames])
    if not np.all(np.isfinite(centres)):
        raise CSAInputError("scene", "camera poses must be finite")
    rng = np.random.default_rng(seed)
    per_frame = max(1, max_points // len(frames))
    clouds = []
    for f in frames:
        if f.depth is None or not (f.depth > 0).any():
            continue
        pts = backproject(
            f.depth.astype(np.float64), intrinsics, np.asarray(f.pose, dtype=np.float64)
        )
        pts = pts[f.depth > 0]
        if len(pts) > per_frame:
            pts = pts[rng.choice(len(pts), per_frame, replace=False)]
        clouds.append(pts)
    if clouds:
        pts = np.concatenate(clouds)
        q = np.percentile(pts, [*_PERCENTILES, *_BULK_PERCENTILES], axis=0)
        reach = _MAX_REACH * (q[3] - q[2])
        lo = np.minimum(np.maximum(q[0], q[2] - reach), centres.min(axis=0))
        hi = np.maximum(np.minimum(q[1], q[3] + reach), centres.max(axis=0))
    else:
        lo = centres.min(axis=0) - DEFAULT_EXTENT_WITHOUT_DEPTH / 2
        hi = centres.max(axis=0) + DEFAULT_EXTENT_WITHOUT_DEPTH / 2
    extent = float((hi - lo).max()) * (1.0 + 2.0 * _MARGIN)
    extent = max(extent, 1e-3)
    c = (lo + hi) / 2.0
    return SceneBox((float(c[0]), float(c[1]), float(c[2])), extent)
