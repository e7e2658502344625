"""Depth discontinuities: where a depth sensor's readings are least reliable.

A pixel beside a jump in depth is missing on a structured-light sensor (the Kinect-like
capture of :mod:`csa_core.data.synth.kinect` makes holes there) and reads a depth between the
two surfaces on a time-of-flight one (flying pixels, ``mix_depth_edges`` there; the fusion
benchmark's ``flying`` variant, benchmarks/results/fusion.md "Flying pixels at depth edges").
"""

from __future__ import annotations

import cv2
import numpy as np


def discontinuity_band(
    depth: np.ndarray, valid: np.ndarray, rel_jump: float, width_px: float
) -> np.ndarray:
    """Pixels on either side of a depth jump larger than ``rel_jump`` times the nearer depth,
    widened to about ``width_px`` pixels per side."""
    jump = np.zeros_like(valid)
    for axis in (0, 1):
        a = np.swapaxes(depth, 0, axis)
        m = np.swapaxes(valid, 0, axis)
        both = m[1:] & m[:-1]
        big = both & (np.abs(a[1:] - a[:-1]) > rel_jump * np.minimum(a[1:], a[:-1]))
        j = np.swapaxes(jump, 0, axis)  # a view: writes land in ``jump``
        j[1:] |= big
        j[:-1] |= big
    radius = max(0, int(round(width_px)) - 1)
    if radius:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
        jump = cv2.dilate(jump.astype(np.uint8), kernel) > 0
    return jump & valid
