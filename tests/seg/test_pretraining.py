"""pretrain(): which views train, which views score, and what the checkpoint records."""

from __future__ import annotations

import pytest

from csa_core.errors import CSAInputError
from csa_core.seg.config import PretrainConfig, TrainConfig
from csa_core.seg.pretraining import pretrain
from tests.seg.conftest import make_pattern_scene


def _config(**train) -> PretrainConfig:
    return PretrainConfig(
        size=(64, 48),
        train=TrainConfig(
            **{
                "epochs": 1,
                "batch_size": 4,
                "progress": False,
                "device": "cpu",
                "precise_bn_images": 8,
                **train,
            }
        ),
    )


def test_separate_validation_scenes_train_on_all_views(tmp_path):
    train = [make_pattern_scene(n=6, seed=0, name="a"), make_pattern_scene(n=6, seed=1, name="b")]
    held_out = [make_pattern_scene(n=5, seed=2, name="c")]
    out = tmp_path / "m.safetensors"
    _, result = pretrain(train, _config(), out=out, val_scenes=held_out)
    assert list(result.best_val_miou) == ["c"]
    assert result.images_seen == 12  # all 12 views of a and b, batches of 4
    assert result.card.train_config["train_split"] == "all"
    assert (
        result.card.train_config["val_scenes"] == ["c"]
        and result.card.train_config["train_images"] == 12
    )
    assert result.card.input_size == [64, 48] and out.is_file()


def test_default_scores_each_scene_on_its_validation_views():
    train = [make_pattern_scene(n=6, seed=0, name="a"), make_pattern_scene(n=6, seed=1, name="b")]
    model, result = pretrain(train, _config())
    assert set(result.best_val_miou) == {"a", "b"}
    assert result.images_seen == 8  # 5 + 5 training views -> two full batches of 4
    assert result.checkpoint is None and not model.training


def test_scene_size_must_match_the_config():
    with pytest.raises(CSAInputError, match="the config says 32x24"):
        pretrain([make_pattern_scene(n=4)], PretrainConfig(size=(32, 24)))
    with pytest.raises(CSAInputError, match="no training scenes"):
        pretrain([], _config())
