"""Segmentation loss: softmax cross-entropy over the 40 NYU40 channels, unknown pixels ignored.

The official implementation passes softmax probabilities into a loss that applies softmax
again, which flattens the gradients; here the logits go straight into one log-softmax.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

IGNORE_INDEX = -100  # target value of unknown pixels (NYU40 id 0); PyTorch's default


def nyu40_to_target(labels: Tensor) -> Tensor:
    """NYU40 ids (0..40) -> class indices for the network's channels (id - 1), 0 -> IGNORE_INDEX."""
    target = labels.long() - 1
    return target.masked_fill_(target < 0, IGNORE_INDEX)


def segmentation_loss(logits: Tensor, labels: Tensor, weight: Tensor | None = None) -> Tensor:
    """Mean cross-entropy over pixels with a known label.

    ``logits``: (B, C, H, W) raw scores; ``labels``: (B, H, W) NYU40 ids, 0 = unknown. A
    batch without any known pixel gives a zero loss that still depends on the logits, so a
    training step never produces NaN.
    """
    if logits.ndim != 4 or labels.shape != (logits.shape[0], *logits.shape[2:]):
        raise ValueError(
            f"segmentation_loss: logits {tuple(logits.shape)} and labels {tuple(labels.shape)} do "
            "not match"
        )
    target = nyu40_to_target(labels)
    if int(target.max()) >= logits.shape[1]:
        raise ValueError(
            f"segmentation_loss: label id {int(target.max()) + 1} exceeds the {logits.shape[1]} "
            "outputs"
        )
    if not bool((target != IGNORE_INDEX).any()):
        return logits.sum() * 0.0
    return F.cross_entropy(logits, target, weight=weight, ignore_index=IGNORE_INDEX)


def pixel_accuracy(logits: Tensor, labels: Tensor) -> float:
    """Fraction of known pixels whose arg-max channel is the label (NaN without known pixels)."""
    target = nyu40_to_target(labels)
    known = target != IGNORE_INDEX
    if not bool(known.any()):
        return float("nan")
    with torch.no_grad():
        return float((logits.argmax(1)[known] == target[known]).float().mean())
