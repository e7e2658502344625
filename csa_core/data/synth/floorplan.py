"""Top-down occupancy of a room's floor and the clearance map derived from it.

Used by the layout (refuse furniture that would leave too little room to walk) and by
the camera path (stay in free space).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

CELL_M = 0.05  # grid resolution
CLEARANCE_M = 0.5  # distance the camera keeps from walls and floor-standing furniture


class FloorGrid:
    """Occupancy of the floor of a ``width`` x ``depth`` room on cells of ``CELL_M``."""

    def __init__(self, width: float, depth: float):
        self.width, self.depth = width, depth
        self.nx, self.ny = int(math.ceil(width / CELL_M)), int(math.ceil(depth / CELL_M))
        xs = (np.arange(self.nx) + 0.5) * width / self.nx
        ys = (np.arange(self.ny) + 0.5) * depth / self.ny
        self.gx, self.gy = np.meshgrid(xs, ys)
        self.occupied = np.zeros((self.ny, self.nx), dtype=bool)

    def footprint(self, centre: np.ndarray, half: np.ndarray, yaw: float) -> np.ndarray:
        """Cells covered by a yaw-rotated box footprint (grown by one cell)."""
        c, s = math.cos(yaw), math.sin(yaw)
        qx, qy = self.gx - centre[0], self.gy - centre[1]
        lx, ly = c * qx + s * qy, -s * qx + c * qy
        return (np.abs(lx) <= half[0] + CELL_M) & (np.abs(ly) <= half[1] + CELL_M)

    def clearance(self, occupied: np.ndarray | None = None) -> np.ndarray:
        """Distance in metres from each cell to the nearest wall or occupied cell."""
        occ = self.occupied if occupied is None else occupied
        free = np.zeros((self.ny + 2, self.nx + 2), dtype=np.uint8)
        free[1:-1, 1:-1] = ~occ
        return cv2.distanceTransform(free, cv2.DIST_L2, 5)[1:-1, 1:-1] * CELL_M

    def walkable(self, occupied: np.ndarray | None = None) -> np.ndarray:
        """Cells of the largest connected region where the camera keeps its clearance."""
        ok = self.clearance(occupied) >= CLEARANCE_M
        if not ok.any():
            return ok
        n, lab = cv2.connectedComponents(ok.astype(np.uint8), connectivity=8)
        sizes = np.bincount(lab[ok].ravel(), minlength=n)
        return lab == int(np.argmax(sizes))

    def cell_of(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Row and column of the cells containing points (m, 2)."""
        i = np.clip((pts[:, 1] / self.depth * self.ny).astype(int), 0, self.ny - 1)
        j = np.clip((pts[:, 0] / self.width * self.nx).astype(int), 0, self.nx - 1)
        return i, j
