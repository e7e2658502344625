"""Where to put samples along rays. Every sampler returns packed ``RaySamples``.

Functions (the algorithms):

- ``sample_uniform`` / ``sample_reference``: the paper's sampler, stratified samples then
  importance samples from their weights (256 + 256 in the reference preset).
- ``sample_depth_guided``: training rays with a measured depth get most samples in a band
  around it and a few stratified ones over the rest of the ray; the intervals tile
  ``[t_near, t_far]`` so that free space is still supervised. Rays without depth get stratified
  samples only (the fallback when a scene has no depth at all).
- ``sample_band``: samples only inside the band around the measured depth (rendering views
  that have depth: the space in front of a measured surface is empty).
- ``OccupancyGrid``: fixed-step marching that drops samples in cells known to be empty, and
  ``first_hit``, the first occupied cell along each ray (the grid alone, no density).
- ``GridSurfaceEstimate``: a surface depth for rays without a measurement (first occupied
  cell, then a coarse density-only march to opacity 1/2), so that they too can be rendered
  in a depth band.

Objects (what the trainer and the renderer hold), in the manner of nerfacc's estimators: each
owns its state and its update schedule, ``sampler.sampling(origins, dirs, t_near, t_far, ...)``
places samples and ``sampler.update_every_n_steps(step, density_fn)`` refreshes the state
during training (a no-op for stateless samplers): ``UniformSampler``, ``ReferenceSampler``,
``DepthGuidedSampler`` (with a fallback sampler for rays without depth) and
``OccupancySampler``. ``SemanticNerf.make_sampler`` builds them from the config.

Rays use unit-z camera directions, so ``t`` is metric z-depth. ``density_fn(points)`` maps
world points ``(N, 3)`` to densities ``(N,)``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor, nn

from csa_core.nerf.normalization import SceneBox
from csa_core.nerf.rendering import (
    MAX_OPTICAL_DEPTH,
    RaySamples,
    exclusive_cumsum,
    render_weights,
)
from csa_core.nerf.visibility import cell_index

DensityFn = Callable[[Tensor], Tensor]
# A density function that also returns per-point features (``OccupancyGrid.sampling``).
FeatureDensityFn = Callable[[Tensor], tuple[Tensor, Tensor]]


def _dense_samples(edges: Tensor) -> RaySamples:
    """Samples whose intervals are consecutive ``edges`` (R, K + 1) of each ray."""
    n_rays, k = edges.shape[0], edges.shape[1] - 1
    ri = torch.arange(n_rays, device=edges.device).repeat_interleave(k)
    return RaySamples(ri, edges[:, :-1].reshape(-1), edges[:, 1:].reshape(-1), n_rays, per_ray=k)


def _stratified_edges(
    t_near: Tensor, t_far: Tensor, n: int, stratified: bool, generator: torch.Generator | None
) -> Tensor:
    """``n`` bins between ``t_near`` and ``t_far`` (R,); inner edges jittered when
    ``stratified``."""
    u = torch.linspace(0.0, 1.0, n + 1, device=t_near.device)
    u = u.expand(t_near.shape[0], n + 1).clone()
    if stratified and n > 1:
        jitter = torch.rand(t_near.shape[0], n - 1, device=t_near.device, generator=generator) - 0.5
        u[:, 1:-1] += jitter / n
    return t_near[:, None] + (t_far - t_near)[:, None] * u


def sample_uniform(
    t_near: Tensor,
    t_far: Tensor,
    n: int,
    stratified: bool = False,
    generator: torch.Generator | None = None,
) -> RaySamples:
    """``n`` equal (or jittered) intervals per ray between ``t_near`` and ``t_far``."""
    return _dense_samples(
        _stratified_edges(t_near, t_far.clamp_min(t_near + 1e-4), n, stratified, generator)
    )


def _sample_pdf(
    edges: Tensor, weights: Tensor, n: int, stratified: bool, generator: torch.Generator | None
) -> Tensor:
    """Inverse-CDF samples ``(R, n)`` of the piecewise-constant density ``weights`` (R, K) on
    ``edges``."""
    w = weights + 1e-5
    pdf = w / w.sum(dim=-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, dim=-1)], dim=-1).clamp_max(
        1.0
    )
    if stratified:
        u = (
            torch.arange(n, device=edges.device)
            + torch.rand(edges.shape[0], n, device=edges.device, generator=generator)
        ) / n
    else:
        u = (
            ((torch.arange(n, device=edges.device) + 0.5) / n)
            .expand(edges.shape[0], n)
            .contiguous()
        )
    idx = torch.searchsorted(cdf, u, right=True).clamp(1, cdf.shape[-1] - 1)
    c0, c1 = torch.gather(cdf, 1, idx - 1), torch.gather(cdf, 1, idx)
    e0, e1 = torch.gather(edges, 1, idx - 1), torch.gather(edges, 1, idx)
    frac = ((u - c0) / (c1 - c0).clamp_min(1e-10)).clamp(0.0, 1.0)
    return e0 + frac * (e1 - e0)


@torch.no_grad()
def sample_reference(
    origins: Tensor,
    dirs: Tensor,
    t_near: Tensor,
    t_far: Tensor,
    density_fn: DensityFn,
    n_uniform: int,
    n_importance: int,
    stratified: bool = False,
    generator: torch.Generator | None = None,
) -> RaySamples:
    """The paper's sampler: ``n_uniform`` stratified samples, their weights from ``density_fn``,
    then ``n_importance`` samples from those weights; returns the sorted union as intervals."""
    t_far = t_far.clamp_min(t_near + 1e-4)
    coarse = sample_uniform(t_near, t_far, n_uniform, stratified, generator)
    mids = coarse.t_mids
    pts = origins[coarse.ray_indices] + dirs[coarse.ray_indices] * mids[:, None]
    weights, _, _ = render_weights(density_fn(pts), coarse, dirs.norm(dim=-1))
    edges = torch.cat(
        [coarse.t_starts.view(-1, n_uniform), coarse.t_ends.view(-1, n_uniform)[:, -1:]], dim=1
    )
    fine = _sample_pdf(edges, weights.view(-1, n_uniform), n_importance, stratified, generator)
    # Union of coarse midpoints and fine samples, sorted; intervals between consecutive midpoints.
    t = torch.sort(torch.cat([mids.view(-1, n_uniform), fine], dim=1), dim=1).values
    bounds = torch.cat([t_near[:, None], 0.5 * (t[:, 1:] + t[:, :-1]), t_far[:, None]], dim=1)
    return _dense_samples(bounds)


def sample_depth_guided(
    t_near: Tensor,
    t_far: Tensor,
    depth: Tensor,
    n_band: int,
    n_spread: int,
    band: float | Tensor,
    band_fraction: float | Tensor = 0.0,
    stratified: bool = True,
    generator: torch.Generator | None = None,
) -> RaySamples:
    """``n_band`` intervals inside ``depth +- (band + band_fraction * depth)`` and ``n_spread``
    intervals over the rest of ``[t_near, t_far]`` (split in proportion to the lengths in front
    of and behind the band); rays with ``depth <= 0`` get ``n_band + n_spread`` stratified
    intervals over the whole ray. Every ray gets exactly ``n_band + n_spread`` samples."""
    t_far = t_far.clamp_min(t_near + 1e-4)
    half = band + band_fraction * depth
    has = depth > 0
    lo = torch.where(has, (depth - half).clamp(min=t_near, max=t_far), t_near)
    hi = torch.where(has, (depth + half).clamp(min=t_near, max=t_far), t_near)
    hi = torch.maximum(hi, lo)
    front, back = lo - t_near, t_far - hi
    # Spread samples before the band, at least one when there is room.
    n_front = torch.round(n_spread * front / (front + back).clamp_min(1e-6)).long()
    n_front = torch.where(front > 1e-4, n_front.clamp(1, n_spread), torch.zeros_like(n_front))
    n_front = torch.where(
        back > 1e-4, n_front.clamp_max(n_spread - 1), n_front.clamp_max(n_spread)
    ).clamp_min(0)
    n_back = n_spread - n_front
    total = n_band + n_spread
    r = depth.shape[0]
    # Bin edges in "segment coordinates": for each output bin k, which segment and which fraction.
    k = torch.arange(total + 1, device=depth.device).expand(r, total + 1)
    nf, nb = n_front[:, None], n_back[:, None]
    front_u = k / nf.clamp_min(1)
    band_u = (k - nf) / n_band
    back_u = (k - nf - n_band) / nb.clamp_min(1)
    e_front = t_near[:, None] + front[:, None] * front_u
    e_band = lo[:, None] + (hi - lo)[:, None] * band_u
    e_back = hi[:, None] + back[:, None] * back_u
    edges = torch.where(k <= nf, e_front, torch.where(k <= nf + n_band, e_band, e_back))
    # Rays without depth: plain stratified bins.
    plain = t_near[:, None] + (t_far - t_near)[:, None] * (k / total)
    edges = torch.where(has[:, None], edges, plain)
    if stratified and total > 1:
        # Move each inner edge by up to a quarter of the smaller neighbouring bin.
        jitter = torch.rand(r, total - 1, device=depth.device, generator=generator) - 0.5
        gaps = torch.minimum(edges[:, 1:-1] - edges[:, :-2], edges[:, 2:] - edges[:, 1:-1])
        edges = edges.clone()
        edges[:, 1:-1] = edges[:, 1:-1] + 0.5 * jitter * gaps
    edges = torch.cummax(edges, dim=1).values
    return _dense_samples(edges)


def sample_band(
    t_near: Tensor,
    t_far: Tensor,
    depth: Tensor,
    n: int,
    band: float | Tensor,
    band_fraction: float | Tensor = 0.0,
    stratified: bool = False,
    generator: torch.Generator | None = None,
) -> RaySamples:
    """``n`` intervals tiling ``depth +- (band + band_fraction * depth)`` (clipped to
    ``[t_near, t_far]``) and nothing else: the space in front of a measured surface is taken to
    be empty. Every ray must have a measurement (``depth > 0``). ``band`` and
    ``band_fraction`` may be per-ray tensors (R,)."""
    half = band + band_fraction * depth
    lo = torch.maximum(depth - half, t_near)
    hi = torch.maximum(torch.minimum(depth + half, t_far), lo)
    return sample_uniform(lo, hi, n, stratified, generator)


def merge_samples(parts: list[tuple[Tensor, RaySamples]], num_rays: int) -> RaySamples:
    """One packed ``RaySamples`` of ``num_rays`` rays from samplings of disjoint ray subsets,
    each given as (the subset's ray ids, its samples); each ray's samples stay in ``t`` order."""
    device = parts[0][0].device if parts else torch.device("cpu")
    parts = [(ids, s) for ids, s in parts if len(s) > 0]
    if len(parts) == 1 and parts[0][1].per_ray is not None:
        ids, s = parts[0]
        if ids.shape[0] == num_rays and bool(
            (ids == torch.arange(num_rays, device=ids.device)).all()
        ):
            return s
    if not parts:
        empty = torch.zeros(0, device=device)
        return RaySamples(empty.long(), empty, empty, num_rays)
    ri = torch.cat([ids[s.ray_indices] for ids, s in parts])
    starts = torch.cat([s.t_starts for _, s in parts])
    ends = torch.cat([s.t_ends for _, s in parts])
    order = torch.argsort(ri, stable=True)
    return RaySamples(ri[order], starts[order], ends[order], num_rays)


class OccupancyGrid(nn.Module):
    """A binary occupancy grid over the unit cube with fixed-step, empty-space-skipping marching.

    ``density_ema`` holds a running estimate of each cell's density (updated from the field
    during training); a cell is occupied while ``density * step`` exceeds the threshold.
    """

    def __init__(self, resolution: int, threshold: float, march_steps: int):
        super().__init__()
        self.resolution = resolution
        self.threshold = threshold
        self.march_steps = march_steps
        self.register_buffer("density_ema", torch.full((resolution,) * 3, 1e3))
        self.register_buffer("occupied", torch.ones((resolution,) * 3, dtype=torch.bool))

    def step_size(self, box: SceneBox) -> float:
        return box.diagonal / self.march_steps

    @torch.no_grad()
    def mark_points(self, box: SceneBox, points: Tensor) -> None:
        """Mark the cells containing world ``points`` (N, 3) as occupied (e.g. from measured
        depth)."""
        idx = self._cell_index(box.to_unit(points))
        ok = idx >= 0
        self.occupied.view(-1)[idx[ok]] = True

    def _cell_index(self, u: Tensor) -> Tensor:
        return cell_index(u, self.resolution)

    @torch.no_grad()
    def keep_visible(
        self, box: SceneBox, visible_fn: Callable[[Tensor], Tensor], chunk: int = 65536
    ) -> None:
        """Empty every cell whose centre ``visible_fn`` (world points -> bool) says no camera
        sees."""
        r = self.resolution
        occ = self.occupied.view(-1)
        cells = torch.nonzero(occ).squeeze(-1)
        for start in range(0, cells.shape[0], chunk):
            c = cells[start : start + chunk]
            ijk = torch.stack([c // (r * r), (c // r) % r, c % r], dim=-1).float()
            seen = visible_fn(box.from_unit((ijk + 0.5) / r))
            occ[c[~seen]] = False

    @torch.no_grad()
    def update(
        self,
        box: SceneBox,
        density_fn: DensityFn,
        decay: float = 0.95,
        chunk: int = 65536,
        generator: torch.Generator | None = None,
        fraction: float = 1.0,
    ) -> None:
        """Re-estimate cell densities at a jittered point per cell (a random ``fraction`` of
        cells)."""
        r = self.resolution
        n = r**3
        device = self.density_ema.device
        cells = (
            torch.arange(n, device=device)
            if fraction >= 1.0
            else torch.randperm(n, device=device, generator=generator)[: max(1, int(n * fraction))]
        )
        ema = self.density_ema.view(-1)
        for start in range(0, cells.shape[0], chunk):
            c = cells[start : start + chunk]
            ijk = torch.stack([c // (r * r), (c // r) % r, c % r], dim=-1).float()
            u = (ijk + torch.rand(ijk.shape, device=device, generator=generator)) / r
            sigma = density_fn(box.from_unit(u))
            ema[c] = torch.maximum(ema[c] * decay, sigma)
        occ = (self.density_ema * self.step_size(box) > self.threshold).float()
        # Dilate by one cell: a jittered point can miss a surface that only grazes a cell.
        occ = torch.nn.functional.max_pool3d(occ[None, None], kernel_size=3, stride=1, padding=1)[
            0, 0
        ]
        self.occupied.copy_(occ > 0)

    @torch.no_grad()
    def sampling(
        self,
        box: SceneBox,
        origins: Tensor,
        dirs: Tensor,
        t_near: Tensor,
        t_far: Tensor,
        stratified: bool = False,
        generator: torch.Generator | None = None,
        max_samples: int | None = None,
        density_fn: DensityFn | FeatureDensityFn | None = None,
        early_stop_eps: float = 1e-3,
        min_weight: float = 1e-4,
        chunk_steps: int = 16,  # benchmarks/results/speed.md "A cheaper march": 16 beat 48
        step: float | None = None,
    ) -> RaySamples:
        """March every ray from ``t_near`` to ``t_far`` in steps of ``step`` metres along the ray
        (default: the box diagonal / ``march_steps``) and keep the samples in occupied cells, at
        most ``max_samples`` per ray. With ``density_fn``, rays stop once their transmittance
        falls below ``early_stop_eps`` and samples whose weight is below ``min_weight`` are
        dropped. The density is evaluated ``chunk_steps`` steps of the active rays at a time:
        smaller chunks waste fewer evaluations behind a surface, larger ones fewer passes.
        ``density_fn`` may return ``(sigma (N,), features (N, F))``: the features of the kept
        samples come back as ``RaySamples.features`` (what a renderer would otherwise compute
        again at the same points)."""
        step = self.step_size(box) if step is None else step
        if not step > 0:
            raise ValueError(f"OccupancyGrid.sampling: step must be > 0 metres, got {step}")
        n_rays = origins.shape[0]
        dev = origins.device
        dt = step / dirs.norm(dim=-1)  # t-step so that each step is ``step`` metres long
        n_steps = (
            int(torch.ceil(((t_far - t_near).clamp_min(0) / dt).max()).item()) if n_rays else 0
        )
        offset = (
            torch.rand(n_rays, device=dev, generator=generator)
            if stratified
            else torch.full((n_rays,), 0.5, device=dev)
        )
        limit = max_samples if max_samples is not None else n_steps + 1
        count = torch.zeros(n_rays, dtype=torch.long, device=dev)
        trans = torch.ones(n_rays, device=dev)
        kept_ri, kept_t, kept_f = [], [], []
        for s0 in range(0, n_steps, chunk_steps):
            active = (count < limit) & (t_near + s0 * dt < t_far) & (trans > early_stop_eps)
            rays = torch.nonzero(active).squeeze(-1)
            if rays.numel() == 0:
                break
            s1 = min(s0 + chunk_steps, n_steps)
            t, pts, keep = self._march_chunk(
                box, origins, dirs, t_near, dt, offset, t_far, rays, s0, s1
            )
            evaluated, features = (keep.clone() if density_fn is not None else keep), None
            if density_fn is not None and bool(keep.any()):
                sigma_dt = torch.zeros_like(t)
                sigma = density_fn(pts[keep])
                if isinstance(sigma, tuple):
                    sigma, features = sigma  # features: one row per evaluated sample
                sigma_dt[keep] = sigma * step
                excl = exclusive_cumsum(sigma_dt.clamp(max=MAX_OPTICAL_DEPTH), dim=1)
                weight = trans[rays, None] * torch.exp(-excl) * (1.0 - torch.exp(-sigma_dt))
                keep &= weight >= min_weight
                trans[rays] = trans[rays] * torch.exp(-sigma_dt.sum(dim=1))
            rank = torch.cumsum(keep.long(), dim=1) + count[rays, None]
            keep &= rank <= limit
            count[rays] += keep.sum(dim=1)
            kept_ri.append(rays[:, None].expand_as(t)[keep])
            kept_t.append(t[keep])
            if features is not None:  # kept is a subset of evaluated, both in row-major order
                kept_f.append(features[keep[evaluated]])
        if not kept_ri:
            empty = torch.zeros(0, device=dev)
            return RaySamples(empty.long(), empty, empty, n_rays)
        ri = torch.cat(kept_ri)
        t = torch.cat(kept_t)
        order = torch.argsort(
            ri * (n_steps + 1) + torch.round((t - t_near[ri]) / dt[ri] - offset[ri]).long(),
            stable=True,
        )
        ri, t = ri[order], t[order]
        half = 0.5 * dt[ri]
        features = None
        if kept_f and sum(f.shape[0] for f in kept_f) == ri.shape[0]:
            features = torch.cat(kept_f)[order]
        return RaySamples(ri, t - half, t + half, n_rays, features=features)

    def _march_chunk(
        self,
        box: SceneBox,
        origins: Tensor,
        dirs: Tensor,
        t_first: Tensor,
        dt: Tensor,
        offset: Tensor | float,
        t_far: Tensor,
        rays: Tensor,
        s0: int,
        s1: int,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Steps ``s0..s1-1`` of the marches of ``rays`` (indices into the per-ray tensors):
        ``t`` (R' x K) at ``t_first + (k + offset) * dt``, their points, and whether each lies
        before ``t_far`` in an occupied cell. ``offset``: per ray (R,) or one number. The
        one stepping code of :meth:`sampling`, :meth:`first_hit` and ``GridSurfaceEstimate``."""
        k = torch.arange(s0, s1, device=origins.device, dtype=torch.float32)
        off = offset[rays, None] if isinstance(offset, Tensor) else offset
        t = t_first[rays, None] + (k[None, :] + off) * dt[rays, None]  # R' x K
        pts = origins[rays, None, :] + dirs[rays, None, :] * t[..., None]
        idx = self._cell_index(box.to_unit(pts))
        occ = (t < t_far[rays, None]) & (idx >= 0)
        occ &= self.occupied.view(-1)[idx.clamp_min(0)]
        return t, pts, occ

    def cell_size(self, box: SceneBox) -> float:
        """Edge of one cell in metres."""
        return box.extent / self.resolution

    @torch.no_grad()
    def first_hit(
        self,
        box: SceneBox,
        origins: Tensor,
        dirs: Tensor,
        t_near: Tensor,
        t_far: Tensor,
        step: float | None = None,
        chunk_steps: int = 64,
    ) -> Tensor:
        """``t`` (R,) of the first point of each ray, stepping ``step`` metres (default half a
        cell) from ``t_near``, that lies in an occupied cell; ``inf`` where the ray meets none
        before ``t_far``. Only the grid is read (no density is evaluated), so the point is at
        most ``step`` behind where the ray enters the first occupied cell."""
        n_rays = origins.shape[0]
        dev = origins.device
        hit = torch.full((n_rays,), float("inf"), device=dev)
        if n_rays == 0:
            return hit
        step = step if step is not None else 0.5 * self.cell_size(box)
        dt = step / dirs.norm(dim=-1)
        n_steps = int(torch.ceil(((t_far - t_near).clamp_min(0) / dt).max()).item())
        pending = t_far > t_near
        for s0 in range(0, n_steps, chunk_steps):
            rays = torch.nonzero(pending & (t_near + s0 * dt < t_far)).squeeze(-1)
            if rays.numel() == 0:
                break
            s1 = min(s0 + chunk_steps, n_steps)
            t, _, occ = self._march_chunk(box, origins, dirs, t_near, dt, 0.5, t_far, rays, s0, s1)
            found = occ.any(dim=1)
            first = torch.argmax(occ.to(torch.uint8), dim=1)  # the first True where any
            got = rays[found]
            hit[got] = t[found, first[found]]
            pending[got] = False
        return hit


