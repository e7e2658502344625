"""Keep training a fitted Semantic-NeRF on new labels: the 2D -> 3D half of joint training.

``csa_core.nerf.fit_semantic_nerf`` always starts from a fresh field; joint training needs to
continue from the pre-fit with the network's latest predictions as semantic targets.
:class:`NerfLabelTrainer` does that with the fit's own loop (:class:`~csa_core.nerf.trainer.
NerfTrainer`: the same sampler, losses, free-space term and weight-decay groups), at a
constant learning rate below the fit's start. A NeRF fitted with per-frame colour
corrections (``appearance="affine"``) keeps them: each ray's colour is compared through its
frame's correction, and the corrections train on with the field.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch

from csa_core.data.scene import Frame, Scene
from csa_core.nerf.model import SemanticNerf
from csa_core.nerf.rays import RayBank
from csa_core.nerf.trainer import NerfTrainer


class NerfLabelTrainer:
    """Adam steps on a fitted NeRF against the training frames' colour and depth and a
    replaceable set of labels (one (H, W) NYU40 map per frame, 0 = ignored)."""

    def __init__(
        self,
        nerf: SemanticNerf,
        scene: Scene,
        frames: Sequence[Frame] | None = None,
        rays_per_step: int | None = None,
        lr: float | None = None,
        seed: int = 0,
    ):
        self.nerf = nerf
        self.frames = list(scene.train_frames if frames is None else frames)
        o = nerf.config.optim
        self.rays = RayBank(
            self.frames,
            scene.intrinsics,
            nerf.device,
            frame_rows=_appearance_index(nerf, self.frames),
        )
        # The fit's final rate, kept constant (below its start where the preset decays it; the
        # same fixed rate in ``cpu`` and ``paper``): the field is already fitted, only the
        # labels moved. The free-space term applies from the first step.
        self.trainer = NerfTrainer(
            nerf,
            self.rays,
            schedule_steps=1,
            lr=lr or o.lr * o.final_lr_fraction,
            final_lr_fraction=1.0,
            rays_per_step=rays_per_step,
            seed=seed,
        )
        self.rays_per_step = self.trainer.rays_per_step

    @property
    def has_depth(self) -> bool:
        return self.rays.has_depth

    @property
    def steps_done(self) -> int:
        return self.trainer.steps_done

    @property
    def labels(self) -> torch.Tensor | None:
        return self.rays.labels

    def set_labels(self, labels: Mapping[str, np.ndarray]) -> None:
        """New semantic targets, ``{frame name: (H, W) uint8 NYU40}`` for every training frame."""
        self.rays.set_labels(labels)

    def train_semantics(self, steps: int, lr: float | None = None) -> float:
        """``steps`` Adam steps on the semantic parameters alone (the semantic table and MLP),
        geometry and colour frozen; returns the last loss.

        Semantics never shape geometry, so they can be trained on after the fit at the cost
        of about one forward pass of the density per step: the fit's semantics lag far behind
        its colours.
        """
        if self.rays.labels is None:
            raise ValueError("train_semantics: call set_labels first")
        return self.trainer.semantic_steps(steps, lr=lr)

    def train(self, steps: int) -> dict[str, float]:
        """``steps`` Adam steps; returns the last step's loss terms. Re-estimates the occupancy
        grid afterwards so rendering sees the updated density."""
        terms = self.trainer.train(steps)
        if steps > 0:
            self.nerf.update_occupancy(decay=0.0, generator=self.trainer.generator)
        return terms


def _appearance_index(nerf: SemanticNerf, frames: Sequence[Frame]) -> torch.Tensor | None:
    """Each frame's row in the NeRF's colour corrections, (F,) on the NeRF's device; ``None``
    when the NeRF has none. Raises ``ValueError`` naming a frame the NeRF was not fitted on."""
    if nerf.appearance is None:
        return None
    rows = {name: i for i, name in enumerate(nerf.info.train_frames)}
    missing = [f.name for f in frames if f.name not in rows]
    if missing:
        raise ValueError(
            f"NeRF of scene {nerf.info.name} has per-frame colour corrections but was not fitted "
            f"on frame(s) {', '.join(missing[:5])}: no correction to train them with"
        )
    return torch.tensor([rows[f.name] for f in frames], dtype=torch.long, device=nerf.device)
