"""Pictures of NYU40 label maps: colour coding, overlays, legends and preview files.

All images here are RGB uint8 (H, W, 3); OpenCV's BGR order appears only at the moment a
file is encoded.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np

from csa_core.atomic_io import write_bytes_atomic
from csa_core.data.nyu40 import CLASS_NAMES, NUM_CLASSES, PALETTE, check_label_map

_FONT = cv2.FONT_HERSHEY_SIMPLEX
_FONT_SCALE = 0.4
_ROW_HEIGHT = 18  # legend row: swatch plus one line of text
_SWATCH = 12
_PAD = 4
_WHITE = (255, 255, 255)


def _check_color(color: np.ndarray, labels: np.ndarray) -> np.ndarray:
    color = np.asarray(color)
    if color.dtype != np.uint8 or color.ndim != 3 or color.shape[2] != 3:
        raise ValueError(
            f"color: expected an (H, W, 3) uint8 RGB image, got {color.dtype} {color.shape}"
        )
    if color.shape[:2] != labels.shape:
        raise ValueError(
            f"color is {color.shape[1]}x{color.shape[0]} but labels are "
            f"{labels.shape[1]}x{labels.shape[0]} (width x height)"
        )
    return color


def colorize(labels: np.ndarray) -> np.ndarray:
    """Colour-code a label map with the NYU40 palette: (H, W) ids -> (H, W, 3) RGB."""
    labels = check_label_map(labels)
    return PALETTE[labels]


def overlay(color_rgb: np.ndarray, labels: np.ndarray, alpha: float = 0.5) -> np.ndarray:
    """Blend class colours into an RGB image; pixels labelled unknown (0) keep the image.

    ``alpha`` is the weight of the class colour: 0 gives the image back, 1 the plain colours.
    """
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"overlay: alpha must be in [0, 1], got {alpha}")
    labels = check_label_map(labels)
    color_rgb = _check_color(color_rgb, labels)
    out = color_rgb.copy()
    known = labels > 0
    blend = (1.0 - alpha) * color_rgb[known] + alpha * PALETTE[labels[known]]
    out[known] = np.clip(np.rint(blend), 0, 255).astype(np.uint8)
    return out


def _text_width(text: str) -> int:
    (width, _), _ = cv2.getTextSize(text, _FONT, _FONT_SCALE, 1)
    return width


def legend_image(class_ids: Iterable[int], max_height: int | None = None) -> np.ndarray:
    """A white RGB image listing each class as a colour swatch followed by "id name".

    Entries go top to bottom in the order given; with ``max_height`` they wrap into further
    columns so the legend is no taller than that (but always at least one row).
    """
    ids = [int(c) for c in class_ids]
    for c in ids:
        if not 0 <= c <= NUM_CLASSES:
            raise ValueError(f"legend_image: id {c} is outside NYU40 0..{NUM_CLASSES}")
    entries: list[tuple[int | None, str]] = [(c, f"{c} {CLASS_NAMES[c]}") for c in ids]
    if not entries:
        entries = [(None, "(no classes)")]
    rows = len(entries)
    if max_height is not None:
        rows = min(rows, max(1, max_height // _ROW_HEIGHT))
    columns = [entries[i : i + rows] for i in range(0, len(entries), rows)]
    widths = [_PAD + max(_SWATCH + _PAD + _text_width(t) for _, t in col) + _PAD for col in columns]
    image = np.full((rows * _ROW_HEIGHT, sum(widths), 3), 255, dtype=np.uint8)
    x0 = 0
    for col, width in zip(columns, widths, strict=True):
        for row, (cid, text) in enumerate(col):
            top = row * _ROW_HEIGHT + (_ROW_HEIGHT - _SWATCH) // 2
            corner, far = (x0 + _PAD, top), (x0 + _PAD + _SWATCH - 1, top + _SWATCH - 1)
            if cid is not None:
                swatch = tuple(int(v) for v in PALETTE[cid])
                cv2.rectangle(image, corner, far, swatch, thickness=-1)
                cv2.rectangle(image, corner, far, (128, 128, 128), thickness=1)
            origin = (x0 + 2 * _PAD + _SWATCH, (row + 1) * _ROW_HEIGHT - 5)
            cv2.putText(image, text, origin, _FONT, _FONT_SCALE, (0, 0, 0), 1, cv2.LINE_AA)
        x0 += width
    return image


def _pad_to_height(image: np.ndarray, height: int) -> np.ndarray:
    missing = height - image.shape[0]
    if missing <= 0:
        return image
    return cv2.copyMakeBorder(image, 0, missing, 0, 0, cv2.BORDER_CONSTANT, value=_WHITE)


def preview_image(
    color: np.ndarray, labels: np.ndarray, alpha: float = 0.5, legend: bool = True
) -> np.ndarray:
    """Side-by-side RGB picture: image | colour-coded labels | overlay (| legend).

    The legend lists the ids present in ``labels``, unknown included when it occurs.
    """
    labels = check_label_map(labels)
    color = _check_color(color, labels)
    panels = [color, colorize(labels), overlay(color, labels, alpha)]
    if legend:
        panels.append(legend_image(np.unique(labels), max_height=labels.shape[0]))
    height = max(p.shape[0] for p in panels)
    return np.concatenate([_pad_to_height(p, height) for p in panels], axis=1)


def save_preview(
    path: str | Path,
    color: np.ndarray,
    labels: np.ndarray,
    alpha: float = 0.5,
    legend: bool = True,
) -> Path:
    """Write :func:`preview_image` to ``path`` atomically (format from the suffix, e.g. .png)."""
    path = Path(path)
    image = preview_image(color, labels, alpha=alpha, legend=legend)
    try:
        ok, encoded = cv2.imencode(path.suffix or ".png", image[:, :, ::-1])
    except cv2.error:
        ok = False
    if not ok:
        raise ValueError(f"{path}: cannot encode an image with suffix {path.suffix!r}")
    write_bytes_atomic(path, encoded.tobytes())
    return path