class GridSurfaceEstimate:
    """Where rays without a measured depth meet a surface, found with few density evaluations
    and no colour or semantic features. From the first occupied cell of ``grid`` along the ray
    (``OccupancyGrid.first_hit``: the grid alone), a coarse march in steps of ``step_cells``
    cells evaluates the density only in occupied cells and stops each ray once its opacity
    reaches ``min_opacity`` (one half); the estimate is the depth where it does (interpolated
    within the step). Calling it gives that z-depth (R,), 0 where the ray meets no occupied cell
    or never gets that opaque: those rays need the full march.

    Against the full occupancy march (``OccupancyGrid.sampling`` with the density): coarser
    steps (half a cell against the box diagonal / ``march_steps``), a stop at opacity 1/2
    instead of 0.999, and nothing but the density; the band around the estimate then costs what
    a pixel with measured depth costs.
    """

    def __init__(
        self,
        grid: OccupancyGrid,
        box: SceneBox,
        step_cells: float = 0.5,
        min_opacity: float = 0.5,
        # benchmarks/results/speed.md "Semantic steps in depth holes": 8 beat 16 and 4
        chunk_steps: int = 8,
    ):
        if not step_cells > 0 or not 0 < min_opacity < 1:
            raise ValueError(
                f"GridSurfaceEstimate: step_cells ({step_cells}) must be > 0 and min_opacity "
                f"({min_opacity}) in (0, 1)"
            )
        self.grid, self.box = grid, box
        self.step_cells, self.min_opacity, self.chunk_steps = step_cells, min_opacity, chunk_steps

    @torch.no_grad()
    def __call__(
        self, origins: Tensor, dirs: Tensor, t_near: Tensor, t_far: Tensor, density_fn: DensityFn
    ) -> Tensor:
        if density_fn is None:
            raise ValueError("GridSurfaceEstimate needs density_fn for its coarse march")
        depth = torch.zeros_like(t_near)
        step = self.step_cells * self.grid.cell_size(self.box)  # metres
        hit = self.grid.first_hit(self.box, origins, dirs, t_near, t_far, step=step)
        rays = torch.nonzero(torch.isfinite(hit)).squeeze(-1)
        if rays.numel() == 0:
            return depth
        o, d, t_far = origins[rays], dirs[rays], t_far[rays]
        dt = step / d.norm(dim=-1)
        start = hit[rays] - 0.5 * dt  # first_hit's point is the middle of its step
        target = -math.log(1.0 - self.min_opacity)  # optical depth of that opacity
        tau = torch.zeros_like(start)
        found = torch.zeros_like(start)
        active = torch.ones_like(start, dtype=torch.bool)
        n_steps = int(torch.ceil(((t_far - start).clamp_min(0) / dt).max()).item())
        for s0 in range(0, n_steps, self.chunk_steps):
            r = torch.nonzero(active & (start + s0 * dt < t_far)).squeeze(-1)
            if r.numel() == 0:
                break
            s1 = min(s0 + self.chunk_steps, n_steps)  # steps' middles:
            t, pts, occ = self.grid._march_chunk(self.box, o, d, start, dt, 0.5, t_far, r, s0, s1)
            sigma_dt = torch.zeros_like(t)
            if bool(occ.any()):
                sigma_dt[occ] = density_fn(pts[occ]) * step
            sigma_dt = sigma_dt.clamp(max=MAX_OPTICAL_DEPTH)
            before = tau[r, None] + exclusive_cumsum(sigma_dt, dim=1)  # optical depth in front
            total = before + sigma_dt
            crossed = total >= target
            done = torch.nonzero(crossed.any(dim=1)).squeeze(-1)
            kk = torch.argmax(crossed[done].to(torch.uint8), dim=1)  # the first step past it
            sd = sigma_dt[done, kk]
            frac = ((target - before[done, kk]) / sd.clamp_min(1e-10)).clamp(0.0, 1.0)
            found[r[done]] = t[done, kk] + (frac - 0.5) * dt[r[done]]
            active[r[done]] = False
            tau[r] = total[:, -1]
        depth[rays] = found
        return depth


