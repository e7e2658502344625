"""A sparse voxel map for the Mapping baseline: a truncated signed distance field (TSDF) for
the geometry and per-voxel class scores for the semantics (docs/method.md, "Baselines").

Each frame is fused into one grid of cells, as the voxblox-style semantic map of Frey et al.
(RA-L 2022) does:

- **geometry**: a projective TSDF. Every voxel near a measured surface point along the
  pixel's ray (within ``truncation`` voxels), and the face neighbours of those, takes the
  distance, along the ray through its centre, from the centre to the surface the frame
  measured there (depth interpolated between neighbouring pixels of one surface), clipped
  at the truncation. Frames are averaged with one unit of weight per observation, less for
  observations behind the surface (voxblox's drop-off); voxels farther than the truncation
  behind the surface are left alone (the frame cannot see them).
- **semantics**: each pixel's label (or class probabilities) is added to the scores of the
  voxel its surface point falls in.

Reading the map for a view casts every pixel's ray through the TSDF: the ray stops where the
trilinearly interpolated distance first turns from positive to non-positive (the surface,
located by linear interpolation between samples half a voxel apart), and the class votes of
the eight voxels around that point, weighted trilinearly like the distances, give its label
(or, where none of them has votes, those within ``search_radius`` cells). A pixel is unknown
only where its ray meets no surface. The view's own depth is not used, so a pixel the sensor
missed still gets the label the map knows.

Everything is vectorised over pixels: voxels are integer cells packed into one int64 key,
kept sorted; a ray march skips empty space by an exact voxel traversal to the first cell next
to one with a non-positive distance (a stopping cell), on a dense grid over the map's bounding
box.

There are two implementations of this one algorithm. ``backend="torch"`` (the default) makes
every step a tensor operation over a view's pixels, voxels or rays, on the map's ``device`` (the
CPU unless told otherwise, with the threads torch uses, or a GPU). ``backend="numpy"`` (one CPU
core) is the reference it is tested against (tests/adapt/baselines/test_voxel_map_backends.py).
Both build the same map. The torch ray cast samples the same windows, with float32 positions
(the reference's are float64), and reaches the first stopping cell by skipping as far as a
distance field allows (how many cells away the nearest stopping cell is) instead of walking
coarse cells.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from csa_core.data.camera import Intrinsics, backproject, pixel_rays
from csa_core.data.nyu40 import NUM_CLASSES, UNKNOWN
from csa_core.device import resolve_device

BACKENDS = ("torch", "numpy")  # the implementation, and the reference it is tested against
# Frey et al. (RA-L 2022) fuse predictions at 5 cm (docs/method.md, "Baselines").
PAPER_VOXEL_SIZE = 0.05

_BITS = 21  # per axis: +-2^20 cells, +-52 km at 5 cm
_TOO_FAR = "voxel map: a point lies farther than 2^20 voxels from the origin; check units"
_OFFSET = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1
# Dense lookup grids up to this many cells (float32 distances: 256 MB); larger maps look cells
# up in their sorted keys instead (same result, slower).
MAX_DENSE_CELLS = 1 << 26
# Ray march: the traversal walks coarse cells of _COARSE^3 voxels, _WINDOW_CELLS at a time,
# to skip empty space; near a surface the TSDF is sampled every half voxel, _SURFACE_SAMPLES
# samples at a time, before the traversal resumes.
_WINDOW_CELLS = 4
_COARSE = 4
_SURFACE_SAMPLES = 8
_RAY_CHUNK = 1 << 15  # rays marched together (bounds the march's memory to some 100 MB)
_PIXEL_CHUNK = 1 << 15  # pixels whose truncation bands are gathered together when fusing
# Packed-key differences to a cell's six face neighbours and itself.
_FACE_DELTAS = np.array(
    [0, 1, -1, 1 << _BITS, -(1 << _BITS), 1 << (2 * _BITS), -(1 << (2 * _BITS))]
)


@dataclass(frozen=True)
class VoxelMapConfig:
    """``voxel_size``: voxel edge in metres. ``truncation``: the TSDF's truncation distance,
    in voxels (3: the band of voxels a frame updates reaches 15 cm either side of its surface
    at 5 cm; voxblox's usual 2 to 4 voxels, and the best of 2, 3 and 4 on the synthetic
    rooms). ``search_radius``: a ray whose surface point has no votes in the eight voxels
    around it takes the summed scores of the voxels within this many cells of the one holding
    it (0: it stays unknown); the depth read-back (:meth:`VoxelSemanticMap.labels_at_depth`)
    does the same for a voxel without votes. ``max_range``: how far (metres along the ray) a
    pixel's ray is followed through the map."""

    voxel_size: float = PAPER_VOXEL_SIZE
    truncation: float = 3.0
    search_radius: int = 1
    num_classes: int = NUM_CLASSES
    max_range: float = 10.0

    def __post_init__(self) -> None:
        if not self.voxel_size > 0:
            raise ValueError(f"VoxelMapConfig: voxel_size must be > 0, got {self.voxel_size}")
        if not self.truncation >= 1:
            raise ValueError(
                f"VoxelMapConfig: truncation must be >= 1 voxel, got {self.truncation}"
            )
        if self.search_radius < 0 or self.num_classes < 1:
            raise ValueError("VoxelMapConfig: search_radius must be >= 0 and num_classes >= 1")
        if not self.max_range > 0:
            raise ValueError(f"VoxelMapConfig: max_range must be > 0, got {self.max_range}")


