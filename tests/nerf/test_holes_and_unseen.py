"""Rendering views with depth holes (surface estimated from the occupancy grid instead of a
full march) and labelling surfaces no training camera saw as unknown."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from csa_core.data.camera import backproject
from csa_core.data.nyu40 import UNKNOWN
from csa_core.nerf.config import SamplerConfig, preset
from csa_core.nerf.normalization import SceneBox
from csa_core.nerf.rays import RayBank, image_rays
from csa_core.nerf.render import render_frames, render_pseudo_labels
from csa_core.nerf.rendering import RaySamples, accumulate_along_rays, render_weights
from csa_core.nerf.samplers import (
    DepthGuidedSampler,
    GridSurfaceEstimate,
    OccupancyGrid,
    OccupancySampler,
)
from csa_core.nerf.trainer import NerfTrainer
from tests.nerf.conftest import tiny_config

BOX = SceneBox((0.0, 0.0, 0.0), 3.0)
RADIUS = 0.6
PLANE_Z = 0.3


def _camera_rays(n: int = 12, spread: float = 0.45):
    """Unit-z rays (t = z-depth) of a pinhole camera at z = -2 looking along +z."""
    u = torch.linspace(-spread, spread, n)
    yy, xx = torch.meshgrid(u, u, indexing="ij")
    d = torch.stack([xx, yy, torch.ones_like(xx)], -1).reshape(-1, 3)
    o = torch.tensor([0.0, 0.0, -2.0]).expand_as(d).contiguous()
    return o, d


def _sphere_density(points: torch.Tensor) -> torch.Tensor:
    return (points.norm(dim=-1) < RADIUS).float() * 200.0


def _sphere_depth(o, d):
    a = (d * d).sum(-1)
    b = 2 * (o * d).sum(-1)
    c = (o * o).sum(-1) - RADIUS**2
    disc = b * b - 4 * a * c
    return (-b - disc.clamp_min(0).sqrt()) / (2 * a), disc


def _sphere_grid() -> OccupancyGrid:
    grid = OccupancyGrid(resolution=32, threshold=0.01, march_steps=512)
    grid.update(BOX, _sphere_density, decay=0.0, generator=torch.Generator().manual_seed(0))
    grid.update(BOX, _sphere_density, decay=1.0, generator=torch.Generator().manual_seed(1))
    return grid


class _Counting:
    """Wraps a sampler or density and counts the rays (or points) it is given."""

    def __init__(self, inner):
        self.inner, self.count = inner, 0

    def __call__(self, points):
        self.count += points.shape[0]
        return self.inner(points)

    def sampling(self, origins, dirs, t_near, t_far, **kw):
        self.count += origins.shape[0]
        return self.inner.sampling(origins, dirs, t_near, t_far, **kw)


# -- the grid's first occupied cell --------------------------------------------------------


def test_first_hit_finds_a_plane_within_one_cell_and_inf_where_the_ray_meets_none():
    grid = OccupancyGrid(resolution=16, threshold=0.01, march_steps=64)
    grid.occupied.zero_()
    # A plane z = PLANE_Z over x < 0.1 only: marks one slab of cells.
    xs = torch.linspace(-1.4, 0.1, 200)
    px, py = torch.meshgrid(xs, torch.linspace(-1.4, 1.4, 200), indexing="ij")
    grid.mark_points(BOX, torch.stack([px, py, torch.full_like(px, PLANE_Z)], -1).reshape(-1, 3))
    o, d = _camera_rays()
    t_near, t_far = BOX.ray_interval(o, d, near=0.05)
    hit = grid.first_hit(BOX, o, d, t_near, t_far)
    t_plane = PLANE_Z - o[:, 2]  # z-depth of the plane along unit-z rays
    x_plane = o[:, 0] + d[:, 0] * t_plane
    cell = grid.cell_size(BOX)
    on = x_plane < 0.1 - cell  # clearly over the marked part of the plane
    off = x_plane > 0.1 + 2 * cell  # clearly past its edge: nothing else is occupied
    assert on.any() and off.any()
    assert float((hit[on] - t_plane[on]).abs().max()) <= cell
    assert torch.isinf(hit[off]).all()
    # The hit lies in an occupied cell.
    pts = o[on] + d[on] * hit[on, None]
    assert grid.occupied.view(-1)[grid._cell_index(BOX.to_unit(pts))].all()


def test_grid_surface_estimate_finds_the_sphere_and_nothing_beside_it():
    grid = _sphere_grid()
    o, d = _camera_rays(16)
    t_near, t_far = BOX.ray_interval(o, d, near=0.05)
    t_true, disc = _sphere_depth(o, d)
    density = _Counting(_sphere_density)
    est = GridSurfaceEstimate(grid, BOX)(o, d, t_near, t_far, density)
    hit, miss = disc > 0.02, disc < -0.02
    assert float((est - t_true)[hit].abs().max()) < 0.03  # half a cell is 0.047
    assert torch.all(est[miss] == 0)
    # Far fewer density evaluations than the full march.
    march = _Counting(_sphere_density)
    grid.sampling(BOX, o, d, t_near, t_far, density_fn=march)
    assert density.count < 0.5 * march.count, (density.count, march.count)
    # A faint surface (opacity below one half along the whole ray) gives no estimate.
    faint = GridSurfaceEstimate(grid, BOX)(
        o, d, t_near, t_far, lambda p: 0.002 * _sphere_density(p)
    )
    assert torch.all(faint == 0)
    with pytest.raises(ValueError, match="density_fn"):
        GridSurfaceEstimate(grid, BOX)(o, d, t_near, t_far, None)


def test_rays_in_holes_render_in_the_band_of_the_estimate_and_misses_fall_back():
    grid = _sphere_grid()
    o, d = _camera_rays(16)
    t_near, t_far = BOX.ray_interval(o, d, near=0.05)
    t_true, disc = _sphere_depth(o, d)
    hit = disc > 0.05
    depth = torch.where(hit, t_true, torch.zeros_like(t_true))
    holes = torch.zeros_like(hit)
    holes[::3] = True  # a third of the rays have no measurement, on and off the sphere
    depth[holes] = 0.0
    results = {}
    for name, estimate in {"march": None, "estimate": GridSurfaceEstimate(grid, BOX)}.items():
        fallback = _Counting(OccupancySampler(grid, BOX, max_samples=None))
        sampler = DepthGuidedSampler(8, 0, band=0.05, fallback=fallback, estimate=estimate)
        s = sampler.sampling(o, d, t_near, t_far, depth=depth, density_fn=_sphere_density)
        per_ray = torch.bincount(s.ray_indices, minlength=o.shape[0])
        pts = o[s.ray_indices] + d[s.ray_indices] * s.t_mids[:, None]
        w, _, _ = render_weights(_sphere_density(pts), s, d.norm(dim=-1))
        results[name] = (
            accumulate_along_rays(w, s.t_mids[:, None], s).squeeze(-1),
            accumulate_along_rays(w, None, s).squeeze(-1),
            per_ray,
            fallback.count,
        )
    (dm, om, _, fm), (de, oe, pe, fe) = results["march"], results["estimate"]
    # Without the estimate every ray without depth marches; with it only those it finds no
    # surface for: all that miss the sphere, few of the others.
    none = depth == 0
    miss, clear = disc < -0.05, holes & (disc > 0.2)
    assert fm == int(none.sum())
    assert fe == int((none & miss).sum())
    assert torch.all(pe[clear] == 8)  # band samples around the estimate
    # The same surface either way.
    assert float((oe - om)[clear].abs().max()) < 0.02
    assert float((de - dm)[clear].abs().max()) < 0.02
    assert float(oe[miss].max()) < 1e-3  # misses stay empty
    # The band around an estimate can be wider than around a measurement.
    wide = DepthGuidedSampler(
        8,
        0,
        band=0.05,
        fallback=fallback,
        estimate=GridSurfaceEstimate(grid, BOX),
        estimate_band_scale=2.0,
    ).sampling(o, d, t_near, t_far, depth=depth, density_fn=_sphere_density)
    lo = torch.full_like(t_near, float("inf")).scatter_reduce(
        0, wide.ray_indices, wide.t_starts, "amin"
    )
    hi = torch.zeros_like(t_near).scatter_reduce(0, wide.ray_indices, wide.t_ends, "amax")
    measured = (depth > 0) & (disc > 0.2)
    torch.testing.assert_close((hi - lo)[measured], torch.full_like(lo[measured], 0.1))
    torch.testing.assert_close((hi - lo)[clear], torch.full_like(lo[clear], 0.2))


# -- a fitted scene ------------------------------------------------------------------------


def _with_holes(depth: np.ndarray, seed: int = 0) -> np.ndarray:
    """``depth`` with a rectangle and scattered pixels set to 0 (no measurement)."""
    out = depth.copy()
    h, w = out.shape
    out[h // 4 : h // 2, w // 4 : 3 * w // 4] = 0
    rng = np.random.default_rng(seed)
    out[rng.random(out.shape) < 0.15] = 0
    return out


def test_hole_labels_agree_with_the_full_march_on_a_fitted_scene(tiny_nerf, tiny_scene):
    marched = copy.deepcopy(tiny_nerf)
    marched.config.sampler.render_hole_estimate = False
    assert tiny_nerf.config.sampler.render_hole_estimate  # the default
    agree, total = 0, 0
    for f in tiny_scene.train_frames[::3]:
        holes = _with_holes(f.depth)
        hole = (holes == 0) & (f.depth > 0)
        poses = [(f.name, f.pose)]
        (new,) = render_frames(tiny_nerf, poses, tiny_scene.intrinsics, [holes], color=False)
        (old,) = render_frames(marched, poses, tiny_scene.intrinsics, [holes], color=False)
        # Pixels with depth are untouched by the estimate.
        assert np.array_equal(new.labels[~hole], old.labels[~hole])
        agree += int((new.labels[hole] == old.labels[hole]).sum())
        total += int(hole.sum())
    assert total > 200
    assert agree / total > 0.9, agree / total


def test_semantic_steps_sample_holes_as_labels_render(tiny_nerf, tiny_scene):
    """The semantic steps place samples the way labels are rendered: rays in depth holes in
    the band around the grid's surface estimate when ``render_hole_estimate`` is on (the
    band's few samples where it finds a surface), marched along the ray when it is off. The
    band holds the fit's ``band_samples``, not the render's ``render_band_samples``."""
    frames = copy.deepcopy(tiny_scene.train_frames[:2])
    for f in frames:
        f.depth = _with_holes(f.depth)
    rays = RayBank(frames, tiny_scene.intrinsics, label_folder="label-nyu40")
    hole = torch.nonzero(rays.depth == 0).squeeze(-1)[:64]
    assert hole.numel() == 64
    origins, dirs = rays.rays(hole)
    per_ray = {}
    for estimate in (True, False):
        nerf = copy.deepcopy(tiny_nerf)
        nerf.config.sampler.render_hole_estimate = estimate
        nerf.config.sampler.render_band_samples = 3  # not the fit's count
        assert nerf.render_sampler(with_depth=True).n_band == 3  # renders use it
        real, made = nerf.render_sampler, []

        def spy(*args, real=real, made=made, **kw):
            made.append(real(*args, **kw))
            return made[-1]

        nerf.render_sampler = spy
        NerfTrainer(nerf, rays, schedule_steps=1).semantic_steps(1, rays_per_step=32)
        assert len(made) == 1 and isinstance(made[0], DepthGuidedSampler)
        assert (made[0].estimate is not None) == estimate
        with torch.no_grad():
            samples = nerf.sample(origins, dirs, made[0], depth=rays.depth[hole])
        per_ray[estimate] = torch.bincount(samples.ray_indices, minlength=64)
    band = tiny_nerf.config.sampler.band_samples
    assert band != 3
    assert float((per_ray[True] == band).float().mean()) > 0.75  # a surface found: the band
    assert int(per_ray[True].sum()) < int(per_ray[False].sum())  # fewer than the march


# -- unseen surfaces -----------------------------------------------------------------------


def _yaw(degrees: float) -> np.ndarray:
    """A camera-frame turn about the camera's vertical axis (right-multiply a pose)."""
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1]])


