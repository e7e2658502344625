"""The label corruption used to simulate per-frame segmentation errors."""

from __future__ import annotations

import numpy as np
import pytest

from csa_core.data.label_noise import LabelNoiseConfig, corrupt_labels


def _labels() -> np.ndarray:
    lab = np.full((60, 80), 1, np.uint8)  # wall
    lab[40:] = 2  # floor
    lab[25:50, 20:45] = 7  # table
    lab[10:30, 55:75] = 5  # chair
    lab[:5, :5] = 0  # unknown
    return lab


def test_corruption_is_reproducible_and_substantial_but_partial():
    lab = _labels()
    a = corrupt_labels(lab, np.random.default_rng(1))
    b = corrupt_labels(lab, np.random.default_rng(1))
    c = corrupt_labels(lab, np.random.default_rng(2))
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    changed = (a != lab).mean()
    assert 0.03 < changed < 0.6
    assert a.dtype == np.uint8 and a.shape == lab.shape
    assert a.max() <= 40


def test_unknown_stays_unknown_and_input_is_untouched():
    lab = _labels()
    copy = lab.copy()
    out = corrupt_labels(
        lab, np.random.default_rng(0), LabelNoiseConfig(blobs=10, swap_probability=1.0)
    )
    assert np.array_equal(lab, copy)
    assert np.all(out[lab == 0] == 0)
    assert np.all(out[lab > 0] > 0)


def test_no_noise_config_is_identity():
    lab = _labels()
    cfg = LabelNoiseConfig(blobs=0, swap_probability=0.0, edge_width=0.0)
    assert np.array_equal(corrupt_labels(lab, np.random.default_rng(0), cfg), lab)


def test_rejects_non_2d_input():
    with pytest.raises(ValueError):
        corrupt_labels(np.zeros((2, 3, 3), np.uint8), np.random.default_rng(0))
