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
    k = back.intrinsics
    assert (k.width, k.height) == (160, 120)
    assert k.fx == pytest.approx(585 / 4) and k.cx == pytest.approx((320 + 0.5) / 4 - 0.5)
    raw = np.loadtxt(seven_scenes_dir / "frame-000020.pose.txt")
    np.testing.assert_allclose(back.frames[1].pose, raw)
    depth = np.stack([f.depth for f in back.frames])
    valid = depth > 0
    assert 0.8 < valid.mean() < 0.99  # Kinect holes are kept as missing, not filled
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


def test_bad_7scenes_folder(tmp_path):
    with pytest.raises(CSAInputError, match="no frame-XXXXXX.color.jpg"):
        load_7scenes(tmp_path)
