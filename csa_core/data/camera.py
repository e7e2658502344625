"""Pinhole camera intrinsics and the conventions for poses.

Poses are 4x4 camera-to-world matrices in metres with OpenCV camera axes
(x right, y down, z forward), as in ScanNet and 7-Scenes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from csa_core.errors import CSAInputError

MIN_SIZE_PX, MAX_SIZE_PX = 8, 8192

MAX_TRANSLATION_M = 1.0e4
"""Largest distance (metres) of a camera from the world origin that a pose may state.

Indoor scans span metres and building-scale captures hundreds of metres; 10 km leaves room for
any real capture in a local frame, while far larger numbers only come from broken trackers or
hostile input, and their squares overflow the float32 ray arithmetic of the NeRF."""

RIGID_TOLERANCE = 1.0e-3
"""Largest entry of |RᵀR - I| (and of the last row's distance from 0 0 0 1) in a rigid pose.

Poses are stored as text with a few decimals and come from trackers working in float32; the
7-Scenes kitchen poses deviate by up to 4e-4. A scaled or sheared matrix deviates by far more
(scale 1.01 already gives 0.02)."""

FOCAL_RATIO_RANGE = (1.0e-2, 1.0e2)
"""Focal length relative to the image side it belongs to (fx / width, fy / height): from a
field of view of 178 degrees to one of 0.6 degrees."""

PRINCIPAL_POINT_MARGIN = 1.0
"""How far the principal point may lie outside the image, in image sizes (0: inside only)."""


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
        return cls(
            float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(width), int(height)
        )

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
        return {
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "width": self.width,
            "height": self.height,
        }

    @classmethod
    def from_dict(cls, d: dict) -> Intrinsics:
        return cls(
            float(d["fx"]),
            float(d["fy"]),
            float(d["cx"]),
            float(d["cy"]),
            int(d["width"]),
            int(d["height"]),
        )


def check_pose(pose: np.ndarray, where: str | Path) -> np.ndarray:
    """``pose`` as a float64 4x4 camera-to-world rigid transform, or a :class:`CSAInputError`
    naming ``where`` and what is wrong: not 4x4, not finite, last row not 0 0 0 1, rotation part
    not orthonormal or a reflection (determinant -1), translation beyond
    :data:`MAX_TRANSLATION_M`. The one check of poses for the scene reader and the server."""
    m = np.asarray(pose, dtype=np.float64)
    if m.shape != (4, 4):
        raise CSAInputError(
            where, f"pose must be a 4x4 matrix, got shape {'x'.join(map(str, m.shape))}"
        )
    if not np.all(np.isfinite(m)):
        raise CSAInputError(where, "pose is not finite")
    if np.abs(m[3] - (0.0, 0.0, 0.0, 1.0)).max() > RIGID_TOLERANCE:
        raise CSAInputError(where, "last row of a camera-to-world pose must be 0 0 0 1")
    R, t = m[:3, :3], m[:3, 3]
    with np.errstate(over="ignore", invalid="ignore"):
        deviation = float(np.abs(R.T @ R - np.eye(3)).max())
    if not deviation <= RIGID_TOLERANCE:
        raise CSAInputError(
            where,
            f"rotation part is not orthonormal (max |RᵀR - I| = {deviation:.3g} > "
            f"{RIGID_TOLERANCE:g}): a pose must be a rigid transform, without scale or shear",
        )
    if np.linalg.det(R) < 0:
        raise CSAInputError(where, "rotation part has determinant -1: a reflection, not a rotation")
    largest = float(np.abs(t).max())
    distance = largest * float(np.linalg.norm(t / largest)) if largest > 0 else 0.0  # no overflow
    if distance > MAX_TRANSLATION_M:
        raise CSAInputError(
            where,
            f"translation is {distance:.3g} m from the origin, more than {MAX_TRANSLATION_M:g} m",
        )
    return m


def check_intrinsics(intr: Intrinsics, where: str | Path) -> Intrinsics:
    """``intr`` when it describes a usable pinhole camera, else a :class:`CSAInputError` naming
    ``where``: image size within 1..:data:`MAX_SIZE_PX`, finite values, focal lengths within
    :data:`FOCAL_RATIO_RANGE` of the image size, principal point within
    :data:`PRINCIPAL_POINT_MARGIN` image sizes of the image."""
    w, h = intr.width, intr.height
    if not (1 <= w <= MAX_SIZE_PX and 1 <= h <= MAX_SIZE_PX):
        raise CSAInputError(
            where, f"image size {w}x{h} is outside 1..{MAX_SIZE_PX} pixels per side"
        )
    values = {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy}
    for name, v in values.items():
        if not np.isfinite(v):
            raise CSAInputError(where, f"{name} is not finite")
    lo, hi = FOCAL_RATIO_RANGE
    for name, f, side in (("fx", intr.fx, w), ("fy", intr.fy, h)):
        if f <= 0:
            raise CSAInputError(where, f"focal lengths must be positive, {name} is {f:g}")
        if not lo * side <= f <= hi * side:
            raise CSAInputError(
                where,
                f"{name} = {f:g} px is not within {lo:g}..{hi:g} times the image size ({side} px)",
            )
    m = PRINCIPAL_POINT_MARGIN
    for name, c, side in (("cx", intr.cx, w), ("cy", intr.cy, h)):
        if not -m * side <= c <= (1 + m) * side:
            raise CSAInputError(
                where,
                f"principal point {name} = {c:g} px lies more than {m:g} image sizes outside the "
                f"{side}-pixel image",
            )
    return intr


CAPTURE_CENTRE_OFFSET = 0.2
"""Largest distance of a captured image's principal point from the image centre, as a fraction
of the image side (at least a pixel). Cameras have it within a few percent of the centre;
intrinsics written for another image size (images resized after calibration) put it at the
image's edge (intrinsics of twice the size) or at a quarter (half the size). A rendering
camera may be anything :func:`check_intrinsics` allows; a stored scene's cameras may not."""

PINHOLE_TOLERANCE = 1.0e-6
"""Largest deviation of the fixed cells of an intrinsic matrix (the zeros and ones of a pinhole
matrix) that :func:`intrinsics_from_matrix` accepts; the skew may reach this times 1000 of fx."""


def intrinsics_from_matrix(K: np.ndarray, width: int, height: int, where: str | Path) -> Intrinsics:
    """The checked camera (:func:`check_intrinsics`) of a 3x3 or 4x4 (ScanNet) intrinsic matrix
    of an image of ``width`` x ``height``, or a :class:`CSAInputError` naming ``where`` when the
    matrix is not a pinhole matrix: a bottom row other than ``0 0 1``, skew (this camera model has
    none), or, in a 4x4 matrix, a fourth row or column other than the identity's. Those cells
    would otherwise be ignored without a word; also when the principal point lies farther than
    :data:`CAPTURE_CENTRE_OFFSET` from the image centre (intrinsics of another image size). The
    one reader of intrinsic matrices for the scene reader and the server."""
    m = np.asarray(K, dtype=np.float64)
    if m.shape not in ((3, 3), (4, 4)):
        raise CSAInputError(
            where,
            f"intrinsics must be a 3x3 or 4x4 matrix, got shape {'x'.join(map(str, m.shape))}",
        )
    intr = check_intrinsics(Intrinsics.from_matrix(m, width, height), where)
    if not np.all(np.isfinite(m)):
        raise CSAInputError(where, "intrinsic matrix is not finite")
    tol = PINHOLE_TOLERANCE
    if not np.abs(m[2, :3] - (0.0, 0.0, 1.0)).max() <= tol:
        raise CSAInputError(
            where,
            "not a pinhole intrinsic matrix: its third row must be 0 0 1, got "
            f"{' '.join(f'{v:g}' for v in m[2, :3])}",
        )
    if not abs(m[1, 0]) <= tol * max(1.0, intr.fy):
        raise CSAInputError(
            where, f"not a pinhole intrinsic matrix: the cell below fx must be 0, got {m[1, 0]:g}"
        )
    if not abs(m[0, 1]) <= 1e3 * tol * intr.fx:
        raise CSAInputError(
            where,
            f"skew {m[0, 1]:g} is not supported: the camera model is a pinhole without skew "
            "(the cell right of fx must be 0)",
        )
    if m.shape == (4, 4) and not (
        np.abs(m[3] - (0.0, 0.0, 0.0, 1.0)).max() <= tol and np.abs(m[:3, 3]).max() <= tol
    ):
        raise CSAInputError(
            where,
            "not a pinhole intrinsic matrix: the fourth row and column of a 4x4 matrix must be "
            "those of the identity (0 0 0 1)",
        )
    for name, c, side in (("cx", intr.cx, intr.width), ("cy", intr.cy, intr.height)):
        centre = (side - 1) / 2
        if abs(c - centre) > max(CAPTURE_CENTRE_OFFSET * side, 1.0):
            raise CSAInputError(
                where,
                f"principal point {name} = {c:g} px is far from the centre ({centre:g}) "
                f"of the {intr.width}x{intr.height} image: "
                "are these the intrinsics of another image size? "
                "(they must match the images as stored)",
            )
    return intr


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


def project(
    points: np.ndarray, intr: Intrinsics, pose: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Project world points (..., 3) into a camera: pixel coordinates (..., 2) and z-depth (...)."""
    w2c = np.linalg.inv(pose)
    p = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = p[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack(
            [p[..., 0] / z * intr.fx + intr.cx, p[..., 1] / z * intr.fy + intr.cy], axis=-1
        )
    return uv, z
