"""Keep training a fitted Semantic-NeRF on new labels: the 2D -> 3D half of joint training.

``csa_core.nerf.fit_semantic_nerf`` always starts from a fresh field; joint training needs to
continue from the pre-fit with the network's latest predictions as semantic targets.
:class:`NerfLabelTrainer` does that with the NeRF's public sampling and rendering calls and
the fit's loss (colour, depth and semantics, DESIGN.md "The method" step 2). A NeRF fitted
with per-frame colour corrections (``appearance="affine"``) keeps them: each ray's colour is
compared through its frame's correction, and the corrections train on with the field.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch

from csa_core.data.scene import Frame, Scene
from csa_core.nerf.fit import camera_directions
from csa_core.nerf.losses import semantic_loss, total_loss
from csa_core.nerf.model import SemanticNerf
from csa_core.nerf.rendering import normalized_class_probabilities, render_weights


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
        cfg = nerf.config
        self.rays_per_step = rays_per_step or cfg.optim.rays_per_step
        dev = nerf.device
        intr = scene.intrinsics
        self.hw = intr.width * intr.height
        self.dirs_cam = camera_directions(intr, dev)
        poses = torch.as_tensor(
            np.stack([np.asarray(f.pose, dtype=np.float64) for f in self.frames]),
            dtype=torch.float32,
            device=dev,
        )
        self.rot, self.origin = poses[:, :3, :3], poses[:, :3, 3]
        self.rgb = torch.as_tensor(
            np.stack([f.color for f in self.frames]).reshape(-1, 3), device=dev
        )
        depth = [
            f.depth if f.depth is not None else np.zeros(f.color.shape[:2], np.float32)
            for f in self.frames
        ]
        self.depth = torch.as_tensor(np.stack(depth).reshape(-1).astype(np.float32), device=dev)
        self.has_depth = bool((self.depth > 0).any())
        self.appearance_index = _appearance_index(nerf, self.frames)
        self.labels: torch.Tensor | None = None
        # The field and, when fitted with them, the per-frame colour corrections. A lower rate
        # than the fit's start: the field is already fitted, only the labels moved.
        self.optimizer = torch.optim.Adam(
            nerf.parameters(),
            lr=lr or cfg.optim.lr * cfg.optim.final_lr_fraction,
            betas=cfg.optim.betas,
            eps=cfg.optim.eps,
        )
        self.generator = torch.Generator(device=dev).manual_seed(seed)
        self.steps_done = 0

    def set_labels(self, labels: Mapping[str, np.ndarray]) -> None:
        """New semantic targets, ``{frame name: (H, W) uint8 NYU40}`` for every training frame."""
        stack = np.stack([np.asarray(labels[f.name], dtype=np.uint8) for f in self.frames])
        self.labels = torch.as_tensor(stack.reshape(-1), device=self.nerf.device)

    def _rays(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        ids = torch.randint(
            0,
            self.rgb.shape[0],
            (self.rays_per_step,),
            device=self.nerf.device,
            generator=self.generator,
        )
        cam, pix = ids // self.hw, ids % self.hw
        dirs = torch.einsum("nij,nj->ni", self.rot[cam], self.dirs_cam[pix])
        return ids, self.origin[cam], dirs

    def train_semantics(self, steps: int, lr: float | None = None) -> float:
        """``steps`` Adam steps on the semantic parameters alone (every field parameter whose
        name starts with ``semantic``), geometry and colour frozen; returns the last loss.

        Semantics never shape geometry, so they can be trained on after the fit at the cost
        of about one forward pass per step: the fit's semantics lag far behind its colours.
        """
        if self.labels is None:
            raise ValueError("train_semantics: call set_labels first")
        field = self.nerf.field
        params = [p for n, p in field.named_parameters() if n.startswith("semantic")]
        opt = torch.optim.Adam(params, lr=lr or self.nerf.config.optim.lr)
        sampler = "depth" if self.has_depth else "reference"
        value = float("nan")
        for _ in range(steps):
            ids, origins, dirs = self._rays()
            with torch.no_grad():
                samples = self.nerf.sample(
                    origins, dirs, sampler, depth=self.depth[ids], generator=self.generator
                )
                t = samples.t_mids
                ri = samples.ray_indices
                x = self.nerf.box.to_unit(origins[ri] + dirs[ri] * t[:, None])
                sigma, _ = field.density(x)
                weights, _, _ = render_weights(sigma, samples, dirs.norm(dim=-1))
            view = torch.nn.functional.normalize(dirs, dim=-1)[ri]
            logits = field(x, view, semantics=True)["semantic_logits"]
            probs = normalized_class_probabilities(weights, logits, samples)
            loss = semantic_loss(probs, self.labels[ids])
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            value = float(loss.detach())
        return value

    def train(self, steps: int) -> dict[str, float]:
        """``steps`` Adam steps; returns the last step's loss terms. Re-estimates the occupancy
        grid afterwards so rendering sees the updated density."""
        sampler = "depth" if self.has_depth else "reference"
        terms: dict[str, float] = {}
        self.nerf.train()
        for _ in range(steps):
            ids, origins, dirs = self._rays()
            target = {"rgb": self.rgb[ids].float() / 255.0, "depth": self.depth[ids]}
            if self.labels is not None:
                target["labels"] = self.labels[ids]
            samples = self.nerf.sample(
                origins,
                dirs,
                sampler,
                depth=target["depth"],
                stratified=True,
                generator=self.generator,
            )
            out = self.nerf.render_samples(
                origins,
                dirs,
                samples,
                semantics=self.labels is not None,
                appearance=None
                if self.appearance_index is None
                else self.appearance_index[ids // self.hw],
            )
            loss = total_loss(out, target, self.nerf.config.loss)
            self.optimizer.zero_grad(set_to_none=True)
            loss["loss"].backward()
            self.optimizer.step()
            self.steps_done += 1
            terms = {k: float(v.detach()) for k, v in loss.items()}
        self.nerf.eval()
        if steps > 0:
            self.nerf.update_occupancy(decay=0.0, generator=self.generator)
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
