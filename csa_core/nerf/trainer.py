"""``NerfTrainer``: the one training loop of the Semantic-NeRF (fits and joint training).

Each step draws random pixels from a :class:`~csa_core.nerf.rays.RayBank`, lets the training
sampler place samples (refreshing its state on its own schedule), renders colour, depth and
class distributions and takes one Adam step on the model's losses (``losses.py``: L2 colour
+ 0.1 L1 depth + 0.04 NLL semantics, paper Eq. 4, and our free-space term).
The model owns its parameter groups and losses; the trainer owns the optimiser, the learning
rate schedule, the random stream and the free-space warm-up.

``semantic_steps`` trains the semantic head alone (geometry and colour frozen) with samples
placed the way labels are rendered: semantics never shape geometry, so this costs about one
forward pass of the density per step.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from csa_core.nerf.losses import band_consistency_loss, semantic_cross_entropy, semantic_loss
from csa_core.nerf.model import SemanticNerf
from csa_core.nerf.rays import RayBank


def make_adam(groups: list[dict], lr: float, nerf: SemanticNerf) -> torch.optim.Optimizer:
    """Adam with the config's betas and eps over parameter ``groups`` (fused where supported)."""
    o = nerf.config.optim
    kwargs = {"lr": lr, "betas": o.betas, "eps": o.eps}
    try:
        return torch.optim.Adam(groups, fused=True, **kwargs)
    except (RuntimeError, TypeError):
        return torch.optim.Adam(groups, **kwargs)


def exponential_decay(
    optimizer: torch.optim.Optimizer, fraction: float, steps: int, name: str
) -> torch.optim.lr_scheduler.ExponentialLR:
    """A schedule that multiplies ``optimizer``'s rates by the same factor at every step, so
    that after ``steps`` steps they are ``fraction`` of what they were (1.0: constant);
    ``fraction`` is the config field ``name`` and must lie in (0, 1]."""
    if not (math.isfinite(fraction) and 0 < fraction <= 1):
        raise ValueError(f"{name} must be in (0, 1], got {fraction}")
    return torch.optim.lr_scheduler.ExponentialLR(
        optimizer, math.exp(math.log(fraction) / max(1, steps))
    )


