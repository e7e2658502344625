"""Datasets of (image, labels) pairs from scenes or arrays."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from csa_core.errors import CSAInputError
from csa_core.seg.dataset import SegmentationDataset
from csa_core.seg.transforms import JointAugment
from tests.seg.conftest import make_pattern_scene


def test_from_scenes_follows_the_split_and_types(pattern_scene):
    other = make_pattern_scene(n=5, seed=3, name="other")
    train = SegmentationDataset.from_scenes([pattern_scene, other], "train")
    val = SegmentationDataset.from_scenes([pattern_scene, other], "val")
    assert len(train) == pattern_scene.num_train + other.num_train
    assert len(val) == len(pattern_scene.val_frames) + len(other.val_frames)
    assert train.names[0] == "pattern/0" and val.names[-1] == "other/4"
    image, labels = train[0]
    assert image.shape == (3, 48, 64) and image.dtype == torch.float32
    assert 0.0 <= image.min() and image.max() <= 1.0
    assert labels.shape == (48, 64) and labels.dtype == torch.int64
    frame = pattern_scene.frames[0]
    assert torch.equal(labels, torch.from_numpy(frame.labels["label-nyu40"]).long())
    assert torch.allclose(image, torch.from_numpy(frame.color).permute(2, 0, 1).float() / 255)


def test_transform_is_applied_per_item(pattern_scene):
    ds = SegmentationDataset.from_scenes(pattern_scene, "all", transform=JointAugment())
    torch.manual_seed(0)
    a = ds[0]
    torch.manual_seed(1)
    b = ds[0]
    assert not torch.equal(a[0], b[0])


def test_missing_label_folder_and_bad_pairs_are_errors(pattern_scene):
    with pytest.raises(CSAInputError, match="no 'pseudo' labels"):
        SegmentationDataset.from_scenes(pattern_scene, "train", label_folder="pseudo")
    img = np.zeros((4, 5, 3), np.uint8)
    with pytest.raises(ValueError, match="differ in size"):
        SegmentationDataset([img], [np.zeros((4, 4), np.uint8)])
    with pytest.raises(ValueError, match="outside NYU40"):
        SegmentationDataset([img], [np.full((4, 5), 41, np.uint8)])
