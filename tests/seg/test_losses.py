"""The loss: one softmax, unknown pixels ignored, equal to a hand computation."""

from __future__ import annotations

import math

import pytest
import torch

from csa_core.seg.losses import IGNORE_INDEX, nyu40_to_target, pixel_accuracy, segmentation_loss


def test_targets_shift_ids_and_ignore_unknown():
    labels = torch.tensor([[0, 1, 40]], dtype=torch.uint8)
    assert nyu40_to_target(labels).tolist() == [[IGNORE_INDEX, 0, 39]]


def test_loss_equals_hand_computed_cross_entropy():
    # One image of 1x3 pixels, 3 channels (NYU40 ids 1..3); the middle pixel is unknown.
    logits = torch.tensor([[[[2.0, 5.0, 0.0]], [[0.0, -1.0, 1.0]], [[1.0, 3.0, 3.0]]]])
    labels = torch.tensor([[[1, 0, 3]]])
    # pixel 0: -log softmax([2, 0, 1])[0];  pixel 2: -log softmax([0, 1, 3])[2]
    p0 = -(2.0 - math.log(math.exp(2) + math.exp(0) + math.exp(1)))
    p2 = -(3.0 - math.log(math.exp(0) + math.exp(1) + math.exp(3)))
    assert segmentation_loss(logits, labels).item() == pytest.approx((p0 + p2) / 2, rel=1e-6)


def test_single_softmax_not_double():
    # Confident, correct logits must give a loss near 0; softmax applied twice could not go below
    # log(1 + (C-1)/e).
    logits = torch.zeros(1, 40, 1, 1)
    logits[0, 6] = 30.0
    labels = torch.tensor([[[7]]])
    assert segmentation_loss(logits, labels).item() < 1e-6


def test_unknown_pixels_neither_count_nor_receive_gradient():
    torch.manual_seed(0)
    logits = torch.randn(2, 40, 4, 5, requires_grad=True)
    labels = torch.randint(1, 41, (2, 4, 5))
    labels[:, :2] = 0
    loss = segmentation_loss(logits, labels)
    loss.backward()
    assert logits.grad[:, :, :2].abs().max() == 0
    assert logits.grad[:, :, 2:].abs().max() > 0
    changed = logits.detach().clone()
    changed[:, :, :2] = 100.0 * torch.randn_like(changed[:, :, :2])
    assert segmentation_loss(changed, labels).item() == pytest.approx(loss.item(), rel=1e-6)


def test_all_unknown_batch_gives_zero_not_nan():
    logits = torch.randn(1, 40, 3, 3, requires_grad=True)
    loss = segmentation_loss(logits, torch.zeros(1, 3, 3, dtype=torch.long))
    assert loss.item() == 0.0
    loss.backward()
    assert logits.grad is not None and logits.grad.abs().max() == 0


def test_shape_and_range_errors():
    with pytest.raises(ValueError, match="do not match"):
        segmentation_loss(torch.zeros(1, 40, 3, 3), torch.zeros(1, 3, 4, dtype=torch.long))
    with pytest.raises(ValueError, match="exceeds"):
        segmentation_loss(torch.zeros(1, 3, 1, 1), torch.tensor([[[4]]]))


def test_pixel_accuracy_ignores_unknown():
    logits = torch.zeros(1, 3, 1, 3)
    logits[0, 0, 0, 0] = logits[0, 1, 0, 1] = logits[0, 2, 0, 2] = 1.0  # predicts ids 1, 2, 3
    assert pixel_accuracy(logits, torch.tensor([[[1, 0, 2]]])) == pytest.approx(0.5)
    assert math.isnan(pixel_accuracy(logits, torch.zeros(1, 1, 3, dtype=torch.long)))
