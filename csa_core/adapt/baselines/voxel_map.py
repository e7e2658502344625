"""A sparse voxel map of per-voxel class scores: the 3D fusion behind the Mapping baseline.

Each frame's labels (or class probabilities) are lifted to 3D with its depth and pose and
added to the scores of the voxel each surface point falls in. Reading the map back for a view
looks up, for every pixel with depth, the voxel of its back-projected surface point and takes
the class with the highest score. Everything is vectorised over pixels: voxels are integer
cells packed into one int64 key, kept sorted so lookups are binary searches.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from csa_core.data.camera import Intrinsics, backproject
from csa_core.data.nyu40 import NUM_CLASSES, UNKNOWN

# Frey et al. (RA-L 2022) fuse predictions at 5 cm (DESIGN.md, "Baselines").
PAPER_VOXEL_SIZE = 0.05

_BITS = 21  # per axis: +-2^20 cells, +-52 km at 5 cm
_OFFSET = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1


@dataclass(frozen=True)
class VoxelMapConfig:
    """Voxel edge in metres; ``search_radius``: when a pixel's own voxel holds no score (a
    view that was not fused, or a surface only ever labelled unknown), sum the scores of the
    voxels up to this many cells away (0: no search, the pixel stays unknown)."""

    voxel_size: float = PAPER_VOXEL_SIZE
    search_radius: int = 0
    num_classes: int = NUM_CLASSES

    def __post_init__(self) -> None:
        if not self.voxel_size > 0:
            raise ValueError(f"VoxelMapConfig: voxel_size must be > 0, got {self.voxel_size}")
        if self.search_radius < 0 or self.num_classes < 1:
            raise ValueError("VoxelMapConfig: search_radius must be >= 0 and num_classes >= 1")


def voxel_coords(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Integer cell (N, 3) of each world point (N, 3): floor(p / voxel_size)."""
    return np.floor(np.asarray(points, dtype=np.float64) / voxel_size).astype(np.int64)


def pack_keys(cells: np.ndarray) -> np.ndarray:
    """One int64 key per integer cell (N, 3); raises when a cell is out of the packable range."""
    shifted = cells + _OFFSET
    if shifted.size and (shifted.min() < 0 or shifted.max() > _MASK):
        raise ValueError(
            "voxel map: a point lies farther than 2^20 voxels from the origin; check units"
        )
    return (shifted[:, 0] << (2 * _BITS)) | (shifted[:, 1] << _BITS) | shifted[:, 2]


def unpack_keys(keys: np.ndarray) -> np.ndarray:
    """Integer cells (N, 3) of packed keys."""
    keys = np.asarray(keys, dtype=np.int64)
    cells = np.stack([keys >> (2 * _BITS), (keys >> _BITS) & _MASK, keys & _MASK], axis=1)
    return cells - _OFFSET


