"""Bringing images of a registered camera to the working resolution and camera."""

from __future__ import annotations

import cv2
import numpy as np

from csa_core.data.camera import Intrinsics


def resample_nearest(img: np.ndarray, src: Intrinsics, dst: Intrinsics) -> np.ndarray:
    """Nearest-neighbour resampling of a depth or label image from camera ``src`` into ``dst``.

    Both cameras share centre and orientation (registered images), so the pixel map is
    affine. Nearest-neighbour never blends depths or class ids across edges; pixels that
    fall outside the source image become 0 (missing / unknown).
    """
    ax, ay = src.fx / dst.fx, src.fy / dst.fy
    M = np.array([[ax, 0.0, src.cx - ax * dst.cx], [0.0, ay, src.cy - ay * dst.cy]])
    if np.allclose(M, [[1, 0, 0], [0, 1, 0]]) and img.shape[:2] == (dst.height, dst.width):
        return img
    return cv2.warpAffine(
        img,
        M,
        (dst.width, dst.height),
        flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )


def resize_color(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """Area-average when shrinking, bilinear otherwise."""
    if img.shape[1] == width and img.shape[0] == height:
        return img
    shrink = width < img.shape[1] and height < img.shape[0]
    return cv2.resize(
        img, (width, height), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
    )
