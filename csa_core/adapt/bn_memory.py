"""BatchNorm statistics of every adapted scene, pooled so one network serves them all.

Each step ends with AdaBN on the current scene's camera images, so after step i the network
normalises with scene i's statistics only. A network trained from scratch is very sensitive
to them: in the demo's first continual run (3 synthetic offices) scene 0 scored 30.8% mIoU
right after its step and 21.9% after step 2, and the mean over the scenes after the last
step fell below the pre-trained network's. The statistics are the suspect: AdaBN alone (no
training) moved scene 0 from 22.0% to 31.9%. Keeping each scene's statistics (a
few KB per scene, beside its NeRF) and running with their pooled mixture treats every
adapted scene alike, much as AdaBN over the union of their images would (exactly so for the
first BatchNorm layer; deeper ones saw per-scene normalised inputs), without storing images.

The mixture gives each scene equal weight: mean = avg_k(mean_k) and
var = avg_k(var_k + mean_k^2) - mean^2 (the variance of the pooled distribution).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from csa_core.seg.adabn import batchnorm_layers


class BatchNormMemory:
    """Per-scene BatchNorm running statistics, and their pooled mixture."""

    def __init__(self) -> None:
        self.scenes: dict[str, list[tuple[Tensor, Tensor]]] = {}

    def add(self, scene: str, model: nn.Module) -> None:
        """Record ``model``'s current statistics as ``scene``'s (replacing an earlier record)."""
        self.scenes[scene] = [
            (bn.running_mean.detach().clone(), bn.running_var.detach().clone())  # type: ignore[union-attr]
            for bn in batchnorm_layers(model)
        ]

    def nbytes(self) -> int:
        return sum(
            m.numel() * m.element_size() + v.numel() * v.element_size()
            for s in self.scenes.values()
            for m, v in s
        )

    @torch.no_grad()
    def apply(self, model: nn.Module) -> None:
        """Set ``model``'s statistics to the equal-weight mixture of the recorded scenes'."""
        if not self.scenes:
            return
        layers = batchnorm_layers(model)
        records = list(self.scenes.values())
        for k, bn in enumerate(layers):
            means = torch.stack([r[k][0] for r in records])
            variances = torch.stack([r[k][1] for r in records])
            mean = means.mean(dim=0)
            var = (variances + means.square()).mean(dim=0) - mean.square()
            bn.running_mean.copy_(mean)  # type: ignore[union-attr]
            bn.running_var.copy_(var.clamp_min(0.0))  # type: ignore[union-attr]
