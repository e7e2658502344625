"""Reading and writing the image files of a scene folder, with errors that name the file."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from csa_core.atomic_io import atomic_file
from csa_core.errors import CSAInputError

COLOR_EXTS = (".jpg", ".jpeg", ".png")


def _imread(path: Path, flags: int) -> np.ndarray:
    if not path.is_file():
        raise CSAInputError(path, "file not found")
    data = np.fromfile(str(path), dtype=np.uint8)
    img = cv2.imdecode(data, flags) if data.size else None
    if img is None:
        raise CSAInputError(path, "cannot decode image (corrupt or not an image)")
    return img


def read_color(path: Path) -> np.ndarray:
    """8-bit RGB image (H, W, 3)."""
    img = _imread(path, cv2.IMREAD_UNCHANGED)
    if img.dtype != np.uint8:
        raise CSAInputError(path, f"colour must be 8-bit, got {img.dtype}")
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    else:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    return img


DEPTH_INVALID_MM = 65535
"""The uint16 maximum, which sensors write where they measured nothing (7-Scenes' Kinect
frames): read as 0, never as a surface 65.5 m away."""


def read_depth_mm(path: Path) -> np.ndarray:
    """Depth in millimetres as a uint16 (H, W) array, 0 = no measurement (stored as 0 or
    :data:`DEPTH_INVALID_MM`)."""
    img = _imread(path, cv2.IMREAD_UNCHANGED)
    if img.dtype != np.uint16 or img.ndim != 2:
        raise CSAInputError(
            path,
            f"depth must be a single-channel uint16 PNG in millimetres, got {img.dtype} with shape "
            f"{img.shape}",
        )
    img[img == DEPTH_INVALID_MM] = 0
    return img


def read_label_image(path: Path, max_id: int | None = 40) -> np.ndarray:
    """A single-channel label image (uint8 or uint16); ids above ``max_id`` are an error."""
    img = _imread(path, cv2.IMREAD_UNCHANGED)
    if img.ndim != 2 or img.dtype not in (np.uint8, np.uint16):
        raise CSAInputError(
            path,
            f"labels must be a single-channel uint8/uint16 PNG, got {img.dtype} with shape "
            f"{img.shape}",
        )
    if max_id is not None:
        top = int(img.max()) if img.size else 0
        if top > max_id:
            raise CSAInputError(path, f"label id {top} is out of range (NYU40 ids are 0..{max_id})")
        img = img.astype(np.uint8)
    return img


def read_matrix(path: Path, shapes: tuple[tuple[int, int], ...]) -> np.ndarray:
    """A whitespace-separated matrix text file of one of the allowed shapes."""
    if not path.is_file():
        raise CSAInputError(path, "file not found")
    if not path.read_text(errors="replace").strip():
        raise CSAInputError(path, "file is empty")
    try:
        m = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as e:
        raise CSAInputError(path, f"not a numeric matrix ({e})") from None
    if m.shape not in shapes:
        want = " or ".join(f"{a}x{b}" for a, b in shapes)
        raise CSAInputError(path, f"expected a {want} matrix, got {m.shape[0]}x{m.shape[1]}")
    return m


def _encode(path: Path, img: np.ndarray, params: list[int] | None = None) -> None:
    ext = path.suffix.lower()
    ok, buf = cv2.imencode(ext, img, params or [])
    if not ok:
        raise CSAInputError(path, "image encoding failed")
    with atomic_file(path) as tmp:
        buf.tofile(str(tmp))


def write_color(path: Path, rgb: np.ndarray, jpeg_quality: int = 95) -> None:
    params = (
        [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality]
        if path.suffix.lower() in (".jpg", ".jpeg")
        else None
    )
    _encode(path, cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR), params)


def depth_to_mm(depth_m: np.ndarray) -> np.ndarray:
    """Metres (0 = missing) to uint16 millimetres; values beyond 65.535 m become missing."""
    mm = np.round(np.nan_to_num(depth_m, nan=0.0, posinf=0.0, neginf=0.0) * 1000.0)
    mm[(mm < 0) | (mm > 65535)] = 0
    return mm.astype(np.uint16)


def write_depth(path: Path, depth_m: np.ndarray) -> None:
    _encode(path, depth_to_mm(depth_m))


def write_labels(path: Path, labels: np.ndarray) -> None:
    _encode(path, np.ascontiguousarray(labels.astype(np.uint8)))


def write_matrix(path: Path, m: np.ndarray) -> None:
    with atomic_file(path) as tmp:
        np.savetxt(tmp, m, fmt="%.17g")