def _project(points: np.ndarray, pose: np.ndarray, intr) -> tuple[np.ndarray, ...]:
    p = (points - pose[:3, 3]) @ pose[:3, :3]
    z = p[:, 2]
    u = p[:, 0] / np.maximum(z, 1e-6) * intr.fx + intr.cx
    v = p[:, 1] / np.maximum(z, 1e-6) * intr.fy + intr.cy
    return z, u, v


def test_without_observed_cells_surfaces_outside_every_training_frustum_render_unknown(
    tiny_nerf, tiny_scene
):
    """A model without the cells of measured surfaces (a checkpoint written before them, or
    ``observed_resolution=0``) falls back to the training cameras' frusta. One training camera
    left, turned 35 degrees away from a view: the pixels of that view whose measured surface
    point the camera does not see get 0, the others keep the class they get without the
    option."""
    intr = tiny_scene.intrinsics
    f = tiny_scene.train_frames[3]
    a = np.asarray(f.pose, np.float64) @ _yaw(35.0)
    nerf = copy.deepcopy(tiny_nerf)
    nerf.observed = None
    nerf.info.train_poses = a[None]
    pts = backproject(f.depth.astype(np.float64), intr, np.asarray(f.pose, np.float64))
    z, u, v = _project(pts.reshape(-1, 3), a, intr)
    inside = (z > 0.2) & (u > 1) & (u < intr.width - 1) & (v > 1) & (v < intr.height - 1)
    outside = (z < 0) | (u < -1) | (u > intr.width + 1) | (v < -1) | (v > intr.height + 1)
    inside, outside = inside.reshape(f.depth.shape), outside.reshape(f.depth.shape)
    assert inside.mean() > 0.2 and outside.mean() > 0.2
    has = f.depth > 0
    poses = [(f.name, f.pose)]
    (plain,) = render_frames(nerf, poses, intr, [f.depth], color=False)
    (masked,) = render_frames(nerf, poses, intr, [f.depth], color=False, unseen_unknown=True)
    assert UNKNOWN not in plain.labels
    assert np.all(masked.labels[outside & has] == UNKNOWN)
    assert np.all(masked.confidence[outside & has] == 0)
    keep = inside & has
    assert np.array_equal(masked.labels[keep], plain.labels[keep])
    # The config switches it on too (pseudo-labels for adaptation).
    nerf.config.render_unseen_unknown = True
    (cfg,) = render_frames(nerf, poses, intr, [f.depth], color=False)
    assert np.array_equal(cfg.labels, masked.labels)


