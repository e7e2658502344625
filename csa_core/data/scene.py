"""Typed scenes and frames: the in-memory form of the scene folder (docs/data-contract.md, "The scene folder")."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from csa_core.data.camera import Intrinsics
from csa_core.errors import CSAInputError

# docs/method.md "Protocols and metrics": the first 80% of the kept frames are training views, the rest validation.
TRAIN_FRACTION = 0.8

NYU40_FOLDER = "label-nyu40"
RAW_SCANNET_FOLDER = "label-filt"


@dataclass
class Frame:
    """One posed RGB-D frame at the scene's working resolution.

    ``color``: (H, W, 3) uint8 RGB. ``depth``: (H, W) float32 z-depth in metres, 0 where the
    sensor measured nothing (or ``None`` when the scene has no depth). ``pose``: 4x4
    camera-to-world, metres, OpenCV axes. ``labels``: label folder name -> (H, W) uint8
    NYU40 ids, 0 = unknown.
    """

    name: str
    color: np.ndarray
    pose: np.ndarray
    depth: np.ndarray | None = None
    labels: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def index(self) -> int:
        return int(self.name) if self.name.isdigit() else -1

    @property
    def depth_mask(self) -> np.ndarray:
        """Pixels with a depth measurement."""
        if self.depth is None:
            return np.zeros(self.color.shape[:2], dtype=bool)
        return self.depth > 0


@dataclass(frozen=True)
class SkippedFrame:
    name: str
    reason: str


@dataclass
class Scene:
    """A scene: frames sorted by frame index, all at one working resolution with one camera."""

    name: str
    intrinsics: Intrinsics
    frames: list[Frame]
    skipped: list[SkippedFrame] = field(default_factory=list)
    root: Path | None = None

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of every image in the scene."""
        return self.intrinsics.width, self.intrinsics.height

    @property
    def label_folders(self) -> list[str]:
        names: set[str] = set()
        for f in self.frames:
            names.update(f.labels)
        return sorted(names)

    @property
    def num_train(self) -> int:
        return split_point(len(self.frames))

    @property
    def train_frames(self) -> list[Frame]:
        return self.frames[: self.num_train]

    @property
    def val_frames(self) -> list[Frame]:
        return self.frames[self.num_train :]

    def split(self, name: str) -> list[Frame]:
        """Frames of the split ``train``, ``val`` or ``all``."""
        if name == "train":
            return self.train_frames
        if name == "val":
            return self.val_frames
        if name == "all":
            return list(self.frames)
        raise ValueError(f"split: unknown split {name!r} (expected train, val or all)")


def require_depth(scene: Scene, needs: str) -> str:
    """Where to name ``scene`` in errors (its folder, else its name), after refusing a scene
    without frames or with a frame without depth: ``needs`` says what needs it ("space
    labels need depth")."""
    where = str(scene.root) if scene.root else f"scene {scene.name}"
    if not scene.frames:
        raise CSAInputError(where, "scene has no frames")
    missing = [f.name for f in scene.frames if f.depth is None]
    if missing:
        raise CSAInputError(where, f"{needs}; frame(s) {', '.join(missing[:5])} have none")
    return where


def split_point(n: int) -> int:
    """Number of training frames among ``n`` kept frames (first 80%, at least one each side when n >= 2)."""
    if n <= 1:
        return n
    return min(max(int(round(TRAIN_FRACTION * n)), 1), n - 1)
