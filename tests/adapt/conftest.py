"""Tiny synthetic scenes and a quickly pre-trained network shared by the adaptation tests."""

from __future__ import annotations

import pytest

from csa_core.adapt.config import AdaptConfig, preset
from csa_core.data.scene import Scene
from csa_core.seg.models import SegmentationNet

SIZE = (48, 36)
FRAMES = 10


def tiny_config(mode: str = "joint") -> AdaptConfig:
    """The test preset in ``mode``."""
    cfg = preset("tiny")
    cfg.mode = mode
    cfg.seg.device = "cpu"
    return cfg


@pytest.fixture(scope="session")
def source_scenes() -> list[Scene]:
    from csa_core.data.synth import generate_scene

    return [generate_scene("apartment", s, FRAMES, SIZE) for s in range(2)]


@pytest.fixture(scope="session")
def target_scenes() -> list[Scene]:
    from csa_core.data.synth import generate_scene

    return [generate_scene("office", 10 + s, FRAMES, SIZE) for s in range(3)]


@pytest.fixture(scope="session")
def pretrained(source_scenes) -> SegmentationNet:
    """The light network after a few epochs on the source scenes (seeded)."""
    from csa_core.seg.config import PretrainConfig, TrainConfig
    from csa_core.seg.pretraining import pretrain

    config = PretrainConfig(
        size=SIZE,
        train=TrainConfig(
            epochs=4, batch_size=4, progress=False, precise_bn_images=16, device="cpu"
        ),
    )
    model, _ = pretrain(source_scenes, config)
    return model
