"""Semantic segmentation scores under the CSA protocol (docs/method.md, "Protocols and metrics").

One confusion matrix is accumulated over every pixel of a scene. Ground truth 0 (unknown) is
ignored. A prediction of 0 is kept: it is a miss of the ground-truth class and a false
positive of no class, so abstaining can only lower the score. IoU is averaged over the classes
that have at least one ground-truth pixel. Scores are fractions in [0, 1]; tables show percent.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from csa_core.data.image_files import read_label_image
from csa_core.data.nyu40 import CLASS_NAMES, NUM_CLASSES, check_label_map
from csa_core.errors import CSAInputError

_N = NUM_CLASSES + 1  # matrix rows/columns are indexed by NYU40 id, 0 included


class ConfusionMatrix:
    """Pixel counts ``counts[g, p]``: ground-truth id ``g`` predicted as id ``p`` (both 0..40).

    Row 0 stays zero because unknown ground truth is ignored; column 0 counts pixels the
    method left unknown.
    """

    def __init__(self, counts: np.ndarray | None = None):
        if counts is None:
            self._counts = np.zeros((_N, _N), dtype=np.int64)
            return
        counts = np.asarray(counts)
        if counts.shape != (_N, _N) or not np.issubdtype(counts.dtype, np.integer):
            raise ValueError(
                f"ConfusionMatrix: expected {_N}x{_N} integer counts, "
                f"got {counts.dtype} {counts.shape}"
            )
        if (counts < 0).any() or counts[0].any():
            raise ValueError("ConfusionMatrix: counts must be >= 0 and row 0 (unknown GT) zero")
        self._counts = counts.astype(np.int64)

    @property
    def counts(self) -> np.ndarray:
        """A copy of the (41, 41) count matrix, rows = ground truth, columns = prediction."""
        return self._counts.copy()

    @property
    def num_pixels(self) -> int:
        """Number of pixels with known ground truth seen so far."""
        return int(self._counts.sum())

    def update(self, pred: np.ndarray, gt: np.ndarray) -> ConfusionMatrix:
        """Add one label map pair (same shape, NYU40 ids 0..40); returns ``self``."""
        pred = check_label_map(pred, "pred")
        gt = check_label_map(gt, "gt")
        if pred.shape != gt.shape:
            raise ValueError(f"update: pred shape {pred.shape} differs from gt shape {gt.shape}")
        known = gt > 0
        flat = gt[known].astype(np.int64) * _N + pred[known]
        self._counts += np.bincount(flat, minlength=_N * _N).reshape(_N, _N)
        return self

    def merge(self, other: ConfusionMatrix) -> ConfusionMatrix:
        """Add the counts of ``other`` (e.g. another frame set or worker); returns ``self``."""
        self._counts += other._counts
        return self

    def present_classes(self) -> np.ndarray:
        """Ids (1..40) with at least one ground-truth pixel, ascending."""
        return np.flatnonzero(self._counts.sum(axis=1))

    def per_class_iou(self) -> np.ndarray:
        """(41,) IoU indexed by id; NaN for id 0 and for classes without ground truth."""
        tp = np.diag(self._counts).astype(np.float64)
        gt_total = self._counts.sum(axis=1)
        # Row 0 is zero, so column sums count only pixels with known ground truth, and
        # abstentions (column 0) are false positives of no class.
        pred_total = self._counts.sum(axis=0)
        union = gt_total + pred_total - tp
        iou = np.full(_N, np.nan)
        present = gt_total > 0
        iou[present] = tp[present] / union[present]
        return iou

    def per_class_accuracy(self) -> np.ndarray:
        """(41,) recall indexed by id; NaN for id 0 and for classes without ground truth."""
        gt_total = self._counts.sum(axis=1)
        acc = np.full(_N, np.nan)
        present = gt_total > 0
        acc[present] = np.diag(self._counts)[present] / gt_total[present]
        return acc

    def miou(self) -> float:
        """Mean IoU over the classes present in the ground truth (NaN if there are none)."""
        return _mean_present(self.per_class_iou())

    def pixel_accuracy(self) -> float:
        """Fraction of known ground-truth pixels predicted correctly (NaN if there are none)."""
        total = self.num_pixels
        return float(np.trace(self._counts)) / total if total else float("nan")

    def mean_class_accuracy(self) -> float:
        """Mean recall over the classes present in the ground truth (NaN if there are none)."""
        return _mean_present(self.per_class_accuracy())

    def summary(self) -> dict[str, Any]:
        """Scores as plain Python values; per-class IoU keyed by class name, present ones only."""
        iou = self.per_class_iou()
        present = self.present_classes()
        return {
            "miou": self.miou(),
            "pixel_accuracy": self.pixel_accuracy(),
            "mean_class_accuracy": self.mean_class_accuracy(),
            "num_pixels": self.num_pixels,
            "present_class_ids": [int(c) for c in present],
            "per_class_iou": {CLASS_NAMES[c]: float(iou[c]) for c in present},
        }


def _mean_present(values: np.ndarray) -> float:
    present = values[~np.isnan(values)]
    return float(present.mean()) if present.size else float("nan")


def _frame_sort_key(name: str) -> tuple[int, int | str]:
    return (0, int(name)) if re.fullmatch(r"\d+", name) else (1, name)


def _label_files(folder: Path) -> dict[str, Path]:
    if not folder.is_dir():
        raise CSAInputError(folder, "not a folder")
    files = {p.stem: p for p in folder.glob("*.png") if not p.name.startswith(".")}
    return dict(sorted(files.items(), key=lambda kv: _frame_sort_key(kv[0])))


def _listed(names: list[str], most: int = 10) -> str:
    """The first ``most`` names, comma-separated, with ``...`` when there are more."""
    return ", ".join(names[:most]) + (", ..." if len(names) > most else "")


def evaluate_label_folders(
    pred_dir: str | Path, gt_dir: str | Path, predicted_only: bool = False
) -> dict[str, Any]:
    """Score a folder of predicted label maps against a ground-truth folder (``<frame>.png``).

    Frames are matched by file stem; every ground-truth frame must have a prediction (extra
    predictions are ignored and never read). With ``predicted_only`` the frames scored are the
    prediction folder's instead (e.g. a render of a scene's training views against the scene's
    whole label folder), and every one of them must have a ground truth. Maps are read one pair at a
    time by the scene reader's :func:`read_label_image`, so the same files are accepted
    (single-channel 8- or 16-bit PNG, ids 0..40). Returns :meth:`ConfusionMatrix.summary` plus
    ``num_frames``. Raises :class:`CSAInputError` naming the file for unreadable, multi-channel or
    out-of-range maps and for size mismatches, and naming the frames a prediction lacks.
    """
    pred_dir, gt_dir = Path(pred_dir), Path(gt_dir)
    gt_files = _label_files(gt_dir)
    pred_files = _label_files(pred_dir)
    if not gt_files:
        raise CSAInputError(gt_dir, "no label maps (*.png) found")
    if predicted_only:
        if not pred_files:
            raise CSAInputError(pred_dir, "no label maps (*.png) found")
        unknown = [name for name in pred_files if name not in gt_files]
        if unknown:
            raise CSAInputError(
                gt_dir, f"no ground truth for {len(unknown)} predicted frame(s): {_listed(unknown)}"
            )
        gt_files = {name: gt_files[name] for name in pred_files}
    missing = [name for name in gt_files if name not in pred_files]
    if missing:
        raise CSAInputError(
            pred_dir, f"no prediction for {len(missing)} ground-truth frame(s): {_listed(missing)}"
        )
    matrix = ConfusionMatrix()
    for name, gt_path in gt_files.items():
        gt = read_label_image(gt_path)
        pred = read_label_image(pred_files[name])
        if pred.shape != gt.shape:
            raise CSAInputError(
                pred_files[name],
                f"size {pred.shape[1]}x{pred.shape[0]} differs from ground truth "
                f"{gt_path} ({gt.shape[1]}x{gt.shape[0]})",
            )
        matrix.update(pred, gt)
    if matrix.num_pixels == 0:
        raise CSAInputError(gt_dir, "ground truth has no labelled pixels (all 0 = unknown)")
    return {**matrix.summary(), "num_frames": len(gt_files)}


def format_miou_table(summary: dict[str, Any], title: str | None = None) -> str:
    """Plain-text table of a :meth:`ConfusionMatrix.summary`: per-class IoU, then the means."""
    per_class: dict[str, float] = summary["per_class_iou"]
    width = max([len(name) for name in per_class] + [len("class accuracy")])
    lines = [title] if title else []
    rule = "-" * (width + 10)
    lines += [f"{'class':<{width}}  {'IoU (%)':>7}", rule]
    lines += [f"{name:<{width}}  {100 * iou:7.1f}" for name, iou in per_class.items()]
    lines += [
        rule,
        f"{'mIoU':<{width}}  {100 * summary['miou']:7.1f}",
        f"{'pixel accuracy':<{width}}  {100 * summary['pixel_accuracy']:7.1f}",
        f"{'class accuracy':<{width}}  {100 * summary['mean_class_accuracy']:7.1f}",
    ]
    return "\n".join(lines)
