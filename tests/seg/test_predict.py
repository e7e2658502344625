"""Prediction: NYU40 ids 1..40, batching that changes nothing, modes restored."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from csa_core.errors import CSAInputError
from csa_core.seg.models import build_model
from csa_core.seg.predict import evaluate_scene, predict_labels, predict_logits, predict_scene


@pytest.fixture
def model():
    torch.manual_seed(0)
    return build_model()


def test_labels_are_nyu40_ids_of_the_input_size(model, pattern_scene):
    images = np.stack([f.color for f in pattern_scene.frames[:5]])
    labels = predict_labels(model, images, batch_size=2, device="cpu")
    assert labels.shape == (5, 48, 64) and labels.dtype == np.uint8
    assert labels.min() >= 1 and labels.max() <= 40
    single = predict_labels(model, images[0], device="cpu")
    assert single.shape == (48, 64)
    assert np.array_equal(single, labels[0])


def test_batch_size_does_not_change_predictions(model, pattern_scene):
    images = [f.color for f in pattern_scene.frames[:5]]
    a = predict_logits(model, images, batch_size=1, device="cpu")
    b = predict_logits(model, images, batch_size=5, device="cpu")
    assert torch.allclose(a, b, atol=1e-4)


def test_eval_mode_is_used_and_training_mode_restored(model, pattern_scene):
    model.train()
    image = pattern_scene.frames[0].color
    first = predict_logits(model, [image], device="cpu")
    assert model.training
    bn_before = {k: v.clone() for k, v in model.state_dict().items()}
    second = predict_logits(model, [image], device="cpu")
    assert torch.equal(first, second)
    assert all(torch.equal(bn_before[k], v) for k, v in model.state_dict().items())


def test_other_network_size_returns_labels_at_image_size(model, pattern_scene):
    labels = predict_labels(model, [pattern_scene.frames[0].color], size=(32, 24), device="cpu")
    assert labels.shape == (1, 48, 64)


def test_predict_scene_and_evaluate_scene(model, pattern_scene):
    labels = predict_scene(model, pattern_scene, "val", device="cpu")
    assert list(labels) == [f.name for f in pattern_scene.val_frames]
    matrix = evaluate_scene(model, pattern_scene, "val", device="cpu")
    gt = np.stack([f.labels["label-nyu40"] for f in pattern_scene.val_frames])
    assert matrix.num_pixels == int((gt > 0).sum())
    with pytest.raises(CSAInputError, match="no 'pseudo' labels"):
        evaluate_scene(model, pattern_scene, "val", label_folder="pseudo")


def test_bad_inputs_are_errors(model):
    with pytest.raises(ValueError, match="no images"):
        predict_logits(model, [])
    with pytest.raises(ValueError, match="same size"):
        predict_logits(model, [np.zeros((8, 8, 3), np.uint8), np.zeros((8, 9, 3), np.uint8)])
    with pytest.raises(ValueError, match="uint8 RGB"):
        predict_labels(model, [np.zeros((8, 8, 3), np.float32)])
