"""Depth-to-colour registration: exact for a co-located camera, geometric for an offset one, and
the multi-view colour consistency measure prefers the true camera."""

from __future__ import annotations

import numpy as np

from csa_core.data.camera import Intrinsics, backproject
from csa_core.data.registration import (
    ColorCamera,
    color_consistency_rms,
    color_pose,
    estimate_color_camera,
    register_depth,
    to_color_camera,
)
from csa_core.data.scene import Frame, Scene
from tests.nerf.conftest import synthetic_scene
from tests.tiny_scenes import look_at_pose


def test_a_co_located_identical_camera_keeps_depth_and_poses():
    scene = synthetic_scene(frames=3, size=(32, 24))
    out = to_color_camera(scene, ColorCamera(scene.intrinsics))
    assert out.intrinsics == scene.intrinsics
    for a, b in zip(scene.frames, out.frames, strict=True):
        assert np.array_equal(a.color, b.color)
        assert np.allclose(a.pose, b.pose)
        assert np.allclose(a.depth, b.depth)


def test_registered_depth_is_the_same_surface_seen_from_the_colour_camera():
    depth_cam = Intrinsics(40.0, 40.0, 15.5, 11.5, 32, 24)
    color_cam = Intrinsics(34.0, 34.0, 16.5, 11.0, 32, 24)  # wider view, shifted centre
    offset = (0.05, 0.0, 0.0)
    v, u = np.mgrid[0:24, 0:32]
    depth = (2.0 + 0.02 * u + 0.01 * v).astype(np.float32)  # a tilted plane
    reg = register_depth(depth, depth_cam, color_cam, offset)
    pts = backproject(depth.astype(np.float64), depth_cam, np.eye(4)).reshape(-1, 3)
    pts -= np.asarray(offset)
    # Every registered pixel holds the z of a point of the plane that projects into it.
    ok = reg > 0
    assert 0.6 < ok.mean() < 1.0  # the colour camera sees past the depth camera's border
    pu = np.round(pts[:, 0] / pts[:, 2] * color_cam.fx + color_cam.cx).astype(int)
    pv = np.round(pts[:, 1] / pts[:, 2] * color_cam.fy + color_cam.cy).astype(int)
    for y, x in zip(*np.nonzero(ok), strict=True):
        hit = (pu == x) & (pv == y)
        assert np.isclose(reg[y, x], pts[hit, 2].min(), atol=1e-5)


def test_colour_camera_pose_moves_the_centre_along_the_camera_axes():
    pose = np.eye(4)
    pose[:3, :3] = [[0, 0, 1], [1, 0, 0], [0, 1, 0]]
    pose[:3, 3] = [1, 2, 3]
    out = color_pose(pose, ColorCamera(Intrinsics(1, 1, 0, 0, 2, 2), (0.1, 0.0, 0.0)))
    assert np.allclose(out[:3, 3], [1.0, 2.1, 3.0]) and np.allclose(out[:3, :3], pose[:3, :3])


def _room_colour(x: np.ndarray) -> np.ndarray:
    """A smooth colour texture on the walls of the test room (no exposure change, no shading)."""
    r = 128 + 90 * np.sin(3.1 * x[..., 0] + 1.7 * x[..., 1] + 0.5)
    g = 128 + 90 * np.sin(2.3 * x[..., 1] - 2.9 * x[..., 2])
    b = 128 + 90 * np.sin(1.9 * x[..., 2] + 2.7 * x[..., 0] - 1.0)
    return np.stack([r, g, b], axis=-1)


def _cast(intr: Intrinsics, pose: np.ndarray) -> np.ndarray:
    """World points where the camera's pixel rays leave the box room [-2, 2]^2 x [0, 3]."""
    v, u = np.mgrid[0 : intr.height, 0 : intr.width]
    d = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones(u.shape)], -1)
    d = d @ pose[:3, :3].T
    o = pose[:3, 3]
    lo, hi = np.array([-2.0, -2.0, 0.0]), np.array([2.0, 2.0, 3.0])
    with np.errstate(divide="ignore"):
        t = np.maximum((lo - o) / d, (hi - o) / d).min(axis=-1)
    return o + d * t[..., None]


def _rgbd_rig_scene(color: ColorCamera, n: int = 8) -> Scene:
    """Depth from the depth camera at the poses, colour from ``color`` rigidly attached to it."""
    k = Intrinsics(52.0, 52.0, 31.5, 23.5, 64, 48)
    frames = []
    for i in range(n):
        a = 0.25 * i
        pose = look_at_pose(
            [0.6 * np.cos(a), 0.6 * np.sin(a), 1.4], [np.cos(a + 1.2) * 2, np.sin(a + 1.2) * 2, 1.2]
        )
        pts = _cast(k, pose)
        inv = np.linalg.inv(pose)
        depth = (pts @ inv[:3, :3].T + inv[:3, 3])[..., 2].astype(np.float32)
        rgb = _room_colour(_cast(color.at_size(64, 48), color_pose(pose, color)))
        frames.append(Frame(str(i), np.clip(rgb, 0, 255).astype(np.uint8), pose, depth))
    return Scene("rig", k, frames)


def test_consistency_prefers_the_true_colour_camera_and_the_search_finds_it():
    true = ColorCamera(Intrinsics(46.0, 46.0, 32.5, 22.5, 64, 48), (0.03, 0.0, 0.0))
    scene = _rgbd_rig_scene(true)
    as_depth = color_consistency_rms(scene, None)  # colour read with the depth camera's rays
    right = color_consistency_rms(scene, true)
    assert right < 2.0 and as_depth > 5 * right, (right, as_depth)
    found, rms = estimate_color_camera(
        scene, ColorCamera(scene.intrinsics), steps=(2.0, 1.0, 1.0, 0.01)
    )
    k = found.intrinsics
    assert abs(k.fx - 46.0) < 1.0 and abs(k.cx - 32.5) < 0.5 and abs(k.cy - 22.5) < 0.5, found
    assert abs(found.offset[0] - 0.03) < 0.015 and rms < 2.0 * right + 0.5
    # Registered to its colour camera, the scene's depth is the depth seen by that camera.
    reg = to_color_camera(scene, true)
    f = reg.frames[3]
    pts = _cast(reg.intrinsics, f.pose)
    inv = np.linalg.inv(f.pose)
    z = (pts @ inv[:3, :3].T + inv[:3, 3])[..., 2]
    ok = f.depth > 0
    assert ok.mean() > 0.6 and np.median(np.abs(f.depth[ok] - z[ok])) < 0.02
