"""Segmentation networks loaded for inference, kept by checkpoint checksum (least recently used
out)."""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Any

import numpy as np

from server.artifacts import ArtifactStore


class ModelCache:
    def __init__(self, store: ArtifactStore, size: int, device: str | None):
        self.store = store
        self.size = max(1, size)
        self.device = device  # None: auto, CUDA when present (Settings.device)
        self._items: OrderedDict[str, tuple[Any, Any]] = OrderedDict()
        self._lock = threading.Lock()
        self._inference_lock = threading.Lock()

    def get(self, sha256: str) -> tuple[Any, Any]:
        """(network in eval mode, model card) of a stored checkpoint."""
        from csa_core.device import resolve_device
        from csa_core.seg import load_checkpoint

        with self._lock:
            if sha256 in self._items:
                self._items.move_to_end(sha256)
                return self._items[sha256]
        net, card = load_checkpoint(
            self.store.open_verified(sha256), device=resolve_device(self.device)
        )
        with self._lock:
            self._items[sha256] = (net, card)
            while len(self._items) > self.size:
                self._items.popitem(last=False)
        return net, card

    def predict(self, sha256: str, rgb: np.ndarray) -> np.ndarray:
        """NYU40 ids (H, W) of an (H, W, 3) uint8 RGB image by a stored checkpoint, at its
        model card's input size; one prediction at a time (see :attr:`inference_lock`)."""
        from csa_core.device import resolve_device
        from csa_core.seg import predict_labels

        net, card = self.get(sha256)
        with self._inference_lock:
            return predict_labels(
                net,
                rgb,
                device=resolve_device(self.device),
                size=tuple(card.input_size) if card.input_size else None,
            )

    @property
    def inference_lock(self) -> threading.Lock:
        """One prediction at a time: networks are shared and the CPU is small."""
        return self._inference_lock