class RaySampler:
    """A sampler object: ``sampling`` places samples along rays, ``update_every_n_steps``
    refreshes its state during training (nothing here: stateless samplers)."""

    uses_depth = False  # whether ``sampling`` reads the measured depth

    def sampling(
        self,
        origins: Tensor,
        dirs: Tensor,
        t_near: Tensor,
        t_far: Tensor,
        *,
        depth: Tensor | None = None,
        density_fn: DensityFn | None = None,
        stratified: bool = False,
        generator: torch.Generator | None = None,
    ) -> RaySamples:
        raise NotImplementedError

    def update_every_n_steps(
        self, step: int, density_fn: DensityFn, generator: torch.Generator | None = None
    ) -> None:
        """Called by the trainer before every step ``step`` (0-based)."""


class UniformSampler(RaySampler):
    """``n`` equal (stratified in training) intervals between the box entry and exit."""

    def __init__(self, n: int):
        self.n = n

    def sampling(
        self,
        origins,
        dirs,
        t_near,
        t_far,
        *,
        depth=None,
        density_fn=None,
        stratified=False,
        generator=None,
    ) -> RaySamples:
        return sample_uniform(t_near, t_far, self.n, stratified, generator)


class ReferenceSampler(RaySampler):
    """The paper's sampler: ``n_uniform`` stratified samples, then ``n_importance`` samples
    from their weights under the current density."""

    def __init__(self, n_uniform: int, n_importance: int):
        self.n_uniform, self.n_importance = n_uniform, n_importance

    def sampling(
        self,
        origins,
        dirs,
        t_near,
        t_far,
        *,
        depth=None,
        density_fn=None,
        stratified=False,
        generator=None,
    ) -> RaySamples:
        if density_fn is None:
            raise ValueError("ReferenceSampler needs density_fn for its importance samples")
        with torch.no_grad():
            return sample_reference(
                origins,
                dirs,
                t_near,
                t_far,
                density_fn,
                self.n_uniform,
                self.n_importance,
                stratified,
                generator,
            )


