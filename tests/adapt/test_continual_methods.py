"""The baselines in the continual protocol: full R matrices, replay and memory records."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from csa_core.adapt.baselines.cotta import CoTTA, module_bytes
from csa_core.adapt.continual import run_continual
from csa_core.adapt.finetune import apply_adabn
from csa_core.adapt.methods import ContinualState
from csa_core.adapt.step import continual_step
from csa_core.errors import CSAInputError
from csa_core.eval.continual import continual_metrics
from csa_core.seg.adabn import batchnorm_layers
from csa_core.seg.checkpoint import load_checkpoint
from csa_core.seg.predict import evaluate_scene
from tests.adapt.conftest import tiny_config


def val_scores(model, scenes) -> np.ndarray:
    return np.array([evaluate_scene(model, s, "val").miou() for s in scenes])


def test_mapping_fills_r_and_replays_stored_pairs(
    pretrained, target_scenes, source_scenes, tmp_path
):
    scenes = target_scenes[:2]
    model = copy.deepcopy(pretrained)
    config = tiny_config()
    result = run_continual(
        model, scenes, config, tmp_path, source_scenes, save_model=False, method="mapping"
    )
    assert result.R.shape == (2, 2) and np.isfinite(result.R).all()
    assert result.metrics == pytest.approx(continual_metrics(result.R, result.b))
    assert np.allclose(result.R[-1], val_scores(model, scenes))
    first, second = result.steps
    assert first["replay"] == {} and second["replay"] == {scenes[0].name: config.replay.buffer_size}
    assert 0.0 <= second["pseudo_label_miou"] <= 1.0 and second["num_voxels"] > 0
    per_scene = result.memory_bytes["mapping_per_scene"]
    assert list(per_scene) == [s.name for s in scenes] and all(v > 0 for v in per_scene.values())
    assert result.memory_bytes["method_total"] == sum(per_scene.values())
    assert result.memory_bytes["pretrain_replay"] > 0
    assert first["memory_bytes"]["method_total"] < second["memory_bytes"]["method_total"]
    assert result.config["method"] == "mapping" and not (tmp_path / "memory").exists()


def test_cotta_fills_r_and_reports_the_teacher(pretrained, target_scenes, tmp_path):
    scenes = target_scenes[:2]
    model = copy.deepcopy(pretrained)
    config = tiny_config()
    config.seg.lr = 1e-3  # CoTTA's own lr (2.5e-6) is set by its config, not this one
    result = run_continual(model, scenes, config, tmp_path, method="cotta")
    assert result.R.shape == (2, 2) and np.isfinite(result.R).all()
    saved, _ = load_checkpoint(tmp_path / "model.safetensors")
    assert np.allclose(result.R[-1], val_scores(saved, scenes))  # R is the teacher's
    student = model.state_dict()
    assert any(
        not torch.equal(t, student[k])
        for k, t in saved.state_dict().items()
        if t.is_floating_point()
    )  # ... and the saved network is the teacher, not the student
    steps = np.cumsum([len(s.train_frames) for s in scenes]).tolist()
    assert [s["online_steps"] for s in result.steps] == steps  # one CoTTA for the sequence
    assert result.memory_bytes["method_total"] == 2 * module_bytes(pretrained)
    assert result.config["method_settings"]["lr"] == pytest.approx(2.5e-6)


def test_finetune_lower_bound_keeps_nothing(pretrained, target_scenes, tmp_path):
    scenes = target_scenes[:2]
    model = copy.deepcopy(pretrained)
    result = run_continual(
        model, scenes, tiny_config(), tmp_path, save_model=False, method="finetune"
    )
    assert np.isfinite(result.R).all() and result.memory_bytes["method_total"] == 0
    assert "replay" not in result.steps[1]
    assert np.allclose(result.R[-1], val_scores(model, scenes))


def test_unknown_method_is_an_input_error(pretrained, target_scenes, tmp_path):
    with pytest.raises(CSAInputError, match="unknown method 'magic'"):
        run_continual(pretrained, target_scenes[:1], tiny_config(), tmp_path, method="magic")
    assert not (tmp_path / "results.json").exists()


def _bn(model: torch.nn.Module) -> list[torch.Tensor]:
    return [t.clone() for bn in batchnorm_layers(model) for t in (bn.running_mean, bn.running_var)]


@pytest.mark.parametrize("placement", ["paper", "ours"])
def test_cotta_honours_adabn_like_every_method(placement, pretrained, target_scenes, monkeypatch):
    """With AdaBN placed ``ours`` the teacher (the reported network) ends the step with
    statistics of the scene's camera images, and the online pass runs with them too; placed
    as the paper (AdaBN only for networks trained on rendered images) or without AdaBN CoTTA
    keeps the source's."""
    scene = target_scenes[0]
    camera = [f.color for f in scene.train_frames]
    during: list[list[torch.Tensor]] = []
    original = CoTTA.adapt

    def adapt(self, frames):
        during.append(_bn(self.teacher) + _bn(self.student))
        return original(self, frames)

    monkeypatch.setattr(CoTTA, "adapt", adapt)
    source = _bn(pretrained)
    adapted_source = copy.deepcopy(pretrained)
    apply_adabn(adapted_source, camera, seed=0)
    for adabn in (True, False):
        during.clear()
        config = tiny_config()
        config.adabn, config.adabn_placement = adabn, placement
        model = copy.deepcopy(pretrained)
        state = ContinualState.start(config, "cotta")
        record = continual_step(state, model, scene)
        teacher = state.method.reported(model)
        (seen,) = during
        if adabn and placement == "ours":
            expected = _bn(adapted_source)
            assert all(torch.allclose(a, b) for a, b in zip(seen, expected + expected, strict=True))
        else:
            assert all(torch.equal(a, b) for a, b in zip(seen, source + source, strict=True))
        if adabn and placement == "ours":
            reference = copy.deepcopy(teacher)
            apply_adabn(reference, camera, seed=0)
            assert all(
                torch.allclose(a, b) for a, b in zip(_bn(teacher), _bn(reference), strict=True)
            )
        else:  # placed as the paper: CoTTA trains on camera images, so no AdaBN at the end
            assert all(torch.equal(a, b) for a, b in zip(_bn(teacher), source, strict=True))
        if adabn:
            assert record["batchnorm_pooled"] == [scene.name]  # pooled like the others
        else:
            assert record["batchnorm_pooled"] is None
