"""``SemanticNerf``: a fitted scene model, everything needed to render it without the scene.

It bundles the field, the scene box (normalisation), the occupancy grid, the config, the
camera and the training poses (so novel views can be rendered from a checkpoint alone).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor, nn

from csa_core.data.camera import Intrinsics
from csa_core.data.nyu40 import CLASS_NAMES
from csa_core.nerf.appearance import FrameAppearance
from csa_core.nerf.config import NerfConfig
from csa_core.nerf.field import SemanticField
from csa_core.nerf.normalization import SceneBox
from csa_core.nerf.rendering import (
    RaySamples,
    accumulate_along_rays,
    normalized_class_probabilities,
    render_weights,
)
from csa_core.nerf.samplers import (
    OccupancyGrid,
    sample_depth_guided,
    sample_reference,
    sample_uniform,
)


@dataclass
class SceneInfo:
    """What the model remembers about the scene it was fitted to."""

    name: str
    intrinsics: Intrinsics
    train_frames: list[str]
    train_poses: np.ndarray  # (F, 4, 4) camera-to-world, metres
    label_folder: str | None = None
    classes: list[str] = field(
        default_factory=lambda: list(CLASS_NAMES[1:])
    )  # channel k = NYU40 id k + 1

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "intrinsics": self.intrinsics.to_dict(),
            "train_frames": list(self.train_frames),
            "label_folder": self.label_folder,
            "classes": list(self.classes),
        }

    @classmethod
    def from_dict(cls, d: dict, train_poses: np.ndarray) -> SceneInfo:
        return cls(
            name=str(d["name"]),
            intrinsics=Intrinsics.from_dict(d["intrinsics"]),
            train_frames=[str(n) for n in d["train_frames"]],
            train_poses=np.asarray(train_poses, dtype=np.float64),
            label_folder=d.get("label_folder"),
            classes=[str(c) for c in d["classes"]],
        )


class SemanticNerf(nn.Module):
    """A Semantic-NeRF of one scene: ``render_rays`` turns metric world rays into colour, depth
    (metric z-depth for unit-z rays) and class probabilities."""

    def __init__(
        self,
        config: NerfConfig,
        box: SceneBox,
        info: SceneInfo,
        generator: torch.Generator | None = None,
    ):
        super().__init__()
        self.config = config
        self.box = box
        self.info = info
        self.field = SemanticField(config.field, generator=generator)
        self.appearance = (
            FrameAppearance(len(info.train_frames)) if config.appearance == "affine" else None
        )
        s = config.sampler
        self.grid = OccupancyGrid(s.occupancy_resolution, s.occupancy_threshold, s.march_steps)

    @property
    def device(self) -> torch.device:
        return self.field.encoding.table.device

    def density_fn(self, points: Tensor) -> Tensor:
        """Density at world points (N, 3)."""
        return self.field.density(self.box.to_unit(points))[0]

    def sample(
        self,
        origins: Tensor,
        dirs: Tensor,
        sampler: str,
        depth: Tensor | None = None,
        stratified: bool = False,
        generator: torch.Generator | None = None,
    ) -> RaySamples:
        """Samples along rays with the named sampler (``reference``, ``depth``, ``occupancy``, ``uniform``)."""
        s = self.config.sampler
        t_near, t_far = self.box.ray_interval(origins, dirs, s.near)
        if sampler == "depth":
            if depth is None:
                depth = torch.zeros_like(t_near)
            return sample_depth_guided(
                t_near,
                t_far,
                depth,
                s.band_samples,
                s.spread_samples,
                s.depth_band,
                s.depth_band_fraction,
                stratified,
                generator,
            )
        if sampler == "reference":
            with torch.no_grad():
                return sample_reference(
                    origins,
                    dirs,
                    t_near,
                    t_far,
                    self.density_fn,
                    s.uniform_samples,
                    s.importance_samples,
                    stratified,
                    generator,
                )
        if sampler == "uniform":
            return sample_uniform(
                t_near, t_far, s.uniform_samples + s.importance_samples, stratified, generator
            )
        if sampler == "occupancy":
            fn = None if self.training else self.density_fn  # early ray termination when rendering
            return self.grid.sampling(
                self.box,
                origins,
                dirs,
                t_near,
                t_far,
                stratified,
                generator,
                max_samples=s.max_render_samples,
                density_fn=fn,
            )
        raise ValueError(
            f"unknown sampler {sampler!r} (expected reference, depth, occupancy or uniform)"
        )

    def render_samples(
        self,
        origins: Tensor,
        dirs: Tensor,
        samples: RaySamples,
        semantics: bool = True,
        appearance: Tensor | int | None = None,
    ) -> dict[str, Tensor]:
        """Evaluate the field at ``samples`` and composite: ``rgb`` (R, 3), ``depth`` (R,),
        ``opacity`` (R,), and with ``semantics`` the class distribution ``semantics`` (R, C).
        ``appearance``: training frame index (one, or (R,) per ray) whose colour correction
        applies to ``rgb``; ``None`` (or a model without corrections): the average appearance."""
        ri = samples.ray_indices
        t = samples.t_mids
        pts = origins[ri] + dirs[ri] * t[:, None]
        view = torch.nn.functional.normalize(dirs, dim=-1)[ri]
        out = self.field(self.box.to_unit(pts), view, semantics=semantics)
        weights, _, _ = render_weights(out["sigma"], samples, dirs.norm(dim=-1))
        rgb = accumulate_along_rays(weights, out["rgb"], samples)
        if self.appearance is not None:
            rgb = self.appearance(rgb, appearance)
        result = {
            "rgb": rgb,
            "depth": accumulate_along_rays(weights, t[:, None], samples).squeeze(-1),
            "opacity": accumulate_along_rays(weights, None, samples).squeeze(-1),
            "weights": weights,
        }
        if semantics:
            result["semantics"] = normalized_class_probabilities(
                weights, out["semantic_logits"], samples
            )
        return result

    def render_rays(
        self,
        origins: Tensor,
        dirs: Tensor,
        sampler: str | None = None,
        depth: Tensor | None = None,
        semantics: bool = True,
        chunk: int | None = None,
        appearance: int | None = None,
    ) -> dict[str, Tensor]:
        """Render rays for inference (no gradients), in chunks; ``sampler`` defaults to the config's,
        ``appearance`` is a training frame whose colour correction applies (``None``: average)."""
        sampler = sampler or self.config.sampler.render
        chunk = chunk or self.config.render_chunk
        parts: list[dict[str, Tensor]] = []
        with torch.no_grad():
            for i in range(0, origins.shape[0], chunk):
                o, d = origins[i : i + chunk], dirs[i : i + chunk]
                dd = depth[i : i + chunk] if depth is not None else None
                samples = self.sample(o, d, sampler, depth=dd)
                parts.append(
                    self.render_samples(o, d, samples, semantics=semantics, appearance=appearance)
                )
        if not parts:
            return {}
        return {k: torch.cat([p[k] for p in parts]) for k in parts[0] if k != "weights"}

    @torch.no_grad()
    def update_occupancy(
        self, decay: float = 0.0, passes: int = 2, generator: torch.Generator | None = None
    ) -> float:
        """Re-estimate the occupancy grid from the field (``decay=0``: from scratch), then empty the
        cells that no training camera sees (the field is unconstrained there); returns the occupied fraction."""
        for i in range(passes):
            self.grid.update(
                self.box, self.density_fn, decay=decay if i == 0 else 1.0, generator=generator
            )
        self.grid.keep_visible(self.box, self.seen_by_training_cameras)
        return float(self.grid.occupied.float().mean())

    def seen_by_training_cameras(self, points: Tensor, margin: float = 0.1) -> Tensor:
        """Whether world points (N, 3) project inside (with a ``margin`` fraction) the image of
        at least one training camera, in front of it."""
        intr = self.info.intrinsics
        poses = torch.as_tensor(self.info.train_poses, dtype=torch.float32, device=points.device)
        seen = torch.zeros(points.shape[0], dtype=torch.bool, device=points.device)
        mw, mh = margin * intr.width, margin * intr.height
        for pose in poses:
            p = (points - pose[:3, 3]) @ pose[:3, :3]  # world -> camera
            z = p[:, 2]
            u = p[:, 0] / z.clamp_min(1e-6) * intr.fx + intr.cx
            v = p[:, 1] / z.clamp_min(1e-6) * intr.fy + intr.cy
            seen |= (
                (z > self.config.sampler.near)
                & (u > -mw)
                & (u < intr.width + mw)
                & (v > -mh)
                & (v < intr.height + mh)
            )
        return seen