class NerfTrainer:
    """Adam steps of ``nerf`` on the pixels of ``rays``.

    ``schedule_steps``: length of the learning-rate schedule, an exponential decay from ``lr``
    (default: the config's) to ``lr * final_lr_fraction`` (default: the config's; 1.0 keeps
    the rate constant). ``free_space_warmup``: steps without the free-space loss, which then
    ramps in over as many steps (carving before surfaces exist can kill the density).
    """

    def __init__(
        self,
        nerf: SemanticNerf,
        rays: RayBank,
        schedule_steps: int,
        lr: float | None = None,
        final_lr_fraction: float | None = None,
        rays_per_step: int | None = None,
        free_space_warmup: float = 0.0,
        seed: int = 0,
        semantics: bool = True,
    ):
        o = nerf.config.optim
        self.nerf, self.rays = nerf, rays
        self.rays_per_step = rays_per_step or o.rays_per_step
        self.free_space_warmup = free_space_warmup
        self.semantics = semantics
        self.sampler = nerf.train_sampler(has_depth=rays.has_depth)
        if nerf.observed is not None and rays.has_depth:
            # The surfaces these views measured, for the unseen test of the renders.
            nerf.observed.mark(nerf.box, rays.surface_points())
        self.optimizer = make_adam(nerf.parameter_groups(), lr or o.lr, nerf)
        fraction = o.final_lr_fraction if final_lr_fraction is None else final_lr_fraction
        self.scheduler = exponential_decay(
            self.optimizer, fraction, schedule_steps, "optim.final_lr_fraction"
        )
        self.generator = torch.Generator(device=rays.device).manual_seed(seed)
        if o.ray_batches not in ("all", "per_view", "class_balanced"):
            raise ValueError(
                "optim.ray_batches must be 'all', 'per_view' or 'class_balanced', "
                f"got {o.ray_batches!r}"
            )
        self.per_view = o.ray_batches == "per_view"
        if o.semantic_ray_batches not in (None, "all", "class_balanced"):
            raise ValueError(
                "optim.semantic_ray_batches must be None, 'all' or 'class_balanced', "
                f"got {o.semantic_ray_batches!r}"
            )
        # Label-stratified draws need labels: a bank without them when the trainer is made
        # (joint training sets its labels later) draws uniformly throughout. The semantic-head
        # steps follow the fit's draws unless optim.semantic_ray_batches says.
        labelled = rays.labels is not None
        fit_balanced = o.ray_batches == "class_balanced"
        semantic = o.semantic_ray_batches
        self.balanced = labelled and fit_balanced
        self.semantic_balanced = labelled and (
            fit_balanced if semantic is None else semantic == "class_balanced"
        )
        power = nerf.config.loss.semantic_depth_power
        if not math.isfinite(power):
            raise ValueError(f"loss.semantic_depth_power must be finite, got {power}")
        self.near_power = power
        self._view_order: list[int] = []
        # The bank's pixels beside a nearer surface (``loss.free_space_edge``), on first use.
        self._beside_nearer: Tensor | None = None
        self.steps_done = 0
        self.samples_seen = 0

    def free_space_scale(self) -> float:
        warm = self.free_space_warmup
        return min(1.0, max(0.0, (self.steps_done - warm) / max(warm, 1.0)))

    def draw(self) -> tuple[Tensor, Tensor | None]:
        """The next step's pixel ids and their importance weights (None: uniform): from every
        view, from the next view of this epoch's random order (``optim.ray_batches="per_view"``),
        or label-stratified with weights (``"class_balanced"``, ``RayBank.balanced_ids``)."""
        if not self.per_view:
            return self._draw_from_all(self.rays_per_step, self.balanced)
        if not self._view_order:
            n = len(self.rays.frames)
            order = torch.randperm(n, generator=self.generator, device=self.generator.device)
            self._view_order = order.tolist()[::-1]
        ids = self.rays.random_ids(self.rays_per_step, self.generator, self._view_order.pop())
        return ids, None

    def _draw_from_all(self, n: int, balanced: bool) -> tuple[Tensor, Tensor | None]:
        """``n`` pixel ids from every view: label-stratified with their weights when
        ``balanced``, else uniform (weights None)."""
        if balanced:
            return self.rays.balanced_ids(n, self.generator)
        return self.rays.random_ids(n, self.generator), None

    def semantic_weights(self, ids: Tensor, ray_weight: Tensor | None) -> Tensor | None:
        """Weights of the semantic loss of pixels ``ids``: their draw's ``ray_weight`` times,
        with ``loss.semantic_depth_power``, the depth weights (``RayBank.near_weights``);
        ``ray_weight`` itself otherwise."""
        near = self.rays.near_weights(ids, self.near_power)
        if near is None:
            return ray_weight
        return near if ray_weight is None else near * ray_weight

    def step(self) -> dict[str, Tensor]:
        """One Adam step on a fresh ray batch; returns the loss terms (tensors)."""
        nerf, gen = self.nerf, self.generator
        ids, ray_weight = self.draw()
        origins, dirs, target = self.rays.batch(ids)
        if ray_weight is not None:
            target["ray_weight"] = ray_weight
        semantic_weight = self.semantic_weights(ids, ray_weight)
        if semantic_weight is not None:
            target["semantic_weight"] = semantic_weight
        edge = nerf.config.loss.free_space_edge
        if edge < 1 and nerf.config.loss.free_space > 0 and self.rays.has_depth:
            if self._beside_nearer is None:
                band = nerf.config.sampler.band_half_width
                self._beside_nearer = self.rays.beside_nearer_surface(band)
            target["free_space_weight"] = torch.where(self._beside_nearer[ids], edge, 1.0)
        self.sampler.update_every_n_steps(self.steps_done, nerf.density_fn, gen)
        samples = nerf.sample(
            origins, dirs, self.sampler, depth=target["depth"], stratified=True, generator=gen
        )
        out = nerf.render_samples(
            origins,
            dirs,
            samples,
            semantics=self.semantics and "labels" in target,
            appearance=target["frame"],
        )
        terms = nerf.losses(out, target, samples, self.free_space_scale())
        self.optimizer.zero_grad(set_to_none=True)
        terms["loss"].backward()
        self.optimizer.step()
        self.scheduler.step()
        self.steps_done += 1
        self.samples_seen += len(samples)
        return terms

    def train(
        self, steps: int, on_step: Callable[[int, dict[str, Tensor]], None] | None = None
    ) -> dict[str, float]:
        """``steps`` steps (model in training mode, back in eval mode after); ``on_step(i, terms)``
        hears every step. Returns the last step's terms as floats."""
        terms: dict[str, Tensor] = {}
        self.nerf.train()
        try:
            for i in range(steps):
                terms = self.step()
                if on_step is not None:
                    on_step(i, terms)
        finally:
            self.nerf.eval()
        return {k: float(v.detach()) for k, v in terms.items()}

    def _surface_term(
        self,
        ids: Tensor,
        origins: Tensor,
        dirs: Tensor,
        labels: Tensor,
        weight: Tensor | None,
        opacity: Tensor | None,
    ) -> Tensor:
        """The surface term of the semantic-head steps (``loss.semantic_surface``): the
        cross-entropy of each ray's label under the semantic head at the ray's measured surface
        point, weighted as the composited term (and, given the rays' ``opacity`` over their
        samples, as with ``loss.semantic_surface_faint_only``, by one less it); rays without
        depth have none. It votes where the voxel map votes, so a thin part the density renders
        faintly still gets its label."""
        depth = self.rays.depth[ids]
        ok = depth > 0
        logits = self.nerf.surface_logits(origins[ok], dirs[ok], depth[ok])
        w = None if weight is None else weight[ok]
        if opacity is None:
            return semantic_cross_entropy(logits, labels[ok], w)
        # The mean over every ray of weight x faintness x cross-entropy: an opaque ray
        # contributes nothing, and a few faint rays are not scaled up to the whole term.
        known = labels[ok] > 0
        base = torch.ones_like(depth[ok]) if w is None else w
        faint = (1.0 - opacity[ok]).clamp(0.0, 1.0)
        share = (base * faint)[known].sum() / base[known].sum().clamp_min(1e-12)
        return share * semantic_cross_entropy(logits, labels[ok], base * faint)

    def semantic_steps(
        self,
        steps: int,
        lr: float | None = None,
        rays_per_step: int | None = None,
        on_step: Callable[[int], None] | None = None,
    ) -> float:
        """``steps`` Adam steps on the semantic head alone (fresh Adam from ``lr``, default the
        config's, decaying exponentially to ``optim.semantic_final_lr_fraction`` of it at the
        last step), samples placed like rendered labels' (``SemanticNerf.render_sampler``,
        holes in the depth included) but as many in the band as the fit's (``band_samples``),
        rays drawn uniformly from every view or label-stratified with their weights as in
        :meth:`step` (``optim.semantic_ray_batches``, by default as ``optim.ray_batches``:
        stratified when it is "class_balanced"), and weighted by their depth
        with ``loss.semantic_depth_power``; with ``loss.semantic_surface`` the loss adds the
        surface term (:meth:`_surface_term`); ``on_step(i)`` hears every step (what it raises
        ends the steps); returns the last loss."""
        if self.rays.labels is None:
            raise ValueError("semantic steps need labels (RayBank.set_labels)")
        nerf, gen = self.nerf, self.generator
        o = nerf.config.optim
        opt = make_adam(nerf.semantic_parameter_groups(), lr or o.lr, nerf)
        # Reaches the fraction at the last step (the step count less the first).
        scheduler = exponential_decay(
            opt, o.semantic_final_lr_fraction, steps - 1, "optim.semantic_final_lr_fraction"
        )
        # Rays in depth holes sample the way their labels render: in the band around the
        # occupancy grid's surface estimate where the config's ``render_hole_estimate`` is on
        # (marching them cost hard scenes 2-3x the clean scenes' semantic steps:
        # benchmarks/results/speed.md, "Semantic steps in depth holes").
        # As many band samples as the fit's steps, not the render's: with the render's 6
        # (``fast``) the hard variants' labels came out 0.2-0.7 lower, rendering 6 from a head
        # trained on 8 cost at most 0.2 (benchmarks/results/speed.md, "Fewer band samples and one
        # corner layout").
        sampler = nerf.render_sampler(
            with_depth=self.rays.has_depth, band_samples=nerf.config.sampler.band_samples
        )
        n = rays_per_step or self.rays_per_step
        value = float("nan")
        for i in range(steps):
            ids, ray_weight = self._draw_from_all(n, self.semantic_balanced)
            origins, dirs = self.rays.rays(ids)
            with torch.no_grad():
                samples = nerf.sample(
                    origins,
                    dirs,
                    sampler,
                    depth=self.rays.depth[ids],
                    stratified=True,
                    generator=gen,
                )
            consistency = nerf.config.loss.semantic_band_consistency
            scores, opacity, *per_sample = nerf.render_semantics(
                origins, dirs, samples, per_sample=consistency > 0
            )
            weight = self.semantic_weights(ids, ray_weight)
            form_loss = (
                semantic_cross_entropy
                if nerf.config.loss.semantic_form == "semantic_nerf"
                else semantic_loss
            )
            labels = self.rays.labels[ids]
            loss = form_loss(scores, labels, weight)
            surface = nerf.config.loss.semantic_surface
            if surface > 0:
                loss = loss + surface * self._surface_term(
                    ids, origins, dirs, labels, weight, opacity
                )
            if consistency > 0:
                loss = loss + consistency * band_consistency_loss(
                    *per_sample, samples, labels, weight
                )
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            scheduler.step()
            value = float(loss.detach())
            if on_step is not None:
                on_step(i)
        return value
