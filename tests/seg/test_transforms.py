"""Joint augmentation keeps labels on their pixels and never invents class ids."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from csa_core.seg.config import AugmentConfig
from csa_core.seg.transforms import JointAugment, image_to_tensor
from tests.seg.conftest import PATTERN_COLORS, make_pattern_scene

GEOMETRY_ONLY = AugmentConfig(brightness=0.0, contrast=0.0, saturation=0.0, hue=0.0)
NO_GEOMETRY = AugmentConfig(hflip=0.0, rotation_deg=0.0, crop_scale=(1.0, 1.0))


def _pair(seed: int = 0):
    frame = make_pattern_scene(
        n=1, size=(96, 72), seed=seed, noise=0.0, unknown_fraction=0.0
    ).frames[0]
    return image_to_tensor(frame.color), torch.from_numpy(frame.labels["label-nyu40"])


def _label_of_colour(image: torch.Tensor) -> np.ndarray:
    """The pattern class whose colour is nearest to each pixel (the label implied by the image)."""
    ids = np.array(list(PATTERN_COLORS))
    palette = np.array(list(PATTERN_COLORS.values()), np.float32)
    pix = image.permute(1, 2, 0).numpy().astype(np.float32)
    dist = ((pix[:, :, None, :] - palette[None, None]) ** 2).sum(-1)
    return ids[dist.argmin(-1)]


def _uniform_neighbourhood(lab: np.ndarray, radius: int) -> np.ndarray:
    """Pixels whose (2r+1)^2 neighbourhood holds a single label."""
    h, w = lab.shape
    pad = np.pad(lab, radius, mode="edge")
    same = np.ones_like(lab, bool)
    for dy in range(2 * radius + 1):
        for dx in range(2 * radius + 1):
            same &= pad[dy : dy + h, dx : dx + w] == lab
    return same


def test_misaligned_labels_would_be_caught():
    image, labels = _pair()
    lab = labels.flip(-1).numpy()
    interior = (lab > 0) & _uniform_neighbourhood(lab, radius=2)
    assert (_label_of_colour(image)[interior] == lab[interior]).mean() < 0.9


@pytest.mark.parametrize("seed", range(6))
def test_geometry_keeps_image_and_labels_aligned(seed):
    torch.manual_seed(seed)
    image, labels = _pair(seed)
    aug = JointAugment(
        AugmentConfig(
            rotation_deg=20.0, crop_scale=(0.3, 1.0), brightness=0, contrast=0, saturation=0, hue=0
        )
    )
    out_img, out_lab = aug(image, labels)
    assert out_img.shape == image.shape and out_img.dtype == torch.uint8
    assert out_lab.shape == labels.shape and out_lab.dtype == labels.dtype
    lab = out_lab.numpy()
    # Away from label boundaries (where the image is interpolated bilinearly and the labels
    # nearest-neighbour) every labelled pixel shows its class's colour.
    interior = (lab > 0) & _uniform_neighbourhood(lab, radius=2)
    assert interior.mean() > 0.5
    agree = (_label_of_colour(out_img)[interior] == lab[interior]).mean()
    assert agree > 0.995
    assert set(np.unique(lab)) <= set(np.unique(labels.numpy())) | {0}


def test_flip_alone_mirrors_both_exactly():
    image, labels = _pair()
    aug = JointAugment(
        AugmentConfig(
            hflip=1.0,
            rotation_deg=0.0,
            crop_scale=(1.0, 1.0),
            brightness=0,
            contrast=0,
            saturation=0,
            hue=0,
        )
    )
    out_img, out_lab = aug(image, labels)
    assert torch.equal(out_img, image.flip(-1)) and torch.equal(out_lab, labels.flip(-1))


def test_a_changed_config_reaches_an_augmenter_already_used():
    image, labels = _pair()
    config = AugmentConfig(
        hflip=0.0,
        rotation_deg=0.0,
        crop_scale=(1.0, 1.0),
        brightness=0,
        contrast=0,
        saturation=0,
        hue=0,
    )
    aug = JointAugment(config)
    out_img, out_lab = aug(image, labels)
    assert torch.equal(out_img, image) and torch.equal(out_lab, labels)
    config.hflip = 1.0  # as an override would set it
    out_img, out_lab = aug(image, labels)
    assert torch.equal(out_img, image.flip(-1)) and torch.equal(out_lab, labels.flip(-1))


def test_rotation_fills_with_unknown_not_a_class():
    torch.manual_seed(3)
    image, labels = _pair()
    aug = JointAugment(
        AugmentConfig(
            hflip=0.0,
            rotation_deg=30.0,
            crop_scale=(1.0, 1.0),
            brightness=0,
            contrast=0,
            saturation=0,
            hue=0,
        )
    )
    _, out_lab = aug(image, labels)
    corners = out_lab[[0, 0, -1, -1], [0, -1, 0, -1]]
    assert (labels > 0).all() and (corners == 0).sum() >= 2


def test_colour_jitter_changes_image_only():
    torch.manual_seed(0)
    image, labels = _pair()
    out_img, out_lab = JointAugment(NO_GEOMETRY)(image, labels)
    assert torch.equal(out_lab, labels)
    assert not torch.equal(out_img, image)


def test_default_augment_is_reproducible_with_a_seed():
    image, labels = _pair()
    torch.manual_seed(7)
    a = JointAugment()(image, labels)
    torch.manual_seed(7)
    b = JointAugment()(image, labels)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


def test_mismatched_shapes_are_rejected():
    with pytest.raises(ValueError, match="expected"):
        JointAugment()(
            torch.zeros(3, 8, 8, dtype=torch.uint8), torch.zeros(8, 9, dtype=torch.uint8)
        )
