"""The training loop: it learns, it is reproducible, it keeps the best checkpoint."""

from __future__ import annotations

import math

import pytest
import torch

from csa_core.seg.checkpoint import load_checkpoint
from csa_core.seg.config import TrainConfig
from csa_core.seg.dataset import SegmentationDataset
from csa_core.seg.models import build_model
from csa_core.seg.predict import evaluate_scene
from csa_core.seg.train import lr_factor, train_segmentation
from tests.seg.conftest import make_pattern_scene

FAST = dict(epochs=6, batch_size=4, lr=1e-2, progress=False, device="cpu")


@pytest.fixture(scope="module")
def scenes():
    return make_pattern_scene(n=16, seed=0, name="train"), make_pattern_scene(
        n=6, seed=1, name="held-out"
    )


@pytest.fixture(scope="module")
def trained(scenes, tmp_path_factory):
    train_scene, held_out = scenes
    ckpt = tmp_path_factory.mktemp("train") / "best.safetensors"
    torch.manual_seed(0)
    model = build_model()
    result = train_segmentation(
        model,
        SegmentationDataset.from_scenes(train_scene, "all"),
        TrainConfig(**FAST),
        val_sets={"held-out": SegmentationDataset.from_scenes(held_out, "all")},
        checkpoint=ckpt,
    )
    return model, result, ckpt


def test_training_reduces_loss_and_learns_the_pattern(scenes, trained):
    model, result, _ = trained
    losses = [e.train_loss for e in result.history]
    assert len(losses) == 6
    assert losses[-1] < 0.25 * losses[0]
    held_out = scenes[1]
    matrix = evaluate_scene(model, held_out, "all", device="cpu")
    # Five flat-coloured classes at 64x48: the light network labels > 85% of held-out pixels
    # correctly after 24 steps (measured 89.5%).
    assert matrix.pixel_accuracy() > 0.85
    assert matrix.miou() > 0.5


def test_best_epoch_is_kept_and_written(scenes, trained):
    model, result, ckpt = trained
    scores = [e.score for e in result.history]
    assert result.best_score == max(scores)
    assert result.best_epoch == scores.index(max(scores)) + 1
    loaded, card = load_checkpoint(ckpt)
    assert card.metrics["best_epoch"] == result.best_epoch
    assert card.metrics["val_miou"] == pytest.approx(result.best_score)
    assert card.train_config["lr"] == FAST["lr"] and card.train_config["optimizer"] == "adam"
    assert evaluate_scene(loaded, scenes[1], "all", device="cpu").miou() == pytest.approx(
        result.best_score
    )
    x = torch.rand(1, 3, 48, 64)
    with torch.no_grad():
        assert torch.equal(loaded(x), model.eval()(x))


def test_learning_rate_decays_to_zero(trained):
    _, result, _ = trained
    lrs = [e.lr for e in result.history]
    assert all(a > b for a, b in zip(lrs, lrs[1:], strict=False)) and lrs[-1] == 0.0
    assert lr_factor("poly", 0, 10) == 1.0 and lr_factor("poly", 10, 10) == 0.0
    assert lr_factor("cosine", 5, 10) == pytest.approx(0.5)
    assert lr_factor("constant", 7, 10) == 1.0


def test_same_seed_same_run_and_no_validation_keeps_last(scenes):
    def run():
        torch.manual_seed(0)
        model = build_model()
        ds = SegmentationDataset.from_scenes(scenes[0], "train")
        result = train_segmentation(
            model, ds, TrainConfig(**{**FAST, "epochs": 1, "precise_bn_images": 8})
        )
        return model, result

    (a, ra), (b, rb) = run(), run()
    assert ra.history[0].train_loss == rb.history[0].train_loss
    assert all(
        torch.equal(x, y)
        for x, y in zip(a.state_dict().values(), b.state_dict().values(), strict=True)
    )
    assert ra.best_epoch == 1 and ra.best_score is None
    assert ra.images_seen == 12  # 12 training frames, batches of 4


def test_settings_validation():
    with pytest.raises(ValueError, match="schedule"):
        TrainConfig(schedule="step")
    with pytest.raises(ValueError, match="lr"):
        TrainConfig(lr=0.0)
    assert math.isclose(TrainConfig().lr, 2e-3)