def voxel_coords(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Integer cell (N, 3) of each world point (N, 3): floor(p / voxel_size)."""
    return np.floor(np.asarray(points, dtype=np.float64) / voxel_size).astype(np.int64)


def pack_keys(cells: np.ndarray) -> np.ndarray:
    """One int64 key per integer cell (N, 3); raises when a cell is out of the packable range."""
    shifted = cells + _OFFSET
    if shifted.size and (shifted.min() < 0 or shifted.max() > _MASK):
        raise ValueError(_TOO_FAR)
    return (shifted[:, 0] << (2 * _BITS)) | (shifted[:, 1] << _BITS) | shifted[:, 2]


def unpack_keys(keys: np.ndarray) -> np.ndarray:
    """Integer cells (N, 3) of packed keys."""
    keys = np.asarray(keys, dtype=np.int64)
    cells = np.stack([keys >> (2 * _BITS), (keys >> _BITS) & _MASK, keys & _MASK], axis=1)
    return cells - _OFFSET


def _rows_of(sorted_keys: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Row of each key in ``sorted_keys``, or -1 where it is absent."""
    if sorted_keys.size == 0:
        return np.full(keys.shape, -1, dtype=np.int64)
    rows = np.minimum(np.searchsorted(sorted_keys, keys), sorted_keys.size - 1)
    return np.where(sorted_keys[rows] == keys, rows, -1)


class VoxelSemanticMap:
    """Two sparse layers over one grid of cells.

    Semantics: ``keys`` (N,) sorted int64 and summed class scores ``scores`` (N, C) of the
    voxels surface points fell in; column ``k`` belongs to NYU40 id ``k + 1``. Label maps add
    one vote per pixel; probability maps add the pixel's probabilities.
    Geometry: ``tsdf_keys`` (M,) sorted int64, the truncated signed distance ``tsdf`` (M,)
    in metres (positive in front of the surface) and its summed observation ``weights`` (M,).
    """

    def __init__(
        self,
        config: VoxelMapConfig | None = None,
        device: str | torch.device | None = None,
        backend: str = "torch",
    ):
        self.config = config or VoxelMapConfig()
        if backend not in BACKENDS:
            raise ValueError(
                f"VoxelSemanticMap: backend must be one of {BACKENDS}, got {backend!r}"
            )
        self.backend = backend
        self.device = torch.device("cpu") if device is None else resolve_device(device)
        if backend == "numpy" and self.device.type != "cpu":
            raise ValueError(
                f"VoxelSemanticMap: the numpy reference runs on the CPU, not on {self.device}"
            )
        c = self.config.num_classes
        if backend == "numpy":
            self._keys: np.ndarray | Tensor = np.zeros(0, dtype=np.int64)
            self._scores: np.ndarray | Tensor = np.zeros((0, c), dtype=np.float32)
            self._tsdf_keys: np.ndarray | Tensor = np.zeros(0, dtype=np.int64)
            self._tsdf: np.ndarray | Tensor = np.zeros(0, dtype=np.float32)
            self._weights: np.ndarray | Tensor = np.zeros(0, dtype=np.float32)
        else:
            dev = self.device
            self._keys = torch.zeros(0, dtype=torch.int64, device=dev)
            self._scores = torch.zeros((0, c), dtype=torch.float32, device=dev)
            self._tsdf_keys = torch.zeros(0, dtype=torch.int64, device=dev)
            self._tsdf = torch.zeros(0, dtype=torch.float32, device=dev)
            self._weights = torch.zeros(0, dtype=torch.float32, device=dev)
        self.frames_integrated = 0
        # ray-cast lookup, rebuilt after integrating
        self._surface: _Surface | _TorchSurface | None = None

    # The layers as numpy arrays (the numpy backend's own arrays; the torch backend's tensors
    # shared on the CPU, copied from another device).
    @property
    def keys(self) -> np.ndarray:
        return _as_numpy(self._keys)

    @property
    def scores(self) -> np.ndarray:
        return _as_numpy(self._scores)

    @property
    def tsdf_keys(self) -> np.ndarray:
        return _as_numpy(self._tsdf_keys)

    @property
    def tsdf(self) -> np.ndarray:
        return _as_numpy(self._tsdf)

    @property
    def weights(self) -> np.ndarray:
        return _as_numpy(self._weights)

    @property
    def voxel_size(self) -> float:
        return self.config.voxel_size

    @property
    def truncation_m(self) -> float:
        """The TSDF's truncation distance in metres."""
        return self.config.truncation * self.config.voxel_size

    @property
    def num_voxels(self) -> int:
        """Voxels with class scores (those surface points fell in)."""
        return int(self._keys.shape[0])

    @property
    def num_tsdf_voxels(self) -> int:
        """Voxels with a signed distance (those within the truncation of a surface a frame
        saw, and their face neighbours)."""
        return int(self._tsdf_keys.shape[0])

    @property
    def nbytes(self) -> int:
        """Bytes held by the map: both layers' keys and values."""
        arrays = (self._keys, self._scores, self._tsdf_keys, self._tsdf, self._weights)
        return int(sum(_nbytes(a) for a in arrays))

    def _surface_keys(
        self, depth: np.ndarray, pose: np.ndarray, intrinsics: Intrinsics
    ) -> tuple[np.ndarray, np.ndarray]:
        """Keys of the voxels hit by the pixels with depth, and the (H, W) mask of those pixels."""
        depth = _check_depth(depth, intrinsics)
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
        (H, W, C) probability map. Every pixel with depth updates the TSDF, whatever its
        label. Returns the number of points that added scores."""
        prediction = np.asarray(prediction)
        depth = _check_depth(depth, intrinsics)
        valid = np.isfinite(depth) & (depth > 0)
        c = self.config.num_classes
        if prediction.ndim == 2:
            if prediction.shape != valid.shape:
                raise ValueError(f"integrate: labels {prediction.shape} vs depth {valid.shape}")
            top = int(prediction[valid].max()) if valid.any() else 0
            if top > c:
                raise ValueError(f"integrate: label id {top} exceeds {c} classes")
        elif prediction.ndim == 3:
            if prediction.shape != (*valid.shape, c):
                raise ValueError(
                    f"integrate: probabilities {prediction.shape}, expected {(*valid.shape, c)}"
                )
        else:
            raise ValueError(
                "integrate: expected (H, W) labels or (H, W, C) probabilities, got "
                f"{prediction.shape}"
            )
        if self.backend == "torch":
            points = _integrate_torch(self, prediction, depth, valid, pose, intrinsics)
        else:
            points = self._integrate_numpy(prediction, depth, valid, pose, intrinsics)
        self.frames_integrated += 1
        self._surface = None
        return points

    def _integrate_numpy(
        self,
        prediction: np.ndarray,
        depth: np.ndarray,
        valid: np.ndarray,
        pose: np.ndarray,
        intrinsics: Intrinsics,
    ) -> int:
        """The reference's :meth:`integrate` of a checked frame."""
        keys = self._surface_keys(depth, pose, intrinsics)[0]
        c = self.config.num_classes
        if prediction.ndim == 2:
            labels = prediction[valid].astype(np.int64)
            voted = labels > UNKNOWN
            keys, labels = keys[voted], labels[voted] - 1
            frame_keys, inverse = np.unique(keys, return_inverse=True)
            frame_scores = np.bincount(inverse * c + labels, minlength=frame_keys.size * c).reshape(
                frame_keys.size, c
            )
        else:
            probs = prediction[valid].astype(np.float32)
            frame_keys, inverse = np.unique(keys, return_inverse=True)
            order = np.argsort(inverse, kind="stable")
            starts = np.flatnonzero(np.r_[True, np.diff(inverse[order]) != 0])
            frame_scores = (
                np.add.reduceat(probs[order], starts, axis=0)
                if probs.size
                else np.zeros((0, c), np.float32)
            )
        self._fuse_distances(*self._frame_distances(depth, valid, pose, intrinsics))
        self._add(frame_keys, frame_scores.astype(np.float32))
        return int(keys.size)

    def _frame_distances(
        self, depth: np.ndarray, valid: np.ndarray, pose: np.ndarray, intrinsics: Intrinsics
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One frame's projective TSDF: sorted keys of the voxels within the truncation of its
        surface points along their rays (and of their face neighbours) that the frame sees,
        each one's distance (metres along the ray through its centre, clipped to the
        truncation) and the weight of that observation."""
        depth = np.asarray(depth, dtype=np.float32)
        pose = np.asarray(pose, dtype=np.float64)
        size, trunc = self.voxel_size, self.truncation_m
        if not valid.any():
            return np.zeros(0, np.int64), np.zeros(0, np.float32), np.zeros(0, np.float32)
        origins, dirs = pixel_rays(intrinsics, pose)
        origin = origins[0, 0]
        d = dirs[valid]
        norm = np.linalg.norm(d, axis=1)
        along = depth[valid] * norm  # metres from the camera to the surface along each ray
        unit = d / norm[:, None]
        # Candidates: the cells of samples every half voxel over each ray's band.
        offsets = np.arange(-trunc, trunc + 0.25 * size, 0.5 * size)
        parts = []
        for i in range(0, along.size, _PIXEL_CHUNK):
            t = np.maximum(along[i : i + _PIXEL_CHUNK, None] + offsets, 0.0)
            points = origin + t[..., None] * unit[i : i + _PIXEL_CHUNK, None, :]
            cells = pack_keys(voxel_coords(points.reshape(-1, 3), size)).reshape(t.shape)
            # Consecutive samples along a ray often share a cell: drop those before sorting.
            parts.append(cells[:, 1:][cells[:, 1:] != cells[:, :-1]])
            parts.append(cells[:, 0])
        # ... and their six neighbours, so that the space beside a surface's edge, which no ray
        # of the band crosses, is observed as free where the frame sees past the edge.
        keys = np.unique((np.unique(np.concatenate(parts))[:, None] + _FACE_DELTAS).ravel())
        # Each candidate's centre, seen from the frame: the measured depth where it projects.
        centres = (unpack_keys(keys) + 0.5) * size
        cam = (centres - pose[:3, 3]) @ pose[:3, :3]
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = intrinsics.fx * cam[:, 0] / z + intrinsics.cx
            v = intrinsics.fy * cam[:, 1] / z + intrinsics.cy
        # Centres up to two pixels outside the image take the border's depth, so that the
        # voxels around the rays of the image's edge all have a distance.
        seen = (z > 0) & (u > -2.5) & (u < depth.shape[1] + 1.5)
        seen &= (v > -2.5) & (v < depth.shape[0] + 1.5)
        keys, z, u, v = keys[seen], z[seen], u[seen], v[seen]
        measured, ok = _depth_at(depth, valid, u, v, jump=trunc)
        ray = np.sqrt(
            ((u - intrinsics.cx) / intrinsics.fx) ** 2
            + ((v - intrinsics.cy) / intrinsics.fy) ** 2
            + 1.0
        )
        sdf = (measured - z) * ray
        # Observations behind the surface count less the deeper they lie (they may be free
        # space the frame cannot see): full weight to one voxel behind, none at the truncation.
        keep = ok & (sdf > -trunc)
        sdf = sdf[keep]
        weight = np.minimum((trunc + sdf) / (trunc - size), 1.0).astype(np.float32)
        return keys[keep], np.minimum(sdf, trunc).astype(np.float32), weight

    def _fuse_distances(self, keys: np.ndarray, sdf: np.ndarray, weight: np.ndarray) -> None:
        """Average one frame's distances (sorted unique ``keys``) into the TSDF with their
        observation weights."""
        if keys.size == 0:
            return
        rows = _rows_of(self.tsdf_keys, keys)
        seen = rows >= 0
        r = rows[seen]
        old, new = self.weights[r], weight[seen]
        self.tsdf[r] = (self.tsdf[r] * old + sdf[seen] * new) / (old + new)
        self.weights[r] = old + new
        at = np.searchsorted(self.tsdf_keys, keys[~seen])
        self._tsdf_keys = np.insert(self.tsdf_keys, at, keys[~seen])
        self._tsdf = np.insert(self.tsdf, at, sdf[~seen])
        self._weights = np.insert(self.weights, at, weight[~seen])

    def _add(self, keys: np.ndarray, scores: np.ndarray) -> None:
        if keys.size == 0:
            return
        merged, inverse = np.unique(np.concatenate([self.keys, keys]), return_inverse=True)
        out = np.zeros((merged.size, self.config.num_classes), dtype=np.float32)
        n_old = self.keys.size
        out[inverse[:n_old]] = self.scores
        out[inverse[n_old:]] += scores
        self._keys, self._scores = merged, out

    def lookup(self, keys: np.ndarray) -> np.ndarray:
        """Row of each key in ``scores``, or -1 where the voxel has no scores."""
        return _rows_of(self.keys, keys)

    def raycast(self, pose: np.ndarray, intrinsics: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
        """Cast every pixel's ray of a camera at ``pose`` through the map: (H, W) uint8 NYU40
        labels of the surface point each ray meets first, the TSDF's first zero crossing (0
        where it meets none within ``max_range``, or no votes lie near that point; see
        :meth:`_scores_near`), and (H, W) float32 z-depth of that point (0 where the ray meets
        no surface)."""
        if self.backend == "torch":
            return _raycast_torch(self, pose, intrinsics)
        h, w = intrinsics.height, intrinsics.width
        labels = np.zeros(h * w, dtype=np.uint8)
        depth = np.zeros(h * w, dtype=np.float32)
        surface = self._surface_index()
        if surface is None:
            return labels.reshape(h, w), depth.reshape(h, w)
        origins, dirs = pixel_rays(intrinsics, np.asarray(pose, dtype=np.float64))
        dirs = dirs.reshape(-1, 3)
        origin = origins.reshape(-1, 3)[0]
        norm = np.linalg.norm(dirs, axis=1)  # metres along the ray per metre of z-depth
        unit = dirs / norm[:, None]
        t = np.concatenate(
            [
                surface.first_crossing(origin, unit[i : i + _RAY_CHUNK], self.config.max_range)
                for i in range(0, unit.shape[0], _RAY_CHUNK)
            ]
        )
        rays = np.flatnonzero(np.isfinite(t))
        scores = self._scores_near(surface, origin + t[rays, None] * unit[rays])
        found = scores.max(axis=1) > 0
        labels[rays] = np.where(found, scores.argmax(axis=1) + 1, UNKNOWN).astype(np.uint8)
        depth[rays] = (t[rays] / norm[rays]).astype(np.float32)
        return labels.reshape(h, w), depth.reshape(h, w)

    def labels_for_pose(self, pose: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
        """(H, W) uint8 NYU40 labels of a camera at ``pose``, read by ray casting
        (:meth:`raycast`)."""
        return self.raycast(pose, intrinsics)[0]

    def labels_at_depth(
        self, depth: np.ndarray, pose: np.ndarray, intrinsics: Intrinsics
    ) -> np.ndarray:
        """(H, W) uint8 NYU40 labels read through a view's own depth instead of by ray casting:
        the class of the voxel at each pixel's measured surface point (0 where the pixel has
        no depth or no scores are near that voxel). Kept to measure what ray casting changes."""
        if self.backend == "torch":
            return _labels_at_depth_torch(self, depth, pose, intrinsics)
        keys, valid = self._surface_keys(depth, pose, intrinsics)
        scores = self._scores_at(keys)
        labels = np.where(scores.max(axis=1) > 0, scores.argmax(axis=1) + 1, UNKNOWN)
        out = np.zeros(valid.shape, dtype=np.uint8)
        out[valid] = labels.astype(np.uint8)
        return out

    def _surface_index(self) -> _Surface | None:
        if self._surface is None and (self.tsdf <= 0).any():
            self._surface = _Surface(self)
        return self._surface if isinstance(self._surface, _Surface) else None

    def _scores_near(self, surface: _Surface, points: np.ndarray) -> np.ndarray:
        """Scores (N, C) at world points (N, 3): those of the eight voxels whose centres
        surround each point, weighted trilinearly (the class votes are read like the
        distances); where none of them has scores, those of the voxel holding the point (see
        :meth:`_scores_at`)."""
        scores = np.zeros((points.shape[0], self.config.num_classes), dtype=np.float32)
        if surface.rows is None:
            return scores
        base, weights = _trilinear(points, self.voxel_size)
        rows = surface.rows.cube(base)
        for k in range(8):
            hit = rows[:, k] >= 0
            scores[hit] += weights[hit, k, None] * self.scores[rows[hit, k]]
        none = ~(scores.max(axis=1) > 0)
        scores[none] = self._scores_at(pack_keys(voxel_coords(points[none], self.voxel_size)))
        return scores

    def _scores_at(self, keys: np.ndarray) -> np.ndarray:
        """Scores (N, C) of the voxels ``keys``; where one has none, the summed scores of the
        voxels within ``search_radius`` cells."""
        rows = self.lookup(keys)
        c = self.config.num_classes
        scores = np.zeros((keys.size, c), dtype=np.float32)
        hit = rows >= 0
        scores[hit] = self.scores[rows[hit]]
        r = self.config.search_radius
        missing = np.flatnonzero(~hit)
        if r == 0 or missing.size == 0 or self.keys.size == 0:
            return scores
        cells = unpack_keys(keys[missing])
        offsets = _cube_offsets(r)
        neighbours = pack_keys((cells[:, None, :] + offsets[None]).reshape(-1, 3))
        rows = self.lookup(neighbours).reshape(missing.size, offsets.shape[0])
        gathered = np.where((rows >= 0)[..., None], self.scores[np.maximum(rows, 0)], 0.0).sum(
            axis=1
        )
        scores[missing] = gathered
        return scores

    def voxel_labels(self) -> np.ndarray:
        """(N,) arg-max NYU40 id of every voxel with scores (0 where all scores are zero)."""
        if self.num_voxels == 0:
            return np.zeros(0, dtype=np.uint8)
        return np.where(
            self.scores.max(axis=1) > 0, self.scores.argmax(axis=1) + 1, UNKNOWN
        ).astype(np.uint8)

    def voxel_centers(self) -> np.ndarray:
        """(N, 3) world coordinates of the centres of the voxels with scores, in ``keys`` order."""
        return (unpack_keys(self.keys) + 0.5) * self.voxel_size


def _check_depth(depth: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    depth = np.asarray(depth, dtype=np.float32)
    if depth.shape != (intrinsics.height, intrinsics.width):
        raise ValueError(
            f"voxel map: depth {depth.shape} does not match the camera "
            f"({intrinsics.height}, {intrinsics.width})"
        )
    return depth


def _depth_at(
    depth: np.ndarray, valid: np.ndarray, u: np.ndarray, v: np.ndarray, jump: float
) -> tuple[np.ndarray, np.ndarray]:
    """Measured z-depth at sub-pixel positions (``u``, ``v``; pixel centres at integers) and
    whether there is one: bilinear between the four pixels around the position where all have
    depth within ``jump`` of each other (one surface), else the nearest pixel's."""
    h, w = depth.shape
    u0 = np.clip(np.floor(u), 0, w - 1).astype(np.int64)
    v0 = np.clip(np.floor(v), 0, h - 1).astype(np.int64)
    u1, v1 = np.minimum(u0 + 1, w - 1), np.minimum(v0 + 1, h - 1)
    fu, fv = np.clip(u - u0, 0.0, 1.0), np.clip(v - v0, 0.0, 1.0)
    corners = [(v0, u0), (v0, u1), (v1, u0), (v1, u1)]
    d = np.stack([depth[r, c] for r, c in corners])
    ok = np.stack([valid[r, c] for r, c in corners])
    bilinear = (d[0] * (1 - fu) + d[1] * fu) * (1 - fv) + (d[2] * (1 - fu) + d[3] * fu) * fv
    smooth = ok.all(axis=0) & (d.max(axis=0) - d.min(axis=0) <= jump)
    un = np.clip(np.rint(u), 0, w - 1).astype(np.int64)
    vn = np.clip(np.rint(v), 0, h - 1).astype(np.int64)
    return np.where(smooth, bilinear, depth[vn, un]), smooth | valid[vn, un]


