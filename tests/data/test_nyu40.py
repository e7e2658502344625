"""NYU40 palette and label pictures: colours, colour coding, overlays, legends, previews."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from csa_core.data.label_images import colorize, legend_image, overlay, preview_image, save_preview
from csa_core.data.nyu40 import (
    CLASS_NAMES,
    NUM_CLASSES,
    PALETTE,
    check_label_map,
    class_color,
    class_id,
)


def test_palette_has_41_distinct_colours_and_unknown_is_black():
    assert PALETTE.shape == (NUM_CLASSES + 1, 3)
    assert PALETTE.dtype == np.uint8
    assert len({tuple(c) for c in PALETTE.tolist()}) == 41
    assert PALETTE[0].tolist() == [0, 0, 0]
    assert class_color(class_id("wall")) == (174, 199, 232)
    assert class_color(class_id("floor")) == (152, 223, 138)


def test_palette_is_read_only():
    with pytest.raises(ValueError):
        PALETTE[1] = 0


def test_class_color_rejects_ids_outside_nyu40():
    with pytest.raises(KeyError):
        class_color(41)


def test_check_label_map_rejects_bad_maps():
    with pytest.raises(ValueError, match="2-D"):
        check_label_map(np.zeros((2, 2, 3), dtype=np.uint8))
    with pytest.raises(ValueError, match="integer"):
        check_label_map(np.zeros((2, 2), dtype=np.float32))
    with pytest.raises(ValueError, match=r"\[41\]"):
        check_label_map(np.array([[1, 41]], dtype=np.uint8))
    with pytest.raises(ValueError, match=r"\[-1\]"):
        check_label_map(np.array([[1, -1]], dtype=np.int32))


def test_colorize_maps_every_pixel_to_its_class_colour():
    labels = np.array([[0, 1], [2, 40]], dtype=np.uint8)
    rgb = colorize(labels)
    assert rgb.shape == (2, 2, 3) and rgb.dtype == np.uint8
    assert rgb[0, 0].tolist() == [0, 0, 0]
    assert rgb[0, 1].tolist() == [174, 199, 232]
    assert rgb[1, 0].tolist() == [152, 223, 138]
    assert rgb[1, 1].tolist() == PALETTE[40].tolist()


def test_overlay_blends_known_pixels_and_keeps_unknown_ones():
    image = np.full((2, 2, 3), 100, dtype=np.uint8)
    labels = np.array([[0, 1], [2, 0]], dtype=np.uint8)
    out = overlay(image, labels, alpha=0.25)
    assert out.shape == (2, 2, 3) and out.dtype == np.uint8
    assert out[0, 0].tolist() == [100, 100, 100]
    assert out[1, 1].tolist() == [100, 100, 100]
    # 0.75 * 100 + 0.25 * (174, 199, 232) = (118.5 -> 118 by round-half-even, 124.75, 133)
    assert out[0, 1].tolist() == [118, 125, 133]
    # 0.75 * 100 + 0.25 * (152, 223, 138) = (113, 130.75, 109.5 -> 110)
    assert out[1, 0].tolist() == [113, 131, 110]
    assert np.array_equal(overlay(image, labels, alpha=0.0), image)
    assert np.array_equal(overlay(image, labels, alpha=1.0)[0, 1], PALETTE[1])


def test_overlay_rejects_bad_alpha_and_size_mismatch():
    image = np.zeros((2, 3, 3), dtype=np.uint8)
    with pytest.raises(ValueError, match="alpha"):
        overlay(image, np.zeros((2, 3), dtype=np.uint8), alpha=1.5)
    with pytest.raises(ValueError, match="3x2"):
        overlay(image, np.zeros((3, 2), dtype=np.uint8))


def test_legend_shows_a_swatch_of_each_class():
    legend = legend_image([1, 5])
    assert legend.ndim == 3 and legend.shape[2] == 3 and legend.dtype == np.uint8
    for cid in (1, 5):
        assert (legend == PALETTE[cid]).all(axis=2).sum() >= 50  # a filled swatch, not stray text
    assert not (legend == PALETTE[2]).all(axis=2).any()


def test_legend_wraps_into_columns_under_max_height():
    tall = legend_image(range(1, 11))
    wrapped = legend_image(range(1, 11), max_height=tall.shape[0] // 2)
    assert wrapped.shape[0] <= tall.shape[0] // 2
    assert wrapped.shape[1] > tall.shape[1]


def test_legend_rejects_unknown_ids():
    with pytest.raises(ValueError):
        legend_image([41])


def test_save_preview_writes_image_labels_and_overlay_side_by_side(tmp_path):
    rng = np.random.default_rng(0)
    h, w = 48, 64
    image = rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8)
    labels = np.zeros((h, w), dtype=np.uint8)
    labels[:, 20:] = class_id("wall")
    labels[30:, :] = class_id("floor")
    path = save_preview(tmp_path / "out" / "preview.png", image, labels)

    assert path.exists()
    assert [p.name for p in path.parent.iterdir()] == ["preview.png"]  # no temporary left
    written = cv2.imread(str(path), cv2.IMREAD_COLOR)[:, :, ::-1]
    assert np.array_equal(written, preview_image(image, labels))
    assert written.shape[0] >= h and written.shape[1] > 3 * w
    assert np.array_equal(written[:h, :w], image)
    assert np.array_equal(written[:h, w : 2 * w], colorize(labels))
    assert np.array_equal(written[:h, 2 * w : 3 * w], overlay(image, labels))


def test_preview_without_legend_is_exactly_three_panels():
    image = np.zeros((4, 5, 3), dtype=np.uint8)
    labels = np.ones((4, 5), dtype=np.uint8)
    assert preview_image(image, labels, legend=False).shape == (4, 15, 3)


def test_class_names_and_palette_agree_in_length():
    assert len(CLASS_NAMES) == len(PALETTE)
