"""Fitting: bad inputs give clear errors, fits are deterministic and learn the scene."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch

from csa_core.data.scene import Scene
from csa_core.errors import CSAInputError
from csa_core.nerf.fit import fit_semantic_nerf
from csa_core.nerf.render import render_image
from tests.nerf.conftest import synthetic_scene, tiny_config
from tests.tiny_scenes import make_random_scene


def test_a_scene_of_one_frame_is_refused():
    scene = make_random_scene(n=1)
    with pytest.raises(CSAInputError, match="at least 2"):
        fit_semantic_nerf(scene, "label-nyu40", tiny_config(), progress=False)


def test_missing_label_folder_is_refused_with_the_folders_that_exist():
    scene = make_random_scene(n=3)
    with pytest.raises(CSAInputError, match="predictions.*label-nyu40"):
        fit_semantic_nerf(scene, "predictions", tiny_config(), progress=False)


def test_frames_of_another_size_are_refused():
    scene = make_random_scene(n=3)
    scene.frames[0].color = scene.frames[0].color[:-2]
    with pytest.raises(CSAInputError, match="frame 0"):
        fit_semantic_nerf(scene, None, tiny_config(), progress=False)


def _nan_depth(scene):
    scene.frames[1].depth[3, 4] = np.nan


def _infinite_depth(scene):
    scene.frames[2].depth[0, 0] = np.inf


def _negative_depth(scene):
    scene.frames[1].depth[5, 5] = -1.0


def _depth_of_another_size(scene):
    scene.frames[0].depth = scene.frames[0].depth[:-1]


def _depth_in_millimetres(scene):
    for f in scene.frames:
        f.depth = f.depth * 1000.0


def _labels_above_40(scene):
    scene.frames[1].labels["label-nyu40"] = np.full((24, 32), 41, np.uint16)


def _float_labels(scene):
    scene.frames[1].labels["label-nyu40"] = scene.frames[1].labels["label-nyu40"].astype(np.float32)


def _labels_of_another_size(scene):
    scene.frames[2].labels["label-nyu40"] = np.zeros((12, 16), np.uint8)


def _scaled_pose(scene):
    scene.frames[1].pose = scene.frames[1].pose @ np.diag([1.1, 1.1, 1.1, 1.0])


@pytest.mark.parametrize(
    ("break_it", "pattern"),
    [
        (_nan_depth, "frame 10: depth holds NaN or infinite values"),
        (_infinite_depth, "frame 20: depth holds NaN or infinite values"),
        (_negative_depth, "frame 10: depth holds negative values"),
        (_depth_of_another_size, "frame 0: depth is 32x23, colour is 32x24"),
        (_depth_in_millimetres, r"typical measured depth is [0-9.e+]+ m, outside 0.1..100 m"),
        (_labels_above_40, r"frame 10: labels 'label-nyu40': ids \[41\] are outside NYU40"),
        (_float_labels, "frame 10: labels 'label-nyu40': expected integer NYU40 ids"),
        (_labels_of_another_size, "frame 20: labels 'label-nyu40' are 16x12, scene is 32x24"),
        (_scaled_pose, "frame 10: rotation part is not orthonormal"),
    ],
)
def test_unusable_frames_in_memory_are_refused_before_any_work(break_it, pattern):
    """Scenes built in memory skip the folder reader's checks: the fit makes the same ones
    (NaN depth would otherwise reach the losses, ids above 40 index past the classes)."""
    scene = make_random_scene(n=4)
    break_it(scene)
    with pytest.raises(CSAInputError, match=pattern):
        fit_semantic_nerf(scene, "label-nyu40", tiny_config(), progress=False)


def test_no_depth_anywhere_falls_back_to_the_reference_sampler(caplog):
    scene = synthetic_scene(frames=4, size=(24, 16))
    for f in scene.frames:
        f.depth = None
    with caplog.at_level(logging.WARNING):
        nerf, stats = fit_semantic_nerf(scene, "label-nyu40", tiny_config(steps=3), progress=False)
    assert "no depth" in caplog.text
    assert np.isfinite(stats.final_loss)


def test_depth_with_holes_only_supervises_measured_pixels():
    scene = synthetic_scene(frames=4, size=(24, 16))
    for f in scene.frames:
        f.depth[::2] = 0.0
    _, stats = fit_semantic_nerf(scene, "label-nyu40", tiny_config(steps=3), progress=False)
    assert np.isfinite(stats.final_loss)


def test_fit_is_deterministic_for_a_seed():
    scene = synthetic_scene(frames=4, size=(24, 16))
    a, _ = fit_semantic_nerf(scene, "label-nyu40", tiny_config(steps=5), progress=False)
    b, _ = fit_semantic_nerf(scene, "label-nyu40", tiny_config(steps=5), progress=False)
    for (name, p), q in zip(
        a.field.state_dict().items(), b.field.state_dict().values(), strict=True
    ):
        assert torch.equal(p, q), name


def test_fit_learns_colour_depth_and_labels(tiny_scene, tiny_nerf):
    """After a short fit, training views render recognisably: not a proof of quality (the label
    fusion test and the benchmark measure that), but catches broken losses or samplers."""
    f = tiny_scene.train_frames[2]
    view = render_image(tiny_nerf, f.pose)
    err = np.abs(view.color.astype(float) - f.color).mean()
    assert err < 40, err
    valid = f.depth > 0
    assert np.median(np.abs(view.depth[valid] - f.depth[valid])) < 0.5
    gt = f.labels["label-nyu40"]
    assert (view.labels == gt)[gt > 0].mean() > 0.4


def test_labels_none_fits_colour_and_depth_only():
    scene = synthetic_scene(frames=4, size=(24, 16))
    nerf, _ = fit_semantic_nerf(scene, None, tiny_config(steps=3), progress=False)
    assert nerf.info.label_folder is None
    assert render_image(nerf, scene.frames[0].pose, semantics=False).labels is None


def test_scene_type_is_checked_before_any_work():
    empty = Scene(name="empty", intrinsics=make_random_scene(n=1).intrinsics, frames=[])
    with pytest.raises(CSAInputError):
        fit_semantic_nerf(empty, None, tiny_config(), progress=False)


def _label_accuracy(nerf, scene) -> float:
    from csa_core.nerf.render import render_views

    hit = total = 0
    views = render_views(nerf, scene, "train", color=False)
    for view, f in zip(views, scene.train_frames, strict=True):
        gt = f.labels["label-nyu40"]
        hit += int(((view.labels == gt) & (gt > 0)).sum())
        total += int((gt > 0).sum())
    return hit / total


def test_labels_fuse_as_well_in_a_world_frame_far_from_the_origin_and_y_up(tiny_scene, tiny_nerf):
    """Real captures come in any world frame: the scene 100 m from the origin and turned y-up
    gets the same scene box (moved with it) and fuses its labels as well as the original."""
    import copy

    move = np.array([[1.0, 0, 0, 100.0], [0, 0, -1, -50.0], [0, 1, 0, 3.0], [0, 0, 0, 1]])
    moved = copy.deepcopy(tiny_scene)
    for f in moved.frames:
        f.pose = move @ f.pose
    nerf, stats = fit_semantic_nerf(moved, "label-nyu40", tiny_config(steps=150), progress=False)
    assert np.isfinite(stats.final_loss)
    assert nerf.box.extent == pytest.approx(tiny_nerf.box.extent, rel=1e-6)
    centre = move[:3, :3] @ np.asarray(tiny_nerf.box.center) + move[:3, 3]
    np.testing.assert_allclose(nerf.box.center, centre, atol=1e-6)
    original = _label_accuracy(tiny_nerf, tiny_scene)
    assert original > 0.6
    assert _label_accuracy(nerf, moved) > original - 0.05  # 0.933 and 0.930 when written
