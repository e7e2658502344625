"""mIoU under the CSA protocol, checked against confusion matrices worked out by hand."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from csa_core.errors import CSAInputError
from csa_core.eval import ConfusionMatrix, evaluate_label_folders, format_miou_table

# 4x4 case. Two ground-truth pixels are unknown (0); predictions there (4, 7) must not count.
GT = np.array(
    [
        [1, 1, 1, 1],
        [1, 2, 2, 0],
        [3, 3, 2, 0],
        [3, 3, 3, 3],
    ],
    dtype=np.uint8,
)
PRED = np.array(
    [
        [1, 1, 2, 0],
        [1, 2, 2, 4],
        [3, 1, 0, 7],
        [3, 3, 3, 2],
    ],
    dtype=np.uint8,
)
# By hand, (gt -> pred) counts over the 14 known pixels:
#   gt 1 (5 px): 3 x 1, 1 x 2, 1 x 0     gt 2 (3 px): 2 x 2, 1 x 0
#   gt 3 (6 px): 4 x 3, 1 x 1, 1 x 2
# predicted totals on known pixels: class 1: 3 + 1 = 4, class 2: 1 + 2 + 1 = 4, class 3: 4
IOU_1 = 3 / (5 + 4 - 3)  # = 3/6
IOU_2 = 2 / (3 + 4 - 2)  # = 2/5
IOU_3 = 4 / (6 + 4 - 4)  # = 4/6


def test_hand_computed_confusion_matrix():
    counts = ConfusionMatrix().update(PRED, GT).counts
    expected = np.zeros((41, 41), dtype=np.int64)
    expected[1, 1], expected[1, 2], expected[1, 0] = 3, 1, 1
    expected[2, 2], expected[2, 0] = 2, 1
    expected[3, 3], expected[3, 1], expected[3, 2] = 4, 1, 1
    assert np.array_equal(counts, expected)


def test_hand_computed_scores():
    cm = ConfusionMatrix().update(PRED, GT)
    iou = cm.per_class_iou()
    assert iou.shape == (41,)
    assert iou[1] == pytest.approx(3 / 6)
    assert iou[2] == pytest.approx(2 / 5)
    assert iou[3] == pytest.approx(4 / 6)
    # Classes 4 and 7 were only predicted on unknown ground truth: absent, not zero.
    assert np.isnan(iou[0]) and np.isnan(iou[4]) and np.isnan(iou[7])
    assert np.isnan(iou[4:]).all()
    assert cm.miou() == pytest.approx((3 / 6 + 2 / 5 + 4 / 6) / 3)
    assert cm.pixel_accuracy() == pytest.approx((3 + 2 + 4) / 14)
    assert cm.mean_class_accuracy() == pytest.approx((3 / 5 + 2 / 3 + 4 / 6) / 3)
    assert cm.num_pixels == 14
    assert cm.present_classes().tolist() == [1, 2, 3]


def test_ground_truth_unknown_is_ignored():
    gt = np.array([[1, 0], [0, 0]], dtype=np.uint8)
    pred = np.array([[1, 2], [3, 4]], dtype=np.uint8)
    cm = ConfusionMatrix().update(pred, gt)
    assert cm.num_pixels == 1
    assert cm.miou() == 1.0
    assert cm.pixel_accuracy() == 1.0


def test_predicting_unknown_is_a_miss_never_a_reward():
    gt = np.ones((2, 2), dtype=np.uint8)
    pred = np.array([[1, 0], [0, 0]], dtype=np.uint8)
    cm = ConfusionMatrix().update(pred, gt)
    assert cm.per_class_iou()[1] == pytest.approx(1 / 4)
    assert cm.miou() == pytest.approx(1 / 4)
    assert cm.pixel_accuracy() == pytest.approx(1 / 4)
    assert cm.mean_class_accuracy() == pytest.approx(1 / 4)
    # Abstaining scores below guessing a wrong class would not, but never above a right one.
    everything_right = ConfusionMatrix().update(gt, gt)
    assert everything_right.miou() == 1.0


def test_classes_absent_from_ground_truth_are_left_out_of_the_mean():
    gt = np.array([[1, 1], [2, 2]], dtype=np.uint8)
    pred = np.array([[1, 5], [2, 2]], dtype=np.uint8)
    cm = ConfusionMatrix().update(pred, gt)
    # IoU(1) = 1 / (2 + 1 - 1) = 1/2, IoU(2) = 2 / (2 + 2 - 2) = 1; class 5 has no GT pixel.
    assert np.isnan(cm.per_class_iou()[5])
    assert cm.miou() == pytest.approx((1 / 2 + 1) / 2)


def test_two_images_accumulate_like_one_concatenated_image():
    rng = np.random.default_rng(3)
    gt_a, pred_a = rng.integers(0, 41, (2, 5, 7), dtype=np.uint8)
    gt_b, pred_b = rng.integers(0, 41, (2, 5, 3), dtype=np.uint8)
    both = ConfusionMatrix().update(pred_a, gt_a).update(pred_b, gt_b)
    joined = ConfusionMatrix().update(np.hstack([pred_a, pred_b]), np.hstack([gt_a, gt_b]))
    assert np.array_equal(both.counts, joined.counts)
    assert both.miou() == joined.miou()
    merged = ConfusionMatrix().update(pred_a, gt_a).merge(ConfusionMatrix().update(pred_b, gt_b))
    assert np.array_equal(merged.counts, joined.counts)


def test_accepts_wider_integer_types():
    gt = np.array([[1, 2]], dtype=np.int64)
    pred = np.array([[1, 1]], dtype=np.uint16)
    assert ConfusionMatrix().update(pred, gt).per_class_iou()[1] == pytest.approx(1 / 2)


def test_empty_matrix_scores_are_nan():
    cm = ConfusionMatrix()
    assert math.isnan(cm.miou())
    assert math.isnan(cm.pixel_accuracy())
    assert math.isnan(cm.mean_class_accuracy())


@pytest.mark.parametrize(
    ("pred", "gt", "match"),
    [
        (np.zeros((2, 3), np.uint8), np.zeros((3, 2), np.uint8), "shape"),
        (np.full((2, 2), 41, np.uint8), np.ones((2, 2), np.uint8), "outside"),
        (np.ones((2, 2), np.uint8), np.full((2, 2), -1, np.int32), "outside"),
        (np.ones((2, 2), np.float32), np.ones((2, 2), np.uint8), "integer"),
    ],
)
def test_update_rejects_bad_maps(pred, gt, match):
    with pytest.raises(ValueError, match=match):
        ConfusionMatrix().update(pred, gt)


def test_counts_are_validated():
    with pytest.raises(ValueError):
        ConfusionMatrix(np.zeros((40, 40), dtype=np.int64))
    bad = np.zeros((41, 41), dtype=np.int64)
    bad[0, 1] = 1  # unknown ground truth is never counted
    with pytest.raises(ValueError):
        ConfusionMatrix(bad)


def test_summary_reports_present_classes_by_name():
    summary = ConfusionMatrix().update(PRED, GT).summary()
    assert summary["per_class_iou"] == pytest.approx(
        {"wall": IOU_1, "floor": IOU_2, "cabinet": IOU_3}
    )
    assert summary["present_class_ids"] == [1, 2, 3]
    assert summary["miou"] == pytest.approx((IOU_1 + IOU_2 + IOU_3) / 3)
    assert summary["num_pixels"] == 14


def test_table_shows_percentages():
    table = format_miou_table(ConfusionMatrix().update(PRED, GT).summary(), title="scene 0")
    lines = table.splitlines()
    assert lines[0] == "scene 0"
    assert any(line.split() == ["wall", "50.0"] for line in lines)
    assert any(line.split() == ["floor", "40.0"] for line in lines)
    assert any(line.split() == ["cabinet", "66.7"] for line in lines)
    assert any(
        line.split() == ["mIoU", f"{100 * (IOU_1 + IOU_2 + IOU_3) / 3:.1f}"] for line in lines
    )
    assert any(line.split() == ["pixel", "accuracy", f"{100 * 9 / 14:.1f}"] for line in lines)


# --- folder evaluation -------------------------------------------------------------------


def _write(folder, name, labels):
    folder.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(folder / f"{name}.png"), labels)


@pytest.fixture
def folders(tmp_path):
    gt_dir, pred_dir = tmp_path / "label-nyu40", tmp_path / "pred"
    _write(gt_dir, "0", GT)
    _write(gt_dir, "10", GT[:, :2])
    _write(pred_dir, "0", PRED)
    _write(pred_dir, "10", PRED[:, :2])
    _write(pred_dir, "99", PRED)  # extra prediction without ground truth: ignored
    return pred_dir, gt_dir


def test_folder_evaluation_matches_the_confusion_matrix(folders):
    pred_dir, gt_dir = folders
    result = evaluate_label_folders(pred_dir, gt_dir)
    expected = ConfusionMatrix().update(PRED, GT).update(PRED[:, :2], GT[:, :2]).summary()
    assert result["num_frames"] == 2
    assert result["miou"] == pytest.approx(expected["miou"])
    assert result["per_class_iou"] == pytest.approx(expected["per_class_iou"])
    assert result["pixel_accuracy"] == pytest.approx(expected["pixel_accuracy"])


def test_folder_evaluation_names_missing_frames(folders):
    pred_dir, gt_dir = folders
    (pred_dir / "10.png").unlink()
    with pytest.raises(CSAInputError, match=r"1 ground-truth frame\(s\): 10") as info:
        evaluate_label_folders(pred_dir, gt_dir)
    assert info.value.where == str(pred_dir)


def test_folder_evaluation_rejects_size_mismatch(folders):
    pred_dir, gt_dir = folders
    _write(pred_dir, "10", PRED)
    with pytest.raises(CSAInputError, match="4x4 differs") as info:
        evaluate_label_folders(pred_dir, gt_dir)
    assert info.value.where == str(pred_dir / "10.png")


def test_folder_evaluation_rejects_invalid_ids(folders):
    pred_dir, gt_dir = folders
    _write(pred_dir, "0", np.full_like(PRED, 41))
    with pytest.raises(CSAInputError, match="41") as info:
        evaluate_label_folders(pred_dir, gt_dir)
    assert info.value.where == str(pred_dir / "0.png")


def test_folder_evaluation_reads_16_bit_maps_like_the_scene_reader(folders):
    pred_dir, gt_dir = folders
    expected = evaluate_label_folders(pred_dir, gt_dir)
    _write(gt_dir, "0", GT.astype(np.uint16))
    assert evaluate_label_folders(pred_dir, gt_dir) == expected
    _write(gt_dir, "0", np.full(GT.shape, 300, np.uint16))  # raw ScanNet ids, not NYU40
    with pytest.raises(CSAInputError, match="300") as info:
        evaluate_label_folders(pred_dir, gt_dir)
    assert info.value.where == str(gt_dir / "0.png")


def test_folder_evaluation_rejects_colour_images(folders):
    pred_dir, gt_dir = folders
    _write(pred_dir, "0", np.dstack([PRED, PRED, PRED]))
    with pytest.raises(CSAInputError, match="single-channel") as info:
        evaluate_label_folders(pred_dir, gt_dir)
    assert info.value.where == str(pred_dir / "0.png")


def test_folder_evaluation_rejects_unreadable_files(folders):
    pred_dir, gt_dir = folders
    (pred_dir / "10.png").write_bytes(b"not a png")
    with pytest.raises(CSAInputError, match="decode") as info:
        evaluate_label_folders(pred_dir, gt_dir)
    assert info.value.where == str(pred_dir / "10.png")


def test_folder_evaluation_never_reads_extra_predictions(folders):
    pred_dir, gt_dir = folders
    (pred_dir / "99.png").write_bytes(b"not a png")
    assert evaluate_label_folders(pred_dir, gt_dir)["num_frames"] == 2


def test_folder_evaluation_rejects_missing_or_empty_folders(tmp_path, folders):
    pred_dir, _ = folders
    with pytest.raises(CSAInputError, match="not a folder"):
        evaluate_label_folders(pred_dir, tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(CSAInputError, match="no label maps"):
        evaluate_label_folders(pred_dir, tmp_path / "empty")
    _write(tmp_path / "blank", "0", np.zeros_like(GT))
    with pytest.raises(CSAInputError, match="no labelled pixels"):
        evaluate_label_folders(pred_dir, tmp_path / "blank")


def test_folder_evaluation_of_the_predicted_frames_only(folders):
    pred_dir, gt_dir = folders
    (pred_dir / "99.png").unlink()
    (pred_dir / "10.png").unlink()  # a render of some of the scene's views
    with pytest.raises(CSAInputError, match="no prediction"):
        evaluate_label_folders(pred_dir, gt_dir)
    result = evaluate_label_folders(pred_dir, gt_dir, predicted_only=True)
    expected = ConfusionMatrix().update(PRED, GT).summary()
    assert result["num_frames"] == 1
    assert result["miou"] == pytest.approx(expected["miou"])
    # every predicted frame still needs a ground truth, named when it has none
    _write(pred_dir, "7", PRED)
    with pytest.raises(CSAInputError, match=r"1 predicted frame\(s\): 7") as info:
        evaluate_label_folders(pred_dir, gt_dir, predicted_only=True)
    assert info.value.where == str(gt_dir)
    for p in pred_dir.glob("*.png"):
        p.unlink()
    with pytest.raises(CSAInputError, match="no label maps") as info:
        evaluate_label_folders(pred_dir, gt_dir, predicted_only=True)
    assert info.value.where == str(pred_dir)
