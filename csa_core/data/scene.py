"""Typed scenes and frames: the in-memory form of the scene folder
(docs/data-contract.md, "The scene folder")."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from csa_core.data.camera import Intrinsics
from csa_core.errors import CSAInputError

# docs/method.md "Protocols and metrics": the first 80% of the kept frames are training views, the
# rest validation.
TRAIN_FRACTION = 0.8

NYU40_FOLDER = "label-nyu40"
RAW_SCANNET_FOLDER = "label-filt"

TYPICAL_DEPTH_RANGE_M = (0.1, 100.0)
"""Where the typical measured depth of an indoor scene lies, in metres (the median over frames
of each frame's median measured depth). Depth in another unit falls far outside: metres stored
as integer millimetres give a few millimetres, millimetres taken for metres give thousands."""


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
    """Number of training frames among ``n`` kept frames (first 80%, at least one each side
    when n >= 2)."""
    if n <= 1:
        return n
    return min(max(int(round(TRAIN_FRACTION * n)), 1), n - 1)


def check_depth(frames: Sequence[Frame], where: str | Path) -> None:
    """Refuse depth that fits and maps cannot use, naming ``where`` and the frame: a depth map
    of another shape than the frame's colour, values that are not finite or negative (0 marks
    a pixel without measurement), or a typical measured depth outside
    :data:`TYPICAL_DEPTH_RANGE_M` (depth in another unit). The one check of depth values for
    the scene reader and the NeRF fit."""
    medians = []
    for f in frames:
        if f.depth is None:
            continue
        d = np.asarray(f.depth)
        if d.shape != f.color.shape[:2]:
            got = "x".join(map(str, d.shape[::-1]))
            raise CSAInputError(
                where,
                f"frame {f.name}: depth is {got}, colour is {f.color.shape[1]}x{f.color.shape[0]}",
            )
        if not np.all(np.isfinite(d)):
            raise CSAInputError(
                where,
                f"frame {f.name}: depth holds NaN or infinite values "
                "(use 0 where nothing was measured)",
            )
        if (d < 0).any():
            raise CSAInputError(
                where,
                f"frame {f.name}: depth holds negative values (use 0 where nothing was measured)",
            )
        measured = d[d > 0]
        if measured.size:
            medians.append(float(np.median(measured)))
    if medians:
        typical = float(np.median(medians))
        lo, hi = TYPICAL_DEPTH_RANGE_M
        if not lo <= typical <= hi:
            raise CSAInputError(
                where,
                f"typical measured depth is {typical:.3g} m, outside {lo:g}..{hi:g} m: "
                "depth in another unit? "
                "(depth PNGs hold millimetres, 1 m = 1000; depth in memory is in metres)",
            )
