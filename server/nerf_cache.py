"""Scene NeRFs loaded from the memory bank for rendering, kept by checkpoint id (LRU)."""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Any

import numpy as np

from csa_core.data.camera import Intrinsics
from server.artifacts import ArtifactStore


class NerfCache:
    def __init__(self, store: ArtifactStore, size: int, device: str | None):
        self.store = store
        self.size = max(1, size)
        self.device = device  # None: auto, CUDA when present (Settings.device)
        self._items: OrderedDict[int, Any] = OrderedDict()
        self._lock = threading.Lock()
        self._render_lock = threading.Lock()

    def get(self, nerf_id: int, files: dict[str, str]) -> Any:
        from csa_core.device import resolve_device
        from csa_core.nerf.checkpoint import load_checkpoint

        with self._lock:
            if nerf_id in self._items:
                self._items.move_to_end(nerf_id)
                return self._items[nerf_id]
        (_, sha), *rest = files.items()
        if rest:
            raise ValueError(f"NeRF {nerf_id}: expected one checkpoint file, found {len(files)}")
        nerf = load_checkpoint(self.store.open_verified(sha), device=resolve_device(self.device))
        with self._lock:
            self._items[nerf_id] = nerf
            while len(self._items) > self.size:
                self._items.popitem(last=False)
        return nerf

    def render(self, nerf_id: int, files: dict[str, str], pose: np.ndarray, intrinsics: Intrinsics) -> dict[str, np.ndarray]:
        """``color`` (H, W, 3) uint8 RGB, ``depth`` (H, W) metres, ``labels`` (H, W) uint8 NYU40 ids."""
        from csa_core.nerf.render import render_image

        nerf = self.get(nerf_id, files)
        with self._render_lock:
            view = render_image(nerf, pose, intrinsics, semantics=True)
        return {"color": view.color, "depth": view.depth, "labels": view.labels}
