"""Joint image + label augmentation for training segmentation networks.

Geometry (crop, flip, rotation) moves image and labels together; labels are only ever
resampled nearest-neighbour and pixels that come from outside the image get label 0
(unknown, ignored by the loss), so augmentation never invents a class id. Colour jitter
touches the image only.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
from torch import Tensor
from torchvision import tv_tensors
from torchvision.transforms import v2

from csa_core.data.nyu40 import UNKNOWN
from csa_core.seg.config import AugmentConfig


class JointAugment:
    """Random augmentation of one (image, labels) pair, drawn from torch's global RNG.

    Call with a (3, H, W) uint8 image tensor and an (H, W) integer label tensor; returns the
    augmented pair at the same size and dtypes. Seed with ``torch.manual_seed`` for
    reproducible draws.
    """

    def __init__(self, config: AugmentConfig | None = None):
        self.config = config or AugmentConfig()
        self._pipelines: dict[tuple, v2.Compose] = {}

    def _pipeline(self, height: int, width: int) -> v2.Compose:
        # Keyed by the config's values too: ``AugmentConfig`` is mutable (``--set
        # seg.augment.*``), and a pipeline built before a change must not outlive it.
        key = (height, width, dataclasses.astuple(self.config))
        if key not in self._pipelines:
            c = self.config
            aspect = width / height
            steps: list[v2.Transform] = []
            if c.rotation_deg > 0:
                steps.append(
                    v2.RandomRotation(
                        c.rotation_deg, fill={tv_tensors.Image: 0, tv_tensors.Mask: UNKNOWN}
                    )
                )
            if c.crop_scale != (1.0, 1.0):
                jitter = 1.0 + c.crop_aspect_jitter
                steps.append(
                    v2.RandomResizedCrop(
                        (height, width),
                        scale=c.crop_scale,
                        ratio=(aspect / jitter, aspect * jitter),
                        antialias=True,
                    )
                )
            if c.hflip > 0:
                steps.append(v2.RandomHorizontalFlip(c.hflip))
            if max(c.brightness, c.contrast, c.saturation, c.hue) > 0:
                steps.append(v2.ColorJitter(c.brightness, c.contrast, c.saturation, c.hue))
            if c.grayscale > 0:
                steps.append(v2.RandomGrayscale(c.grayscale))
            # Every strength zero is a valid config (an override can set it): the identity.
            self._pipelines[key] = v2.Compose(steps or [v2.Identity()])
        return self._pipelines[key]

    def __call__(self, image: Tensor, labels: Tensor) -> tuple[Tensor, Tensor]:
        if image.ndim != 3 or image.shape[0] != 3 or labels.shape != image.shape[1:]:
            raise ValueError(
                "JointAugment: expected (3, H, W) image and (H, W) labels, got "
                f"{tuple(image.shape)} and {tuple(labels.shape)}"
            )
        img, lab = self._pipeline(*labels.shape)(tv_tensors.Image(image), tv_tensors.Mask(labels))
        return img.as_subclass(Tensor), lab.as_subclass(Tensor)


def image_to_tensor(image: np.ndarray) -> Tensor:
    """(H, W, 3) uint8 RGB array -> (3, H, W) uint8 tensor (no copy when possible)."""
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got {image.dtype} {image.shape}")
    return torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)


def to_float_image(image: Tensor) -> Tensor:
    """uint8 image tensor(s) -> float32 in [0, 1]; float input is returned unchanged."""
    return image.float().div_(255.0) if image.dtype == torch.uint8 else image
