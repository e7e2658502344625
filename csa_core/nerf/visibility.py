"""Which surfaces the training views measured: a bit grid over the scene box.

The voxel map (``csa_core/adapt/baselines/voxel_map.py``) answers "unknown" where no training
view measured a surface; a NeRF answers everywhere, and on a surface no training view saw
its answer is a guess (the field's labels there come from whatever lies near). Scored by
mIoU, a wrong guess is a false positive of some class while "unknown" is only a miss, so a
fuser that guesses is penalised twice where the map abstains (benchmarks/results/fusion.md
"Unseen surfaces: cells the training depth measured").

:class:`ObservedCells` marks the cells of the box that contain a training view's measured
surface point, widened by ``dilate`` cells (the measured points of one surface scatter with
the sensor's noise); ``NerfConfig.render_unseen_unknown`` then labels a pixel unknown where
its surface point falls in no marked cell (``csa_core/nerf/render.py``, ``seen_surface``).
Unlike the training cameras' frusta (the test of models without cells, the default), it
knows occlusion: the back of a cabinet inside every frustum is unseen if no view measured
it. Built only with ``NerfConfig.observed_resolution`` > 0 (128 in the ``fast`` preset): on
walks whose last views look at surfaces the first never measured, it took the held-out views
above the map (benchmarks/results/fusion.md "Unseen surfaces: cells the training depth
measured").
"""

from __future__ import annotations

from collections.abc import Iterable

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from csa_core.nerf.normalization import SceneBox


def cell_index(u: Tensor, resolution: int) -> Tensor:
    """Flat index of the cell of ``resolution``^3 holding each unit-cube point (..., 3);
    -1 outside the cube."""
    r = resolution
    inside = ((u >= 0) & (u < 1)).all(dim=-1)
    c = (u.clamp(0, 1 - 1e-6) * r).long()
    flat = (c[..., 0] * r + c[..., 1]) * r + c[..., 2]
    return torch.where(inside, flat, torch.full_like(flat, -1))


class ObservedCells(nn.Module):
    """Cells of the scene box (``resolution`` per axis) where a training view measured a
    surface. Empty until :meth:`mark` is called; :attr:`marked` says whether it was."""

    def __init__(self, resolution: int):
        super().__init__()
        if resolution < 1:
            raise ValueError(f"ObservedCells: resolution must be >= 1, got {resolution}")
        self.resolution = resolution
        self.register_buffer("cells", torch.zeros((resolution,) * 3, dtype=torch.bool))

    @property
    def marked(self) -> bool:
        return bool(self.cells.any())

    @torch.no_grad()
    def mark(self, box: SceneBox, points: Tensor | Iterable[Tensor], dilate: int = 1) -> None:
        """Mark the cells holding world ``points`` (N, 3), or every tensor of an iterable of
        them, and those within ``dilate`` cells of them (a cube of side ``2 * dilate + 1``);
        points outside the box are ignored."""
        hit = torch.zeros_like(self.cells)
        for part in [points] if isinstance(points, Tensor) else points:
            idx = cell_index(box.to_unit(part.to(self.cells.device)), self.resolution)
            hit.view(-1)[idx[idx >= 0]] = True
        if dilate > 0:
            k = 2 * dilate + 1
            hit = F.max_pool3d(hit[None, None].float(), k, stride=1, padding=dilate)[0, 0] > 0
        self.cells |= hit

    def contains(self, box: SceneBox, points: Tensor) -> Tensor:
        """Whether each world point (N, 3) lies in a marked cell, (N,) bool."""
        idx = cell_index(box.to_unit(points), self.resolution)
        out = torch.zeros(points.shape[0], dtype=torch.bool, device=points.device)
        ok = idx >= 0
        out[ok] = self.cells.view(-1)[idx[ok]]
        return out