class DepthGuidedSampler(RaySampler):
    """Samples around the measured depth of each ray.

    ``n_spread > 0`` (training): ``n_band`` samples in the band and ``n_spread`` over the rest
    of the ray (``sample_depth_guided``), so free space is seen too. ``n_spread == 0``
    (rendering a view that has depth): the band only (``sample_band``). Rays without a
    measurement inside the box go to ``fallback`` (e.g. the occupancy march), or, without one,
    get ``n_band + n_spread`` stratified samples over the whole ray. With ``estimate`` (e.g. a
    ``GridSurfaceEstimate``: ``estimate(origins, dirs, t_near, t_far, density_fn)`` -> z-depth,
    0 = none), rays without a measurement first get an estimated depth and are sampled in the
    band around it, widened by ``estimate_band_scale`` (the estimate is less certain than a
    measurement); only rays it finds nothing for go to ``fallback``.
    """

    uses_depth = True

    def __init__(
        self,
        n_band: int,
        n_spread: int,
        band: float,
        band_fraction: float = 0.0,
        fallback: RaySampler | None = None,
        estimate: Callable[..., Tensor] | None = None,
        estimate_band_scale: float = 1.0,
    ):
        self.n_band, self.n_spread = n_band, n_spread
        self.band, self.band_fraction = band, band_fraction
        self.fallback = fallback
        self.estimate, self.estimate_band_scale = estimate, estimate_band_scale

    def update_every_n_steps(self, step, density_fn, generator=None) -> None:
        if self.fallback is not None:
            self.fallback.update_every_n_steps(step, density_fn, generator)

    def _guided(self, t_near, t_far, depth, stratified, generator, scale=None) -> RaySamples:
        # ``scale`` (R,): per-ray widening of the band (estimated depths), None = as configured.
        band, fraction = self.band, self.band_fraction
        if scale is not None:
            band, fraction = band * scale, fraction * scale
        if self.n_spread > 0:
            return sample_depth_guided(
                t_near,
                t_far,
                depth,
                self.n_band,
                self.n_spread,
                band,
                fraction,
                stratified,
                generator,
            )
        return sample_band(t_near, t_far, depth, self.n_band, band, fraction, stratified, generator)

    def sampling(
        self,
        origins,
        dirs,
        t_near,
        t_far,
        *,
        depth=None,
        density_fn=None,
        stratified=False,
        generator=None,
    ) -> RaySamples:
        n_rays = origins.shape[0]
        if depth is None:
            depth = torch.zeros_like(t_near)
        has = (depth > 0) & (depth < t_far)
        scale = None
        if self.estimate is not None and not bool(has.all()):
            missing = torch.nonzero(~has).squeeze(-1)
            depth = depth.clone()
            depth[missing] = self.estimate(
                origins[missing], dirs[missing], t_near[missing], t_far[missing], density_fn
            )
            has = (depth > 0) & (depth < t_far)
            if self.estimate_band_scale != 1.0:
                scale = torch.ones_like(depth)
                scale[missing] = self.estimate_band_scale
        if self.fallback is None and self.n_spread > 0:
            # Rays without depth: stratified over the whole ray, inside sample_depth_guided.
            return self._guided(t_near, t_far, depth, stratified, generator, scale)
        if self.fallback is None:
            raise ValueError("DepthGuidedSampler: band-only sampling needs a fallback sampler")
        if bool(has.all()):
            return self._guided(t_near, t_far, depth, stratified, generator, scale)
        with_d = torch.nonzero(has).squeeze(-1)
        without = torch.nonzero(~has).squeeze(-1)
        parts = []
        if with_d.numel():
            parts.append(
                (
                    with_d,
                    self._guided(
                        t_near[with_d],
                        t_far[with_d],
                        depth[with_d],
                        stratified,
                        generator,
                        None if scale is None else scale[with_d],
                    ),
                )
            )
        parts.append(
            (
                without,
                self.fallback.sampling(
                    origins[without],
                    dirs[without],
                    t_near[without],
                    t_far[without],
                    density_fn=density_fn,
                    stratified=stratified,
                    generator=generator,
                ),
            )
        )
        return merge_samples(parts, n_rays)


