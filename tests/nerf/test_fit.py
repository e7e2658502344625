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
