"""The 7-Scenes importer on the real Kinect frames."""

from __future__ import annotations

import numpy as np
import pytest

from csa_core.data.scene_io import read_scene
from csa_core.data.sevenscenes import import_7scenes, load_7scenes
from csa_core.errors import CSAInputError


def test_import_real_frames(tmp_path, seven_scenes_dir):
    scene = import_7scenes(seven_scenes_dir, tmp_path / "kitchen", every=2, size=(160, 120))
    back = read_scene(tmp_path / "kitchen")
    assert len(scene) == len(back) == 50
    assert [f.name for f in back.frames[:3]] == ["0", "20", "40"]
    k = back.intrinsics  # the Kinect colour camera (default), not the file's depth camera
    assert (k.width, k.height) == (160, 120)
    assert k.fx == pytest.approx(523 / 4) and k.cx == pytest.approx((319.5 + 0.5) / 4 - 0.5)
    raw = np.loadtxt(seven_scenes_dir / "frame-000020.pose.txt")
    np.testing.assert_allclose(back.frames[1].pose[:3, :3], raw[:3, :3])
    # the colour camera sits 2.5 cm along the depth camera's x axis
    np.testing.assert_allclose(
        back.frames[1].pose[:3, 3], raw[:3, 3] + 0.025 * raw[:3, 0], atol=1e-9
    )
    depth = np.stack([f.depth for f in back.frames])
    valid = depth > 0
    # Kinect holes are kept as missing, not filled; the colour camera also sees a wider field
    # than the depth camera, so about (523 / 585)^2 = 80% of its image can have depth at all.
    assert 0.6 < valid.mean() < 0.8
    assert 0.3 < np.median(depth[valid]) < 4.0  # a kitchen, in metres
    # depth survives the uint16 mm round trip to the millimetre
    np.testing.assert_allclose(back.frames[1].depth, scene.frames[1].depth, atol=5e-4)
    assert back.num_train == 40 and len(back.val_frames) == 10


def test_depth_agrees_between_consecutive_real_frames(seven_scenes_dir):
    """Poses and depth are consistent: points of one frame land at similar depth in the next."""
    from csa_core.data.camera import backproject, project

    scene = load_7scenes(seven_scenes_dir, every=1, size=(160, 120))
    a, b = scene.frames[10], scene.frames[11]
    k = scene.intrinsics
    pts = backproject(a.depth, k, a.pose).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(1)]
    uv, z = project(pts, k, b.pose)
    ui, vi = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
    inside = (ui >= 0) & (ui < k.width) & (vi >= 0) & (vi < k.height) & (z > 0)
    zb = b.depth[vi[inside], ui[inside]]
    ok = zb > 0
    rel = np.abs(zb[ok] - z[inside][ok]) / zb[ok]
    assert inside.mean() > 0.5
    assert np.median(rel) < 0.05


def test_depth_camera_import_keeps_the_raw_frames(tmp_path, seven_scenes_dir):
    scene = import_7scenes(
        seven_scenes_dir, tmp_path / "raw", every=25, size=(160, 120), camera="depth"
    )
    k = scene.intrinsics
    assert k.fx == pytest.approx(585 / 4) and k.cx == pytest.approx((320 + 0.5) / 4 - 0.5)
    raw = np.loadtxt(seven_scenes_dir / "frame-000250.pose.txt")
    np.testing.assert_allclose(scene.frames[1].pose, raw)


def test_colour_import_equals_registering_the_raw_frames(seven_scenes_dir):
    """At full size the importer's colour camera is exactly the registration of the raw frames."""
    from csa_core.data.registration import KINECT_V1_COLOR, to_color_camera

    colour = load_7scenes(seven_scenes_dir, every=50)
    raw = load_7scenes(seven_scenes_dir, every=50, camera="depth")
    moved = to_color_camera(raw, KINECT_V1_COLOR)
    assert colour.intrinsics == moved.intrinsics
    for a, b in zip(colour.frames, moved.frames, strict=True):
        np.testing.assert_allclose(a.pose, b.pose)
        np.testing.assert_array_equal(a.depth, b.depth)
        assert np.array_equal(a.color, b.color)
    # the colour camera's wider border has no depth; most of the rest is measured
    assert 0.6 < np.mean([(f.depth > 0).mean() for f in colour.frames]) < 0.8


def test_bad_7scenes_folder(tmp_path):
    with pytest.raises(CSAInputError, match="no frame-XXXXXX.color.jpg"):
        load_7scenes(tmp_path)
    with pytest.raises(CSAInputError, match="--camera"):
        load_7scenes(tmp_path, camera="ir")
