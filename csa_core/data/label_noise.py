"""View-inconsistent label corruption: the kind of errors a per-frame segmentation network makes.

Used to test that fusing labels in 3D removes errors that differ from frame to frame, and
by the adaptation code to simulate imperfect predictions. Each call corrupts one frame
independently: blobs of wrong classes, parts of objects swapped to another class, and
ragged class boundaries. Unknown pixels (0) stay unknown.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from csa_core.data.nyu40 import NUM_CLASSES


@dataclass
class LabelNoiseConfig:
    """How strongly to corrupt a label map (sizes relative to the shorter image side)."""

    blobs: int = 3  # wrong-class ellipses per frame
    blob_radius: tuple[float, float] = (0.08, 0.2)
    swap_probability: float = 0.3  # chance that each object class gets part of it swapped
    swap_fraction: tuple[float, float] = (0.3, 0.7)  # part of the object that is swapped
    edge_width: float = 0.04  # ragged boundaries: maximum displacement of a boundary
    present_class_bias: float = 0.7  # wrong classes come from the frame's own classes this often


def _wrong_class(rng: np.random.Generator, present: np.ndarray, avoid: int, bias: float) -> int:
    choices = present[present != avoid]
    if choices.size and rng.random() < bias:
        return int(rng.choice(choices))
    c = int(rng.integers(1, NUM_CLASSES + 1))
    return c if c != avoid else (c % NUM_CLASSES) + 1


def corrupt_labels(
    labels: np.ndarray, rng: np.random.Generator, cfg: LabelNoiseConfig | None = None
) -> np.ndarray:
    """A corrupted copy of an (H, W) uint8 NYU40 label map; ``rng`` makes it reproducible."""
    cfg = cfg or LabelNoiseConfig()
    labels = np.asarray(labels)
    if labels.ndim != 2:
        raise ValueError(f"corrupt_labels: expected an (H, W) label map, got shape {labels.shape}")
    h, w = labels.shape
    side = min(h, w)
    known = labels > 0
    out = labels.astype(np.uint8).copy()
    present = np.unique(labels[known])
    if present.size == 0:
        return out

    # Ragged edges: near class boundaries, take the label from a smoothly displaced position.
    if cfg.edge_width > 0:
        amp = cfg.edge_width * side
        coarse = (max(2, h // 8), max(2, w // 8))
        dx = cv2.resize(
            rng.uniform(-amp, amp, coarse).astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC
        )
        dy = cv2.resize(
            rng.uniform(-amp, amp, coarse).astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC
        )
        yy, xx = np.mgrid[0:h, 0:w]
        sx = np.clip(np.rint(xx + dx), 0, w - 1).astype(np.int64)
        sy = np.clip(np.rint(yy + dy), 0, h - 1).astype(np.int64)
        moved = labels[sy, sx]
        out = np.where(known & (moved > 0), moved, out).astype(np.uint8)

    # Partly swapped objects: a half-plane through the object's centre, at a random angle.
    for c in present:
        if rng.random() >= cfg.swap_probability:
            continue
        ys, xs = np.nonzero(labels == c)
        cy, cx = ys.mean(), xs.mean()
        angle = rng.uniform(0, 2 * np.pi)
        proj = (xs - cx) * np.cos(angle) + (ys - cy) * np.sin(angle)
        cut = np.quantile(proj, 1.0 - rng.uniform(*cfg.swap_fraction))
        sel = proj >= cut
        out[ys[sel], xs[sel]] = _wrong_class(rng, present, int(c), cfg.present_class_bias)

    # Blobs of wrong classes.
    for _ in range(cfg.blobs):
        mask = np.zeros((h, w), np.uint8)
        centre = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        axes = tuple(max(1, int(rng.uniform(*cfg.blob_radius) * side)) for _ in range(2))
        cv2.ellipse(mask, centre, axes, float(rng.uniform(0, 180)), 0, 360, 1, -1)
        region = (mask > 0) & known
        if region.any():
            under = np.bincount(labels[region], minlength=NUM_CLASSES + 1).argmax()
            out[region] = _wrong_class(rng, present, int(under), cfg.present_class_bias)

    out[~known] = 0
    return out
