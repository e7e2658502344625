"""Samplers: layout invariants, and equivalence of all samplers on an analytic scene."""

from __future__ import annotations

import pytest
import torch

from csa_core.nerf.normalization import SceneBox
from csa_core.nerf.rendering import RaySamples, accumulate_along_rays, render_weights
from csa_core.nerf.samplers import (
    DepthGuidedSampler,
    OccupancyGrid,
    OccupancySampler,
    ReferenceSampler,
    UniformSampler,
    sample_depth_guided,
    sample_reference,
    sample_uniform,
)

RADIUS = 0.6
BOX = SceneBox((0.0, 0.0, 0.0), 3.0)


def _sphere_density(points: torch.Tensor) -> torch.Tensor:
    return (points.norm(dim=-1) < RADIUS).float() * 200.0


def _rays(n: int = 16):
    """A pinhole camera 2 m in front of the sphere, unit-z directions (t = z-depth)."""
    u = torch.linspace(-0.45, 0.45, n)
    yy, xx = torch.meshgrid(u, u, indexing="ij")
    d = torch.stack([xx, yy, torch.ones_like(xx)], -1).reshape(-1, 3)
    o = torch.tensor([0.0, 0.0, -2.0]).expand_as(d).contiguous()
    # Analytic z-depth of the first hit: |o + t d| = r.
    a = (d * d).sum(-1)
    b = 2 * (o * d).sum(-1)
    c = (o * o).sum(-1) - RADIUS**2
    disc = b * b - 4 * a * c
    t_hit = (-b - disc.clamp_min(0).sqrt()) / (2 * a)
    return o, d, torch.where(disc > 0, t_hit, torch.zeros_like(t_hit)), disc


def _composite(o, d, samples: RaySamples):
    pts = o[samples.ray_indices] + d[samples.ray_indices] * samples.t_mids[:, None]
    w, _, _ = render_weights(_sphere_density(pts), samples, d.norm(dim=-1))
    depth = accumulate_along_rays(w, samples.t_mids[:, None], samples).squeeze(-1)
    opacity = accumulate_along_rays(w, None, samples).squeeze(-1)
    return depth, opacity


def test_all_samplers_render_the_same_sphere():
    o, d, t_true, disc = _rays()
    t_near, t_far = BOX.ray_interval(o, d, near=0.05)
    hit = disc > 0.05  # clearly inside the silhouette
    miss = disc < -0.05
    grid = OccupancyGrid(resolution=64, threshold=0.01, march_steps=1024)
    grid.update(BOX, _sphere_density, decay=0.0, generator=torch.Generator().manual_seed(0))
    grid.update(BOX, _sphere_density, decay=1.0, generator=torch.Generator().manual_seed(1))
    results = {
        "reference": sample_reference(o, d, t_near, t_far, _sphere_density, 128, 128),
        "uniform": sample_uniform(t_near, t_far, 1024),
        "depth": sample_depth_guided(t_near, t_far, t_true, n_band=16, n_spread=8, band=0.1),
        "occupancy": grid.sampling(BOX, o, d, t_near, t_far, density_fn=_sphere_density),
    }
    for name, samples in results.items():
        depth, opacity = _composite(o, d, samples)
        assert torch.all(opacity[hit] > 0.97), name
        assert torch.all(opacity[miss] < 1e-3), name
        err = (depth[hit] - t_true[hit]).abs()
        assert float(err.max()) < 0.03, (name, float(err.max()))
    # Empty-space skipping really skips: far fewer samples than uniform marching.
    assert len(results["occupancy"]) < 0.2 * len(results["uniform"])


def test_depth_guided_layout_tiles_the_ray():
    g = torch.Generator().manual_seed(0)
    n = 50
    t_near = torch.full((n,), 0.05)
    t_far = torch.rand(n, generator=g) * 4 + 2
    depth = torch.rand(n, generator=g) * 5
    depth[::5] = 0.0  # no measurement -> stratified over the whole ray
    depth[1] = 0.06  # band clipped at the near plane
    depth[2] = 100.0  # beyond the far bound
    s = sample_depth_guided(
        t_near,
        t_far,
        depth,
        n_band=6,
        n_spread=4,
        band=0.1,
        band_fraction=0.02,
        stratified=True,
        generator=g,
    )
    assert s.per_ray == 10 and len(s) == n * 10
    ts, te = s.t_starts.view(n, 10), s.t_ends.view(n, 10)
    assert torch.all(te >= ts)
    torch.testing.assert_close(ts[:, 1:], te[:, :-1])  # contiguous
    torch.testing.assert_close(ts[:, 0], t_near)
    torch.testing.assert_close(te[:, -1], t_far)
    # With a measurement inside the ray, the band holds most of the samples.
    ok = (depth > 0.3) & (depth + 0.3 < t_far)
    mids = s.t_mids.view(n, 10)
    in_band = ((mids - depth[:, None]).abs() <= 0.1 + 0.02 * depth[:, None] + 1e-4).sum(1)
    assert torch.all(in_band[ok] >= 6)


