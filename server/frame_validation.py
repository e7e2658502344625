"""Validation of one uploaded frame with the core scene-folder readers.

Every part is checked before anything is stored: images decode and are not larger than the
limit (read from the header first), colour is 8-bit, depth is a single-channel uint16 PNG in
millimetres, labels are a PNG of NYU40 ids, the pose is a rigid 4x4 camera-to-world transform
and the intrinsics a sane camera for the image (the core's rules, ``csa_core.data.camera``),
and the sizes agree with each other and with the frames already in the scene. Errors name the
field.
"""

from __future__ import annotations

import re
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from csa_core.data import image_files
from csa_core.data.camera import Intrinsics, check_pose, intrinsics_from_matrix
from csa_core.errors import CSAInputError
from server.db.models import MAX_ID
from server.errors import APIError, invalid
from server.image_headers import UploadHeaderError, check_upload_header, image_format

FRAME_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
ASPECT_TOLERANCE = 0.01  # depth and labels may be stored at another resolution of the same camera


@dataclass(frozen=True)
class FrameParts:
    """Raw bytes of an uploaded frame; ``fields`` maps part -> the name used in errors."""

    color: bytes
    depth: bytes
    pose: str
    labels: bytes | None = None
    intrinsics: str | None = None
    depth_intrinsics: str | None = None
    fields: dict[str, str] | None = None

    def field(self, part: str) -> str:
        return (self.fields or {}).get(part, part)


@dataclass(frozen=True)
class SceneCamera:
    """What the scene already fixes: colour camera and depth image size."""

    intrinsics: Intrinsics | None = None
    depth_intrinsics: Intrinsics | None = None
    depth_size: tuple[int, int] | None = None


@dataclass(frozen=True)
class ValidFrame:
    color: bytes
    color_ext: str
    depth: bytes
    labels: bytes | None
    pose: np.ndarray
    color_size: tuple[int, int]
    depth_size: tuple[int, int]
    intrinsics: Intrinsics | None  # given with this frame (colour camera)
    depth_intrinsics: Intrinsics | None


class NonFinitePose(APIError):
    """The pose is not finite (ScanNet marks lost tracking so); archives skip such frames."""


def check_frame_name(name: str, field: str = "name") -> str:
    if not FRAME_NAME.fullmatch(name):
        raise invalid(
            field,
            f"frame name {name!r} must be 1-64 letters, digits, '_', '-' or '.', starting with a "
            "letter or digit",
        )
    if name.isdigit() and int(name) > MAX_ID:  # numeric names are the frames' order keys
        raise invalid(field, f"numeric frame name {name} is larger than {MAX_ID}")
    return name


def _decode_checked(
    data: bytes, field: str, max_pixels: int, tmp: Path, reader, png_only: bool = False, **kw
) -> np.ndarray:
    if png_only and image_format(data) == ".jpg":
        # Depth and labels are kept and served as PNG files; JPEG's lossy compression would
        # change their values (label ids blur into their neighbours' at every edge).
        raise invalid(field, "must be a PNG file, not a JPEG (lossy compression changes values)")
    try:
        fmt, size = check_upload_header(data, field, max_pixels)
    except UploadHeaderError as e:
        raise invalid(e.where, e.problem) from None
    path = tmp / f"{field.replace('/', '_')}{fmt}"
    path.write_bytes(data)
    try:
        img = reader(path, **kw)
    except CSAInputError as e:
        raise invalid(field, e.problem) from None
    if (img.shape[1], img.shape[0]) != size:
        raise invalid(field, "image header and content disagree on the size")
    return img


def _matrix(text: str, field: str, shapes: tuple[tuple[int, int], ...], tmp: Path) -> np.ndarray:
    path = tmp / f"{field.replace('/', '_')}.txt"
    path.write_text(text)
    try:
        return image_files.read_matrix(path, shapes)
    except CSAInputError as e:
        raise invalid(field, e.problem) from None


def parse_pose(text: str, field: str, tmp: Path) -> np.ndarray:
    pose = _matrix(text, field, ((4, 4),), tmp)
    if not np.all(np.isfinite(pose)):
        raise NonFinitePose(422, "invalid", f"{field}: pose is not finite", field=field)
    try:
        return check_pose(pose, field)
    except CSAInputError as e:
        raise invalid(field, e.problem) from None


def parse_intrinsics(text: str, field: str, size: tuple[int, int], tmp: Path) -> Intrinsics:
    K = _matrix(text, field, ((3, 3), (4, 4)), tmp)
    try:
        return intrinsics_from_matrix(K, *size, field)
    except CSAInputError as e:
        raise invalid(field, e.problem) from None


