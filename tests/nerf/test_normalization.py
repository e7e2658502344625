"""Scene normalisation: metric world <-> unit cube."""

from __future__ import annotations

import numpy as np
import pytest
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


def _looking_at(target: np.ndarray, origins: np.ndarray) -> list:
    """Camera-to-world poses (OpenCV axes) at ``origins``, each looking at ``target``."""
    poses = []
    for o in origins:
        z = (target - o) / np.linalg.norm(target - o)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        pose = np.eye(4)
        pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, np.cross(z, x), z, o
        poses.append(pose)
    return poses


def test_fixed_cube_is_centred_where_the_cameras_look_and_scaled_by_their_distance():
    from types import SimpleNamespace

    from csa_core.errors import CSAInputError
    from csa_core.nerf.config import NerfConfig
    from csa_core.nerf.normalization import attention_point, fitted_box, fixed_cube_box

    target = np.array([1.0, 2.0, 0.5])
    angles = np.linspace(0.0, 5.0, 9)
    origins = target + np.stack([2 * np.cos(angles), 2 * np.sin(angles), 0.6 + 0 * angles], 1)
    poses = _looking_at(target, origins)
    np.testing.assert_allclose(attention_point(np.stack(poses)), target, atol=1e-9)
    frames = [SimpleNamespace(pose=p, depth=None) for p in poses]
    box = fixed_cube_box(frames, bound=4.0, camera_distance=1.32)
    distance = float(np.hypot(2.0, 0.6))  # every camera's distance from the target
    np.testing.assert_allclose(box.center, target, atol=1e-9)
    assert box.extent == pytest.approx(8.0 * distance / 1.32)
    # In the official units (cameras 1.32 from the centre) the grid spans [-4, 4]^3.
    official = (box.to_unit(torch.tensor(origins)) - 0.5) * 8.0
    np.testing.assert_allclose(official.norm(dim=1).numpy(), 1.32, rtol=1e-9)
    assert fixed_cube_box(frames, bound=2.0).extent == pytest.approx(box.extent / 2)
    # The config chooses: the scene's box by default, the cube with normalization=cube.
    scene = make_random_scene(n=6)
    assert fitted_box(scene.frames, scene.intrinsics, NerfConfig()) == scene_box_from_frames(
        scene.frames, scene.intrinsics
    )
    cube = NerfConfig(normalization="cube", cube_bound=3.0)
    assert fitted_box(scene.frames, scene.intrinsics, cube) == fixed_cube_box(scene.frames, 3.0)
    # Parallel optical axes look at no common point: the mean camera centre.
    straight = [np.eye(4) for _ in range(3)]
    for k, p in enumerate(straight):
        p[0, 3] = float(k)
    np.testing.assert_allclose(attention_point(np.stack(straight)), [1.0, 0.0, 0.0])
    with pytest.raises(CSAInputError, match="normalization=box"):
        fixed_cube_box([SimpleNamespace(pose=np.eye(4), depth=None)])
    with pytest.raises(ValueError, match="normalization"):
        NerfConfig(normalization="sphere")
    with pytest.raises(ValueError, match="cube_bound"):
        NerfConfig(cube_bound=0.0)