def test_rays_that_render_nothing_are_unknown(tiny_nerf, tiny_scene):
    nerf = copy.deepcopy(tiny_nerf)
    nerf.grid.occupied.zero_()  # no surface anywhere for rays without depth
    f = tiny_scene.train_frames[0]
    holes = f.depth.copy()
    holes[: holes.shape[0] // 2] = 0
    (view,) = render_frames(
        nerf, [(f.name, f.pose)], tiny_scene.intrinsics, [holes], color=False, unseen_unknown=True
    )
    assert np.all(view.labels[holes == 0] == UNKNOWN)
    # A training view's own measured surface is seen (by that camera).
    assert np.all(view.labels[holes > 0] != UNKNOWN)


def test_pseudo_labels_with_unknown_are_ignored_by_the_segmentation_loss(tiny_nerf, tiny_scene):
    from csa_core.seg.losses import IGNORE_INDEX, nyu40_to_target

    nerf = copy.deepcopy(tiny_nerf)
    nerf.observed = None  # the frustum test
    nerf.info.train_poses = (np.asarray(tiny_scene.train_frames[0].pose) @ _yaw(35.0))[None]
    labels = render_pseudo_labels(nerf, tiny_scene, "train", unseen_unknown=True)
    stack = torch.as_tensor(np.stack(list(labels.values())))
    assert bool((stack == UNKNOWN).any()) and bool((stack != UNKNOWN).any())
    target = nyu40_to_target(stack)
    assert torch.all((target == IGNORE_INDEX) == (stack == UNKNOWN))


def _with_cells(nerf, scene, resolution: int = 64):
    """A copy of ``nerf`` with the cells of its scene's measured surfaces, as a fit with
    ``observed_resolution`` marks them."""
    from csa_core.nerf.visibility import ObservedCells

    nerf = copy.deepcopy(nerf)
    nerf.config.observed_resolution = resolution
    nerf.observed = ObservedCells(resolution)
    nerf.observed.mark(nerf.box, RayBank(scene.train_frames, scene.intrinsics).surface_points())
    return nerf


def test_the_fit_marks_the_cells_of_every_measured_surface_point(tiny_scene):
    from csa_core.nerf.fit import fit_semantic_nerf

    cfg = tiny_config(steps=10)
    cfg.observed_resolution = 64
    nerf, _ = fit_semantic_nerf(tiny_scene, "label-nyu40", cfg, device="cpu", progress=False)
    observed = nerf.observed
    assert observed is not None and observed.marked and observed.resolution == 64
    bank = RayBank(tiny_scene.train_frames, tiny_scene.intrinsics)
    points = torch.cat(list(bank.surface_points(chunk=1000)))
    assert points.shape[0] == sum(int((f.depth > 0).sum()) for f in tiny_scene.train_frames)
    assert bool(observed.contains(nerf.box, points).all())
    # Most of the box is empty space or behind the walls: not measured.
    assert 0.0 < float(observed.cells.float().mean()) < 0.5
    # `reference` builds none; `fast` builds them and leaves unseen surfaces unknown.
    assert preset("reference").observed_resolution == 0
    assert preset("fast").observed_resolution == 128 and preset("fast").render_unseen_unknown


def test_observed_cells_know_occlusion_where_the_frusta_do_not(tiny_nerf, tiny_scene):
    """A point 30 cm behind a measured surface, on the same training ray: inside that camera's
    image (the frustum test says seen) but in no cell a view measured (the cells say unseen)."""
    nerf = _with_cells(tiny_nerf, tiny_scene)
    f = tiny_scene.train_frames[0]
    origins, dirs = image_rays(tiny_scene.intrinsics, f.pose)
    depth = torch.as_tensor(f.depth.reshape(-1))
    surface = origins + dirs * depth[:, None]
    behind = origins + dirs * (depth[:, None] + 0.3)
    u = nerf.box.to_unit(behind)
    ok = (depth > 0) & ((u >= 0) & (u < 1)).all(-1)  # behind points inside the box
    assert int(ok.sum()) > 100
    n = int(ok.sum())
    pts = torch.cat([surface[ok], behind[ok]])
    by_cells = nerf.seen_surface_points(pts)
    assert bool(by_cells[:n].all())  # every measured point is seen
    assert float(by_cells[n:].float().mean()) < 0.2  # what lies behind it mostly not
    frusta = nerf.seen_by_training_cameras(pts, margin=0.01)
    assert bool(frusta.all())  # while the camera's image holds both
    nerf.observed = None  # a model without cells: the frusta
    assert torch.equal(nerf.seen_surface_points(pts, margin=0.01), frusta)


def test_with_cells_measured_pixels_off_every_cell_are_unknown_and_holes_keep_their_label(
    tiny_nerf, tiny_scene
):
    """With cells, a pixel whose measured surface lies in no cell a training view measured is
    unknown; a depth hole that renders a surface keeps the field's label (a surface the
    sensor never returns is in no cell although every view saw it); a training view's own
    measured pixels are all seen."""
    nerf = _with_cells(tiny_nerf, tiny_scene)
    f = tiny_scene.train_frames[0]
    intr = tiny_scene.intrinsics
    (plain,) = render_frames(nerf, [(f.name, f.pose)], intr, [f.depth], color=False)
    (own,) = render_frames(
        nerf, [(f.name, f.pose)], intr, [f.depth], color=False, unseen_unknown=True
    )
    assert np.array_equal(own.labels, plain.labels)  # every measured point marked its cell
    # The same view with the top half in a hole and the measured bottom half pushed 40 cm
    # further, behind the surfaces the views measured (into cells none of them marked).
    depth = f.depth.copy()
    top = np.zeros(depth.shape, dtype=bool)
    top[: depth.shape[0] // 2] = True
    depth[top] = 0
    bottom = (f.depth > 0) & ~top
    depth[bottom] += 0.4
    origins, dirs = image_rays(intr, f.pose)
    far = origins + dirs * torch.as_tensor(depth.reshape(-1))[:, None]
    off_cells = ~nerf.seen_surface_points(far).numpy().reshape(depth.shape) & bottom
    assert off_cells.sum() > 50
    (view,) = render_frames(
        nerf, [(f.name, f.pose)], intr, [depth], color=False, unseen_unknown=True
    )
    assert np.all(view.labels[off_cells] == UNKNOWN)
    assert np.all(view.labels[bottom & ~off_cells] != UNKNOWN)
    (marched,) = render_frames(nerf, [(f.name, f.pose)], intr, [depth], color=False)
    rendered = top & (marched.labels != UNKNOWN)
    assert rendered.sum() > 50
    assert np.array_equal(view.labels[rendered], marched.labels[rendered])
    # A view without depth: every ray that renders a surface keeps the field's label.
    (novel,) = render_frames(nerf, [(f.name, f.pose)], intr, color=False, unseen_unknown=True)
    (novel_plain,) = render_frames(nerf, [(f.name, f.pose)], intr, color=False)
    assert np.array_equal(novel.labels, novel_plain.labels)


def test_observed_cells_mark_points_and_their_neighbours():
    from csa_core.nerf.normalization import SceneBox
    from csa_core.nerf.visibility import ObservedCells

    box = SceneBox(center=(0.0, 0.0, 0.0), extent=8.0)  # cells of 1 m at resolution 8
    cells = ObservedCells(8)
    assert not cells.marked
    p = torch.tensor([[0.5, 0.5, 0.5], [100.0, 0.0, 0.0]])  # the second is outside the box
    cells.mark(box, p, dilate=0)
    assert int(cells.cells.sum()) == 1
    assert cells.contains(box, p).tolist() == [True, False]
    near = torch.tensor([[1.5, 0.5, 0.5], [2.5, 0.5, 0.5]])  # one and two cells away
    assert cells.contains(box, near).tolist() == [False, False]
    cells.mark(box, iter([p[:1], p[:1]]), dilate=1)  # an iterable of chunks, one cell around
    assert int(cells.cells.sum()) == 27
    assert cells.contains(box, near).tolist() == [True, False]
    with pytest.raises(ValueError, match="resolution"):
        ObservedCells(0)


def test_seen_surface_uses_the_measured_depth_first(tiny_nerf, tiny_scene):
    from csa_core.nerf.render import seen_surface

    f = tiny_scene.train_frames[0]
    origins, dirs = image_rays(tiny_scene.intrinsics, f.pose)
    n = origins.shape[0]
    out = {"depth": torch.zeros(n), "opacity": torch.zeros(n)}
    depth = torch.as_tensor(f.depth.reshape(-1))
    seen = seen_surface(tiny_nerf, origins, dirs, out, depth)
    assert torch.equal(seen, depth > 0)  # a training camera sees its own measured surface
    assert not seen_surface(tiny_nerf, origins, dirs, out).any()  # nothing rendered, no depth


# -- views without any depth ---------------------------------------------------------------


@pytest.mark.parametrize("band_color", [False, True])
def test_views_without_depth_render_around_the_estimate_when_asked(
    tiny_nerf, tiny_scene, band_color
):
    """``render_novel_estimate``: every ray of a view without depth renders in the band around
    its estimated surface and its labels agree with the full march; with the option off the
    render is the march itself (bit-identical to the explicit sampler). Colour is not compared:
    this 150-step field is too foggy for it (the fusion benchmark's ``novel-estimated`` row
    measures both on fitted scenes)."""
    marched = copy.deepcopy(tiny_nerf)
    marched.config.sampler.render_band_color = band_color
    assert not marched.config.sampler.render_novel_estimate  # the default
    estimated = copy.deepcopy(marched)
    estimated.config.sampler.render_novel_estimate = True
    real, made = estimated.render_sampler, []

    def spy(*args, **kw):
        made.append(real(*args, **kw))
        return made[-1]

    estimated.render_sampler = spy
    agree, total = 0, 0
    for f in tiny_scene.train_frames[::3]:
        poses = [(f.name, f.pose)]
        (new,) = render_frames(estimated, poses, tiny_scene.intrinsics)
        (old,) = render_frames(marched, poses, tiny_scene.intrinsics)
        (ref,) = render_frames(marched, poses, tiny_scene.intrinsics, sampler="occupancy")
        assert np.array_equal(old.labels, ref.labels) and np.array_equal(old.color, ref.color)
        agree += int((new.labels == old.labels).sum())
        total += new.labels.size
        assert new.color.shape == old.color.shape and new.color.dtype == np.uint8
    assert any(isinstance(m, DepthGuidedSampler) and m.estimate is not None for m in made)
    assert agree / total > 0.9, agree / total


@pytest.mark.parametrize("form", ["paper", "semantic_nerf"])
def test_rays_whose_samples_hold_no_weight_take_the_label_at_their_measured_surface(
    tiny_nerf, tiny_scene, form
):
    """A part thinner than the field resolves leaves its rays' band without weight: their
    labels come from the semantic head at the measured surface point, not from an all-zero
    (or uniform) distribution that reads as the first class, wall."""
    nerf = copy.deepcopy(tiny_nerf)
    nerf.config.loss.semantic_form = form
    with torch.no_grad():  # an empty field: zero density everywhere
        nerf.field.density_mlp[-1].weight[0].zero_()
        nerf.field.density_mlp[-1].bias[0] = -200.0
    f = tiny_scene.train_frames[0]
    (view,) = render_frames(nerf, [(f.name, f.pose)], tiny_scene.intrinsics, [f.depth], color=False)
    origins, dirs = image_rays(tiny_scene.intrinsics, f.pose)
    depth = torch.as_tensor(f.depth.reshape(-1))
    with torch.no_grad():
        points = origins + dirs * depth[:, None]
        _, logits = nerf.field.semantics(nerf.box.to_unit(points))
    expected = (logits.argmax(dim=-1) + 1).numpy().reshape(f.depth.shape)
    measured = f.depth > 0
    assert measured.any()
    assert np.array_equal(view.labels[measured], expected[measured])
    assert len(np.unique(view.labels[measured])) > 1  # the fitted head's classes, not one


def test_band_label_focus_is_a_gaussian_of_the_distance_to_the_measured_depth(tiny_nerf):
    """``render_band_label_sigma``: factor 1 at the measured depth, exp(-1/2) one standard
    deviation (that fraction of the band's half-width) away, 1 on rays without a measurement;
    no factors at all when the option is off."""
    nerf = copy.deepcopy(tiny_nerf)
    s = nerf.config.sampler
    depth = torch.tensor([2.0, 0.0, 3.0])
    half = s.depth_band + s.depth_band_fraction * depth
    t = torch.stack([depth, depth + 0.05 * (depth + 1), depth - 0.25 * half, depth + 0.25 * half])
    t = t.T.reshape(-1)  # 4 samples per ray, ray-major
    ri = torch.arange(3).repeat_interleave(4)
    samples = RaySamples(ri, t - 1e-3, t + 1e-3, 3)
    assert nerf._label_focus(samples, depth) is None
    s.render_band_label_sigma = 0.25
    focus = nerf._label_focus(samples, depth).reshape(3, 4)
    assert torch.allclose(focus[1], torch.ones(4))  # no measurement: plain weights
    for r in (0, 2):
        assert focus[r, 0] == pytest.approx(1.0)
        assert focus[r, 2] == pytest.approx(float(np.exp(-0.5)), rel=1e-4)
        assert focus[r, 3] == pytest.approx(float(np.exp(-0.5)), rel=1e-4)
        assert 0 < focus[r, 1] < 1
    with pytest.raises(ValueError, match="render_band_label_sigma"):
        SamplerConfig(render_band_label_sigma=-0.1)


@pytest.mark.parametrize("form", ["paper", "semantic_nerf"])
def test_band_label_focus_changes_labels_only(tiny_nerf, tiny_scene, form):
    """The Gaussian on the band's label weights leaves colour, depth and opacity as they
    were, changes the class distribution of some rays, and a narrow one reads the class the
    semantic field holds at the band sample nearest the measured depth."""
    nerf = copy.deepcopy(tiny_nerf)
    nerf.config.loss.semantic_form = form
    f = tiny_scene.train_frames[0]
    origins, dirs = image_rays(tiny_scene.intrinsics, f.pose)
    depth = torch.as_tensor(f.depth.reshape(-1))
    plain = nerf.render_rays(origins, dirs, depth=depth)
    nerf.config.sampler.render_band_label_sigma = 0.05
    focused = nerf.render_rays(origins, dirs, depth=depth)
    for key in ("rgb", "depth", "opacity"):
        assert torch.equal(plain[key], focused[key]), key
    measured = depth > 0
    assert not torch.allclose(plain["semantics"][measured], focused["semantics"][measured])
    # The band sample nearest the measured depth, and the class the field holds there.
    band = nerf.render_sampler(with_depth=True)
    with torch.no_grad():
        samples = nerf.sample(origins, dirs, band, depth=depth)
        gap = (samples.t_mids - depth[samples.ray_indices]).abs()
        nearest = torch.full((depth.shape[0],), float("inf")).scatter_reduce(
            0, samples.ray_indices, gap, reduce="amin"
        )
        pick = torch.nonzero(gap == nearest[samples.ray_indices]).squeeze(-1)
        rays = samples.ray_indices[pick]
        pts = origins[rays] + dirs[rays] * samples.t_mids[pick, None]
        _, logits = nerf.field.semantics(nerf.box.to_unit(pts))
    held = torch.full((depth.shape[0],), -1, dtype=torch.long)
    held[rays] = logits.argmax(dim=-1)
    opaque = measured & (focused["opacity"] > 0.5)
    assert opaque.sum() > 100

    def agree(out):
        return (out["semantics"].argmax(dim=-1) == held)[opaque].float().mean().item()

    assert agree(focused) > 0.97, agree(focused)
    assert agree(focused) > agree(plain)


@pytest.mark.parametrize("form", ["paper", "semantic_nerf"])
def test_surface_label_weight_mixes_the_surface_points_distribution_into_the_bands(
    tiny_nerf, tiny_scene, form
):
    """``render_surface_label_weight`` w: rays with a measured depth render (1 - w) x the
    band's class distribution + w x the semantic head's at their measured surface point;
    colour, depth, opacity and rays without a measurement stay as they were."""
    nerf = copy.deepcopy(tiny_nerf)
    nerf.config.loss.semantic_form = form
    f = tiny_scene.train_frames[0]
    origins, dirs = image_rays(tiny_scene.intrinsics, f.pose)
    depth = torch.as_tensor(_with_holes(f.depth).reshape(-1))
    measured = depth > 0
    assert measured.any() and (~measured).any()
    plain = nerf.render_rays(origins, dirs, depth=depth)
    with torch.no_grad():
        surface = torch.softmax(nerf.surface_logits(origins, dirs, depth), dim=-1)
    for w in (0.25, 1.0):
        nerf.config.sampler.render_surface_label_weight = w
        mixed = nerf.render_rays(origins, dirs, depth=depth)
        for key in ("rgb", "depth", "opacity"):
            assert torch.equal(plain[key], mixed[key]), key
        expected = (1 - w) * plain["semantics"][measured] + w * surface[measured]
        torch.testing.assert_close(mixed["semantics"][measured], expected)
        torch.testing.assert_close(mixed["semantics"][~measured], plain["semantics"][~measured])
    with pytest.raises(ValueError, match="render_surface_label_weight"):
        SamplerConfig(render_surface_label_weight=1.5)


def test_band_labels_behind_the_measured_depth_are_cut_at_the_given_distance(tiny_nerf):
    """``render_band_label_behind``: factor 1 up to that many metres behind the measured
    depth and 0 beyond; rays without a measurement keep every sample; with the Gaussian as
    well, the two factors multiply."""
    nerf = copy.deepcopy(tiny_nerf)
    s = nerf.config.sampler
    depth = torch.tensor([2.0, 0.0])
    t = torch.tensor([1.9, 2.0, 2.04, 2.06, 1.9, 2.0, 2.04, 2.06])
    samples = RaySamples(torch.arange(2).repeat_interleave(4), t - 1e-3, t + 1e-3, 2)
    s.render_band_label_behind = 0.05
    focus = nerf._label_focus(samples, depth).reshape(2, 4)
    assert focus[0].tolist() == [1.0, 1.0, 1.0, 0.0]
    assert focus[1].tolist() == [1.0, 1.0, 1.0, 1.0]
    s.render_band_label_sigma = 0.25
    both = nerf._label_focus(samples, depth).reshape(2, 4)
    assert both[0, 3] == 0 and 0 < both[0, 0] < 1 and both[0, 1] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="render_band_label_behind"):
        SamplerConfig(render_band_label_behind=-0.01)


def test_rays_whose_labels_read_no_sample_take_the_label_at_their_measured_surface(
    tiny_nerf, tiny_scene
):
    """A band whose weight lies wholly behind the cut (``render_band_label_behind``) has no
    class distribution left though it is opaque: such a ray takes the semantic head's class
    distribution at its measured surface point, as a ray without any weight does, never an
    all-zero one (wall); rays with a distribution, or without a measurement, keep theirs."""
    nerf = copy.deepcopy(tiny_nerf)
    f = tiny_scene.train_frames[0]
    origins, dirs = image_rays(tiny_scene.intrinsics, f.pose)
    depth = torch.as_tensor(f.depth.reshape(-1))[:6].clone()
    origins, dirs = origins[:6], dirs[:6]
    depth[:4] = depth[:4].clamp_min(0.5)
    depth[4:] = torch.tensor([0.0, 1.0])
    semantics = torch.zeros(6, 40)
    semantics[1, 3] = semantics[3, 7] = 1.0  # rays 1 and 3 read a distribution
    out = {"opacity": torch.tensor([0.9, 0.9, 0.9, 0.9, 0.9, 0.9]), "semantics": semantics}
    out["semantics"][5, 5] = 1.0
    before = out["semantics"].clone()
    nerf._surface_labels(origins, dirs, depth, out)
    with torch.no_grad():
        surface = torch.softmax(nerf.surface_logits(origins, dirs, depth), dim=-1)
    for ray in (0, 2):  # opaque, measured, no distribution: the surface point's
        torch.testing.assert_close(out["semantics"][ray], surface[ray])
    for ray in (1, 3, 4, 5):  # a distribution of their own, or no measurement
        assert torch.equal(out["semantics"][ray], before[ray])