def _same_aspect(a: tuple[int, int], b: tuple[int, int]) -> bool:
    return abs(a[0] / a[1] - b[0] / b[1]) <= ASPECT_TOLERANCE * (b[0] / b[1])


def same_camera(a: Intrinsics, b: Intrinsics) -> bool:
    return np.allclose(
        [a.fx, a.fy, a.cx, a.cy, a.width, a.height],
        [b.fx, b.fy, b.cx, b.cy, b.width, b.height],
        rtol=1e-6,
        atol=1e-6,
    )


def validate_frame(parts: FrameParts, scene: SceneCamera, max_pixels: int) -> ValidFrame:
    """Check an uploaded frame against itself and its scene; raises :class:`APIError` (422)."""
    with tempfile.TemporaryDirectory(prefix="csa-frame-") as d:
        tmp = Path(d)
        color = _decode_checked(
            parts.color, parts.field("color"), max_pixels, tmp, image_files.read_color
        )
        color_size = (color.shape[1], color.shape[0])
        depth = _decode_checked(
            parts.depth,
            parts.field("depth"),
            max_pixels,
            tmp,
            image_files.read_depth_mm,
            png_only=True,
        )
        depth_size = (depth.shape[1], depth.shape[0])
        labels = None
        if parts.labels is not None:
            labels = _decode_checked(
                parts.labels,
                parts.field("labels"),
                max_pixels,
                tmp,
                image_files.read_label_image,
                png_only=True,
                max_id=40,
            )
        pose = parse_pose(parts.pose, parts.field("pose"), tmp)
        intr = (
            parse_intrinsics(parts.intrinsics, parts.field("intrinsics"), color_size, tmp)
            if parts.intrinsics
            else None
        )
        dintr = (
            parse_intrinsics(
                parts.depth_intrinsics, parts.field("depth_intrinsics"), depth_size, tmp
            )
            if parts.depth_intrinsics
            else None
        )

    if scene.intrinsics is not None:
        want = (scene.intrinsics.width, scene.intrinsics.height)
        if color_size != want:
            raise invalid(
                parts.field("color"),
                f"size mismatch: colour is {color_size[0]}x{color_size[1]}, this scene's frames "
                f"are {want[0]}x{want[1]}",
            )
        if intr is not None and not same_camera(intr, scene.intrinsics):
            raise invalid(
                parts.field("intrinsics"),
                "differ from the intrinsics of this scene's earlier frames",
            )
    elif intr is None:
        raise invalid(
            parts.field("intrinsics"),
            "required with the first frame of a scene (3x3 or 4x4 matrix)",
        )
    if scene.depth_size is not None and depth_size != scene.depth_size:
        raise invalid(
            parts.field("depth"),
            f"size mismatch: depth is {depth_size[0]}x{depth_size[1]}, this scene's depth images "
            f"are {scene.depth_size[0]}x{scene.depth_size[1]}",
        )
    # A scene has one depth camera, fixed by its first frame: its own (depth_intrinsics with
    # the first frame) or the colour camera scaled to the depth size (none with the first frame).
    if dintr is not None and scene.intrinsics is not None and scene.depth_intrinsics is None:
        raise invalid(
            parts.field("depth_intrinsics"),
            "this scene's depth is the colour camera (its first frame came without depth "
            "intrinsics); a scene has one depth camera, so leave depth_intrinsics out or upload to "
            "a new scene",
        )
    if (
        dintr is None
        and scene.depth_intrinsics is None
        and not _same_aspect(depth_size, color_size)
    ):
        raise invalid(
            parts.field("depth"),
            f"size mismatch: depth is {depth_size[0]}x{depth_size[1]}, colour is "
            f"{color_size[0]}x{color_size[1]} (aspect ratios differ; send depth_intrinsics for a "
            "separate depth camera)",
        )
    if (
        scene.depth_intrinsics is not None
        and dintr is not None
        and not same_camera(dintr, scene.depth_intrinsics)
    ):
        raise invalid(parts.field("depth_intrinsics"), "differ from this scene's depth intrinsics")
    if labels is not None and not _same_aspect((labels.shape[1], labels.shape[0]), color_size):
        raise invalid(
            parts.field("labels"),
            f"size mismatch: labels are {labels.shape[1]}x{labels.shape[0]}, colour is "
            f"{color_size[0]}x{color_size[1]}",
        )

    return ValidFrame(
        color=parts.color,
        color_ext=image_format(parts.color) or ".png",
        depth=parts.depth,
        labels=parts.labels,
        pose=pose,
        color_size=color_size,
        depth_size=depth_size,
        intrinsics=intr,
        depth_intrinsics=dintr,
    )