def test_reference_sampler_concentrates_samples_at_the_surface():
    o, d, t_true, disc = _rays(4)
    t_near, t_far = BOX.ray_interval(o, d, near=0.05)
    s = sample_reference(o, d, t_near, t_far, _sphere_density, 64, 64)
    assert s.per_ray == 128
    near_surface = ((s.t_mids.view(-1, 128) - t_true[:, None]).abs() < 0.1).sum(1)
    hit = disc > 0.05
    assert torch.all(near_surface[hit] > 40)


def test_occupancy_grid_marks_points_and_stratifies_deterministically():
    grid = OccupancyGrid(resolution=16, threshold=0.01, march_steps=64)
    grid.occupied.zero_()
    grid.mark_points(BOX, torch.tensor([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]]))
    assert int(grid.occupied.sum()) == 1
    grid.occupied.fill_(True)
    o, d, _, _ = _rays(4)
    t_near, t_far = BOX.ray_interval(o, d, near=0.05)
    a = grid.sampling(
        BOX, o, d, t_near, t_far, stratified=True, generator=torch.Generator().manual_seed(3)
    )
    b = grid.sampling(
        BOX, o, d, t_near, t_far, stratified=True, generator=torch.Generator().manual_seed(3)
    )
    assert torch.equal(a.t_starts, b.t_starts) and len(a) > 0


# -- sampler objects ---------------------------------------------------------------------------


class _CountingDensity:
    """The sphere's density, counting the points it was asked for."""

    def __init__(self):
        self.points = 0

    def __call__(self, points: torch.Tensor) -> torch.Tensor:
        self.points += points.shape[0]
        return _sphere_density(points)


