"""Scene normalisation: metric world <-> unit cube."""

from __future__ import annotations

import numpy as np
import torch

from csa_core.data.camera import backproject
from csa_core.nerf.normalization import (
    DEFAULT_EXTENT_WITHOUT_DEPTH,
    SceneBox,
    scene_box_from_frames,
)
from tests.tiny_scenes import make_random_scene


def test_unit_cube_round_trip_is_exact_to_float_precision():
    box = SceneBox((1.5, -2.0, 0.25), 7.3)
    x = torch.randn(1000, 3, dtype=torch.float64) * 3
    torch.testing.assert_close(box.from_unit(box.to_unit(x)), x, rtol=0, atol=1e-12)
    assert box.to_unit(torch.tensor([[1.5, -2.0, 0.25]])).tolist() == [[0.5, 0.5, 0.5]]
    assert SceneBox.from_dict(box.to_dict()) == box


def test_box_holds_cameras_and_most_surface_points():
    scene = make_random_scene(n=6)
    box = scene_box_from_frames(scene.frames, scene.intrinsics)
    cams = torch.tensor(np.stack([f.pose[:3, 3] for f in scene.frames]))
    u = box.to_unit(cams)
    assert bool(((u > 0) & (u < 1)).all())
    pts = np.concatenate(
        [backproject(f.depth, scene.intrinsics, f.pose)[f.depth > 0] for f in scene.frames]
    )
    inside = ((box.to_unit(torch.tensor(pts)) >= 0) & (box.to_unit(torch.tensor(pts)) <= 1)).all(-1)
    assert float(inside.float().mean()) > 0.99


def test_without_depth_the_box_surrounds_the_cameras():
    scene = make_random_scene(n=4)
    for f in scene.frames:
        f.depth = None
    box = scene_box_from_frames(scene.frames, scene.intrinsics)
    assert box.extent >= DEFAULT_EXTENT_WITHOUT_DEPTH


def test_ray_interval_enters_and_leaves_the_box():
    box = SceneBox((0.0, 0.0, 0.0), 2.0)
    o = torch.tensor([[0.0, 0.0, -5.0], [0.0, 0.0, 0.0], [5.0, 5.0, -5.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    t0, t1 = box.ray_interval(o, d, near=0.05)
    torch.testing.assert_close(t0[:2], torch.tensor([4.0, 0.05]))
    torch.testing.assert_close(t1[:2], torch.tensor([6.0, 1.0]))
    assert t1[2] <= t0[2]  # misses


def test_far_outliers_do_not_stretch_the_box():
    """A sensor's far outliers (3% of the pixels 20-60 m away) leave the room's box within a
    small factor; they used to set the 99.5th percentile, and the box grew 16-fold to 58 m."""
    from tests.nerf.conftest import synthetic_scene

    scene = synthetic_scene(frames=6, size=(32, 24))
    clean = scene_box_from_frames(scene.frames, scene.intrinsics)
    rng = np.random.default_rng(0)
    for f in scene.frames:
        far = rng.random(f.depth.shape) < 0.03
        f.depth[far] = rng.uniform(20.0, 60.0, int(far.sum()))
    noisy = scene_box_from_frames(scene.frames, scene.intrinsics)
    assert clean.extent < 10.0
    assert noisy.extent < 2.5 * clean.extent, (noisy.extent, clean.extent)