class VoxelSemanticMap:
    """Sparse voxels with summed class scores: ``keys`` (N,) sorted int64, ``scores`` (N, C).

    Column ``k`` of ``scores`` belongs to NYU40 id ``k + 1``. Label maps add one vote per
    pixel; probability maps add the pixel's probabilities.
    """

    def __init__(self, config: VoxelMapConfig | None = None):
        self.config = config or VoxelMapConfig()
        self.keys = np.zeros(0, dtype=np.int64)
        self.scores = np.zeros((0, self.config.num_classes), dtype=np.float32)
        self.frames_integrated = 0

    @property
    def voxel_size(self) -> float:
        return self.config.voxel_size

    @property
    def num_voxels(self) -> int:
        return int(self.keys.size)

    @property
    def nbytes(self) -> int:
        """Bytes held by the map (keys and scores)."""
        return int(self.keys.nbytes + self.scores.nbytes)

    def _surface_keys(
        self, depth: np.ndarray, pose: np.ndarray, intrinsics: Intrinsics
    ) -> tuple[np.ndarray, np.ndarray]:
        """Keys of the voxels hit by the pixels with depth, and the (H, W) mask of those pixels."""
        depth = np.asarray(depth, dtype=np.float32)
        if depth.shape != (intrinsics.height, intrinsics.width):
            raise ValueError(
                f"voxel map: depth {depth.shape} does not match the camera "
                f"({intrinsics.height}, {intrinsics.width})"
            )
        valid = np.isfinite(depth) & (depth > 0)
        points = backproject(np.where(valid, depth, 0.0), intrinsics, np.asarray(pose, np.float64))
        return pack_keys(voxel_coords(points[valid], self.voxel_size)), valid

    def integrate(
        self,
        prediction: np.ndarray,
        depth: np.ndarray,
        pose: np.ndarray,
        intrinsics: Intrinsics,
    ) -> int:
        """Add one frame: ``prediction`` is an (H, W) NYU40 label map (0 = no vote) or an
        (H, W, C) probability map. Returns the number of points added."""
        prediction = np.asarray(prediction)
        keys, valid = self._surface_keys(depth, pose, intrinsics)
        c = self.config.num_classes
        if prediction.ndim == 2:
            if prediction.shape != valid.shape:
                raise ValueError(f"integrate: labels {prediction.shape} vs depth {valid.shape}")
            labels = prediction[valid].astype(np.int64)
            if labels.size and labels.max() > c:
                raise ValueError(f"integrate: label id {labels.max()} exceeds {c} classes")
            voted = labels > UNKNOWN
            keys, labels = keys[voted], labels[voted] - 1
            frame_keys, inverse = np.unique(keys, return_inverse=True)
            frame_scores = np.bincount(inverse * c + labels, minlength=frame_keys.size * c).reshape(
                frame_keys.size, c
            )
        elif prediction.ndim == 3:
            if prediction.shape != (*valid.shape, c):
                raise ValueError(
                    f"integrate: probabilities {prediction.shape}, expected {(*valid.shape, c)}"
                )
            probs = prediction[valid].astype(np.float32)
            frame_keys, inverse = np.unique(keys, return_inverse=True)
            order = np.argsort(inverse, kind="stable")
            starts = np.flatnonzero(np.r_[True, np.diff(inverse[order]) != 0])
            frame_scores = (
                np.add.reduceat(probs[order], starts, axis=0)
                if probs.size
                else np.zeros((0, c), np.float32)
            )
        else:
            raise ValueError(
                f"integrate: expected (H, W) labels or (H, W, C) probabilities, got {prediction.shape}"
            )
        self._add(frame_keys, frame_scores.astype(np.float32))
        self.frames_integrated += 1
        return int(keys.size)

    def _add(self, keys: np.ndarray, scores: np.ndarray) -> None:
        if keys.size == 0:
            return
        merged, inverse = np.unique(np.concatenate([self.keys, keys]), return_inverse=True)
        out = np.zeros((merged.size, self.config.num_classes), dtype=np.float32)
        n_old = self.keys.size
        out[inverse[:n_old]] = self.scores
        out[inverse[n_old:]] += scores
        self.keys, self.scores = merged, out

    def lookup(self, keys: np.ndarray) -> np.ndarray:
        """Row of each key in ``scores``, or -1 where the voxel is empty."""
        if self.keys.size == 0:
            return np.full(keys.shape, -1, dtype=np.int64)
        rows = np.searchsorted(self.keys, keys)
        rows = np.minimum(rows, self.keys.size - 1)
        return np.where(self.keys[rows] == keys, rows, -1)

    def labels_for_view(
        self, depth: np.ndarray, pose: np.ndarray, intrinsics: Intrinsics
    ) -> np.ndarray:
        """(H, W) uint8 NYU40 labels of a view: the arg-max class of the voxel at each pixel's
        surface point; 0 where the pixel has no depth or no (searched) voxel has a score."""
        keys, valid = self._surface_keys(depth, pose, intrinsics)
        scores = self._scores_at(keys)
        labels = np.where(scores.max(axis=1) > 0, scores.argmax(axis=1) + 1, UNKNOWN)
        out = np.zeros(valid.shape, dtype=np.uint8)
        out[valid] = labels.astype(np.uint8)
        return out

    def _scores_at(self, keys: np.ndarray) -> np.ndarray:
        rows = self.lookup(keys)
        c = self.config.num_classes
        scores = np.zeros((keys.size, c), dtype=np.float32)
        hit = rows >= 0
        scores[hit] = self.scores[rows[hit]]
        r = self.config.search_radius
        missing = np.flatnonzero(~hit)
        if r == 0 or missing.size == 0:
            return scores
        cells = unpack_keys(keys[missing])
        offsets = np.stack(
            np.meshgrid(*[np.arange(-r, r + 1)] * 3, indexing="ij"), axis=-1
        ).reshape(-1, 3)
        neighbours = pack_keys((cells[:, None, :] + offsets[None]).reshape(-1, 3))
        rows = self.lookup(neighbours).reshape(missing.size, offsets.shape[0])
        gathered = np.where((rows >= 0)[..., None], self.scores[np.maximum(rows, 0)], 0.0).sum(
            axis=1
        )
        scores[missing] = gathered
        return scores

    def voxel_labels(self) -> np.ndarray:
        """(N,) arg-max NYU40 id of every voxel (0 where all scores are zero)."""
        if self.num_voxels == 0:
            return np.zeros(0, dtype=np.uint8)
        return np.where(
            self.scores.max(axis=1) > 0, self.scores.argmax(axis=1) + 1, UNKNOWN
        ).astype(np.uint8)

    def voxel_centers(self) -> np.ndarray:
        """(N, 3) world coordinates of the voxel centres, in ``keys`` order."""
        return (unpack_keys(self.keys) + 0.5) * self.voxel_size
