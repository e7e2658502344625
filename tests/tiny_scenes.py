"""Tiny scenes built in memory for tests."""

from __future__ import annotations

import numpy as np

from csa_core.data.camera import Intrinsics
from csa_core.data.scene import Frame, Scene


def look_at_pose(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes) at ``eye`` looking at ``target``, z-up world."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, y, z], axis=1)
    pose[:3, 3] = eye
    return pose


def make_random_scene(n: int = 5, size=(32, 24), seed: int = 0, labels=("label-nyu40",)) -> Scene:
    """A scene of random content with exact-millimetre depth (holes included) and label maps."""
    rng = np.random.default_rng(seed)
    w, h = size
    intr = Intrinsics(fx=30.0, fy=31.0, cx=w / 2 - 0.5, cy=h / 2 - 0.5, width=w, height=h)
    frames = []
    for i in range(n):
        depth = rng.integers(300, 5000, size=(h, w)).astype(np.float32) / 1000.0
        depth[rng.random((h, w)) < 0.1] = 0.0
        pose = look_at_pose([np.cos(i), np.sin(i), 1.5], [0, 0, 0.5])
        frames.append(
            Frame(
                name=str(i * 10),
                color=rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8),
                pose=pose,
                depth=depth,
                labels={k: rng.integers(0, 41, size=(h, w)).astype(np.uint8) for k in labels},
            )
        )
    return Scene(name="random", intrinsics=intr, frames=frames)
