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
from csa_core.nerf.hash_encoding import INFERENCE_BLOCK
from csa_core.nerf.losses import band_consistency_loss, free_space_loss, total_loss
from csa_core.nerf.normalization import SceneBox
from csa_core.nerf.rendering import (
    RaySamples,
    accumulate_along_rays,
    class_distribution,
    render_weights,
)
from csa_core.nerf.samplers import (
    DensityFn,
    DepthGuidedSampler,
    FeatureDensityFn,
    GridSurfaceEstimate,
    OccupancyGrid,
    OccupancySampler,
    RaySampler,
    ReferenceSampler,
    UniformSampler,
)
from csa_core.nerf.visibility import ObservedCells


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


# Below this opacity a rendered ray holds no surface worth a label: labels come from the
# semantic head at its measured surface point (``SemanticNerf._surface_labels``).
EMPTY_RAY_OPACITY = 1e-6


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
        # Surfaces the training views measured (visibility.py), for the unseen test.
        self.observed = (
            ObservedCells(config.observed_resolution) if config.observed_resolution else None
        )

    @property
    def device(self) -> torch.device:
        return self.field.encoding.table.device

    def density_fn(self, points: Tensor) -> Tensor:
        """Density at world points (N, 3)."""
        return self.field.density(self.box.to_unit(points))[0]

    # -- samplers ---------------------------------------------------------------------------

    def make_sampler(self, kind: str, training: bool = False) -> RaySampler:
        """The sampler object of a config name: ``reference``, ``uniform``, ``depth`` (the
        training layout: band and spread samples) or ``occupancy`` (marching this model's grid;
        pruned by density unless ``training``)."""
        s = self.config.sampler
        if kind == "reference":
            return ReferenceSampler(s.uniform_samples, s.importance_samples)
        if kind == "uniform":
            return UniformSampler(s.uniform_samples + s.importance_samples)
        if kind == "depth":
            return DepthGuidedSampler(
                s.band_samples, s.spread_samples, s.depth_band, s.depth_band_fraction
            )
        if kind == "occupancy":
            steps = (
                s.march_steps if training or s.render_march_steps is None else s.render_march_steps
            )
            if steps < 1:
                raise ValueError(f"sampler.render_march_steps must be at least 1, got {steps}")
            return OccupancySampler(
                self.grid,
                self.box,
                s.max_render_samples,
                update_every=s.occupancy_update_every,
                prune=not training,
                step=self.box.diagonal / steps,
                early_stop_eps=s.render_early_stop,
                min_weight=s.render_min_weight,
            )
        raise ValueError(
            f"unknown sampler {kind!r} (expected reference, depth, occupancy or uniform)"
        )

    def train_sampler(self, has_depth: bool = True) -> RaySampler:
        """The config's training sampler; depth-guided falls back to ``reference`` without depth."""
        kind = self.config.sampler.train
        if kind == "depth" and not has_depth:
            kind = "reference"
        return self.make_sampler(kind, training=True)

    def render_sampler(
        self,
        with_depth: bool = False,
        hole_estimate: bool | None = None,
        band_samples: int | None = None,
    ) -> RaySampler:
        """The config's render sampler; for views ``with_depth`` and ``render_depth_guided``,
        ``band_samples`` (default: the config's ``render_band_samples``) samples in the band
        around the measured depth, and for rays without one in the band around an estimated
        depth where ``hole_estimate`` (default: the config's ``render_hole_estimate``) finds a
        surface, the render sampler for the rest."""
        s = self.config.sampler
        fallback = self.make_sampler(s.render)
        if with_depth and s.render_depth_guided:
            if hole_estimate is None:
                hole_estimate = s.render_hole_estimate
            estimate = (
                GridSurfaceEstimate(self.grid, self.box, step_cells=s.render_estimate_step)
                if hole_estimate
                else None
            )
            return DepthGuidedSampler(
                s.render_band_samples if band_samples is None else band_samples,
                0,
                s.depth_band,
                s.depth_band_fraction,
                fallback=fallback,
                estimate=estimate,
                estimate_band_scale=s.render_estimate_band_scale,
            )
        return fallback

    def sample(
        self,
        origins: Tensor,
        dirs: Tensor,
        sampler: RaySampler | str,
        depth: Tensor | None = None,
        stratified: bool = False,
        generator: torch.Generator | None = None,
        density_fn: DensityFn | FeatureDensityFn | None = None,
    ) -> RaySamples:
        """Samples along rays inside the scene box with ``sampler`` (an object, or a config
        name for :meth:`make_sampler`). ``density_fn``: what the sampler evaluates (default
        :meth:`density_fn`; :meth:`render_rays` gives the march one that keeps features)."""
        if isinstance(sampler, str):
            sampler = self.make_sampler(sampler, training=self.training)
        t_near, t_far = self.box.ray_interval(origins, dirs, self.config.sampler.near)
        return sampler.sampling(
            origins,
            dirs,
            t_near,
            t_far,
            depth=depth,
            density_fn=density_fn or self.density_fn,
            stratified=stratified,
            generator=generator,
        )

    # -- rendering --------------------------------------------------------------------------

    def render_samples(
        self,
        origins: Tensor,
        dirs: Tensor,
        samples: RaySamples,
        semantics: bool = True,
        appearance: Tensor | int | None = None,
        color: bool = True,
    ) -> dict[str, Tensor]:
        """Evaluate the field at ``samples`` and composite: ``rgb`` (R, 3) (with ``color``),
        ``depth`` (R,), ``opacity`` (R,), ``weights`` (S,), and with ``semantics`` the class
        distribution ``semantics`` (R, C). ``appearance``: training frame index (one, or (R,)
        per ray) whose colour correction applies to ``rgb``; ``None`` (or a model without
        corrections): the average appearance."""
        ri = samples.ray_indices
        t = samples.t_mids
        pts = origins[ri] + dirs[ri] * t[:, None]
        view = torch.nn.functional.normalize(dirs, dim=-1)[ri] if color else None
        out = self.field(self.box.to_unit(pts), view, semantics=semantics, color=color)
        weights, _, _ = render_weights(out["sigma"], samples, dirs.norm(dim=-1))
        result = {}
        if color:
            rgb = accumulate_along_rays(weights, out["rgb"], samples)
            result["rgb"] = rgb if self.appearance is None else self.appearance(rgb, appearance)
        result["depth"] = accumulate_along_rays(weights, t[:, None], samples).squeeze(-1)
        result["opacity"] = accumulate_along_rays(weights, None, samples).squeeze(-1)
        result["weights"] = weights
        if semantics:
            result["semantics"], composited = class_distribution(
                weights, out["semantic_logits"], samples, self.config.loss.semantic_form
            )
            if composited is not None:
                result["semantic_logits"] = composited
            if self.config.loss.semantic_band_consistency > 0:
                result["sample_logits"] = out["semantic_logits"]
        return result

    @torch.inference_mode()
    def render_samples_pruned(
        self,
        origins: Tensor,
        dirs: Tensor,
        samples: RaySamples,
        semantics: bool = True,
        appearance: int | None = None,
        color: bool = True,
        min_weight: float = 1e-3,
        label_focus: Tensor | None = None,
    ) -> dict[str, Tensor]:
        """Inference version of :meth:`render_samples` (same outputs but ``weights``): the
        encoding (both tables, one corner computation) and the density everywhere, then the
        colour and semantic MLPs only at the samples whose weight is at least ``min_weight``
        times the largest of their ray (what is dropped are the faint tails in front of and
        behind a surface). Samples that carry the march's features (``samples.features``,
        from :meth:`_march_features`) are not evaluated again. ``label_focus`` (S,): factors on
        the samples' weights for the class distribution only (:meth:`_label_focus`)."""
        ri = samples.ray_indices
        t = samples.t_mids
        if samples.features is not None:
            sigma, geo, sem = self._unpack_features(samples.features, semantics)
        else:
            x = self.box.to_unit(origins[ri] + dirs[ri] * t[:, None])
            sigma, geo, sem = self.field.features(x, semantic_features=semantics)
        weights, _, _ = render_weights(sigma, samples, dirs.norm(dim=-1))
        result = {
            "depth": accumulate_along_rays(weights, t[:, None], samples).squeeze(-1),
            "opacity": accumulate_along_rays(weights, None, samples).squeeze(-1),
        }
        if not (color or semantics):
            return result
        ray_max = weights.new_zeros(samples.num_rays).scatter_reduce(
            0, ri, weights, reduce="amax", include_self=True
        )
        keep = torch.nonzero(weights >= min_weight * ray_max[ri]).squeeze(-1)
        kept = RaySamples(ri[keep], samples.t_starts[keep], samples.t_ends[keep], samples.num_rays)
        w, g = weights[keep], geo[keep]
        if color:
            view = torch.nn.functional.normalize(dirs, dim=-1)[kept.ray_indices]
            rgb = accumulate_along_rays(w, _blocked(self.field.color, g, view), kept)
            result["rgb"] = rgb if self.appearance is None else self.appearance(rgb, appearance)
        if semantics:
            logits = _blocked(self.field.semantic_head, g, None if sem is None else sem[keep])
            if label_focus is not None:
                w = w * label_focus[keep]
            result["semantics"], _ = class_distribution(
                w, logits, kept, self.config.loss.semantic_form
            )
        return result

    def _march_features(self, semantics: bool) -> FeatureDensityFn:
        """A density function for the rendering march that also returns, per point, what
        :meth:`render_samples_pruned` needs there (density, geometry features and, with
        ``semantics``, the semantic table's features, one row each): the march evaluates the
        encoding at every sample it keeps, and the render then need not do it again."""

        def fn(points: Tensor) -> tuple[Tensor, Tensor]:
            sigma, geo, sem = self.field.features(
                self.box.to_unit(points), semantic_features=semantics
            )
            parts = [sigma[:, None], geo] + ([] if sem is None else [sem])
            return sigma, torch.cat(parts, dim=-1)

        return fn

    def _unpack_features(
        self, features: Tensor, semantics: bool
    ) -> tuple[Tensor, Tensor, Tensor | None]:
        """The density, geometry and semantic features of :meth:`_march_features`' rows."""
        g = self.field.cfg.geo_features
        sem = features[:, 1 + g :] if semantics and features.shape[1] > 1 + g else None
        if semantics and self.field.semantic_table is not None and sem is None:
            raise ValueError("render_samples_pruned: the march kept no semantic features")
        return features[:, 0], features[:, 1 : 1 + g], sem

    def render_semantics(
        self, origins: Tensor, dirs: Tensor, samples: RaySamples, per_sample: bool = False
    ) -> tuple[Tensor, Tensor | None] | tuple[Tensor, Tensor | None, Tensor, Tensor]:
        """What the semantic loss of ``config.loss.semantic_form`` reads, (R, C), with
        gradients for the semantic head only (the density, hence the weights, computed
        without): one semantic training step's forward pass. ``paper``: the class
        distributions; ``semantic_nerf``: the composited logits. Also each ray's opacity
        over its samples (R,), without gradient, where the surface term reads it
        (``loss.semantic_surface_faint_only``), else None. With ``per_sample`` also each
        sample's logits (S, C) and its rendering weight (S,), detached (what
        ``loss.semantic_band_consistency`` reads)."""
        ri = samples.ray_indices
        pts = origins[ri] + dirs[ri] * samples.t_mids[:, None]
        sigma, logits = self.field.semantics(self.box.to_unit(pts))
        weights, _, _ = render_weights(sigma, samples, dirs.norm(dim=-1))
        probs, composited = class_distribution(
            weights, logits, samples, self.config.loss.semantic_form
        )
        opacity = None
        if self.config.loss.semantic_surface_faint_only:
            opacity = accumulate_along_rays(weights.detach(), None, samples)[:, 0]
        scores = probs if composited is None else composited
        if per_sample:
            return scores, opacity, logits, weights.detach()
        return scores, opacity

    def render_rays(
        self,
        origins: Tensor,
        dirs: Tensor,
        sampler: RaySampler | str | None = None,
        depth: Tensor | None = None,
        semantics: bool = True,
        chunk: int | None = None,
        appearance: int | None = None,
        color: bool = True,
    ) -> dict[str, Tensor]:
        """Render rays for inference (no autograd), in chunks of rays. ``sampler`` defaults to
        :meth:`render_sampler` (depth-guided where ``depth`` (R,) is given and the config
        says so); ``appearance`` is a training frame whose colour correction applies
        (``None``: average); without ``color`` only depth, opacity and semantics are made.

        Depth guidance places samples in the measured depth band only, which suits the class
        distributions (normalised over each ray's weights) but not colour: whatever opacity
        the field has outside the band is missing from the composite, and a partly fitted
        field's image comes out dark. So with ``color`` the default sampler renders colour,
        depth and opacity with the ``render`` sampler (as for a view without depth) and only
        the semantics in the band; without ``color`` everything comes from the band (depth
        and opacity then describe the band, not the whole ray). With
        ``SamplerConfig.render_band_color`` colour and depth come from the band as well,
        normalised by its opacity, where that opacity is high enough
        (:meth:`_render_band_color`)."""
        s = self.config.sampler
        if sampler is None and depth is None and s.render_depth_guided and s.render_novel_estimate:
            # A view without depth: every ray is a hole, rendered around its estimated surface.
            depth = torch.zeros(origins.shape[0], device=origins.device)
        if sampler is None and color and depth is not None and s.render_depth_guided:
            if s.render_band_color and self.appearance is None:
                return self._render_band_color(origins, dirs, depth, semantics, chunk)
            out = self.render_rays(
                origins,
                dirs,
                self.make_sampler(s.render),
                semantics=False,
                chunk=chunk,
                appearance=appearance,
            )
            if semantics:
                band = self.render_rays(origins, dirs, depth=depth, chunk=chunk, color=False)
                out["semantics"] = band["semantics"]
            return out
        if sampler is None:
            sampler = self.render_sampler(with_depth=depth is not None)
        elif isinstance(sampler, str):
            sampler = self.make_sampler(sampler)
        chunk = chunk or render_chunk(self.config.render_chunk, origins.device)
        # A pruned march evaluates the field at every sample it keeps: keep the features too
        # (benchmarks/results/speed.md "A cheaper march for novel views").
        march_fn = (
            self._march_features(semantics)
            if isinstance(sampler, OccupancySampler) and sampler.prune
            else None
        )
        parts: list[dict[str, Tensor]] = []
        with torch.inference_mode():
            for i in range(0, origins.shape[0], chunk):
                o, d = origins[i : i + chunk], dirs[i : i + chunk]
                dd = depth[i : i + chunk] if depth is not None else None
                samples = self.sample(o, d, sampler, depth=dd, density_fn=march_fn)
                focus = self._label_focus(samples, dd) if semantics else None
                part = self.render_samples_pruned(
                    o,
                    d,
                    samples,
                    semantics=semantics,
                    appearance=appearance,
                    color=color,
                    label_focus=focus,
                )
                if semantics and dd is not None:
                    self._surface_labels(o, d, dd, part)
                parts.append(part)
        if not parts:
            return {}
        return {k: torch.cat([p[k] for p in parts]) for k in parts[0]}

    def _label_focus(self, samples: RaySamples, depth: Tensor | None) -> Tensor | None:
        """Per-sample factors (S,) on the weights of the class distribution: a Gaussian of the
        sample's distance to its ray's measured ``depth`` (R,), of standard deviation
        ``SamplerConfig.render_band_label_sigma`` times the ray's band half-width; 1 on rays
        without a measurement. ``None`` when the option is off or no depth is given. Near a
        flat panel set in a wall (a window, a mirror) or beside a curtain, the band's outer
        samples pass close to the neighbouring surface and vote for its class; the surface
        the sensor measured is at the band's centre."""
        s = self.config.sampler
        behind = s.render_band_label_behind
        if depth is None or (s.render_band_label_sigma <= 0 and behind is None):
            return None
        d = depth[samples.ray_indices]
        focus = torch.ones_like(samples.t_mids)
        if s.render_band_label_sigma > 0:
            sigma = s.render_band_label_sigma * s.band_half_width(d)
            z = (samples.t_mids - d) / sigma
            focus = torch.exp(-0.5 * z * z)
        if behind is not None:
            focus = focus * (samples.t_mids <= d + behind)
        return torch.where(d > 0, focus, torch.ones_like(focus))

    def surface_logits(self, origins: Tensor, dirs: Tensor, depth: Tensor) -> Tensor:
        """The semantic head's logits (R, C) at the surface points ``origins + dirs * depth``
        of rays (R, 3) with measured ``depth`` (R,): where the voxel map votes, read by the
        semantic-head steps' surface term and by the labels of rays with depth
        (:meth:`_surface_labels`); only the semantic head sees gradients."""
        points = origins + dirs * depth[:, None]
        _, logits = self.field.semantics(self.box.to_unit(points))
        return logits

    def _surface_labels(
        self, origins: Tensor, dirs: Tensor, depth: Tensor, out: dict[str, Tensor]
    ) -> None:
        """Labels from the semantic head at the measured surface point of rays with ``depth``
        (in place in ``out["semantics"]``), its distribution computed once for both uses.

        Give rays with a measured ``depth`` whose samples hold (next to) no rendering weight
        the semantic head's class distribution at their measured surface point, where the
        fit's surface term trained it (``LossConfig.semantic_surface``), in ``out["semantics"]``
        (in place). Such a ray met a part thinner than the field resolves (a chair spindle one
        pixel wide, carved by the free space beside it); its own distribution, normalised from
        no weight, was all zeros (``paper``) or uniform (``semantic_nerf``) and read as the
        first class, wall (benchmarks/results/fusion.md "Thin furniture: empty bands").
        With ``SamplerConfig.render_surface_label_weight`` w, every other ray with a measurement
        takes (1 - w) x its own distribution + w x the surface point's."""
        # No class distribution at all: no weight anywhere, or none where the labels read
        # (``render_band_label_behind``).
        faint = (out["opacity"] < EMPTY_RAY_OPACITY) | (out["semantics"].sum(dim=-1) <= 0)
        w = self.config.sampler.render_surface_label_weight
        rows = torch.nonzero((depth > 0) & (faint | (w > 0))).squeeze(-1)
        if rows.numel() == 0:
            return
        surface = torch.softmax(self.surface_logits(origins[rows], dirs[rows], depth[rows]), dim=-1)
        sem = out["semantics"]
        empty = faint[rows]
        mixed = torch.where(empty[:, None], surface, (1 - w) * sem[rows] + w * surface)
        sem[rows] = mixed.to(sem.dtype)

    @torch.inference_mode()
    def _render_band_color(
        self, origins: Tensor, dirs: Tensor, depth: Tensor, semantics: bool, chunk: int | None
    ) -> dict[str, Tensor]:
        """Colour, depth and semantics of rays with measured depth from the band samples
        alone. Colour and depth are divided by the band's opacity (the composite of the
        surface the band holds, as the class distributions already are); a ray whose band
        opacity is below ``render_band_min_opacity`` takes colour, depth and opacity from the
        whole ray (the ``render`` sampler), its semantics still from the band. ``opacity`` is
        the band's where the band is used."""
        s = self.config.sampler
        band = self.render_sampler(with_depth=True)
        out = self.render_rays(origins, dirs, band, depth, semantics=semantics, chunk=chunk)
        if not out:
            return out
        opacity = out["opacity"]
        ok = opacity >= s.render_band_min_opacity
        scale = torch.where(ok, 1.0 / opacity.clamp_min(1e-6), torch.ones_like(opacity))
        out["rgb"] = out["rgb"] * scale[:, None]
        out["depth"] = out["depth"] * scale
        miss = torch.nonzero(~ok).squeeze(-1)
        if miss.numel():
            whole = self.render_rays(
                origins[miss], dirs[miss], self.make_sampler(s.render), semantics=False, chunk=chunk
            )
            for key in ("rgb", "depth", "opacity"):
                if whole:
                    out[key][miss] = whole[key]
                else:  # no sample anywhere on those rays: blank, as a whole render would be
                    out[key][miss] = 0.0
        return out

    # -- training ---------------------------------------------------------------------------

    def parameter_groups(self) -> list[dict]:
        """Optimiser groups: feature tables and per-frame colour corrections without weight
        decay, MLP weights with the config's small L2 (Instant-NGP)."""
        tables, mlp = [], []
        for name, p in self.field.named_parameters():
            is_table = name.startswith("encoding.") or name == "semantic_table"
            (tables if is_table else mlp).append(p)
        if self.appearance is not None:
            tables += list(self.appearance.parameters())
        return [
            {"params": tables, "weight_decay": 0.0},
            {"params": mlp, "weight_decay": self.config.optim.weight_decay_mlp},
        ]

    def semantic_parameter_groups(self) -> list[dict]:
        """The semantic head's parameters (table and MLP), grouped like :meth:`parameter_groups`."""
        named = dict(self.field.named_parameters())
        table = [named["semantic_table"]] if "semantic_table" in named else []
        mlp = [p for n, p in named.items() if n.startswith("semantic_mlp.")]
        return [
            {"params": table, "weight_decay": 0.0},
            {"params": mlp, "weight_decay": self.config.optim.weight_decay_mlp},
        ]

    def losses(
        self,
        out: dict[str, Tensor],
        target: dict[str, Tensor],
        samples: RaySamples,
        free_space_scale: float = 1.0,
    ) -> dict[str, Tensor]:
        """The fit's loss terms and their weighted sum ``loss`` (``losses.total_loss``), with
        the free-space term on depth-banded samples scaled by ``free_space_scale`` (its warm-up)
        and weighed per ray by ``target["free_space_weight"]`` when given
        (``loss.free_space_edge``)."""
        s = self.config.sampler
        if self.config.loss.free_space > 0 and free_space_scale > 0 and "depth" in target:
            d = target["depth"][samples.ray_indices]
            half = s.band_half_width(d)
            in_front = ((d > 0) & (samples.t_ends < d - half)).float()
            if "free_space_weight" in target:
                in_front = in_front * target["free_space_weight"][samples.ray_indices]
            out = dict(out)
            out["free_space"] = free_space_scale * free_space_loss(
                out["weights"], in_front, samples, target.get("ray_weight")
            )
        if self.config.loss.semantic_band_consistency > 0 and "sample_logits" in out:
            if "labels" in target:
                out = dict(out)
                out["band_consistency"] = band_consistency_loss(
                    out["sample_logits"],
                    out["weights"].detach(),
                    samples,
                    target["labels"],
                    target.get("semantic_weight", target.get("ray_weight")),
                )
        return total_loss(out, target, self.config.loss)

    @torch.no_grad()
    def update_occupancy(
        self, decay: float = 0.0, passes: int = 2, generator: torch.Generator | None = None
    ) -> float:
        """Re-estimate the occupancy grid from the field (``decay=0``: from scratch), then empty the
        cells that no training camera sees (the field is unconstrained there); returns the occupied
        fraction."""
        for i in range(passes):
            self.grid.update(
                self.box, self.density_fn, decay=decay if i == 0 else 1.0, generator=generator
            )
        self.grid.keep_visible(self.box, self.seen_by_training_cameras)
        return float(self.grid.occupied.float().mean())

    def seen_surface_points(self, points: Tensor, margin: float = 0.1) -> Tensor:
        """Whether world surface points (N, 3) were seen in training: in a cell where a
        training view measured a surface (:attr:`observed`, when marked), else inside a
        training camera's image (:meth:`seen_by_training_cameras`, ``margin``)."""
        if self.observed is not None and self.observed.marked:
            return self.observed.contains(self.box, points)
        return self.seen_by_training_cameras(points, margin=margin)

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


# On CUDA, rays rendered per chunk at least this many (the config's ``render_chunk`` is sized
# for CPU caches; a GPU needs far more work per launch: benchmarks/results/gpu.md "The GPU path").
CUDA_RENDER_CHUNK = 2**15


def render_chunk(configured: int, device: torch.device) -> int:
    """Rays per rendering chunk on ``device``: the config's, raised to ``CUDA_RENDER_CHUNK`` on
    CUDA."""
    return max(configured, CUDA_RENDER_CHUNK) if device.type == "cuda" else configured


def _blocked(fn, *inputs: Tensor | None, block: int = INFERENCE_BLOCK) -> Tensor:
    """``fn(*inputs)`` on blocks of ``block`` rows (inference on a CPU: keeps the work
    cache-sized); on CUDA in one call."""
    n = inputs[0].shape[0]
    if n <= block or inputs[0].is_cuda:
        return fn(*inputs)
    parts = [
        fn(*(None if t is None else t[i : i + block] for t in inputs)) for i in range(0, n, block)
    ]
    return torch.cat(parts)