def test_occupancy_sampler_owns_its_grid_update_schedule():
    grid = OccupancyGrid(resolution=16, threshold=0.01, march_steps=128)
    sampler = OccupancySampler(
        grid, BOX, max_samples=None, update_every=4, ema_decay=0.0, prune=False
    )
    density = _CountingDensity()
    g = torch.Generator().manual_seed(0)
    cells = 16**3
    counts = []
    for step in range(9):
        before = density.points
        sampler.update_every_n_steps(step, density, generator=g)
        counts.append(density.points - before)
    # Step 0: every cell; steps 4 and 8: a random quarter of the cells; nothing in between.
    assert counts == [cells, 0, 0, 0, cells // 4, 0, 0, 0, cells // 4]
    # The grid it updated (no memory of the initial estimate) knows the sphere: cells far from
    # it are empty.
    assert 0 < float(grid.occupied.float().mean()) < 0.2
    o, d, _, disc = _rays(8)
    t_near, t_far = BOX.ray_interval(o, d, near=0.05)
    s = sampler.sampling(o, d, t_near, t_far, density_fn=density)
    per_ray = torch.bincount(s.ray_indices, minlength=o.shape[0])
    assert torch.all(per_ray[disc > 0.05] > 0)
    grid.occupied.fill_(True)
    assert len(s) < 0.3 * len(sampler.sampling(o, d, t_near, t_far))  # empty space skipped


def test_depth_guided_sampler_sends_rays_without_depth_to_its_fallback():
    o, d, t_true, disc = _rays(8)
    t_near, t_far = BOX.ray_interval(o, d, near=0.05)
    depth = torch.where(disc > 0.05, t_true, torch.zeros_like(t_true))
    fallback = UniformSampler(32)
    sampler = DepthGuidedSampler(4, 0, band=0.05, fallback=fallback)
    s = sampler.sampling(o, d, t_near, t_far, depth=depth)
    per_ray = torch.bincount(s.ray_indices, minlength=o.shape[0])
    has = depth > 0
    assert torch.all(per_ray[has] == 4) and torch.all(per_ray[~has] == 32)
    # Packed layout: rays in order, each ray's samples sorted along it.
    assert torch.all(s.ray_indices[1:] >= s.ray_indices[:-1])
    same_ray = s.ray_indices[1:] == s.ray_indices[:-1]
    assert torch.all(s.t_starts[1:][same_ray] >= s.t_starts[:-1][same_ray])
    # Band samples stay inside depth +- band.
    band = has[s.ray_indices]
    assert torch.all((s.t_mids[band] - depth[s.ray_indices][band]).abs() <= 0.05 + 1e-5)
    # Training layout without a fallback: every ray gets band + spread samples (dense).
    train = DepthGuidedSampler(6, 4, band=0.1)
    t = train.sampling(o, d, t_near, t_far, depth=depth, stratified=True)
    assert t.per_ray == 10 and len(t) == 10 * o.shape[0]
    with pytest.raises(ValueError, match="fallback"):
        DepthGuidedSampler(4, 0, band=0.05).sampling(o, d, t_near, t_far, depth=depth)


def test_reference_sampler_object_needs_the_density():
    o, d, _, _ = _rays(2)
    t_near, t_far = BOX.ray_interval(o, d, near=0.05)
    s = ReferenceSampler(16, 16).sampling(o, d, t_near, t_far, density_fn=_sphere_density)
    assert s.per_ray == 32
    with pytest.raises(ValueError, match="density_fn"):
        ReferenceSampler(16, 16).sampling(o, d, t_near, t_far)


def test_depth_guided_rendering_matches_the_full_march_where_depth_is_exact():
    """Band-only samples around exact depth (few per ray) render the same depth, opacity and
    per-sample values (here: which half of the sphere) as the pruned occupancy march."""
    o, d, t_true, disc = _rays(24)
    t_near, t_far = BOX.ray_interval(o, d, near=0.05)
    grid = OccupancyGrid(resolution=64, threshold=0.01, march_steps=1024)
    march = OccupancySampler(grid, BOX, max_samples=None, update_every=1)
    march.update_every_n_steps(0, _sphere_density, generator=torch.Generator().manual_seed(0))
    inside = disc > 0.05
    depth = torch.where(inside, t_true, torch.zeros_like(t_true))  # no depth off the sphere
    guided = DepthGuidedSampler(8, 0, band=0.05, band_fraction=0.01, fallback=march)
    results = {}
    for name, sampler in {"march": march, "guided": guided}.items():
        s = sampler.sampling(o, d, t_near, t_far, depth=depth, density_fn=_sphere_density)
        pts = o[s.ray_indices] + d[s.ray_indices] * s.t_mids[:, None]
        w, _, _ = render_weights(_sphere_density(pts), s, d.norm(dim=-1))
        halves = torch.stack([(pts[:, 0] < 0).float(), (pts[:, 0] >= 0).float()], dim=-1)
        results[name] = (
            accumulate_along_rays(w, s.t_mids[:, None], s).squeeze(-1),
            accumulate_along_rays(w, None, s).squeeze(-1),
            accumulate_along_rays(w, halves, s),
            len(s),
        )
    (dm, om, hm, nm), (dg, og, hg, ng) = results["march"], results["guided"]
    torch.testing.assert_close(og, om, atol=0.02, rtol=0)
    assert float((dg - dm)[inside].abs().max()) < 0.01
    assert float((dg - t_true)[inside].abs().max()) < 0.01
    torch.testing.assert_close(hg, hm, atol=0.02, rtol=0)
    assert ng < nm  # and with fewer samples


def test_a_coarser_pruned_march_still_finds_the_sphere_with_fewer_samples():
    """The rendering march's knobs: a longer step and harder pruning keep fewer samples, stop
    rays once opaque and still put the surface where it is."""
    o, d, t_true, disc = _rays(16)
    t_near, t_far = BOX.ray_interval(o, d, near=0.05)
    grid = OccupancyGrid(resolution=64, threshold=0.01, march_steps=1024)
    grid.update(BOX, _sphere_density, decay=0.0, generator=torch.Generator().manual_seed(0))
    hit = disc > 0.05
    fine = grid.sampling(BOX, o, d, t_near, t_far, density_fn=_sphere_density, early_stop_eps=0.0)
    coarse = OccupancySampler(
        grid, BOX, None, step=2 * grid.step_size(BOX), early_stop_eps=1e-2, min_weight=1e-3
    ).sampling(o, d, t_near, t_far, density_fn=_sphere_density)
    assert 0 < len(coarse) < 0.5 * len(fine)
    for s in (fine, coarse):
        depth, opacity = _composite(o, d, s)
        assert torch.all(opacity[hit] > 0.98)
        assert torch.allclose(depth[hit], t_true[hit], atol=2 * 2 * grid.step_size(BOX))
    with pytest.raises(ValueError, match="step"):
        grid.sampling(BOX, o, d, t_near, t_far, step=0.0)
    with pytest.raises(ValueError, match="min_weight"):
        OccupancySampler(grid, BOX, None, min_weight=-1.0)


def test_the_march_returns_the_features_of_the_samples_it_keeps():
    """A density function returning ``(sigma, features)``: the kept samples come back with
    their features, row for row, whatever was pruned and however the chunks fell."""
    o, d, _, _ = _rays(12)
    t_near, t_far = BOX.ray_interval(o, d, near=0.05)
    grid = OccupancyGrid(resolution=32, threshold=0.01, march_steps=256)
    grid.update(BOX, _sphere_density, decay=0.0, generator=torch.Generator().manual_seed(0))

    def with_points(points):
        return _sphere_density(points), torch.cat([points, points.norm(dim=-1, keepdim=True)], -1)

    for chunk in (3, 16, 64):
        s = grid.sampling(
            BOX, o, d, t_near, t_far, density_fn=with_points, chunk_steps=chunk, max_samples=6
        )
        plain = grid.sampling(
            BOX, o, d, t_near, t_far, density_fn=_sphere_density, chunk_steps=chunk, max_samples=6
        )
        assert len(s) > 0 and torch.equal(s.t_starts, plain.t_starts)
        pts = o[s.ray_indices] + d[s.ray_indices] * s.t_mids[:, None]
        torch.testing.assert_close(s.features[:, :3], pts, atol=1e-5, rtol=0)
        assert plain.features is None
