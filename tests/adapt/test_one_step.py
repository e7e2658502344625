"""One-step adaptation in every mode, AdaBN on camera images, and the NeRF label updates."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch

from csa_core.adapt.finetune import apply_adabn
from csa_core.adapt.modes import adapt_one_step
from csa_core.adapt.nerf_training import NerfLabelTrainer
from csa_core.adapt.pseudo_labels import label_miou, make_pseudo_labels, render_pairs
from csa_core.adapt.replay import PretrainReplay
from csa_core.seg.adabn import batchnorm_layers
from tests.adapt.conftest import tiny_config


def _changed(a: torch.nn.Module, b: torch.nn.Module) -> float:
    """Largest absolute change of any trainable parameter."""
    return max(
        float((p - q).detach().abs().max())
        for p, q in zip(a.parameters(), b.parameters(), strict=True)
    )


def _bn_stats(model: torch.nn.Module) -> list[torch.Tensor]:
    return [t.clone() for bn in batchnorm_layers(model) for t in (bn.running_mean, bn.running_var)]


@pytest.mark.parametrize("mode", ["gi_nl", "ni_nl", "joint"])
def test_each_mode_adapts_end_to_end(mode, pretrained, target_scenes, source_scenes):
    scene = target_scenes[0]
    model = copy.deepcopy(pretrained)
    config = tiny_config(mode)
    config.collapse.enabled = False  # exercise the mode itself; the guard has its own tests
    pretrain = PretrainReplay.from_scenes(source_scenes, 0.25)
    result = adapt_one_step(model, scene, config, pretrain=pretrain)
    assert result.mode == mode and result.trained
    assert [d.action for d in result.decisions][0] == "continue"
    for scores in (result.before, result.after):
        assert set(scores) == {"val", "train"}
        assert all(0.0 <= v <= 1.0 for v in scores.values())
    assert 0.0 < result.prediction_miou <= 1.0 and 0.0 < result.pseudo_label_miou <= 1.0
    assert _changed(model, pretrained) > 1e-4
    assert result.nerf is not None and result.nerf.info.name == scene.name
    if mode == "joint":
        rounds = [h for h in result.history if "round" in h]
        assert [h["round"] for h in rounds] == [1, 2]
        assert all(math.isfinite(h["loss"]) and 0 < h["nerf_label_miou"] <= 1 for h in rounds)
    else:
        assert len(result.history) == config.seg.epochs
    assert all(math.isfinite(h["loss"]) for h in result.history)
    assert all(v >= 0 for v in result.seconds.values())


def test_ni_nl_ends_with_adabn_on_camera_images(pretrained, target_scenes):
    scene = target_scenes[1]
    config = tiny_config("ni_nl")
    config.collapse.enabled = False
    adapted = copy.deepcopy(pretrained)
    adapt_one_step(adapted, scene, config, evaluate_before=False)
    camera = [f.color for f in scene.train_frames]
    stats = _bn_stats(adapted)
    weights = [p.clone() for p in adapted.parameters()]
    # The statistics are exactly those of the camera images under the adapted weights ...
    apply_adabn(adapted, camera, seed=config.seg.seed)
    assert all(torch.allclose(a, b) for a, b in zip(stats, _bn_stats(adapted), strict=True))
    assert all(torch.equal(a, b) for a, b in zip(weights, adapted.parameters(), strict=True))
    # ... and not what training on rendered images left behind.
    config.adabn = False
    plain = copy.deepcopy(pretrained)
    adapt_one_step(plain, scene, config, evaluate_before=False)
    differs = [not torch.allclose(a, b) for a, b in zip(_bn_stats(plain), stats, strict=True)]
    assert sum(differs) > len(differs) // 2


def test_nerf_label_trainer_follows_new_labels(pretrained, target_scenes):
    scene = target_scenes[2]
    nerf, pseudo = make_pseudo_labels(pretrained, scene, tiny_config().nerf)
    truth = {f.name: f.labels["label-nyu40"] for f in scene.train_frames}
    before = label_miou(pseudo.labels, scene)
    trainer = NerfLabelTrainer(nerf, scene, rays_per_step=512)
    trainer.set_labels(truth)
    first = trainer.train_semantics(1)
    last = trainer.train_semantics(60)
    _, labels = render_pairs(nerf, scene)
    assert last < first
    assert label_miou(labels, scene) > before
    assert set(np.unique(np.concatenate([v.ravel() for v in labels.values()]))) <= set(range(1, 41))


@pytest.mark.parametrize("mode", ["ni_nl", "joint"])
def test_unlabelled_scene_adapts_without_scores(mode, pretrained, target_scenes):
    """The product's case: a new scene without any ground truth adapts; scores stay empty."""
    scene = copy.deepcopy(target_scenes[2])
    for f in scene.frames:
        f.labels.clear()
    model = copy.deepcopy(pretrained)
    before = [p.detach().clone() for p in model.parameters()]
    result = adapt_one_step(model, scene, tiny_config(mode))
    assert result.before == {} and result.after == {}
    assert math.isnan(result.prediction_miou) and math.isnan(result.pseudo_label_miou)
    assert result.trained
    assert any(not torch.equal(a, b) for a, b in zip(before, model.parameters(), strict=True))