def _cube_offsets(radius: int) -> np.ndarray:
    r = np.arange(-radius, radius + 1)
    return np.stack(np.meshgrid(r, r, r, indexing="ij"), axis=-1).reshape(-1, 3)


def _box(cells: np.ndarray) -> tuple[np.ndarray, tuple[int, ...], np.ndarray, bool]:
    """The bounding box of ``cells`` padded by one cell: its lowest cell, shape, flat strides
    and whether a dense grid over it fits in ``MAX_DENSE_CELLS``."""
    lo = cells.min(axis=0) - 1
    shape = tuple(int(v) for v in cells.max(axis=0) + 2 - lo)
    strides = np.array([shape[1] * shape[2], shape[2], 1], dtype=np.int64)
    return lo, shape, strides, math.prod(shape) <= MAX_DENSE_CELLS


class _CellSet:
    """A set of integer cells with a vectorised membership test: a dense boolean grid over the
    cells' bounding box (padded by one empty cell) when it has at most ``MAX_DENSE_CELLS``
    cells, else their sorted packed keys."""

    def __init__(self, cells: np.ndarray):
        self.lo, self.shape, self.strides, dense = _box(cells)
        self.hi = self.lo + np.array(self.shape)  # exclusive
        self.grid: np.ndarray | None = None
        self.keys: np.ndarray | None = None
        if dense:
            self.grid = np.zeros(math.prod(self.shape), dtype=bool)
            self.grid[(cells - self.lo) @ self.strides] = True
        else:
            self.keys = np.unique(pack_keys(cells))

    def cell_of(self, flat: np.ndarray) -> np.ndarray:
        """Integer cells (N, 3) of flat indices into the dense grid."""
        idx = np.stack(np.unravel_index(flat, self.shape), axis=-1)
        return idx + self.lo

    def contains(self, cells: np.ndarray) -> np.ndarray:
        """(...,) whether each integer cell (..., 3) is in the set."""
        if self.grid is not None:
            # The callers' cells lie in the box (rays are clipped to it); one cell beyond, as
            # rounding may give at a face, lands on the empty padding.
            flat = (cells - self.lo) @ self.strides
            return self.grid[np.clip(flat, 0, self.grid.size - 1)]
        keys = pack_keys(cells.reshape(-1, 3))
        rows = np.minimum(np.searchsorted(self.keys, keys), self.keys.size - 1)
        return (self.keys[rows] == keys).reshape(cells.shape[:-1])


class _CellValues:
    """Values at integer cells, ``fill`` at every other cell: a dense grid over the cells'
    bounding box (padded by one cell) when it fits in ``MAX_DENSE_CELLS``, else the sorted
    packed keys."""

    _CORNERS = np.array(list(np.ndindex(2, 2, 2)), dtype=np.int64)  # (8, 3)

    def __init__(self, keys: np.ndarray, values: np.ndarray, fill: float | int):
        cells = unpack_keys(keys)
        self.lo, shape, self.strides, dense = _box(cells)
        self.hi = self.lo + np.array(shape)
        self.fill = fill
        self.grid: np.ndarray | None = None
        self.keys, self.values = keys, values
        if dense:
            self.grid = np.full(math.prod(shape), fill, dtype=values.dtype)
            self.grid[(cells - self.lo) @ self.strides] = values

    def cube(self, base: np.ndarray) -> np.ndarray:
        """Values (N, 8) at the cells ``base + corner`` (N, 3) for the corners of a unit cube,
        in ``np.ndindex(2, 2, 2)`` order."""
        out = np.full((base.shape[0], 8), self.fill, dtype=self.values.dtype)
        # A cube reaching out of the box holds only padding and cells outside: all ``fill``.
        inside = ((base >= self.lo) & (base + 1 < self.hi)).all(axis=1)
        if self.grid is not None:
            flat = (base[inside] - self.lo) @ self.strides
            out[inside] = self.grid[flat[:, None] + self._CORNERS @ self.strides]
            return out
        cells = base[inside, None, :] + self._CORNERS
        rows = _rows_of(self.keys, pack_keys(cells.reshape(-1, 3))).reshape(-1, 8)
        out[inside] = np.where(rows >= 0, self.values[np.maximum(rows, 0)], self.fill)
        return out


