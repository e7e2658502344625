"""Fixtures for the segmentation tests: small scenes whose labels follow from the colours."""

from __future__ import annotations

import numpy as np
import pytest

from csa_core.data.camera import Intrinsics
from csa_core.data.scene import Frame, Scene
from tests.tiny_scenes import look_at_pose

# NYU40 id -> the flat colour of that class in pattern scenes (wall is the background).
PATTERN_COLORS: dict[int, tuple[int, int, int]] = {
    1: (200, 200, 200),  # wall
    2: (40, 60, 200),  # floor
    5: (220, 40, 40),  # chair
    7: (40, 190, 60),  # table
    4: (230, 210, 40),  # bed
}


def make_pattern_scene(
    n: int = 12,
    size: tuple[int, int] = (64, 48),
    seed: int = 0,
    name: str = "pattern",
    unknown_fraction: float = 0.05,
    noise: float = 6.0,
) -> Scene:
    """Frames of axis-aligned blocks on a wall background, labelled by the block's colour.

    Each frame has a floor band at the bottom and two blocks of other classes; a few small
    patches are labelled 0 (unknown) without changing the image.
    """
    rng = np.random.default_rng(seed)
    w, h = size
    intr = Intrinsics(fx=w * 0.9, fy=w * 0.9, cx=w / 2 - 0.5, cy=h / 2 - 0.5, width=w, height=h)
    frames = []
    for i in range(n):
        lab = np.full((h, w), 1, np.uint8)
        lab[int(h * rng.uniform(0.65, 0.8)) :, :] = 2
        for cls in rng.choice([4, 5, 7], size=2, replace=False):
            bw, bh = int(rng.integers(w // 5, w // 2)), int(rng.integers(h // 5, h // 2))
            x0, y0 = int(rng.integers(0, w - bw)), int(rng.integers(0, h - bh))
            lab[y0 : y0 + bh, x0 : x0 + bw] = cls
        palette = np.zeros((41, 3), np.float32)
        for cls, rgb in PATTERN_COLORS.items():
            palette[cls] = rgb
        color = palette[lab] + rng.normal(0.0, noise, size=(h, w, 3))
        color = np.clip(color, 0, 255).astype(np.uint8)
        unknown = rng.random((h // 4, w // 4)) < unknown_fraction
        lab[np.kron(unknown, np.ones((4, 4), bool))[:h, :w]] = 0
        pose = look_at_pose([np.cos(i / 3), np.sin(i / 3), 1.5], [0, 0, 0.5])
        depth = np.full((h, w), 2.0, np.float32)
        frames.append(
            Frame(name=str(i), color=color, pose=pose, depth=depth, labels={"label-nyu40": lab})
        )
    return Scene(name=name, intrinsics=intr, frames=frames)


@pytest.fixture
def pattern_scene() -> Scene:
    return make_pattern_scene()
