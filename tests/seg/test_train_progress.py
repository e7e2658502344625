"""The training loop's ``on_progress`` callback: reported once per epoch (and within long
epochs), and an exception from it stops training at once without writing a checkpoint."""

from __future__ import annotations

import pytest
import torch

from csa_core.seg import train as train_module
from csa_core.seg.checkpoint import read_model_card
from csa_core.seg.config import TrainConfig
from csa_core.seg.dataset import SegmentationDataset
from csa_core.seg.models import build_model
from csa_core.seg.train import train_segmentation
from tests.seg.conftest import make_pattern_scene

# 8 images in batches of 4: 2 batches per epoch, fewer than BATCH_PROGRESS_EVERY.
FAST = dict(batch_size=4, lr=1e-2, progress=False, device="cpu", precise_bn_images=8)


class Stop(Exception):
    """What a caller raises to stop the loop (the service raises JobCancelled)."""


@pytest.fixture(scope="module")
def train_set() -> SegmentationDataset:
    return SegmentationDataset.from_scenes(make_pattern_scene(n=8, seed=0), "all")


def test_called_once_per_epoch_with_increasing_progress(train_set) -> None:
    calls: list[tuple[str, float]] = []
    torch.manual_seed(0)
    result = train_segmentation(
        build_model(),
        train_set,
        TrainConfig(epochs=3, **FAST),
        on_progress=lambda message, fraction: calls.append((message, fraction)),
    )
    assert len(result.history) == 3
    assert [f for _, f in calls] == pytest.approx([1 / 3, 2 / 3, 1.0])
    assert [m.split()[:2] for m, _ in calls] == [
        ["epoch", "1/3"],
        ["epoch", "2/3"],
        ["epoch", "3/3"],
    ]


def test_long_epochs_also_report_between_batches(train_set, monkeypatch) -> None:
    monkeypatch.setattr(train_module, "BATCH_PROGRESS_EVERY", 1)
    calls: list[tuple[str, float]] = []
    torch.manual_seed(0)
    train_segmentation(
        build_model(),
        train_set,
        TrainConfig(epochs=2, **FAST),
        on_progress=lambda message, fraction: calls.append((message, fraction)),
    )
    fractions = [f for _, f in calls]
    assert fractions == pytest.approx([0.25, 0.5, 0.75, 1.0])  # batch 1, end of epoch 1, ...
    assert "batch 1/2" in calls[0][0] and "batch" not in calls[1][0]


def test_an_exception_in_the_first_epoch_stops_before_any_checkpoint(train_set, tmp_path) -> None:
    ckpt = tmp_path / "best.safetensors"
    stop = Stop("cancelled")
    calls: list[float] = []

    def cancel(message: str, fraction: float) -> None:
        calls.append(fraction)
        raise stop

    torch.manual_seed(0)
    with pytest.raises(Stop) as raised:
        train_segmentation(
            build_model(),
            train_set,
            TrainConfig(epochs=50, **FAST),
            checkpoint=ckpt,
            on_progress=cancel,
        )
    assert raised.value is stop  # propagated unchanged, not wrapped
    assert calls == pytest.approx([1 / 50])  # one epoch of fifty ran
    assert list(tmp_path.iterdir()) == []  # no checkpoint, no temporary left behind


def test_an_exception_later_stops_early_and_keeps_the_earlier_checkpoint(
    train_set, tmp_path
) -> None:
    """With validation every improved epoch writes the checkpoint; epoch 3's never is."""
    ckpt = tmp_path / "best.safetensors"
    calls: list[float] = []

    def cancel_in_epoch_3(message: str, fraction: float) -> None:
        calls.append(fraction)
        if len(calls) == 3:
            raise Stop("cancelled")

    val = {"held-out": SegmentationDataset.from_scenes(make_pattern_scene(n=2, seed=1), "all")}
    torch.manual_seed(0)
    with pytest.raises(Stop):
        train_segmentation(
            build_model(),
            train_set,
            TrainConfig(epochs=50, **FAST),
            val_sets=val,
            checkpoint=ckpt,
            on_progress=cancel_in_epoch_3,
        )
    assert len(calls) == 3  # epochs 4..50 never ran
    assert [p.name for p in tmp_path.iterdir()] == ["best.safetensors"]  # complete, no temporary
    assert read_model_card(ckpt).metrics["best_epoch"] in (1, 2)