def _trilinear(points: np.ndarray, voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """For world points (N, 3): the lowest of the eight voxels whose centres surround each
    (N, 3) and the eight trilinear weights (N, 8), in ``np.ndindex(2, 2, 2)`` order."""
    g = points / voxel_size - 0.5
    base = np.floor(g)
    f = (g - base).astype(np.float32)
    wx, wy, wz = (np.stack([1.0 - f[:, a], f[:, a]], axis=1) for a in range(3))
    weights = (wx[:, :, None, None] * wy[:, None, :, None] * wz[:, None, None, :]).reshape(-1, 8)
    return base.astype(np.int64), weights


class _Surface:
    """The map as a ray caster: trilinear samples of the distances, which cells a ray must
    reach before a sample can be non-positive (those within one cell of a voxel with a
    non-positive distance: the eight voxels a trilinear sample mixes all lie that close to the
    cell holding it), and the rows of the voxels with scores."""

    def __init__(self, voxel_map: VoxelSemanticMap):
        self.voxel_size = voxel_map.voxel_size
        keys, tsdf = voxel_map.tsdf_keys, voxel_map.tsdf
        self.distances = _CellValues(keys, tsdf, fill=np.nan)
        self.index = _RayIndex(unpack_keys(keys[tsdf <= 0]), self.voxel_size, radius=1)
        self.rows = (
            _CellValues(voxel_map.keys, np.arange(voxel_map.num_voxels, dtype=np.int32), fill=-1)
            if voxel_map.num_voxels
            else None
        )

    def sample(self, points: np.ndarray) -> np.ndarray:
        """Trilinear interpolation (N,) of the distances at world points (N, 3) between the
        centres of the eight voxels around each, over those with a distance (NaN: none).
        Voxels without one are unobserved space (free space a frame saw has a distance: the
        band's neighbours are fused too, see :meth:`VoxelSemanticMap._frame_distances`)."""
        base, weights = _trilinear(points, self.voxel_size)
        values = self.distances.cube(base)
        seen = ~np.isnan(values)
        weights = np.where(seen, weights, 0.0)
        total = np.einsum("ij,ij->i", weights, np.where(seen, values, 0.0))
        wsum = weights.sum(axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(wsum > 1e-6, total / wsum, np.nan)

    def first_crossing(self, origin: np.ndarray, dirs: np.ndarray, max_range: float) -> np.ndarray:
        """Distance (N,) along unit rays ``dirs`` (N, 3) from ``origin`` to the first point
        where the interpolated TSDF turns non-positive (NaN where none within ``max_range``):
        linear between the last positive sample and the first non-positive one, or that
        sample itself where the ray comes from unobserved space."""
        o = np.asarray(origin, dtype=np.float64)
        d = np.asarray(dirs, dtype=np.float64)
        out = np.full(d.shape[0], np.nan)
        step = 0.5 * self.voxel_size
        offsets = step * np.arange(-1, _SURFACE_SAMPLES)  # one sample before the stop cell
        rays, start, end = self.index.clip(o, d, max_range)
        while rays.size:
            hit, t_in, _ = self.index.march(o, d[rays], start, end)
            rays, end = rays[hit], end[hit]
            t = t_in[hit, None] + offsets
            f = self.sample((o + t[..., None] * d[rays, None, :]).reshape(-1, 3)).reshape(t.shape)
            before, after = f[:, :-1], f[:, 1:]
            enter = (after <= 0) & ~(before <= 0) & (t[:, 1:] <= end[:, None])
            with np.errstate(divide="ignore", invalid="ignore"):
                t_cross = t[:, 1:] + np.where(before > 0, step * after / (before - after), 0.0)
            found = enter.any(axis=1)
            k = enter.argmax(axis=1)
            out[rays[found]] = t_cross[found, k[found]]
            going = ~found & (t[:, -1] < end)
            rays, start, end = rays[going], t[going, -1], end[going]
        return out


class _RayIndex:
    """Which cells stop a ray: the given cells, grown by ``radius`` cells; and, to skip empty
    space, the coarse cells (``_COARSE`` voxels a side) that hold any of them."""

    def __init__(self, cells: np.ndarray, voxel_size: float, radius: int):
        if radius and cells.size:
            grown = pack_keys((cells[:, None, :] + _cube_offsets(radius)[None]).reshape(-1, 3))
            cells = unpack_keys(np.unique(grown))
        self.voxel_size = voxel_size
        self.empty = cells.shape[0] == 0
        if self.empty:
            return
        self.fine = _CellSet(cells)
        self.coarse = _CellSet(np.floor_divide(cells, _COARSE))  # repeats are harmless
        self.lo = self.fine.lo * voxel_size
        self.hi = self.fine.hi * voxel_size

    def clip(
        self, origin: np.ndarray, dirs: np.ndarray, max_range: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The rays (indices into ``dirs``, unit (N, 3)) that cross the stopping cells' bounding
        box within ``max_range``, and where each enters and leaves it (slab test)."""
        if self.empty:
            return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
        with np.errstate(divide="ignore", invalid="ignore"):
            t_lo = (self.lo - origin) / dirs
            t_hi = (self.hi - origin) / dirs
        t_near = np.nan_to_num(np.minimum(t_lo, t_hi), nan=-np.inf)
        t_far = np.nan_to_num(np.maximum(t_lo, t_hi), nan=np.inf)
        start = np.maximum(t_near.max(axis=1), 0.0)
        end = np.minimum(t_far.min(axis=1), max_range)
        rays = np.flatnonzero(start < end)
        return rays, start[rays], end[rays]

    def march(
        self, origin: np.ndarray, dirs: np.ndarray, start: np.ndarray, end: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Follow unit-length rays from ``origin`` (3,) along ``dirs`` (N, 3) between ``start``
        and ``end`` (N,) (inside the box, see :meth:`clip`); returns (N,) whether each meets a
        stopping cell, the distance where it enters the first one (``start`` if it begins in
        one) and that cell (N, 3). The march walks coarse cells and looks inside the ones that
        hold stopping cells."""
        o = np.asarray(origin, dtype=np.float64)
        d = np.asarray(dirs, dtype=np.float64)
        n = d.shape[0]
        hit = np.zeros(n, dtype=bool)
        t_hit = np.zeros(n)
        cell_hit = np.zeros((n, 3), dtype=np.int64)
        if self.empty:
            return hit, t_hit, cell_hit
        rays = np.flatnonzero(start < end)
        start, end = start[rays], end[rays]
        coarse_size = _COARSE * self.voxel_size
        while rays.size:
            # The next coarse cell on each ray that holds stopping cells ...
            got, t_in, t_out, _ = _first_stop(
                o, d[rays], start, end, coarse_size, self.coarse, _WINDOW_CELLS
            )
            rays, start, end = rays[got], t_in[got], end[got]
            stop_at = np.minimum(t_out[got], end)
            # ... and the first stopping cell inside it; rays that meet none there go on.
            # (a coarse cell spans less than 2 * _COARSE voxels along any ray: one window)
            got, f_in, _, cell = _first_stop(
                o, d[rays], start, stop_at, self.voxel_size, self.fine, 2 * _COARSE
            )
            hit[rays[got]] = True
            t_hit[rays[got]] = f_in[got]
            cell_hit[rays[got]] = cell[got]
            going = ~got & (stop_at < end)
            rays, start, end = rays[going], stop_at[going], end[going]
        return hit, t_hit, cell_hit


def _first_stop(
    o: np.ndarray,
    d: np.ndarray,
    start: np.ndarray,
    end: np.ndarray,
    size: float,
    cells: _CellSet,
    window: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For rays ``o + t d`` (unit ``d`` (R, 3)) between ``start`` and ``end`` (R,), the first
    cell of edge ``size`` in ``cells`` that each crosses, marching ``window`` cells' length at a
    time: (R,) whether there is one, the ``t`` where the ray enters and leaves it, and the cell
    (R, 3).

    Exact traversal (Amanatides and Woo's, vectorised): a ray changes cell where it crosses a
    cell plane, one axis at a time. Within a window the plane crossings of the three axes,
    sorted, cut the ray into pieces that each lie in one cell; piece j's cell is the first
    piece's moved one step along the axis of each of the first j crossings.
    """
    n = start.shape[0]
    hit = np.zeros(n, dtype=bool)
    t_in = np.zeros(n)
    t_out = np.zeros(n)
    found = np.zeros((n, 3), dtype=np.int64)
    k = np.arange(1, window + 2, dtype=np.float64)  # enough planes for one window
    axis_of = np.repeat(np.arange(3), k.size)  # axis of each column of the crossings
    todo = np.arange(n)
    a, b = start.copy(), end
    while todo.size:
        rows = np.arange(todo.size)
        dd = d[todo]
        lo = a
        hi = np.minimum(lo + window * size, b[todo])
        x = (o + lo[:, None] * dd) / size  # (R, 3) where this window begins, in cells
        step = np.sign(dd).astype(np.int64)
        # The cell the ray is in just after ``x`` (on a plane: the one it moves into), and the
        # k-th plane it crosses along each axis from there, in travel order. Planes are counted
        # from the cell, so the walk below stays consistent however ``x`` was rounded.
        cell0 = np.where(dd < 0, np.ceil(x) - 1, np.floor(x))
        with np.errstate(divide="ignore", invalid="ignore"):
            planes = (cell0 + (dd > 0))[:, :, None] + step[:, :, None] * (k - 1)  # (R, 3, K)
            cross = lo[:, None, None] + (planes - x[:, :, None]) * size / dd[:, :, None]
        cross = np.where(np.isfinite(cross), cross, np.inf).reshape(todo.size, -1)
        cell0 = cell0.astype(np.int64)
        order = np.argsort(cross, axis=1)
        t = np.take_along_axis(cross, order, axis=1)
        axis = axis_of[order]
        # Pieces: [lo, t0], [t0, t1], ... up to ``hi``, each in one cell; rounding can leave a
        # piece empty, and an empty piece stops no ray.
        enter = np.maximum(np.concatenate([lo[:, None], t], axis=1), lo[:, None])
        leave = np.concatenate([t, np.full((todo.size, 1), np.inf)], axis=1)
        real = (np.minimum(leave, hi[:, None]) > enter) & (enter < hi[:, None])
        if cells.grid is not None:
            move = np.take_along_axis(step * cells.strides, axis, axis=1)
            flat = ((cell0 - cells.lo) @ cells.strides)[:, None] + np.concatenate(
                [np.zeros((todo.size, 1), np.int64), np.cumsum(move, axis=1)], axis=1
            )
            flat = np.clip(flat, 0, cells.grid.size - 1)
            stop = cells.grid[flat] & real
        else:
            walk = _walk(cell0, step, axis)
            stop = cells.contains(walk) & real
        j = stop.argmax(axis=1)
        got = stop[rows, j]
        r, jg = rows[got], j[got]
        idx = todo[got]
        hit[idx] = True
        t_in[idx] = enter[r, jg]
        t_out[idx] = leave[r, jg]  # where the ray leaves the cell, even past ``end``
        if cells.grid is not None:
            found[idx] = cells.cell_of(flat[r, jg])
        else:
            found[idx] = walk[r, jg]
        going = ~got & (hi < b[todo])
        todo, a = todo[going], hi[going]
    return hit, t_in, t_out, found


def _walk(cell0: np.ndarray, step: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Cells (R, P + 1, 3) of the pieces of rays that start in ``cell0`` (R, 3) and then cross
    planes of the axes ``axis`` (R, P), moving ``step`` (R, 3) along each."""
    counts = np.stack([np.cumsum(axis == a, axis=1) for a in range(3)], axis=-1)
    counts = np.concatenate([np.zeros((axis.shape[0], 1, 3), np.int64), counts], axis=1)
    return cell0[:, None, :] + step[:, None, :] * counts


# The torch implementation (``backend="torch"``, the default): the algorithm above on the map's
# device, every step a tensor operation over all pixels, voxels or rays of a view.

_T_PIECES = 8  # cells the exact traversal looks at per ray and march iteration
_T_EXACT = 16  # the skips are exact (one less than the Chebyshev distance) up to this
_T_SKIP = 64  # the most voxels the march skips at once (_T_EXACT times a power of two)
_T_SKIP_STEPS = 3  # skips per ray and march iteration
_T_FIRST = 5  # samples of a window taken first (the rest where they hold no crossing)
_T_RAY_CHUNK = 1 << 18  # rays marched together
_T_CORNERS = torch.tensor(list(np.ndindex(2, 2, 2)), dtype=torch.int64)  # (8, 3)


def _as_numpy(a: np.ndarray | Tensor) -> np.ndarray:
    return a if isinstance(a, np.ndarray) else a.detach().cpu().numpy()


def _nbytes(a: np.ndarray | Tensor) -> int:
    return int(a.nbytes) if isinstance(a, np.ndarray) else a.element_size() * a.numel()


def _t_pack(cells: Tensor) -> Tensor:
    """:func:`pack_keys` of integer cells (..., 3) on any device."""
    shifted = cells + _OFFSET
    if shifted.numel() and bool(((shifted.min() < 0) | (shifted.max() > _MASK)).item()):
        raise ValueError(_TOO_FAR)
    return (shifted[..., 0] << (2 * _BITS)) | (shifted[..., 1] << _BITS) | shifted[..., 2]


def _t_unpack(keys: Tensor) -> Tensor:
    """:func:`unpack_keys` on any device."""
    cells = torch.stack([keys >> (2 * _BITS), (keys >> _BITS) & _MASK, keys & _MASK], dim=-1)
    return cells - _OFFSET


def _t_rows_of(sorted_keys: Tensor, keys: Tensor) -> Tensor:
    """Row of each key in ``sorted_keys``, or -1 where it is absent."""
    if sorted_keys.numel() == 0:
        return torch.full_like(keys, -1)
    rows = torch.searchsorted(sorted_keys, keys).clamp_(max=sorted_keys.numel() - 1)
    return torch.where(sorted_keys[rows] == keys, rows, -1)


def _t_merge(old: Tensor, new: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Sorted unique keys ``new`` merged into sorted unique ``old``: the merged keys and the row
    of each old and of each new key in them."""
    rows = _t_rows_of(old, new)
    hit = rows >= 0
    fresh = new[~hit]
    at_old = torch.arange(old.numel(), device=old.device)
    if fresh.numel():
        at_old += torch.searchsorted(fresh, old)
    at_fresh = torch.searchsorted(old, fresh) + torch.arange(fresh.numel(), device=old.device)
    merged = torch.empty(old.numel() + fresh.numel(), dtype=old.dtype, device=old.device)
    merged[at_old] = old
    merged[at_fresh] = fresh
    at_new = torch.empty_like(new)
    at_new[hit] = at_old[rows[hit]]
    at_new[~hit] = at_fresh
    return merged, at_old, at_new


def _t_box(cells: Tensor) -> tuple[Tensor, list[int], Tensor, bool]:
    """:func:`_box` on any device."""
    lo = cells.amin(dim=0) - 1
    shape = [int(v) for v in (cells.amax(dim=0) + 2 - lo).tolist()]
    strides = torch.tensor([shape[1] * shape[2], shape[2], 1], device=cells.device)
    return lo, shape, strides, math.prod(shape) <= MAX_DENSE_CELLS


def _t_frame_rays(
    voxel_map: VoxelSemanticMap, valid: np.ndarray, pose: np.ndarray, intrinsics: Intrinsics
) -> tuple[Tensor, Tensor, Tensor]:
    """The camera centre (3,), the rays (N, 3) of the pixels with depth (unit z in the camera,
    as :func:`pixel_rays`) and the flat (H * W,) mask of those pixels, on the map's device."""
    origins, dirs = pixel_rays(intrinsics, np.asarray(pose, dtype=np.float64))
    dev = voxel_map.device
    mask = torch.from_numpy(valid.reshape(-1)).to(dev)
    return (
        torch.from_numpy(origins[0, 0].copy()).to(dev),
        torch.from_numpy(dirs.reshape(-1, 3)).to(dev)[mask],
        mask,
    )


def _t_surface_keys(
    voxel_map: VoxelSemanticMap, depth: np.ndarray, valid: np.ndarray, dirs: Tensor, origin: Tensor
) -> tuple[Tensor, Tensor]:
    """Keys (N,) of the voxels the pixels with depth fall in, and their z-depths (N,)."""
    z = torch.from_numpy(depth[valid]).to(voxel_map.device)
    points = origin + dirs * z[:, None].double()
    return _t_pack(torch.floor(points / voxel_map.voxel_size).long()), z


def _integrate_torch(
    voxel_map: VoxelSemanticMap,
    prediction: np.ndarray,
    depth: np.ndarray,
    valid: np.ndarray,
    pose: np.ndarray,
    intrinsics: Intrinsics,
) -> int:
    """:meth:`VoxelSemanticMap.integrate` of a checked frame, on the map's device."""
    dev, c = voxel_map.device, voxel_map.config.num_classes
    origin, dirs, mask = _t_frame_rays(voxel_map, valid, pose, intrinsics)
    keys, z = _t_surface_keys(voxel_map, depth, valid, dirs, origin)
    flat = torch.from_numpy(np.ascontiguousarray(prediction)).to(dev)
    if prediction.ndim == 2:
        labels = flat.reshape(-1)[mask].long()
        voted = labels > UNKNOWN
        keys, labels = keys[voted], labels[voted] - 1
        frame_keys, inverse = torch.unique(keys, return_inverse=True)
        frame_scores = torch.zeros(frame_keys.numel() * c, device=dev)
        frame_scores.index_add_(
            0, inverse * c + labels, torch.ones_like(frame_scores[:1]).expand(labels.numel())
        )
        frame_scores = frame_scores.view(-1, c)
    else:
        probs = flat.reshape(-1, c)[mask].float()
        frame_keys, inverse = torch.unique(keys, return_inverse=True)
        frame_scores = torch.zeros((frame_keys.numel(), c), device=dev)
        frame_scores.index_add_(0, inverse, probs)
    _t_fuse_distances(
        voxel_map, *_t_frame_distances(voxel_map, depth, valid, dirs, z, origin, pose, intrinsics)
    )
    if frame_keys.numel():
        merged, at_old, at_new = _t_merge(voxel_map._keys, frame_keys)
        scores = torch.zeros((merged.numel(), c), device=dev)
        scores[at_old] = voxel_map._scores
        scores.index_add_(0, at_new, frame_scores)
        voxel_map._keys, voxel_map._scores = merged, scores
    return int(keys.numel())


def _t_frame_distances(
    voxel_map: VoxelSemanticMap,
    depth: np.ndarray,
    valid: np.ndarray,
    dirs: Tensor,
    z: Tensor,
    origin: Tensor,
    pose: np.ndarray,
    intrinsics: Intrinsics,
) -> tuple[Tensor, Tensor, Tensor]:
    """:meth:`VoxelSemanticMap._frame_distances` on the map's device, the candidate voxels
    gathered in a dense grid over the frame's box where it fits."""
    dev = voxel_map.device
    size, trunc = voxel_map.voxel_size, voxel_map.truncation_m
    if dirs.shape[0] == 0:
        empty = torch.zeros(0, device=dev)
        return torch.zeros(0, dtype=torch.int64, device=dev), empty, empty
    norm = torch.sqrt((dirs * dirs).sum(dim=1))
    along = z.double() * norm
    unit = dirs / norm[:, None]
    offsets = torch.from_numpy(np.arange(-trunc, trunc + 0.25 * size, 0.5 * size)).to(dev)
    # One axis at a time (contiguous tensors), the same arithmetic as the reference's points.
    o, axes = origin.tolist(), unit.T.contiguous()
    if (max(map(abs, o)) + float(along.max()) + trunc) / size >= 1 << 30:
        raise ValueError(_TOO_FAR)  # (and the cells below would overflow int32)
    parts: list[list[Tensor]] = [[], [], []]
    for i in range(0, along.numel(), _PIXEL_CHUNK):
        t = torch.clamp(along[i : i + _PIXEL_CHUNK, None] + offsets, min=0.0)
        for a in range(3):
            points = o[a] + t * axes[a, i : i + _PIXEL_CHUNK, None]
            parts[a].append(torch.floor(points / size).int().view(-1))  # int32: 4 bytes a cell
    cx, cy, cz = (torch.cat(p) for p in parts)
    bounds = torch.stack([torch.stack([c.min(), c.max()]) for c in (cx, cy, cz)]).tolist()
    if min(b[0] for b in bounds) < -_OFFSET or max(b[1] for b in bounds) > _MASK - _OFFSET:
        raise ValueError(_TOO_FAR)
    lo = [b[0] - 1 for b in bounds]
    shape = [b[1] + 2 - b[0] + 1 for b in bounds]
    if math.prod(shape) <= MAX_DENSE_CELLS:
        grid = torch.zeros(shape, dtype=torch.bool, device=dev)
        grid.view(-1)[((cx - lo[0]) * shape[1] + (cy - lo[1])) * shape[2] + (cz - lo[2])] = True
        band = grid.clone()  # ... and the six face neighbours (see the reference)
        band[1:] |= grid[:-1]
        band[:-1] |= grid[1:]
        band[:, 1:] |= grid[:, :-1]
        band[:, :-1] |= grid[:, 1:]
        band[:, :, 1:] |= grid[:, :, :-1]
        band[:, :, :-1] |= grid[:, :, 1:]
        flat = band.view(-1).nonzero().squeeze(1)  # sorted, as are the keys of the cells
        yz = shape[1] * shape[2]
        cand = torch.stack([flat // yz, flat // shape[2] % shape[1], flat % shape[2]], 1).long()
        cand += torch.tensor(lo, device=dev)
    else:
        keys = torch.unique(_t_pack(torch.stack([cx, cy, cz], dim=1).long()))
        deltas = torch.from_numpy(_FACE_DELTAS).to(dev)
        cand = _t_unpack(torch.unique((keys[:, None] + deltas).reshape(-1)))
    centres = (cand.double() + 0.5) * size
    pose_t = torch.from_numpy(np.asarray(pose, dtype=np.float64)).to(dev)
    cam = (centres - pose_t[:3, 3]) @ pose_t[:3, :3]
    zc = cam[:, 2]
    u = intrinsics.fx * cam[:, 0] / zc + intrinsics.cx
    v = intrinsics.fy * cam[:, 1] / zc + intrinsics.cy
    h, w = depth.shape
    seen = (zc > 0) & (u > -2.5) & (u < w + 1.5) & (v > -2.5) & (v < h + 1.5)
    cand, zc, u, v = cand[seen], zc[seen], u[seen], v[seen]
    depth_t = torch.from_numpy(np.where(valid, depth, 0.0).astype(np.float32)).to(dev)
    measured, ok = _t_depth_at(depth_t, depth_t > 0, u, v, jump=trunc)
    ray = torch.sqrt(
        ((u - intrinsics.cx) / intrinsics.fx) ** 2
        + ((v - intrinsics.cy) / intrinsics.fy) ** 2
        + 1.0
    )
    sdf = (measured - zc) * ray
    keep = ok & (sdf > -trunc)
    sdf = sdf[keep]
    weight = torch.clamp((trunc + sdf) / (trunc - size), max=1.0).float()
    return _t_pack(cand[keep]), torch.clamp(sdf, max=trunc).float(), weight


def _t_depth_at(
    depth: Tensor, valid: Tensor, u: Tensor, v: Tensor, jump: float
) -> tuple[Tensor, Tensor]:
    """:func:`_depth_at` on any device."""
    h, w = depth.shape
    flat_d, flat_ok = depth.reshape(-1), valid.reshape(-1)
    u0 = torch.clamp(torch.floor(u), 0, w - 1).long()
    v0 = torch.clamp(torch.floor(v), 0, h - 1).long()
    u1, v1 = torch.clamp(u0 + 1, max=w - 1), torch.clamp(v0 + 1, max=h - 1)
    fu, fv = torch.clamp(u - u0, 0.0, 1.0), torch.clamp(v - v0, 0.0, 1.0)
    idx = torch.stack([v0 * w + u0, v0 * w + u1, v1 * w + u0, v1 * w + u1])
    d = flat_d[idx].double()
    ok = flat_ok[idx]
    bilinear = (d[0] * (1 - fu) + d[1] * fu) * (1 - fv) + (d[2] * (1 - fu) + d[3] * fu) * fv
    smooth = ok.all(dim=0) & (d.amax(dim=0) - d.amin(dim=0) <= jump)
    un = torch.clamp(torch.round(u), 0, w - 1).long()
    vn = torch.clamp(torch.round(v), 0, h - 1).long()
    near = vn * w + un
    return torch.where(smooth, bilinear, flat_d[near].double()), smooth | flat_ok[near]


def _t_fuse_distances(
    voxel_map: VoxelSemanticMap, keys: Tensor, sdf: Tensor, weight: Tensor
) -> None:
    """:meth:`VoxelSemanticMap._fuse_distances` on the map's device."""
    if keys.numel() == 0:
        return
    merged, at_old, at_new = _t_merge(voxel_map._tsdf_keys, keys)
    tsdf = torch.zeros(merged.numel(), device=keys.device)
    weights = torch.zeros(merged.numel(), device=keys.device)
    tsdf[at_old] = voxel_map._tsdf
    weights[at_old] = voxel_map._weights
    old, before = weights[at_new], tsdf[at_new]
    total = old + weight
    tsdf[at_new] = torch.where(old > 0, (before * old + sdf * weight) / total, sdf)
    weights[at_new] = total
    voxel_map._tsdf_keys, voxel_map._tsdf, voxel_map._weights = merged, tsdf, weights


class _TorchCells:
    """:class:`_CellValues` on any device: values at integer cells (N, 3), ``fill`` elsewhere."""

    def __init__(self, cells: Tensor, values: Tensor, fill: float | int):
        self.lo, self.shape, self.strides, self.dense = _t_box(cells)
        shape = self.shape
        self.hi = self.lo + torch.tensor(shape, device=cells.device)
        self.fill = fill
        self.corners = _T_CORNERS.to(cells.device)
        if self.dense:
            self.grid = torch.full(
                (math.prod(shape),), fill, dtype=values.dtype, device=cells.device
            )
            self.grid[((cells - self.lo) * self.strides).sum(dim=1)] = values
            self.offsets = (self.corners * self.strides).sum(dim=1)
        else:
            keys = _t_pack(cells)
            order = torch.argsort(keys)
            self.keys, self.values = keys[order], values[order]

    def cube(self, base: Tensor) -> Tensor:
        """Values (..., 8) at the cells ``base + corner`` (..., 3), as :meth:`_CellValues.cube`."""
        inside = ((base >= self.lo) & (base + 1 < self.hi)).all(dim=-1)
        if self.dense:
            flat = torch.where(inside, ((base - self.lo) * self.strides).sum(dim=-1), 0)
            corners = (flat[..., None] + self.offsets).view(-1)
            out = self.grid.index_select(0, corners).view(*flat.shape, 8)
        else:
            cells = torch.where(inside[..., None], base, self.lo)[..., None, :] + self.corners
            rows = _t_rows_of(self.keys, _t_pack(cells))
            out = torch.where(rows >= 0, self.values[rows.clamp(min=0)], self.fill)
        return torch.where(inside[..., None], out, self.fill)


def _along(o: Tensor, d: Tensor, t: Tensor) -> Tensor:
    """The points (W, K, 3) ``o + t d`` of rays from ``o`` (3,) along the columns of ``d``
    (3, W), at ``t`` (W, K): one coordinate at a time (a broadcast over an axis of three is
    slow on the CPU)."""
    out = torch.empty((*t.shape, 3), dtype=t.dtype, device=t.device)
    for a in range(3):
        torch.addcmul(o[a], t, d[a, :, None], out=out[..., a])
    return out


def _t_trilinear(points: Tensor, voxel_size: float) -> tuple[Tensor, Tensor]:
    """:func:`_trilinear` on any device (float32 weights)."""
    g = points / voxel_size - 0.5
    base = torch.floor(g)
    f = (g - base).float()
    # The products one column at a time (broadcasts over axes of two are slow on the CPU).
    fx, fy, fz = f.unbind(-1)
    x = (1.0 - fx, fx)
    y = (1.0 - fy, fy)
    z = (1.0 - fz, fz)
    xy = [x[i] * y[j] for i in range(2) for j in range(2)]
    weights = torch.stack([xy[k // 2] * z[k % 2] for k in range(8)], dim=-1)
    return base.long(), weights


class _TorchSurface:
    """:class:`_Surface` on any device. The march is the reference's (windows of samples half
    a voxel apart from where each ray enters a stopping cell, by an exact voxel traversal), but
    it skips empty space with a distance field on the voxel grid instead of coarse cells: for
    each cell, how many voxels a ray in it may advance at once, one less than the Chebyshev
    distance (in cells) to the nearest stopping cell (exact up to ``_T_EXACT`` cells, then
    ``_T_EXACT`` times a power of two, at most ``_T_SKIP``; every point on the way lies in a
    cell at most that many cells from its own). Next to a stopping cell a ray walks cell by cell
    (the exact traversal, up to ``_T_PIECES`` cells) until it enters one or a cell it may skip
    from. Samples are interpolated by ``grid_sample``. Maps too large for a dense grid look
    cells up in sorted keys and walk every cell, ``_T_PIECES`` at a time.

    On the CPU, torch runs operations over a long axis fast and broadcasts or reductions over an
    axis of two or three slowly, and ``index_select`` / ``index_copy_`` faster than indexing
    with ``[]``: the march works one coordinate at a time and compacts its rays' state with
    those."""

    def __init__(self, voxel_map: VoxelSemanticMap):
        self.voxel_size = size = voxel_map.voxel_size
        cells, tsdf = _t_unpack(voxel_map._tsdf_keys), voxel_map._tsdf
        dev = cells.device
        self.distances = _TorchCells(cells, tsdf, fill=math.nan)
        stop = cells[tsdf <= 0]
        # The stopping cells' box, in metres.
        self.lo = (stop.amin(dim=0) - 1).double() * size
        self.hi = (stop.amax(dim=0) + 2).double() * size
        self.field: Tensor | None = None
        if self.distances.dense:
            d = self.distances
            shape = d.shape
            grid = d.grid.view(shape)
            # Trilinear sampling by grid_sample: the distances (0 where unobserved) and
            # whether observed, so that the sample is the reference's weighted mean.
            # The volume's axes are reversed (z, y, x), as grid_sample takes x, y, z positions
            # of the last, middle and first axis.
            seen = ~torch.isnan(grid)
            volume = torch.stack([torch.where(seen, grid, 0.0), seen.float()])
            self.volume = volume.permute(0, 3, 2, 1).contiguous()[None]
            # A position in metres to grid_sample's (-1 at the first voxel's centre, 1 at the
            # last one's): position * scale + shift.
            self.grid_scale = 2.0 / (torch.tensor(shape, device=dev) - 1).float() / size
            self.grid_shift = -(d.lo.float() + 0.5) * size * self.grid_scale - 1.0
            # The field: -1 at stopping cells, else how many voxels a ray may skip: one less
            # than the Chebyshev distance (in cells) to the nearest stopping cell up to
            # _T_EXACT, then r where that distance is more than r (r = _T_EXACT, 2 _T_EXACT, ...
            # up to _T_SKIP). The stopping cells are grown one cell at a time, then r at a time.
            stopping = grown = _grow(grid <= 0, 1)
            field = torch.zeros(shape, dtype=torch.int8, device=dev)
            for _ in range(_T_EXACT):
                grown = _grow(grown, 1)
                field += ~grown  # + 1 for every step that has not reached the cell yet
            r = _T_EXACT
            while r < _T_SKIP:
                grown = _grow(grown, r)  # now 2r cells around the stopping cells
                field.masked_fill_(~grown, 2 * r)
                r *= 2
            field.masked_fill_(stopping, -1)
            # Padded by _T_PIECES cells that are neither stopping nor skipped, so that the
            # traversal's cells from one in the box need no bounds checks.
            pad = _T_PIECES + 1
            field = torch.nn.functional.pad(field[None], (pad,) * 6, value=0)[0]
            self.field = field.reshape(-1)
            self.field_lo = (d.lo - pad).float()
            self.field_top = [float(n - 1) for n in field.shape]
            self.field_strides = [field.shape[1] * field.shape[2], field.shape[2], 1]
        else:
            grown = stop[:, None, :] + torch.from_numpy(_cube_offsets(1)).to(dev)
            self.stop_keys = torch.unique(_t_pack(grown.reshape(-1, 3)))
        n = voxel_map.num_voxels
        self.rows = (
            _TorchCells(
                _t_unpack(voxel_map._keys),
                torch.arange(n, dtype=torch.int32, device=dev),
                fill=-1,
            )
            if n
            else None
        )

    def sample(self, o: Tensor, d: Tensor, t: Tensor) -> Tensor:
        """:meth:`_Surface.sample` (W, K) at the points ``o + t d`` of rays from ``o`` (3,)
        along ``d`` (W, 3), ``t`` (W, K)."""
        if self.field is None:
            base, weights = _t_trilinear(o + t[..., None] * d[:, None, :], self.voxel_size)
            values = self.distances.cube(base)
            seen = ~torch.isnan(values)
            weights = torch.where(seen, weights, 0.0)
            total = (weights * torch.where(seen, values, 0.0)).sum(dim=-1)
            wsum = weights.sum(dim=-1)
        else:
            g0, dg = o * self.grid_scale + self.grid_shift, (d * self.grid_scale).T
            g = _along(g0, dg, t)
            out = torch.nn.functional.grid_sample(
                self.volume, g.view(1, 1, 1, -1, 3), align_corners=True
            ).view(2, *t.shape)
            total, wsum = out[0], out[1]
        return torch.where(wsum > 1e-6, total / wsum, math.nan)

    def _field_flat(self, o: Tensor, d: Tensor, t: Tensor) -> Tensor:
        """Flat int32 index (R,) into the field of the cells that hold the points ``o + t d``
        of rays from ``o`` (3,) (in cells from the field's first cell) along ``d`` (R, 3)
        (unit, in metres) at ``t`` (R,), clamped into the grid. One coordinate at a time
        (broadcasts and sums over an axis of three are slow on the CPU)."""
        flat = None
        for a in range(3):
            c = torch.addcmul(o[a], t, d[:, a], value=1.0 / self.voxel_size).floor_()
            c = c.clamp_(0.0, self.field_top[a]).int().mul_(self.field_strides[a])
            flat = c if flat is None else flat.add_(c)
        return flat

    def _field_at(self, o: Tensor, d: Tensor, t: Tensor) -> Tensor:
        """The field (R,) at the points ``o + t d`` (as in :meth:`_field_flat`). A point outside
        the grid takes the value of the nearest cell in it, which is never farther from a
        stopping cell."""
        return self.field.index_select(0, self._field_flat(o, d, t))

    def _walk(self, o: Tensor, d: Tensor, start: Tensor, end: Tensor) -> tuple[Tensor, Tensor]:
        """The exact voxel traversal on the field, one cell at a time for up to ``_T_PIECES``
        cells while the rays ``o + t d`` (as in :meth:`_field_at`) from ``start`` (R,) stay next
        to stopping cells: (R,) whether each enters a stopping cell before ``end``, and where
        it enters it (``start`` if it begins in one), else where the first cell it may skip
        from lets it skip to, or where it enters the cell after the last one walked (``end`` or
        beyond where it leaves the box first)."""
        # Each ray's state in two rows, compacted at once: where it crosses the next plane of
        # each axis, how far apart those planes are, where it entered its cell and where it
        # ends; and its cell's flat index, the index's change a cell along each axis, its row.
        # Built one axis at a time (broadcasts over an axis of three are slow on the CPU).
        n = start.shape[0]
        real_state = torch.empty((n, 8), device=d.device)
        int_state = torch.empty((n, 5), dtype=torch.int32, device=d.device)
        real_state[:, 6], real_state[:, 7] = start, end
        int_state[:, 4] = torch.arange(n, dtype=torch.int32, device=d.device)
        flat = int_state[:, 0]
        for a in range(3):
            da = d[:, a]
            x = torch.addcmul(o[a], start, da, value=1.0 / self.voxel_size)
            # The cell the ray is in just after ``x`` (on a plane: the one it moves into).
            cell = torch.where(da < 0, torch.ceil(x) - 1, torch.floor(x))
            per_cell = self.voxel_size / da
            cross = torch.addcmul(start, cell + (da > 0) - x, per_cell, out=real_state[:, a])
            cross.nan_to_num_(nan=math.inf, neginf=math.inf)  # a ray parallel to the planes
            torch.abs(per_cell, out=real_state[:, 3 + a])
            stride = self.field_strides[a]
            torch.mul(torch.sign(da).int(), stride, out=int_state[:, 1 + a])
            c = cell.clamp_(0.0, self.field_top[a]).int().mul_(stride)
            if a:
                flat += c
            else:
                flat.copy_(c)
        hit = torch.zeros_like(start, dtype=torch.bool)
        t_out = start.clone()
        for _ in range(_T_PIECES):
            cx, cy, cz = real_state[:, 0], real_state[:, 1], real_state[:, 2]
            enter, end = real_state[:, 6], real_state[:, 7]
            field = self.field.index_select(0, int_state[:, 0])
            # The nearest plane (the first axis of equal ones).
            nearer = torch.minimum(cx, cy)
            leave = torch.minimum(nearer, cz)
            axis = torch.where(cz < nearer, 2, (cy < cx).long())[:, None]
            # Rounding can leave a piece of a ray empty, and an empty piece stops no ray.
            real = torch.minimum(leave, end) > enter
            done = (real & (field != 0)) | (enter >= end)
            if bool(done.any()):
                ended = done.nonzero().squeeze(1)
                rows = int_state[:, 4].index_select(0, ended).long()
                hit.index_copy_(0, rows, (real & (field < 0)).index_select(0, ended))
                f = field.index_select(0, ended)
                # A ray in a cell it may skip from skips: every point of the skip lies in a
                # cell at most ``field`` cells from the one it enters, whose face it enters on.
                f = f.clamp(min=0) * self.voxel_size
                t_out.index_copy_(0, rows, enter.index_select(0, ended) + f)
                going = (~done).nonzero().squeeze(1)
                if not going.numel():
                    return hit, t_out
                real_state, int_state = (
                    real_state.index_select(0, going),
                    int_state.index_select(0, going),
                )
                leave, axis = leave.index_select(0, going), axis.index_select(0, going)
            # Into the next cell, across the nearest plane.
            int_state[:, 0] += int_state[:, 1:4].gather(1, axis).squeeze(1)
            torch.maximum(leave, real_state[:, 6], out=real_state[:, 6])
            real_state[:, :3].scatter_add_(1, axis, real_state[:, 3:6].gather(1, axis))
        t_out.index_copy_(0, int_state[:, 4].long(), real_state[:, 6])
        return hit, t_out

    def _enter_stop(
        self, o: Tensor, d: Tensor, start: Tensor, end: Tensor
    ) -> tuple[Tensor, Tensor]:
        """For maps without a dense grid, one step of the exact voxel traversal of
        :func:`_first_stop` over ``_T_PIECES`` cells, looked up in the stopping cells' sorted
        keys: for rays ``o + t d`` (metres) from ``start`` (R,), whether one of those cells
        before ``end`` is a stopping cell and where the ray enters the first such (``start`` if
        it begins in one), else where the last of them ends."""
        size, n = self.voxel_size, _T_PIECES
        x = (o + start[:, None] * d) / size  # (R, 3) in cells
        step = torch.sign(d)
        cell0 = torch.where(d < 0, torch.ceil(x) - 1, torch.floor(x))
        k = torch.arange(n - 1, device=d.device, dtype=d.dtype)
        planes = (cell0 + (d > 0))[:, :, None] + step[:, :, None] * k  # (R, 3, n - 1)
        cross = start[:, None, None] + (planes - x[:, :, None]) * size / d[:, :, None]
        cross = torch.where(torch.isfinite(cross), cross, math.inf).view(-1, 3 * (n - 1))
        t, order = torch.sort(cross, dim=1)
        t, axis = t[:, : n - 1], torch.div(order[:, : n - 1], n - 1, rounding_mode="floor")
        # Pieces [start, t0], [t0, t1], ...: piece j's cell is the first one's moved a step
        # along the axes of the first j crossings.
        moves = torch.nn.functional.one_hot(axis, 3) * step.long()[:, None, :]
        cells = cell0.long()[:, None, :] + torch.cat(
            [torch.zeros_like(moves[:, :1]), moves.cumsum(dim=1)], dim=1
        )
        stop = _t_rows_of(self.stop_keys, _t_pack(cells)) >= 0
        enter = torch.maximum(torch.cat([start[:, None], t], dim=1), start[:, None])
        leave = torch.cat([t, torch.full_like(t[:, :1], math.inf)], dim=1)
        real = (torch.minimum(leave, end[:, None]) > enter) & (enter < end[:, None])
        stop &= real
        hit = stop.any(dim=1)
        j = stop.to(torch.uint8).argmax(dim=1, keepdim=True)
        return hit, torch.where(hit, enter.gather(1, j).squeeze(1), t[:, -1])

    def first_crossing(self, origin: Tensor, dirs: Tensor, max_range: float) -> Tensor:
        """:meth:`_Surface.first_crossing` (float32 (N,), NaN where none) of unit rays (N, 3)
        from ``origin`` (3,): the same windows of samples from the same first stopping cells;
        the traversal skips by the distance field instead of coarse cells."""
        dev = dirs.device
        out = torch.full((dirs.shape[0],), math.nan, device=dev)
        # Where each ray enters and leaves the box (slab test, one axis at a time; NaN, from a
        # ray in a face's plane, limits nothing).
        near = torch.zeros_like(dirs[:, 0])
        far = torch.full_like(near, max_range)
        for a in range(3):
            inv = 1.0 / dirs[:, a]
            t_lo, t_hi = (self.lo[a] - origin[a]) * inv, (self.hi[a] - origin[a]) * inv
            near = torch.fmax(near, torch.minimum(t_lo, t_hi))
            far = torch.fmin(far, torch.maximum(t_lo, t_hi))
        rays = (near < far).nonzero().squeeze(1)
        o = origin.float()
        # Each ray's state in one row, compacted at once: start, end, direction, index.
        state = torch.cat(
            [
                near.index_select(0, rays)[:, None],
                far.index_select(0, rays)[:, None],
                dirs.index_select(0, rays),
                rays[:, None].double(),
            ],
            dim=1,
        ).float()
        if self.field is not None:
            oc = o / self.voxel_size - self.field_lo  # in cells from the field's first cell
        while state.shape[0]:
            start, end, d = state[:, 0], state[:, 1], state[:, 2:5]
            if self.field is not None:
                # Skip ``skip`` voxels where the nearest stopping cell is farther, a few times.
                for _ in range(_T_SKIP_STEPS):
                    skip = self._field_at(oc, d, start)
                    start = torch.where(skip > 0, start + skip * self.voxel_size, start)
                # A ray in a stopping cell enters it where it is; one next to one walks.
                inside = ((skip < 0) & (start < end)).nonzero().squeeze(1)
                close = ((skip == 0) & (start < end)).nonzero().squeeze(1)
                walk = self._walk
            else:
                close = torch.arange(state.shape[0], device=dev)
                inside = close[:0]
                walk, oc = self._enter_stop, o
            win, t_in = inside, start.index_select(0, inside)
            if close.numel():
                hit, t_close = walk(
                    oc,
                    d.index_select(0, close),
                    start.index_select(0, close),
                    end.index_select(0, close),
                )
                start.index_copy_(0, close, t_close)
                hit = hit.nonzero().squeeze(1)
                win = torch.cat([win, close.index_select(0, hit)])
                t_in = torch.cat([t_in, t_close.index_select(0, hit)])
            found_rows = win[:0]
            if win.numel():
                t_last, found, t_cross = self._window(o, d, end, win, t_in)
                start.index_copy_(0, win, t_last)
                found_rows = win.index_select(0, found)
                rays = state[:, 5].index_select(0, found_rows).long()
                out.index_copy_(0, rays, t_cross)
            going = (start < end).index_fill_(0, found_rows, False)
            state[:, 0] = start
            state = state.index_select(0, going.nonzero().squeeze(1))
        return out

    def _window(
        self, o: Tensor, d: Tensor, end: Tensor, win: Tensor, t_in: Tensor
    ) -> tuple[Tensor, Tensor, Tensor]:
        """The window of samples half a voxel apart from where the rays ``win`` (W,) (of rays
        ``o + t d`` (R, 3) that end at ``end`` (R,)) enter a stopping cell, at ``t_in`` (W,):
        where the window's last sample lies (W,), the windows (F,) that hold a crossing (the
        TSDF turning from positive or unobserved to non-positive before ``end``) and where the
        first one lies (F,). The window's second half is sampled only where its first half
        holds no crossing."""
        step = 0.5 * self.voxel_size
        offsets = step * torch.arange(-1, _SURFACE_SAMPLES, device=d.device, dtype=torch.float32)
        t = t_in[:, None] + offsets
        dw, e = d.index_select(0, win), end.index_select(0, win)[:, None]
        f = self.sample(o, dw, t[:, :_T_FIRST])
        before, after = f[:, :-1], f[:, 1:]
        first = ((after <= 0) & ~(before <= 0) & (t[:, 1:_T_FIRST] <= e)).any(dim=1)
        rest = (~first & (t[:, _T_FIRST] <= e[:, 0])).nonzero().squeeze(1)
        f = torch.cat([f, torch.full_like(t[:, _T_FIRST:], math.nan)], dim=1)
        if rest.numel():
            later = self.sample(o, dw.index_select(0, rest), t.index_select(0, rest)[:, _T_FIRST:])
            f[:, _T_FIRST:].index_copy_(0, rest, later)
        before, after = f[:, :-1], f[:, 1:]
        enter = (after <= 0) & ~(before <= 0) & (t[:, 1:] <= e)
        found = enter.any(dim=1).nonzero().squeeze(1)
        enter, before, after = (
            enter.index_select(0, found),
            before.index_select(0, found),
            after.index_select(0, found),
        )
        j = enter.to(torch.uint8).argmax(dim=1, keepdim=True)
        b, a = before.gather(1, j).squeeze(1), after.gather(1, j).squeeze(1)
        t_cross = t.index_select(0, found)[:, 1:].gather(1, j).squeeze(1)
        return t[:, -1], found, t_cross + torch.where(b > 0, step * a / (b - a), 0.0)


def _grow(mask: Tensor, r: int) -> Tensor:
    """A 3D boolean grid of the cells within ``r`` cells (Chebyshev) of a true cell of
    ``mask``: along each axis in turn, the union of shifts by -s, 0 and +s for s = 1, 2, 4 ...
    (each doubling the reach, the last one what is left of ``r``)."""
    out = mask
    for axis in range(3):
        n, reach = out.shape[axis], 0
        while reach < min(r, n - 1):
            s = min(reach + 1, r - reach, n - 1 - reach)
            src, out = out, out.clone()
            out.narrow(axis, s, n - s).logical_or_(src.narrow(axis, 0, n - s))
            out.narrow(axis, 0, n - s).logical_or_(src.narrow(axis, s, n - s))
            reach += s
    return out


def _t_surface(voxel_map: VoxelSemanticMap) -> _TorchSurface | None:
    if voxel_map._surface is None and bool((voxel_map._tsdf <= 0).any().item()):
        voxel_map._surface = _TorchSurface(voxel_map)
    return voxel_map._surface if isinstance(voxel_map._surface, _TorchSurface) else None


def _raycast_torch(
    voxel_map: VoxelSemanticMap, pose: np.ndarray, intrinsics: Intrinsics
) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`VoxelSemanticMap.raycast` on the map's device."""
    h, w = intrinsics.height, intrinsics.width
    surface = _t_surface(voxel_map)
    if surface is None:
        return np.zeros((h, w), dtype=np.uint8), np.zeros((h, w), dtype=np.float32)
    origin, dirs, _ = _t_frame_rays(voxel_map, np.ones((h, w), dtype=bool), pose, intrinsics)
    norm = torch.sqrt((dirs * dirs).sum(dim=1))
    unit = dirs / norm[:, None]
    t = torch.cat(
        [
            surface.first_crossing(origin, unit[i : i + _T_RAY_CHUNK], voxel_map.config.max_range)
            for i in range(0, unit.shape[0], _T_RAY_CHUNK)
        ]
    )
    rays = torch.isfinite(t).nonzero().squeeze(1)
    hit_t = t[rays].double()
    scores = _t_scores_near(voxel_map, surface, origin + hit_t[:, None] * unit[rays])
    best, arg = scores.max(dim=1)  # the first of equal maxima, as numpy's argmax
    labels = torch.zeros(h * w, dtype=torch.uint8, device=dirs.device)
    depth = torch.zeros(h * w, dtype=torch.float32, device=dirs.device)
    labels[rays] = torch.where(best > 0, arg + 1, UNKNOWN).to(torch.uint8)
    depth[rays] = (hit_t / norm[rays]).float()
    return _as_numpy(labels.view(h, w)), _as_numpy(depth.view(h, w))


def _labels_at_depth_torch(
    voxel_map: VoxelSemanticMap, depth: np.ndarray, pose: np.ndarray, intrinsics: Intrinsics
) -> np.ndarray:
    """:meth:`VoxelSemanticMap.labels_at_depth` on the map's device."""
    depth = _check_depth(depth, intrinsics)
    valid = np.isfinite(depth) & (depth > 0)
    origin, dirs, mask = _t_frame_rays(voxel_map, valid, pose, intrinsics)
    keys = _t_surface_keys(voxel_map, depth, valid, dirs, origin)[0]
    # The voxels' own labels where they have scores (one arg-max per voxel, not per pixel) ...
    rows = _t_rows_of(voxel_map._keys, keys)
    labels = torch.zeros(keys.numel(), dtype=torch.int64, device=keys.device)
    hit = (rows >= 0).nonzero().squeeze(1)
    if hit.numel():
        best, arg = voxel_map._scores.max(dim=1)
        labels[hit] = torch.where(best > 0, arg + 1, UNKNOWN)[rows[hit]]
    # ... else those of their neighbours' summed scores, as :meth:`_scores_at`.
    missing = (rows < 0).nonzero().squeeze(1)
    if voxel_map.config.search_radius and missing.numel() and voxel_map.num_voxels:
        best, arg = _t_neighbour_scores(voxel_map, keys[missing]).max(dim=1)
        labels[missing] = torch.where(best > 0, arg + 1, UNKNOWN)
    out = torch.zeros(mask.numel(), dtype=torch.uint8, device=mask.device)
    out[mask] = labels.to(torch.uint8)
    return _as_numpy(out.view(valid.shape))


def _t_scores_near(voxel_map: VoxelSemanticMap, surface: _TorchSurface, points: Tensor) -> Tensor:
    """:meth:`VoxelSemanticMap._scores_near` on the map's device."""
    n, c = points.shape[0], voxel_map.config.num_classes
    if surface.rows is None or n == 0:
        return torch.zeros((n, c), device=points.device)
    base, weights = _t_trilinear(points, voxel_map.voxel_size)
    rows = surface.rows.cube(base)
    # The weighted sum of the rows of the corners with scores, as one bag of eight rows a point.
    scores = torch.nn.functional.embedding_bag(
        rows.clamp(min=0).long(),
        voxel_map._scores,
        per_sample_weights=torch.where(rows >= 0, weights, 0.0),
        mode="sum",
    )
    none = (~(scores.amax(dim=1) > 0)).nonzero().squeeze(1)
    if none.numel():
        cells = torch.floor(points[none] / voxel_map.voxel_size).long()
        scores[none] = _t_scores_at(voxel_map, _t_pack(cells))
    return scores


def _t_scores_at(voxel_map: VoxelSemanticMap, keys: Tensor) -> Tensor:
    """:meth:`VoxelSemanticMap._scores_at` on the map's device."""
    rows = _t_rows_of(voxel_map._keys, keys)
    c = voxel_map.config.num_classes
    scores = torch.zeros((keys.numel(), c), device=keys.device)
    hit = rows >= 0
    scores[hit] = voxel_map._scores[rows[hit]]
    r = voxel_map.config.search_radius
    missing = (~hit).nonzero().squeeze(1)
    if r == 0 or missing.numel() == 0 or voxel_map.num_voxels == 0:
        return scores
    scores[missing] = _t_neighbour_scores(voxel_map, keys[missing])
    return scores


def _t_neighbour_scores(voxel_map: VoxelSemanticMap, keys: Tensor) -> Tensor:
    """Summed scores (N, C) of the voxels within ``search_radius`` cells of the voxels
    ``keys`` (N,)."""
    offsets = torch.from_numpy(_cube_offsets(voxel_map.config.search_radius)).to(keys.device)
    cells = _t_unpack(keys)[:, None, :] + offsets
    rows = _t_rows_of(voxel_map._keys, _t_pack(cells)).view(-1, offsets.shape[0])
    # The sums as bags of rows, those without scores weighing nothing.
    return torch.nn.functional.embedding_bag(
        rows.clamp(min=0),
        voxel_map._scores,
        per_sample_weights=(rows >= 0).float(),
        mode="sum",
    )