class OccupancySampler(RaySampler):
    """Empty-space-skipping march through ``grid`` (an ``OccupancyGrid`` over ``box``).

    The grid is refreshed every ``update_every`` training steps (a full pass at step 0, a
    random quarter of the cells after). With ``prune`` (rendering), rays stop once their
    transmittance is below ``early_stop_eps`` and samples of weight below ``min_weight`` are
    dropped; training samples are not pruned. ``step``: metres per marching step (default: the
    grid's, the box diagonal / ``march_steps``).
    """

    def __init__(
        self,
        grid: OccupancyGrid,
        box: SceneBox,
        max_samples: int | None,
        update_every: int = 16,
        ema_decay: float = 0.95,
        prune: bool = True,
        step: float | None = None,
        early_stop_eps: float = 1e-3,
        min_weight: float = 1e-4,
    ):
        if not 0 <= early_stop_eps < 1 or not 0 <= min_weight < 1:
            raise ValueError(
                f"OccupancySampler: early_stop_eps ({early_stop_eps}) and min_weight "
                f"({min_weight}) must be in [0, 1)"
            )
        self.grid, self.box = grid, box
        self.max_samples = max_samples
        self.update_every, self.ema_decay = update_every, ema_decay
        self.prune = prune
        self.step = step
        self.early_stop_eps, self.min_weight = early_stop_eps, min_weight

    def update_every_n_steps(self, step, density_fn, generator=None) -> None:
        if step % self.update_every == 0:
            self.grid.update(
                self.box,
                density_fn,
                decay=self.ema_decay,
                generator=generator,
                fraction=0.25 if step else 1.0,
            )

    def sampling(
        self,
        origins,
        dirs,
        t_near,
        t_far,
        *,
        depth=None,
        density_fn=None,
        stratified=False,
        generator=None,
    ) -> RaySamples:
        return self.grid.sampling(
            self.box,
            origins,
            dirs,
            t_near,
            t_far,
            stratified,
            generator,
            max_samples=self.max_samples,
            density_fn=density_fn if self.prune else None,
            early_stop_eps=self.early_stop_eps,
            min_weight=self.min_weight,
            step=self.step,
        )
