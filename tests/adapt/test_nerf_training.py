"""Joint training's NeRF half keeps a NeRF's per-frame colour corrections working."""

from __future__ import annotations

import pytest
import torch

from csa_core.adapt.nerf_training import NerfLabelTrainer
from tests.nerf.test_appearance import exposed_scene, fit_with_corrections, log_gain_by_exposure


def test_label_trainer_trains_the_colour_corrections_of_each_frame():
    scene = exposed_scene()
    nerf = fit_with_corrections(scene, steps=30)
    before = nerf.appearance.params.detach().clone()
    spread_before = log_gain_by_exposure(nerf, scene)
    trainer = NerfLabelTrainer(nerf, scene, rays_per_step=512)
    trainer.set_labels({f.name: f.labels["label-nyu40"] for f in scene.train_frames})
    trainer.train(120)
    after = log_gain_by_exposure(nerf, scene)
    assert not torch.equal(nerf.appearance.params, before)
    assert after[0] < after[1] < after[2], after
    # Trained on, the corrections separate the exposures further than the short fit left them.
    assert after[2] - after[0] > spread_before[2] - spread_before[0] + 0.05, (spread_before, after)


def test_label_trainer_names_a_frame_without_a_correction():
    scene = exposed_scene()
    nerf = fit_with_corrections(scene, steps=5)
    outsider = scene.val_frames[0]
    with pytest.raises(ValueError, match=outsider.name):
        NerfLabelTrainer(nerf, scene, frames=[*scene.train_frames, outsider])
