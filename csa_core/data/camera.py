"""Pinhole camera intrinsics and the conventions for poses.

Poses are 4x4 camera-to-world matrices in metres with OpenCV camera axes
(x right, y down, z forward), as in ScanNet and 7-Scenes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from csa_core.errors import CSAInputError

MIN_SIZE_PX, MAX_SIZE_PX = 8, 8192


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of an image of ``width`` x ``height`` pixels."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @classmethod
    def from_matrix(cls, K: np.ndarray, width: int, height: int) -> Intrinsics:
        """Build from a 3x3 or 4x4 (ScanNet) intrinsic matrix."""
        K = np.asarray(K, dtype=np.float64)
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(width), int(height))

    def matrix(self) -> np.ndarray:
        """The 3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, width: int, height: int) -> Intrinsics:
        """Intrinsics of the same camera resized to ``width`` x ``height`` (scaled per axis).

        Uses the pixel-edge convention (pixel centres at +0.5), so that resizing by an
        integer factor maps pixel centres onto pixel centres.
        """
        sx, sy = width / self.width, height / self.height
        return Intrinsics(
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
            width=int(width),
            height=int(height),
        )

    def to_dict(self) -> dict:
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "width": self.width, "height": self.height}

    @classmethod
    def from_dict(cls, d: dict) -> Intrinsics:
        return cls(float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"]), int(d["width"]), int(d["height"]))


def parse_size(text: str, field: str = "--size") -> tuple[int, int]:
    """``"160x120"`` -> ``(160, 120)`` (width, height); anything else is a :class:`CSAInputError`
    naming ``field``. The one parser of image sizes for the CLI, the server and the benchmarks."""
    parts = str(text).lower().split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
        raise CSAInputError(field, f"expected WIDTHxHEIGHT such as 160x120, got {text!r}")
    w, h = int(parts[0]), int(parts[1])
    if not (MIN_SIZE_PX <= w <= MAX_SIZE_PX and MIN_SIZE_PX <= h <= MAX_SIZE_PX):
        raise CSAInputError(
            field, f"width and height must be within {MIN_SIZE_PX}..{MAX_SIZE_PX}, got {text!r}"
        )
    return w, h


def pixel_rays(intr: Intrinsics, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-space ray origins and directions through every pixel centre.

    Directions have unit z in the camera frame (so ``t`` along a ray is z-depth),
    shaped (H, W, 3); the origin is the camera centre broadcast to the same shape.
    """
    u, v = np.meshgrid(np.arange(intr.width) + 0.0, np.arange(intr.height) + 0.0)
    d_cam = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], axis=-1)
    R, t = pose[:3, :3], pose[:3, 3]
    d_world = d_cam @ R.T
    return np.broadcast_to(t, d_world.shape).copy(), d_world


def backproject(depth: np.ndarray, intr: Intrinsics, pose: np.ndarray) -> np.ndarray:
    """World points (H, W, 3) of a z-depth map in metres; pixels with depth 0 give NaN."""
    o, d = pixel_rays(intr, pose)
    pts = o + d * depth[..., None]
    pts[depth <= 0] = np.nan
    return pts


def project(points: np.ndarray, intr: Intrinsics, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project world points (..., 3) into a camera: pixel coordinates (..., 2) and z-depth (...)."""
    w2c = np.linalg.inv(pose)
    p = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = p[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([p[..., 0] / z * intr.fx + intr.cx, p[..., 1] / z * intr.fy + intr.cy], axis=-1)
    return uv, z
