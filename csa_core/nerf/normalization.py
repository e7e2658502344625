"""Scene normalisation: the metric world box that the hash grid covers.

Two placements (``NerfConfig.normalization``): ``box`` (ours), described here, and ``cube``
(the paper's fixed cube, :func:`fixed_cube_box`). Callers always use metric world poses; the field
sees ``(x - center) / extent + 0.5`` in the unit cube. The box is found from the camera centres and
the measured depth (robust percentiles, so flying pixels do not inflate it, reaching at most three
quarters of the size of the bulk of the points beyond it, so that a few percent of far outliers
cannot either), padded by a margin, and made a cube so that the grid is isotropic. It is stored in
every checkpoint. Ray parameters ``t`` stay metric z-depth along unit-z camera rays, so rendered
depth needs no conversion.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from csa_core.data.camera import Intrinsics, backproject
from csa_core.data.scene import Frame
from csa_core.errors import CSAInputError

if TYPE_CHECKING:
    from csa_core.nerf.config import NerfConfig

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
        """``t`` where each ray enters (at least ``near``) and leaves the box; ``t_far <= t_near``
        if it misses."""
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


# Pairs of optical axes more parallel than this (squared sine of their angle) give no point
# both cameras look at (the official convention's weight cut-off).
_MIN_AXIS_WEIGHT = 1e-5
_MAX_ATTENTION_CAMERAS = 512  # cameras paired to find the point they look at (evenly picked)


def attention_point(poses: np.ndarray) -> np.ndarray:
    """The point the cameras look at: for every pair of cameras, the midpoint of the closest
    points of their optical axes (in front of both cameras), averaged with the squared sine
    of the axes' angle as weight, so near-parallel pairs count little. Without any
    converging pair: the mean camera centre. ``poses`` (N, 4, 4) camera-to-world, OpenCV
    axes (a camera looks along its +z)."""
    if len(poses) > _MAX_ATTENTION_CAMERAS:
        poses = poses[np.linspace(0, len(poses) - 1, _MAX_ATTENTION_CAMERAS).round().astype(int)]
    o = poses[:, :3, 3]
    d = poses[:, :3, 2] / np.linalg.norm(poses[:, :3, 2], axis=1, keepdims=True)
    oa, ob = o[:, None], o[None, :]
    da, db = d[:, None], d[None, :]
    c = np.cross(da, db)
    w = (c**2).sum(-1)
    t = ob - oa
    # Closest points oa + ta * da and ob + tb * db (Cramer's rule), clamped in front.
    ta = (np.cross(t, db) * c).sum(-1) / (w + 1e-10)
    tb = (np.cross(t, da) * c).sum(-1) / (w + 1e-10)
    mid = 0.5 * (
        oa + np.maximum(ta, 0.0)[..., None] * da + ob + np.maximum(tb, 0.0)[..., None] * db
    )
    w = np.where(w > _MIN_AXIS_WEIGHT, w, 0.0)
    if w.sum() <= 0:
        return o.mean(axis=0)
    return (mid * w[..., None]).sum(axis=(0, 1)) / w.sum()


def fixed_cube_box(
    frames: Sequence[Frame], bound: float = 4.0, camera_distance: float = 1.32
) -> SceneBox:
    """The paper's fixed cube as the official code sets it up: the poses centred on the point
    the cameras look at (:func:`attention_point`) and scaled so that the cameras average
    ``camera_distance`` units from it (Instant-NGP's 4 units times torch-ngp's scale 0.33),
    the grid spanning ``[-bound, bound]^3`` of those units (bound 4). In metres: a cube
    centred on that point, ``2 * bound * mean distance / camera_distance`` wide. The depth is
    not read: what lies outside the cube is outside the field, as in the official code.
    Our boxes are axis-aligned in the world frame; the official data loader's re-orientation
    of the poses is not applied.

    Measured on our synthetic rooms (``generate_scene(family, 0, 40, (80, 60))``, the
    training frames; 2026-12-04): cameras that walk inside a room and look outwards sit close
    to the point "they look at", so the cube is small: 4.41 m across in the office (the box:
    8.04 m) and 3.90 m in the apartment (5.19 m), holding 40.7% and 28.2% of the measured
    surface points against the box's 100%. Raise ``NerfConfig.cube_bound`` for such
    captures."""
    if not frames:
        raise CSAInputError("scene", "no frames to normalise")
    poses = np.stack([np.asarray(f.pose, dtype=np.float64) for f in frames])
    if not np.all(np.isfinite(poses)):
        raise CSAInputError("scene", "camera poses must be finite")
    centre = attention_point(poses)
    mean_distance = float(np.linalg.norm(poses[:, :3, 3] - centre, axis=1).mean())
    if not mean_distance > 1e-6:
        raise CSAInputError(
            "normalization",
            "the fixed cube is scaled by the cameras' mean distance from the point they look at, "
            "which is 0 here (one camera, or all at one spot): use normalization=box",
        )
    extent = 2.0 * bound * mean_distance / camera_distance
    return SceneBox((float(centre[0]), float(centre[1]), float(centre[2])), extent)


def fitted_box(frames: Sequence[Frame], intrinsics: Intrinsics, config: NerfConfig) -> SceneBox:
    """The box a fit of ``config`` normalises ``frames`` into: the scene's box
    (:func:`scene_box_from_frames`) or the paper's fixed cube (:func:`fixed_cube_box`), as
    ``config.normalization`` says."""
    if config.normalization == "cube":
        return fixed_cube_box(frames, config.cube_bound, config.cube_camera_distance)
    return scene_box_from_frames(frames, intrinsics, seed=config.seed)
